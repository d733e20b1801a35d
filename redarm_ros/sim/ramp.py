"""Per-joint online setpoint generator: trapezoidal moves, streamed steps, ramped velocity, halt.

Pure Python (no numpy, no pybullet) so it is cheap to step at 1 kHz and easy to test.

Position moves track a *reference*. Every step the generator picks the velocity closest to
``reference velocity + correction`` that (a) differs from the current velocity by at most ``acc * dt``
and (b) is at most the velocity cap, where the correction is the largest speed from which the remaining
error can still be closed with deceleration ``acc`` (exact in discrete time, :func:`braking_speed`).

* A single move (FRAMP, or an FSTEP from rest) has a fixed reference at the target: the result is a
  time-optimal trapezoid (or triangle) that lands exactly on the target, never faster than the cap and
  never accelerating harder than ``acc``. An FSTEP's ``duration_s`` caps the cruise speed at
  ``distance / duration_s`` ("get there in that time"; arrival is later by the ramp time).
* FSTEPs arriving back to back (a host streaming one step per cycle, each with the cycle time as
  duration) form a stream: the reference runs linearly from the previous target to the new one over
  ``duration_s`` and its velocity is fed forward, so a smooth stream is followed without lag. A new step
  continues the stream if it arrives within :data:`STREAM_GRACE` durations of the previous one.
  When the stream stops, the reference stops at the last target and the joint brakes at ``acc``; if it
  was faster than ``sqrt(2 acc d)`` for the distance ``d`` left, it overshoots and comes back, as an
  acceleration-limited joint must (a stream that ends abruptly asks for an infinite deceleration).

Acceleration is limited everywhere, velocity is capped everywhere, and the setpoint never leaves
``[lower, upper]``. Units: rad, rad/s, rad/s^2, s.
"""

from __future__ import annotations

import math
from enum import Enum

# Below this distance (rad), with a speed that can stop in one step, a move snaps onto its target.
SNAP_POS = 1e-9
# An FSTEP continues the running stream if it arrives at most this many of its durations after the
# previous one (covers host cycle jitter; a slower host gets single moves from rest).
STREAM_GRACE = 2.0


class RampMode(Enum):
    """What the generator is doing."""

    IDLE = "idle"  # holding ``pos``
    POSITION = "position"  # tracking the position reference towards ``target``
    VELOCITY = "velocity"  # ramping to / holding ``target_vel``
    HALT = "halt"  # braking to rest, then IDLE


def braking_speed(dist: float, acc: float, dt: float) -> float:
    """Largest speed (rad/s) for the next step from which the joint stops exactly after ``dist`` (rad).

    Discrete time, semi-implicit Euler (``v += a dt; p += v dt``): a first speed ``(j + f) acc dt`` with
    integer j >= 0 and 0 < f <= 1, followed by speeds falling by exactly ``acc dt`` per step down to
    ``f acc dt`` and then 0, covers ``acc dt^2 ((j + 1) f + j (j + 1) / 2)``. Solving for j, f given
    ``dist`` makes stops land exactly on the target without ever decelerating harder than ``acc``.
    """
    if dist <= 0.0:
        return 0.0
    adt = acc * dt
    x = dist / (adt * dt)
    j = max(0, math.ceil((math.sqrt(1.0 + 8.0 * x) - 3.0) / 2.0))
    while (j + 1) * (j + 2) / 2 < x:  # guard the float rounding of the closed form
        j += 1
    while j > 0 and j * (j + 1) / 2 >= x:
        j -= 1
    f = (x - j * (j + 1) / 2) / (j + 1)
    return (j + f) * adt


