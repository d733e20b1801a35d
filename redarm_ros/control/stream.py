"""Goal streams: telling a stream from a new goal, and estimating where the streamed goal is now.

**Stream or new goal.** A goal message continues the current stream when it arrives within
``gap`` s of the previous message and lies within ``jump`` m / ``jump_angle`` rad of where the
stream was predicted to be at its stamp; otherwise it is a new goal (a click elsewhere, a new task),
reached by the attractor dynamics. The first message of a stream is therefore a new goal; from the
second one on the controller tracks (phase TRACKING). A message that repeats the active point goal
(within the reach tolerances) changes nothing (a goal republished at a fixed rate stays a point
goal).

**Clock.** Header stamps within ``clock_tolerance`` of the receive clock are taken as on that clock
(ROS time on one machine or synchronised machines). Otherwise (sim time, another machine's clock) the
offset is estimated as the smallest ``arrival - stamp`` seen, which leaves the transport delay out:
the goal is then followed with that delay. A zero stamp means "now": the arrival time is used.

**Estimate.** Over the samples whose stamps lie within ``window`` s of the newest (at least the
newest three within ``gap``), a least-squares fit ``p(tau) = p0 + v tau + a tau^2 / 2`` (tau =
stamp - newest stamp; the acceleration with a small ridge weight ``accel_weight``) gives position,
velocity and acceleration at the newest stamp; the same fit on rotation vectors (relative to the
newest orientation) gives the angular motion. A fit averages out stamp jitter; samples may arrive in
any order (late ones are inserted by stamp, duplicates and stale ones dropped) and may be missing
(the period is the median stamp spacing, which a dropped message does not move). The goal at time
``t`` is the fit evaluated ``t - newest stamp + lead`` s ahead, at most ``extrapolate_periods``
periods: a stream that stops does not drag the target on. ``end_periods`` periods after the last
arrival the stream has ended and the target is the last goal itself, at rest.

Units: s, m, rad; quaternions (w, x, y, z).
"""

from __future__ import annotations

import math
from bisect import insort
from dataclasses import dataclass, field

import numpy as np

from redarm_ros.control.params import StreamParams
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.kinematics.quaternion import (
    matrix_from_quat,
    quat_angle,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    rotvec_between,
)


