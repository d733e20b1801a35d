"""The base-move suggestion in the controller's rejection of a goal it cannot reach where the base stands.

When a goal is rejected as out of reach or without an in-limit solution, the rejection message ends
with the smallest planar base move after which the goal is solvable with the elbow in the optimal
region (:func:`redarm_ros.kinematics.base_placement.suggest_base_move`), e.g. ``goal out of reach: ...;
move the base by dx = 0.412 m, dy = 0.000 m (yaw 0.0 deg), base first, then the arm (phi4 = 0.0 deg,
the optimal region)``.

The search runs inside the control step's thread, so it is bounded: at most ``budget_s`` seconds, once
per rejected goal (:class:`BaseMoveHints` remembers the last pose and its sentence, so a goal sent again
and again costs nothing). Units: m, rad, s.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from redarm_ros.control.types import GoalCheck, GoalStatus
from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.self_collision import CollisionModel, collision_model
from redarm_ros.kinematics.base_placement import BasePlacement, suggest_base_move
from redarm_ros.kinematics.protocols import ControlledArm

__all__ = ["HINTED", "BaseMoveHints", "hint_text"]

#: The rejections that get a suggestion: a base move can help these.
HINTED = (GoalStatus.OUT_OF_REACH, GoalStatus.NO_SOLUTION_IN_LIMITS)


def hint_text(bp: BasePlacement) -> str:
    """The sentence of a suggestion: 'move the base by dx = ..., dy = ... m (yaw ... deg), ...'."""
    if not bp.valid:
        return f"no base move found ({bp.message})"
    region = "the optimal region" if bp.optimal else "the optimal region is out of reach of a planar move"
    return (f"move the base by dx = {bp.x:.3f} m, dy = {bp.y:.3f} m (yaw {math.degrees(bp.yaw):.1f} deg), "
            f"base first, then the arm ({bp.elbow_name} = {math.degrees(bp.elbow):.1f} deg, {region})")


class BaseMoveHints:
    """Base-move suggestions for rejected goals of one arm, the last one remembered.

    ``budget_s``: time limit of one search (s); ``check_collisions``: the suggested placement must have
    a solution free of self-collision and the ground (the arm's collision model); ``step_deg``: spacing
    of the candidate base positions along a circle (the nearest one always comes first; a coarse
    spacing keeps the search within its budget when the nearest one fails, e.g. a vertical approach of
    the 6-DOF arm at a wrist limit: about 150 candidates at 60 deg instead of 9000 at 1 deg)."""

    def __init__(self, arm: ControlledArm, budget_s: float = 0.05, check_collisions: bool = True,
                 step_deg: float = 60.0) -> None:
        self.arm = arm
        self.budget_s = float(budget_s)
        self.step_deg = float(step_deg)
        self.check_collisions = bool(check_collisions)
        # Built once (reading the arm's YAML entry), not in every bounded search.
        self._model: CollisionModel | None = collision_model(arm) if self.check_collisions else None
        self._last: tuple[bytes, BasePlacement] | None = None
        self.searches = 0  # searches run so far (a repeated goal does not run one)

    def placement(self, T: Any, q_seed: Any = None) -> BasePlacement:
        """The suggestion for pose ``T`` (4x4, base frame); ``q_seed`` (rad) picks among its solutions."""
        key = np.asarray(T, float).tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        self.searches += 1
        try:
            bp = suggest_base_move(self.arm, T, q_seed=q_seed, check_collisions=self.check_collisions,
                                   model=self._model, timeout_s=self.budget_s, step_deg=self.step_deg)
        except InvalidInputError as exc:
            bp = BasePlacement(False, getattr(self.arm, "name", ""), message=str(exc))
        self._last = (key, bp)
        return bp

    def annotate(self, check: GoalCheck, T: Any, q_seed: Any = None) -> GoalCheck:
        """``check`` with the suggestion appended to its message if it is a rejection a base move can
        help (:data:`HINTED`); otherwise ``check`` unchanged."""
        if check.status not in HINTED:
            return check
        text = hint_text(self.placement(T, q_seed))
        return dataclasses.replace(check, message=f"{check.message}; {text}")
