"""Reaching controller: attractor dynamics for point goals, a servo for goal streams and twists,
a joint-space re-planner for dead ends; closed-form IK at the elbow swivel; a collision guard.

The goal decides the law that moves the *reference* (a tool pose, a swivel and their IK):

* a **point goal** (:meth:`ReachController.set_goal`, or a goal message that is not part of a
  stream) is reached by the attractor dynamics (heading direction with obstacle repellers, a speed
  profile that stops at the goal, orientation and swivel attractors). If its straight route is a
  dead end, or the arm stops making progress, the joint-space re-planner
  (:mod:`~redarm_ros.control.replan`) moves the arm to a goal configuration instead;
* a **goal stream** (:meth:`ReachController.goal_message` telling samples from new goals,
  :mod:`~redarm_ros.control.stream`) or a **twist** (:meth:`ReachController.set_twist`) is tracked by
  the servo law (:mod:`~redarm_ros.control.servo`) with the goal's estimated velocity fed forward;

while the swivel dynamics (eq. 31 of the swivel paper) keeps the elbow away from obstacles, joint
limits and singularities in every mode. Each step the reference goes through the IK step and its
fallback cascade (:mod:`~redarm_ros.control.ik_step`); the *command* follows the reference within
the joint velocity, acceleration and position limits (:mod:`~redarm_ros.control.joint_limits`) and
passes the collision guard (:mod:`~redarm_ros.control.guard`). Distances use only the obstacles the
broad phase keeps (:mod:`~redarm_ros.control.broadphase`).

Units: m, rad, s. Quaternions are (w, x, y, z). The core is pure Python/numpy (no ROS); the
controller node converts messages to these calls.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from redarm_ros.control.attractor import HeadingDynamics, SpeedProfile, direction, heading_angles
from redarm_ros.control.broadphase import LEFT_OUT, LocalScene, SceneIndex
from redarm_ros.control.elbow import ArmGeometry, ElbowCircle, elbow_circle
from redarm_ros.control.goal_check import check_goal, stream_feasibility
from redarm_ros.control.guard import CollisionGuard, describe
from redarm_ros.control.ik_step import DeadEnd, IKStep, IKStepper, blend, pose_matrix
from redarm_ros.control.joint_limits import braking_speed, velocity_bounds
from redarm_ros.control.obstacles import Clearance, Scene
from redarm_ros.control.params import ControllerParams, ReplanParams, ServoParams, StreamParams
from redarm_ros.control.replan import JointPath, JointPlanner, check_route, move_time
from redarm_ros.control.rotations import (
    quat_angle,
    quat_between_vectors,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    rotvec_between,
    slerp_vectors,
)
from redarm_ros.control.servo import ServoTarget, servo_step
from redarm_ros.control.slide import obstacle_slide, workspace_slide, wrist_shell
from redarm_ros.control.state import (
    ZERO3,
    Command,
    CoreState,
    Goal,
    Mode,
    Progress,
    Reference,
    Twist,
)
from redarm_ros.control.stream import StreamEstimator
from redarm_ros.control.swivel_dynamics import SwivelDynamics, SwivelForces, wrap_angle
from redarm_ros.control.types import GoalCheck, GoalKind, GoalStatus, Phase, Quat, StepResult, Vec3
from redarm_ros.errors import ConfigError, InvalidInputError, UnreachableError

LOG = logging.getLogger(__name__)
SMALL_SCENE = 4  # obstacles within reach up to which every step uses them all (no per-step culling)

__all__ = [
    "ControllerParams",
    "GoalCheck",
    "GoalKind",
    "GoalStatus",
    "Phase",
    "ReachController",
    "ReplanParams",
    "ServoParams",
    "StepResult",
    "StreamParams",
    "has_swivel",
]


def has_swivel(arm: Any) -> bool:
    """Does ``arm`` have an elbow circle, i.e. closed-form IK at a swivel angle? Asked by capability
    (a 7-joint arm whose ``ik(T, swivel)`` answers), not by attribute names."""
    if getattr(arm, "n", None) != 7:
        return False
    try:
        q = np.clip(np.full(7, 0.3), np.asarray(arm.lower, float), np.asarray(arm.upper, float))
        arm.ik(np.asarray(arm.fk(q), float), 0.0)
        arm.swivel(q)
    except (NotImplementedError, AttributeError, TypeError):
        return False
    return True


def _swivel_low(circle: ElbowCircle) -> float | None:
    """Swivel (rad) of the lowest elbow position on the circle; None if the circle is horizontal."""
    az, bz = circle.a[2], circle.b[2]
    if math.hypot(az, bz) < 0.05:
        return None
    return math.atan2(-bz, -az)


def _pose_of(T: np.ndarray) -> tuple[Vec3, Quat]:
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), quat_from_matrix(T[:3, :3])


class ReachController:
    """Reach Cartesian goals, follow goal streams and twists with a 7-DOF swivel arm (see the module
    docstring).

    Typical use::

        ctl = ReachController(load_arm("pa10"), load_scene("table_cylinder"))
        ctl.reset(q_measured)
        check = ctl.set_goal(T_goal)          # GoalCheck; rejected goals leave the arm holding
        while True:
            r = ctl.step(0.01)                # StepResult; command r.q
            if r.phase is Phase.REACHED: ...

    Raises:
        ConfigError: the arm has no elbow circle (not a spherical-shoulder/wrist 7-DOF arm).
    """

    def __init__(self, arm: Any, scene: Scene | None = None, params: ControllerParams | None = None) -> None:
        if not has_swivel(arm):
            raise ConfigError(f"ReachController needs a 7-DOF swivel arm, got {getattr(arm, 'name', arm)!r}",
                              field="arm")
        self.arm = arm
        self.params = params or ControllerParams()
        p = self.params
        self.geom = ArmGeometry.from_arm(arm)
        self.swivel_dyn = SwivelDynamics(p.swivel)
        self.heading_dyn = HeadingDynamics(p.heading)
        self.speed_profile = SpeedProfile(p.speed)
        self.stepper = IKStepper(arm, self.geom, p.flip_ratio, p.swivel_search_step, p.swivel_search_count)
        self.guard = CollisionGuard(arm, p.capsules, p.collision_margin, p.guard_step)
        self._lower = np.asarray(arm.lower, float)
        self._upper = np.asarray(arm.upper, float)
        self._max_vel = np.asarray(arm.max_vel, float)
        self._inv_vel = 1.0 / self._max_vel
        self._max_acc = np.asarray(arm.max_acc, float)
        self._d_inner, self._d_outer = wrist_shell(float(self._lower[3]), float(self._upper[3]),
                                                   self.geom.upper, self.geom.fore)
        self._st: CoreState | None = None
        self.scene = Scene()
        self._index = SceneIndex(self.scene, self.geom.shoulder, 1.0, 0.0)
        self._local = self._index.reach_scene
        self._install_scene(scene if scene is not None else Scene())

    # ------------------------------------------------------------------ properties
    @property
    def phase(self) -> Phase:
        """Current :class:`Phase`."""
        return Phase.IDLE if self._st is None else self._st.phase

    @property
    def q(self) -> np.ndarray | None:
        """Last commanded joint positions (rad), None before :meth:`reset`."""
        return None if self._st is None else self._st.cmd.q.copy()

    @property
    def swivel(self) -> float:
        """Current swivel angle of the reference (rad)."""
        return 0.0 if self._st is None else self._st.ref.s

    @property
    def elbow_circle(self) -> ElbowCircle | None:
        """Elbow circle of the current reference pose (centre, normal, radius, basis), for display."""
        return None if self._st is None else self._st.ref.circle

    @property
    def heading_direction(self) -> Vec3:
        """Unit vector (base frame) of the current end-effector heading (or motion direction)."""
        st = self._st
        if st is None:
            return (1.0, 0.0, 0.0)
        v = st.ref.vel
        n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if st.mode is Mode.SERVO and n > 1e-6:
            return (v[0] / n, v[1] / n, v[2] / n)
        return direction(st.att.phi, st.att.theta)

    @property
    def goal(self) -> tuple[Vec3, Quat] | None:
        """Active goal as (position m, quaternion w,x,y,z) or None (for a stream: its newest sample)."""
        if self._st is None or self._st.goal is None:
            return None
        return self._st.goal.pos, self._st.goal.rot

    @property
    def goal_kind(self) -> GoalKind | None:
        """How the active goal came (point goal, stream, twist), None without one."""
        return None if self._st is None or self._st.goal is None else self._st.goal.kind

    @property
    def stream(self) -> StreamEstimator:
        """The goal stream's estimator (a fresh one after every :meth:`reset` and new point goal).

        Raises:
            InvalidInputError: before :meth:`reset`.
        """
        return self._state().stream

    @property
    def time(self) -> float:
        """The controller clock (s): the sum of the step durations, or the caller's ``now``."""
        return 0.0 if self._st is None else self._st.time

    @property
    def culled_obstacles(self) -> int:
        """Obstacles of the scene the broad phase leaves out for good (beyond the arm's reach)."""
        return self._index.culled

    def _state(self) -> CoreState:
        if self._st is None:
            raise InvalidInputError("reset(q) must be called first", field="q")
        return self._st

    # ------------------------------------------------------------------ set-up
    def reset(self, q: Any, now: float | None = None) -> None:
        """Start from measured joint positions ``q`` (rad); clears the goal (phase IDLE). ``now``
        (s) sets the controller clock (e.g. the node's ROS time), else it keeps running.

        Raises:
            InvalidInputError: wrong length or NaN. Positions slightly outside the limits are
                clamped into them.
        """
        qa = np.clip(self.arm.check_q(q), self._lower, self._upper)
        T = np.asarray(self.arm.fk(qa), float)
        pos, rot = _pose_of(T)
        s = float(self.arm.swivel(qa))
        try:
            circle: ElbowCircle | None = elbow_circle(self.geom, T)
        except UnreachableError:  # singular reset pose (arm stretched): no circle; the planner moves first
            circle = None
        t = now if now is not None else (0.0 if self._st is None else self._st.time)
        local = self._index.reach_scene
        kp = self.guard.key_points(qa)
        clear = self.guard.clearance(qa, local.scene, kp)
        cmd = Command(qa.copy(), self._globalise(clear, local), pos, rot, kp)
        cmd.obs_clear = self._obstacle_clearance(qa, local, kp)
        ref = Reference(qa.copy(), pos, rot, s, circle, s_des=s, s_fixed=s)
        self._st = CoreState(ref, cmd, stream=StreamEstimator(self.params.stream), time=float(t))

    def _install_scene(self, scene: Scene) -> None:
        self.scene = scene
        reach = self.geom.upper + self.geom.fore + float(np.linalg.norm(self.geom.wrist_in_tool))
        self._index = SceneIndex(scene, self.geom.shoulder, reach + max(self.params.capsules.radii),
                                 self.params.broad_phase_margin)
        self._local = self._index.reach_scene

    def set_scene(self, scene: Scene) -> GoalCheck | None:
        """Replace the obstacles (e.g. from the node's MarkerArray). Re-checks the active point goal;
        if it is now inside an obstacle it is dropped (phase REJECTED, the arm stops) and the failing
        :class:`GoalCheck` is returned; otherwise returns None. A BLOCKED goal is planned again."""
        if not isinstance(scene, Scene):
            raise InvalidInputError("scene must be a Scene", field="scene", value=scene)
        self._install_scene(scene)
        st = self._st
        if st is None:
            return None
        local = self._index.reach_scene
        st.cmd.clear = self._globalise(self.guard.clearance(st.cmd.q, local.scene, st.cmd.kp), local)
        st.cmd.obs_clear = self._obstacle_clearance(st.cmd.q, local, st.cmd.kp)
        st.cmd.obs_rate = 0.0
        if st.goal is None:
            return None
        T = pose_matrix(st.goal.pos, st.goal.rot)
        if st.goal.kind is GoalKind.POINT:
            check = self.check_goal(T)
            if not check.accepted:
                self._reject(check)
                return check
            if st.phase is Phase.BLOCKED or st.mode in (Mode.PLAN, Mode.JOINT):
                st.progress = Progress(t_best=st.time)
                self._start_plan("the scene changed")
        elif st.goal.kind is GoalKind.STREAM:
            st.stream_note = stream_feasibility(self.geom, T, local.scene, self.params.capsules)
        return None

    def set_preferred_swivel(self, value: float) -> None:
        """Change the preferred swivel (rad, same reference as ``params.swivel_reference``)."""
        v = float(value)
        if not math.isfinite(v):
            raise InvalidInputError("preferred swivel must be finite", field="preferred_swivel", value=value)
        self.params = self.params.with_(preferred_swivel=v)

    # ------------------------------------------------------------------ goals
    def check_goal(self, T: Any) -> GoalCheck:
        """Check a goal pose (4x4, base frame) without changing state; see :class:`GoalStatus`."""
        local = self._index.reach_scene
        check = check_goal(self.arm, self.geom, T, local.scene, self.params.capsules, self.params.goal_scan)
        return check

    def set_goal(self, T: Any) -> GoalCheck:
        """Set a new point goal (4x4 homogeneous, base frame, m). A goal mid-motion retargets smoothly
        (heading and speed are continuous). A rejected goal stops the arm smoothly (phase REJECTED).
        If the straight route to it is a dead end, the arm moves in joint space (phase REPLANNING)."""
        if self._st is None:
            return GoalCheck(GoalStatus.NOT_READY, "reset(q) must be called before set_goal()")
        check = self.check_goal(T)
        if not check.accepted:
            self._reject(check)
            return check
        self.stream.reset()
        self._accept_point_goal(np.asarray(T, float))
        return check

    def goal_message(self, T: Any, stamp: float | None = None, now: float | None = None) -> GoalCheck:
        """A goal from a topic: one more sample of the current goal stream, or a new goal.

        ``stamp``: the message's header stamp (s; 0/None = now); ``now``: the receive time on the
        controller's clock (s; default: the controller clock). See :mod:`~redarm_ros.control.stream`
        for how a stream is told apart from a new goal. A stream sample is never rejected: if it cannot
        be followed exactly the servo follows as closely as the limits allow and the step's message
        says why. Returns the :class:`GoalCheck` (``kind`` says how the message was taken).
        """
        st = self._st
        if st is None:
            return GoalCheck(GoalStatus.NOT_READY, "reset(q) must be called before goal_message()")
        try:
            Tn = np.asarray(self.arm.check_pose(T), float)
        except InvalidInputError as exc:
            check = GoalCheck(GoalStatus.INVALID_INPUT, str(exc))
            self._reject(check)
            return check
        now = st.time if now is None else float(now)
        pos, rot = _pose_of(Tn)
        t = self.stream.stamp_time(stamp, now)
        goal = st.goal
        p = self.params
        if goal is not None and goal.kind is GoalKind.POINT and math.dist(goal.pos, pos) <= p.pos_tolerance \
                and quat_angle(goal.rot, rot) <= p.ori_tolerance:
            self.stream.add(pos, rot, t, now)  # the same goal again: nothing changes
            return GoalCheck(GoalStatus.ACCEPTED, "same goal", kind=GoalKind.POINT)
        if goal is not None and goal.kind in (GoalKind.POINT, GoalKind.STREAM) \
                and self.stream.continues(pos, rot, t, now):
            self.stream.add(pos, rot, t, now)
            if goal.kind is not GoalKind.STREAM:
                self._enter_servo()
                st.goal = Goal(pos, rot, GoalKind.STREAM, st.time)
                st.progress = Progress(t_best=st.time)
            newest = self.stream.newest
            assert newest is not None
            st.goal.pos, st.goal.rot = newest.pos, newest.rot
            st.stream_note = stream_feasibility(self.geom, Tn, self._index.reach_scene.scene, p.capsules)
            return GoalCheck(GoalStatus.ACCEPTED, st.stream_note, kind=GoalKind.STREAM)
        check = self.set_goal(Tn)
        if check.accepted:
            self.stream.add(pos, rot, t, now)
        return check

    def set_twist(self, linear: Any, angular: Any, now: float | None = None) -> None:
        """A velocity command for the hand: ``linear`` (m/s) and ``angular`` (rad/s) 3-vectors in the
        base frame, held for ``servo.twist_timeout`` s (send it at a rate). The servo follows it within
        the same limits and guard as a stream (phase TRACKING); when it stops the hand decelerates to
        rest and the controller becomes IDLE.

        Raises:
            InvalidInputError: not 3 finite numbers each, or called before :meth:`reset`.
        """
        st = self._state()
        try:
            lin = np.asarray(linear, float).reshape(3)
            ang = np.asarray(angular, float).reshape(3)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError("twist needs 3 linear and 3 angular numbers", field="twist") from exc
        if not (np.all(np.isfinite(lin)) and np.all(np.isfinite(ang))):
            raise InvalidInputError("twist must be finite", field="twist", value=(linear, angular))
        now = st.time if now is None else float(now)
        st.twist = Twist((float(lin[0]), float(lin[1]), float(lin[2])),
                         (float(ang[0]), float(ang[1]), float(ang[2])), now)
        if st.goal is None or st.goal.kind is not GoalKind.TWIST:
            self.stream.reset()
            self._enter_servo()
            st.goal = Goal(st.ref.pos, st.ref.rot, GoalKind.TWIST, st.time)
            st.progress = Progress(t_best=st.time)
            st.phase = Phase.TRACKING
            st.message = ""

    def stop(self) -> None:
        """Drop the goal; the arm decelerates smoothly and holds (phase IDLE)."""
        st = self._state()
        st.goal = None
        st.twist = None
        st.phase = Phase.IDLE
        st.message = "stopped"
        self._leave_plan()

    def _reject(self, check: GoalCheck) -> None:
        LOG.info("goal rejected: %s", check.message)
        st = self._st
        if st is None:
            return
        st.goal = None
        st.twist = None
        st.phase = Phase.REJECTED
        st.message = check.message
        self._leave_plan()

    def _leave_plan(self) -> None:
        """Out of PLAN/JOINT (a stop or rejection): the reference becomes Cartesian again."""
        st = self._state()
        if st.mode in (Mode.PLAN, Mode.JOINT):
            st.planner = None
            st.path = None
            self._resync_reference(keep_velocity=True)
            st.mode = Mode.ATTRACTOR
            self._enter_attractor()

    def _accept_point_goal(self, T: np.ndarray) -> None:
        st = self._state()
        pos, rot = _pose_of(T)
        was_moving = st.mode in (Mode.JOINT, Mode.PLAN)
        st.goal = Goal(pos, rot, GoalKind.POINT, st.time)
        st.twist = None
        st.progress = Progress(t_best=st.time)
        st.message = ""
        st.phase = Phase.REACHING
        st.planner = None
        st.path = None
        if was_moving:
            self._resync_reference(keep_velocity=True)
        if st.ref.circle is None:
            self._start_plan("the arm is stretched (no elbow circle)")
            return
        reason = self._route_dead_end(T) if self.params.replan.enabled else ""
        if reason:
            self._start_plan(reason)
            return
        if st.mode is not Mode.ATTRACTOR:
            st.mode = Mode.ATTRACTOR
            self._enter_attractor()
        elif st.att.v < 1e-6:  # starting from rest: head straight at the goal
            st.att.phi, st.att.theta = self._heading_to_goal()
            st.att.turn = (0.0, 0.0)

    def _route_dead_end(self, T: np.ndarray) -> str:
        """Why the attractor should not take the straight route to ``T`` ('' if it should): a dead end
        on it, or joint motion along it much slower than a joint-space move to the nearest goal
        configuration (e.g. through the shoulder singularity, or the long way round a wide joint)."""
        st = self._state()
        p = self.params
        T0 = pose_matrix(st.ref.pos, st.ref.rot)
        if p.swivel_mode == "fixed":
            def s_des(_c: ElbowCircle) -> float:
                return st.ref.s_fixed
        else:
            def s_des(c: ElbowCircle) -> float:
                return self._desired_swivel(c)
        route = check_route(self.stepper, T0, st.ref.s, st.ref.q, T, s_des, p.replan.route_steps,
                            p.speed.v_max, p.max_ori_rate, p.swivel.max_rate)
        # The attractor is given a generous multiple of the route's least time before it counts as
        # overdue (it accelerates gently, slows near obstacles and at the goal).
        st.progress.due = st.time + p.replan.overdue_factor * route.time + p.replan.overdue_slack
        if route.dead_end:
            return route.dead_end
        if route.singular:
            return route.singular
        q_near, info = self.arm.ik_nearest(T, st.ref.q)
        if q_near is None:
            return ""
        t_joint = move_time(np.asarray(q_near, float) - st.ref.q, self._max_vel, self._max_acc)
        if route.time > max(p.replan.slow_route * t_joint, t_joint + 2.0):
            return (f"the straight route needs {route.time:.1f} s of joint motion, a joint-space move "
                    f"{t_joint:.1f} s")
        return ""

    # ------------------------------------------------------------------ mode changes
    def _enter_attractor(self) -> None:
        """Attractor state continuous with the reference's motion (heading = motion direction)."""
        st = self._state()
        v = st.ref.vel
        n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if n > 1e-4:
            st.att.phi, st.att.theta = heading_angles(v, st.att.phi)
        else:
            st.att.phi, st.att.theta = self._heading_to_goal()
        st.att.v, st.att.a, st.att.turn, st.att.v_cap = n, 0.0, (0.0, 0.0), None

    def _enter_servo(self) -> None:
        """Servo state continuous with the reference's motion."""
        st = self._state()
        if st.mode in (Mode.PLAN, Mode.JOINT):
            st.planner = None
            st.path = None
            self._resync_reference(keep_velocity=True)
        if st.mode is Mode.ATTRACTOR:
            e = direction(st.att.phi, st.att.theta)
            st.ref.vel = (st.att.v * e[0], st.att.v * e[1], st.att.v * e[2])
        st.mode = Mode.SERVO
        st.ref.sdot_dyn = st.ref.sdot
        st.message = ""
        st.stream_note = ""

    def _start_plan(self, reason: str) -> None:
        st = self._state()
        if not self.params.replan.enabled:
            self._hold(reason)
            return
        st.progress.replans += 1
        if st.progress.replans > self.params.replan.max_replans:
            self._block(f"gave up after {self.params.replan.max_replans} re-plans; last: {reason}")
            return
        LOG.info("re-planning in joint space: %s", reason)
        st.mode = Mode.PLAN
        st.planner = None
        st.path = None
        st.plan_reason = reason
        st.phase = Phase.REPLANNING
        st.message = f"re-planning in joint space: {reason}"

    def _block(self, why: str) -> None:
        st = self._state()
        LOG.warning("goal blocked: %s", why)
        st.mode = Mode.HOLD
        st.planner = None
        st.path = None
        st.phase = Phase.BLOCKED
        st.message = why
        st.ref.q = st.cmd.q.copy()
        st.ref.qd = np.zeros(7)

    # ------------------------------------------------------------------ the step
    def step(self, dt: float | None = None, now: float | None = None) -> StepResult:
        """Advance by ``dt`` seconds (default ``params.dt``) and return the command. ``now`` (s) is the
        time the command is for, on the clock of :meth:`goal_message` (default: clock + dt).

        Raises:
            InvalidInputError: called before :meth:`reset`, or a non-finite/negative dt.
        """
        st = self._st
        if st is None:
            raise InvalidInputError("reset(q) must be called before step()", field="q")
        p = self.params
        dt = p.dt if dt is None else float(dt)
        if not math.isfinite(dt) or dt < 0.0:
            raise InvalidInputError(f"dt must be finite and >= 0, got {dt!r}", field="dt", value=dt)
        dt = min(dt, p.max_dt)
        st.time = float(now) if now is not None else st.time + dt
        if dt == 0.0:
            return self._result()
        self._local = self._local_scene(dt)
        if st.mode is Mode.ATTRACTOR and st.goal is None and st.att.v <= 0.0:
            st.mode = Mode.HOLD
        if st.mode is Mode.SERVO and st.goal is None and self._at_rest_servo():
            st.mode = Mode.HOLD
        if st.mode is Mode.HOLD:
            if st.goal is not None and st.phase is not Phase.BLOCKED:
                if st.goal.kind is GoalKind.POINT:
                    st.mode = Mode.ATTRACTOR
                    self._enter_attractor()
            if st.mode is Mode.HOLD:
                if np.any(st.cmd.qd != 0.0) or not np.array_equal(st.ref.q, st.cmd.q):
                    st.ref.qd = np.zeros(7)  # the reference stands: the command brakes onto it
                    self._track(dt)
                return self._result()
        if st.mode is Mode.PLAN:
            self._plan_step(dt)
        elif st.mode is Mode.JOINT:
            self._joint_step(dt)
        elif st.mode is Mode.SERVO:
            self._servo_step(dt)
        elif st.ref.circle is None:
            if st.goal is not None:
                self._start_plan("the arm is stretched (no elbow circle)")
            else:
                st.mode = Mode.HOLD
        else:
            self._attractor_step(dt)
        self._update_phase()
        self._watch_progress()
        return self._result()

    # -- broad phase ------------------------------------------------------------------------------
    def _local_scene(self, dt: float) -> LocalScene:
        """This step's obstacles: those within reach of any distance the step may compute."""
        st = self._state()
        if len(self._index.reach_scene.index) <= SMALL_SCENE:  # culling would cost more than it saves
            return self._index.reach_scene
        kc = st.cmd.kp
        kr = np.asarray(st.ref.circle.key_points(st.ref.s), float) if st.ref.circle is not None \
            else self.guard.key_points(st.ref.q)
        lever = self.guard.levers(st.cmd.q, kc)
        qd = np.maximum(np.abs(st.cmd.qd), np.abs(st.ref.qd)) + self._max_acc * dt
        travel = float(np.dot(lever, qd * qd / (2.0 * self._max_acc) + 2.0 * self._max_vel * dt))
        radius = self.params.broad_phase_margin + travel + self.params.swivel.obs_influence
        return self._index.local((kc, kr), self.params.capsules.radii, radius)

    @staticmethod
    def _globalise(c: Clearance, local: LocalScene) -> Clearance:
        """A clearance of the local scene with the obstacle index of the full scene."""
        return Clearance(c.distance, c.link, local.global_index(c.obstacle))

    def _obstacle_clearance(self, q: np.ndarray, local: LocalScene, kp: np.ndarray) -> float:
        if not local.scene.obstacles:
            return math.inf
        return self.guard.clearance(q, Scene(local.scene.obstacles, None), kp).distance

    # -- attractor dynamics -----------------------------------------------------------------------
    def _attractor_step(self, dt: float) -> None:
        st = self._state()
        p = self.params
        ref, att = st.ref, st.att
        pos, rot = ref.pos, ref.rot
        goal_p = st.goal.pos if st.goal is not None else None
        dist = math.inf
        # 1-2. heading and speed
        if goal_p is not None:
            dist = math.dist(pos, goal_p)
            reach = self._index.reach_scene
            ahead = reach.scene.obstacles if len(reach.index) <= SMALL_SCENE else \
                self._index.ahead(pos, dist + 0.3 + p.heading.target_gate * 10.0).scene.obstacles
            att.phi, att.theta, rates = self.heading_dyn.step(att.phi, att.theta, dt, pos, goal_p, ahead,
                                                              att.turn)
            att.turn = rates.applied
            cap = att.v_cap
            if rates.speed_factor < 1.0:
                v_obs = rates.speed_factor * self.speed_profile.params.v_max
                cap = v_obs if cap is None else min(cap, v_obs)
            v_stop = self._joint_braking_speed(dist)
            if v_stop is not None:
                cap = v_stop if cap is None else min(cap, v_stop)
            cmd = st.cmd
            if cmd.obs_rate > 1e-4 and att.v > 1e-3:
                # Stopping distance: the clearance the arm would lose while its joints brake at their
                # acceleration limits (~ rate * t_stop / 2) must stay within stop_share of the
                # clearance left; the swivel meanwhile turns the elbow away.
                t_stop = float(np.max(np.abs(cmd.qd) / self._max_acc))
                loss = cmd.obs_rate * (0.5 * t_stop + dt)
                room = p.stop_share * max(cmd.obs_clear - p.collision_margin, 0.0)
                if loss > room:
                    v_stop = att.v * math.sqrt(room / loss)
                    cap = v_stop if cap is None else min(cap, v_stop)
            att.v, att.a = self.speed_profile.step(att.v, att.a, dist, dt, cap, self._hand_acc())
        else:  # no goal: decelerate along the current heading (jerk-limited, like any speed change)
            att.v, att.a = self.speed_profile.step(att.v, att.a, math.inf, dt, 0.0)
            if att.v < 1e-4:
                att.v, att.a = 0.0, 0.0
        e = direction(att.phi, att.theta)
        if goal_p is not None and dist < p.final_distance:
            # Final approach: blend towards the straight line so that a heading which ended up
            # opposite to the target (an unstable but balanced state) cannot carry the hand away.
            w = 1.0 - dist / p.final_distance
            g = ((goal_p[0] - pos[0]) / dist, (goal_p[1] - pos[1]) / dist, (goal_p[2] - pos[2]) / dist) \
                if dist > 1e-12 else e
            m = ((1.0 - w) * e[0] + w * g[0], (1.0 - w) * e[1] + w * g[1], (1.0 - w) * e[2] + w * g[2])
            mn = math.sqrt(m[0] ** 2 + m[1] ** 2 + m[2] ** 2)
            e = (m[0] / mn, m[1] / mn, m[2] / mn) if mn > 1e-9 else g
        e = workspace_slide(e, pos, rot, self.geom, self._d_inner, self._d_outer, p.workspace_margin)
        if goal_p is None or dist > p.final_distance:  # (the goal itself was checked clear)
            e = obstacle_slide(e, ref.circle, ref.s, self._local.scene, p.capsules, p.slide_band)
        step_len = att.v * dt
        if goal_p is not None:
            step_len = min(step_len, dist)
        new_pos = (pos[0] + step_len * e[0], pos[1] + step_len * e[1], pos[2] + step_len * e[2])
        # 3. orientation
        new_rot = rot
        if st.goal is not None:
            target_rot = self._orientation_target(e, dist if goal_p is not None else 0.0)
            w = rotvec_between(rot, target_rot)
            wn = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
            # Rate of the attractor, clamped, and changed by at most max_ori_acc per second (braking
            # in time): without this the rate jumps when a goal is set.
            ori_acc = self._joint_share_acc(ref.w_ori, p.max_ori_acc)
            rate = min(p.lam_ori * wn, p.max_ori_rate, float(braking_speed(wn, ori_acc, dt)))
            rate = max(0.0, min(rate, ref.w_ori + ori_acc * dt))
            gain = min(rate * dt / wn, 1.0) if wn > 1e-12 else 0.0
            new_rot = quat_normalize(quat_mul(quat_from_rotvec((gain * w[0], gain * w[1], gain * w[2])), rot))
        # 4-5. swivel and IK (with velocity scaling / swivel search / hold)
        out = self.stepper.advance(pos, rot, ref.s, ref.q, new_pos, new_rot, dt, self._swivel_fn(dt))
        if isinstance(out, DeadEnd):
            att.v *= out.speed_scale
            self._hold(out.reason)
            self._track(dt)  # the command brakes onto the (standing) reference
            return
        att.v *= out.speed_scale
        self._commit(out, dt, attractor=True)

    def _swivel_fn(self, dt: float) -> Any:
        """The swivel the dynamics asks for at a proposed pose (see :data:`ik_step.SwivelFn`)."""
        st = self._state()
        p = self.params
        # Tracking a moving goal, the preferred swivel moves with it (e.g. the highest elbow turns as the
        # wrist moves): its change is fed forward, so the elbow does not lag behind its preference
        # (a lagging elbow costs the joints much more motion than the hand needs).
        feed = st.mode is Mode.SERVO and p.swivel_mode != "fixed" and st.ref.circle is not None
        s_des_prev = self._desired_swivel(st.ref.circle) if feed and st.ref.circle is not None else 0.0
        s_acc_feed = p.max_swivel_acc
        if feed:
            # How much each joint turns per radian of swivel here: the swivel may change its rate only
            # as fast as keeps every joint within joint_brake_share of its acceleration limit (the rest
            # is the hand's, which has priority while tracking).
            T_ref = pose_matrix(st.ref.pos, st.ref.rot)
            pick = self.stepper.solve(T_ref, st.ref.s + 0.01, st.ref.q, 1.0)
            if pick is not None:
                dq_ds = np.abs(pick[0] - st.ref.q) / 0.01
                with np.errstate(divide="ignore"):
                    lim = np.where(dq_ds > 1e-9, p.joint_brake_share * self._max_acc / dq_ds, np.inf)
                s_acc_feed = min(s_acc_feed, float(np.min(lim)))

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            if p.swivel_mode == "fixed":
                return st.ref.s_fixed, st.ref.s_fixed, False
            s_des = self._desired_swivel(circle)
            margins = self.stepper.limit_margins(T, s0, st.ref.q, p.swivel.eps, p.swivel.lim_threshold)
            forces = self.swivel_dyn.forces(circle, s0, self._local.scene, p.capsules, margins)
            s_new = self.swivel_dyn.step(s0, s_des, dt, forces)
            # The swivel rate changes by at most max_swivel_acc per second.
            sd = wrap_angle(s_new - s0) / dt
            if feed:
                # The dynamics' own rate (attraction, obstacles, limits) within its share of the
                # joints' acceleration; the preferred swivel's motion is fed forward on top.
                sd = max(st.ref.sdot_dyn - s_acc_feed * dt, min(st.ref.sdot_dyn + s_acc_feed * dt, sd))
                st.ref.sdot_dyn = sd
                sd += wrap_angle(s_des - s_des_prev) / dt
            else:
                s_acc = self._joint_share_acc(abs(st.ref.sdot), p.max_swivel_acc)
                sd = max(st.ref.sdot - s_acc * dt, min(st.ref.sdot + s_acc * dt, sd))
            st.ref.s_des = s_des
            return wrap_angle(s0 + sd * dt), s_des, forces.clearance < p.elbow_priority_clearance

        return swivel

    def _hand_acc(self) -> float | None:
        """Largest hand acceleration (m/s^2) along the path that keeps every joint within
        ``joint_brake_share`` of its acceleration limit, with joint speeds proportional to the hand
        speed; None when the hand is (nearly) at rest."""
        a = self._joint_share_acc(self._state().ref.v_tool, math.inf)
        return None if math.isinf(a) else a

    def _joint_share_acc(self, rate: float, default: float) -> float:
        """Largest rate of change of ``rate`` (a hand speed or an orientation rate) that keeps every
        joint within ``joint_brake_share`` of its acceleration limit, the joint velocities of the last
        reference step taken as proportional to ``rate``; ``default`` caps it and is used at rest."""
        if rate < 1e-4:  # from rest: a gentle first step, the ratio is measured from the next one
            return min(default, 0.1 * float(np.min(self._max_acc)))
        qd = np.abs(self._state().ref.qd)
        mask = qd > 1e-6
        if not np.any(mask):
            return default
        a = float(np.min(self._max_acc[mask] / qd[mask])) * rate * self.params.joint_brake_share
        return max(min(a, default), 1e-3)

    def _joint_braking_speed(self, dist: float) -> float | None:
        """Hand speed (m/s) from which the hand can still stop within the remaining ``dist`` (m) at the
        acceleration of :meth:`_hand_acc`."""
        a_hand = self._hand_acc()
        if a_hand is None:
            return None
        return math.sqrt(2.0 * a_hand * max(dist, 0.0))

    def _orientation_target(self, e: Vec3, dist: float) -> Quat:
        """Goal orientation, turned so that the tool axis leans towards the heading far from the goal."""
        st = self._state()
        assert st.goal is not None
        p = self.params
        goal_q = st.goal.rot
        if p.tangent_weight <= 0.0 or st.att.v < 1e-3:
            return goal_q
        w = p.tangent_weight * max(0.0, min(1.0, (dist - p.tangent_distance) / p.tangent_distance))
        if w <= 0.0:
            return goal_q
        g = quat_rotate(goal_q, (0.0, 0.0, 1.0))  # tool approach axis at the goal
        a = slerp_vectors(g, e, w)
        return quat_normalize(quat_mul(quat_between_vectors(g, a), goal_q))

    def _desired_swivel(self, circle: ElbowCircle) -> float:
        p = self.params
        if p.swivel_reference == "absolute":
            return wrap_angle(p.preferred_swivel)
        low = _swivel_low(circle)
        if low is None:
            return self._state().ref.s_des
        ref = low if p.swivel_reference == "low" else low + math.pi
        return wrap_angle(ref + p.preferred_swivel)

    def _heading_to_goal(self) -> tuple[float, float]:
        st = self._state()
        if st.goal is None:
            return st.att.phi, st.att.theta
        gp, cp = st.goal.pos, st.ref.pos
        return heading_angles((gp[0] - cp[0], gp[1] - cp[1], gp[2] - cp[2]), st.att.phi)

    # -- servo ------------------------------------------------------------------------------------
    def _servo_target(self, dt: float) -> ServoTarget:
        st = self._state()
        ref = st.ref
        goal = st.goal
        if goal is None:  # stopped or rejected while tracking: decelerate
            return ServoTarget(ref.pos, ref.rot, ZERO3, ZERO3, hold_position=False)
        if goal.kind is GoalKind.TWIST:
            tw = st.twist
            if tw is None or st.time - tw.since > self.params.servo.twist_timeout:
                return ServoTarget(ref.pos, ref.rot, ZERO3, ZERO3, hold_position=False)
            return ServoTarget(ref.pos, ref.rot, tw.vel, tw.w, hold_position=False)
        pred = self.stream.predict(st.time, st.time)
        if pred is None:
            return ServoTarget(goal.pos, goal.rot, ZERO3, ZERO3)
        return ServoTarget(pred.pos, pred.rot, pred.vel, pred.w)

    def _servo_step(self, dt: float) -> None:
        st = self._state()
        p = self.params
        sp: ServoParams = p.servo
        if float(np.max(np.abs(st.ref.q - st.cmd.q) * self._inv_vel)) > sp.resync_lag:
            # The command lags (a joint at its acceleration limit, the guard): the servo goes on from
            # where the arm is, so the reference never runs off to a configuration the arm cannot
            # follow; the hand then follows as closely as the limits allow.
            self._resync_reference(keep_velocity=True)
        ref = st.ref
        target = self._servo_target(dt)
        # The servo's own bounds are Cartesian; the joints' velocity limits shorten the IK step below
        # and their acceleration limits bound the command (which then lags the reference).
        new_pos, new_rot, _, _ = servo_step(ref.pos, ref.rot, ref.vel, ref.w, target, dt, sp.gain, sp.acc,
                                            p.speed.v_max, sp.ori_gain, sp.ori_acc, p.max_ori_rate)
        # Slide along the workspace shells and obstacles: keep only the motion that can be made.
        d = (new_pos[0] - ref.pos[0], new_pos[1] - ref.pos[1], new_pos[2] - ref.pos[2])
        d = workspace_slide(d, ref.pos, ref.rot, self.geom, self._d_inner, self._d_outer, p.workspace_margin,
                            project=True)
        d = obstacle_slide(d, ref.circle, ref.s, self._local.scene, p.capsules, p.slide_band, project=True)
        # Elbow before hand: while the arm closes in on an obstacle within elbow_priority_clearance,
        # the hand slows so that the gap would last at least ``yield_time`` at the present rate; the
        # swivel meanwhile turns the elbow away (the hand catches up once the gap opens again).
        cmd = st.cmd
        if cmd.obs_rate > 0.0 and cmd.obs_clear < p.elbow_priority_clearance:
            room = max(cmd.obs_clear - p.collision_margin, 0.0)
            k = min(1.0, room / (cmd.obs_rate * sp.yield_time))
            d = (k * d[0], k * d[1], k * d[2])
            if k < 1.0:
                new_rot = ref.rot if k <= 0.0 else blend(ref.pos, ref.rot, ref.pos, new_rot, k)[1]
        new_pos = (ref.pos[0] + d[0], ref.pos[1] + d[1], ref.pos[2] + d[2])
        out = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, new_pos, new_rot, dt, self._swivel_fn(dt))
        if isinstance(out, DeadEnd):
            self._hold(f"{self._stream_word()}: {out.reason}")
            ref.vel, ref.w = ZERO3, ZERO3
            self._track(dt)
            return
        limited = "joint velocity limits" if out.speed_scale < 1.0 else ""
        shaped = self._joint_acceleration_fit(out, dt)
        if shaped is not None:
            out = shaped
            limited = "joint acceleration limits"
        self._commit(out, dt, attractor=False)
        if limited and not st.message:
            st.message = f"{self._stream_word()}: {limited}: following as closely as they allow"

    def _joint_acceleration_fit(self, step: IKStep, dt: float) -> IKStep | None:
        """If ``step`` asks a joint for more than its acceleration limit, the step that keeps as much
        of the servo's change of the hand's motion as the joints allow: a blend between coasting (the
        hand keeps its velocity) and ``step``, its share found per joint from the (nearly linear)
        joint accelerations of the two. None if ``step`` fits."""
        st = self._state()
        ref = st.ref
        amax = 0.98 * self._max_acc * dt * dt
        base = ref.q + ref.qd * dt  # where every joint would coast to
        dev = step.q - base
        if np.all(np.abs(dev) <= amax):
            return None
        v, w = ref.vel, ref.w
        c_pos = (ref.pos[0] + v[0] * dt, ref.pos[1] + v[1] * dt, ref.pos[2] + v[2] * dt)
        c_rot = quat_normalize(quat_mul(quat_from_rotvec((w[0] * dt, w[1] * dt, w[2] * dt)), ref.rot))
        coast = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, c_pos, c_rot, dt, lambda c, T, s0: (
            step.s, step.s_des, False))
        if isinstance(coast, DeadEnd):
            return None
        d0 = coast.q - base  # joint acceleration (times dt^2) when coasting
        d1 = dev - d0  # what the servo's change adds
        lo, hi = 0.0, 1.0
        for j in range(7):
            if abs(d1[j]) < 1e-12:
                continue
            a, b = (-amax[j] - d0[j]) / d1[j], (amax[j] - d0[j]) / d1[j]
            lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
        alpha = hi if lo <= hi else (0.0 if np.max(np.abs(d0) / amax) <= np.max(np.abs(dev) / amax) else 1.0)
        alpha = min(max(alpha, 0.0), 1.0)
        if alpha >= 1.0:
            return None
        pos, rot = blend(coast.pos, coast.rot, step.pos, step.rot, alpha)
        out = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, pos, rot, dt, lambda c, T, s0: (
            step.s, step.s_des, False))
        return None if isinstance(out, DeadEnd) else out

    def _stream_word(self) -> str:
        st = self._state()
        return "twist" if st.goal is not None and st.goal.kind is GoalKind.TWIST else "stream"

    def _at_rest_servo(self) -> bool:
        st = self._state()
        v, w = st.ref.vel, st.ref.w
        return max(abs(c) for c in (*v, *w)) < 1e-6

    # -- re-planning ------------------------------------------------------------------------------
    def _plan_step(self, dt: float) -> None:
        st = self._state()
        if np.any(st.cmd.qd != 0.0):  # brake to rest first, through the guard
            self._brake(dt)
            return
        if st.planner is None:
            assert st.goal is not None
            T = pose_matrix(st.goal.pos, st.goal.rot)
            s_pref = None
            try:
                circle: ElbowCircle | None = elbow_circle(self.geom, T)
            except UnreachableError:
                circle = None
            if circle is not None and self.params.swivel_mode != "fixed":
                s_pref = self._desired_swivel(circle)
            clear_enough = self.params.replan.clearance + 2.0 * self.guard.step
            retreat = [q for q, c in reversed(st.history) if c >= clear_enough][::10]
            st.planner = JointPlanner(self.stepper, self.guard, self._index.reach_scene.scene,
                                      st.cmd.q.copy(),
                                      T, self.params.replan, self.params.unfold_pitch, retreat, s_pref)
        if not st.planner.work():
            return
        planner = st.planner
        st.planner = None
        if planner.path is None:
            self._block(f"{planner.reason} (after: {st.plan_reason})")
            return
        st.path = JointPath(planner.path, self._max_vel, self._max_acc)
        st.path_t = 0.0
        st.ref.q = st.cmd.q.copy()
        st.ref.qd = np.zeros(7)
        st.brake_sync = True
        st.mode = Mode.JOINT
        vias = len(planner.path) - 2
        st.message = f"moving in joint space ({vias} via points, {st.path.duration:.1f} s): {st.plan_reason}"

    def _joint_step(self, dt: float) -> None:
        st = self._state()
        path = st.path
        assert path is not None
        st.path_t += dt
        q_ref, _ = path.sample(st.path_t)
        st.ref.qd = (q_ref - st.ref.q) / dt
        st.ref.q = q_ref
        if not self._track(dt):
            st.path = None
            self._start_plan(f"the collision guard stopped the joint-space move ({st.message})")
            return
        done = st.path_t >= path.duration and float(np.max(np.abs(st.cmd.q - q_ref))) <= 1e-9 \
            and float(np.max(np.abs(st.cmd.qd))) <= 1e-9
        if done:
            st.path = None
            self._resync_reference(keep_velocity=False)
            st.ref.s_fixed = st.ref.s
            st.mode = Mode.ATTRACTOR
            self._enter_attractor()
            st.message = ""
            st.progress.best = math.inf
            st.progress.t_best = st.time

    def _watch_progress(self) -> None:
        """Stall detection of point goals (see :class:`~redarm_ros.control.params.ReplanParams`)."""
        st = self._state()
        rp: ReplanParams = self.params.replan
        goal = st.goal
        if goal is None or goal.kind is not GoalKind.POINT or st.mode is not Mode.ATTRACTOR:
            return
        pr = st.progress
        d = math.dist(st.cmd.pos, goal.pos)
        a = quat_angle(st.cmd.rot, goal.rot)
        err = d + 0.1 * a
        if (d <= self.params.pos_tolerance and a <= self.params.ori_tolerance) or err < pr.best - rp.progress:
            pr.best = err
            pr.t_best = st.time
            pr.travel = 0.0
        pr.travel += st.cmd.tool_speed * (st.time - pr.t_last) if pr.t_last else 0.0
        pr.t_last = st.time
        if st.phase is Phase.HOLDING:
            pr.hold_since = st.time if pr.hold_since is None else pr.hold_since
        else:
            pr.hold_since = None
        if not rp.enabled:
            return
        pr.guard_stops = [t for t in pr.guard_stops if st.time - t <= rp.stall_time * 2.0]
        if pr.hold_since is not None and st.time - pr.hold_since >= rp.hold_time:
            self._start_plan(f"held {rp.hold_time:.1f} s ({st.message})")
        elif len(pr.guard_stops) >= rp.guard_stops:
            pr.guard_stops = []
            self._start_plan(f"the collision guard stopped the arm {rp.guard_stops} times in "
                             f"{2.0 * rp.stall_time:.1f} s ({st.message or 'sliding along an obstacle'})")
        elif st.time > pr.due and err > 0.01:
            self._start_plan(f"overdue: {d * 1e3:.0f} mm, {a:.2f} rad from the goal after "
                             f"{st.time - goal.since:.1f} s")
        else:
            since = st.time - pr.t_best
            creeping = since >= rp.stall_time and pr.travel < rp.stall_travel
            if creeping or since >= rp.detour_time:
                why = f"; {st.message}" if st.message else ""
                self._start_plan(f"no progress for {since:.1f} s ({d * 1e3:.0f} mm, {a:.2f} rad from the "
                                 f"goal{why})")

    # -- reference -> command ---------------------------------------------------------------------
    def _commit(self, step: IKStep, dt: float, attractor: bool) -> bool:
        """Take the IK step as the new reference and move the command towards it within the velocity
        and acceleration limits, through the guard. Returns False if the guard refused the command."""
        st = self._state()
        p = self.params
        ref = st.ref
        q, pos, rot, s = step.q, step.pos, step.rot, step.s
        moved = math.dist(pos, ref.pos)
        ratio = float(np.max(np.abs(q - ref.q) * self._inv_vel)) / dt
        ref.sdot = wrap_angle(s - ref.s) / dt if p.swivel_mode != "fixed" else 0.0
        ref.w_ori = quat_angle(ref.rot, rot) / dt
        ref.vel = ((pos[0] - ref.pos[0]) / dt, (pos[1] - ref.pos[1]) / dt, (pos[2] - ref.pos[2]) / dt)
        wv = rotvec_between(ref.rot, rot)
        ref.w = (wv[0] / dt, wv[1] / dt, wv[2] / dt)
        ref.qd = (q - ref.q) / dt
        ref.q = q
        ref.pos, ref.rot, ref.s, ref.circle = pos, rot, s, step.circle
        if st.message.startswith(("collision guard", "stream", "twist", "no joint solution")):
            st.message = ""
        st.brake_sync = False
        if not self._track(dt):
            return False
        v_now = moved / dt
        ref.v_tool = v_now
        if attractor:
            self._speed_budget(ratio, v_now, dt)
        if st.phase is Phase.HOLDING:
            st.phase = Phase.REACHING
        return True

    def _speed_budget(self, ratio: float, v_now: float, dt: float) -> None:
        """When a joint nears its velocity limit, when the reference asks a joint for much of its
        acceleration, or when the command lags behind the reference, cap the hand speed ahead of
        time (the filter then slows down with bounded jerk)."""
        st = self._state()
        p = self.params
        att = st.att
        sp = self.speed_profile.params
        predicted = ratio + 4.0 * max(ratio - att.ratio, 0.0)  # the ratio can grow fast in turns
        att.ratio = ratio
        cap = math.inf
        if predicted > 0.85 and v_now > 1e-4:
            cap = max(v_now * 0.85 / predicted, 0.02)
        lag = float(np.max(np.abs(st.ref.q - st.cmd.q) * self._inv_vel))  # s at full joint speed
        if lag > p.max_lag and v_now > 1e-3:
            cap = min(cap, max(v_now * p.max_lag / lag, 0.02))
        if math.isfinite(cap):
            att.v_cap = cap if att.v_cap is None else min(cap, att.v_cap + sp.a_max * dt)
        elif att.v_cap is not None:
            att.v_cap += 0.5 * sp.a_max * dt
            if att.v_cap > sp.v_max:
                att.v_cap = None

    def _track(self, dt: float) -> bool:
        """Move the command towards the reference within the joint velocity, acceleration and
        position limits (time-optimal per joint: the reference velocity plus the speed from which the
        lag can still be braked away), then check it with the collision guard. Returns False if the
        guard refused it (then the arm brakes and holds)."""
        st = self._state()
        cmd, ref = st.cmd, st.ref
        qc, qd = cmd.q, cmd.qd
        # The lag behind where the reference was a step ago: with the reference's velocity fed
        # forward, a command on the reference stays on it (no limit cycle around a moving reference).
        u = np.clip(ref.qd, -self._max_vel, self._max_vel)
        e = ref.q - u * dt - qc
        v_des = u + np.sign(e) * braking_speed(np.abs(e), self._max_acc, dt)
        e = ref.q - qc
        lo, hi = velocity_bounds(qc, qd, dt, self._max_vel, self._max_acc, self._lower, self._upper)
        v = np.clip(v_des, lo, hi)
        small = np.abs(e) <= 1e-12  # land exactly on a resting reference
        v = np.where(small & (np.abs(ref.qd) <= 1e-12) & (lo <= 0.0) & (hi >= 0.0), 0.0, v)
        q_new = np.clip(qc + v * dt, self._lower, self._upper)
        snap = np.abs(ref.q - q_new) <= 1e-12
        q_new = np.where(snap, ref.q, q_new)
        return self._command(q_new, (q_new - qc) / dt, dt)

    def _command(self, q: np.ndarray, qd: np.ndarray, dt: float) -> bool:
        """Commit command ``q`` (rad) moving at ``qd`` (rad/s) if the guard allows it; otherwise brake."""
        st = self._state()
        local = self._local
        sync = st.brake_sync  # a planned path: braking keeps to it
        kp = self.guard.key_points(q)
        clear, bad = self.guard.check(q, qd, st.cmd.clear.distance, dt, local.scene, sync,
                                      on_path=st.mode is Mode.JOINT, kp=kp)
        if bad is not None:
            self._guard_stop(bad, dt)
            return False
        self._set_command(q, qd, clear, dt, kp)
        return True

    def _set_command(self, q: np.ndarray, qd: np.ndarray, clear: Clearance, dt: float,
                     kp: np.ndarray | None = None) -> None:
        st = self._state()
        cmd = st.cmd
        local = self._local
        kp = self.guard.key_points(q) if kp is None else kp
        cmd.kp = kp
        obs = self._obstacle_clearance(q, local, kp)
        both = math.isfinite(cmd.obs_clear) and math.isfinite(obs)
        cmd.obs_rate = (cmd.obs_clear - obs) / dt if both else 0.0
        cmd.obs_clear = obs
        cmd.q = q
        cmd.qd = qd
        cmd.clear = self._globalise(clear, local)
        T = np.asarray(self.arm.fk(q), float)
        cpos, crot = _pose_of(T)
        cmd.tool_speed = math.dist(cpos, cmd.pos) / dt
        cmd.pos, cmd.rot = cpos, crot
        st.history.append((q, clear.distance))

    def _resync_reference(self, keep_velocity: bool = False) -> None:
        """Make the reference the command's pose (after a guard stop, or to leave a joint-space move):
        pose, swivel and circle from FK; the Cartesian velocity from the command's when asked."""
        st = self._state()
        ref, cmd = st.ref, st.cmd
        ref.q = cmd.q.copy()
        ref.qd = cmd.qd.copy() if keep_velocity else np.zeros(7)
        T = np.asarray(self.arm.fk(cmd.q), float)
        ref.pos, ref.rot = _pose_of(T)
        try:
            ref.circle = elbow_circle(self.geom, T)
            ref.s = float(self.arm.swivel(cmd.q))
        except UnreachableError:
            ref.circle = None
        ref.sdot = 0.0
        ref.sdot_dyn = 0.0
        ref.w_ori = 0.0
        if keep_velocity:
            J = np.asarray(self.arm.jacobian(cmd.q), float)
            tw = J @ cmd.qd
            ref.vel = (float(tw[0]), float(tw[1]), float(tw[2]))
            ref.w = (float(tw[3]), float(tw[4]), float(tw[5]))
            ref.w_ori = math.sqrt(ref.w[0] ** 2 + ref.w[1] ** 2 + ref.w[2] ** 2)
            if ref.circle is not None and np.any(cmd.qd != 0.0):  # the swivel rate, by a step ahead
                h = 1e-3
                q_h = np.clip(cmd.q + h * cmd.qd, self._lower, self._upper)
                ref.sdot = wrap_angle(float(self.arm.swivel(q_h)) - ref.s) / h
        else:
            ref.vel, ref.w = ZERO3, ZERO3
        st.att.v = 0.0 if not keep_velocity else math.sqrt(sum(c * c for c in ref.vel))
        st.att.a = 0.0

    def _guard_stop(self, bad: Clearance, dt: float) -> None:
        st = self._state()
        st.progress.guard_stops.append(st.time)
        local = self._local
        what = describe(bad, local.scene)
        braked = self._brake(dt)
        self._resync_reference()
        self._hold(f"collision guard: the next step would bring {what}; {'braking' if braked else 'holding'}")

    def _brake(self, dt: float) -> bool:
        """One step of the hardest allowed joint braking, if the guard lets it through; otherwise stop
        where the arm is (an emergency stop: the only command that may exceed the acceleration limit).
        Returns True if a braking step was commanded."""
        st = self._state()
        cmd = st.cmd
        if not np.any(cmd.qd != 0.0):
            return False
        local = self._local
        out = self.guard.brake(cmd.q, cmd.qd, cmd.clear.distance, dt, local.scene, st.brake_sync)
        if out is not None:
            self._set_command(out[0], out[1], out[2], dt)
            return True
        LOG.warning("emergency stop: even braking would bring the arm into the scene")
        cmd.qd = np.zeros(7)
        return False

    def _hold(self, why: str) -> None:
        """Stop the hand (the command then brakes onto the reference) and report HOLDING with ``why``
        (for a stream or twist the phase stays TRACKING: it is followed as closely as allowed)."""
        st = self._state()
        st.att.v = 0.0
        st.att.a = 0.0
        st.ref.qd = np.zeros(7)
        st.ref.vel, st.ref.w = ZERO3, ZERO3
        if st.goal is not None and st.goal.kind is GoalKind.POINT:
            st.phase = Phase.HOLDING
        st.message = why

    # -- phase and result -------------------------------------------------------------------------
    def _update_phase(self) -> None:
        st = self._state()
        goal = st.goal
        if goal is None or st.phase in (Phase.HOLDING, Phase.BLOCKED):
            return
        if st.mode in (Mode.PLAN, Mode.JOINT):
            st.phase = Phase.REPLANNING
            return
        if st.mode is Mode.SERVO:
            if goal.kind is GoalKind.TWIST:
                tw = st.twist
                active = tw is not None and st.time - tw.since <= self.params.servo.twist_timeout
                if not active and self._at_rest_servo():
                    st.goal = None
                    st.phase = Phase.IDLE
                    st.message = "twist ended"
                    return
                st.phase = Phase.TRACKING
                if active:
                    goal.pos, goal.rot = st.ref.pos, st.ref.rot
                return
            if not self.stream.ended(st.time):
                st.phase = Phase.TRACKING
                if st.stream_note and not st.message:
                    st.message = f"{st.stream_note}: following as closely as the limits allow"
                return
        p = self.params
        d = math.dist(st.cmd.pos, goal.pos)
        err = quat_angle(st.cmd.rot, goal.rot)
        if d <= p.pos_tolerance and err <= p.ori_tolerance and self._settled():
            st.phase = Phase.REACHED
        else:
            st.phase = Phase.REACHING

    def _settled(self) -> bool:
        """The reference is at the goal too, the commanded tool has (nearly) stopped (below
        ``pos_tolerance`` per 0.1 s) and so have the joints (below 5 % of their velocity limits, within
        1 mrad of the reference): REACHED neither flickers while the command catches up nor comes
        while the elbow still swings about its swivel."""
        st = self._state()
        p = self.params
        goal = st.goal
        assert goal is not None
        if math.dist(st.ref.pos, goal.pos) > p.pos_tolerance or \
                quat_angle(st.ref.rot, goal.rot) > p.ori_tolerance:
            return False
        if st.cmd.tool_speed > p.pos_tolerance / 0.1:
            return False
        return float(np.max(np.abs(st.cmd.qd) / self._max_vel)) <= 0.05 and \
            float(np.max(np.abs(st.ref.q - st.cmd.q))) <= 1e-3

    def _result(self) -> StepResult:
        st = self._state()
        if st.goal is not None:
            d = math.dist(st.cmd.pos, st.goal.pos)
            err = quat_angle(st.cmd.rot, st.goal.rot)
        else:
            d = math.inf
            err = math.inf
        gv, gw, rate = ZERO3, ZERO3, 0.0
        if st.goal is not None and st.goal.kind is GoalKind.STREAM and not self.stream.ended(st.time):
            gv, gw = self.stream.velocity()
            rate = self.stream.rate()
        elif st.goal is not None and st.goal.kind is GoalKind.TWIST and st.twist is not None:
            gv, gw = st.twist.vel, st.twist.w
        speed = st.att.v if st.mode is Mode.ATTRACTOR else math.sqrt(sum(c * c for c in st.ref.vel))
        clear = st.cmd.clear
        if self._local.floor < clear.distance:  # an obstacle left out may be nearer: report the bound
            clear = Clearance(self._local.floor, -1, LEFT_OUT)
        return StepResult(
            q=st.cmd.q.copy(),
            phase=st.phase,
            swivel=st.ref.s,
            swivel_desired=st.ref.s_des,
            clearance=clear.distance,
            clearance_link=clear.link,
            clearance_obstacle=clear.obstacle,
            distance_to_goal=d,
            orientation_error=err,
            heading=(st.att.phi, st.att.theta),
            speed=speed,
            position=st.cmd.pos,
            message=st.message,
            goal_velocity=gv,
            goal_rate=gw,
            stream_rate=rate,
        )

    def forces(self) -> SwivelForces | None:
        """Swivel forces at the current state (for plots and diagnostics)."""
        st = self._state()
        if st.ref.circle is None:
            return None
        return self.swivel_dyn.forces(st.ref.circle, st.ref.s, self._index.reach_scene.scene,
                                      self.params.capsules)

