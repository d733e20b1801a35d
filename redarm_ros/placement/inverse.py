"""Inverse reachability: for a task pose, the base positions from which it can be reachable, with no IK.

A pose can only be reached if its wrist point is reachable from the shoulder: the shoulder-wrist
distance ``d`` of the arm's two middle links is a function of the elbow joint alone,
``d(q) = sqrt(a^2 + b^2 + 2 a b cos q)``, so the elbow's limits bound it to ``[d_min, d_max]``
exactly. The wrist point of a task depends on the task alone (the tool offset along the approach), and
the shoulder's place in the world depends only on the base position, not its yaw:

* 7-DOF swivel arms (PA10 geometry): the shoulder is on the base axis, ``L1`` above the base frame.
  The task's base positions lie in an annulus around the wrist point's foot: the shell
  ``d_min <= |W - S| <= d_max``, a disc minus a disc at each height.
* powercube6: the shoulder sits ``L1`` off the base axis, in the vertical plane through the wrist
  (pointing towards it or away): the two candidate distances ``sqrt((rho -+ L1)^2 + dz^2)``.

This is the capability map's reachable shell in closed form and turned around: a necessary condition,
exact and conservative (a position it rejects has no solution at any yaw; nothing reachable is ever
pruned, so the exact check that follows decides alone). A sampled capability map could not promise
that: between its voxel centres and orientation samples it can miss reachable poses. The map is a
boolean mask over (base pose, task) pairs; only the pairs it keeps go to the exact check.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from redarm_ros.kinematics.protocols import has_swivel

__all__ = ["shell_bounds", "wrist_points", "possible_pairs"]

SHELL_TOL = 1e-9  # m: widen the shell by this much, so rounding never prunes a reachable pose


def _elbow_range(a: float, b: float, lo: float, hi: float) -> tuple[float, float]:
    """[d_min, d_max] of ``sqrt(a^2 + b^2 + 2ab cos q)`` for q in [lo, hi] (rad)."""
    qmin = 0.0 if lo <= 0.0 <= hi else min(abs(lo), abs(hi))
    qmax = max(abs(lo), abs(hi))

    def d(q: float) -> float:
        return math.sqrt(max(a * a + b * b + 2.0 * a * b * math.cos(min(q, math.pi)), 0.0))

    return d(qmax) - SHELL_TOL, d(qmin) + SHELL_TOL


def shell_bounds(arm: Any) -> tuple[float, float]:
    """[d_min, d_max] (m) of the shoulder-wrist distance over the elbow joint's limits."""
    if has_swivel(arm):
        _, L2, L3, _ = arm.link_lengths
        return _elbow_range(L2, L3, float(arm.lower[3]), float(arm.upper[3]))
    if getattr(arm, "kind", "") == "powercube6":
        _, L23, L4, _ = arm.link_lengths
        return _elbow_range(L23, L4, float(arm.lower[3]), float(arm.upper[3]))
    raise ValueError(f"no inverse reachability model for arm kind {getattr(arm, 'kind', '?')!r}")


def wrist_points(arm: Any, tasks: np.ndarray) -> np.ndarray:
    """(m, 3) wrist points (world frame, m) of (m, 4, 4) task poses: the tool offset taken off along
    the approach (tool z for the swivel arms, tool x for powercube6)."""
    T = np.asarray(tasks, dtype=float)
    if has_swivel(arm):
        return T[:, :3, 3] - arm.link_lengths[3] * T[:, :3, 2]
    return T[:, :3, 3] - arm.link_lengths[3] * T[:, :3, 0]


def possible_pairs(arm: Any, tasks: np.ndarray, poses: np.ndarray, base_height: float) -> np.ndarray:
    """(N, m) bool: task j may be reachable from base pose i (False: provably not, at any yaw)."""
    d_min, d_max = shell_bounds(arm)
    W = wrist_points(arm, tasks)
    P = np.asarray(poses, dtype=float).reshape(-1, 3)
    rho = np.hypot(W[None, :, 0] - P[:, None, 0], W[None, :, 1] - P[:, None, 1])
    L1 = arm.link_lengths[0]
    if has_swivel(arm):
        dz = W[None, :, 2] - (base_height + L1)
        d = np.hypot(rho, dz)
        return (d >= d_min) & (d <= d_max)
    dz = W[None, :, 2] - base_height  # powercube6: the shoulder is at the base frame's height
    out = np.zeros(rho.shape, dtype=bool)
    for r in (rho - L1, rho + L1):  # shoulder towards the wrist, or turned away from it
        d = np.hypot(r, dz)
        out |= (d >= d_min) & (d <= d_max)
    return out
