"""controller node in-process against an ideal arm (joint_command echoed to joint_states): reaching,
retargeting mid-motion, rejection (out of reach, inside an obstacle, foreign frame), obstacles from a
MarkerArray, markers and state, parameter validation; marker <-> obstacle conversion."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from support.requires import require_ros
from support.waits import spin_until

require_ros()

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseStamped, TwistStamped  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from redarm_interfaces.msg import ControllerState  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from redarm_ros.errors import InvalidInputError  # noqa: E402
from redarm_ros.geometry.obstacles import Box, Cylinder, Sphere  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.nodes._common import DuplicateNodeError  # noqa: E402
from redarm_ros.nodes.controller import (  # noqa: E402
    PARAMS,
    ControllerNode,
    controller_params,
    marker_to_obstacle,
    obstacle_to_marker,
    pose_to_msg,
)

ARM = load_arm("pa10")
# A comfortable start: elbow bent, tool in front of the robot at table height + 0.3 m.
Q0 = np.array([0.0, 0.6, 0.0, 1.4, 0.0, 1.1, 0.0])


class IdealArm:
    """Test double of can_driver + hardware: the last commanded point becomes the measured state."""

    def __init__(self, ctx: Any, q0: np.ndarray, stamp_offset: float | None = None) -> None:
        self.node = rclpy.create_node("fake_arm", context=ctx)
        self.stamp_offset = stamp_offset  # joint_states stamped with the clock plus this (None: unstamped)
        self.segment_ends: list[float] = []  # stamped commands: segment end minus receipt (s)
        self.q = q0.astype(float).copy()
        self.commands: list[np.ndarray] = []
        self.segment_starts_ok = True  # every two-point message starts at the previous command
        self.speed_ratio = 0.0  # largest |dq| / (max_vel * duration) of a two-point segment, over the joints
        self.longest_segment = 0.0  # s
        self.commanded_s = 0.0  # the controller's time in motion: the durations of its steps, summed
        self.pub = self.node.create_publisher(JointState, "joint_states", 10)
        self.node.create_subscription(JointTrajectory, "joint_command", self._on_cmd, 100)
        self.node.create_timer(0.01, self.publish)
        self.publishing = True
        self.ticks = 0  # calls of that 100 Hz timer: the executor's own clock, slowed with the machine

    def _on_cmd(self, msg: JointTrajectory) -> None:
        assert list(msg.joint_names) == ARM.joint_names
        # One step per message: [previous command at t=0,] new command at t=dt > 0.
        assert len(msg.points) in (1, 2)
        end = msg.points[-1]
        assert end.time_from_start.sec * 1e9 + end.time_from_start.nanosec > 0
        if len(msg.points) == 2:
            assert msg.points[0].time_from_start.sec == msg.points[0].time_from_start.nanosec == 0
            self.segment_starts_ok &= bool(self.commands) and np.allclose(msg.points[0].positions,
                                                                          self.commands[-1])
        if msg.header.stamp.sec or msg.header.stamp.nanosec:
            t_end = (msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 + end.time_from_start.sec
                     + end.time_from_start.nanosec * 1e-9)
            self.segment_ends.append(t_end - self.node.get_clock().now().nanoseconds * 1e-9)
        q = np.array(end.positions)
        duration = end.time_from_start.sec + end.time_from_start.nanosec * 1e-9
        self.longest_segment = max(self.longest_segment, duration)
        self.commanded_s += duration
        if len(msg.points) == 2:  # the speed the segment asks for, whatever the step's duration was
            dq = np.abs(q - np.array(msg.points[0].positions))
            self.speed_ratio = max(self.speed_ratio, float(np.max(dq / (ARM.max_vel * duration))))
        self.commands.append(q)
        self.q = q

    def publish(self) -> None:
        self.ticks += 1
        if self.publishing:
            msg = JointState(name=ARM.joint_names, position=[float(v) for v in self.q])
            if self.stamp_offset is not None:
                t = self.node.get_clock().now().nanoseconds * 1e-9 + self.stamp_offset
                msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), int((t - int(t)) * 1e9)
            self.pub.publish(msg)


class Harness:
    """Controller node + ideal arm + a probe (goals/obstacles out, state/markers in), one executor."""

    def __init__(self, ctx: Any, q0: np.ndarray = Q0, stamp_offset: float | None = None,
                 **params: Any) -> None:
        overrides = [Parameter("duplicate_check_s", value=0.0)]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.ctl = ControllerNode(context=ctx, parameter_overrides=overrides)
        self.arm = IdealArm(ctx, q0, stamp_offset)
        self.probe = rclpy.create_node("probe", context=ctx)
        self.goal_pub = self.probe.create_publisher(PoseStamped, "goal_pose", 10)
        self.twist_pub = self.probe.create_publisher(TwistStamped, "/controller/target_twist", 10)
        self.obs_pub = self.probe.create_publisher(MarkerArray, "obstacles", 10)
        self.states: list[ControllerState] = []
        self.markers: list[MarkerArray] = []
        self.probe.create_subscription(ControllerState, "/controller/state", self.states.append, 100)
        self.probe.create_subscription(MarkerArray, "/controller/markers", self.markers.append, 10)
        self.ex = SingleThreadedExecutor(context=ctx)
        for n in (self.ctl, self.arm.node, self.probe):
            self.ex.add_node(n)

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        return spin_until(self.ex, cond, timeout, 0.01)

    def spin_ticks(self, ticks: int, cond: Callable[[], bool] = lambda: False) -> bool:
        """Spin until ``cond`` holds (True) or the ideal arm's 100 Hz timer has fired ``ticks`` times
        more (False): a window on the executor's clock, which a loaded machine stretches together with
        the controller's timers (a rcl timer skips the periods it missed, never fires faster)."""
        k = self.arm.ticks
        self.spin_until(lambda: bool(cond()) or self.arm.ticks - k >= ticks, 60.0 + ticks * 0.1)
        return bool(cond())

    def pump(self, wait_s: float = 0.002, at_most: int = 30) -> None:
        """Run the callbacks that are ready (waiting up to ``wait_s`` for the first). A test's sending
        loop calls it between messages: one callback per message would starve the nodes on a loaded
        machine, and their subscriptions (depth 10) would drop most of what was sent."""
        self.ex.spin_once(timeout_sec=wait_s)
        for _ in range(at_most):
            self.ex.spin_once(timeout_sec=0.0)

    def wait_connected(self) -> None:
        assert self.spin_until(lambda: self.goal_pub.get_subscription_count() > 0
                               and self.twist_pub.get_subscription_count() > 0
                               and self.ctl.cmd_pub.get_subscription_count() > 0
                               and len(self.states) > 0, 10.0)

    def send_goal(self, T: np.ndarray, frame: str = "base_link", stamp: float | None = None) -> None:
        """Publish a goal; ``stamp``: header stamp (s, ROS time), else left zero ("now")."""
        msg = pose_to_msg(T)
        msg.header.frame_id = frame
        if stamp is not None:
            msg.header.stamp.sec = int(stamp)
            msg.header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)
        self.goal_pub.publish(msg)

    def ros_now(self) -> float:
        return self.probe.get_clock().now().nanoseconds * 1e-9

    def phase(self) -> str:
        return self.states[-1].phase if self.states else ""

    def wait_phase(self, phase: str, timeout: float, after: int = 0) -> bool:
        return self.spin_until(lambda: any(s.phase == phase for s in self.states[after:]), timeout)

    def wait_reached(self, timeout: float, after: int = 0) -> bool:
        """REACHED (commanded pose within tolerance), then a short settle so the last command is in."""
        ok = self.wait_phase(ControllerState.REACHED, timeout, after)
        self.spin_until(lambda: False, 0.3)
        return ok

    def close(self) -> None:
        self.ex.shutdown()
        for n in (self.ctl, self.arm.node, self.probe):
            n.destroy_node()


