"""Parameters of the reaching controller (all with units; validated on construction).

:class:`ControllerParams` holds the top-level parameters and the nested groups ``heading``, ``swivel``,
``speed`` (the attractor dynamics), ``capsules`` (the collision model), ``stream`` (how goal messages
are told apart and how a stream's velocity is estimated), ``servo`` (the tracking law) and ``replan``
(stall detection and the joint-space re-planner). ``ControllerParams.from_dict`` reads the YAML form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

from redarm_ros.control.attractor import HeadingParams, SpeedParams
from redarm_ros.control.checks import check_positive as _check_positive
from redarm_ros.control.obstacles import ArmCapsules
from redarm_ros.control.paper_redundancy import PaperSwivelParams
from redarm_ros.control.swivel_dynamics import SwivelParams
from redarm_ros.errors import ConfigError, InvalidInputError


@dataclass(frozen=True)
class StreamParams:
    """How goal messages are told apart and how a stream's velocity is estimated.

    gap [s]: a goal message arriving more than ``gap`` after the previous one starts a new goal.
    jump [m], jump_angle [rad]: a message farther than this from where the stream was predicted to be
    at its stamp starts a new goal (a click elsewhere, not a stream sample).
    window [s]: the velocity is fitted over the samples of the last ``window`` s of stamps.
    end_periods: the stream counts as stopped ``end_periods`` estimated message periods after the
    last sample (at least ``end_min``, at most ``gap``): then the hand settles on the last goal.
    extrapolate_periods: the goal is extrapolated with the estimated velocity for at most this many
    periods past the newest stamp (a late message does not drag the target along).
    accel_weight [s^2]: ridge weight of the acceleration term of the fit (0 = a free quadratic fit;
    larger values trust a straight line more when the stamps are noisy).
    clock_tolerance [s]: stamps within this of the receive clock are taken as on the same clock;
    otherwise the offset between the clocks is estimated from the messages (zero stamps: receive time).
    lead [s]: the target is predicted this much further ahead, to make up for the delay between the
    command and the arm (the driver's interpolation, the bus); 0 = command the goal of now.
    """

    gap: float = 0.5
    jump: float = 0.05
    jump_angle: float = 0.35
    window: float = 0.2
    end_periods: float = 3.0
    end_min: float = 0.05
    extrapolate_periods: float = 1.5
    accel_weight: float = 1e-6
    clock_tolerance: float = 1.0
    lead: float = 0.0

    def __post_init__(self) -> None:
        _check_positive(self, ("gap", "jump", "jump_angle", "window", "end_periods", "end_min",
                               "extrapolate_periods", "clock_tolerance"), ("accel_weight", "lead"))


@dataclass(frozen=True)
class ServoParams:
    """The tracking law of streams and twists (the reference pose follows the predicted goal).

    gain [1/s]: position error -> correction speed in the linear region (``v = v_goal + gain e``,
    capped by the speed from which the error can be braked away at ``acc``).
    acc [m/s^2]: largest change of the hand's velocity (also bounded by the joints' acceleration).
    ori_gain [1/s], ori_acc [rad/s^2]: the same for the orientation (rate capped by ``max_ori_rate``).
    twist_timeout [s]: a twist command is held this long, then the hand decelerates to rest.
    """

    gain: float = 30.0
    acc: float = 3.0
    ori_gain: float = 20.0
    ori_acc: float = 12.0
    twist_timeout: float = 0.1
    resync_lag: float = 0.005
    yield_time: float = 0.3

    def __post_init__(self) -> None:
        _check_positive(self, ("gain", "acc", "ori_gain", "ori_acc", "twist_timeout", "resync_lag",
                               "yield_time"))


@dataclass(frozen=True)
class ReplanParams:
    """Stall detection and the joint-space re-planner (see :mod:`redarm_ros.control.replan`).

    enabled: re-plan at all (False: the arm holds in a dead end, as before).
    route_steps: samples of the straight Cartesian route checked when a point goal is set; a route
    without a continuous in-limit IK solution goes to the planner at once, and so does one whose joint
    motion would take more than ``slow_route`` times (and 2 s more than) a joint-space move to the
    nearest goal configuration.
    hold_time [s]: holding (no continuous step, or the collision guard) this long triggers a re-plan.
    stall_time [s], progress [m], stall_travel [m]: no improvement of the goal error (position +
    0.1 m/rad orientation) by ``progress`` within ``stall_time`` while the tool moved less than
    ``stall_travel`` (stuck or creeping) triggers a re-plan; so does no improvement within
    ``detour_time`` [s] whatever the tool does (a detour that leads nowhere), and ``guard_stops``
    stops by the collision guard within ``2 * stall_time`` (sliding along an obstacle); and so does an
    attractor run still 1 cm (0.1 m/rad) away after ``overdue_factor`` times the straight route's
    least time plus ``overdue_slack`` [s] (crawling through a bad configuration).
    limit_margin [rad]: goal configurations closer than this to a joint limit are penalised.
    clearance [m]: clearance every configuration of a planned joint path keeps from the scene.
    vias: random via configurations tried when neither the direct joint path nor the fold posture
    clears the scene.
    work_per_step: units of work the planner may do in one control step (a unit: one clearance
    evaluation or the IK of one swivel sample; the arm holds meanwhile; the loop stays periodic;
    counted, not timed, so runs are repeatable).
    max_replans: re-plans per goal before the goal is reported BLOCKED.
    seed: seed of the via sampler (deterministic plans).
    """

    enabled: bool = True
    route_steps: int = 40
    slow_route: float = 2.0
    hold_time: float = 0.3
    stall_time: float = 0.8
    progress: float = 0.002
    stall_travel: float = 0.03
    detour_time: float = 3.0
    guard_stops: int = 4
    overdue_factor: float = 1.5
    overdue_slack: float = 2.5
    limit_margin: float = 0.2
    clearance: float = 0.02
    vias: int = 300
    work_per_step: int = 50
    max_replans: int = 3
    seed: int = 7

    def __post_init__(self) -> None:
        _check_positive(self, ("slow_route", "hold_time", "stall_time", "progress", "stall_travel",
                               "detour_time", "clearance", "overdue_factor"),
                        ("limit_margin", "overdue_slack"))
        for name in ("route_steps", "vias", "work_per_step", "max_replans", "guard_stops"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise InvalidInputError(f"ReplanParams.{name} must be an integer >= 1, got {v!r}", field=name,
                                        value=v)
        if not isinstance(self.enabled, bool):
            raise InvalidInputError("ReplanParams.enabled must be a bool", field="enabled",
                                    value=self.enabled)


#: The values of ``ControllerParams.swivel_mode``.
SWIVEL_MODES = ("dynamics", "fixed", "attractor_paper")


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
    swivel_mode: ``"dynamics"`` (eq. 31) or ``"fixed"`` (keep the swivel of reset(): redundancy unused),
    or ``"attractor_paper"`` (the attractor paper's eq. 22-24 with sector force-lets and its path-tangent
    hand orientation, eq. 20-21; parameters in ``paper_swivel``, :mod:`~redarm_ros.control.paper_redundancy`).
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
    unfold_pitch [rad]: (shoulder, elbow, wrist) pitch of the bent "fold" posture the joint-space
    planner passes through when the direct joint path to a goal is blocked.
    stream, servo, replan: see :class:`StreamParams`, :class:`ServoParams`, :class:`ReplanParams`.
    broad_phase_margin [m]: obstacles farther than this (beyond the reach of the arm, or beyond the
    influence of the forces around the current arm) are left out of the distance computations.
    """

    dt: float = 0.01
    heading: HeadingParams = field(default_factory=HeadingParams)
    swivel: SwivelParams = field(default_factory=SwivelParams)
    paper_swivel: PaperSwivelParams = field(default_factory=PaperSwivelParams)
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
    stream: StreamParams = field(default_factory=StreamParams)
    servo: ServoParams = field(default_factory=ServoParams)
    replan: ReplanParams = field(default_factory=ReplanParams)
    broad_phase_margin: float = 0.2

    def __post_init__(self) -> None:
        if self.swivel_reference not in ("high", "low", "absolute"):
            raise ConfigError(f"swivel_reference must be 'high', 'low' or 'absolute', got "
                              f"{self.swivel_reference!r}",
                              field="swivel_reference", value=self.swivel_reference)
        if self.swivel_mode not in SWIVEL_MODES:
            raise ConfigError(f"swivel_mode must be one of {SWIVEL_MODES}, got {self.swivel_mode!r}",
                              field="swivel_mode", value=self.swivel_mode)
        for name in ("dt", "lam_ori", "max_ori_rate", "tangent_distance", "final_distance",
                     "workspace_margin", "pos_tolerance", "ori_tolerance", "max_dt", "flip_ratio",
                     "swivel_search_step", "max_ori_acc", "max_swivel_acc", "elbow_priority_clearance",
                     "stop_share", "joint_brake_share", "max_lag", "guard_step", "slide_band",
                     "broad_phase_margin"):
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
        """Parameters from a (YAML-like) dict; nested dicts for ``heading``, ``swivel``, ``speed``,
        ``capsules``, ``stream``, ``servo`` and ``replan``, e.g. ``{"preferred_swivel": 0.3, "speed":
        {"v_max": 0.25}}``. Missing keys keep their defaults.

        Raises:
            ConfigError: unknown key or bad value (the message names it).
        """
        if not d:
            return cls()
        if not isinstance(d, dict):
            raise ConfigError("controller parameters must be a mapping", value=d)
        nested = {"heading": HeadingParams, "swivel": SwivelParams, "paper_swivel": PaperSwivelParams,
                  "speed": SpeedParams,
                  "capsules": ArmCapsules, "stream": StreamParams, "servo": ServoParams,
                  "replan": ReplanParams}
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
