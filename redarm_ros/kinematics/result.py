"""Result types shared by every IK solver: :class:`IKStatus` and :class:`IKInfo`."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np


class IKStatus(enum.Enum):
    """Why an IK call ended."""

    SUCCESS = "success"
    NO_SOLUTION_IN_LIMITS = "no_solution_in_limits"
    OUT_OF_REACH = "out_of_reach"
    INVALID_INPUT = "invalid_input"
    TIMEOUT = "timeout"
    INTERNAL_ERROR = "internal_error"
    #: the pose has in-limit solutions, but every one makes two links collide or a link go below the
    #: ground plane (the IK front end's collision filter; SolveIK code 8)
    ALL_SOLUTIONS_COLLIDE = "all_solutions_collide"


@dataclass
class IKInfo:
    """Diagnostics of one IK call.

    ``pos_err`` is the position error of the returned q in metres, ``rot_err`` its orientation error in
    radians (angle of the residual rotation); both are ``inf`` when no q was returned. ``swivel`` is the
    elbow swivel angle (rad) of the answer for swivel arms, else ``None``. ``iterations`` counts solver
    iterations (numeric solvers, or refinement steps of ``ik_nearest``) and ``candidates`` the joint
    vectors that were examined. ``branch`` is the flip pattern (f2, f4, f6) in binary (0..7, the row
    order of ``ik``) of a swivel arm's answer, else ``None``.
    """

    status: IKStatus
    message: str = ""
    swivel: float | None = None
    pos_err: float = float("inf")
    rot_err: float = float("inf")
    iterations: int = 0
    candidates: int = 0
    branch: int | None = None

    @property
    def ok(self) -> bool:
        """True when a solution was returned."""
        return self.status is IKStatus.SUCCESS


# IKBatchResult.status codes (the numbering of redarm_interfaces/srv/SolveIK)
BATCH_SUCCESS = 0
BATCH_NO_SOLUTION_IN_LIMITS = 1
BATCH_OUT_OF_REACH = 2
BATCH_STATUS = {
    BATCH_SUCCESS: IKStatus.SUCCESS,
    BATCH_NO_SOLUTION_IN_LIMITS: IKStatus.NO_SOLUTION_IN_LIMITS,
    BATCH_OUT_OF_REACH: IKStatus.OUT_OF_REACH,
}


@dataclass
class IKBatchResult:
    """Answers of a batched nearest solve for m poses.

    ``q`` (m, n) rad, NaN rows where there is no answer; ``swivel`` (m,) rad (NaN), ``branch`` (m,) flip
    pattern 0..7 (-1), ``cost`` (m,) weighted squared distance to the seed in rad^2 (inf), ``status``
    (m,) int8 codes: BATCH_SUCCESS 0, BATCH_NO_SOLUTION_IN_LIMITS 1, BATCH_OUT_OF_REACH 2 (the SolveIK
    numbering; ``BATCH_STATUS`` maps them to :class:`IKStatus`).
    """

    q: np.ndarray
    swivel: np.ndarray
    branch: np.ndarray
    cost: np.ndarray
    status: np.ndarray

    @classmethod
    def unsolved(cls, m: int, n: int = 7) -> IKBatchResult:
        """m rows of no answer (status OUT_OF_REACH), to be filled in."""
        return cls(
            np.full((m, n), np.nan),
            np.full(m, np.nan),
            np.full(m, -1, dtype=int),
            np.full(m, np.inf),
            np.full(m, BATCH_OUT_OF_REACH, dtype=np.int8),
        )

    @property
    def ok(self) -> np.ndarray:
        """(m,) bool: a solution was returned."""
        return self.status == BATCH_SUCCESS