class JointRamp:
    """Setpoint generator of one joint.

    ``lower``/``upper`` (rad) bound the setpoint in every mode; ``max_vel`` (rad/s) and ``max_acc``
    (rad/s^2) are the joint's hard limits: commanded limits are clamped to them.
    """

    def __init__(self, pos: float, lower: float, upper: float, max_vel: float, max_acc: float) -> None:
        if not (max_vel > 0 and max_acc > 0 and lower <= upper):
            raise ValueError("JointRamp needs max_vel > 0, max_acc > 0 and lower <= upper")
        self.lower, self.upper = float(lower), float(upper)
        self.max_vel, self.max_acc = float(max_vel), float(max_acc)
        self.pos = min(max(float(pos), self.lower), self.upper)
        self.vel = 0.0
        self.mode = RampMode.IDLE
        self.target = self.pos
        self.target_vel = 0.0
        self.vel_limit = self.max_vel
        self.acc_limit = self.max_acc
        self.time = 0.0  # s, advanced by step()
        self.ref = self.pos  # position reference (rad)
        self.ref_vel = 0.0  # its velocity while it runs (rad/s)
        self.ref_left = 0.0  # s until the reference reaches the target
        self._stream_until = -math.inf  # an FSTEP before this time continues the stream

    # -- commands ---------------------------------------------------------------------------------
    def _limits(self, vel_limit: float | None, acc_limit: float | None) -> tuple[float, float]:
        v = self.max_vel if vel_limit is None or not vel_limit > 0 else min(float(vel_limit), self.max_vel)
        a = self.max_acc if acc_limit is None or not acc_limit > 0 else min(float(acc_limit), self.max_acc)
        return v, a

    def command_position(
        self,
        target: float,
        vel_limit: float | None = None,
        acc_limit: float | None = None,
        duration_s: float | None = None,
    ) -> None:
        """Move to ``target`` (rad, clamped to the limits) at most at ``vel_limit`` / ``acc_limit``.

        Without ``duration_s`` (FRAMP): a trapezoid. With ``duration_s`` > 0 (FSTEP): a step of that
        duration, continuing a stream of steps if one is running (see the module docstring).
        """
        if not math.isfinite(target):
            raise ValueError("target must be finite")
        v, a = self._limits(vel_limit, acc_limit)
        target = min(max(float(target), self.lower), self.upper)
        dur = float(duration_s) if duration_s is not None and duration_s > 0 else 0.0
        streaming = (
            dur > 0 and self.mode in (RampMode.POSITION, RampMode.IDLE) and self.time <= self._stream_until
        )
        if streaming:
            d = target - self.ref
            t = max(dur, abs(d) / v)
            self.ref_vel, self.ref_left = d / t, t
        else:
            self.ref, self.ref_vel, self.ref_left = target, 0.0, 0.0
            if dur > 0:
                v = min(v, max(abs(target - self.pos) / dur, 1e-9))
        self._stream_until = self.time + STREAM_GRACE * dur if dur > 0 else -math.inf
        self.target, self.vel_limit, self.acc_limit = target, v, a
        self.mode = RampMode.POSITION

    def command_velocity(self, vel: float, acc_limit: float | None = None) -> None:
        """Ramp to velocity ``vel`` (rad/s, clamped to +-max_vel); braking to rest before a joint limit."""
        if not math.isfinite(vel):
            raise ValueError("velocity must be finite")
        _, a = self._limits(None, acc_limit)
        self.target_vel = max(-self.max_vel, min(self.max_vel, float(vel)))
        self.acc_limit = a
        self._stream_until = -math.inf
        self.mode = RampMode.VELOCITY

    def halt(self, acc: float | None = None) -> None:
        """Brake to rest at ``acc`` (default: the joint's max acceleration) and then hold."""
        self.acc_limit = self.max_acc if acc is None or not acc > 0 else float(acc)
        self._stream_until = -math.inf
        self.mode = RampMode.HALT

    def hold(self, pos: float | None = None) -> None:
        """Stop at once and hold ``pos`` (default: the current setpoint); used on reset/re-sync."""
        if pos is not None:
            self.pos = min(max(float(pos), self.lower), self.upper)
        self.vel = 0.0
        self.target = self.ref = self.pos
        self.ref_vel = self.ref_left = 0.0
        self._stream_until = -math.inf
        self.mode = RampMode.IDLE

    @property
    def active(self) -> bool:
        """True while the setpoint moves or will move."""
        return self.mode is not RampMode.IDLE or self.vel != 0.0

    # -- integration ------------------------------------------------------------------------------
    def _idle(self) -> float:
        self.vel = 0.0
        self.mode = RampMode.IDLE
        return self.pos

    def step(self, dt: float) -> float:
        """Advance by ``dt`` (s); returns the new setpoint position (rad)."""
        self.time += dt
        mode, v, a = self.mode, self.vel, self.acc_limit
        if mode is RampMode.IDLE:
            return self._idle()  # also zeroes the landing step's speed (at most acc * dt)
        dv = a * dt
        vcap = self.vel_limit
        if mode is RampMode.POSITION:
            # advance the reference; ff is its velocity over this step
            err = self.ref - self.pos  # tracking error before this step
            if self.ref_left > dt:
                ff = self.ref_vel
                self.ref += ff * dt
                self.ref_left -= dt
            else:
                ff = (self.target - self.ref) / dt if self.ref_left > 0 else 0.0
                self.ref, self.ref_left = self.target, 0.0
            settled = self.ref_left == 0.0 and ff == 0.0
            if settled and abs(self.target - self.pos) <= SNAP_POS and abs(v) <= dv:
                self.pos = self.target
                return self._idle()
            v_des = ff + math.copysign(braking_speed(abs(err), a, dt), err)
            v_des = max(-vcap, min(vcap, v_des))
        elif mode is RampMode.VELOCITY:
            v_des = self.target_vel
            # never run into a joint limit: brake so as to stop on it
            if v_des > 0:
                v_des = min(v_des, braking_speed(self.upper - self.pos, a, dt))
            elif v_des < 0:
                v_des = max(v_des, -braking_speed(self.pos - self.lower, a, dt))
        else:  # HALT
            v_des = 0.0
        v_new = v + max(-dv, min(dv, v_des - v))
        p_new = self.pos + v_new * dt
        if mode is RampMode.POSITION and settled:
            e = self.target - self.pos
            if (self.target - p_new) * e <= 0.0 and abs(v_new) <= dv * (1 + 1e-9):
                # reached at a speed it can stop from; keep that speed for one step (IDLE zeroes it)
                self.vel = e / dt
                self.pos, self.mode = self.target, RampMode.IDLE
                return self.pos
        if p_new >= self.upper or p_new <= self.lower:
            p_clamped = min(max(p_new, self.lower), self.upper)
            v_new = (p_clamped - self.pos) / dt
            p_new = p_clamped
        self.pos, self.vel = p_new, v_new
        if mode is RampMode.HALT and v_new == 0.0:
            self.mode = RampMode.IDLE
        return p_new
