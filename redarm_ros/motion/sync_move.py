"""A synchronised point-to-point joint move: every joint starts and arrives together (numpy only).

Used by the CAN driver's ``~/park``: the move from wherever the arm stands to its park posture is one
straight line in joint space, timed by a trapezoidal velocity profile of the path parameter
``s`` (0 -> 1) that keeps every joint within ``scale`` times its velocity and acceleration limits. The
slowest joint sets the pace; the others move proportionally slower. A straight line in joint space is
predictable (the arm does not sweep through postures a joint-by-joint move would) and stays inside
the joint limits when both ends are inside them (the limits are a box).

Units: rad, rad/s, rad/s^2, s.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.motion.limits import JointLimits

__all__ = ["synchronized_move"]


def _profile(t: np.ndarray, sd: float, sdd: float) -> tuple[np.ndarray, float]:
    """Trapezoid (or triangle) of ``s`` from 0 to 1 at peak rate ``sd`` (1/s), acceleration ``sdd``
    (1/s^2), sampled at ``t`` (s); returns (s(t), duration)."""
    if sd * sd / sdd >= 1.0:  # never reaches the peak rate: a triangle
        ta = math.sqrt(1.0 / sdd)
        sd = sdd * ta
        tc = 0.0
    else:
        ta = sd / sdd
        tc = 1.0 / sd - ta  # cruise time
    total = 2.0 * ta + tc
    t = np.clip(t, 0.0, total)
    s = np.where(
        t < ta,
        0.5 * sdd * t * t,
        np.where(t < ta + tc, 0.5 * sdd * ta * ta + sd * (t - ta),
                 1.0 - 0.5 * sdd * (total - t) ** 2),
    )
    return np.clip(s, 0.0, 1.0), total


def synchronized_move(
    q_start: Any, q_goal: Any, limits: JointLimits, dt: float, scale: float = 0.9
) -> tuple[np.ndarray, np.ndarray]:
    """Knots of a synchronised straight-line move from ``q_start`` to ``q_goal`` (n,) rad.

    Returns ``(times (k,) s, points (k, n) rad)``: ``times`` start at ``dt`` and step by ``dt``
    (the driver interpolates from its current reference at time 0), the last point is ``q_goal``
    exactly. Every joint's velocity stays within ``scale * max_vel`` and, between knots, its
    acceleration within ``scale * max_acc`` (the headroom leaves the driver's reference shaper room to
    blend into the move from a moving reference). A move of zero length gives one knot at ``dt``.

    Raises:
        InvalidInputError: shapes differ from the limits, values not finite, ``dt`` or ``scale`` not
            in (0, inf) / (0, 1], or an end outside the position limits.
    """
    q0 = np.asarray(q_start, dtype=float).reshape(-1)
    q1 = np.asarray(q_goal, dtype=float).reshape(-1)
    if q0.shape != (limits.n,) or q1.shape != (limits.n,):
        raise InvalidInputError(f"move ends need {limits.n} values", field="q", value=(q0.shape, q1.shape))
    if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(q1))):
        raise InvalidInputError("move ends contain NaN or inf", field="q")
    if not (dt > 0 and math.isfinite(dt)) or not (0.0 < scale <= 1.0):
        raise InvalidInputError("dt must be > 0 and scale in (0, 1]", field="dt", value=(dt, scale))
    if not (np.all(limits.contains(q0, 1e-9)) and np.all(limits.contains(q1, 1e-9))):
        raise InvalidInputError("move ends must be inside the joint limits", field="q",
                                value=(q0.tolist(), q1.tolist()))
    d = np.abs(q1 - q0)
    moving = d > 0.0
    if not np.any(moving):
        return np.array([dt]), q1[None, :].copy()
    # Rates of the path parameter s that keep every joint inside its scaled limits.
    sd = float(np.min(scale * limits.max_vel[moving] / d[moving]))
    sdd = float(np.min(scale * limits.max_acc[moving] / d[moving]))
    _, total = _profile(np.zeros(1), sd, sdd)
    k = max(1, math.ceil(total / dt))
    times = dt * np.arange(1, k + 1, dtype=float)
    s, _ = _profile(times, sd, sdd)
    s[-1] = 1.0
    points = q0[None, :] + s[:, None] * (q1 - q0)[None, :]
    points[-1] = q1
    return times, points
