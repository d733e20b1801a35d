"""Controller node: Cartesian goals on a topic -> joint motion by attractor dynamics.

Wiring only: the dynamics (heading, hand orientation, swivel with obstacle and joint-limit force-lets)
and the closed-form IK step live in :class:`redarm_ros.control.reach_controller.ReachController`.
This node feeds it the measured joint state, goals and obstacles, steps it at ``rate_hz`` and
publishes what it returns.

Topics (relative names, so a namespace or remapping applies):

* in  ``goal_pose`` (geometry_msgs/PoseStamped): a new goal, also mid-motion (retargets smoothly), or
  one more sample of a goal stream (tracked like a servo, with the stream's velocity estimated from
  the header stamps and fed forward); the core tells the two apart (docs/control.md);
* in  ``~/target_twist`` (geometry_msgs/TwistStamped): a velocity command for the hand (joystick, space
  mouse), in ``base_frame`` or ``tool_frame``; held for ``twist_timeout_s``;
* in  ``obstacles`` (visualization_msgs/MarkerArray): SPHERE, CYLINDER (vertical) and CUBE markers,
  ADD/MODIFY/DELETE/DELETEALL by (ns, id); replaces the obstacles of the ``scene`` parameter, whose
  table stays;
* in  ``joint_states`` (sensor_msgs/JointState): the measured arm (from ``can_driver``);
* out ``joint_command`` (trajectory_msgs/JointTrajectory): one segment per control step, from the
  previous command to the new one, stamped to end ``command_delay_s`` after the step
  (:mod:`redarm_ros.nodes.command_timing`);
* out ``~/state`` (redarm_interfaces/ControllerState): phase, swivel, clearance, distance to goal...
  every step;
* out ``~/markers`` (visualization_msgs/MarkerArray): elbow circle, arm, heading, goal, obstacles;
* action ``~/reach`` (redarm_interfaces/action/Reach): a goal with feedback, result, cancel and
  pre-emption (:mod:`redarm_ros.nodes.reach_action`).

A goal out of reach, without an in-limit solution, or inside an obstacle is rejected with a log
line and phase ``rejected`` on ``~/state``; the arm stops smoothly and holds. Parameters and
examples: docs/nodes.md. Units: m, rad, s; message quaternions are (x, y, z, w).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, TwistStamped
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from redarm_interfaces.msg import ControllerState
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import Marker, MarkerArray

from redarm_ros.can.realtime import scheduling_now
from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import ControllerParams, GoalStatus, Phase
from redarm_ros.control.types import GoalKind
from redarm_ros.errors import InvalidInputError, RedarmError
from redarm_ros.geometry.obstacles import (
    MARKER_CUBE,
    MARKER_CYLINDER,
    MARKER_SPHERE,
    Box,
    Cylinder,
    Scene,
    Sphere,
    load_scene,
    obstacle_from_marker,
)
from redarm_ros.kinematics import load_arm_or_urdf
from redarm_ros.kinematics.quaternion import matrix_to_quat, quat_to_matrix
from redarm_ros.nodes._common import (
    NICE_PARAM,
    PROCESS_RT_PARAM,
    ParamNode,
    ParamSpec,
    UniqueNameCheck,
    in_range,
    non_empty_string,
    non_negative,
    pose_msg_to_matrix,
    positive,
    run_node,
    urdf_arm_params,
    watch_duplicates,
)
from redarm_ros.nodes.command_timing import CommandClock
from redarm_ros.nodes.loop_stats import LoopStats
from redarm_ros.nodes.reach_action import ReachActionServer
from redarm_ros.param_table import table

NODE_NAME = "controller"
STILL_WINDOW_S = 0.25  # s of joint_states looked at to decide that the arm stands still
STILL_TOLERANCE = 1e-3  # rad: largest joint motion within that window of an arm standing still
OBSTACLE_MARKERS_S = 2.0  # s between re-sends of unchanged obstacle markers
DIAGNOSTICS_PERIOD_S = 1.0  # s between /diagnostics messages
IDLE_PERIODS = 10  # periods without a step after which /diagnostics says the loop is not stepping
# Idle: once nothing moves (no goal, or a goal reached and held) the loop stops stepping until an input
# arrives; a step would only repeat the last command. "Nothing moves": every commanded joint slower
# than IDLE_RATE_RAD_S (the last of an elbow's self-motion towards its preferred swivel is left undone:
# it stops within about a second's worth of that rate) for the parameter idle_after_s. The measured
# joints moving by more than IDLE_WAKE_RAD from where they stood (a halt, another client's
# /joint_command) wake it too.
IDLE_RATE_RAD_S = 1e-4
IDLE_WAKE_RAD = 1e-4
IDLE_PHASES = (Phase.IDLE, Phase.REACHED, Phase.REJECTED)


#: Node parameters that set one controller parameter each: ROS name -> (section of the parameter table
#: redarm_ros/parameters.yaml, name there; "controller" is the top level). Their type, default, bound and
#: description are the table's (:func:`table_params`); only the ROS name is the node's.
NODE_TO_TABLE: dict[str, tuple[str, str]] = {
    "preferred_swivel": ("controller", "preferred_swivel"),
    "swivel_reference": ("controller", "swivel_reference"),
    "swivel_mode": ("controller", "swivel_mode"),
    "max_speed": ("speed", "v_max"),
    "pos_tolerance": ("controller", "pos_tolerance"),
    "ori_tolerance": ("controller", "ori_tolerance"),
    "stream_gap_s": ("stream", "gap"),
    "stream_jump": ("stream", "jump"),
    "twist_timeout_s": ("servo", "twist_timeout"),
    "replan": ("replan", "enabled"),
    "corridor": ("replan", "corridor"),
}
#: Of those, the ones that may change at run time (the rest are set at start-up).
SETTABLE = ("preferred_swivel",)


def table_params(names: dict[str, tuple[str, str]]) -> list[ParamSpec]:
    """The node parameters of ``names`` (ROS name -> table section, name), built from the table rows."""
    specs = []
    for ros_name, (section, name) in names.items():
        row = table()[section].param(name)
        bound = row.bound

        def check(value: Any, bound: Any = bound) -> str | None:
            return None if bound.check(value)[0] else f"must be {bound.phrase}"

        unit = f" [{row.unit}]" if row.unit else ""
        doc = " ".join(row.doc.split())
        specs.append(ParamSpec(ros_name, row.default, f"{doc[:1].upper()}{doc[1:]}{unit}.", check,
                               read_only=ros_name not in SETTABLE,
                               range=bound.arg if bound.word == "range" else None))
    return specs


PARAMS = [
    ParamSpec("arm", "pa10", "Arm model (config/arms/<name>.yaml or a path); a 7-DOF swivel arm or "
              "powercube6.", read_only=True),
    *urdf_arm_params("Run"),
    PROCESS_RT_PARAM,
    NICE_PARAM,
    ParamSpec("rate_hz", 100.0, "Control rate (Hz): one step and one /joint_command point per period.",
              in_range(1.0, 1000.0), read_only=True),
    ParamSpec("scene", "", "Initial scene: name in config/scenes or a YAML path ('' = none). Its table "
              "stays when obstacles arrive on the obstacles topic.", read_only=True),
    ParamSpec("base_frame", "base_link", "Frame of goals and obstacles ('' frame_id means this one) and of "
              "the published markers.", non_empty_string),
    ParamSpec("markers_rate_hz", 10.0, "RViz marker rate (Hz, 0 = none, at most 100); may be changed at "
              "run time.", in_range(0.0, 100.0)),
    ParamSpec("resync_threshold", 0.2, "If the arm stands still while its measured joints differ from the "
              "last command by more than this (rad, any joint), the controller restarts from the measured "
              "state (after a halt, homing, a collision).", positive),
    ParamSpec("joint_states_timeout_s", 0.5, "No joint_states for this long (s): stop commanding and warn.",
              positive),
    ParamSpec("duplicate_check_s", 1.0, "At start-up, watch the graph this long (s) for another node of "
              "the same name and refuse to start if there is one (0 = no check).", non_negative,
              read_only=True),
    ParamSpec("command_delay_s", 0.05, "Each /joint_command segment is stamped to end this long (s) after "
              "its control step, so the driver plays it at a fixed delay whatever the message latency (0 = "
              "unstamped segments, started on receipt). Stamps only while the joint_states stamps show that "
              "the driver's clock is this node's.", in_range(0.0, 0.5), read_only=True),
    ParamSpec("stream_lead_s", 0.01, "The arm's own lag (s) behind the driver's command (driver cycle, "
              "module set-point generator): a goal stream is tracked command_delay_s + this far ahead of "
              "now.", in_range(0.0, 0.5), read_only=True),
    ParamSpec("tool_frame", "tool", "Frame name of twists given in the tool frame (others: base_frame).",
              None, read_only=True),
    ParamSpec("idle_after_s", 0.5, "Once nothing has moved for this long (s; no goal, or the goal reached "
              "and held) the loop rests: no steps, no commands (the driver holds the arm), ~/state once a "
              "second, until a goal, twist, obstacle, parameter or a move of the arm wakes it (0 = never "
              "rest).", non_negative, read_only=True),
    *table_params(NODE_TO_TABLE),
]

# ControllerState.phase strings (lower case) from the core's Phase (upper case names).
_PHASE_MSG = {ph: getattr(ControllerState, ph.name) for ph in Phase}
_COLOR = {
    "arm": (0.8, 0.1, 0.1, 1.0),
    "circle": (0.2, 0.6, 1.0, 0.8),
    "heading": (1.0, 0.8, 0.0, 1.0),
    "obstacle": (0.5, 0.5, 0.5, 0.7),
    "goal_ok": (0.1, 0.9, 0.1, 0.9),
    "goal_bad": (1.0, 0.1, 0.1, 0.9),
    "table": (0.6, 0.45, 0.3, 0.5),
}


# ----------------------------------------------------------------------------------------------
# Message <-> core conversions (plain functions, no state)
# ----------------------------------------------------------------------------------------------
def _quat_xyzw_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def marker_to_obstacle(m: Marker) -> tuple[Sphere | Cylinder | Box | None, str]:
    """One RViz marker as an obstacle shape (base frame, m) and a note ('' or why it was changed).

    The conversion is the core's :func:`~redarm_ros.geometry.obstacles.obstacle_from_marker` (SPHERE,
    upright CYLINDER, CUBE with a yaw). A tilted cylinder or cube, which the core refuses, is kept as
    its bounding sphere rather than dropped: an obstacle the controller ignores could be hit. Other
    marker types give (None, reason).
    """
    p = (m.pose.position.x, m.pose.position.y, m.pose.position.z)
    o = m.pose.orientation
    scale = (m.scale.x, m.scale.y, m.scale.z)
    name = f"{m.ns}/{m.id}"
    if m.type not in (MARKER_CUBE, MARKER_SPHERE, MARKER_CYLINDER):
        return None, f"marker type {m.type} is not an obstacle shape (SPHERE, CYLINDER, CUBE)"
    if not all(math.isfinite(v) and v > 0.0 for v in scale):  # (a guessed size could be too small)
        raise InvalidInputError(f"scale {scale} must be finite and > 0 on every axis", field="scale",
                                value=scale)
    try:
        return obstacle_from_marker(m.type, p, (o.x, o.y, o.z, o.w), scale, name), ""
    except InvalidInputError as exc:
        if "tilted" not in str(exc):
            raise
    radius = 0.5 * math.sqrt(sum(v * v for v in scale))
    return Sphere(p, radius, name), "tilted shape kept as its bounding sphere"


def obstacle_to_marker(o: Sphere | Cylinder | Box, frame: str, ns: str, mid: int) -> Marker:
    """RViz marker drawing an obstacle shape."""
    m = Marker()
    m.header.frame_id = frame
    m.ns, m.id, m.action = ns, mid, Marker.ADD
    m.pose.position = Point(x=o.center[0], y=o.center[1], z=o.center[2])
    m.pose.orientation.w = 1.0
    if isinstance(o, Sphere):
        m.type = Marker.SPHERE
        m.scale.x = m.scale.y = m.scale.z = 2.0 * o.radius
    elif isinstance(o, Cylinder):
        m.type = Marker.CYLINDER
        m.scale.x = m.scale.y = 2.0 * o.radius
        m.scale.z = o.height
    else:
        m.type = Marker.CUBE
        m.scale.x, m.scale.y, m.scale.z = o.size
        x, y, z, w = _quat_xyzw_from_yaw(o.yaw)
        m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = x, y, z, w
    m.color = ColorRGBA(r=_COLOR["obstacle"][0], g=_COLOR["obstacle"][1], b=_COLOR["obstacle"][2],
                        a=_COLOR["obstacle"][3])
    return m


def _color(key: str) -> ColorRGBA:
    r, g, b, a = _COLOR[key]
    return ColorRGBA(r=r, g=g, b=b, a=a)


def _pt(v: Sequence[float]) -> Point:
    return Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def controller_params(p: dict[str, Any]) -> ControllerParams:
    """The controller's parameters from the node's: those of :data:`NODE_TO_TABLE`, the step from
    ``rate_hz`` and the stream's lead from ``command_delay_s + stream_lead_s``; the rest at their defaults."""
    d: dict[str, Any] = {"dt": 1.0 / p["rate_hz"],
                         "stream": {"lead": float(p["command_delay_s"]) + float(p["stream_lead_s"])}}
    for node_name, (section, name) in NODE_TO_TABLE.items():
        (d if section == "controller" else d.setdefault(section, {}))[name] = p[node_name]
    return ControllerParams.from_dict(d)