@pytest.fixture
def ctx(rclpy_context: Any) -> Any:
    return rclpy_context  # conftest's fresh context on the session's domain


@pytest.fixture
def h(ctx: Any) -> Iterator[Harness]:
    harness = Harness(ctx)
    harness.wait_connected()
    yield harness
    harness.close()


@pytest.fixture
def h_busy(ctx: Any) -> Iterator[Harness]:
    """A controller whose loop never rests (idle_after_s 0): it steps at its rate, goal or not."""
    harness = Harness(ctx, idle_after_s=0.0)
    harness.wait_connected()
    yield harness
    harness.close()


def goal_from(q0: np.ndarray, dp: tuple[float, float, float], rot: np.ndarray | None = None) -> np.ndarray:
    T = ARM.fk(q0).copy()
    T[:3, 3] += dp
    if rot is not None:
        T[:3, :3] = rot @ T[:3, :3]
    return T


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def assert_within_joint_speeds(arm: IdealArm) -> None:
    """Continuous motion: every segment asks for at most each joint's velocity limit over its own duration,
    and no segment is longer than the node's clamp of a late step (2 periods of 0.01 s). Judged on what
    was commanded, not on how punctual the timer was on a loaded machine."""
    assert arm.speed_ratio <= 1.0 + 1e-6, arm.speed_ratio
    assert arm.longest_segment <= 0.02 + 1e-6, arm.longest_segment


