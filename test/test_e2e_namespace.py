"""End to end under a namespace: the whole simulated stack (bring-up's ``namespace``, i.e. every node
started with ``-r __ns:=/left`` and the shipped parameter files) reaches a goal sent on
``/left/goal_pose``, nothing of it is left in the root namespace, and the browser view started beside
it listens to ``/left/...``."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from support.requires import require_ros

require_ros(stack=True)

from redarm_interfaces.msg import ControllerState  # noqa: E402
from support import stack_client as sc  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.testing import SimulatedArm  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

NS = "/left"
ARM = load_arm("pa10")
READY_Q = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])
POS_TOL, ROT_TOL = 1e-3, 0.01


class Client(sc.GoalClient):
    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx, "ns_client", namespace=NS)


stack = sc.stack_fixture(arm="pa10", namespace=NS, description=True, view=True, view_port=0,
                         ready_timeout_s=90.0)
client = sc.ready_client_fixture(Client, ARM.joint_names, READY_Q, start_s=30.0, ik_s=10.0,
                                 reach_s=15.0, recover_s=15.0)


def test_the_stack_under_a_namespace_reaches_a_goal(stack: SimulatedArm, client: Client) -> None:
    T = ARM.fk(np.array([0.4, 0.7, -0.3, 1.0, 0.2, 0.9, 0.3]))
    n = client.send(T)

    def reached() -> bool:
        return any(s.phase == ControllerState.REACHED and abs(s.goal.position.x - T[0, 3]) < 1e-6
                   for s in client.states[n:])

    assert client.spin_until(reached, 45.0), [s.phase for s in client.states[n:]][-5:]
    assert sc.sim_tool_reaches(client, stack, T, POS_TOL, ROT_TOL, 15.0), sc.pose_err(sc.sim_tool(stack), T)
    stack.check()


def test_nothing_of_the_stack_is_in_the_root_namespace(stack: SimulatedArm, client: Client) -> None:
    node = client.node
    topics = {name for name, _ in node.get_topic_names_and_types()}
    assert {f"{NS}/joint_states", f"{NS}/joint_command", f"{NS}/goal_pose", f"{NS}/controller/state",
            f"{NS}/robot_description"} <= topics, sorted(topics)
    assert not {"/joint_states", "/joint_command", "/controller/state", "/robot_description"} & topics
    services = {name for name, _ in node.get_service_names_and_types()}
    assert {f"{NS}/can_driver/init", f"{NS}/ik_service/solve_ik"} <= services
    # the view: every topic it reads but /diagnostics is the namespaced one
    assert client.spin_until(lambda: bool(node.get_subscriber_names_and_types_by_node("view", NS)), 20.0)
    view_in = {name for name, _ in node.get_subscriber_names_and_types_by_node("view", NS)}
    assert {f"{NS}/joint_states", f"{NS}/controller/state", f"{NS}/controller/markers",
            f"{NS}/robot_description"} <= view_in, sorted(view_in)
    view_out = {name for name, _ in node.get_publisher_names_and_types_by_node("view", NS)}
    assert f"{NS}/goal_pose" in view_out, sorted(view_out)
