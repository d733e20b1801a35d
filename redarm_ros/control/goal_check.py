"""Goal check: can a tool pose be reached at all, in limits and collision-free, before the arm moves?

:func:`check_goal` (a new goal) answers with a :class:`~redarm_ros.control.types.GoalCheck`:

* malformed pose -> ``INVALID_INPUT``;
* wrist outside the reachable shell -> ``OUT_OF_REACH`` (with the distance);
* tool point inside an obstacle, or the hand capsule colliding with an obstacle or the table ->
  ``IN_COLLISION`` (names the obstacle);
* no in-limit IK solution at any of ``scan`` swivels -> ``NO_SOLUTION_IN_LIMITS``;
* every in-limit elbow position colliding -> ``IN_COLLISION``.

:func:`stream_feasibility` is the cheap per-sample variant for goal streams: it never rejects, it
says why a sample cannot be followed exactly (the servo then follows as closely as the limits allow).
Units: m, rad.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from redarm_ros.control.elbow import ArmGeometry, elbow_circle
from redarm_ros.control.types import GoalCheck, GoalStatus
from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.geometry.obstacles import TABLE, ArmCapsules, Scene, links_clearance
from redarm_ros.kinematics.protocols import ControlledArm


def check_goal(arm: ControlledArm, geom: ArmGeometry, T: Any, scene: Scene, capsules: ArmCapsules,
               scan: int) -> GoalCheck:
    """Check goal pose ``T`` (4x4, base frame) against the arm's reach, limits and ``scene``."""
    try:
        Tl = arm.check_pose(T)
    except InvalidInputError as exc:
        return GoalCheck(GoalStatus.INVALID_INPUT, str(exc))
    Tn = np.asarray(Tl, float)
    try:
        circle = elbow_circle(geom, Tn)
    except UnreachableError as exc:
        return GoalCheck(GoalStatus.OUT_OF_REACH, f"goal out of reach: {exc}")
    p = circle.tool
    for j, o in enumerate(scene.obstacles):
        if o.signed_distance(p) < 0.0:
            return GoalCheck(GoalStatus.IN_COLLISION, f"goal position lies inside obstacle {j} "
                             f"{o.name or type(o).__name__.lower()!r}")
    hand = links_clearance(circle.key_points(0.0), scene, capsules, (3,))
    if hand.distance < 0.0:
        what = "the table" if hand.obstacle == TABLE else f"obstacle {hand.obstacle}"
        return GoalCheck(GoalStatus.IN_COLLISION,
                         f"the hand at the goal would collide with {what} (clearance {hand.distance:.3f} m)")
    n = max(8, int(scan))
    in_limits = 0
    free = 0
    best: tuple[float, float] | None = None
    for k in range(n):
        s = -math.pi + 2.0 * math.pi * k / n
        if arm.ik(Tn, s).shape[0] == 0:
            continue
        in_limits += 1
        c = links_clearance(circle.key_points(s), scene, capsules, (1, 2)).distance
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


def stream_feasibility(geom: ArmGeometry, T: np.ndarray, scene: Scene, capsules: ArmCapsules) -> str:
    """Why a stream sample cannot be followed exactly ('' if nothing is known against it): out of the
    wrist's reach, or the tool point / hand capsule inside the scene. Cheap (no IK): the limits and
    the elbow are handled by the servo step itself."""
    try:
        circle = elbow_circle(geom, T)
    except UnreachableError as exc:
        return f"stream goal out of reach ({exc})"
    except InvalidInputError as exc:
        return f"stream goal invalid ({exc})"
    p = circle.tool
    for j, o in enumerate(scene.obstacles):
        if o.signed_distance(p) < 0.0:
            return f"stream goal inside obstacle {j} {o.name or type(o).__name__.lower()!r}"
    hand = links_clearance(circle.key_points(0.0), scene, capsules, (3,))
    if hand.distance < 0.0:
        what = "the table" if hand.obstacle == TABLE else f"obstacle {hand.obstacle}"
        return f"stream goal puts the hand into {what}"
    return ""