def test_reaches_goal_and_holds(h: Harness) -> None:
    assert h.phase() == ControllerState.IDLE
    assert h.arm.commands == [], "nothing is commanded before the first goal"
    T = goal_from(Q0, (0.05, 0.15, 0.05), rot_z(0.3))
    h.send_goal(T)
    assert h.wait_phase(ControllerState.REACHING, 5.0)
    assert h.wait_reached(20.0), h.states[-1]
    pe, re = ARM.pose_error(h.arm.q, T)
    assert pe < 1e-3 and re < 0.01
    st = h.states[-1]
    assert st.distance_to_goal < 1e-3 and st.orientation_error < 0.01
    assert st.goal.position.x == pytest.approx(T[0, 3])
    assert st.clearance > 0.0  # no obstacles: the arm's clearance to itself and the ground
    assert_within_joint_speeds(h.arm)
    C = np.array(h.arm.commands)  # every command within the limits, both sides
    assert np.all(C >= ARM.lower - 1e-9) and np.all(C <= ARM.upper + 1e-9)
    assert h.arm.segment_starts_ok
    # After REACHED the hand stays on the goal (the elbow may still settle towards its preferred swivel).
    n = len(h.arm.commands)
    assert h.spin_until(lambda: len(h.arm.commands) > n + 50, 10.0)
    for q in h.arm.commands[n:]:
        pe, re = ARM.pose_error(q, T)
        assert pe < 1e-3 and re < 0.01


def test_retarget_mid_motion_is_smooth(h: Harness) -> None:
    T1 = goal_from(Q0, (0.0, 0.25, 0.0))
    T2 = goal_from(Q0, (0.1, -0.1, 0.1))
    h.send_goal(T1)
    assert h.wait_phase(ControllerState.REACHING, 5.0)
    assert h.spin_until(lambda: len(h.arm.commands) > 40, 5.0)
    assert h.phase() != ControllerState.REACHED  # the new goal comes mid-motion
    h.send_goal(T2)
    n = len(h.states)
    assert h.wait_reached(25.0, after=n)
    pe, re = ARM.pose_error(h.arm.q, T2)
    assert pe < 1e-3 and re < 0.01
    assert_within_joint_speeds(h.arm)
    assert h.arm.segment_starts_ok  # each segment starts where the last one ended
    # The state never went through REJECTED or IDLE on the way.
    assert not any(s.phase in (ControllerState.REJECTED, ControllerState.IDLE) for s in h.states[n:])


def test_out_of_reach_goal_rejected_arm_holds(h: Harness) -> None:
    T = np.eye(4)
    T[:3, 3] = (2.0, 0.0, 0.3)
    q_before = h.arm.q.copy()
    h.send_goal(T)
    assert h.wait_phase(ControllerState.REJECTED, 5.0)
    st = next(s for s in h.states if s.phase == ControllerState.REJECTED)
    assert "reach" in st.message
    h.spin_until(lambda: False, 0.3)
    assert np.allclose(h.arm.q, q_before)
    # A good goal afterwards is taken.
    h.send_goal(goal_from(Q0, (0.0, 0.1, 0.0)))
    assert h.wait_reached(20.0)


def test_foreign_frame_and_nan_goal_rejected(h: Harness) -> None:
    h.send_goal(goal_from(Q0, (0.0, 0.1, 0.0)), frame="camera")
    assert h.wait_phase(ControllerState.REJECTED, 5.0)
    assert "camera" in [s for s in h.states if s.phase == ControllerState.REJECTED][-1].message
    msg = pose_to_msg(goal_from(Q0, (0.0, 0.1, 0.0)))
    msg.pose.position.x = math.nan
    n = len(h.states)
    h.goal_pub.publish(msg)
    assert h.wait_phase(ControllerState.REJECTED, 5.0, after=n)
    assert h.arm.commands == []


def _marker(mtype: int, pos: tuple[float, float, float], scale: tuple[float, float, float], mid: int = 0,
            action: int = Marker.ADD) -> Marker:
    m = Marker()
    m.header.frame_id = "base_link"
    m.ns, m.id, m.type, m.action = "test", mid, mtype, action
    m.pose.position.x, m.pose.position.y, m.pose.position.z = pos
    m.pose.orientation.w = 1.0
    m.scale.x, m.scale.y, m.scale.z = scale
    return m


def test_goal_inside_obstacle_rejected_and_obstacles_on_topic(h: Harness) -> None:
    T = goal_from(Q0, (0.0, 0.2, 0.0))
    h.obs_pub.publish(MarkerArray(markers=[_marker(Marker.SPHERE, tuple(T[:3, 3]), (0.1, 0.1, 0.1))]))
    assert h.spin_until(lambda: len(h.ctl.ctl.scene) == 1, 5.0)
    h.send_goal(T)
    assert h.wait_phase(ControllerState.REJECTED, 5.0)
    assert "obstacle" in [s for s in h.states if s.phase == ControllerState.REJECTED][-1].message
    # Clear the obstacles: the same goal is accepted and reached.
    clear_all = _marker(Marker.SPHERE, (0, 0, 0), (1, 1, 1), action=Marker.DELETEALL)
    h.obs_pub.publish(MarkerArray(markers=[clear_all]))
    assert h.spin_until(lambda: len(h.ctl.ctl.scene) == 0, 5.0)
    h.send_goal(T)
    assert h.wait_reached(20.0)


