"""Pieces the end-to-end stack tests share: the simulated arm with the ROS nodes as a module fixture
(:class:`redarm_ros.testing.SimulatedArm`), an rclpy client base (own context, executor,
``spin_until``), the move to a ready pose with ``~/recover`` on a starved machine, and the simulated
tool's pose. Import after ``pytest.importorskip("rclpy")``."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from redarm_interfaces.msg import ControllerState
from redarm_interfaces.srv import SolveIK
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from redarm_ros.nodes._common import call_resending
from redarm_ros.nodes.controller import pose_to_msg
from redarm_ros.testing import SimulatedArm
from support.waits import spin_until as spin_executor_until

# Tool pointing down (z of the tool along -z of the base).
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def pose_down(p: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """4x4 pose at ``p`` with the tool pointing down."""
    T = np.eye(4)
    T[:3, :3] = R_DOWN
    T[:3, 3] = p
    return T


def sim_tool(arm: SimulatedArm) -> np.ndarray:
    """4x4 tool pose of the simulated arm (pybullet link state, read from the simulator now)."""
    return arm.status().tool


def pose_err(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Position (m) and rotation angle (rad) between two 4x4 poses."""
    pe = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    c = (np.trace(T_a[:3, :3].T @ T_b[:3, :3]) - 1.0) / 2.0
    return pe, float(math.acos(max(-1.0, min(1.0, c))))


def stack_fixture(node_args: dict[str, list[str]] | None = None, **cfg: Any) -> Any:
    """A module-scoped ``stack`` fixture: a :class:`SimulatedArm` with the driver (homed), the
    controller and the IK service (``cfg`` overrides, keywords of ``SimArmConfig``: e.g.
    ``description=True`` for a test that needs ``/robot_description``) on the test's ROS domain.
    Assign it to a module global named ``stack``."""

    @pytest.fixture(scope="module")
    def stack(ros_env: Any) -> Iterator[SimulatedArm]:
        settings = {"driver": True, "controller": True, "ik_service": True, **cfg}
        with SimulatedArm(domain_id=ros_env.domain_id, sink=stderr_sink, node_args=node_args or {},
                          **settings) as arm:
            yield arm

    return stack


def stderr_sink(line: str) -> None:
    """Stack output to stderr (pytest may have closed it at teardown)."""
    try:
        sys.stderr.write(line + "\n")
    except (ValueError, OSError):
        pass


class StackClient:
    """One rclpy node on its own executor; subclasses add the publishers and subscriptions."""

    SPIN_S = 0.02  # executor wait per spin in spin_until

    def __init__(self, ctx: Any, name: str, namespace: str = "") -> None:
        self.node = rclpy.create_node(name, context=ctx, namespace=namespace)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        return spin_executor_until(self.ex, cond, timeout, self.SPIN_S)

    def call(self, client: Any, request: Any, timeout: float) -> Any | None:
        """The service's answer to ``request`` (sent again while unanswered), or None after ``timeout`` s."""
        name = client.srv_name
        return call_resending(client, request, self.spin_until, timeout,
                              on_resend=lambda n: print(f"{name}: no answer, sent again ({n})"))

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()


class GoalClient(StackClient):
    """A client of the whole stack: goals on goal_pose, joint commands, ik_service, the controller's
    state messages; subclasses keep what they need of joint_states in ``on_joint_state``. Every name is
    relative: a client in ``namespace`` talks to the stack started there."""

    def __init__(self, ctx: Any, name: str, namespace: str = "") -> None:
        super().__init__(ctx, name, namespace)
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 10)
        self.cmd_pub = self.node.create_publisher(JointTrajectory, "joint_command", 10)
        self.ik = self.node.create_client(SolveIK, "ik_service/solve_ik")
        self.states: list[ControllerState] = []
        self.node.create_subscription(ControllerState, "controller/state", self.states.append, 50)
        self.joint_states = 0  # how many joint_states messages came
        self.node.create_subscription(JointState, "joint_states", self._joint_state, 50)

    def _joint_state(self, msg: JointState) -> None:
        self.joint_states += 1
        self.on_joint_state(msg)

    def on_joint_state(self, msg: JointState) -> None:
        pass

    def send(self, T: np.ndarray) -> int:
        """Publish ``T`` as a goal in base_link; the index of the first state message after it."""
        n = len(self.states)
        msg = pose_to_msg(T)
        msg.header.frame_id = "base_link"
        self.goal_pub.publish(msg)
        return n


