"""Value types of the controller core: phases, goal verdicts and the result of one step.

Plain data, no behaviour: every other module of :mod:`redarm_ros.control` and the controller node use
them. Units: m, rad, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class Phase(enum.StrEnum):
    """What the controller is doing (names match the ``ControllerState`` phase constants)."""

    IDLE = "IDLE"  # no goal since reset: holds
    REACHING = "REACHING"  # moving towards a point goal (attractor dynamics)
    REACHED = "REACHED"  # within tolerance of the goal and at rest (keeps tracking it)
    HOLDING = "HOLDING"  # a goal is set but the arm waits (guard, no step right now): message says why
    REJECTED = "REJECTED"  # the last goal was rejected: stops smoothly and holds
    TRACKING = "TRACKING"  # following a goal stream or a twist (servo with velocity feed-forward)
    REPLANNING = "REPLANNING"  # the direct route is a dead end: planning/executing a joint-space move
    BLOCKED = "BLOCKED"  # an accepted goal that cannot be reached from here: holds; message says why


class GoalStatus(enum.Enum):
    """Outcome of checking a goal (IKStatus-like)."""

    ACCEPTED = "accepted"
    OUT_OF_REACH = "out_of_reach"
    NO_SOLUTION_IN_LIMITS = "no_solution_in_limits"
    IN_COLLISION = "in_collision"
    INVALID_INPUT = "invalid_input"
    NOT_READY = "not_ready"


class GoalKind(enum.Enum):
    """How a goal message was taken (see :mod:`redarm_ros.control.stream`)."""

    POINT = "point"  # a new goal: reached by the attractor dynamics (or a joint-space move)
    STREAM = "stream"  # one more sample of a goal stream: tracked by the servo
    TWIST = "twist"  # a velocity command: the servo integrates it


@dataclass(frozen=True)
class GoalCheck:
    """Verdict on a goal pose: ``status``, human-readable ``message``; for accepted goals the number of
    scanned swivels that are reachable and collision-free (``free_swivels``) and the clearest one.
    ``kind`` says how a goal message was taken (a new goal or a stream sample); ``repeat``: it only
    repeated the active point goal (nothing changed)."""

    status: GoalStatus
    message: str = ""
    free_swivels: int = 0
    best_swivel: float | None = None
    kind: GoalKind = GoalKind.POINT
    repeat: bool = False

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
    speed: end-effector speed of the reference (m/s). position: commanded tool position (m).
    message: why it holds, re-plans, is blocked, or what limits a stream.
    goal_velocity / goal_rate: the estimated linear (m/s) and angular (rad/s) velocity of a tracked
    goal stream or twist (zeros otherwise); stream_rate: its message rate (Hz, 0 without a stream).
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
    goal_velocity: Vec3 = (0.0, 0.0, 0.0)
    goal_rate: Vec3 = (0.0, 0.0, 0.0)
    stream_rate: float = 0.0