def test_obstacle_appearing_on_goal_drops_it(h: Harness) -> None:
    T = goal_from(Q0, (0.0, 0.25, 0.0))
    h.send_goal(T)
    assert h.wait_phase(ControllerState.REACHING, 5.0)
    h.obs_pub.publish(MarkerArray(markers=[_marker(Marker.CUBE, tuple(T[:3, 3]), (0.1, 0.1, 0.1))]))
    n = len(h.states)
    assert h.wait_phase(ControllerState.REJECTED, 5.0, after=n)
    # It stops smoothly and then holds.
    h.spin_until(lambda: False, 1.0)
    k = len(h.arm.commands)
    h.spin_until(lambda: False, 0.3)
    assert np.allclose(h.arm.q, h.arm.commands[k - 1], atol=1e-6)
    assert_within_joint_speeds(h.arm)


def test_diagnostics_count_the_loops_steps_and_the_obstacles_kept(h_busy: Harness) -> None:
    """/diagnostics carries the loop's own step count (cumulative, with its clock: a reader takes the
    rate between two messages however many it missed) and how many obstacles the broad phase keeps."""
    h = h_busy
    diags: list[dict[str, str]] = []

    def on_diag(arr: DiagnosticArray) -> None:
        diags.extend({kv.key: kv.value for kv in st.values} | {"_name": st.name, "_msg": st.message}
                     for st in arr.status if st.name == "controller: loop")

    h.probe.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    near = _marker(Marker.SPHERE, (0.5, -0.4, 0.3), (0.1, 0.1, 0.1), mid=0)
    far = _marker(Marker.SPHERE, (6.0, 6.0, 0.3), (0.1, 0.1, 0.1), mid=1)  # beyond any reach
    h.obs_pub.publish(MarkerArray(markers=[near, far]))
    # Two reports of the loop stepping (on a starved machine a report may come after ten missed ticks
    # and say "no step for ..."; that is the stopped case below, not this one).
    def stepping() -> list[dict[str, str]]:
        return [d for d in diags if d["obstacles"] == "2" and not d["_msg"].startswith("no step for")]

    assert h.spin_until(lambda: len(stepping()) >= 2, 30.0), diags
    a, b = stepping()[-2:]
    assert b["obstacles_within_reach"] == "1"
    assert b["rate_hz_target"] == "100"
    steps = int(b["steps"]) - int(a["steps"])
    span = float(b["loop_clock_s"]) - float(a["loop_clock_s"])
    assert steps > 0 and span > 0.0
    assert int(b["missed_ticks"]) >= 0 and float(b["step_busy_max_ms"]) >= float(b["step_busy_median_ms"]) > 0
    assert float(b["rate_hz_achieved"]) > 0.0 and b["_msg"].endswith("Hz") or "misses ticks" in b["_msg"]
    assert b["scheduling"]  # in a test process: whatever the runner has, said in words
    assert float(b["last_step_age_s"]) < 0.5
    # joint_states stop: the loop holds without stepping, and the diagnostics say so (not the last rate).
    h.arm.publishing = False
    n = len(diags)
    assert h.spin_until(lambda: any(d["_msg"].startswith("no step for") for d in diags[n:]), 10.0), diags[n:]
    stopped = next(d for d in diags[n:] if d["_msg"].startswith("no step for"))
    assert float(stopped["last_step_age_s"]) > 0.1
    assert float(stopped["rate_hz_achieved"]) < 0.9 * 100


def test_markers_published(h: Harness) -> None:
    h.send_goal(goal_from(Q0, (0.0, 0.2, 0.0)))
    h.obs_pub.publish(MarkerArray(markers=[_marker(Marker.CYLINDER, (0.5, -0.4, 0.1), (0.1, 0.1, 0.2))]))
    # Over the arrays since the goal: obstacles are re-sent every 2 s, the heading only while the arm
    # moves, so one array need not carry both (on a loaded machine often does not).
    def drawn(ns: str) -> list[Marker]:
        return [m for ma in h.markers for m in ma.markers if m.ns == ns and m.action == Marker.ADD]

    wanted = ("arm", "elbow_circle", "goal", "obstacles", "heading")
    assert h.spin_until(lambda: all(drawn(ns) for ns in wanted), 30.0), [ns for ns in wanted if not drawn(ns)]
    circle = drawn("elbow_circle")[-1]
    assert len(circle.points) > 20 and circle.header.frame_id == "base_link"
    obs = drawn("obstacles")[-1]
    assert obs.type == Marker.CYLINDER and obs.scale.z == pytest.approx(0.2)


