"""End to end with an arm of its own: the whole stack (bus server, simulator, can_driver, ik_service,
controller, description) started by ``redarm-bringup --urdf`` for the iiwa14-like arm's URDF file. The
ik_service answers with the closed form, the controller reaches the pose as a goal, and the simulated
tool (pybullet, built from the URDF's chain) ends within 1 mm / 0.01 rad of it."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from support.requires import require_ros

require_ros(stack=True)

from redarm_interfaces.msg import ControllerState  # noqa: E402
from redarm_interfaces.srv import SolveIK  # noqa: E402
from support import stack_client as sc  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.nodes.controller import pose_to_msg  # noqa: E402
from redarm_ros.sim.urdf_arms import iiwa14_urdf  # noqa: E402
from redarm_ros.testing import SimulatedArm  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

URDF_TEXT = iiwa14_urdf()
ARM = load_arm(URDF_TEXT, base_link="base_link", tip_link="tool0")
READY_Q = np.array([0.0, 0.5, 0.0, -1.3, 0.0, 1.0, 0.0])  # elbow bent (joint 4 turns about -y)
POS_TOL, ROT_TOL = 1e-3, 0.01


@pytest.fixture(scope="module")
def stack(ros_env: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedArm]:
    f = tmp_path_factory.mktemp("urdf") / "iiwa14_like.urdf"
    f.write_text(URDF_TEXT, encoding="utf-8")
    with SimulatedArm(domain_id=ros_env.domain_id, sink=sc.stderr_sink, driver=True, controller=True,
                      ik_service=True, description=True, urdf=str(f), base_link="base_link",
                      tip_link="tool0", ready_timeout_s=60.0) as arm:
        yield arm


class Client(sc.GoalClient):
    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx, "e2e_urdf_client")


client = sc.ready_client_fixture(Client, ARM.joint_names, READY_Q, start_s=30.0, ik_s=10.0,
                                 reach_s=15.0, recover_s=15.0)


def test_urdf_arm_through_the_whole_stack(stack: SimulatedArm, client: Client) -> None:
    q_target = np.array([0.4, 0.7, -0.3, -1.0, 0.2, 0.9, 0.3])
    T = ARM.fk(q_target)
    req = SolveIK.Request()
    req.target = pose_to_msg(T)
    req.target.header.frame_id = "base_link"
    req.seed = [float(v) for v in READY_Q]
    resp = client.call(client.ik, req, 10.0)
    assert resp is not None and resp.status == SolveIK.Response.SUCCESS, resp
    assert resp.solver == "closed-form swivel IK"
    assert list(resp.solution.name) == ARM.joint_names
    assert sc.pose_err(ARM.fk(np.array(resp.solution.position)), T)[0] < 1e-9
    n = client.send(T)

    def reached() -> bool:
        return any(s.phase == ControllerState.REACHED and abs(s.goal.position.x - T[0, 3]) < 1e-6
                   for s in client.states[n:])

    assert client.spin_until(reached, 45.0), f"never reached; last state: {client.states[-1]}"
    assert sc.sim_tool_reaches(client, stack, T, POS_TOL, ROT_TOL, 10.0)
    stack.check()