C = TypeVar("C", bound=StackClient)


@contextmanager
def client_in_context(domain_id: int, make: Callable[[Any], C]) -> Iterator[C]:
    """A client made by ``make(ctx)`` in a fresh rclpy context; closed and shut down on exit."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    c = make(ctx)
    try:
        yield c
    finally:
        c.close()
        rclpy.shutdown(context=ctx)


def ready_client_fixture(make: Callable[[Any], GoalClient], joint_names: list[str], ready_q: np.ndarray,
                         start_s: float, ik_s: float, reach_s: float, recover_s: float) -> Any:
    """A module-scoped ``client`` fixture (assign it to a module global named ``client``): a
    ``GoalClient`` made by ``make`` (``client_in_context``) that has seen joint_states and controller
    state (``start_s``) and ik_service (``ik_s``), with the arm moved to ``ready_q``
    (``move_to_ready``)."""

    @pytest.fixture(scope="module")
    def client(stack: SimulatedArm, ros_env: Any) -> Iterator[GoalClient]:
        with client_in_context(ros_env.domain_id, make) as c:
            assert c.spin_until(lambda: c.joint_states > 5 and len(c.states) > 0, start_s), \
                "no joint_states / controller state"
            assert c.spin_until(c.ik.service_is_ready, ik_s)
            move_to_ready(c, c.cmd_pub, stack, joint_names, ready_q, reach_s=reach_s, recover_s=recover_s)
            yield c

    return client


def sim_tool_reaches(c: StackClient, stack: SimulatedArm, T: np.ndarray, pos_tol: float, rot_tol: float,
                     timeout: float, stay_s: float = 0.5) -> bool:
    """Spin until the simulated tool has stayed within ``pos_tol`` m and ``rot_tol`` rad of ``T`` for
    ``stay_s`` s. A tool only passing through the tolerance does not count: the joints end their moves
    at different times, so the tool's way in need not be monotone (a busy run read 1.02 mm just after a
    reading within 1 mm)."""
    since: list[float] = []

    def there() -> bool:
        pe, re = pose_err(sim_tool(stack), T)
        now = time.monotonic()
        if not (pe < pos_tol and re < rot_tol):
            since.clear()
            return False
        if not since:
            since.append(now)
        return now - since[0] >= stay_s

    return c.spin_until(there, timeout)


def sim_arm_still(c: StackClient, stack: SimulatedArm, window_s: float = 0.5, tol: float = 1e-4,
                  timeout: float = 15.0) -> bool:
    """Spin until the simulated joints have moved less than ``tol`` rad over the last ``window_s``
    seconds (``SimulatedArm.still``). False after ``timeout`` s."""
    return c.spin_until(stack.still(window_s, tol), timeout)


def move_to_ready(c: StackClient, cmd_pub: Any, stack: SimulatedArm, joint_names: list[str],
                  ready_q: np.ndarray, reach_s: float, recover_s: float) -> None:
    """Move the arm to ``ready_q`` through ``cmd_pub`` (/joint_command, made early so it is matched;
    a 3 s trajectory) and let the controller
    resync. On a starved 2-core machine the modules' 100 ms watchdog can halt the arm while the stack
    starts; the documented way out is ~/recover, so this recovers (twice at most) and says so."""
    traj = JointTrajectory(joint_names=joint_names)
    traj.points = [JointTrajectoryPoint(positions=[float(v) for v in ready_q],
                                        time_from_start=Duration(sec=3))]

    def at_ready() -> bool:
        return float(np.max(np.abs(stack.q - ready_q))) < 1e-3

    recover = c.node.create_client(Trigger, "can_driver/recover")
    for attempt in range(3):
        cmd_pub.publish(traj)
        if c.spin_until(at_ready, reach_s):
            break
        assert attempt < 2, f"arm not at the ready pose: {stack.q}"
        assert c.spin_until(recover.service_is_ready, 5.0)
        resp = c.call(recover, Trigger.Request(), recover_s)
        assert resp is not None and resp.success, f"~/recover failed: {resp}"
        print(f"e2e set-up: driver halted before the ready pose; recovered ({resp.message})")
    c.spin_until(lambda: False, 0.6)  # the controller sees a still arm away from its plan: resync