def test_markers_built_only_for_listeners_and_a_late_one_gets_the_obstacles(h: Harness) -> None:
    """With nobody on ~/markers nothing is built (a thousand obstacles cost half the control rate);
    a listener that joins later gets the obstacles (re-sent for it)."""
    h.obs_pub.publish(MarkerArray(markers=[_marker(Marker.SPHERE, (0.5, -0.4, 0.3), (0.1, 0.1, 0.1))]))
    assert h.spin_until(lambda: any(m.ns == "obstacles" for ma in h.markers for m in ma.markers), 5.0)
    sub = next(s for s in h.probe.subscriptions if s.topic_name == "/controller/markers")
    h.probe.destroy_subscription(sub)
    assert h.spin_until(lambda: h.ctl.marker_pub.get_subscription_count() == 0, 5.0)
    h.spin_until(lambda: False, 0.3)
    assert h.ctl._marker_listeners == 0 and h.ctl._last_marker_ids == set()
    late: list[MarkerArray] = []
    h.probe.create_subscription(MarkerArray, "/controller/markers", late.append, 10)
    assert h.spin_until(lambda: any(m.ns == "obstacles" for ma in late for m in ma.markers), 5.0)


def test_goal_before_joint_states_waits(ctx: Any) -> None:
    h = Harness(ctx)
    try:
        h.arm.publishing = False
        assert h.spin_until(lambda: h.goal_pub.get_subscription_count() > 0, 10.0)
        T = goal_from(Q0, (0.0, 0.1, 0.0))
        h.send_goal(T)
        h.spin_until(lambda: False, 0.3)
        assert h.arm.commands == []
        h.arm.publishing = True
        assert h.wait_reached(20.0)
        assert ARM.pose_error(h.arm.q, T)[0] < 1e-3
    finally:
        h.close()


@pytest.mark.parametrize("offset", [0.0, 5.0])
def test_commands_stamped_to_end_the_delay_after_their_step(ctx: Any, offset: float) -> None:
    """joint_states stamped with the controller's clock: every segment is stamped to end
    command_delay_s after its step, i.e. at most that long after it arrives (how much earlier depends
    on the machine's load, not asserted); a driver clock 5 s ahead: unstamped segments."""
    h = Harness(ctx, stamp_offset=offset, command_delay_s=0.05)
    try:
        h.wait_connected()
        h.send_goal(goal_from(Q0, (0.0, 0.1, 0.0)))
        assert h.wait_reached(20.0)
        ends = np.array(h.arm.segment_ends)
        if offset:
            assert ends.size == 0
            return
        assert ends.size > 20
        assert np.all(ends <= 0.05 + 1e-3)
    finally:
        h.close()


def test_parameters(ctx: Any) -> None:
    h = Harness(ctx, preferred_swivel=0.2, rate_hz=50.0, idle_after_s=0.0)  # markers timed: never rests
    try:
        node = h.ctl
        assert node.ctl.params.preferred_swivel == pytest.approx(0.2)
        assert node.set_parameters([Parameter("preferred_swivel", value=-0.4)])[0].successful
        assert node.ctl.params.preferred_swivel == pytest.approx(-0.4)
        assert not node.set_parameters([Parameter("preferred_swivel", value=math.nan)])[0].successful
        assert not node.set_parameters([Parameter("preferred_swivel", value=1e300)])[0].successful
        assert node.ctl.params.preferred_swivel == pytest.approx(-0.4)
        assert not node.set_parameters([Parameter("rate_hz", value=10.0)])[0].successful  # read-only
        # an empty base_frame would refuse every goal given in base_link: refused itself
        assert not node.set_parameters([Parameter("base_frame", value="")])[0].successful
        assert node.get_parameter("base_frame").value == "base_link"
        # The marker rate applies at run time: 0 stops the markers, 50 Hz runs them at 50 Hz. Counted
        # against the loop's own steps (50 Hz too), not the wall clock: on a starved machine both
        # timers fire late together.
        def markers_per_step(steps: int) -> float:
            n, k = len(h.markers), node.steps
            assert h.spin_until(lambda: node.steps - k >= steps, 60.0), "the loop stopped stepping"
            return (len(h.markers) - n) / (node.steps - k)

        assert node.set_parameters([Parameter("markers_rate_hz", value=0.0)])[0].successful
        markers_per_step(10)  # (a message already in flight)
        assert markers_per_step(50) == 0.0
        assert node.set_parameters([Parameter("markers_rate_hz", value=50.0)])[0].successful
        markers_per_step(10)
        assert markers_per_step(50) >= 0.6  # about 1 (0.2 at the 10 Hz before)
        assert not node.set_parameters([Parameter("markers_rate_hz", value=-1.0)])[0].successful
    finally:
        h.close()
    with pytest.raises(ValueError):
        ControllerNode(context=ctx, node_name="ctl_bad", parameter_overrides=[
            Parameter("duplicate_check_s", value=0.0), Parameter("arm", value="no_such_arm")])
    with pytest.raises(ValueError):
        ControllerNode(context=ctx, node_name="ctl_bad2", parameter_overrides=[
            Parameter("duplicate_check_s", value=0.0), Parameter("swivel_mode", value="sideways")])
    # a misspelt parameter is named in a warning (the node starts with its defaults)
    typo = ControllerNode(context=ctx, node_name="ctl_typo", parameter_overrides=[
        Parameter("duplicate_check_s", value=0.0), Parameter("prefered_swivel", value=0.3)])
    try:
        assert typo.unknown_parameters == ["prefered_swivel"]
    finally:
        typo.destroy_node()


