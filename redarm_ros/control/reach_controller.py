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
broad phase keeps (:mod:`~redarm_ros.geometry.broadphase`).

:class:`ReachController` is the core: it owns the :class:`~redarm_ros.control.state.CoreState`, picks
the law, and composes the parts, each a class whose methods take the state and the parameters:
:class:`~redarm_ros.control.attractor_law.AttractorLaw`, :class:`~redarm_ros.control.servo_law.ServoLaw`,
:class:`~redarm_ros.control.replan_law.ReplanLaw`, :class:`~redarm_ros.control.command.CommandShaper`
(reference to command), and the arm's redundancy strategy (:mod:`~redarm_ros.control.redundancy`: the
swivel of a 7-DOF arm, none for the 6-DOF arm).

Units: m, rad, s. Quaternions are (w, x, y, z). The core is pure Python/numpy (no ROS); the
controller node converts messages to these calls.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any, cast

import numpy as np

from redarm_ros.control.attractor import direction
from redarm_ros.control.attractor_law import AttractorLaw
from redarm_ros.control.command import CommandShaper, SceneView
from redarm_ros.control.corridor_route import CorridorRoute
from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.goal_hint import BaseMoveHints
from redarm_ros.control.ik_step import pose_matrix, pose_of
from redarm_ros.control.ik_step6 import is_6dof
from redarm_ros.control.joint_limits import JointBounds
from redarm_ros.control.params import ControllerParams, ReplanParams, ServoParams, StreamParams
from redarm_ros.control.redundancy import Redundancy, SwivelRedundancy
from redarm_ros.control.replan_law import ReplanLaw
from redarm_ros.control.servo_law import ServoLaw
from redarm_ros.control.slide import wrist_shell
from redarm_ros.control.state import (
    REST_SPEED_SHARE,
    ZERO3,
    Command,
    CoreState,
    Goal,
    Mode,
    Progress,
    Twist,
)
from redarm_ros.control.stream import StreamEstimator
from redarm_ros.control.swivel_dynamics import SwivelForces
from redarm_ros.control.types import GoalCheck, GoalKind, GoalStatus, Phase, Quat, StepResult, Vec3
from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.broadphase import LEFT_OUT, SceneIndex
from redarm_ros.geometry.obstacles import ArmCapsules, Clearance, Scene
from redarm_ros.kinematics.protocols import ControlledArm, ControlledSwivelArm
from redarm_ros.kinematics.quaternion import quat_angle
from redarm_ros.kinematics.urdf_chain import MappedSwivelArm, capsules_from_urdf

LOG = logging.getLogger(__name__)
SETTLING = "at the goal; the elbow is settling on its preferred swivel"
#: the message of a point goal without a swivel corridor whose straight route the attractor takes
NO_CORRIDOR = "attractor dynamics, no swivel corridor"
PLANNING = "planning the straight route through the swivel corridor"
#: s a swivel must stand (below settle_swivel_rate) while its dynamics asks to move, to count as settled
SETTLE_DWELL_S = 0.3
#: s the elbow's wanted rate must stay above REACHED's threshold to make REACHED leave: near a joint
#: limit the limit force and the attraction balance, and the wanted rate flickers over it for a step
#: or two while the elbow stands (sequence benchmark: REACHED left for 0.07 s, 0.01 rad of travel)
WANT_HOLD_S = 0.1

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
    "controller_refusal",
]


def has_swivel(arm: object) -> bool:
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


def controller_refusal(arm: object) -> str | None:
    """One line saying why the controller cannot run ``arm`` (a URDF model), or None.

    A URDF chain without the closed form carries its reason; a URDF chain that maps onto the swivel model
    only through a base transform, joint signs or offsets (kind ``swivel7_urdf``) is refused too: the
    controller's geometry is the model's own frames (an arm whose URDF is the model itself runs).
    """
    name = getattr(arm, "name", arm)
    why = (getattr(arm, "config", None) or {}).get("closed_form_refused")
    if why:
        return f"arm {name!r} is not a spherical-shoulder / elbow / spherical-wrist chain: {why}"
    if getattr(arm, "kind", "") == "swivel7_urdf" and not arm.frames_are_canonical:
        return (f"arm {name!r} maps onto the swivel model only through a base or tool transform; the "
                "controller runs arms whose base and tool frames are the model's (joint signs and offsets "
                "are fine)")
    return None