def _rotvec_matrices(rv: np.ndarray) -> np.ndarray:
    """Rotation matrices (k, 3, 3) of rotation vectors ``rv`` (k, 3) rad (Rodrigues)."""
    th = np.linalg.norm(rv, axis=1)
    safe = np.where(th > 1e-12, th, 1.0)
    u = rv / safe[:, None]
    K = np.zeros((len(rv), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -u[:, 2], u[:, 1], -u[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = u[:, 2], -u[:, 1], u[:, 0]
    s = np.where(th > 1e-12, np.sin(th), 0.0)[:, None, None]
    c = np.where(th > 1e-12, 1.0 - np.cos(th), 0.0)[:, None, None]
    return np.eye(3) + s * K + c * (K @ K)


def _median_spacing(stamps: list[float]) -> float:
    """Median of the gaps (s) between sorted ``stamps`` longer than 1 us (inf if there is none)."""
    gaps = sorted(b - a for a, b in zip(stamps, stamps[1:], strict=False) if b - a > 1e-6)
    if not gaps:
        return math.inf
    mid = len(gaps) // 2
    return gaps[mid] if len(gaps) % 2 else 0.5 * (gaps[mid - 1] + gaps[mid])


@dataclass(frozen=True)
class StreamTarget:
    """Where the streamed goal is: ``pos`` (m), ``rot`` (w, x, y, z), ``vel`` (m/s), ``w`` (rad/s,
    base frame); ``ended``: the stream stopped (the target is its last goal, at rest)."""

    pos: Vec3
    rot: Quat
    vel: Vec3
    w: Vec3
    ended: bool


@dataclass(order=True)
class _Sample:
    t: float
    pos: Vec3 = field(compare=False)
    rot: Quat = field(compare=False)


class StreamEstimator:
    """State of one goal stream (see the module docstring)."""

    def __init__(self, params: StreamParams | None = None) -> None:
        self.params = params or StreamParams()
        self.reset()

    def reset(self) -> None:
        """Forget the stream."""
        self._samples: list[_Sample] = []
        self._offset: float | None = None  # receive clock - stamp clock (s), None: same clock
        self._last_arrival = -math.inf
        self._fit: tuple[np.ndarray, ...] | None = None
        self._fit3: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (p0, v, a) of _fitted_turn
        self._tau_pos: tuple[np.ndarray, np.ndarray] | None = None  # the fit's stamps (tau) and positions
        self._still: tuple[Quat, np.ndarray] | None = None  # see _still_rotation
        self._period: float | None = None  # period() of the samples as they are (None: not computed yet)
        self.count = 0  # samples accepted since reset
        self.dropped = 0  # out-of-window or duplicate samples ignored

    # -- clock ------------------------------------------------------------------------------------
    def stamp_time(self, stamp: float | None, now: float) -> float:
        """A message stamp (s) on the receive clock (``now``, s)."""
        if stamp is None or stamp == 0.0 or not math.isfinite(stamp):
            return now
        if self._offset is None and abs(now - stamp) <= self.params.clock_tolerance:
            return stamp
        off = now - stamp
        self._offset = off if self._offset is None else min(self._offset, off)
        return stamp + self._offset

    # -- samples ----------------------------------------------------------------------------------
    @property
    def newest(self) -> _Sample | None:
        """The sample with the newest stamp."""
        return self._samples[-1] if self._samples else None

    def period(self) -> float:
        """Median spacing (s) of the stamps in the window (inf with fewer than two samples)."""
        # Asked several times per control step; the samples change only in add().
        if self._period is None:
            self._period = _median_spacing([s.t for s in self._samples])
        return self._period

    def rate(self) -> float:
        """Message rate (Hz) of the stream, 0 if unknown."""
        T = self.period()
        return 0.0 if not math.isfinite(T) else 1.0 / T

    def end_time(self) -> float:
        """How long (s) after the last arrival the stream counts as stopped."""
        p = self.params
        T = self.period()
        if not math.isfinite(T):
            return p.gap
        return min(max(p.end_periods * T, p.end_min), p.gap)

    def ended(self, now: float) -> bool:
        """The stream stopped (or never started)."""
        return now - self._last_arrival > self.end_time()

    def recent(self, now: float) -> bool:
        """A message arrived within ``gap`` s."""
        return now - self._last_arrival <= self.params.gap

    def add(self, pos: Vec3, rot: Quat, t: float, now: float) -> bool:
        """Add a sample stamped ``t`` (receive clock, s) that arrived at ``now``. Returns False if it
        was ignored (a duplicate stamp, or older than the window)."""
        self._last_arrival = max(self._last_arrival, now)
        newest = self.newest
        if newest is not None:
            if t < newest.t - self.params.window:
                self.dropped += 1
                return False
            if any(abs(s.t - t) < 1e-6 for s in self._samples):
                self.dropped += 1
                return False
        insort(self._samples, _Sample(t, (pos[0], pos[1], pos[2]), (rot[0], rot[1], rot[2], rot[3])))
        t_new = self._samples[-1].t
        # Keep the window, at least three samples (a slow stream), nothing older than the gap.
        while self._samples[0].t < t_new - self.params.gap or \
                (len(self._samples) > 3 and self._samples[0].t < t_new - self.params.window):
            self._samples.pop(0)
        self.count += 1
        self._fit = self._fit3 = self._period = None
        return True

    # -- fit and prediction -----------------------------------------------------------------------
    def _fitted(self) -> tuple[np.ndarray, ...]:
        """(p0, v, a, r0, w, alpha): position, velocity and acceleration at the newest stamp, and the
        same for the rotation vector relative to the newest orientation."""
        if self._fit is not None:
            return self._fit
        ref = self._samples[-1]
        n = len(self._samples)
        tau = np.array([s.t - ref.t for s in self._samples])
        P = np.array([s.pos for s in self._samples])
        # (a stream that keeps its orientation: the one rotation vector, not one call per sample)
        same = rotvec_between(ref.rot, ref.rot)
        R = np.array([same if s.rot == ref.rot else rotvec_between(ref.rot, s.rot) for s in self._samples])
        self._tau_pos = (tau, P)
        z = np.zeros(3)
        if n == 1:
            self._fit = (P[0], z, z, z, z, z)
            return self._fit
        A = np.empty((n, 3 if n >= 3 else 2))  # columns 1, tau, tau^2 / 2 (n >= 3)
        A[:, 0] = 1.0
        A[:, 1] = tau
        if n >= 3:
            A[:, 2] = 0.5 * tau * tau
        M = A.T @ A
        if n >= 3:
            M[2, 2] += self.params.accel_weight
        try:
            X = np.linalg.solve(M, A.T @ np.hstack([P, R]))
        except np.linalg.LinAlgError:
            X = np.zeros((A.shape[1], 6))
            X[0] = np.hstack([P[-1], R[-1]])
        acc = X[2] if n >= 3 else np.zeros(6)
        self._fit = (X[0, :3], X[1, :3], acc[:3], X[0, 3:], X[1, 3:], acc[3:])
        return self._fit

    def _fitted_turn(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p0, v, a): position, velocity and acceleration at the newest stamp of the positions' fit on a
        path that turns at a constant rate ``w``:
        ``p(tau) = p0 + v sin(w tau) / w + a (1 - cos(w tau)) / w^2``
        (a circle at constant speed exactly; the quadratic fit as ``w`` goes to 0), ``w = |a_n| / |v|`` of
        the fit before, three times over from the quadratic fit. The quadratic fit takes a turning path's
        jerk for a deceleration (on a circle at 0.3 m/s its acceleration comes out a third too short), a
        free cubic fit amplifies the stamps' jitter."""
        if self._fit3 is not None:
            return self._fit3
        p0, v, a, *_ = self._fitted()
        n = len(self._samples)
        if n >= 4:
            tau, P = self._tau_pos  # (of the same samples as the fit)
            A = np.empty((n, 3))
            A[:, 0] = 1.0
            for _ in range(3):
                speed2 = float(v @ v)
                if speed2 < 1e-12:
                    break
                a_n = a - (float(a @ v) / speed2) * v
                w = math.sqrt(float(a_n @ a_n) / speed2)
                if not 1e-3 < w * float(-tau[0]) < 1.0:
                    break  # (straight: the quadratic fit is the fit; over 1 rad: no turn to trust)
                A[:, 1] = np.sin(w * tau) / w
                A[:, 2] = (1.0 - np.cos(w * tau)) / (w * w)
                M = A.T @ A
                M[2, 2] += self.params.accel_weight
                try:
                    X = np.linalg.solve(M, A.T @ P)
                except np.linalg.LinAlgError:
                    break
                p0, v, a = X[0], X[1], X[2]
        self._fit3 = (p0, v, a)
        return self._fit3

    def path_poses(self, times: np.ndarray, now: float) -> np.ndarray | None:
        """The goal's poses (k, 4, 4) at ``times`` (k,) s, further ahead than :meth:`predict` trusts a
        parabola: the hand goes on along a path of constant curvature (a circle, or a line) in the plane of
        its velocity and acceleration, its speed changing at the present tangential acceleration for at
        most ``window`` s (never below 0), from :meth:`_fitted_turn`; the orientation extrapolated as by
        :meth:`predict`. With the lead. None before the first sample, once the stream has ended (``now``
        s), and while no sample has come for longer than :meth:`predict` extrapolates."""
        if not self._samples or self.ended(now):
            return None
        ref = self._samples[-1]
        T = self.period()
        if not math.isfinite(T) or now - ref.t > self.params.extrapolate_periods * T:
            return None  # (no newer sample for longer than predict() extrapolates: the stream may stop)
        tau = np.asarray(times, float) + self.params.lead - ref.t
        p0, v, a = self._fitted_turn()
        out = np.zeros((len(tau), 4, 4))
        out[:, 3, 3] = 1.0
        speed = float(np.linalg.norm(v))
        if speed < 1e-6:
            _, _, _, r0, w, al = self._fitted()
            out[:, :3, 3] = p0
        else:
            e = v / speed
            a_t = float(a @ e)
            a_n = a - a_t * e
            k = float(np.linalg.norm(a_n)) / (speed * speed)  # curvature (1/m)
            # The speed changes at a_t for at most the fit's window (then it holds; never below 0): a
            # speed-up or a slow-down seen in the window is not taken to last.
            lasts = self.params.window if a_t >= 0.0 else min(self.params.window, speed / -a_t)
            tt = np.minimum(tau, lasts)
            arc = speed * tau + a_t * tt * (tau - 0.5 * tt)
            if k * float(np.abs(arc).max()) < 1e-9:
                out[:, :3, 3] = p0 + arc[:, None] * e
            else:
                nrm = a_n / (k * speed * speed)
                th = k * arc
                out[:, :3, 3] = p0 + (np.sin(th)[:, None] * e + (1.0 - np.cos(th))[:, None] * nrm) / k
            _, _, _, r0, w, al = self._fitted()
        rv = r0 + tau[:, None] * w + 0.5 * (tau * tau)[:, None] * al
        if rv.any():
            out[:, :3, :3] = _rotvec_matrices(rv) @ np.asarray(matrix_from_quat(ref.rot))
        else:  # the orientation holds: every row the identity times R0, the same numbers, made once
            out[:, :3, :3] = self._still_rotation(ref.rot)
        return out

    def _still_rotation(self, rot: Quat) -> np.ndarray:
        """``_rotvec_matrices(0) @ R(rot)`` (1, 3, 3), as the general case computes it for a zero rotation
        vector (the exact identity times R), kept for the last ``rot``."""
        kept = self._still
        if kept is None or kept[0] != rot:
            kept = self._still = (rot, _rotvec_matrices(np.zeros((1, 3))) @ np.asarray(matrix_from_quat(rot)))
        return kept[1]

    def velocity(self) -> tuple[Vec3, Vec3]:
        """Estimated linear (m/s) and angular (rad/s) velocity of the stream."""
        if not self._samples:
            return (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        _, v, _, _, w, _ = self._fitted()
        return (float(v[0]), float(v[1]), float(v[2])), (float(w[0]), float(w[1]), float(w[2]))

    def predict(self, t: float, now: float | None = None, *, lead: bool = True,
                clamp: bool = True) -> StreamTarget | None:
        """The goal at time ``t`` (receive clock, s); ``now`` (default ``t``) decides whether the
        stream has ended. ``lead``: add ``params.lead``; ``clamp``: extrapolate at most
        ``extrapolate_periods`` periods. None before the first sample."""
        if not self._samples:
            return None
        now = t if now is None else now
        ref = self._samples[-1]
        if self.ended(now):
            return StreamTarget(ref.pos, ref.rot, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), True)
        # Plain floats from here (3-vectors: numpy's per-call cost is most of the work; the same
        # arithmetic element by element gives the same numbers).
        p0, v, a, r0, w, al = (x.tolist() for x in self._fitted())
        T = self.period()
        ahead = self.params.lead if lead else 0.0
        # (the lead is a known delay made up for, not a guess: the clamp applies beyond it)
        horizon = self.params.extrapolate_periods * (T if math.isfinite(T) else 0.0) + ahead
        tau = t + ahead - ref.t
        if not clamp:
            horizon = max(horizon, tau)
        moving = tau <= horizon
        tau = min(max(tau, -self.params.window), horizon)
        pos = tuple(p0[i] + v[i] * tau + 0.5 * a[i] * tau * tau for i in range(3))
        rv = tuple(r0[i] + w[i] * tau + 0.5 * al[i] * tau * tau for i in range(3))
        rot = quat_normalize(quat_mul(quat_from_rotvec(rv), ref.rot))
        still = (0.0, 0.0, 0.0)
        vel = tuple(v[i] + a[i] * tau for i in range(3)) if moving else still
        wv = tuple(w[i] + al[i] * tau for i in range(3)) if moving else still
        return StreamTarget(pos, rot, vel, wv, False)  # type: ignore[arg-type]

    def continues(self, pos: Vec3, rot: Quat, t: float, now: float) -> bool:
        """Would a message (pose, stamp ``t`` on the receive clock, arriving ``now``) continue this
        stream? (see the module docstring)"""
        if not self._samples or not self.recent(now):
            return False
        # at its own stamp, as if the stream were still running, extrapolated as far as needed
        pred = self.predict(t, now=self._last_arrival, lead=False, clamp=False)
        assert pred is not None
        return math.dist(pred.pos, pos) <= self.params.jump and \
            quat_angle(pred.rot, rot) <= self.params.jump_angle
