"""Per-joint online setpoint generator, as a module's firmware would run it: moves, streamed steps,
ramped velocity, halt, and the position limits always in view.

Pure Python (no numpy, no pybullet) so it is cheap to step at 1 kHz; the braking law is the one of
:mod:`redarm_ros.motion` (:func:`~redarm_ros.motion.braking_speed_scalar`), shared with the CAN
driver's reference shaper.

Position moves track a *reference*. Every step the generator picks the velocity closest to
``reference velocity + correction`` that (a) differs from the current velocity by at most ``acc * dt``,
(b) is at most the velocity cap and (c) still lets the joint stop on ``lower``/``upper`` braking at
``acc`` (so no mode ever runs into a limit: the setpoint slows down in time instead of being clamped).
The correction is the largest speed from which the remaining error can still be closed with
deceleration ``acc`` (exact in discrete time).

* A single move (FRAMP, or an FSTEP from rest) has a fixed reference at the target: the result is a
  time-optimal trapezoid (or triangle) that lands exactly on the target, never faster than the cap and
  never accelerating harder than ``acc``. An FSTEP's ``duration_s`` caps the cruise speed at
  ``distance / duration_s`` ("get there in that time"; arrival is later by the ramp time).
* FSTEPs arriving back to back (a host streaming one step per cycle with the cycle time as duration;
  each within :data:`STREAM_GRACE` durations of the previous one) form a *stream*, played back from a
  small step buffer as servo drives interpolate cyclic setpoints: the reference is the C1 curve through
  the midpoints of the host's steps, with each step's mean velocity at its midpoint (a cubic Hermite
  piece between two midpoints; for steps of equal duration it is exactly a constant-acceleration
  parabola). A host stream that respects the joint's velocity and acceleration limits therefore gives
  a reference that respects them too, so the joint follows it exactly (feed-forward, no correction
  needed) and never overtakes the stream: each step's target is reached one step after it was due.
  A step that arrives while the previous one still plays waits in the buffer (at most
  :data:`STREAM_BUFFER`; beyond that the oldest waiting step is skipped); when the buffer runs dry the
  reference runs on to the last target at the last step's velocity and stops there, and a step that
  arrives late continues smoothly from wherever the reference is. So arrival jitter does not reach the
  reference. When the stream stops, the joint brakes onto the last target; a stream that stops faster
  than ``acc`` allows is overshot by up to ``v^2 / 2 acc``, as an acceleration-limited joint must (but
  never beyond a position limit). Nor beyond where the host's stream can stop at the earliest (its
  newest target plus the braking distance of its newest step): a stream that arrives late, in bursts,
  lets the joint overtake the reference while the buffer is dry, and a host that brakes for a margin
  of its own (the CAN driver keeps 1 mrad from each limit) would otherwise see the joint pass it; the
  speed is bounded for that point and the integration clamped to it.

Acceleration is limited everywhere, velocity is capped everywhere, and the setpoint never leaves
``[lower, upper]``. Units: rad, rad/s, rad/s^2, s.
"""

from __future__ import annotations

import math
from collections import deque
from enum import Enum

from redarm_ros.motion import braking_speed_scalar

# Below this distance (rad), with a speed that can stop in one step, a move snaps onto its target.
SNAP_POS = 1e-9
# An FSTEP continues the running stream if it arrives at most this many of its durations after the
# previous one (covers host cycle jitter; a slower host gets single moves from rest).
STREAM_GRACE = 2.0
# Steps a stream may queue behind the one playing (a host running ahead, or a burst of steps that
# waited in the bus); beyond that the oldest waiting step is skipped so the lag stays bounded.
STREAM_BUFFER = 4

__all__ = ["JointRamp", "RampMode", "STREAM_BUFFER", "STREAM_GRACE", "braking_speed"]

#: The shared discrete braking law (re-exported for the callers of this module).
braking_speed = braking_speed_scalar