def test_the_corridor_route_is_a_node_parameter() -> None:
    """``corridor`` (read-only, default the table's true) switches the controller's corridor route."""
    spec = {p.name: p for p in PARAMS}["corridor"]
    assert spec.default is True and spec.read_only
    values = {p.name: p.default for p in PARAMS}
    assert controller_params(values).replan.corridor is True
    assert controller_params({**values, "corridor": False}).replan.corridor is False


def test_marker_obstacle_round_trip() -> None:
    for shape in (Sphere((0.1, 0.2, 0.3), 0.05), Cylinder((0.4, 0.0, 0.1), 0.03, 0.2),
                  Box((0.5, -0.1, 0.05), (0.1, 0.2, 0.1), 0.4)):
        back, note = marker_to_obstacle(obstacle_to_marker(shape, "base_link", "x", 1))
        assert note == ""
        assert type(back) is type(shape)
        assert np.allclose(back.center, shape.center)
        for fld in ("radius", "height", "size", "yaw"):
            if hasattr(shape, fld):
                assert np.allclose(getattr(back, fld), getattr(shape, fld)), fld


def test_marker_conversions_are_conservative() -> None:
    """Tilted shapes become their bounding sphere (never dropped); non-shapes are refused."""
    m = _marker(Marker.CYLINDER, (0.3, 0.0, 0.2), (0.1, 0.1, 0.4))
    m.pose.orientation.x, m.pose.orientation.w = math.sin(0.5), math.cos(0.5)  # tilted by 1 rad
    shape, note = marker_to_obstacle(m)
    assert isinstance(shape, Sphere) and note
    assert shape.radius == pytest.approx(0.5 * math.sqrt(0.1**2 + 0.1**2 + 0.4**2))
    m = _marker(Marker.CUBE, (0.0, 0.0, 0.0), (0.2, 0.1, 0.1))
    m.pose.orientation.y, m.pose.orientation.w = math.sin(math.pi / 8), math.cos(math.pi / 8)  # 45 deg
    shape, note = marker_to_obstacle(m)
    assert isinstance(shape, Sphere) and shape.radius >= 0.1 and note
    m = _marker(Marker.SPHERE, (0.0, 0.0, 0.0), (0.1, 0.2, 0.1))
    shape, _ = marker_to_obstacle(m)
    assert shape.radius == pytest.approx(0.1)  # an ellipsoid is bounded by its largest axis
    shape, note = marker_to_obstacle(_marker(Marker.ARROW, (0, 0, 0), (1, 1, 1)))
    assert shape is None and "not an obstacle" in note
    # a size that is not one is refused, not guessed (|-0.1| would be a smaller ball than meant)
    for bad in ((-0.1, -0.1, -0.1), (math.nan, 0.1, 0.1), (0.1, math.inf, 0.1), (0.0, 0.1, 0.1)):
        with pytest.raises(InvalidInputError, match="scale"):
            marker_to_obstacle(_marker(Marker.SPHERE, (0.5, 0.0, 0.3), bad))
    tilted = _marker(Marker.CYLINDER, (0.3, 0.0, 0.2), (0.1, 0.1, math.inf))
    tilted.pose.orientation.x, tilted.pose.orientation.w = math.sin(0.5), math.cos(0.5)
    with pytest.raises(InvalidInputError, match="scale"):
        marker_to_obstacle(tilted)


def test_second_controller_of_the_same_name_refuses_to_start(h: Harness, ctx: Any) -> None:
    """The harness runs /controller; another one in the same domain must refuse (graph check)."""
    twin = ControllerNode(context=ctx, parameter_overrides=[Parameter("duplicate_check_s", value=1.0)])
    # The constructor does not wait for discovery: the check runs as a timer, in the executor.
    assert not twin.name_check.done and twin.name_check.refused is None
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(twin)
    try:
        with pytest.raises(DuplicateNodeError, match="already running"):
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline:
                ex.spin_once(timeout_sec=0.05)
        assert not twin.name_check.done and "already running" in (twin.name_check.refused or "")
    finally:
        ex.remove_node(twin)
        ex.shutdown()
        twin.destroy_node()
    # A remapped name is fine: its check passes the window without a twin.
    other = ControllerNode(context=ctx, node_name="controller_2",
                           parameter_overrides=[Parameter("duplicate_check_s", value=0.3)])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(other)
    try:
        deadline = time.monotonic() + 15.0
        while not other.name_check.done and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        assert other.name_check.done and other.name_check.refused is None
    finally:
        ex.remove_node(other)
        ex.shutdown()
        other.destroy_node()


