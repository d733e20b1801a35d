"""The controller's state, as plain dataclasses: :class:`CoreState` is everything that
:meth:`~redarm_ros.control.reach_controller.ReachController.reset` sets (one assignment).

Two joint states are kept: the *reference* (the dynamics' tool pose and swivel with their closed-form
IK, velocity-limited) and the *command* that tracks it within the velocity and acceleration limits
through the collision guard (what is sent). Units: m, rad, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from redarm_ros.control.corridor_route import CorridorRoute
from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.replan import JointPath, PathSearch
from redarm_ros.control.stream import StreamEstimator
from redarm_ros.control.types import GoalKind, Phase, Quat, Vec3
from redarm_ros.geometry.obstacles import Clearance

ZERO3: Vec3 = (0.0, 0.0, 0.0)
#: share of its velocity limit below which a joint counts as at rest for REACHED
REST_SPEED_SHARE = 0.05


class Mode(enum.Enum):
    """Which law moves the reference."""

    HOLD = "hold"  # no goal: the command brakes onto the standing reference
    ATTRACTOR = "attractor"  # point goal: heading, speed, orientation and swivel dynamics
    SERVO = "servo"  # goal stream or twist: the reference follows the predicted goal
    PLAN = "plan"  # brake to rest, then search a joint path (the arm holds)
    JOINT = "joint"  # execute a joint-space path, then back to ATTRACTOR


@dataclass
class Reference:
    """The dynamics' state: joints ``q`` (IK of ``pos``/``rot`` at swivel ``s``) and the joint
    velocity ``qd`` of the last step; ``circle`` is None at a stretched (singular) pose."""

    q: np.ndarray
    pos: Vec3
    rot: Quat
    s: float
    circle: ElbowCircle | None
    qd: np.ndarray = field(default_factory=lambda: np.zeros(7))
    s_des: float = 0.0
    s_fixed: float = 0.0
    sdot: float = 0.0  # swivel rate of the last step (rad/s)
    sdot_dyn: float = 0.0  # the swivel dynamics' part of it while tracking (without the feed-forward)
    # the rate the swivel dynamics asked for at the last step, before the rate limits (rad/s); NaN until
    # the dynamics has run from the current reference (e.g. right after a joint-space move)
    sdot_want: float = 0.0
    # controller time (s) since which sdot_want has stayed above twice settle_swivel_rate (REACHED's
    # threshold; inf while below): only a wanted rate that lasts makes REACHED leave (WANT_HOLD_S)
    want_over_since: float = math.inf
    # controller time (s) at which the swivel last turned faster than settle_swivel_rate, the hand
    # last moved, or the reference was reset: a swivel its dynamics asks to move that stands this long
    # with the hand still is held by the limits, and counts as settled after SETTLE_DWELL_S
    swivel_moved_at: float = -math.inf
    # the last servo step was shortened to the joints' acceleration limits (the hand fell behind): the
    # pose law's offset then holds instead of closing (the hand has priority over the elbow's way back)
    acc_limited: bool = False
    w_ori: float = 0.0  # orientation rate of the last step (rad/s)
    v_tool: float = 0.0  # tool speed of the last step (m/s)
    vel: Vec3 = ZERO3  # tool velocity of the last step (m/s), the servo's state
    w: Vec3 = ZERO3  # angular velocity of the last step (rad/s, base frame), the servo's state


@dataclass
class Attractor:
    """Heading (azimuth ``phi``, elevation ``theta``) and speed state of the attractor dynamics."""

    phi: float = 0.0
    theta: float = 0.0
    turn: tuple[float, float] = (0.0, 0.0)  # heading rates applied in the last step (rad/s)
    v: float = 0.0  # hand speed (m/s)
    a: float = 0.0  # its rate (m/s^2)
    v_cap: float | None = None  # speed budget from the joints (m/s)
    ratio: float = 0.0  # largest joint speed / limit in the last step


@dataclass
class PlanAhead:
    """The servo's plan ahead (``servo.plan_horizon``): the controller time (s) ``until`` which it plans,
    when it last ``checked`` whether the path ahead needs it, and the pose law's swivel ``offset`` (rad)
    and its ``rate`` (rad/s) along which the path ahead is solved, kept here while it plans (measured
    from the planned joints, a joint held back by its limit would feed its own lag back as an offset)."""

    until: float = -math.inf
    checked: float = -math.inf
    offset: float = 0.0
    rate: float = 0.0


@dataclass
class Command:
    """What was sent: joints ``q`` moving at ``qd``, their ``clear``-ance and tool pose."""

    q: np.ndarray
    clear: Clearance
    pos: Vec3
    rot: Quat
    kp: np.ndarray  # key points (5, 3) m: base, shoulder, elbow, wrist, tool
    qd: np.ndarray = field(default_factory=lambda: np.zeros(7))
    tool_speed: float = 0.0  # m/s
    obs_clear: float = math.inf  # clearance to the obstacles (not the table), m
    obs_rate: float = 0.0  # how fast it shrank (m/s, > 0 approaching)


@dataclass
class Goal:
    """The active goal: ``pos`` (m), ``rot`` (w, x, y, z), how it came (``kind``) and when (``since``,
    controller time s)."""

    pos: Vec3
    rot: Quat
    kind: GoalKind
    since: float
    # where the elbow may rest at this goal (start, swivel samples, which are clear of the limit force):
    # found once, when the hand first gets there (rest_known), None if it could not be found
    rest: tuple[float, np.ndarray, np.ndarray] | None = None
    rest_known: bool = False
    rest_pick: int | None = None  # the sample of ``rest`` the elbow was last sent to

    def point_at(self, pos: Vec3, tol: float) -> bool:
        """A point goal within ``tol`` m of ``pos``. Not a stream's or a twist's: their goal moves (a
        twist's follows the hand), so what is found for it at one instant goes stale."""
        return self.kind is GoalKind.POINT and math.dist(pos, self.pos) <= tol


@dataclass
class Progress:
    """Stall detection of a point goal: the best goal error so far and when it was reached; when the
    arm began holding; how often it re-planned."""

    best: float = math.inf
    t_best: float = 0.0
    travel: float = 0.0  # tool path (m) since the best error
    t_last: float = 0.0
    hold_since: float | None = None
    guard_stops: list[float] = field(default_factory=list)  # controller times of recent guard stops
    due: float = math.inf  # controller time by which the attractor should have arrived
    replans: int = 0


@dataclass
class Twist:
    """The latest twist command: linear (m/s) and angular (rad/s) velocity in the base frame, and the
    controller time it arrived."""

    vel: Vec3 = ZERO3
    w: Vec3 = ZERO3
    since: float = -math.inf


@dataclass
class CoreState:
    """Everything :meth:`ReachController.reset` starts afresh."""

    ref: Reference
    cmd: Command
    stream: StreamEstimator
    att: Attractor = field(default_factory=Attractor)
    mode: Mode = Mode.HOLD
    phase: Phase = Phase.IDLE
    message: str = ""
    goal: Goal | None = None
    progress: Progress = field(default_factory=Progress)
    twist: Twist | None = None
    planner: PathSearch | None = None
    path: JointPath | None = None
    path_t: float = 0.0
    plan_reason: str = ""
    brake_sync: bool = False  # the command follows a joint path: braking keeps to it
    history: deque[tuple[np.ndarray, float]] = field(default_factory=lambda: deque(maxlen=1500))
    """The last commands (joints, clearance m), oldest first: where the re-planner may retreat to."""
    stream_note: str = ""
    route: CorridorRoute | None = None  # the point goal's straight route through the swivel corridor
    corridor_plan: Future[tuple[CorridorRoute | None, str]] | None = None  # planned in the worker thread
    time: float = 0.0  # controller clock (s): advanced by step(), or the caller's ``now``
    ahead: PlanAhead = field(default_factory=PlanAhead)
