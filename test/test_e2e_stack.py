"""End to end: the whole stack as separate processes (bus server, pybullet simulator, can_driver,
ik_service, controller) started by redarm_ros.bringup. The test process is an rclpy client: it moves
the arm to a ready pose through /joint_command, asks ik_service for a pose, sends the same pose as a
goal on /goal_pose, and checks the *simulated* tool (pybullet link state from the simulator's status
file) ends within 1 mm / 0.01 rad of it. Everything is stopped and checked gone at the end."""

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
pytest.importorskip("redarm_ros.nodes.can_driver", reason="can_driver node not written yet")
pytest.importorskip("redarm_ros.sim.hardware", reason="simulator not written yet")

from builtin_interfaces.msg import Duration  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from redarm_interfaces.msg import ControllerState  # noqa: E402
from redarm_interfaces.srv import SolveIK  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from redarm_ros.bringup import Stack, StackConfig  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.kinematics.quaternion import from_xyzw, quat_to_matrix  # noqa: E402
from redarm_ros.nodes.controller import pose_to_msg  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

ARM = load_arm("pa10")
# The driver homes the modules to 0 on init, the stretched (singular) pose of the PA10; the demo and
# this test first move to a ready pose with the elbow bent.
READY_Q = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])
POS_TOL, ROT_TOL = 1e-3, 0.01


def _stderr(line: str) -> None:
    try:
        sys.stderr.write(line + "\n")
    except (ValueError, OSError):
        pass


def sim_tool(stack: Stack) -> np.ndarray:
    """4x4 tool pose of the simulated arm (pybullet link state, from the sim's status file)."""
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
    """rclpy side of the test: goals, joint commands, IK calls, controller state, joint states."""

    def __init__(self, ctx: Any) -> None:
        self.node = rclpy.create_node("e2e_client", context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 10)
        self.cmd_pub = self.node.create_publisher(JointTrajectory, "joint_command", 10)
        self.ik = self.node.create_client(SolveIK, "/ik_service/solve_ik")
        self.states: list[ControllerState] = []
        self.joints: list[np.ndarray] = []
        self.node.create_subscription(ControllerState, "/controller/state", self.states.append, 50)
        self.node.create_subscription(JointState, "joint_states",
                                      lambda m: self.joints.append(np.array(m.position)), 50)

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.ex.spin_once(timeout_sec=0.02)
            if cond():
                return True
        return False

    def seen(self, phase: str, after: int) -> bool:
        """True if the controller reported ``phase`` in a state message after index ``after``."""
        return any(s.phase == phase for s in self.states[after:])

    def solve(self, T: np.ndarray, seed: np.ndarray) -> SolveIK.Response:
        req = SolveIK.Request()
        req.target = pose_to_msg(T)
        req.target.header.frame_id = "base_link"
        req.seed = [float(v) for v in seed]
        fut = self.ik.call_async(req)
        assert self.spin_until(fut.done, 10.0), "ik_service did not answer"
        return fut.result()

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()


@pytest.fixture(scope="module")
def stack(ros_env: Any) -> Iterator[Stack]:
    cfg = StackConfig(arm="pa10", log_level="warn", ready_timeout_s=60.0)
    st = Stack(cfg, sink=_stderr, domain_id=ros_env.domain_id)
    try:
        st.start()
        st.children["can_driver"].wait_for_line(r"init done", timeout=30.0, from_start=True)
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
        assert c.spin_until(lambda: len(c.joints) > 5 and len(c.states) > 0, 30.0), \
            "no joint_states / controller state"
        assert c.spin_until(c.ik.service_is_ready, 10.0)
        # Move to the ready pose through the driver (a 3 s trajectory), then let the controller resync.
        traj = JointTrajectory(joint_names=ARM.joint_names)
        traj.points = [JointTrajectoryPoint(positions=[float(v) for v in READY_Q],
                                            time_from_start=Duration(sec=3))]

        def at_ready() -> bool:
            return float(np.max(np.abs(np.array(stack.sim_status()["q"]) - READY_Q))) < 1e-3

        # On a starved 2-core CI machine the modules' 100 ms watchdog can halt the arm while the stack
        # starts; the documented way out is ~/recover, so the set-up recovers (twice at most) and says so.
        recover = c.node.create_client(Trigger, "/can_driver/recover")
        for attempt in range(3):
            c.cmd_pub.publish(traj)
            if c.spin_until(at_ready, 15.0):
                break
            assert attempt < 2, f"arm not at the ready pose: {stack.sim_status()['q']}"
            assert c.spin_until(recover.service_is_ready, 5.0)
            fut = recover.call_async(Trigger.Request())
            assert c.spin_until(fut.done, 15.0) and fut.result().success, "~/recover failed"
            print(f"e2e set-up: driver halted before the ready pose; recovered ({fut.result().message})")
        c.spin_until(lambda: False, 0.6)  # the controller sees a still arm away from its plan: resync
        yield c
    finally:
        c.close()
        rclpy.shutdown(context=ctx)


def test_ik_then_goal_reached_by_the_simulated_arm(stack: Stack, client: Client) -> None:
    q_target = np.array([0.4, 0.7, -0.3, 1.0, 0.2, 0.9, 0.3])
    T = ARM.fk(q_target)
    resp = client.solve(T, READY_Q)
    assert resp.status == SolveIK.Response.SUCCESS, resp.message
    q_ik = np.array(resp.solution.position)
    assert pose_err(ARM.fk(q_ik), T)[0] < 1e-9
    stack.check()

    n = len(client.states)
    msg = pose_to_msg(T)
    msg.header.frame_id = "base_link"
    client.goal_pub.publish(msg)
    def reached_this_goal() -> bool:  # a REACHED still in flight for an earlier goal does not count
        return any(s.phase == ControllerState.REACHED and abs(s.goal.position.x - T[0, 3]) < 1e-6
                   and abs(s.goal.position.y - T[1, 3]) < 1e-6 for s in client.states[n:])

    reached = client.spin_until(reached_this_goal, 45.0)
    stack.check()
    halts = sum("HALTED:" in line for line in stack.children["can_driver"].output())
    assert reached, (f"controller never reached the goal; last state: {client.states[-1]}; "
                     f"driver halts: {halts}")
    # The simulated arm follows the last commands within a few control periods.
    ok = client.spin_until(lambda: all(e < t for e, t in zip(pose_err(sim_tool(stack), T), (POS_TOL, ROT_TOL),
                                                              strict=True)), 10.0)
    pe, re = pose_err(sim_tool(stack), T)
    assert ok, f"simulated tool {pe * 1e3:.3f} mm / {re:.4f} rad from the goal"
    assert pe < POS_TOL and re < ROT_TOL
    stack.check()


def test_out_of_reach_goal_rejected_and_arm_holds(stack: Stack, client: Client) -> None:
    q_before = np.array(stack.sim_status()["q"])
    T = np.eye(4)
    T[:3, 3] = (1.5, 0.0, 0.5)
    n = len(client.states)
    msg = pose_to_msg(T)
    msg.header.frame_id = "base_link"
    client.goal_pub.publish(msg)
    assert client.spin_until(lambda: client.seen(ControllerState.REJECTED, n), 10.0)
    assert client.solve(T, READY_Q).status == SolveIK.Response.OUT_OF_REACH
    client.spin_until(lambda: False, 1.0)
    # Holding: the arm stays where it was (the elbow may not drift either).
    assert np.max(np.abs(np.array(stack.sim_status()["q"]) - q_before)) < 0.02
    stack.check()