def test_a_twin_found_after_its_start_up_check_stops_itself(h: Harness, ctx: Any) -> None:
    """A second /controller whose start-up window passed before discovery showed the first (slow
    discovery under load) stops itself as soon as it hears the first one's announcement: it is the
    younger. Its graph check is taken out here, so only the announcement can stop it."""
    twin = ControllerNode(context=ctx, parameter_overrides=[Parameter("duplicate_check_s", value=1.0)])
    twin.name_check._cancel()  # noqa: SLF001  (as if the window had passed without a twin)
    twin.name_check.done = True
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(twin)
    try:
        with pytest.raises(DuplicateNodeError, match="started before this one"):
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline:
                ex.spin_once(timeout_sec=0.05)
                h.ex.spin_once(timeout_sec=0.0)  # the first one runs on (and repeats its announcement)
    finally:
        ex.remove_node(twin)
        ex.shutdown()
        twin.destroy_node()
    # the first one keeps working
    h.send_goal(goal_from(Q0, (0.0, 0.1, 0.0)))
    assert h.wait_phase(ControllerState.REACHED, 30.0), h.states[-1]


def test_singular_start_is_reported_and_left(ctx: Any) -> None:
    """From the homed, stretched pose (all zeros) the elbow circle degenerates: the controller says so
    on ~/state (phase replanning, the reason in the message), moves in joint space and reaches the
    goal."""
    h = Harness(ctx, q0=np.zeros(7))
    try:
        h.wait_connected()
        h.send_goal(goal_from(Q0, (0.0, 0.0, 0.0)))
        assert h.wait_phase(ControllerState.REACHED, 30.0), h.states[-1]
        assert any(s.phase == ControllerState.REPLANNING and "stretched" in s.message for s in h.states)
    finally:
        h.close()


def test_goal_stream_on_the_topic_is_tracked(h: Harness) -> None:
    """Goals stamped and published at 50 Hz along a line (0.08 m/s): the controller reports a goal
    stream (phase tracking, goal_kind stream, its rate and velocity), follows it within its limits and
    settles on the last goal."""
    T0 = ARM.fk(Q0)
    h.send_goal(T0)
    assert h.wait_reached(30.0)
    n = len(h.states)
    t0 = h.ros_now()
    sent = 0
    # 1.5 s; each goal stamped with its sample time. A sender that woke late sends every sample due at
    # once, as a real one does: sending one per turn, a starved loop fell ever further behind until its
    # stamps lay a second in the past, which the controller rightly took for another clock.
    while sent <= 75:
        while sent <= 75 and h.ros_now() - t0 >= sent * 0.02:
            T = T0.copy()
            T[1, 3] += 0.08 * sent * 0.02
            h.send_goal(T, stamp=t0 + sent * 0.02)
            sent += 1
        h.pump()
    tracking = [s for s in h.states[n:] if s.phase == ControllerState.TRACKING]
    assert tracking, [s.phase for s in h.states[n:]]
    mid = tracking[len(tracking) // 2]
    assert mid.goal_kind == "stream"
    # Rate and velocity as most tracking states give them: on a starved executor goals can arrive so late
    # (seen: 2.4 s) that their stamps count as another clock and the stream starts anew, its first
    # estimates from a few samples.
    assert float(np.median([s.stream_rate for s in tracking])) == pytest.approx(50.0, rel=0.3)
    assert float(np.median([s.goal_velocity.linear.y for s in tracking])) == pytest.approx(0.08, rel=0.3)
    assert h.wait_reached(30.0, after=len(h.states))
    assert ARM.pose_error(h.arm.q, T)[0] < 1e-3
    assert_within_joint_speeds(h.arm)


def test_target_twist_moves_the_hand(h: Harness) -> None:
    """A twist of 0.05 m/s along +y in the base frame for 0.6 s of the controller's motion: phase tracking
    (goal_kind twist); the hand moves about 3 cm along y; when the twist stops the arm comes to rest
    (phase idle). The 0.6 s are the controller's own (its steps' durations, which a loaded machine
    shortens against the wall clock: a late step is clamped to two periods)."""
    p0 = ARM.fk(h.arm.q)[:3, 3]
    t0 = time.monotonic()
    moved0 = h.arm.commanded_s
    k = 0
    while h.arm.commanded_s - moved0 < 0.6:
        assert time.monotonic() - t0 < 60.0, "the controller does not follow the twist"
        if time.monotonic() - t0 >= k * 0.02:
            msg = TwistStamped()
            msg.header.frame_id = "base_link"
            msg.header.stamp = h.probe.get_clock().now().to_msg()
            msg.twist.linear.y = 0.05
            h.twist_pub.publish(msg)
            k += 1
        h.pump()
    assert any(s.phase == ControllerState.TRACKING and s.goal_kind == "twist" for s in h.states)
    assert h.wait_phase(ControllerState.IDLE, 30.0, after=len(h.states))
    h.spin_ticks(30)
    p1 = ARM.fk(h.arm.q)[:3, 3]
    assert 0.015 < p1[1] - p0[1] < 0.045 and abs(p1[0] - p0[0]) < 0.003 and abs(p1[2] - p0[2]) < 0.003
    assert_within_joint_speeds(h.arm)


def test_a_controller_with_nothing_to_move_rests_and_wakes_on_an_input(h: Harness) -> None:
    """No goal, or a goal reached and held: the loop stops stepping and commanding (the driver holds the
    arm), ~/state comes once a second and /diagnostics says it is idle; a goal or a move of the measured
    arm wakes it at once."""
    # Windows and deadlines in ticks of the ideal arm's 100 Hz timer, not wall seconds: a loaded
    # machine slows the executor and the controller's timers together.
    diags: list[str] = []
    h.probe.create_subscription(DiagnosticArray, "/diagnostics", lambda arr: diags.extend(
        st.message for st in arr.status if st.name == "controller: loop"), 10)
    assert h.spin_until(lambda: h.ctl.idle, 30.0)
    h.spin_ticks(20)  # what was published before it rested arrives
    steps, n_cmd, n_state, n_markers = h.ctl.steps, len(h.arm.commands), len(h.states), len(h.markers)
    n_diag = len(diags)
    h.spin_ticks(150)  # at least 1.5 s
    assert h.ctl.steps == steps and len(h.arm.commands) == n_cmd
    assert len(h.markers) - n_markers <= 1  # drawn once at rest, not at markers_rate_hz
    # the heartbeat, sent with each diagnostics message (1 Hz), not 100 Hz
    assert 1 <= len(h.states) - n_state <= len(diags) - n_diag + 1
    assert any(m.startswith("idle") for m in diags)
    n = len(h.states)
    h.send_goal(goal_from(Q0, (0.0, 0.1, 0.0)))
    assert h.spin_ticks(100, lambda: not h.ctl.idle and h.ctl.steps > steps)
    assert h.wait_reached(30.0, after=n)
    assert h.spin_until(lambda: h.ctl.idle, 30.0)  # reached, the elbow settled and held: resting again
    h.spin_ticks(20)  # the last commands sent arrive
    q_held, n_cmd = h.arm.q.copy(), len(h.arm.commands)
    h.spin_ticks(50)
    assert np.array_equal(h.arm.q, q_held) and len(h.arm.commands) == n_cmd and h.ctl.idle
    steps = h.ctl.steps
    h.arm.q = h.arm.q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01])  # another client moved the arm
    assert h.spin_ticks(100, lambda: not h.ctl.idle and h.ctl.steps > steps)