def urdf_capsules(arm: ControlledArm, params: ControllerParams | None) -> ControllerParams:
    """``params`` (default: the defaults), with the capsule radii of the arm's URDF collision geometry
    (:func:`~redarm_ros.kinematics.urdf_chain.capsules_from_urdf`) where the capsules are left at the
    defaults."""
    p = params or ControllerParams()
    if p.capsules != ArmCapsules():
        return p
    caps = capsules_from_urdf(arm, p.capsules)
    return p if caps == p.capsules else dataclasses.replace(p, capsules=caps)


class JointMappedController:
    """The controller of a URDF arm that is the swivel model up to joint signs and zero offsets (its base
    and tool frames the model's, as the iiwa's): a :class:`ReachController` on ``arm.canonical`` with the
    joint values mapped at the boundary, ``q_c = sign (q - offset)``. Poses, twists, the scene and every
    distance are the same in both; limits, rates and accelerations keep their sizes. Everything else is
    the inner controller's. Built by :func:`~redarm_ros.control.make.make_controller` for such an arm."""

    def __init__(self, arm: MappedSwivelArm, scene: Scene | None = None,
                 params: ControllerParams | None = None) -> None:
        if getattr(arm, "kind", "") != "swivel7_urdf":
            raise ConfigError(f"JointMappedController maps a URDF swivel arm onto its model; "
                              f"{getattr(arm, 'name', arm)!r} is not one", field="arm")
        self.arm = arm
        self.inner = ReachController(arm.canonical, scene, urdf_capsules(arm, params))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    @property
    def q(self) -> np.ndarray | None:
        """Last commanded joint positions (rad, the arm's own), None before :meth:`reset`."""
        qc = self.inner.q
        return None if qc is None else self.arm.from_canonical_q(qc)

    def reset(self, q: Any, now: float | None = None) -> None:
        """:meth:`ReachController.reset` from the arm's measured joint positions."""
        self.inner.reset(self.arm.to_canonical_q(self.arm.check_q(q)), now)

    def step(self, *args: Any, **kwargs: Any) -> StepResult:
        """:meth:`ReachController.step`; the result's q in the arm's joint values."""
        res = self.inner.step(*args, **kwargs)
        return dataclasses.replace(res, q=self.arm.from_canonical_q(res.q))


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

    :func:`~redarm_ros.control.make.make_controller` builds the controller of any arm: this class for a
    7-DOF swivel arm, :class:`~redarm_ros.control.reach6.ReachController6` (the same dynamics without
    the swivel) for the 6-DOF PowerCube arm.

    Raises:
        ConfigError: the arm is not one this class runs (the message names the one that does).
    """

    #: Time budget (s) of the base-move suggestion in the rejection of a goal out of reach (one search
    #: per rejected goal, in the control step's thread).
    BASE_MOVE_BUDGET_S = 0.1

    #: False (the node): the arm holds while the worker thread plans a point goal's corridor route, the
    #: steps go on. True: the step after the goal waits for the plan, so an in-process run (tests,
    #: benches) does not depend on the thread's speed
    wait_for_plans = False

    def __init__(self, arm: ControlledArm, scene: Scene | None = None,
                 params: ControllerParams | None = None) -> None:
        refused = controller_refusal(arm) or self.refusal(arm)
        if refused:
            raise ConfigError(refused, field="arm")
        self.arm = arm
        self.params = urdf_capsules(arm, params)
        p = self.params
        bounds = JointBounds.of(arm)
        self.redundancy = self._redundancy(arm, p, bounds)
        geom = self.redundancy.geom
        shell = wrist_shell(float(bounds.lower[3]), float(bounds.upper[3]), geom.upper, geom.fore)
        self._st: CoreState | None = None
        self._corridor_pool: ThreadPoolExecutor | None = None  # plans corridor routes off the control step
        self._hints = BaseMoveHints(arm, self.BASE_MOVE_BUDGET_S)
        self.scene = Scene()
        self.view = SceneView.of(SceneIndex(self.scene, geom.shoulder, 1.0, 0.0))
        self.command = CommandShaper(arm, self.redundancy.guard, bounds, self.view, self.redundancy)
        self.attractor = AttractorLaw(p, self.redundancy, self.command, bounds, self.view, shell)
        self.servo = ServoLaw(self.redundancy, self.command, bounds, self.view, shell)
        self.replan = ReplanLaw(self.redundancy, self.command, bounds, self.view)
        self._install_scene(scene if scene is not None else Scene())

    @classmethod
    def _redundancy(cls, arm: ControlledArm, params: ControllerParams, bounds: JointBounds) -> Redundancy:
        """The redundancy strategy of ``arm``: the swivel (:class:`SwivelRedundancy`)."""
        return SwivelRedundancy(cast(ControlledSwivelArm, arm), params, bounds)  # (refusal() checked it)

    @classmethod
    def refusal(cls, arm: object) -> str | None:
        """Why this class cannot run ``arm`` (None if it can): it runs 7-DOF swivel arms in the model's
        frames."""
        name = getattr(arm, "name", arm)
        if getattr(arm, "kind", "") == "swivel7_urdf":
            return (f"arm {name!r} is a URDF chain: make_controller(arm, scene, params) builds its "
                    "controller (the joint values mapped onto the model)")
        if is_6dof(arm):
            return (f"arm {name!r} has no swivel: make_controller(arm, scene, params) builds its controller "
                    "(ReachController6)")
        if not has_swivel(arm):
            return (f"ReachController needs a 7-DOF swivel arm or the 6-DOF PowerCube arm (through "
                    f"make_controller), got {name!r}")
        return None

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
        """Elbow circle of the current reference pose (centre, normal, radius, basis), for display; None
        without one (no self-motion, or the arm stretched)."""
        return None if self._st is None else self.redundancy.elbow_circle(self._st)

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
        return self.view.index.culled

    # ------------------------------------------------------------------ set-up
    def reset(self, q: Any, now: float | None = None) -> None:
        """Start from measured joint positions ``q`` (rad); clears the goal (phase IDLE). ``now``
        (s) sets the controller clock (e.g. the node's ROS time), else it keeps running.

        Raises:
            InvalidInputError: wrong length or NaN. Positions slightly outside the limits are
                clamped into them.
        """
        b = self.command.bounds
        qa = np.clip(self.arm.check_q(q), b.lower, b.upper)
        T = np.asarray(self.arm.fk(qa), float)
        pos, rot = pose_of(T)
        t = now if now is not None else (0.0 if self._st is None else self._st.time)
        local = self.view.index.reach_scene
        guard = self.command.guard
        kp = guard.key_points(qa)
        clear = guard.clearance(qa, local.scene, kp)
        cmd = Command(qa.copy(), self.command.globalise(clear, local), pos, rot, kp, qd=np.zeros(self.arm.n))
        cmd.obs_clear = self.command.obstacle_clearance(qa, local, kp)
        ref = self.redundancy.reference(qa, T, pos, rot, kp)
        self._st = CoreState(ref, cmd, stream=StreamEstimator(self.params.stream), time=float(t))

    def _install_scene(self, scene: Scene) -> None:
        self.scene = scene
        self.view.index = self.redundancy.scene_index(scene, self.params)
        self.view.local = self.view.index.reach_scene

    def set_scene(self, scene: Scene) -> GoalCheck | None:
        """Replace the obstacles (e.g. from the node's MarkerArray). Re-checks the active point goal;
        if it is now inside an obstacle it is dropped (phase REJECTED, the arm stops) and the failing
        :class:`GoalCheck` is returned; otherwise returns None. A BLOCKED goal is planned again."""
        if not isinstance(scene, Scene):
            raise InvalidInputError("scene must be a Scene", field="scene", value=scene)
        changed = scene != self.scene
        self._install_scene(scene)
        st = self._st
        if st is None:
            return None
        local = self.view.index.reach_scene
        st.cmd.clear = self.command.globalise(self.command.guard.clearance(st.cmd.q, local.scene, st.cmd.kp),
                                              local)
        st.cmd.obs_clear = self.command.obstacle_clearance(st.cmd.q, local, st.cmd.kp)
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
                self.replan.start(st, self.params, "the scene changed")
            elif changed:
                self._corridor_rescene(st, T)
        elif st.goal.kind is GoalKind.STREAM:
            st.stream_note = self.redundancy.stream_feasibility(T, local.scene, self.params)
        return None

    def set_preferred_swivel(self, value: float) -> None:
        """Change the preferred swivel (rad, same reference as ``params.swivel_reference``).

        Raises:
            InvalidInputError: not a number within the table's bound (+/- 2 pi).
        """
        try:
            v = float(value)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError("preferred swivel must be a number", field="preferred_swivel",
                                    value=value) from exc
        self.params = self.params.with_(preferred_swivel=v)

    # ------------------------------------------------------------------ goals
    def check_goal(self, T: Any) -> GoalCheck:
        """Check a goal pose (4x4, base frame) without changing state; see :class:`GoalStatus`."""
        # A goal out of reach (or without an in-limit solution): say where the base should go.
        return self.redundancy.check_goal(T, self.view.index.reach_scene.scene, self.params,
                                          None if self._st is None else self._st.cmd.q, self._hints)

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
        pos, rot = pose_of(Tn)
        t = self.stream.stamp_time(stamp, now)
        goal = st.goal
        p = self.params
        if goal is not None and goal.point_at(pos, p.pos_tolerance) \
                and quat_angle(goal.rot, rot) <= p.ori_tolerance:
            self.stream.add(pos, rot, t, now)  # the same goal again: nothing changes
            return GoalCheck(GoalStatus.ACCEPTED, "the active goal again", kind=GoalKind.POINT, repeat=True)
        if goal is not None and goal.kind in (GoalKind.POINT, GoalKind.STREAM) \
                and self.stream.continues(pos, rot, t, now):
            self.stream.add(pos, rot, t, now)
            if goal.kind is not GoalKind.STREAM:
                st.goal = Goal(pos, rot, GoalKind.STREAM, st.time)
                st.progress = Progress(t_best=st.time)
            if st.mode not in (Mode.SERVO, Mode.PLAN, Mode.JOINT):
                # (a joint-space move under way, e.g. out of the stretched pose, is finished first)
                self._enter_servo(st)
            newest = self.stream.newest
            assert newest is not None
            st.goal.pos, st.goal.rot = newest.pos, newest.rot
            st.stream_note = self.redundancy.stream_feasibility(Tn, self.view.index.reach_scene.scene,
                                                                self.params)
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
            self._enter_servo(st)
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
        st.corridor_plan = None
        self._leave_plan(st)

    def _reject(self, check: GoalCheck) -> None:
        LOG.info("goal rejected: %s", check.message)
        st = self._st
        if st is None:
            return
        st.goal = None
        st.twist = None
        st.phase = Phase.REJECTED
        st.message = check.message
        st.corridor_plan = None
        self._leave_plan(st)

    def _accept_point_goal(self, T: np.ndarray) -> None:
        st = self._state()
        pos, rot = pose_of(T)
        was_moving = st.mode in (Mode.JOINT, Mode.PLAN)
        st.goal = Goal(pos, rot, GoalKind.POINT, st.time)
        st.twist = None
        st.progress = Progress(t_best=st.time)
        st.message = ""
        st.phase = Phase.REACHING
        st.planner = None
        st.path = None
        if was_moving:
            self.command.resync_reference(st, keep_velocity=True)
        st.route = None
        st.corridor_plan = None
        if st.ref.circle is None:
            self.replan.start(st, self.params, "the arm is stretched (no elbow circle)")
            return
        scene = self.view.index.reach_scene.scene
        if self.redundancy.corridor_asked(st, self.params, scene):
            # planned in the worker thread (up to about a second); the arm holds at rest meanwhile
            if self._corridor_pool is None:
                self._corridor_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="swivel-corridor")
            st.corridor_plan = self._corridor_pool.submit(
                self.redundancy.corridor_job(st, self.params, T, scene))
            st.mode = Mode.ATTRACTOR
            st.att.v, st.att.a, st.att.turn, st.att.v_cap = 0.0, 0.0, (0.0, 0.0), None
            st.message = PLANNING
            # (the progress watch counts the planning as progress; the route's time sets the due time)
            st.progress.due = math.inf
            return
        self._point_goal_route(T, None, "")

    def _corridor_rescene(self, st: CoreState, T: np.ndarray) -> None:
        """The scene changed: a corridor route being planned is planned again against the new scene (the
        arm still holds); one being followed, checked against the old scene, is left for the attractor
        dynamics."""
        if st.corridor_plan is not None:
            assert self._corridor_pool is not None
            st.corridor_plan.cancel()
            st.corridor_plan = self._corridor_pool.submit(
                self.redundancy.corridor_job(st, self.params, T, self.view.index.reach_scene.scene))
        elif st.route is not None:
            st.route = None
            self.attractor.enter(st)
            st.message = "the scene changed on the corridor route: attractor dynamics"

    def _point_goal_route(self, T: np.ndarray, route: CorridorRoute | None, no_corridor: str) -> None:
        """Start the point goal ``T`` on its corridor ``route``, or without one (``no_corridor`` says why
        there is none, '' if none was planned): the joint-space re-planner at a dead end, else the
        attractor dynamics."""
        st = self._state()
        p = self.params
        if route is not None:
            self.attractor.take_corridor(st, p, route)
            st.mode = Mode.ATTRACTOR
            st.message = route.message()
            return
        reason = self.redundancy.route_dead_end(st, p, T) if p.replan.enabled else ""
        if reason:
            self.replan.start(st, p, f"{reason} (no swivel corridor: {no_corridor})" if no_corridor
                              else reason)
            return
        st.message = f"{NO_CORRIDOR}: {no_corridor}" if no_corridor else ""
        if st.mode is not Mode.ATTRACTOR:
            st.mode = Mode.ATTRACTOR
            self.attractor.enter(st)
        elif st.att.v < 1e-6:  # starting from rest: head straight at the goal
            st.att.phi, st.att.theta = self.attractor.heading_to_goal(st)
            st.att.turn = (0.0, 0.0)

    # ------------------------------------------------------------------ mode changes
    def _enter_servo(self, st: CoreState) -> None:
        """Track a stream or twist from here: a corridor route or a joint-space move ends, the servo
        goes on from the reference's motion."""
        st.route = None  # (a point goal's corridor route ends where a stream or twist begins)
        self.replan.end_joint_motion(st)  # from a joint-space move: drop its plan
        self.servo.enter(st)

    def _leave_plan(self, st: CoreState) -> None:
        """Out of PLAN/JOINT (a stop or rejection): the reference becomes Cartesian again."""
        if self.replan.end_joint_motion(st):
            st.mode = Mode.ATTRACTOR
            self.attractor.enter(st)

    def _attractor_step(self, st: CoreState, dt: float) -> None:
        """A point goal's step: wait for its corridor plan (the arm holds meanwhile), start the goal on
        the plan's outcome, then the attractor law."""
        p = self.params
        if st.corridor_plan is not None:
            if not self.wait_for_plans and not st.corridor_plan.done():  # the arm holds while it plans
                st.ref.qd = np.zeros_like(st.ref.q)
                self.command.track(st, dt)
                return
            route, why = st.corridor_plan.result()
            st.corridor_plan = None
            scene = self.view.index.reach_scene.scene
            if route is not None and not self.redundancy.corridor_asked(st, p, scene):
                route, why = None, "the arm or the parameters changed while it was planned"
            assert st.goal is not None
            self._point_goal_route(pose_matrix(st.goal.pos, st.goal.rot), route, why)
            # this step's command: the planner's (it brakes the arm), or braking onto the reference
            if st.mode is Mode.PLAN:
                self.replan.plan_step(st, p, dt)
                return
            if st.mode is not Mode.ATTRACTOR:
                st.ref.qd = np.zeros_like(st.ref.q)
                self.command.track(st, dt)
                return
        self.attractor.step(st, p, dt)

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
        self.view.local = self.command.local_scene(st, p, dt)
        if st.mode is Mode.ATTRACTOR and st.goal is None and st.att.v <= 0.0:
            st.mode = Mode.HOLD
        if st.mode is Mode.SERVO and st.goal is None and self.servo.at_rest(st):
            st.mode = Mode.HOLD
        if st.mode is Mode.HOLD:
            if st.goal is not None and st.phase is not Phase.BLOCKED:
                if st.goal.kind is GoalKind.POINT:
                    st.mode = Mode.ATTRACTOR
                    self.attractor.enter(st)
            if st.mode is Mode.HOLD:
                if np.any(st.cmd.qd != 0.0) or not np.array_equal(st.ref.q, st.cmd.q):
                    st.ref.qd = np.zeros_like(st.ref.q)  # the reference stands: the command brakes onto it
                    self.command.track(st, dt)
                return self._result()
        if st.mode is Mode.PLAN:
            self.replan.plan_step(st, p, dt)
        elif st.mode is Mode.JOINT:
            if self.replan.joint_step(st, p, dt):
                if st.goal is not None and st.goal.kind is GoalKind.STREAM:
                    self._enter_servo(st)  # a stream that arrived meanwhile: track it from here
                else:
                    st.mode = Mode.ATTRACTOR
                    self.attractor.enter(st)
        elif st.mode is Mode.SERVO and st.ref.circle is None:
            self.replan.start(st, p, "the arm is stretched (no elbow circle): moving in joint space to the "
                              "stream first")
        elif st.mode is Mode.SERVO:
            self.servo.step(st, p, dt)
        elif st.ref.circle is None:
            if st.goal is not None:
                self.replan.start(st, p, "the arm is stretched (no elbow circle)")
            else:
                st.mode = Mode.HOLD
        else:
            self._attractor_step(st, dt)
        self._update_phase()
        self.replan.watch(st, p)
        return self._result()

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
                if not active and self.servo.at_rest(st):
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
        at_goal = d <= p.pos_tolerance and err <= p.ori_tolerance
        # Hysteresis: once REACHED, the rate thresholds are doubled, so a rate that hovers at a
        # threshold does not make the phase flicker (the tolerances on the pose stay as they are).
        if at_goal and self._settled(2.0 if st.phase is Phase.REACHED else 1.0):
            st.phase = Phase.REACHED
            if st.message.startswith(SETTLING):
                st.message = ""
        else:
            st.phase = Phase.REACHING
            if at_goal and (not st.message or st.message.startswith(NO_CORRIDOR)):
                st.message = SETTLING

    def _settled(self, slack: float = 1.0) -> bool:
        """The reference is at the goal too, the commanded tool has (nearly) stopped (below
        ``pos_tolerance`` per 0.1 s) and so have the joints (below 5 % of their velocity limits, within
        1 mrad of the reference), and the elbow has settled: the swivel's rate below
        ``settle_swivel_rate``, and so the rate its dynamics asks for, unless the swivel has stood for
        :data:`SETTLE_DWELL_S` anyway (held by the joint limits). So REACHED neither flickers while the
        command catches up nor comes while the elbow still has to swing to its swivel (after a
        joint-space move the joints stop first, then the swivel dynamics turns the elbow). The elbow's
        last slow approach (below that rate; a self-motion: the tool stands) may go on after REACHED; a
        corridor route's tail may not (it moves the hand).
        ``slack`` scales the rate thresholds; with ``slack`` > 1 (REACHED) the wanted rate counts only
        once it has lasted :data:`WANT_HOLD_S`."""
        st = self._state()
        p = self.params
        goal = st.goal
        assert goal is not None
        if st.route is not None:  # the corridor route's tail (within the tolerance) still moves the hand
            return False
        if math.dist(st.ref.pos, goal.pos) > p.pos_tolerance or \
                quat_angle(st.ref.rot, goal.rot) > p.ori_tolerance:
            return False
        if st.cmd.tool_speed > slack * p.pos_tolerance / 0.1:
            return False
        # The elbow too: right after a joint-space move the joints are at rest, but the swivel dynamics
        # has yet to run (sdot_want NaN) and turn the elbow to its preferred swivel, starting slowly
        # (its acceleration is limited). A swivel its dynamics asks to move that stands for
        # SETTLE_DWELL_S is held by the limits: settled too.
        settle = slack * p.settle_swivel_rate
        ref = st.ref
        if math.isnan(ref.sdot_want) or abs(ref.sdot) > settle:
            return False
        if abs(ref.sdot_want) > settle and st.time - ref.swivel_moved_at < SETTLE_DWELL_S:
            if slack <= 1.0 or st.time - ref.want_over_since >= WANT_HOLD_S:
                return False
        max_vel = self.command.bounds.max_vel
        return float(np.max(np.abs(st.cmd.qd) / max_vel)) <= slack * REST_SPEED_SHARE and \
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
        local = self.view.local
        if local.floor < clear.distance:  # an obstacle left out may be nearer: report the bound
            clear = Clearance(local.floor, -1, LEFT_OUT)
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
        return self.redundancy.forces(self._state(), self.view.index.reach_scene.scene, self.params)

    def _state(self) -> CoreState:
        if self._st is None:
            raise InvalidInputError("reset(q) must be called first", field="q")
        return self._st

