"""End to end with the 6-DOF PowerCube arm: the stack (bus server, simulator with 6 modules, can_driver,
ik_service, controller) started by redarm_ros.bringup with ``arm=powercube6``. The test process moves
the arm to a ready pose through /joint_command, sends a reachable goal (reached by the *simulated*
tool) and one out of reach (rejected with the base-move suggestion). Generous time bounds: a busy
2-core machine slows every process."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from builtin_interfaces.msg import Duration  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from redarm_interfaces.msg import ControllerState  # noqa: E402
from redarm_interfaces.srv import SolveIK  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from redarm_ros.bringup import Stack, StackConfig  # noqa: E402
from redarm_ros.demo import DEMOS  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.kinematics.quaternion import from_xyzw, quat_to_matrix  # noqa: E402
from redarm_ros.nodes.controller import pose_to_msg  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

ARM = load_arm("powercube6")
DEMO = DEMOS["powercube6"]
READY_Q = np.array(DEMO.ready_q)


def _stderr(line: str) -> None:
    try:
        sys.stderr.write(line + "\n")
    except (ValueError, OSError):
        pass


def sim_tool(stack: Stack) -> np.ndarray:
    st = stack.sim_status()
    assert st is not None, "no simulator status"
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(from_xyzw(st["tool"]["quaternion_xyzw"]))
    T[:3, 3] = st["tool"]["position"]
    return T


def pose_err(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    pe = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    c = (np.trace(T_a[:3, :3].T @ T_b[:3, :3]) - 1.0) / 2.0
    return pe, float(math.acos(max(-1.0, min(1.0, c))))


class Client:
    def __init__(self, ctx: Any) -> None:
        self.node = rclpy.create_node("e2e6_client", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 10)
        self.cmd_pub = self.node.create_publisher(JointTrajectory, "joint_command", 10)
        self.ik = self.node.create_client(SolveIK, "/ik_service/solve_ik")
        self.states: list[ControllerState] = []
        self.names: list[list[str]] = []  # joint names of each joint_states message
        self.node.create_subscription(ControllerState, "/controller/state", self.states.append, 50)
        self.node.create_subscription(JointState, "joint_states",
                                      lambda m: self.names.append(list(m.name)), 50)

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.ex.spin_once(timeout_sec=0.02)
            if cond():
                return True
        return False

    def send(self, T: np.ndarray) -> int:
        n = len(self.states)
        msg = pose_to_msg(T)
        msg.header.frame_id = "base_link"
        self.goal_pub.publish(msg)
        return n

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()


@pytest.fixture(scope="module")
def stack(ros_env: Any) -> Iterator[Stack]:
    cfg = StackConfig(arm="powercube6", log_level="warn", ready_timeout_s=90.0)
    st = Stack(cfg, sink=_stderr, domain_id=ros_env.domain_id)
    try:
        st.start()
        st.children["can_driver"].wait_for_line(r"init done", timeout=60.0, from_start=True)
        yield st
    finally:
        pids = [c.pid for c in st.children.values()]
        st.close()
        from redarm_ros.procs import group_members

        assert not [p for p in pids if group_members(p)], "a stack process outlived Stack.close()"


@pytest.fixture(scope="module")
def client(stack: Stack, ros_env: Any) -> Iterator[Client]:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_env.domain_id)
    c = Client(ctx)
    try:
        assert c.spin_until(lambda: len(c.names) > 5 and len(c.states) > 0, 60.0), \
            "no joint_states / controller state"
        assert c.spin_until(c.ik.service_is_ready, 20.0)
        traj = JointTrajectory(joint_names=ARM.joint_names)
        traj.points = [JointTrajectoryPoint(positions=[float(v) for v in READY_Q],
                                            time_from_start=Duration(sec=3))]

        def at_ready() -> bool:
            return float(np.max(np.abs(np.array(stack.sim_status()["q"]) - READY_Q))) < 1e-3

        # A starved machine can make the driver halt the modules (watchdog); ~/recover is the way out.
        recover = c.node.create_client(Trigger, "/can_driver/recover")
        for attempt in range(3):
            c.cmd_pub.publish(traj)
            if c.spin_until(at_ready, 25.0):
                break
            assert attempt < 2, f"arm not at the ready pose: {stack.sim_status()['q']}"
            assert c.spin_until(recover.service_is_ready, 5.0)
            fut = recover.call_async(Trigger.Request())
            assert c.spin_until(fut.done, 20.0) and fut.result().success, "~/recover failed"
        c.spin_until(lambda: False, 0.6)  # the controller restarts from the still arm
        yield c
    finally:
        c.close()
        rclpy.shutdown(context=ctx)


def test_six_joints_and_a_goal_reached_by_the_simulated_arm(stack: Stack, client: Client) -> None:
    assert client.names[-1] == list(ARM.joint_names)
    goal = next(g for g in DEMO.goals if g.name == "front")
    T = goal.matrix()
    driver = stack.children["can_driver"]
    recover = client.node.create_client(Trigger, "/can_driver/recover")
    for attempt in range(3):
        halts = sum("HALTED:" in line for line in driver.output())
        n = client.send(T)

        def reached(n: int = n) -> bool:
            return any(s.phase == ControllerState.REACHED and abs(s.goal.position.x - T[0, 3]) < 1e-6
                       for s in client.states[n:])

        if client.spin_until(reached, 150.0):
            break
        # A starved machine can make the driver halt the modules mid-motion: recover and send it again
        # (as an operator would, and as the demo does); anything else is a failure.
        assert attempt < 2 and sum("HALTED:" in line for line in driver.output()) > halts, \
            f"goal not reached; last state: {client.states[-1]}"
        assert client.spin_until(recover.service_is_ready, 5.0)
        fut = recover.call_async(Trigger.Request())
        assert client.spin_until(fut.done, 20.0) and fut.result().success, "~/recover failed"
        client.spin_until(lambda: False, 1.0)  # the controller restarts from the still arm
    ok = client.spin_until(lambda: all(e < t for e, t in zip(pose_err(sim_tool(stack), T), (2e-3, 0.02),
                                                              strict=True)), 40.0)
    assert ok, f"simulated tool {pose_err(sim_tool(stack), T)} from the goal"
    stack.check()


def test_out_of_reach_goal_rejected_with_the_base_move(stack: Stack, client: Client) -> None:
    goal = next(g for g in DEMO.goals if g.name == "out_of_reach")
    n = client.send(goal.matrix())

    def rejected() -> ControllerState | None:
        return next((s for s in client.states[n:] if s.phase == ControllerState.REJECTED), None)

    assert client.spin_until(lambda: rejected() is not None, 30.0)
    msg = rejected().message
    assert "out of reach" in msg and "move the base by dx =" in msg, msg
    stack.check()
