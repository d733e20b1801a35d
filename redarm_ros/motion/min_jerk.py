"""The minimum-jerk profile (Flash & Hogan): the progress 10 x^3 - 15 x^4 + 6 x^5 of a rest-to-rest move
at the time share x, the single-peaked speed bell of a human reach; its derivatives and its inverse.

The corridor schedule, the corridor route, the joint-space re-planner, the benchmarks and the HIL
scenarios all time their moves by it. Floats stay floats (the controller samples it every step);
arrays are taken element-wise. x is clamped to [0, 1]: before the start and after the end the move rests.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

X = TypeVar("X", float, np.ndarray)

#: peaks of |d progress / dx| (at x = 1/2) and |d^2 progress / dx^2| (10 / sqrt 3, x = 1/2 -+ sqrt 3 / 6)
PEAK_RATE = 1.875
PEAK_ACC = 5.7735


def _clamp(x: X) -> X:
    if isinstance(x, np.ndarray):
        return np.clip(x, 0.0, 1.0)
    return min(max(float(x), 0.0), 1.0)


def min_jerk(x: X) -> X:
    """Progress (0..1) at the time share ``x``."""
    x = _clamp(x)
    return x * x * x * (10.0 - 15.0 * x + 6.0 * x * x)


def min_jerk_rate(x: X) -> X:
    """d progress / d x at ``x`` (peak 1.875 at x = 0.5; 0 outside the move)."""
    x = _clamp(x)
    return 30.0 * x * x * (1.0 - x) * (1.0 - x)


def min_jerk_accel(x: X) -> X:
    """d^2 progress / d x^2 at ``x``."""
    x = _clamp(x)
    return 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x)


def min_jerk_inverse(u: float) -> float:
    """The time share x with ``min_jerk(x) == u`` (bisection to 1e-15; the profile is increasing)."""
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if min_jerk(mid) < u:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
