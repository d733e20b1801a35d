"""Per-joint velocity and acceleration limits for one control step (numpy only, no ROS).

The controller produces a joint target each step; :func:`limit_step` turns it into a command that
respects, per joint, ``|v| <= max_vel``, ``|v - v_prev| <= max_acc * dt`` and the joint position limits,
braking onto those limits in time (the command never needs more than ``max_acc`` to stop before a
limit). Velocities are finite differences of commanded positions over ``dt``. Units: rad, rad/s,
rad/s^2, s.

The braking law and the admissible velocity interval are those of :mod:`redarm_ros.motion.limits`,
the one law the driver's reference shaper and the simulator's setpoint generator follow too (exact
in discrete time: a joint keeping to :func:`braking_speed` stops on the point, not before or past
it). This module keeps the controller's API on top of it: the step limiter and its argument order.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from redarm_ros.kinematics.protocols import ControlledArm
from redarm_ros.motion import limits as motion


class LimitMode(enum.Enum):
    """How :func:`limit_step` had to change the target."""

    EXACT = "exact"  # the target itself fits every limit
    SCALED = "scaled"  # the whole joint step was shortened by ``alpha`` (same direction: path kept)
    CLIPPED = "clipped"  # joints were limited one by one (the direction changed: path left)


@dataclass(frozen=True)
class LimitedStep:
    """Result of :func:`limit_step`: command ``q`` (rad), its velocity ``v`` (rad/s), the ``mode`` and,
    for SCALED/EXACT, the fraction ``alpha`` of the requested step that was taken."""

    q: np.ndarray
    v: np.ndarray
    mode: LimitMode
    alpha: float


def braking_speed(distance: np.ndarray | float, acc: np.ndarray | float, dt: float) -> np.ndarray:
    """Largest speed (rad/s) for the next step of ``dt`` s from which a joint ``distance`` rad away
    from a stop can still stop there braking at ``acc`` (rad/s^2): :func:`redarm_ros.motion.limits.
    braking_speed` (the scalar form for plain numbers: the laws call it once per step)."""
    if isinstance(distance, float | int) and isinstance(acc, float | int):
        return np.asarray(motion.braking_speed_scalar(float(distance), float(acc), dt))
    return motion.braking_speed(distance, acc, dt)


def braking_distance(speed: np.ndarray | float, acc: np.ndarray | float, dt: float) -> np.ndarray:
    """Distance (rad) a joint covers stopping from ``speed`` braking at ``acc``: the inverse of
    :func:`braking_speed` (:func:`redarm_ros.motion.limits.braking_distance`)."""
    return motion.braking_distance(speed, acc, dt)


def velocity_bounds(q_prev: np.ndarray, v_prev: np.ndarray, dt: float, max_vel: np.ndarray,
                    max_acc: np.ndarray, lower: np.ndarray, upper: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint interval (rad/s) of velocities allowed this step: velocity limit, acceleration limit
    around ``v_prev`` and braking onto the position limits. Where the braking bound contradicts the
    acceleration bound (the joint already moves too fast towards a limit) the position limit wins.
    :func:`redarm_ros.motion.limits.velocity_bounds` in the controller's argument order."""
    return motion.velocity_bounds(q_prev, v_prev, dt, lower, upper, max_vel, max_acc)


def limit_step(q_prev: np.ndarray, v_prev: np.ndarray, q_target: np.ndarray, dt: float,
               max_vel: np.ndarray, max_acc: np.ndarray, lower: np.ndarray, upper: np.ndarray
               ) -> LimitedStep:
    """Command for one step of ``dt`` s from ``q_prev`` (rad, moving at ``v_prev`` rad/s) towards
    ``q_target`` (rad) within the velocity, acceleration and position limits.

    First the whole step is scaled by the largest ``alpha`` in [0, 1] that fits every joint (the
    joint-space direction, hence the path, is kept); if no common scale exists (a joint must brake
    while another must not, e.g. the path bends), each joint is clipped to its own interval.
    """
    lo, hi = velocity_bounds(q_prev, v_prev, dt, max_vel, max_acc, lower, upper)
    v_des = (q_target - q_prev) / dt
    a_lo, a_hi = 0.0, 1.0
    feasible = True
    for j in range(v_des.shape[0]):
        vd = float(v_des[j])
        if abs(vd) < 1e-12:
            if lo[j] > 1e-12 or hi[j] < -1e-12:
                feasible = False
                break
            continue
        x, y = lo[j] / vd, hi[j] / vd
        if x > y:
            x, y = y, x
        a_lo, a_hi = max(a_lo, x), min(a_hi, y)
        if a_lo > a_hi + 1e-12:
            feasible = False
            break
    if feasible and a_lo <= min(a_hi, 1.0) + 1e-12:
        alpha = max(min(a_hi, 1.0), a_lo)
        if alpha >= 1.0 - 1e-12:
            q = np.clip(q_target, lower, upper)
            return LimitedStep(q, (q - q_prev) / dt, LimitMode.EXACT, 1.0)
        v = alpha * v_des
        q = np.clip(q_prev + v * dt, lower, upper)
        return LimitedStep(q, (q - q_prev) / dt, LimitMode.SCALED, alpha)
    v = np.clip(v_des, lo, hi)
    q = np.clip(q_prev + v * dt, lower, upper)
    return LimitedStep(q, (q - q_prev) / dt, LimitMode.CLIPPED, math.nan)