def _braking_distance(speed: float, acc: float, dt: float) -> float:
    """Distance (rad) covered stopping from ``speed`` >= 0 (the next step's) braking at ``acc``:
    the inverse of :func:`~redarm_ros.motion.braking_speed_scalar` (scalar form of
    :func:`redarm_ros.motion.braking_distance`)."""
    if speed <= 0.0:
        return 0.0
    adt = acc * dt
    k = speed / adt
    j = max(math.ceil(k) - 1, 0)
    f = k - j
    return adt * dt * ((j + 1) * f + j * (j + 1) / 2)


def _speed_cap(speed: float, distance: float, acc: float, dt: float) -> float:
    """``min(speed, braking_speed_scalar(distance, acc, dt))``: a speed (rad/s) towards a stop ``distance``
    rad ahead, capped to one from which the joint stops there. The law is evaluated only where it may
    bind (most bounds, per joint and step, do not): its speed ``v`` is at least 0, and since the
    distance it brakes in is at most ``v^2 / 2 acc + v dt / 2 + acc dt^2 / 8``, at least
    ``sqrt(2 acc d) - acc dt / 2``; a speed below that (less a rounding margin) is returned as it is."""
    if speed <= 0.0:
        return speed
    if distance > 0.0:
        least = math.sqrt(2.0 * acc * distance) - 0.5 * acc * dt
        if speed < least - 1e-9 * (least + acc * dt):
            return speed
    return min(speed, braking_speed_scalar(distance, acc, dt))


class _Piece(Enum):
    HERMITE = "hermite"  # towards the next step's midpoint
    TAIL = "tail"  # buffer dry: on to the last target at the last step's velocity
    HOLD = "hold"  # on the last target


class RampMode(Enum):
    """What the generator is doing."""

    IDLE = "idle"  # holding ``pos``
    POSITION = "position"  # tracking the position reference towards ``target``
    VELOCITY = "velocity"  # ramping to / holding ``target_vel``
    HALT = "halt"  # braking to rest, then IDLE