def test_joint_states_in_any_order_with_missing_repeated_or_bad_joints(ctx: Any) -> None:
    """joint_states by name: any order, extra joints, a repeated name (its last value), positions fewer
    than names (those names count as missing); a message without every arm joint or with NaN is ignored
    with a warning; a new layout is looked up again, also back to an earlier one."""
    node = ControllerNode(context=ctx, parameter_overrides=[Parameter("duplicate_check_s", value=0.0)])
    try:
        names = list(node.arm.joint_names)
        q = np.linspace(-0.5, 0.7, len(names))
        warned: list[str] = []
        node._warn_throttled = lambda key, text, period_s=2.0: warned.append(key)  # type: ignore[method-assign]

        def js(nm: list[str], pos: list[float]) -> JointState:
            m = JointState()
            m.name, m.position = nm, pos
            return m

        def got() -> list[float]:
            assert node._q_meas is not None
            return node._q_meas.tolist()

        node._on_joint_states(js(names, q.tolist()))
        assert got() == q.tolist()
        order = [6, 0, 5, 1, 4, 2, 3]
        node._on_joint_states(js(["gripper", *[names[i] for i in order]], [9.0, *(q[order] + 1.0).tolist()]))
        assert got() == (q + 1.0).tolist()
        node._on_joint_states(js([*names, names[2]], [*q.tolist(), 5.0]))  # a repeated name: its last value
        assert got()[2] == 5.0 and got()[:2] == q[:2].tolist()
        before = got()
        node._on_joint_states(js(names[:-1], q[:-1].tolist()))  # a joint missing
        node._on_joint_states(js(names, q[:-1].tolist()))  # fewer positions than names
        assert got() == before and warned == ["js-names", "js-names"]
        node._on_joint_states(js(names, [*q[:-1].tolist(), math.nan]))
        assert got() == before and warned[-1] == "js-nan"
        node._on_joint_states(js(names, (q + 2.0).tolist()))  # back to the first layout
        assert got() == (q + 2.0).tolist()
    finally:
        node.destroy_node()
