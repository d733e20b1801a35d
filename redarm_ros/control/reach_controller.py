"""Reaching controller: attractor dynamics for the hand, swivel dynamics for the elbow, closed-form IK.

One :meth:`ReachController.step` (forward Euler, ``dt`` in s) does, in this order:

1. heading direction (azimuth, elevation) of the end effector: target attractor plus obstacle
   repellers (:class:`~redarm_ros.control.attractor.HeadingDynamics`);
2. speed along the heading from a smooth profile that stops at the target
   (:class:`~redarm_ros.control.attractor.SpeedProfile`);
3. hand orientation: rotation-vector attractor towards the goal orientation, optionally turned so
   that the tool axis follows the path tangent far from the goal (eq. 20-21 in rotation-vector form);
4. swivel angle: ``tau ds/dt = l1 h(s_des - s) + l_obs F_obs + l_sing F_sing + l_lim F_lim``
   (:class:`~redarm_ros.control.swivel_dynamics.SwivelDynamics`), ``s_des`` the preferred elbow;
5. joint positions from the closed-form IK at the new pose and swivel: the in-limit solution nearest
   (in time at the joint velocity limits) to the previous one, so there is no branch flip; a step that
   would exceed the joint velocity limits is shortened; if no continuous solution exists at that
   swivel, nearby swivels are searched; if none, the arm holds.

Units: m, rad, s. Quaternions are (w, x, y, z). The core is pure Python/numpy (no ROS); the
controller node converts messages to these calls.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from redarm_ros.control.attractor import (
    HeadingDynamics,
    HeadingParams,
    SpeedParams,
    SpeedProfile,
    direction,
    heading_angles,
)
from redarm_ros.control.elbow import ArmGeometry, ElbowCircle, elbow_circle
from redarm_ros.control.joint_limits import brake_step, braking_speed, velocity_bounds
from redarm_ros.control.obstacles import (
    TABLE,
    ArmCapsules,
    Clearance,
    Scene,
    links_clearance,
    min_distance,
)
from redarm_ros.control.rotations import (
    matrix_from_quat,
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
from redarm_ros.control.swivel_dynamics import SwivelDynamics, SwivelForces, SwivelParams, wrap_angle
from redarm_ros.errors import ConfigError, InvalidInputError, UnreachableError

LOG = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class Phase(enum.StrEnum):
    """What the controller is doing (string values match ``ControllerState`` constants)."""

    IDLE = "IDLE"  # no goal since reset: holds
    REACHING = "REACHING"  # moving towards the goal
    REACHED = "REACHED"  # within tolerance of the goal (keeps tracking it)
    HOLDING = "HOLDING"  # a goal is set but no continuous, in-limit step exists: holds
    REJECTED = "REJECTED"  # the last goal was rejected: stops smoothly and holds


class GoalStatus(enum.Enum):
    """Outcome of :meth:`ReachController.set_goal` (IKStatus-like)."""

    ACCEPTED = "accepted"
    OUT_OF_REACH = "out_of_reach"
    NO_SOLUTION_IN_LIMITS = "no_solution_in_limits"
    IN_COLLISION = "in_collision"
    INVALID_INPUT = "invalid_input"
    NOT_READY = "not_ready"


@dataclass(frozen=True)
class GoalCheck:
    """Verdict on a goal pose: ``status``, human-readable ``message``; for accepted goals the swivel
    range that is reachable and collision-free was seen (``free_swivels``: count of scanned swivels)."""

    status: GoalStatus
    message: str = ""
    free_swivels: int = 0
    best_swivel: float | None = None

    @property
    def accepted(self) -> bool:
        """True if the goal was accepted."""
        return self.status is GoalStatus.ACCEPTED


@dataclass(frozen=True)
class StepResult:
    """Outcome of one control step.

    q: joint positions to command (rad), always within limits. phase: :class:`Phase`.
    swivel / swivel_desired: current and preferred swivel angle (rad, paper convention eq. 13-16).
    clearance: minimum signed distance arm-obstacles/table (m, > 0 is collision-free) with the
    closest ``clearance_link`` (0 base, 1 upper arm, 2 forearm, 3 hand) and ``clearance_obstacle``
    (index in the scene, -1 table). distance_to_goal (m) and orientation_error (rad) of the commanded
    pose (inf without a goal). heading: (azimuth, elevation) of the end-effector heading (rad).
    speed: end-effector speed (m/s). position: commanded tool position (m). message: why it holds.
    """

    q: np.ndarray
    phase: Phase
    swivel: float
    swivel_desired: float
    clearance: float
    clearance_link: int
    clearance_obstacle: int
    distance_to_goal: float
    orientation_error: float
    heading: tuple[float, float]
    speed: float
    position: Vec3
    message: str = ""


@dataclass(frozen=True)
class ControllerParams:
    """Controller parameters (units in brackets).

    dt [s]: nominal step (``step()`` takes the actual one; it is clamped to ``max_dt``).
    heading, swivel, speed: parameters of the three dynamics (see their classes).
    capsules: link radii of the collision model.
    preferred_swivel [rad]: the swivel attractor ``s_des``. With ``swivel_reference="high"`` it is an
    offset from the highest elbow position on the circle (0 = elbow as high as possible, the natural
    posture of a PA10 on a table, whose shoulder pitch of +/-91 deg keeps the elbow above the
    shoulder); ``"low"``: offset from the lowest elbow position (the human-like low elbow of an arm
    mounted above the table); for both, positive offsets turn the elbow one way around the
    shoulder-wrist axis (right-handed about ``n``); ``"absolute"``: the swivel angle of eq. 13-16.
    swivel_mode: ``"dynamics"`` (eq. 31) or ``"fixed"`` (keep the swivel of reset(): redundancy unused).
    lam_ori [1/s], max_ori_rate [rad/s]: orientation attractor rate and its clamp.
    tangent_weight [0..1], tangent_distance [m]: how much the tool axis follows the path tangent
    (eq. 20-21) while farther than ``tangent_distance`` from the goal (blended to the goal orientation
    nearer).
    final_distance [m]: within this distance the motion direction blends into the straight line to
    the goal (the heading dynamics is singular at the goal).
    workspace_margin [m]: within this distance of the inner shell of the wrist workspace (elbow at
    its joint limit) or of the outer shell (arm stretched) the motion slides along the shell.
    pos_tolerance [m], ori_tolerance [rad]: REACHED when both errors are below.
    flip_ratio: a joint step above ``flip_ratio * max_vel * dt`` is a branch change, never taken.
    swivel_search_step [rad], swivel_search_count: search around the swivel when the IK has no
    continuous solution there.
    goal_scan: number of swivel samples used to check a goal.
    max_ori_acc [rad/s^2], max_swivel_acc [rad/s^2]: how fast the orientation rate and the swivel
    rate may change (they would otherwise jump when a goal is set or an obstacle appears).
    collision_margin [m]: the guard never commands a configuration whose clearance is below this
    margin and lower than the clearance of the previous command; it brakes and holds instead.
    elbow_priority_clearance [m]: below this clearance of the upper arm/forearm the elbow has
    priority over the hand (the hand step is shortened so that the swivel moves at its full rate).
    stop_share (0..1]: the hand is slowed so that the clearance to the obstacles the arm would lose
    while braking at its joint acceleration limits stays below this share of the clearance left.
    joint_brake_share (0..1]: share of the joints' acceleration limits that the hand may use to speed
    up or brake along its path (the rest absorbs the orientation and swivel motion and the path's
    bends); it bounds the speed filter's acceleration and the speed from which it can stop at the goal.
    guard_step [m]: the guard samples the braking path every this much travel of the arm, and asks
    that much more clearance at the samples.
    slide_band [m]: within this clearance of the hand to an obstacle or the table, the part of the
    motion towards it is removed (fully at contact): the hand slides along it.
    max_lag [s]: when the command lags the reference by more than this (at full joint speed), the
    hand speed is capped.
    unfold_pitch [rad]: (shoulder, elbow, wrist) pitch of the posture the arm unfolds to, in joint
    space, when it starts stretched (no elbow circle, e.g. after homing to q = 0).
    """

    dt: float = 0.01
    heading: HeadingParams = field(default_factory=HeadingParams)
    swivel: SwivelParams = field(default_factory=SwivelParams)
    speed: SpeedParams = field(default_factory=SpeedParams)
    capsules: ArmCapsules = field(default_factory=ArmCapsules)
    preferred_swivel: float = 0.0
    swivel_reference: str = "high"
    swivel_mode: str = "dynamics"
    lam_ori: float = 5.0
    max_ori_rate: float = 1.5
    tangent_weight: float = 0.0
    tangent_distance: float = 0.15
    final_distance: float = 0.02
    workspace_margin: float = 0.05
    pos_tolerance: float = 1e-3
    ori_tolerance: float = 0.01
    max_dt: float = 0.05
    flip_ratio: float = 10.0
    swivel_search_step: float = 0.03
    swivel_search_count: int = 10
    goal_scan: int = 72
    max_ori_acc: float = 6.0
    max_swivel_acc: float = 8.0
    collision_margin: float = 0.0
    elbow_priority_clearance: float = 0.08
    stop_share: float = 0.5
    unfold_pitch: tuple[float, float, float] = (0.4, 1.2, 1.0)
    joint_brake_share: float = 0.5
    max_lag: float = 0.03
    guard_step: float = 0.005
    slide_band: float = 0.03

    def __post_init__(self) -> None:
        if self.swivel_reference not in ("high", "low", "absolute"):
            raise ConfigError(f"swivel_reference must be 'high', 'low' or 'absolute', got "
                              f"{self.swivel_reference!r}",
                              field="swivel_reference", value=self.swivel_reference)
        if self.swivel_mode not in ("dynamics", "fixed"):
            raise ConfigError(f"swivel_mode must be 'dynamics' or 'fixed', got {self.swivel_mode!r}",
                              field="swivel_mode", value=self.swivel_mode)
        for name in ("dt", "lam_ori", "max_ori_rate", "tangent_distance", "final_distance",
                     "workspace_margin", "pos_tolerance", "ori_tolerance", "max_dt", "flip_ratio",
                     "swivel_search_step", "max_ori_acc", "max_swivel_acc", "elbow_priority_clearance",
                     "stop_share", "joint_brake_share", "max_lag", "guard_step", "slide_band"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name} must be finite and > 0, got {v!r}", field=name, value=v)
        if not (0.0 <= self.tangent_weight <= 1.0):
            raise ConfigError("tangent_weight must be in [0, 1]", field="tangent_weight",
                              value=self.tangent_weight)
        for name in ("joint_brake_share", "stop_share"):
            if getattr(self, name) > 1.0:
                raise ConfigError(f"{name} must be in (0, 1]", field=name, value=getattr(self, name))
        if not (math.isfinite(self.collision_margin) and self.collision_margin >= 0.0):
            raise ConfigError("collision_margin must be finite and >= 0", field="collision_margin",
                              value=self.collision_margin)
        try:
            pitch = tuple(float(v) for v in self.unfold_pitch)
        except (TypeError, ValueError):
            pitch = ()
        if len(pitch) != 3 or not all(math.isfinite(v) for v in pitch) or abs(pitch[1]) < 0.2:
            raise ConfigError("unfold_pitch must be 3 finite angles (rad) with an elbow pitch of at least "
                              "0.2 rad", field="unfold_pitch", value=self.unfold_pitch)
        object.__setattr__(self, "unfold_pitch", pitch)
        if not math.isfinite(self.preferred_swivel):
            raise ConfigError("preferred_swivel must be finite", field="preferred_swivel",
                              value=self.preferred_swivel)

    def with_(self, **changes: Any) -> ControllerParams:
        """A copy with some fields changed."""
        return replace(self, **changes)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> ControllerParams:
        """Parameters from a (YAML-like) dict; nested dicts for ``heading``, ``swivel``, ``speed`` and
        ``capsules``, e.g. ``{"preferred_swivel": 0.3, "speed": {"v_max": 0.25}}``. Missing keys keep
        their defaults.

        Raises:
            ConfigError: unknown key or bad value (the message names it).
        """
        if not d:
            return cls()
        if not isinstance(d, dict):
            raise ConfigError("controller parameters must be a mapping", value=d)
        nested = {"heading": HeadingParams, "swivel": SwivelParams, "speed": SpeedParams,
                  "capsules": ArmCapsules}
        known = {f.name for f in fields(cls)}
        kwargs: dict[str, Any] = {}
        for key, value in d.items():
            if key not in known:
                raise ConfigError(f"unknown controller parameter {key!r}; known: {sorted(known)}", field=key)
            if key in nested:
                sub = nested[key]
                sub_known = {f.name for f in fields(sub)}
                if not isinstance(value, dict):
                    raise ConfigError(f"{key} must be a mapping", field=key, value=value)
                bad = set(value) - sub_known
                if bad:
                    raise ConfigError(f"unknown {key} parameter(s) {sorted(bad)}; known: {sorted(sub_known)}",
                                      field=f"{key}.{sorted(bad)[0]}")
                vals = {k: (tuple(v) if isinstance(v, list) else v) for k, v in value.items()}
                try:
                    kwargs[key] = sub(**vals)
                except InvalidInputError as exc:
                    raise ConfigError(f"{key}: {exc}", field=f"{key}.{exc.field}", value=exc.value) from exc
            else:
                kwargs[key] = value
        return cls(**kwargs)


def _swivel_low(circle: ElbowCircle) -> float | None:
    """Swivel (rad) of the lowest elbow position on the circle; None if the circle is horizontal."""
    az, bz = circle.a[2], circle.b[2]
    if math.hypot(az, bz) < 0.05:
        return None
    return math.atan2(-bz, -az)


class ReachController:
    """Reach Cartesian goals with a 7-DOF swivel arm by attractor dynamics (see module docstring).

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
        if getattr(arm, "n", None) != 7 or not hasattr(arm, "elbow_circle"):
            raise ConfigError(f"ReachController needs a 7-DOF swivel arm, got {getattr(arm, 'name', arm)!r}",
                              field="arm")
        self.arm = arm
        self.params = params or ControllerParams()
        self.scene = scene if scene is not None else Scene()
        self.geom = ArmGeometry.from_arm(arm)
        self.swivel_dyn = SwivelDynamics(self.params.swivel)
        self.heading_dyn = HeadingDynamics(self.params.heading)
        self.speed_profile = SpeedProfile(self.params.speed)
        self._lower = np.asarray(arm.lower, float)
        self._upper = np.asarray(arm.upper, float)
        self._max_vel = np.asarray(arm.max_vel, float)
        self._inv_vel = 1.0 / self._max_vel
        self._max_acc = np.asarray(arm.max_acc, float)
        self._wide = [j for j in range(7) if self._upper[j] - self._lower[j] > 2.0 * math.pi]
        self._d_inner, self._d_outer = _wrist_shell(arm, self.geom)
        self._q: np.ndarray | None = None
        self._goal_p: Vec3 | None = None
        self._goal_q: Quat | None = None
        self._phase = Phase.IDLE
        self._message = ""
        self._pos: Vec3 = (0.0, 0.0, 0.0)
        self._rot: Quat = (1.0, 0.0, 0.0, 0.0)
        self._s = 0.0
        self._s_des = 0.0
        self._s_fixed = 0.0
        self._phi = 0.0
        self._theta = 0.0
        self._v = 0.0
        self._a = 0.0
        self._v_cap: float | None = None
        self._turn = (0.0, 0.0)  # heading rates applied in the last step (rad/s)
        self._ratio = 0.0  # largest joint speed / limit in the last step
        self._circle: ElbowCircle | None = None
        self._clear = Clearance(math.inf, -1, -1)
        # Two joint states: the reference ``_q`` (IK of the dynamics' pose, velocity-limited) and the
        # command ``_qc`` that tracks it within the velocity and acceleration limits (what is sent).
        self._qc = np.zeros(7)
        self._qd = np.zeros(7)  # command velocity of the last step (rad/s)
        self._qrd = np.zeros(7)  # reference velocity of the last step (rad/s)
        self._v_ref = 0.0  # tool speed of the reference in the last step (m/s)
        self._cpos: Vec3 = (0.0, 0.0, 0.0)  # tool pose of the command (m, w x y z)
        self._ctool_speed = 0.0  # m/s
        self._crot: Quat = (1.0, 0.0, 0.0, 0.0)
        self._w_ori = 0.0  # orientation rate of the last step (rad/s)
        self._sdot = 0.0  # swivel rate of the last step (rad/s)
        self._obs_clear = math.inf  # clearance to the obstacles (not the table) of the last command (m)
        self._obs_rate = 0.0  # how fast it shrank (m/s, > 0 approaching)
        self._obstacles_only = Scene(self.scene.obstacles, None)
        self._unfold: np.ndarray | None = None  # joint-space unfold target (rad) while unfolding

    # ------------------------------------------------------------------ properties
    @property
    def phase(self) -> Phase:
        """Current :class:`Phase`."""
        return self._phase

    @property
    def q(self) -> np.ndarray | None:
        """Last commanded joint positions (rad), None before :meth:`reset`."""
        return None if self._q is None else self._qc.copy()

    @property
    def swivel(self) -> float:
        """Current swivel angle (rad)."""
        return self._s

    @property
    def elbow_circle(self) -> ElbowCircle | None:
        """Elbow circle of the current commanded pose (centre, normal, radius, basis), for display."""
        return self._circle

    @property
    def heading_direction(self) -> Vec3:
        """Unit vector (base frame) of the current end-effector heading."""
        return direction(self._phi, self._theta)

    @property
    def goal(self) -> tuple[Vec3, Quat] | None:
        """Active goal as (position m, quaternion w,x,y,z) or None."""
        if self._goal_p is None or self._goal_q is None:
            return None
        return self._goal_p, self._goal_q

    # ------------------------------------------------------------------ set-up
    def reset(self, q: Any) -> None:
        """Start from measured joint positions ``q`` (rad); clears the goal (phase IDLE).

        Raises:
            InvalidInputError: wrong length or NaN.
            JointLimitError-free: positions slightly outside the limits are clamped into them.
        """
        qa = self.arm.check_q(q)
        qa = np.clip(qa, self._lower, self._upper)
        T = np.asarray(self.arm.fk(qa), float)
        self._q = qa
        self._pos = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        self._rot = quat_from_matrix(T[:3, :3])
        self._s = float(self.arm.swivel(qa))
        self._s_fixed = self._s
        self._s_des = self._s
        self._v = 0.0
        self._a = 0.0
        self._v_cap = None
        self._turn = (0.0, 0.0)
        self._ratio = 0.0
        self._goal_p = None
        self._goal_q = None
        self._phase = Phase.IDLE
        self._message = ""
        self._qc = qa.copy()
        self._qd = np.zeros(7)
        self._qrd = np.zeros(7)
        self._cpos, self._crot = self._pos, self._rot
        self._ctool_speed = 0.0
        self._w_ori = 0.0
        self._sdot = 0.0
        self._unfold = None
        self._obs_rate = 0.0
        try:
            self._circle = elbow_circle(self.geom, T)
        except UnreachableError:  # singular reset pose (arm stretched): no circle yet, unfold first
            self._circle = None
        self._clear = min_distance(self.arm, qa, self.scene, self.params.capsules)
        self._obs_clear = min_distance(self.arm, qa, self._obstacles_only, self.params.capsules).distance

    def set_scene(self, scene: Scene) -> GoalCheck | None:
        """Replace the obstacles (e.g. from the node's MarkerArray). Re-checks the active goal; if it
        is now inside an obstacle it is dropped (phase REJECTED, the arm stops) and the failing
        :class:`GoalCheck` is returned; otherwise returns None."""
        if not isinstance(scene, Scene):
            raise InvalidInputError("scene must be a Scene", field="scene", value=scene)
        self.scene = scene
        self._obstacles_only = Scene(scene.obstacles, None)
        if self._q is not None:
            self._clear = min_distance(self.arm, self._qc, scene, self.params.capsules)
            self._obs_clear = min_distance(self.arm, self._qc, self._obstacles_only,
                                           self.params.capsules).distance
            self._obs_rate = 0.0
        if self._goal_p is not None and self._goal_q is not None:
            T = self._goal_matrix()
            check = self.check_goal(T)
            if not check.accepted:
                self._reject(check)
                return check
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
        try:
            Tl = self.arm.check_pose(T)
        except InvalidInputError as exc:
            return GoalCheck(GoalStatus.INVALID_INPUT, str(exc))
        Tn = np.asarray(Tl, float)
        try:
            circle = elbow_circle(self.geom, Tn)
        except UnreachableError as exc:
            return GoalCheck(GoalStatus.OUT_OF_REACH, f"goal out of reach: {exc}")
        caps = self.params.capsules
        p = circle.tool
        for j, o in enumerate(self.scene.obstacles):
            if o.signed_distance(p) < 0.0:
                return GoalCheck(GoalStatus.IN_COLLISION, f"goal position lies inside obstacle {j} "
                                 f"{o.name or type(o).__name__.lower()!r}")
        hand = links_clearance(circle.key_points(0.0), self.scene, caps, (3,))
        if hand.distance < 0.0:
            what = "the table" if hand.obstacle == TABLE else f"obstacle {hand.obstacle}"
            return GoalCheck(GoalStatus.IN_COLLISION,
                             f"the hand at the goal would collide with {what} "
                             f"(clearance {hand.distance:.3f} m)")
        n = max(8, int(self.params.goal_scan))
        in_limits = 0
        free = 0
        best: tuple[float, float] | None = None
        for k in range(n):
            s = -math.pi + 2.0 * math.pi * k / n
            sols = self.arm.ik(Tn, s)
            if sols.shape[0] == 0:
                continue
            in_limits += 1
            c = links_clearance(circle.key_points(s), self.scene, caps, (1, 2)).distance
            if c > 0.0:
                free += 1
                if best is None or c > best[1]:
                    best = (s, c)
        if in_limits == 0:
            return GoalCheck(GoalStatus.NO_SOLUTION_IN_LIMITS,
                             f"no IK solution within the joint limits at any of {n} swivel angles")
        if free == 0:
            return GoalCheck(GoalStatus.IN_COLLISION,
                             "every elbow position on the swivel circle collides with the scene")
        return GoalCheck(GoalStatus.ACCEPTED, "", free, None if best is None else best[0])

    def set_goal(self, T: Any) -> GoalCheck:
        """Set a new goal pose (4x4 homogeneous, base frame, m). A goal mid-motion retargets smoothly
        (heading and speed are continuous). A rejected goal stops the arm smoothly (phase REJECTED).
        """
        if self._q is None:
            return GoalCheck(GoalStatus.NOT_READY, "reset(q) must be called before set_goal()")
        check = self.check_goal(T)
        if not check.accepted:
            self._reject(check)
            return check
        Tn = np.asarray(T, float)
        self._goal_p = (float(Tn[0, 3]), float(Tn[1, 3]), float(Tn[2, 3]))
        self._goal_q = quat_from_matrix(Tn[:3, :3])
        if self._v < 1e-6:  # starting from rest: head straight at the goal
            gp, cp = self._goal_p, self._pos
            self._phi, self._theta = heading_angles((gp[0] - cp[0], gp[1] - cp[1], gp[2] - cp[2]), self._phi)
            self._turn = (0.0, 0.0)
        self._phase = Phase.REACHING
        self._message = ""
        return check

    def stop(self) -> None:
        """Drop the goal; the arm decelerates smoothly and holds (phase IDLE)."""
        self._goal_p = None
        self._goal_q = None
        self._phase = Phase.IDLE
        self._message = "stopped"

    def _reject(self, check: GoalCheck) -> None:
        LOG.info("goal rejected: %s", check.message)
        self._goal_p = None
        self._goal_q = None
        self._phase = Phase.REJECTED
        self._message = check.message

    def _goal_matrix(self) -> np.ndarray:
        assert self._goal_p is not None and self._goal_q is not None
        T = np.eye(4)
        T[:3, :3] = matrix_from_quat(self._goal_q)
        T[:3, 3] = self._goal_p
        return T

    # ------------------------------------------------------------------ the step
    def step(self, dt: float | None = None) -> StepResult:
        """Advance the dynamics by ``dt`` seconds (default ``params.dt``) and return the command.

        Raises:
            InvalidInputError: called before :meth:`reset`, or a non-finite/negative dt.
        """
        if self._q is None:
            raise InvalidInputError("reset(q) must be called before step()", field="q")
        p = self.params
        dt = p.dt if dt is None else float(dt)
        if not math.isfinite(dt) or dt < 0.0:
            raise InvalidInputError(f"dt must be finite and >= 0, got {dt!r}", field="dt", value=dt)
        dt = min(dt, p.max_dt)
        if dt == 0.0:
            return self._result()
        if (self._goal_p is None and self._v <= 0.0) or (self._circle is None and self._goal_p is None):
            self._unfold = None
            if np.any(self._qd != 0.0) or not np.array_equal(self._q, self._qc):
                self._qrd = np.zeros(7)  # the reference stands: the command brakes onto it
                self._track(dt)
            return self._result()
        if self._circle is None or self._unfold is not None:
            # Stretched arm (e.g. homed to q = 0): no elbow circle, so no swivel and an ill-conditioned
            # IK. Unfold in joint space to a bent posture first, then reach from rest.
            self._unfold_step(dt)
            self._update_phase()
            return self._result()

        pos, rot = self._pos, self._rot
        goal_p = self._goal_p
        obstacles = self.scene.obstacles
        # 1-2. heading and speed
        if goal_p is not None:
            dist = math.dist(pos, goal_p)
            self._phi, self._theta, rates = self.heading_dyn.step(self._phi, self._theta, dt, pos, goal_p,
                                                                  obstacles, self._turn)
            self._turn = rates.applied
            cap = self._v_cap
            if rates.speed_factor < 1.0:
                v_obs = rates.speed_factor * self.speed_profile.params.v_max
                cap = v_obs if cap is None else min(cap, v_obs)
            v_stop = self._joint_braking_speed(dist)
            if v_stop is not None:
                cap = v_stop if cap is None else min(cap, v_stop)
            if self._obs_rate > 1e-4 and self._v > 1e-3:
                # Stopping distance: the clearance the arm would lose while its joints brake at their
                # acceleration limits (~ rate * t_stop / 2, which grows with the square of the speed)
                # must stay within stop_share of the clearance left; the swivel meanwhile turns the
                # elbow away.
                t_stop = float(np.max(np.abs(self._qd) / self._max_acc))
                loss = self._obs_rate * (0.5 * t_stop + dt)
                room = p.stop_share * max(self._obs_clear - p.collision_margin, 0.0)
                if loss > room:
                    v_stop = self._v * math.sqrt(room / loss)
                    cap = v_stop if cap is None else min(cap, v_stop)
            self._v, self._a = self.speed_profile.step(self._v, self._a, dist, dt, cap, self._hand_acc())
        else:  # no goal: decelerate along the current heading (jerk-limited, like any speed change)
            self._v, self._a = self.speed_profile.step(self._v, self._a, math.inf, dt, 0.0)
            if self._v < 1e-4:
                self._v, self._a = 0.0, 0.0
        e = direction(self._phi, self._theta)
        if goal_p is not None and dist < p.final_distance:
            # Final approach: blend towards the straight line so that a heading which ended up
            # opposite to the target (an unstable but balanced state) cannot carry the hand away.
            w = 1.0 - dist / p.final_distance
            g = ((goal_p[0] - pos[0]) / dist, (goal_p[1] - pos[1]) / dist, (goal_p[2] - pos[2]) / dist) \
                if dist > 1e-12 else e
            m = ((1.0 - w) * e[0] + w * g[0], (1.0 - w) * e[1] + w * g[1], (1.0 - w) * e[2] + w * g[2])
            mn = math.sqrt(m[0] ** 2 + m[1] ** 2 + m[2] ** 2)
            e = (m[0] / mn, m[1] / mn, m[2] / mn) if mn > 1e-9 else g
        e = self._workspace_slide(e, pos, rot)
        if goal_p is None or dist > p.final_distance:  # (the goal itself was checked clear)
            e = self._obstacle_slide(e)
        step_len = self._v * dt
        if goal_p is not None:
            step_len = min(step_len, dist)
        new_pos = (pos[0] + step_len * e[0], pos[1] + step_len * e[1], pos[2] + step_len * e[2])
        # 3. orientation
        new_rot = rot
        if self._goal_q is not None:
            target_rot = self._orientation_target(e, dist if goal_p is not None else 0.0)
            w = rotvec_between(rot, target_rot)
            wn = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
            # Rate of the attractor, clamped, and changed by at most max_ori_acc per second (braking
            # in time): without this the rate jumps when a goal is set.
            ori_acc = self._joint_share_acc(self._w_ori, p.max_ori_acc)
            rate = min(p.lam_ori * wn, p.max_ori_rate, float(braking_speed(wn, ori_acc, dt)))
            rate = max(0.0, min(rate, self._w_ori + ori_acc * dt))
            gain = min(rate * dt / wn, 1.0) if wn > 1e-12 else 0.0
            new_rot = quat_normalize(quat_mul(quat_from_rotvec((gain * w[0], gain * w[1], gain * w[2])), rot))
        # 4-5. swivel and IK (with velocity scaling / swivel search / hold)
        self._advance(new_pos, new_rot, dt)
        self._update_phase()
        return self._result()

    def _hand_acc(self) -> float | None:
        """Largest hand acceleration (m/s^2) along the path that keeps every joint within
        ``joint_brake_share`` of its acceleration limit, with joint speeds proportional to the hand
        speed (``dq/ds = qdot / v``); None when the hand is (nearly) at rest."""
        a = self._joint_share_acc(self._v_ref, math.inf)
        return None if math.isinf(a) else a

    def _joint_share_acc(self, rate: float, default: float) -> float:
        """Largest rate of change of ``rate`` (a hand speed or an orientation rate) that keeps every
        joint within ``joint_brake_share`` of its acceleration limit, the joint velocities of the last
        reference step taken as proportional to ``rate``; ``default`` caps it and is used at rest."""
        if rate < 1e-4:  # from rest: a gentle first step, the ratio is measured from the next one
            return min(default, 0.1 * float(np.min(self._max_acc)))
        qd = np.abs(self._qrd)
        mask = qd > 1e-6
        if not np.any(mask):
            return default
        a = float(np.min(self._max_acc[mask] / qd[mask])) * rate * self.params.joint_brake_share
        return max(min(a, default), 1e-3)

    def _joint_braking_speed(self, dist: float) -> float | None:
        """Hand speed (m/s) from which the hand can still stop within the remaining ``dist`` (m) at the
        acceleration of :meth:`_hand_acc` (the speed filter's own ``a_max`` would outrun slow joints)."""
        a_hand = self._hand_acc()
        if a_hand is None:
            return None
        return math.sqrt(2.0 * a_hand * max(dist, 0.0))

    def _workspace_slide(self, e: Vec3, pos: Vec3, rot: Quat) -> Vec3:
        """Remove the part of the motion direction that would take the wrist through the inner shell
        (elbow at its joint limit) or the outer shell (arm stretched) of the workspace, smoothly within
        ``workspace_margin`` of the shell: the hand then slides along the shell."""
        m = self.params.workspace_margin
        w_t = self.geom.wrist_in_tool
        off = quat_rotate(rot, w_t)
        ps = self.geom.shoulder
        r = (pos[0] + off[0] - ps[0], pos[1] + off[1] - ps[1], pos[2] + off[2] - ps[2])
        d = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
        if d < 1e-9:
            return e
        r = (r[0] / d, r[1] / d, r[2] / d)
        radial = e[0] * r[0] + e[1] * r[1] + e[2] * r[2]
        w = 0.0
        if radial < 0.0:
            w = _smoothstep((self._d_inner + m - d) / m)
        elif radial > 0.0:
            w = _smoothstep((d - (self._d_outer - m)) / m)
        if w <= 0.0:
            return e
        f = w * radial
        v = (e[0] - f * r[0], e[1] - f * r[1], e[2] - f * r[2])
        n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if n < 1e-6:
            return e
        return (v[0] / n, v[1] / n, v[2] / n)

    def _obstacle_slide(self, e: Vec3) -> Vec3:
        """Within ``slide_band`` of an obstacle or the table, remove (smoothly, fully at contact) the
        part of the motion direction that takes the hand closer to it: the hand slides along the
        surface instead of pressing into it, where the guard would stop it for good."""
        band = self.params.slide_band
        if self._circle is None:
            return e
        kp = [tuple(float(c) for c in v) for v in self._circle.key_points(self._s)]
        caps = self.params.capsules
        c0 = links_clearance(kp, self.scene, caps, (3,)).distance
        if c0 >= band:
            return e
        h = 1e-3
        g = []
        for axis in range(3):
            shifted = [list(v) for v in kp]
            shifted[3][axis] += h
            shifted[4][axis] += h
            g.append((links_clearance(shifted, self.scene, caps, (3,)).distance - c0) / h)
        gn = math.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2)
        if gn < 1e-6:
            return e
        g = [gi / gn for gi in g]
        toward = e[0] * g[0] + e[1] * g[1] + e[2] * g[2]
        if toward >= 0.0:
            return e
        w = _smoothstep((band - c0) / band)
        v = (e[0] - w * toward * g[0], e[1] - w * toward * g[1], e[2] - w * toward * g[2])
        n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if n < 1e-6:
            return e
        return (v[0] / n, v[1] / n, v[2] / n)

    def _orientation_target(self, e: Vec3, dist: float) -> Quat:
        """Goal orientation, turned so that the tool axis leans towards the heading far from the goal."""
        assert self._goal_q is not None
        p = self.params
        if p.tangent_weight <= 0.0 or self._v < 1e-3:
            return self._goal_q
        w = p.tangent_weight * max(0.0, min(1.0, (dist - p.tangent_distance) / p.tangent_distance))
        if w <= 0.0:
            return self._goal_q
        g = quat_rotate(self._goal_q, (0.0, 0.0, 1.0))  # tool approach axis at the goal
        a = slerp_vectors(g, e, w)
        return quat_normalize(quat_mul(quat_between_vectors(g, a), self._goal_q))

    def _desired_swivel(self, circle: ElbowCircle) -> float:
        p = self.params
        if p.swivel_reference == "absolute":
            return wrap_angle(p.preferred_swivel)
        low = _swivel_low(circle)
        if low is None:
            return self._s_des
        ref = low if p.swivel_reference == "low" else low + math.pi
        return wrap_angle(ref + p.preferred_swivel)

    def _limit_margins(self, T: np.ndarray, circle: ElbowCircle, s: float, q_ref: np.ndarray
                       ) -> tuple[float, float, float] | None:
        """Joint-limit margins (rad) at s, s+eps, s-eps on the current branch, if near a limit."""
        m0 = self._margin(q_ref)
        if m0 >= self.params.swivel.lim_threshold:
            return None
        eps = self.params.swivel.eps
        out = [m0]
        for ds in (eps, -eps):
            sols = self.arm.ik(T, s + ds)
            pick = self._select(sols, q_ref, 1.0)
            out.append(self._margin(pick[0]) if pick is not None else -1.0)
        return out[0], out[1], out[2]

    def _margin(self, q: np.ndarray) -> float:
        return float(np.min(np.minimum(q - self._lower, self._upper - q)))

    def _select(self, sols: np.ndarray, q_ref: np.ndarray, dt: float) -> tuple[np.ndarray, float] | None:
        """Solution nearest to q_ref in time at the velocity limits, and its ratio to the limit over dt."""
        if sols.shape[0] == 0:
            return None
        sols = sols.copy()
        for j in self._wide:  # pick the 2*pi copy nearest to the reference within the limits
            k = np.round((sols[:, j] - q_ref[j]) / (2.0 * math.pi))
            cand = sols[:, j] - 2.0 * math.pi * k
            ok = (cand >= self._lower[j]) & (cand <= self._upper[j])
            sols[ok, j] = cand[ok]
        ratios = np.max(np.abs(sols - q_ref) * self._inv_vel, axis=1) / dt
        i = int(np.argmin(ratios))
        return sols[i], float(ratios[i])

    def _advance(self, new_pos: Vec3, new_rot: Quat, dt: float) -> bool:
        """Swivel dynamics + IK for the proposed pose; commits the state and returns True on success."""
        p = self.params
        q_prev = self._q
        assert q_prev is not None
        pos0, rot0, s0 = self._pos, self._rot, self._s
        for _attempt in range(4):
            T = np.eye(4)
            T[:3, :3] = matrix_from_quat(new_rot)
            T[:3, 3] = new_pos
            try:
                circle = elbow_circle(self.geom, T)
            except UnreachableError:
                circle = None
            if circle is None:  # the heading would leave the workspace: shorten the step
                new_pos, new_rot = _blend(pos0, rot0, new_pos, new_rot, 0.5)
                self._v *= 0.5
                continue
            # swivel dynamics
            if p.swivel_mode == "fixed":
                s_des = self._s_fixed
                s_new = self._s_fixed
            else:
                s_des = self._desired_swivel(circle)
                margins = self._limit_margins(T, circle, s0, q_prev)
                forces = self.swivel_dyn.forces(circle, s0, self.scene, p.capsules, margins)
                s_new = self.swivel_dyn.step(s0, s_des, dt, forces)
                # The swivel rate changes by at most max_swivel_acc per second.
                sd = wrap_angle(s_new - s0) / dt
                s_acc = self._joint_share_acc(abs(self._sdot), p.max_swivel_acc)
                sd = max(self._sdot - s_acc * dt, min(self._sdot + s_acc * dt, sd))
                s_new = wrap_angle(s0 + sd * dt)
                if forces.clearance < p.elbow_priority_clearance and s_new != s0:
                    # An obstacle is close to the upper arm/forearm: the hand yields to the elbow.
                    shortened = self._yield_hand(pos0, rot0, new_pos, new_rot, s_new, q_prev, dt)
                    if shortened is not None:
                        new_pos, new_rot, T, circle = shortened
            self._s_des = s_des
            pick = self._select(self.arm.ik(T, s_new), q_prev, dt)
            if (pick is None or pick[1] > 1.0 + 1e-9) and s_new != s0:
                # Too fast for a joint (or no solution there): the elbow yields first, the hand path
                # has priority.
                yielded = self._yield_swivel(T, s0, s_new, q_prev, dt, math.inf if pick is None else pick[1])
                if yielded is not None and (pick is None or yielded[2] < pick[1]):
                    s_new, pick = yielded[0], (yielded[1], yielded[2])
            if pick is None or pick[1] > p.flip_ratio:
                pick, s_new = self._search_swivel(T, s_new, q_prev, dt)
            if pick is None:
                # No continuous solution here: try a shorter Cartesian step before holding.
                new_pos, new_rot = _blend(pos0, rot0, new_pos, new_rot, 0.5)
                self._v *= 0.5
                continue
            q_new, ratio = pick
            if ratio > 1.0 + 1e-9:
                # Too fast for a joint: shorten the whole step (pose and swivel) and retry once or twice.
                scaled = self._scale_step(pos0, rot0, s0, new_pos, new_rot, s_new, q_prev, dt, ratio)
                if scaled is None:
                    new_pos, new_rot = _blend(pos0, rot0, new_pos, new_rot, 0.5)
                    continue
                new_pos, new_rot, s_new, q_new, circle = scaled
            return self._commit(q_new, new_pos, new_rot, s_new, circle, dt)
        self._hold("no joint solution continuous with the current configuration "
                   "(joint limits or singularity)")
        self._track(dt)  # the command brakes onto the (standing) reference
        return False

    def _yield_hand(self, pos0: Vec3, rot0: Quat, pos1: Vec3, rot1: Quat, s: float, q_prev: np.ndarray,
                    dt: float) -> tuple[Vec3, Quat, np.ndarray, ElbowCircle] | None:
        """Shorten the hand step (not the swivel change) until the joint velocities fit; None if the
        whole hand step fits already or no shortening helps."""
        frac = 1.0
        for _ in range(4):
            pos, rot = _blend(pos0, rot0, pos1, rot1, frac)
            T = np.eye(4)
            T[:3, :3] = matrix_from_quat(rot)
            T[:3, 3] = pos
            try:
                circle = elbow_circle(self.geom, T)
            except UnreachableError:
                return None
            pick = self._select(self.arm.ik(T, s), q_prev, dt)
            if pick is None or pick[1] > self.params.flip_ratio:
                return None
            if pick[1] <= 1.0 + 1e-9:
                if frac >= 1.0:
                    return None
                self._v *= frac
                return pos, rot, T, circle
            frac = 0.0 if frac < 0.1 else frac * 0.9 / pick[1]
        return None

    def _yield_swivel(self, T: np.ndarray, s0: float, s1: float, q_prev: np.ndarray, dt: float,
                      ratio: float) -> tuple[float, np.ndarray, float] | None:
        """Shorten only the swivel change so the joint velocities fit; None if the hand motion alone
        is already too fast (then the whole step is shortened)."""
        ds = wrap_angle(s1 - s0)
        fracs = (0.98 / ratio, 0.5 / ratio, 0.0) if math.isfinite(ratio) else (0.5, 0.1, 0.0)
        best: tuple[float, np.ndarray, float] | None = None
        for frac in fracs:
            s = wrap_angle(s0 + frac * ds)
            pick = self._select(self.arm.ik(T, s), q_prev, dt)
            if pick is None or pick[1] > self.params.flip_ratio:
                continue
            if best is None or pick[1] < best[2]:
                best = (s, pick[0], pick[1])
            if pick[1] <= 1.0 + 1e-9:
                return best
        return best

    def _search_swivel(self, T: np.ndarray, s_new: float, q_prev: np.ndarray, dt: float
                       ) -> tuple[tuple[np.ndarray, float] | None, float]:
        p = self.params
        for k in range(1, p.swivel_search_count + 1):
            for sign in (1.0, -1.0):
                s_try = wrap_angle(s_new + sign * k * p.swivel_search_step)
                pick = self._select(self.arm.ik(T, s_try), q_prev, dt)
                if pick is not None and pick[1] <= p.flip_ratio:
                    return pick, s_try
        return None, s_new

    def _scale_step(self, pos0: Vec3, rot0: Quat, s0: float, pos1: Vec3, rot1: Quat, s1: float,
                    q_prev: np.ndarray, dt: float, ratio: float
                    ) -> tuple[Vec3, Quat, float, np.ndarray, ElbowCircle] | None:
        frac = 1.0
        for _ in range(4):
            frac *= 0.98 / ratio  # shorten the (already shortened) step by the excess ratio
            pos, rot = _blend(pos0, rot0, pos1, rot1, frac)
            s = wrap_angle(s0 + frac * wrap_angle(s1 - s0))
            T = np.eye(4)
            T[:3, :3] = matrix_from_quat(rot)
            T[:3, 3] = pos
            try:
                circle = elbow_circle(self.geom, T)
            except UnreachableError:
                return None
            pick = self._select(self.arm.ik(T, s), q_prev, dt)
            if pick is None:
                return None
            q, ratio = pick
            if ratio <= 1.0 + 1e-9:
                self._v *= frac
                return pos, rot, s, q, circle
        return None

    def _commit(self, q: np.ndarray, pos: Vec3, rot: Quat, s: float, circle: ElbowCircle | None,
                dt: float) -> bool:
        """Take ``q`` (the IK of the proposed pose, within the velocity limits) as the new reference and
        move the command towards it within the velocity and acceleration limits, through the guard.
        Returns False if the guard refused the command (the arm brakes and holds)."""
        p = self.params
        assert self._q is not None
        qr_d = (q - self._q) / dt
        moved = math.dist(pos, self._pos)
        ratio = float(np.max(np.abs(q - self._q) * self._inv_vel)) / dt
        self._sdot = wrap_angle(s - self._s) / dt if p.swivel_mode != "fixed" else 0.0
        self._w_ori = quat_angle(self._rot, rot) / dt
        self._q, self._qrd = q, qr_d
        self._pos, self._rot, self._s, self._circle = pos, rot, s, circle
        if self._message.startswith("collision guard"):
            self._message = ""
        if not self._track(dt):
            return False
        # Speed budget for the hand: when a joint nears its velocity limit, when the reference asks
        # a joint for much of its acceleration, or when the command lags behind the reference, cap
        # the hand speed ahead of time (the filter then slows down with bounded jerk).
        sp = self.speed_profile.params
        v_now = moved / dt
        self._v_ref = v_now
        predicted = ratio + 4.0 * max(ratio - self._ratio, 0.0)  # the ratio can grow fast in turns
        self._ratio = ratio
        cap = math.inf
        if predicted > 0.85 and v_now > 1e-4:
            cap = max(v_now * 0.85 / predicted, 0.02)
        lag = float(np.max(np.abs(self._q - self._qc) * self._inv_vel))  # s at full joint speed
        if lag > p.max_lag and v_now > 1e-3:
            cap = min(cap, max(v_now * p.max_lag / lag, 0.02))
        if math.isfinite(cap):
            self._v_cap = cap if self._v_cap is None else min(cap, self._v_cap + sp.a_max * dt)
        elif self._v_cap is not None:
            self._v_cap += 0.5 * sp.a_max * dt
            if self._v_cap > sp.v_max:
                self._v_cap = None
        if self._phase is Phase.HOLDING:
            self._phase = Phase.REACHING
            self._message = ""
        return True

    def _track(self, dt: float) -> bool:
        """Move the command ``_qc`` one step towards the reference ``_q`` within the joint velocity,
        acceleration and position limits (time-optimal per joint: the reference velocity plus the
        speed from which the lag can still be braked away), then check it with the collision guard.
        Returns False if the guard refused it (then the arm brakes and holds)."""
        qc, qd = self._qc, self._qd
        e = self._q - qc
        v_des = np.clip(self._qrd, -self._max_vel, self._max_vel) + \
            np.sign(e) * braking_speed(np.abs(e), self._max_acc, dt)
        lo, hi = velocity_bounds(qc, qd, dt, self._max_vel, self._max_acc, self._lower, self._upper)
        v = np.clip(v_des, lo, hi)
        small = np.abs(e) <= 1e-12  # land exactly on a resting reference
        v = np.where(small & (np.abs(self._qrd) <= 1e-12) & (lo <= 0.0) & (hi >= 0.0), 0.0, v)
        q_new = np.clip(qc + v * dt, self._lower, self._upper)
        snap = (np.abs(self._q - q_new) <= 1e-12)
        q_new = np.where(snap, self._q, q_new)
        return self._command(q_new, (q_new - qc) / dt, dt)

    def _command(self, q: np.ndarray, qd: np.ndarray, dt: float) -> bool:
        """Commit command ``q`` (rad) moving at ``qd`` (rad/s) if the guard allows it; otherwise brake."""
        clear = min_distance(self.arm, q, self.scene, self.params.capsules)
        if not self._clear_enough(clear.distance):
            self._guard_stop(clear, dt)
            return False
        stop = self._braking_clearance(q, qd, clear.distance, dt)
        if stop is not None and not self._clear_enough_from(stop.distance, clear.distance):
            # Braking from the new state at the acceleration limits would run into the scene: do
            # not take it; brake from the current state instead (its own braking path was checked).
            self._guard_stop(stop, dt)
            return False
        self._set_command(q, qd, clear, dt)
        return True

    def _braking_clearance(self, q: np.ndarray, qd: np.ndarray, c: float, dt: float) -> Clearance | None:
        """Smallest clearance along the hardest allowed braking from ``q`` moving at ``qd`` (sampled
        every ``guard_step`` m of possible travel and lowered by that much), or None if no point of the
        arm can travel ``c - collision_margin`` before the joints stop (each joint turns at most
        ``qd^2 / (2 a) + |qd| dt`` more, moving points at most its lever arm times that)."""
        p = self.params
        turn = qd * qd / (2.0 * self._max_acc) + np.abs(qd) * dt  # rad still to go per joint
        if not np.any(turn > 0.0):
            return None
        kp = np.asarray(self.arm.key_points(q), float)
        lever = self._levers(kp)
        if c - float(np.dot(lever, turn)) >= p.collision_margin:
            return None
        # March along the braking path; a sample with clearance cb proves the next cb - margin of
        # travel safe (no point moves farther), so samples are sparse away from the scene.
        worst: Clearance | None = None
        n = int(float(np.max(np.abs(qd) / self._max_acc)) / dt) + 2
        k = np.arange(1, n + 1)[:, None]
        v = np.sign(qd) * np.maximum(np.abs(qd) - k * self._max_acc * dt, 0.0)  # brake_step, closed form
        path = np.clip(q + dt * np.cumsum(v, axis=0), self._lower, self._upper)
        moved = np.cumsum(np.abs(np.diff(np.vstack([q, path]), axis=0)) @ lever)
        at, gap = 0.0, max(c - p.collision_margin, p.guard_step)
        while True:
            i = min(int(np.searchsorted(moved, at + gap)), n - 1)
            cb = min_distance(self.arm, path[i], self.scene, p.capsules)
            room = cb.distance - p.collision_margin
            if room < p.guard_step and i < n - 1:  # dense sampling: ask guard_step more
                cb = Clearance(cb.distance - p.guard_step, cb.link, cb.obstacle)
            if worst is None or cb.distance < worst.distance:
                worst = cb
            if i >= n - 1:
                return worst
            at, gap = float(moved[i]), max(room, p.guard_step)

    def _levers(self, kp: np.ndarray) -> np.ndarray:
        """Per joint, the largest distance (m) from it to a point of the arm it moves (key points
        plus the thickest capsule): shoulder joints 1-3, elbow joint 4, wrist joints 5-7."""
        r = max(self.params.capsules.radii)
        sh = max(float(np.linalg.norm(kp[i] - kp[1])) for i in (2, 3, 4)) + r
        el = max(float(np.linalg.norm(kp[i] - kp[2])) for i in (3, 4)) + r
        wr = float(np.linalg.norm(kp[4] - kp[3])) + r
        return np.array([sh, sh, sh, el, wr, wr, wr])

    def _clear_enough_from(self, c: float, c_from: float) -> bool:
        """Like :meth:`_clear_enough`, relative to a clearance ``c_from`` instead of the last one."""
        return c >= self.params.collision_margin or c >= c_from - 1e-9

    def _set_command(self, q: np.ndarray, qd: np.ndarray, clear: Clearance, dt: float) -> None:
        obs = math.inf
        if self._obstacles_only.obstacles:
            obs = min_distance(self.arm, q, self._obstacles_only, self.params.capsules).distance
        both = math.isfinite(self._obs_clear) and math.isfinite(obs)
        self._obs_rate = (self._obs_clear - obs) / dt if both else 0.0
        self._obs_clear = obs
        self._qc = q
        self._qd = qd
        self._clear = clear
        T = np.asarray(self.arm.fk(q), float)
        cpos = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        self._ctool_speed = math.dist(cpos, self._cpos) / dt
        self._cpos = cpos
        self._crot = quat_from_matrix(T[:3, :3])

    def _resync_reference(self) -> None:
        """Make the reference the command (after a guard stop): pose, swivel and circle from FK."""
        self._q = self._qc.copy()
        self._qrd = np.zeros(7)
        T = np.asarray(self.arm.fk(self._qc), float)
        self._pos = (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        self._rot = quat_from_matrix(T[:3, :3])
        try:
            self._circle = elbow_circle(self.geom, T)
            self._s = float(self.arm.swivel(self._qc))
        except UnreachableError:
            self._circle = None
        self._sdot = 0.0
        self._w_ori = 0.0
        self._v = 0.0
        self._a = 0.0

    def _clear_enough(self, c: float) -> bool:
        """The guard: a command may not go below ``collision_margin`` unless it gets no closer than the
        previous command (so an arm started in collision can still move out)."""
        return c >= self.params.collision_margin or c >= self._clear.distance - 1e-9

    def _guard_stop(self, bad: Clearance, dt: float) -> None:
        what = "the table" if bad.obstacle == TABLE else f"obstacle {bad.obstacle}"
        if 0 <= bad.obstacle < len(self.scene.obstacles) and self.scene.obstacles[bad.obstacle].name:
            what += f" {self.scene.obstacles[bad.obstacle].name!r}"
        link = ("base", "upper arm", "forearm", "hand")[bad.link] if 0 <= bad.link < 4 else "arm"
        braked = self._brake(dt)
        self._resync_reference()
        self._hold(f"collision guard: the next step would bring the {link} to {bad.distance:.3f} m of "
                   f"{what}; {'braking' if braked else 'holding'}")

    def _brake(self, dt: float) -> bool:
        """One step of the hardest allowed joint braking, if the guard lets it through; otherwise stop
        where the arm is (an emergency stop: the only command that may exceed the acceleration limit).
        Returns True if a braking step was commanded."""
        if not np.any(self._qd != 0.0):
            return False
        q_b, v_b = brake_step(self._qc, self._qd, dt, self._max_acc, self._lower, self._upper)
        clear = min_distance(self.arm, q_b, self.scene, self.params.capsules)
        if self._clear_enough(clear.distance):
            self._set_command(q_b, v_b, clear, dt)
            return True
        LOG.warning("emergency stop: even braking would bring the arm within %.3f m of the scene",
                    clear.distance)
        self._qd = np.zeros(7)
        return False

    def _hold(self, why: str) -> None:
        """Stop the hand (the command then brakes onto the reference) and report HOLDING with ``why``."""
        self._v = 0.0
        self._a = 0.0
        self._qrd = np.zeros(7)
        if self._goal_p is not None:
            self._phase = Phase.HOLDING
        self._message = why

    def _unfold_target(self) -> np.ndarray:
        """Bent posture to unfold to from a stretched one: the arm turned (joint 1) so that it bends
        towards the goal, pitches ``unfold_pitch`` for shoulder, elbow and wrist, rolls unchanged."""
        q = self._qc.copy()
        sign = 1.0
        if self._goal_p is not None and math.hypot(self._goal_p[0], self._goal_p[1]) > 1e-6:
            az = math.atan2(self._goal_p[1], self._goal_p[0])
            d = wrap_angle(az - q[0])
            if abs(d) > 0.5 * math.pi:  # bend backwards rather than turn by more than 90 deg
                d = wrap_angle(d - math.pi)
                sign = -1.0
            if self._lower[0] <= q[0] + d <= self._upper[0]:
                q[0] += d
        p2, p4, p6 = self.params.unfold_pitch
        roll3 = 1.0 if math.cos(q[2]) >= 0.0 else -1.0
        roll5 = 1.0 if math.cos(q[4]) >= 0.0 else -1.0
        q[1] = sign * p2
        q[3] = sign * roll3 * p4
        q[5] = sign * roll3 * roll5 * p6
        return np.clip(q, self._lower, self._upper)

    def _unfold_step(self, dt: float) -> None:
        """One joint-space step of the unfold: the reference jumps to the bent posture and the command
        moves there time-optimally within the joint limits, through the collision guard; at rest there
        the Cartesian loop takes over from rest."""
        if self._unfold is None:
            self._unfold = self._unfold_target()
            LOG.info("stretched start (no elbow circle): unfolding in joint space to %s",
                     np.round(self._unfold, 3).tolist())
        self._q = self._unfold.copy()
        self._qrd = np.zeros(7)
        if not self._track(dt):
            return
        self._message = "unfolding from a stretched posture (no elbow circle) in joint space"
        if self._phase is Phase.HOLDING:
            self._phase = Phase.REACHING
        if np.array_equal(self._qc, self._unfold) and not np.any(self._qd != 0.0):
            self._unfold = None
            self._resync_reference()
            self._s_fixed = self._s
            self._message = ""
            self._phi, self._theta = self._heading_to_goal()
            self._turn = (0.0, 0.0)

    def _heading_to_goal(self) -> tuple[float, float]:
        if self._goal_p is None:
            return self._phi, self._theta
        gp, cp = self._goal_p, self._pos
        return heading_angles((gp[0] - cp[0], gp[1] - cp[1], gp[2] - cp[2]), self._phi)

    def _update_phase(self) -> None:
        if self._goal_p is None or self._goal_q is None or self._phase is Phase.HOLDING:
            return
        p = self.params
        d = math.dist(self._cpos, self._goal_p)
        err = quat_angle(self._crot, self._goal_q)
        if d <= p.pos_tolerance and err <= p.ori_tolerance and self._settled():
            self._phase = Phase.REACHED
        else:
            self._phase = Phase.REACHING

    def _settled(self) -> bool:
        """The reference is at the goal too, the commanded tool has (nearly) stopped (below
        ``pos_tolerance`` per 0.1 s) and so have the joints (below 5 % of their velocity limits, within
        1 mrad of the reference): REACHED neither flickers while the command catches up nor comes
        while the elbow still swings about its swivel, which a real (lagging) arm would turn into tool
        error."""
        p = self.params
        assert self._goal_p is not None and self._goal_q is not None
        if math.dist(self._pos, self._goal_p) > p.pos_tolerance or \
                quat_angle(self._rot, self._goal_q) > p.ori_tolerance:
            return False
        if self._ctool_speed > p.pos_tolerance / 0.1:
            return False
        # The joints too (the elbow settling on its swivel moves no tool, but a tracking arm lags in
        # every joint): nearly at rest and on the reference.
        return float(np.max(np.abs(self._qd) / self._max_vel)) <= 0.05 and \
            float(np.max(np.abs(self._q - self._qc))) <= 1e-3

    def _result(self) -> StepResult:
        assert self._q is not None
        if self._goal_p is not None and self._goal_q is not None:
            d = math.dist(self._cpos, self._goal_p)
            err = quat_angle(self._crot, self._goal_q)
        else:
            d = math.inf
            err = math.inf
        return StepResult(
            q=self._qc.copy(),
            phase=self._phase,
            swivel=self._s,
            swivel_desired=self._s_des,
            clearance=self._clear.distance,
            clearance_link=self._clear.link,
            clearance_obstacle=self._clear.obstacle,
            distance_to_goal=d,
            orientation_error=err,
            heading=(self._phi, self._theta),
            speed=self._v,
            position=self._cpos,
            message=self._message,
        )

    def forces(self) -> SwivelForces | None:
        """Swivel forces at the current state (for plots and diagnostics)."""
        if self._circle is None:
            return None
        return self.swivel_dyn.forces(self._circle, self._s, self.scene, self.params.capsules)


def _smoothstep(x: float) -> float:
    """0 for x <= 0, 1 for x >= 1, C1 in between."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    return x * x * (3.0 - 2.0 * x)


def _wrist_shell(arm: Any, geom: ArmGeometry) -> tuple[float, float]:
    """Smallest and largest shoulder-wrist distance (m) allowed by the elbow joint's limits."""
    l2, l3 = geom.upper, geom.fore
    lo, hi = float(arm.lower[3]), float(arm.upper[3])
    bend = max(abs(lo), abs(hi))
    straight = 0.0 if lo <= 0.0 <= hi else min(abs(lo), abs(hi))
    d_in = math.sqrt(max(l2 * l2 + l3 * l3 + 2.0 * l2 * l3 * math.cos(min(bend, math.pi)), 0.0))
    d_out = math.sqrt(max(l2 * l2 + l3 * l3 + 2.0 * l2 * l3 * math.cos(straight), 0.0))
    return d_in, d_out


def _blend(pos0: Vec3, rot0: Quat, pos1: Vec3, rot1: Quat, t: float) -> tuple[Vec3, Quat]:
    """Pose a fraction ``t`` of the way from (pos0, rot0) to (pos1, rot1)."""
    pos = (pos0[0] + t * (pos1[0] - pos0[0]), pos0[1] + t * (pos1[1] - pos0[1]),
           pos0[2] + t * (pos1[2] - pos0[2]))
    w = rotvec_between(rot0, rot1)
    rot = quat_normalize(quat_mul(quat_from_rotvec((t * w[0], t * w[1], t * w[2])), rot0))
    return pos, rot
