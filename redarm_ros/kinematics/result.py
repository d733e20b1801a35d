"""Result types shared by every IK solver: :class:`IKStatus` and :class:`IKInfo`."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class IKStatus(enum.Enum):
    """Why an IK call ended."""

    SUCCESS = "success"
    NO_SOLUTION_IN_LIMITS = "no_solution_in_limits"
    OUT_OF_REACH = "out_of_reach"
    INVALID_INPUT = "invalid_input"
    TIMEOUT = "timeout"


@dataclass
class IKInfo:
    """Diagnostics of one IK call.

    ``pos_err`` is the position error of the returned q in metres, ``rot_err`` its orientation error in
    radians (angle of the residual rotation); both are ``inf`` when no q was returned. ``swivel`` is the
    elbow swivel angle (rad) of the answer for swivel arms, else ``None``. ``iterations`` counts solver
    iterations (numeric solvers, or refinement steps of ``ik_nearest``) and ``candidates`` the joint
    vectors that were examined.
    """

    status: IKStatus
    message: str = ""
    swivel: float | None = None
    pos_err: float = float("inf")
    rot_err: float = float("inf")
    iterations: int = 0
    candidates: int = 0

    @property
    def ok(self) -> bool:
        """True when a solution was returned."""
        return self.status is IKStatus.SUCCESS