# ----------------------------------------------------------------------------------------------
# The node
# ----------------------------------------------------------------------------------------------
class ControllerNode(ParamNode, node_name=NODE_NAME, params=PARAMS):
    """``controller``: attractor-dynamics reaching (see the module docstring for topics)."""

    #: :func:`run_node` puts the whole process at ``realtime_priority`` (the control path).
    PROCESS_REALTIME = True

    def _setup(self, p: dict[str, Any]) -> None:
        try:
            self.arm = load_arm_or_urdf(p["arm"], p["urdf"], p["base_link"], p["tip_link"])
            self.base_scene = load_scene(p["scene"]) if p["scene"] else Scene()
            self.ctl = make_controller(self.arm, self.base_scene, controller_params(p))
        except (RedarmError, OSError) as exc:
            raise ValueError(f"controller configuration: {exc}") from exc
        self.name_check = UniqueNameCheck(self, p["duplicate_check_s"])  # a timer: no blocking here
        watch_duplicates(self, yield_to_elder=p["duplicate_check_s"] > 0)
        self.period = 1.0 / p["rate_hz"]
        self._names = list(self.arm.joint_names)
        self._q_meas: np.ndarray | None = None
        self._t_meas = -math.inf
        self._started = False
        self._pending_goal: np.ndarray | None = None
        self._goal_T: np.ndarray | None = None
        self._last_step = time.monotonic()
        self._last_dt = 1.0 / p["rate_hz"]
        self._meas_hist: list[tuple[float, np.ndarray]] = []
        # joint_states layout: ((names, count of positions), index of each arm joint or None, missing names)
        self._js_layout: tuple[Any, list[int] | None, list[str]] = (None, None, [])
        self._last_cmd: np.ndarray | None = None
        self._cmd_clock = CommandClock(float(p["command_delay_s"]))
        self._markers: dict[tuple[str, int], Any] = {}
        self._last_marker_ids: set[tuple[str, int]] = set()
        self._warned: dict[str, float] = {}
        self._last_phase: Phase | None = None
        self._last_message = ""
        self._obstacles_published = -math.inf
        self._scene_changed = True
        self._marker_listeners = 0
        self._obstacle_markers: list[Marker] = []
        self._last_result: Any = None
        self._state_out = ControllerState()  # ~/state, refilled per message (_state_msg)
        self._cmd_msg = (JointTrajectory(joint_names=self._names), JointTrajectoryPoint(),
                         JointTrajectoryPoint())  # /joint_command and its two points (_publish_command)
        self.steps = 0
        self.loop_stats = LoopStats(self.period)
        # Wiring.
        self.cmd_pub = self.create_publisher(JointTrajectory, "joint_command", QoSProfile(depth=10))
        self.state_pub = self.create_publisher(ControllerState, "~/state", QoSProfile(depth=10))
        self.marker_pub = self.create_publisher(MarkerArray, "~/markers", QoSProfile(depth=2))
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self.create_subscription(PoseStamped, "goal_pose", self._on_goal, 10)
        self.create_subscription(TwistStamped, "~/target_twist", self._on_twist, 10)
        self.create_subscription(MarkerArray, "obstacles", self._on_obstacles, 10)
        self.create_subscription(JointState, "joint_states", self._on_joint_states, 10)
        self._step_timer = self.create_timer(self.period, self._on_timer)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        self.idle = False  # the loop rests (see idle_after_s); any input wakes it
        self._idle_after_s = float(p["idle_after_s"])
        self._idle_markers_sent = False  # the markers went out since the loop rested
        self._quiet_since: float | None = None
        self._idle_q_meas: np.ndarray | None = None
        self._markers_timer = None
        self._set_markers_rate(p["markers_rate_hz"])
        self.add_post_set_parameters_callback(self._on_params_set)
        self.reach = ReachActionServer(self)  # ~/reach (redarm_interfaces/action/Reach)
        self.get_logger().info(
            f"controller ready: arm {self.arm.name}, {p['rate_hz']:g} Hz, scene "
            f"{self.base_scene.name or '(none)'} with {len(self.base_scene)} obstacles, preferred swivel "
            f"{p['preferred_swivel']:g} rad ({p['swivel_reference']}); waiting for joint_states"
        )

    def destroy_node(self) -> None:
        self.reach.destroy()  # action servers are not destroyed with the node
        super().destroy_node()

    # -- helpers ----------------------------------------------------------------------------------
    def _warn_throttled(self, key: str, text: str, period_s: float = 2.0) -> None:
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) >= period_s:
            self._warned[key] = now
            self.get_logger().warning(text)

    def _frame_ok(self, frame: str) -> bool:
        return not frame or frame.lstrip("/") == self.get_parameter("base_frame").value

    def _set_markers_rate(self, hz: float) -> None:
        """(Re)start the marker timer at ``hz`` (0: no markers)."""
        if self._markers_timer is not None:
            self.destroy_timer(self._markers_timer)
            self._markers_timer = None
        if hz > 0:
            self._markers_timer = self.create_timer(1.0 / hz, self._publish_markers)

    def _on_params_set(self, params: list[Parameter]) -> None:
        for prm in params:
            if prm.name == "preferred_swivel":
                self.ctl.set_preferred_swivel(float(prm.value))
                self.get_logger().info(f"preferred swivel now {float(prm.value):g} rad")
            elif prm.name == "markers_rate_hz":
                self._set_markers_rate(float(prm.value))
                self.get_logger().info(f"markers now at {float(prm.value):g} Hz")
        self.wake()

    # -- idle -------------------------------------------------------------------------------------
    def wake(self) -> None:
        """Resume stepping (an input arrived: a goal, a twist, obstacles, a parameter, the arm moved)."""
        self._quiet_since = None
        self._idle_markers_sent = False
        if self.idle:
            self.idle = False
            self.loop_stats.pause()  # the rest is no missed tick
            # The core's clock stood still with the loop: bring it to now without moving (dt 0), so
            # what comes next (a goal's timing, its progress watch) does not count the rest.
            self.ctl.step(0.0, self._now())
            self._step_timer.reset()

    def _rest_if_quiet(self, res: Any, q_before: np.ndarray | None, now: float) -> None:
        """After a step: stop the loop once nothing has moved for idle_after_s."""
        still = (q_before is not None and res.phase in IDLE_PHASES
                 and self.ctl.goal_kind is not GoalKind.TWIST
                 and float(np.max(np.abs(res.q - q_before))) < IDLE_RATE_RAD_S * self._last_dt)
        if not still:
            self._quiet_since = None
            return
        if self._quiet_since is None:
            self._quiet_since = now
        elif 0.0 < self._idle_after_s <= now - self._quiet_since and self._q_meas is not None:
            self.idle = True
            self._idle_q_meas = self._q_meas.copy()
            self._step_timer.cancel()

    # -- inputs -----------------------------------------------------------------------------------
    def _on_joint_states(self, msg: JointState) -> None:
        pos = msg.position
        key = (tuple(msg.name), len(pos))
        if key != self._js_layout[0]:  # (a driver sends the same names every time: looked up once)
            at = {n: i for i, n in enumerate(msg.name[:len(pos)])}  # (a repeated name: its last value)
            missing = [n for n in self._names if n not in at]
            self._js_layout = (key, None if missing else [at[n] for n in self._names], missing)
        index, missing = self._js_layout[1], self._js_layout[2]
        if index is None:
            self._warn_throttled("js-names", f"joint_states lacks joints {missing}; ignored")
            return
        q = np.array([pos[i] for i in index], dtype=float)
        if not np.isfinite(q).all():
            self._warn_throttled("js-nan", "joint_states with NaN/inf ignored")
            return
        self._q_meas = q
        self._t_meas = time.monotonic()
        self._cmd_clock.joint_state(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, self._now())
        # A short history tells a halted arm (not moving) from one that merely lags the command.
        # The one sample at or before the window's start stays: at a still arm's low rate of joint_states
        # (or the driver's polls) the history still spans the whole window.
        hist = self._meas_hist
        hist.append((self._t_meas, q))
        while len(hist) > 1 and self._t_meas - hist[1][0] >= STILL_WINDOW_S:
            hist.pop(0)
        if self.idle and self._idle_q_meas is not None and \
                float(np.max(np.abs(q - self._idle_q_meas))) > IDLE_WAKE_RAD:
            self.wake()

    def _now(self) -> float:
        """ROS time (s): the clock of header stamps, given to the core with every goal and step."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_goal(self, msg: PoseStamped) -> None:
        self.wake()
        if not self._frame_ok(msg.header.frame_id):
            self._reject_message(f"goal in frame {msg.header.frame_id!r} refused: give goals in "
                                 f"{self.get_parameter('base_frame').value!r} (this node has no tf)")
            return
        try:
            T = pose_msg_to_matrix(msg.pose, 1e-3)
        except InvalidInputError as exc:
            self._reject_message(f"goal refused: {exc}")
            return
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if self.reach.running:
            # a goal the core would reject (out of reach, in an obstacle) pre-empts nothing: the
            # running Reach goal goes on (the same check, without changing state)
            check = self.ctl.check_goal(T)
            if not check.accepted:
                self._reject_message(f"goal on goal_pose rejected [{check.status.name}]: {check.message}; "
                                     "the running Reach goal goes on")
                return
        self.reach.preempt("a goal on goal_pose")
        if not self._started:
            self._pending_goal = T
            self.get_logger().info("goal received before the first joint_states; it starts when the arm "
                                   "state is known")
            return
        self._apply_goal(T, stamp)

    def _apply_goal(self, T: np.ndarray, stamp: float = 0.0) -> None:
        """A goal message: the core decides whether it continues the goal stream or is a new goal."""
        retarget = self.ctl.phase in (Phase.REACHING, Phase.HOLDING, Phase.TRACKING, Phase.REPLANNING)
        was = self.ctl.goal_kind
        check = self.ctl.goal_message(T, stamp, self._now())
        p = T[:3, 3]
        if check.accepted:
            self._goal_T = T
            if check.kind is GoalKind.STREAM:
                if was is not GoalKind.STREAM:
                    self.get_logger().info("goal stream: tracking it")
            elif not check.repeat:
                what = "retarget to" if retarget else "new goal"
                self.get_logger().info(f"{what} ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m")
        else:
            self._goal_T = None
            self.get_logger().warning(f"goal ({p[0]:.4g}, {p[1]:.4g}, {p[2]:.4g}) m rejected "
                                      f"[{check.status.name}]: {check.message}; holding")

    def _on_twist(self, msg: TwistStamped) -> None:
        self.wake()
        frame = msg.header.frame_id.lstrip("/")
        lin = np.array([msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z], float)
        ang = np.array([msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z], float)
        if not (np.all(np.isfinite(lin)) and np.all(np.isfinite(ang))):
            self._warn_throttled("twist-nan", "target_twist with NaN/inf ignored")
            return
        if not self._started:
            self._warn_throttled("twist-early", "target_twist before the first joint_states ignored")
            return
        if frame and frame == self.get_parameter("tool_frame").value:
            q = self.ctl.q
            assert q is not None
            R = np.asarray(self.arm.fk(q), float)[:3, :3]  # tool -> base
            lin, ang = R @ lin, R @ ang
        elif not self._frame_ok(frame):
            self._warn_throttled("twist-frame", f"target_twist in frame {frame!r} ignored: give it in "
                                 f"{self.get_parameter('base_frame').value!r} or "
                                 f"{self.get_parameter('tool_frame').value!r} (no tf here)")
            return
        self.reach.preempt("a twist on target_twist")
        if self.ctl.goal_kind is not GoalKind.TWIST:
            self.get_logger().info("target_twist: following it")
        self.ctl.set_twist(lin, ang, self._now())
        self._goal_T = None

    def _reject_message(self, text: str) -> None:
        """A goal message that never reached the core (bad frame, NaN): log it and report it on ~/state."""
        self.get_logger().warning(text)
        st = self._state_msg(self._last_result)
        st.phase = ControllerState.REJECTED
        st.message = text
        self.state_pub.publish(st)

    def _on_obstacles(self, msg: MarkerArray) -> None:
        changed = False
        for m in msg.markers:
            key = (m.ns, m.id)
            if m.action == Marker.DELETEALL:
                changed |= bool(self._markers)
                self._markers.clear()
            elif m.action == Marker.DELETE:
                changed |= self._markers.pop(key, None) is not None
            elif m.action == Marker.ADD:  # ADD and MODIFY share the value 0
                # (warnings throttled per marker: one bad marker must not hide another's warning)
                if not self._frame_ok(m.header.frame_id):
                    self._warn_throttled(f"obs-frame {key}", f"obstacle {m.ns}/{m.id} in frame "
                                         f"{m.header.frame_id!r} ignored (no tf here)")
                    continue
                try:
                    shape, note = marker_to_obstacle(m)
                except (InvalidInputError, ValueError) as exc:
                    self._warn_throttled(f"obs-bad {key}", f"obstacle {m.ns}/{m.id} ignored: {exc}")
                    continue
                if shape is None:
                    self._warn_throttled(f"obs-type {key}", f"obstacle {m.ns}/{m.id} ignored: {note}")
                    continue
                if note:
                    self._warn_throttled(f"obs-note {key}", f"obstacle {m.ns}/{m.id}: {note}")
                self._markers[key] = shape
                changed = True
            else:
                self._warn_throttled(f"obs-action {key}", f"obstacle {m.ns}/{m.id} ignored: action "
                                     f"{m.action} is none of ADD/MODIFY (0), DELETE (2), DELETEALL (3)")
        if not changed:
            return
        self.wake()
        scene = self.base_scene.with_obstacles(self._markers.values())
        check = self.ctl.set_scene(scene)
        self._scene_changed = True
        self.get_logger().info(f"obstacles updated: {len(scene)} from the obstacles topic")
        if check is not None:
            self._goal_T = None
            self.get_logger().warning(f"active goal dropped [{check.status.name}]: {check.message}; holding")

    # -- the control step -------------------------------------------------------------------------
    def _on_timer(self) -> None:
        if not self.name_check.done:  # no commands while a twin of this name may still show up
            return
        now = time.monotonic()
        if self._q_meas is None:
            self._warn_throttled("no-js", "no joint_states yet; not commanding", 5.0)
            return
        stale = now - self._t_meas > self.get_parameter("joint_states_timeout_s").value
        if not self._started:
            self.ctl.reset(self._q_meas, self._now())
            self._started = True
            self._last_step = now
            self.get_logger().info("arm state known; controller running")
            if self._pending_goal is not None:
                self._apply_goal(self._pending_goal)
                self._pending_goal = None
        if stale:
            self._warn_throttled("stale-js", "joint_states stopped; holding (not commanding)")
            self._last_step = now
            return
        self._resync_if_needed()
        q_before = None if self._last_result is None else self._last_result.q
        dt = min(max(now - self._last_step, 0.0), 2.0 * self.period)
        self._last_step = now
        t_step = self._now()
        res = self.ctl.step(dt, t_step)
        self._last_dt = dt
        self.steps += 1
        self._last_result = res
        if res.phase is not self._last_phase:
            if res.phase is Phase.REACHED:
                self.get_logger().info(f"goal reached (distance {res.distance_to_goal:.2e} m, orientation "
                                       f"error {res.orientation_error:.2e} rad)")
            elif res.phase is Phase.HOLDING:
                self.get_logger().warning(f"holding: {res.message}")
            elif res.phase is Phase.REPLANNING:
                self.get_logger().warning(res.message)
            elif res.phase is Phase.BLOCKED:
                self.get_logger().error(f"goal blocked: {res.message}")
            self._last_phase = res.phase
        elif res.message and res.message != self._last_message and \
                res.phase in (Phase.REACHING, Phase.TRACKING, Phase.REPLANNING):
            # The core says why it cannot follow exactly (a stream too fast, out of reach; a re-plan).
            self._warn_throttled(f"msg-{res.phase}", f"{res.phase.value.lower()}: {res.message}", 1.0)
        self._last_message = res.message
        # Before the first goal nothing is commanded (the driver holds); afterwards every step is, and
        # after the goal is dropped until the arm has stopped.
        moving = self._last_cmd is not None and float(np.max(np.abs(res.q - self._last_cmd))) > 1e-12
        if moving or res.phase not in (Phase.IDLE, Phase.REJECTED):
            self._publish_command(res.q, t_step)
        self.state_pub.publish(self._state_msg(res))
        self.loop_stats.step(now, time.monotonic() - now)
        self._rest_if_quiet(res, q_before, now)

    def _publish_diagnostics(self) -> None:
        """``controller: loop`` on ``/diagnostics``: the steps the loop took (counted here, exact even
        when a listener is too busy to receive every ``~/state``), missed ticks, the step's duration,
        the obstacles (all, and those the broad phase keeps) and the process's scheduling."""
        s = self.loop_stats.summary(time.monotonic())
        nominal = 1.0 / self.period
        st = DiagnosticStatus(name=f"{NODE_NAME}: loop", hardware_id=self.arm.name)
        stale = time.monotonic() - self._t_meas > self.get_parameter("joint_states_timeout_s").value
        if s.steps < 2:
            st.level, st.message = DiagnosticStatus.OK, "not stepping yet (waiting for joint_states)"
        elif self.idle and not stale:
            # At rest the loop does not step (nothing would move); ~/state repeats at this timer's rate.
            st.level, st.message = DiagnosticStatus.OK, "idle: nothing to move (stepping resumes on an input)"
        elif s.idle_s > IDLE_PERIODS * self.period:
            # The loop holds without stepping while joint_states are stale: not a rate problem.
            st.level = DiagnosticStatus.WARN
            st.message = f"no step for {s.idle_s:.1f} s (joint_states stale?)"
        elif s.rate_hz >= 0.9 * nominal:
            st.level, st.message = DiagnosticStatus.OK, f"{s.rate_hz:.1f} Hz"
        else:
            st.level = DiagnosticStatus.WARN
            st.message = f"{s.rate_hz:.1f} Hz of {nominal:g}: the loop misses ticks (a busy machine?)"
        scene = self.ctl.scene
        values = {
            "rate_hz_target": f"{nominal:g}",
            "rate_hz_achieved": f"{s.rate_hz:.1f}",
            "steps": str(s.steps),
            "loop_clock_s": f"{s.clock:.6f}",
            "missed_ticks": str(s.missed),
            "last_step_age_s": f"{s.idle_s:.3f}",
            "step_busy_median_ms": f"{s.busy_median * 1e3:.3f}",
            "step_busy_max_ms": f"{s.busy_max * 1e3:.3f}",
            "obstacles": str(len(scene.obstacles)),
            "obstacles_within_reach": str(len(scene.obstacles) - self.ctl.culled_obstacles),
            "scheduling": scheduling_now(),
            "idle": str(self.idle).lower(),
        }
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.diag_pub.publish(arr)
        if self.idle:
            self.state_pub.publish(self._state_msg(self._last_result))

    def _resync_if_needed(self) -> None:
        """Restart from the measured joints when the arm is not where we commanded it (halt, homing)."""
        q_cmd = self.ctl.q
        if q_cmd is None or self._q_meas is None:
            return
        dev = float(np.max(np.abs(self._q_meas - q_cmd)))
        if dev <= self.get_parameter("resync_threshold").value:
            return
        # A moving arm lagging behind (acceleration limits, homing) is left alone; only a still one
        # (halted, blocked) far from the command means the plan and the arm have parted.
        hist = self._meas_hist
        if not hist or hist[-1][0] - hist[0][0] < 0.8 * STILL_WINDOW_S:
            return
        if float(np.max(np.ptp(np.array([h[1] for h in hist]), axis=0))) > STILL_TOLERANCE:
            return
        goal = self._goal_T if self.ctl.goal_kind is GoalKind.POINT else None
        self.ctl.reset(self._q_meas, self._now())
        self._last_cmd = None
        if goal is not None:
            self._warn_throttled("resync", f"arm is {dev:.3f} rad away from the command; re-planning from "
                                 "the measured joints", 1.0)
            check = self.ctl.set_goal(goal)
            if not check.accepted:
                self._goal_T = None
        else:
            self.get_logger().info(f"measured joints moved by {dev:.3f} rad; restarting from them")

    def _publish_command(self, q: np.ndarray, t_step: float) -> None:
        """One control step as a self-contained segment: the previous command at t = 0, the new one at
        t = the step's duration (a late timer tick covers more motion, so the driver sees the speed the
        controller planned). The driver interpolates between the two commands, whatever its own
        (shaped, possibly lagging) reference is; the first command after a (re)start is one point.
        Stamped (``command_delay_s``), the segment ends that long after the step ``t_step`` (ROS time);
        the driver follows the previous one until it starts."""
        seg = self._cmd_clock.segment(t_step, self._last_dt)
        # One message and its two points, refilled every step (publish() copies them out at once): a
        # new message is some 10 us of constructors a step.
        msg, start, end = self._cmd_msg
        dt = seg.duration
        sec = int(dt)
        end.positions = q.tolist()
        end.time_from_start.sec, end.time_from_start.nanosec = sec, int((dt - sec) * 1e9)
        stamp = msg.header.stamp
        if seg.stamp is not None:
            sec = int(seg.stamp)
            stamp.sec, stamp.nanosec = sec, int((seg.stamp - sec) * 1e9)
        else:
            stamp.sec, stamp.nanosec = 0, 0
            if self._cmd_clock.delay > 0.0:
                off = self._cmd_clock.offset()
                why = "unstamped" if math.isinf(off) else f"{off:+.3f} s off this node's clock"
                self._warn_throttled("cmd-clock", f"joint_states stamps are {why}: /joint_command "
                                     "segments go out unstamped (started on receipt; command_delay_s not "
                                     "applied)", 10.0)
        if self._last_cmd is None:
            msg.points = [end]
        else:
            start.positions = self._last_cmd.tolist()
            msg.points = [start, end]
        self.cmd_pub.publish(msg)
        self._last_cmd = q.copy()

    def _state_msg(self, res: Any) -> ControllerState:
        """``~/state`` of step result ``res`` (None: no step yet). One message, every field refilled on each
        call (publish() copies it out at once; a new one costs some 10 us of constructors a step)."""
        st = self._state_out
        st.header.stamp = self.get_clock().now().to_msg()
        st.header.frame_id = self.get_parameter("base_frame").value
        v = w = (0.0, 0.0, 0.0)
        goal = None
        if res is None:
            st.phase = ControllerState.IDLE
            st.swivel = st.swivel_desired = math.nan
            st.clearance = st.distance_to_goal = st.orientation_error = math.inf
            st.message = "waiting for joint_states"
            st.goal_kind = ""
            st.stream_rate = 0.0
        else:
            st.phase = _PHASE_MSG[res.phase]
            st.swivel = float(res.swivel)
            st.swivel_desired = float(res.swivel_desired)
            st.clearance = float(res.clearance)
            st.distance_to_goal = float(res.distance_to_goal)
            st.orientation_error = float(res.orientation_error)
            st.message = res.message
            kind = self.ctl.goal_kind
            st.goal_kind = "" if kind is None else kind.value
            v, w = res.goal_velocity, res.goal_rate
            st.stream_rate = float(res.stream_rate)
            goal = self.ctl.goal
        lin, ang = st.goal_velocity.linear, st.goal_velocity.angular
        lin.x, lin.y, lin.z = v
        ang.x, ang.y, ang.z = w
        p, o = st.goal.position, st.goal.orientation
        if goal is not None:
            (p.x, p.y, p.z), (qw, qx, qy, qz) = goal
            o.x, o.y, o.z, o.w = float(qx), float(qy), float(qz), float(qw)
        else:  # (a message's defaults)
            p.x = p.y = p.z = 0.0
            o.x, o.y, o.z, o.w = 0.0, 0.0, 0.0, 1.0
        return st

    # -- RViz -------------------------------------------------------------------------------------
    def _publish_markers(self) -> None:
        q = self.ctl.q
        if q is None:
            return
        # Nobody listening: build nothing. Turning a thousand obstacles into messages took a
        # 100 Hz controller down to about 50 Hz on two cores; a new listener gets them all at once.
        listeners = self.marker_pub.get_subscription_count()
        joined = listeners > self._marker_listeners
        if listeners == 0 or joined:
            self._obstacles_published = -math.inf
            self._last_marker_ids = set()
        self._marker_listeners = listeners
        if listeners == 0:
            return
        # At rest nothing drawn changes: the markers (kept by RViz) go out once, then again only for a
        # new listener or a new scene.
        if self.idle and self._idle_markers_sent and not joined and not self._scene_changed:
            return
        self._idle_markers_sent = self.idle
        frame = self.get_parameter("base_frame").value
        stamp = self.get_clock().now().to_msg()
        out: list[Marker] = []

        def marker(ns: str, mid: int, mtype: int, color: str) -> Marker:
            m = Marker()
            m.header.frame_id, m.header.stamp = frame, stamp
            m.ns, m.id, m.type, m.action = ns, mid, mtype, Marker.ADD
            m.pose.orientation.w = 1.0
            m.color = _color(color)
            out.append(m)
            return m

        kp = self.arm.key_points(q)  # base, shoulder, elbow, wrist, tool
        m = marker("arm", 0, Marker.LINE_STRIP, "arm")
        m.scale.x = 0.03
        m.points = [_pt(v) for v in kp]
        m = marker("arm", 1, Marker.SPHERE, "arm")
        m.pose.position = _pt(kp[2])
        m.scale.x = m.scale.y = m.scale.z = 0.06
        circle = self.ctl.elbow_circle  # None at a singular pose: nothing to draw
        if circle is not None:
            m = marker("elbow_circle", 0, Marker.LINE_STRIP, "circle")
            m.scale.x = 0.008
            m.points = [_pt(circle.elbow(t)) for t in np.linspace(0.0, 2.0 * math.pi, 49)]
        res = self._last_result
        if res is not None and res.speed > 1e-4:
            e = self.ctl.heading_direction
            m = marker("heading", 0, Marker.ARROW, "heading")
            m.scale.x, m.scale.y, m.scale.z = 0.01, 0.02, 0.03
            m.points = [_pt(kp[4]), _pt(kp[4] + 0.15 * np.asarray(e))]
        goal = self.ctl.goal
        if goal is not None:
            m = marker("goal", 0, Marker.ARROW, "goal_ok")
            (gx, gy, gz), qg = goal
            R = quat_to_matrix(qg)
            m.scale.x, m.scale.y, m.scale.z = 0.01, 0.02, 0.03
            m.points = [_pt((gx, gy, gz)), _pt(np.array([gx, gy, gz]) + 0.1 * R[:, 2])]
        scene = self.ctl.scene
        now = time.monotonic()
        keep: set[tuple[str, int]] = set()
        if now - self._obstacles_published >= OBSTACLE_MARKERS_S or self._scene_changed:
            # RViz keeps markers: the (possibly many) obstacles are re-sent only when they change and
            # every OBSTACLE_MARKERS_S, not at the marker rate; built once per scene (stamp 0: latest).
            if self._scene_changed or len(self._obstacle_markers) != len(scene.obstacles):
                self._obstacle_markers = [obstacle_to_marker(o, frame, "obstacles", i)
                                          for i, o in enumerate(scene.obstacles)]
            out.extend(self._obstacle_markers)
            self._obstacles_published = now
            self._scene_changed = False
        else:
            keep = {k for k in self._last_marker_ids if k[0] == "obstacles"}
        if scene.table_height is not None:
            m = marker("table", 0, Marker.CUBE, "table")
            m.pose.position = _pt((0.5, 0.0, scene.table_height - 0.01))
            m.scale.x, m.scale.y, m.scale.z = 1.6, 1.6, 0.02
        ids = {(mk.ns, mk.id) for mk in out} | keep
        for ns, mid in self._last_marker_ids - ids:  # e.g. an obstacle deleted, the goal gone
            d = Marker()
            d.header.frame_id, d.header.stamp = frame, stamp
            d.ns, d.id, d.action = ns, mid, Marker.DELETE
            out.append(d)
        self._last_marker_ids = ids
        self.marker_pub.publish(MarkerArray(markers=out))


def pose_to_msg(T: np.ndarray) -> PoseStamped:
    """PoseStamped (frame left empty) of a 4x4 pose; quaternion in message order x, y, z, w."""
    msg = PoseStamped()
    msg.pose.position = _pt(T[:3, 3])
    w, x, y, z = matrix_to_quat(T[:3, :3])
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = float(x), float(y), float(z), float(w)
    return msg


__all__ = ["ControllerNode", "GoalStatus", "main", "marker_to_obstacle", "obstacle_to_marker", "pose_to_msg"]


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``ros2 run redarm_ros controller``)."""
    return run_node(ControllerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
