"""Per-joint motion limits and the discrete braking law that keeps a joint inside them.

The one rule every motion generator in the package follows (the CAN driver's reference shaper, the
simulator's per-joint setpoint generator, and the controller once migrated): a joint stepped every
``dt`` seconds with semi-implicit Euler (``v += dv; p += v dt``, ``|dv| <= a dt``) may move at speed
``v`` towards a stop point only if it can still stop *on* that point by braking at ``a``.
:func:`braking_speed` is that largest speed, exact in discrete time: a joint that keeps to it lands
on the stop point without overshoot and never brakes harder than ``a``; :func:`braking_distance` is
its inverse. :class:`JointLimits` bundles the limits of an arm (position, velocity, acceleration) and
answers the questions asked of them every step (clip, inset margin, admissible velocity interval,
largest plausible jump).

Units: rad, rad/s, rad/s^2, s. Arrays are ``(n,)`` float, one entry per joint. Scalar
(pure-Python) versions exist for the 1 kHz per-joint loops where numpy's call overhead would
dominate (:func:`braking_speed_scalar`).

The law, derived once: braking from a first step at speed ``(j + f) a dt`` (integer ``j >= 0``,
``0 < f <= 1``), the speeds fall by exactly ``a dt`` per step down to ``f a dt`` and then 0, so the
distance covered is ``a dt^2 ((j + 1) f + j (j + 1) / 2)``. Solving that for ``j`` and ``f`` given
the distance gives :func:`braking_speed`. It tends to ``sqrt(2 a d)`` for ``d >> a dt^2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from operator import attrgetter
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError

__all__ = ["JointLimits", "braking_distance", "braking_distance_scalar", "braking_speed",
           "braking_speed_scalar", "velocity_bounds", "velocity_bounds_scalar"]


#: Up to this many values, :func:`braking_speed` evaluates the scalar law value by value.
_SCALAR_LOOP_MAX = 16


def braking_speed_scalar(distance: float, acc: float, dt: float) -> float:
    """Largest speed (rad/s) for the next step of ``dt`` s from which a joint stops within ``distance``
    (rad) braking at ``acc`` (rad/s^2); 0 for ``distance <= 0``. Pure Python, for per-joint loops.

    Exact in discrete time (see the module docstring): a joint that keeps to this speed every step
    stops exactly on the point ``distance`` ahead.
    """
    if distance <= 0.0:
        return 0.0
    adt = acc * dt
    x = distance / (adt * dt)
    j = math.ceil((math.sqrt(1.0 + 8.0 * x) - 3.0) / 2.0)
    if j < 0:
        j = 0
    while (j + 1) * (j + 2) / 2 < x:  # guard the float rounding of the closed form
        j += 1
    while j > 0 and j * (j + 1) / 2 >= x:
        j -= 1
    f = (x - j * (j + 1) / 2) / (j + 1)
    return (j + f) * adt


def braking_speed(distance: Any, acc: Any, dt: float) -> np.ndarray:
    """Vectorised :func:`braking_speed_scalar`: largest next-step speed (rad/s) from which each joint
    stops within ``distance`` (rad, values <= 0 give 0) braking at ``acc`` (rad/s^2), steps of ``dt`` s.

    ``distance`` and ``acc`` broadcast against each other; the result is a float array.
    """
    d = np.asarray(distance, dtype=float)
    a = np.asarray(acc, dtype=float)
    # An arm's few joints (and scalars) go through the scalar law: a dozen numpy calls on seven
    # values cost several times more than seven scalar evaluations, and the controller asks every
    # step. The results are the same numbers; NaN, inf and zero or negative accelerations (errors for
    # the scalar law) take the vectorised path.
    if d.size <= _SCALAR_LOOP_MAX and d.ndim <= 1 and a.shape in ((), d.shape):
        try:
            if a.ndim == 0:
                acc0 = float(a)
                out = [braking_speed_scalar(x, acc0, dt) for x in d.ravel().tolist()]
            else:
                out = [braking_speed_scalar(x, ai, dt) for x, ai in zip(d.tolist(), a.tolist(), strict=True)]
        except (ValueError, OverflowError, ZeroDivisionError):
            pass
        else:
            return np.array(out).reshape(d.shape)
    return _braking_speed_array(d, a, dt)


def _braking_speed_array(distance: np.ndarray, acc: np.ndarray, dt: float) -> np.ndarray:
    """:func:`braking_speed` in numpy, for any shapes and values."""
    d = np.maximum(distance, 0.0)
    adt = acc * dt
    x = d / (adt * dt)
    j = np.maximum(0.0, np.ceil((np.sqrt(1.0 + 8.0 * x) - 3.0) / 2.0))
    # One correction step each way covers the rounding of the closed form (as the scalar loop does).
    j = np.where((j + 1.0) * (j + 2.0) / 2.0 < x, j + 1.0, j)
    j = np.where((j > 0) & (j * (j + 1.0) / 2.0 >= x), j - 1.0, j)
    f = (x - j * (j + 1.0) / 2.0) / (j + 1.0)
    return np.where(d > 0.0, (j + f) * adt, 0.0)


def braking_distance_scalar(speed: float, acc: float, dt: float) -> float:
    """:func:`braking_distance` of one joint in pure Python (the same operations: the same number)."""
    s = abs(speed)
    if not s > 0.0:
        return 0.0
    adt = acc * dt
    k = s / adt
    j = float(math.ceil(k)) - 1.0
    if not j > 0.0:
        j = 0.0
    f = k - j
    return adt * dt * ((j + 1.0) * f + j * (j + 1.0) / 2.0)


def braking_distance(speed: Any, acc: Any, dt: float) -> np.ndarray:
    """Distance (rad, >= 0) a joint covers stopping from ``|speed|`` (rad/s, the speed of its next
    step) while braking at ``acc`` (rad/s^2) in steps of ``dt`` s: the inverse of :func:`braking_speed`
    (``braking_distance(braking_speed(d)) == d``). Tends to ``v^2 / (2 a)`` for large speeds."""
    s = np.abs(np.asarray(speed, dtype=float))
    adt = np.asarray(acc, dtype=float) * dt
    k = s / adt
    j = np.maximum(np.ceil(k) - 1.0, 0.0)
    f = k - j
    return np.where(s > 0.0, adt * dt * ((j + 1.0) * f + j * (j + 1.0) / 2.0), 0.0)


def velocity_bounds_scalar(q: float, v_prev: float, dt: float, lower: float, upper: float, max_vel: float,
                           max_acc: float) -> tuple[float, float]:
    """:func:`velocity_bounds` of one joint in plain floats, with the same picks in the same order (so
    the same floats): for per-joint loops, where seven-element numpy calls cost more than the arithmetic."""
    adt = max_acc * dt
    lo = v_prev - adt
    lo = lo if lo > -max_vel else -max_vel
    hi = v_prev + adt
    hi = hi if hi < max_vel else max_vel
    hi_pos = braking_speed_scalar(upper - q, max_acc, dt)
    lo_pos = -braking_speed_scalar(q - lower, max_acc, dt)
    lo = lo if lo < hi_pos else hi_pos
    lo = lo if lo > lo_pos else lo_pos
    hi = hi if hi > lo_pos else lo_pos
    hi = hi if hi < hi_pos else hi_pos
    return lo, hi


def velocity_bounds(
    q: Any,
    v_prev: Any,
    dt: float,
    lower: Any,
    upper: Any,
    max_vel: Any,
    max_acc: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """Interval ``(lo, hi)`` (rad/s) of velocities allowed for the next step of ``dt`` s.

    Per joint: ``|v| <= max_vel``, ``|v - v_prev| <= max_acc dt``, and slow enough to stop on
    ``lower``/``upper`` (rad) by braking at ``max_acc`` from position ``q`` (:func:`braking_speed`).
    A joint that kept to these bounds in its previous steps always has a non-empty interval; if it
    did not (it already moves too fast towards a limit), the position limit wins (``hi``/``lo`` is the
    braking bound) and the caller's acceleration clamp decides how hard it brakes.
    """
    q = np.asarray(q, dtype=float)
    v_prev = np.asarray(v_prev, dtype=float)
    vmax = np.asarray(max_vel, dtype=float)
    a = np.asarray(max_acc, dtype=float)
    lo = np.maximum(v_prev - a * dt, -vmax)
    hi = np.minimum(v_prev + a * dt, vmax)
    hi_pos = braking_speed(np.asarray(upper, dtype=float) - q, a, dt)
    lo_pos = -braking_speed(q - np.asarray(lower, dtype=float), a, dt)
    return np.maximum(np.minimum(lo, hi_pos), lo_pos), np.minimum(np.maximum(hi, lo_pos), hi_pos)


def _vector(name: str, value: Any, n: int | None) -> np.ndarray:
    a = np.array(value, dtype=float).reshape(-1)
    if (n is not None and a.shape != (n,)) or a.size == 0 or not np.all(np.isfinite(a)):
        want = f"{n} finite values" if n is not None else "finite values"
        raise InvalidInputError(f"{name} must be {want}, got {value!r}", field=name, value=value)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class JointLimits:
    """Motion limits of an ``n``-joint arm: position ``lower``/``upper`` (rad), ``max_vel`` (rad/s),
    ``max_acc`` (rad/s^2), each ``(n,)``. Immutable (the arrays are read-only copies).

    Raises:
        InvalidInputError: shapes differ, a value is not finite, ``lower > upper``, or a velocity or
            acceleration limit is not positive.

    Example::

        lim = JointLimits.from_arm(load_arm("pa10")).inset(1e-3)   # 1 mrad clear of every limit
        lo, hi = lim.velocity_bounds(q, v_prev, dt=0.004)           # admissible next-step speeds
    """

    lower: np.ndarray
    upper: np.ndarray
    max_vel: np.ndarray
    max_acc: np.ndarray

    def __post_init__(self) -> None:
        lower = _vector("lower", self.lower, None)
        n = lower.size
        upper = _vector("upper", self.upper, n)
        vmax = _vector("max_vel", self.max_vel, n)
        amax = _vector("max_acc", self.max_acc, n)
        if np.any(lower > upper):
            raise InvalidInputError("lower must not exceed upper", field="lower", value=self.lower)
        if np.any(vmax <= 0) or np.any(amax <= 0):
            raise InvalidInputError("max_vel and max_acc must be > 0", field="max_vel",
                                    value=(self.max_vel, self.max_acc))
        for name, arr in (("lower", lower), ("upper", upper), ("max_vel", vmax), ("max_acc", amax)):
            object.__setattr__(self, name, arr)

    @classmethod
    def from_arm(cls, arm: Any) -> JointLimits:
        """The limits of an arm model (anything with ``lower``, ``upper``, ``max_vel``, ``max_acc``)."""
        return cls(arm.lower, arm.upper, arm.max_vel, arm.max_acc)

    @property
    def n(self) -> int:
        """Number of joints."""
        return int(self.lower.size)

    def inset(self, margin: float | Any) -> JointLimits:
        """The same limits with the position range shrunk by ``margin`` (rad, >= 0; scalar or (n,))
        at both ends. A range narrower than ``2 margin`` collapses onto its midpoint."""
        m = np.broadcast_to(np.asarray(margin, dtype=float), self.lower.shape)
        if np.any(m < 0) or not np.all(np.isfinite(m)):
            raise InvalidInputError("margin must be finite and >= 0", field="margin", value=margin)
        mid = 0.5 * (self.lower + self.upper)
        return JointLimits(np.minimum(self.lower + m, mid), np.maximum(self.upper - m, mid),
                           self.max_vel, self.max_acc)

    def clip(self, q: Any) -> np.ndarray:
        """``q`` (rad) clipped into ``[lower, upper]`` (a new array)."""
        return np.clip(np.asarray(q, dtype=float), self.lower, self.upper)

    def contains(self, q: Any, tol: float = 0.0) -> np.ndarray:
        """Per joint: ``lower - tol <= q <= upper + tol`` (bool array)."""
        q = np.asarray(q, dtype=float)
        return (q >= self.lower - tol) & (q <= self.upper + tol)

    def velocity_bounds(self, q: Any, v_prev: Any, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """:func:`velocity_bounds` with these limits: admissible next-step velocities (rad/s)."""
        return velocity_bounds(q, v_prev, dt, self.lower, self.upper, self.max_vel, self.max_acc)

    def stop_speeds(self, q: Any, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Largest speeds (rad/s, >= 0) at position ``q`` towards ``upper`` and towards ``lower`` from
        which each joint still stops on that limit braking at ``max_acc`` in steps of ``dt`` s."""
        q = np.asarray(q, dtype=float)
        return (braking_speed(self.upper - q, self.max_acc, dt),
                braking_speed(q - self.lower, self.max_acc, dt))

    def max_jump(self, elapsed_s: Any, margin: float = 0.0) -> np.ndarray:
        """Largest distance (rad) each joint can travel in ``elapsed_s`` seconds at its velocity limit,
        plus ``margin``: a measured position that moved further is implausible."""
        return self.max_vel * np.maximum(np.asarray(elapsed_s, dtype=float), 0.0) + margin


class LimitsView:
    """Mixin: ``lower``, ``upper``, ``max_vel`` and ``max_acc`` read through from ``self.limits``
    (a :class:`JointLimits`), for classes that hold one and expose its arrays (the CAN driver, the
    driver's reference shaper, whose ``limits`` are already inset by its margin)."""

    limits: JointLimits

    lower = property(attrgetter("limits.lower"), doc="Lower position limits (rad).")
    upper = property(attrgetter("limits.upper"), doc="Upper position limits (rad).")
    max_vel = property(attrgetter("limits.max_vel"), doc="Velocity limits (rad/s).")
    max_acc = property(attrgetter("limits.max_acc"), doc="Acceleration limits (rad/s^2).")