class JointRamp:
    """Setpoint generator of one joint.

    ``lower``/``upper`` (rad) bound the setpoint in every mode (:meth:`set_limits` moves them, e.g. when
    a module's soft limits change); ``max_vel`` (rad/s) and ``max_acc`` (rad/s^2) are the joint's hard
    limits: commanded limits are clamped to them.
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
        # Stream playback (see the module docstring). The reference runs through pieces: HERMITE from
        # (_p0, _v0) to (_p1, _v1) over _tau s, TAIL at constant velocity _v0 from _p0 to the last
        # target, or HOLD on the last target. _knot is the last target taken from the buffer, _knot_vel
        # its step's mean velocity and _knot_dur its duration.
        self._piece = _Piece.HOLD
        self._p0 = self._p1 = self._v0 = self._v1 = 0.0
        self._tau = self._s = 0.0
        self._knot = self._knot_vel = self._knot_dur = 0.0
        self._pending: deque[tuple[float, float]] = deque()  # (target, duration) waiting to play
        self._host = (self.pos, 0.0, 0.0)  # newest streamed target (rad), its step's velocity and duration
        self._fence_key: tuple[tuple[float, float, float], float] | None = None  # (_host, acc) of _host_stop
        self._host_stop = (self.pos, self.pos)  # where the host's stream can stop at the earliest (lo, hi)
        self._streaming = False
        self._stream_until = -math.inf  # an FSTEP before this time continues the stream
        self._single_end = 0.0  # when the last single FSTEP move was due to arrive
        self.skipped_steps = 0  # stream steps dropped because the buffer was full
        self._far_key = (math.nan, math.nan)  # (acc, dt) of _far
        self._far = math.inf  # distance (rad) from which the braking speed is at least max_vel

    # -- commands ---------------------------------------------------------------------------------
    def _limits(self, vel_limit: float | None, acc_limit: float | None) -> tuple[float, float]:
        v = self.max_vel if vel_limit is None or not vel_limit > 0 else min(float(vel_limit), self.max_vel)
        a = self.max_acc if acc_limit is None or not acc_limit > 0 else min(float(acc_limit), self.max_acc)
        return v, a

    def set_limits(self, lower: float, upper: float) -> None:
        """Move the position limits (rad); the setpoint brakes towards the new range from now on."""
        if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
            raise ValueError("limits must be finite with lower <= upper")
        self.lower, self.upper = float(lower), float(upper)
        self.target = min(max(self.target, self.lower), self.upper)

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
        continues = (
            dur > 0 and self.mode in (RampMode.POSITION, RampMode.IDLE) and self.time <= self._stream_until
        )
        if continues:
            if not self._streaming:
                # The previous step was a single move: the stream starts from where the joint is now,
                # its last target being the knot, due at the end of that move's duration.
                self._streaming = True
                self._knot, self._knot_dur = self.ref, 0.0
                self._p0, self._v0 = self.pos, self.vel
                self._piece, self._s = _Piece.TAIL, 0.0
                self._tau = max(0.0, self._single_end - self.time)
            self._queue_step(target, dur)
        else:
            self._streaming = False
            self._pending.clear()
            self.ref = target
            self._single_end = self.time + dur
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
        self._end_stream()
        self.mode = RampMode.VELOCITY

    def halt(self, acc: float | None = None) -> None:
        """Brake to rest at ``acc`` (default: the joint's max acceleration) and then hold."""
        self.acc_limit = self.max_acc if acc is None or not acc > 0 else float(acc)
        self._end_stream()
        self.mode = RampMode.HALT

    def hold(self, pos: float | None = None) -> None:
        """Stop at once and hold ``pos`` (default: the current setpoint); used on reset/re-sync."""
        if pos is not None:
            self.pos = min(max(float(pos), self.lower), self.upper)
        self.vel = 0.0
        self.target = self.ref = self.pos
        self._end_stream()
        self.mode = RampMode.IDLE

    def _end_stream(self) -> None:
        self._streaming = False
        self._pending.clear()
        self._piece = _Piece.HOLD
        self._stream_until = -math.inf

    @property
    def active(self) -> bool:
        """True while the setpoint moves or will move."""
        return self.mode is not RampMode.IDLE or self.vel != 0.0

    @property
    def streaming(self) -> bool:
        """True while a stream of steps is being played (or waits for its next step)."""
        return self._streaming and self.mode is RampMode.POSITION

    # -- integration ------------------------------------------------------------------------------
    def _far_distance(self, a: float, dt: float) -> float:
        """A distance (rad) from which :func:`braking_speed` (at ``a``, steps of ``dt``) is at least
        ``max_vel``: a speed bound from that far is no bound (every speed is capped at ``max_vel`` by
        then) and need not be evaluated. Cached per (a, dt)."""
        if self._far_key != (a, dt):
            far = _braking_distance(self.max_vel, a, dt) * (1.0 + 1e-6) + 1e-12
            while braking_speed_scalar(far, a, dt) < self.max_vel:  # (never taken: rounding guard)
                far *= 2.0
            self._far_key, self._far = (a, dt), far
        return self._far

    def _idle(self) -> float:
        self.vel = 0.0
        self.mode = RampMode.IDLE
        return self.pos

    # -- stream playback ---------------------------------------------------------------------------
    def _queue_step(self, target: float, dur: float) -> None:
        """Take one streamed step: queue it behind a playing piece, or start playing it now."""
        prev = self._pending[-1][0] if self._pending else self._knot
        self._host = (target, (target - prev) / dur, dur)  # the host's newest position, velocity, step
        if self._piece is _Piece.HERMITE:
            if len(self._pending) >= STREAM_BUFFER:
                self._pending.popleft()
                self.skipped_steps += 1
            self._pending.append((target, dur))
            return
        # TAIL or HOLD (stream start, or the buffer ran dry): continue smoothly from the reference as it
        # is now. The new step's midpoint is reached after the rest of the tail plus one and a half
        # steps, so the next step (due one step from now) is already buffered when it is needed: half a
        # step of arrival jitter is absorbed.
        if self._piece is _Piece.TAIL:
            p, v, left = self._p0 + self._v0 * self._s, self._v0, max(0.0, self._tau - self._s)
        else:
            p, v, left = self.ref, 0.0, 0.0
        self._start_hermite(p, v, target, dur, left + 1.5 * dur)

    def _start_hermite(self, p: float, v: float, target: float, dur: float, tau: float) -> None:
        u = (target - self._knot) / dur
        p1 = 0.5 * (self._knot + target)
        delta, fastest = p1 - p, max(abs(v), abs(u))
        if fastest > 0.0 and delta * v >= 0.0 and delta * u >= 0.0:
            # Both end velocities point the way to go: a cubic stays monotone (never passes p1) if
            # neither end speed exceeds 3 delta / tau (Fritsch and Carlson), so shorten tau if needed.
            tau = min(tau, 3.0 * abs(delta) / fastest)
        self._p0, self._v0 = p, v
        self._p1, self._v1 = p1, u
        self._tau, self._s = max(tau, 1e-9), 0.0
        self._piece = _Piece.HERMITE
        self._knot, self._knot_vel, self._knot_dur = target, u, dur

    def _stream_fence(self, a: float) -> tuple[float, float]:
        """(lower, upper) bound (rad) of the setpoint while streaming: the hull of the reference and of
        where the host's stream can stop at the earliest, i.e. its newest target widened in the
        direction of that step's velocity ``u`` by the distance a host braking at ``a`` from there
        covers (its next step is at least ``|u| - a h`` fast; its steps last ``h``)."""
        if self._fence_key != (self._host, a):  # (computed once per host step, used every physics step)
            q, u, h = self._host
            d = _braking_distance(abs(u) - a * h, a, h)
            self._fence_key = (self._host, a)
            self._host_stop = (q - d if u < 0.0 else q), (q + d if u > 0.0 else q)
        lo, hi = self._host_stop
        return min(lo, self.ref), max(hi, self.ref)

    def _advance_reference(self, dt: float) -> float:
        """Move the stream reference on by ``dt`` (s) through its pieces; returns its mean velocity."""
        ref0 = self.ref
        self._s += dt
        while self._piece is not _Piece.HOLD and self._s >= self._tau:
            self._s -= self._tau  # carry the rest into the next piece: no pause between steps
            if self._piece is _Piece.HERMITE and self._pending:
                target, dur = self._pending.popleft()
                carry = self._s
                self._start_hermite(self._p1, self._v1, target, dur, 0.5 * (self._knot_dur + dur))
                self._s = carry
            elif self._piece is _Piece.HERMITE:
                # Buffer dry: run on to the last target at the last step's velocity.
                self._p0, self._v0 = self._p1, self._v1
                self._tau = 0.5 * self._knot_dur
                self._piece = _Piece.TAIL
            else:
                self._piece, self._s = _Piece.HOLD, 0.0
        if self._piece is _Piece.HERMITE and self._p0 == self._p1 and self._v0 == 0.0 and self._v1 == 0.0:
            # A piece that holds still (a host holding the arm): the cubic's exact value, not its
            # rounding, which moved the reference by an ulp now and then and the setpoint with it.
            self.ref = self._p1
        elif self._piece is _Piece.HERMITE:
            t = self._s / self._tau
            t2, t3 = t * t, t * t * t
            self.ref = ((2 * t3 - 3 * t2 + 1) * self._p0 + (t3 - 2 * t2 + t) * self._tau * self._v0
                        + (3 * t2 - 2 * t3) * self._p1 + (t3 - t2) * self._tau * self._v1)
        elif self._piece is _Piece.TAIL:
            self.ref = self._p0 + self._v0 * self._s
        else:
            self.ref = self._knot
        return (self.ref - ref0) / dt

    def step(self, dt: float) -> float:
        """Advance by ``dt`` (s); returns the new setpoint position (rad)."""
        self.time += dt
        mode, v, a = self.mode, self.vel, self.acc_limit
        if mode is RampMode.IDLE:
            return self._idle()  # also zeroes the landing step's speed (at most acc * dt)
        dv = a * dt
        vcap = self.vel_limit
        settled = False
        if mode is RampMode.POSITION:
            err = self.ref - self.pos  # tracking error before this step
            ff = self._advance_reference(dt) if self._streaming else 0.0
            settled = ff == 0.0 and self.ref == self.target and not self._pending
            if settled and abs(self.target - self.pos) <= SNAP_POS and abs(v) <= dv:
                self.pos = self.target
                return self._idle()
            if ff == 0.0 and v == 0.0 and self._streaming and self.ref == self.pos \
                    and self._host[0] == self.pos and self._host[1] == 0.0:
                # A stream that holds still (a host holding the arm sends the same step every cycle):
                # reference, error, fence and every speed below are zero, so the setpoint stays where
                # it is; skip the law's evaluation (7 joints at 1 kHz are most of a held arm's cost).
                self.vel = 0.0
                return self.pos
            v_des = ff + math.copysign(braking_speed_scalar(abs(err), a, dt), err)
            if ff != 0.0:
                # Never overtake the reference: stay slow enough to stop where the reference could
                # stop at the earliest (braking at ``acc``), so a lag is made up only where the joint
                # has acceleration to spare and a reference braking at ``acc`` is never passed.
                d_ref = _braking_distance(abs(ff), a, dt)
                if ff > 0.0:
                    v_des = min(v_des, braking_speed_scalar(err + d_ref, a, dt))
                else:
                    v_des = max(v_des, -braking_speed_scalar(d_ref - err, a, dt))
            # (Bounds from at least far away are at least max_vel >= vcap: the cap below decides, so
            # they are not evaluated.)
            far = self._far_distance(a, dt)
            if self._streaming:
                # The host's stream stops at the earliest on its last target plus the braking distance
                # of that step's velocity (a host braking for a limit of its own, e.g. the CAN driver's
                # margin, stops there): never faster than allows stopping on that point, and never
                # past it (below). A joint that overtook a late stream (the buffer ran dry, the
                # reference stopped, the joint ran on) otherwise stayed ahead of it and passed the
                # host's stop: 0.5-0.9 mrad past the driver's 1 mrad margin.
                fence_lo, fence_hi = self._stream_fence(a)
                if fence_hi - self.pos < far:
                    v_des = _speed_cap(v_des, fence_hi - self.pos, a, dt)
                if self.pos - fence_lo < far:
                    v_des = -_speed_cap(-v_des, self.pos - fence_lo, a, dt)
            v_des = max(-vcap, min(vcap, v_des))
        elif mode is RampMode.VELOCITY:
            v_des = self.target_vel
            far = self._far_distance(a, dt)
        else:  # HALT
            v_des = 0.0
            far = self._far_distance(a, dt)
        # The limits in view in every mode: never faster towards one than allows stopping on it
        # (|v_des| <= max_vel here: a bound from at least ``far`` away changes nothing).
        if self.upper - self.pos < far:
            v_des = _speed_cap(v_des, self.upper - self.pos, a, dt)
        if self.pos - self.lower < far:
            v_des = -_speed_cap(-v_des, self.pos - self.lower, a, dt)
        v_new = v + max(-dv, min(dv, v_des - v))
        p_new = self.pos + v_new * dt
        if settled:
            e = self.target - self.pos
            if (self.target - p_new) * e <= 0.0 and abs(v_new) <= dv * (1 + 1e-9):
                # reached at a speed it can stop from; keep that speed for one step (IDLE zeroes it)
                self.vel = e / dt
                self.pos, self.mode = self.target, RampMode.IDLE
                self._streaming = False
                return self.pos
        if mode is RampMode.POSITION and self._streaming:
            # Clamp the integration too, not only the speed: a step never carries the setpoint past the
            # host's stop point (it binds only after a late stream let the joint overtake it). (The
            # fence of the speed bound above: nothing it depends on changed since.)
            if p_new > fence_hi and v_new > 0.0:
                p_new = max(self.pos, fence_hi)
                v_new = (p_new - self.pos) / dt
            elif p_new < fence_lo and v_new < 0.0:
                p_new = min(self.pos, fence_lo)
                v_new = (p_new - self.pos) / dt
        if p_new >= self.upper or p_new <= self.lower:
            # Only reached when the joint already moved too fast towards a limit (it started outside
            # the braking envelope, e.g. after set_limits): stop on the limit rather than pass it.
            p_clamped = min(max(p_new, self.lower), self.upper)
            v_new = (p_clamped - self.pos) / dt
            p_new = p_clamped
        self.pos, self.vel = p_new, v_new
        if mode is RampMode.HALT and v_new == 0.0:
            self.mode = RampMode.IDLE
        return p_new