def track_step(q: list[float], qd: list[float], q_ref: list[float], qd_ref: list[float], dt: float,
               bounds: JointBounds) -> tuple[list[float], list[float]]:
    """One command step (rad, rad/s) from ``q`` moving at ``qd`` towards a reference at ``q_ref``
    moving at ``qd_ref`` (plain float lists; finite values): the reference velocity (clipped to the
    velocity limit) fed forward plus the speed from which the lag can still be braked away, within
    :func:`velocity_bounds`; lands exactly on a resting reference within 1e-12 rad.

    Joint by joint in plain floats: seven-element numpy calls cost several times the arithmetic. The
    operations are those of the array form (np.clip is ``x if x > lo else lo`` then ``y if y < hi else
    hi``, np.maximum / np.minimum pick the same way, np.sign gives +0.0 for -0.0), so the floats are
    the same, signed zeros included (test_control_joint_limits compares the two)."""
    bs, bounds_of = motion.braking_speed_scalar, motion.velocity_bounds_scalar
    q_new: list[float] = []
    qd_new: list[float] = []
    for qc, vp, qr, vr, lower, upper, vmax, acc in zip(q, qd, q_ref, qd_ref, *bounds.lists, strict=True):
        u = vr if vr > -vmax else -vmax  # the reference velocity within the velocity limit
        u = u if u < vmax else vmax
        e = qr - u * dt - qc  # the lag behind where the reference was a step ago
        sign = 1.0 if e > 0.0 else (-1.0 if e < 0.0 else 0.0)
        v = u + sign * bs(abs(e), acc, dt)
        lo, hi = bounds_of(qc, vp, dt, lower, upper, vmax, acc)
        v = v if v > lo else lo
        v = v if v < hi else hi
        if abs(qr - qc) <= 1e-12 and abs(vr) <= 1e-12 and lo <= 0.0 and hi >= 0.0:
            v = 0.0  # land exactly on a resting reference
        x = qc + v * dt
        x = x if x > lower else lower
        x = x if x < upper else upper
        if abs(qr - x) <= 1e-12:
            x = qr
        q_new.append(x)
        qd_new.append((x - qc) / dt)
    return q_new, qd_new


def brake_step(q_prev: np.ndarray, v_prev: np.ndarray, dt: float, max_acc: np.ndarray,
               lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One step of the hardest allowed braking (each joint's speed reduced towards 0 by
    ``max_acc * dt``); returns ``(q, v)``."""
    v = np.sign(v_prev) * np.maximum(np.abs(v_prev) - max_acc * dt, 0.0)
    q = np.clip(q_prev + v * dt, lower, upper)
    return q, (q - q_prev) / dt


@dataclass(frozen=True)
class JointBounds:
    """An arm's joint limits as arrays: positions ``lower``/``upper`` (rad), ``max_vel`` (rad/s) and its
    reciprocal ``inv_vel``, ``max_acc`` (rad/s^2)."""

    lower: np.ndarray
    upper: np.ndarray
    max_vel: np.ndarray
    inv_vel: np.ndarray
    max_acc: np.ndarray

    @cached_property
    def lists(self) -> tuple[list[float], list[float], list[float], list[float]]:
        """(lower, upper, max_vel, max_acc) as plain float lists (the per-joint loop of
        :func:`track_step`)."""
        return self.lower.tolist(), self.upper.tolist(), self.max_vel.tolist(), self.max_acc.tolist()

    @classmethod
    def of(cls, arm: ControlledArm) -> JointBounds:
        """The limits of ``arm``."""
        max_vel = np.asarray(arm.max_vel, float)
        return cls(np.asarray(arm.lower, float), np.asarray(arm.upper, float), max_vel, 1.0 / max_vel,
                   np.asarray(arm.max_acc, float))


def joint_share_acc(rate: float, default: float, qd: np.ndarray, max_acc: np.ndarray, share: float) -> float:
    """Largest rate of change of ``rate`` (a hand speed or an orientation rate) that keeps every joint
    within ``share`` of its acceleration limit ``max_acc``, the joint velocities ``qd`` of the last
    reference step taken as proportional to ``rate``; ``default`` caps it and is used at rest."""
    acc = max_acc.tolist()  # (plain floats: the same quotients and least one, without numpy's per-call cost)
    if rate < 1e-4:  # from rest: a gentle first step, the ratio is measured from the next one
        return min(default, 0.1 * min(acc))
    least = math.inf
    moving = False
    for a_j, v in zip(acc, qd.tolist(), strict=True):
        v = abs(v)
        if v > 1e-6:
            moving = True
            least = min(least, a_j / v)
    if not moving:
        return default
    a = least * rate * share
    return max(min(a, default), 1e-3)
