"""The cyclic driver loop around a PowerCube arm driver (ROS-free).

The ROS node (``redarm_ros.nodes.can_driver``) is wiring only; everything that
decides *what* is sent and *when* lives here so it can be tested and
benchmarked without ROS:

* :class:`JointCommandSource` turns incoming commands (a timed trajectory, or a
  stream of position targets) into one joint target per cycle, and holds
  position when there is nothing to follow.
* :class:`PeriodStats` measures the achieved cycle period against the nominal.
* :class:`ReferenceShaper` turns the sampled target into what is sent: velocity- and
  acceleration-limited, staying :data:`DEFAULT_LIMIT_MARGIN` inside each joint limit and braking
  early enough to stop there (targets beyond a limit are clamped to it first and reported). Its
  limits and braking law are those of :mod:`redarm_ros.motion`.
* :class:`Backoff` spaces reconnect attempts.
* :class:`DriverLoop` is the dedicated thread: absolute deadlines at ``rate_hz``, one
  ``driver.cycle()`` per tick, and a request queue so that init/halt/recover run on the loop
  thread (the bus has exactly one user), and ``park`` moves the arm to its park posture
  (:func:`redarm_ros.motion.sync_move.synchronized_move` through the same shaper). It drives any
  :class:`ArmDriver` (the protocol that :class:`~redarm_ros.can.driver_core.PowerCubeArmDriver`
  implements). Its state is not a second
  state machine: while the bus is up it is the driver's state seen through one table
  (:data:`LOOP_STATE_OF`); a fault is data (:class:`~redarm_ros.can.driver_core.Fault`).

:mod:`redarm_ros.can.driver_process` runs the same loop in a process of its own (the node's
default), away from the ROS executor's interpreter lock and garbage collector.

Units: seconds, radians; times are ``time.monotonic()`` seconds.
"""

from __future__ import annotations

import enum
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import can
import numpy as np

from redarm_ros.can import realtime
from redarm_ros.can.bus import NO_ANSWER_ADVICE, ReopenableBus
from redarm_ros.can.driver_core import (
    ArmState,
    CycleResult,
    DiscoveryReport,
    DriverState,
    Fault,
    FaultKind,
    ForeignHostError,
    ModuleStats,
    ModuleStatsView,
)
from redarm_ros.errors import BusError, BusTimeoutError, InvalidInputError, RedarmError, RequestRefusedError
from redarm_ros.motion import (
    JointLimits,
    LimitsView,
    braking_distance_scalar,
    braking_speed,
    braking_speed_scalar,
)
from redarm_ros.motion.sync_move import synchronized_move

_LOG = logging.getLogger(__name__)

__all__ = [
    "ACTIONS",
    "DEFAULT_LIMIT_MARGIN",
    "LOOP_STATE_OF",
    "MAX_QUEUED_TRAJECTORIES",
    "ArmDriver",
    "Backoff",
    "CommandMode",
    "CycleSample",
    "DriverLoop",
    "JointCommandSource",
    "LoopConfig",
    "LoopSnapshot",
    "LoopState",
    "PeriodStats",
    "ReferenceShaper",
    "braking_speed",
    "check_stream_target",
    "check_trajectory",
]


def _check_index(n: int, index: Sequence[int]) -> np.ndarray:
    idx = np.asarray(index, dtype=int).reshape(-1)
    if idx.size == 0:
        raise InvalidInputError("command names no joint", field="joint_names", value=list(index))
    if np.any(idx < 0) or np.any(idx >= n) or len(set(idx.tolist())) != idx.size:
        raise InvalidInputError("joint indices out of range or repeated", field="joint_names",
                                value=idx.tolist())
    return idx


def check_trajectory(
    n: int, index: Sequence[int], times_s: Sequence[float], points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``(index (m,), times (k,) s, points (k, m) rad)`` of a trajectory for an ``n``-joint arm.

    Raises:
        InvalidInputError: no joint, joints out of range or repeated, shape mismatch, NaN/inf,
            negative or decreasing times.
    """
    idx = _check_index(n, index)
    t = np.asarray(times_s, dtype=float).reshape(-1)
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape != (t.size, idx.size) or t.size == 0:
        raise InvalidInputError(
            f"trajectory needs points of shape ({t.size}, {idx.size}), got {p.shape}", field="points",
            value=p.shape,
        )
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
        raise InvalidInputError("trajectory contains NaN or inf", field="points")
    if t[0] < 0 or np.any(np.diff(t) < 0):
        raise InvalidInputError("time_from_start must be >= 0 and non-decreasing", field="times",
                                value=t.tolist())
    return idx, t, p


def check_stream_target(n: int, index: Sequence[int], q: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Validated ``(index (m,), q (m,) rad)`` of a streamed target for an ``n``-joint arm.

    Raises:
        InvalidInputError: no joint, joints out of range or repeated, length mismatch, NaN/inf.
    """
    idx = _check_index(n, index)
    qq = np.asarray(q, dtype=float).reshape(-1)
    if qq.size != idx.size:
        raise InvalidInputError(f"{qq.size} positions for {idx.size} joints", field="position")
    if not np.all(np.isfinite(qq)):
        raise InvalidInputError("target contains NaN or inf", field="position")
    return idx, qq


#: Trajectories that may wait for their start behind the one being followed (a controller stamping
#: its segments ahead queues a few; beyond this the earliest waiting one is dropped).
MAX_QUEUED_TRAJECTORIES = 64


class CommandMode(enum.Enum):
    """What the command source is following."""

    HOLD = "hold"  # keep the held position (after start, init, recover, reconnect, stream stop)
    TRAJECTORY = "trajectory"  # interpolate a timed trajectory, then keep its last point
    STREAM = "stream"  # follow streamed targets; hold if they stop arriving
    PARK = "park"  # the ~/park move (a trajectory of the driver's own), then hold the park posture


@dataclass
class _Trajectory:
    index: np.ndarray  # (m,) model joint indices the trajectory commands
    times: np.ndarray  # (k,) s from start, non-decreasing, >= 0
    points: np.ndarray  # (k, m) rad
    start: float  # monotonic s at which time 0 falls
    q_start: np.ndarray | None = None  # (n,) reference captured at the first sample
    # Set for a move planned on the cycle grid (park): it advances this many s per cycle sampled,
    # not with the wall clock, so cycles lost to an overloaded machine slow it down instead of
    # making the target run ahead of the shaper (which would catch up joint by joint).
    cycle_s: float | None = None
    cycles: int = 0


class JointCommandSource:
    """Thread-safe holder of the current joint command; the loop samples it once per cycle.

    Subscribers call :meth:`set_trajectory` / :meth:`set_stream_target` from any
    thread; the loop calls :meth:`sample` with its current reference.

    Trajectory semantics (as ``trajectory_msgs/JointTrajectory``): time 0 is
    ``start`` (monotonic s); between the reference at time 0 and the points,
    positions are linearly interpolated per joint at each cycle; after the
    last point its position is kept. Joints the trajectory does not name
    keep the reference value they had when it started.

    A trajectory that starts later than the last sample while another one is
    being followed is spliced in at its start, as ros2_control's joint
    trajectory controller does: the current one is followed until then (a
    controller that stamps its segments a little ahead of time is thus played
    on its own clock, whatever the message latency). A new trajectory replaces
    those queued to start at or after its own start.

    Stream semantics (``sensor_msgs/JointState`` targets): the latest target is
    followed; if no new one arrives within ``stream_timeout_s`` the source
    switches to HOLD at the measured position at that moment.
    """

    def __init__(self, n: int, stream_timeout_s: float = 0.5) -> None:
        self.n = int(n)
        self.stream_timeout_s = float(stream_timeout_s)
        self._lock = threading.Lock()
        self._mode = CommandMode.HOLD
        self._hold: np.ndarray | None = None
        self._traj: _Trajectory | None = None
        self._queued: list[_Trajectory] = []  # spliced in at their starts (sorted by start)
        self._last_sample = -math.inf  # time of the last sample (s)
        self._stream_q: np.ndarray | None = None
        self._stream_index: np.ndarray | None = None
        self._stream_time = 0.0
        self.generation = 0  # bumps on every new command or clear (for tests/diagnostics)

    @property
    def mode(self) -> CommandMode:
        """The current mode."""
        with self._lock:
            return self._mode

    def clear(self, hold_q: np.ndarray | None) -> None:
        """Drop any command and hold ``hold_q`` (n,) rad (None: hold the reference given to sample)."""
        with self._lock:
            self._mode = CommandMode.HOLD
            self._hold = None if hold_q is None else np.array(hold_q, dtype=float).reshape(self.n)
            self._traj = None
            self._queued = []
            self._stream_q = None
            self.generation += 1

    def set_trajectory(
        self, index: Sequence[int], times_s: Sequence[float], points: np.ndarray, start: float
    ) -> None:
        """Follow a trajectory: ``points`` (k, m) rad for model joints ``index`` (m,) at ``times_s`` (k,).

        Raises:
            InvalidInputError: see :func:`check_trajectory` (the current command is kept).
        """
        idx, t, p = check_trajectory(self.n, index, times_s, points)
        tr = _Trajectory(idx, t, p, float(start))
        with self._lock:
            cur = self._traj
            if (self._mode is CommandMode.TRAJECTORY and cur is not None and tr.start > self._last_sample
                    and tr.start > cur.start):
                # Splice: the current trajectory plays until this one starts.
                queued = [q for q in self._queued if q.start < tr.start]
                if len(queued) >= MAX_QUEUED_TRAJECTORIES:
                    queued.pop(0)
                queued.append(tr)
                self._queued = queued
            else:
                self._traj = tr
                self._queued = []
            self._mode = CommandMode.TRAJECTORY
            self._stream_q = None
            self.generation += 1

    @property
    def queued(self) -> int:
        """Trajectories waiting for their start behind the one being followed."""
        with self._lock:
            return len(self._queued)

    def set_park(self, times_s: Sequence[float], points: np.ndarray, cycle_s: float) -> int:
        """Follow the park move (all joints, ``points`` (k, n) rad at ``times_s`` (k,), planned on a
        grid of ``cycle_s`` s) in mode PARK, one ``cycle_s`` per :meth:`sample` from the next one on;
        returns the new :attr:`generation` (any later command or clear changes it)."""
        idx, t, p = check_trajectory(self.n, range(self.n), times_s, points)
        if not cycle_s > 0:
            raise InvalidInputError(f"park cycle must be > 0 s, got {cycle_s}", field="cycle_s",
                                    value=cycle_s)
        with self._lock:
            self._traj = _Trajectory(idx, t, p, 0.0, cycle_s=float(cycle_s))
            self._queued = []
            self._mode = CommandMode.PARK
            self._stream_q = None
            self.generation += 1
            return self.generation

    def set_stream_target(self, index: Sequence[int], q: Sequence[float], now: float) -> None:
        """Follow the streamed target ``q`` (m,) rad for model joints ``index``, received at ``now``.

        Raises:
            InvalidInputError: see :func:`check_stream_target` (the current command is kept).
        """
        idx, qq = check_stream_target(self.n, index, q)
        with self._lock:
            self._stream_index = idx
            self._stream_q = qq
            self._stream_time = float(now)
            self._mode = CommandMode.STREAM
            self._traj = None
            self._queued = []
            self.generation += 1

    def sample(self, now: float, q_ref: np.ndarray, q_measured: np.ndarray,
               q_stop: np.ndarray | None = None) -> np.ndarray:
        """The joint target (n,) rad for the cycle at ``now``.

        ``q_ref`` is the target sent in the previous cycle (continuity for new
        commands), ``q_measured`` the latest measured position (used when a
        stream stops), ``q_stop`` where the reference comes to rest if it brakes now
        (:meth:`ReferenceShaper.stopping_point`): a HOLD with no position yet (a command
        dropped mid-motion) holds there, so the arm brakes to a stop and does not come
        back to where it was measured (``q_measured`` when not given).
        """
        with self._lock:
            self._last_sample = max(self._last_sample, now)
            mode = self._mode
            if mode is CommandMode.TRAJECTORY or mode is CommandMode.PARK:
                while mode is CommandMode.TRAJECTORY and self._queued and self._queued[0].start <= now:
                    self._traj = self._queued.pop(0)  # its q_start: the reference as it is now
                tr = self._traj
                assert tr is not None
                if tr.q_start is None:
                    tr.q_start = np.array(q_ref, dtype=float)
                if tr.cycle_s is not None:
                    t_move = tr.cycles * tr.cycle_s
                    tr.cycles += 1
                    return _interpolate(tr, t_move)
                return _interpolate(tr, now)
            if mode is CommandMode.STREAM:
                assert self._stream_q is not None and self._stream_index is not None
                if now - self._stream_time > self.stream_timeout_s:
                    self._mode = CommandMode.HOLD
                    self._hold = np.array(q_measured, dtype=float)
                    self._stream_q = None
                    return self._hold.copy()
                q = np.array(q_ref, dtype=float)
                q[self._stream_index] = self._stream_q
                return q
            if self._hold is None:
                self._hold = np.array(q_measured if q_stop is None else q_stop, dtype=float)
            return self._hold.copy()


def _interpolate(tr: _Trajectory, now: float) -> np.ndarray:
    assert tr.q_start is not None
    q = tr.q_start.copy()
    t = now - tr.start
    if t < 0.0:
        return q
    # Prepend the starting reference at time 0 so the first segment starts where the arm is.
    times = tr.times
    if t >= times[-1]:
        q[tr.index] = tr.points[-1]
        return q
    k = int(np.searchsorted(times, t, side="right"))  # times[k-1] <= t < times[k]
    if k == 0:
        t0, p0 = 0.0, tr.q_start[tr.index]
    else:
        t0, p0 = times[k - 1], tr.points[k - 1]
    t1, p1 = times[k], tr.points[k]
    a = 1.0 if t1 <= t0 else (t - t0) / (t1 - t0)
    q[tr.index] = p0 + a * (p1 - p0)
    return q


#: How far (rad) the driver's reference stays inside each joint limit (the modules' soft limits):
#: the modules refuse targets beyond their soft limit and trip BEYOND_SOFT 1e-4 rad past it, so the
#: arm is never commanded closer than this to a limit (10x that tolerance).
DEFAULT_LIMIT_MARGIN = 1e-3


class ReferenceShaper(LimitsView):  # lower/upper: the joint limits inset by the margin
    """Velocity- and acceleration-limited joint reference that follows a (moving) target.

    Every cycle the reference moves toward the target with the target's own velocity fed
    forward plus a braking-law correction (:func:`redarm_ros.motion.braking_speed`), so a feasible
    trajectory is followed without lag, while a jump is turned into a trapezoid. Limits enforced on
    the *reference* (what is sent): ``|v| <= max_vel``, ``|dv/dt| <= max_acc``, and the reference
    keeps ``margin`` (rad) inside every position limit and slows down early enough to stop on that
    inset limit at ``max_acc``: a target at (or clamped to) a joint limit is reached ``margin`` short
    of it, never overshooting, which a stream of FSTEPs arriving at full speed would otherwise do.

    Args:
        limits: the arm's joint limits (rad, rad/s, rad/s^2).
        dt: the nominal cycle period (s).
        margin: distance (rad, >= 0) kept from each position limit (:data:`DEFAULT_LIMIT_MARGIN`).
    """

    def __init__(self, limits: JointLimits, dt: float, margin: float = DEFAULT_LIMIT_MARGIN) -> None:
        self.limits = limits.inset(margin)
        self.margin = float(margin)
        self.dt = float(dt)
        self.r: np.ndarray | None = None
        self.v = np.zeros(limits.n)
        self._g_prev: list[float] | None = None
        # Per joint as floats: the law runs joint by joint (see step).
        lim = self.limits
        self._lower, self._upper = lim.lower.tolist(), lim.upper.tolist()
        self._acc, self._vmax = lim.max_acc.tolist(), lim.max_vel.tolist()
        self._acc_dt = (lim.max_acc * self.dt).tolist()

    def reset(self, q: np.ndarray) -> None:
        """Start from rest at ``q`` (rad): after init, recover, reconnect."""
        self.r = self.limits.clip(q)
        self.v = np.zeros_like(self.r)
        self._g_prev = None

    def hold_still(self) -> None:
        """The target stops here: the next step feeds no target velocity forward (the jump from a
        moving command to a fixed hold point is not a velocity), it only brakes onto the target."""
        self._g_prev = None

    def stopping_point(self) -> np.ndarray | None:
        """Where the reference comes to rest (rad, inside the inset limits) if it brakes at max_acc
        from its velocity now; None before the first step."""
        if self.r is None:
            return None
        if not self.v.any():  # at rest (most cycles of a held arm): where it is, as the law below gives
            return self.r.copy()
        # the discrete law's own distance from the next step's speed (|v| braked by a dt): the
        # braking step then lands on this point exactly, with no overshoot to come back from
        # (joint by joint on floats, as in step)
        dt, distance = self.dt, braking_distance_scalar
        out = []
        for rj, vj, a, adt, lo, hi in zip(self.r.tolist(), self.v.tolist(), self._acc, self._acc_dt,
                                          self._lower, self._upper, strict=True):
            s = abs(vj) - adt
            d = distance(s if s > 0.0 else 0.0, a, dt)
            x = rj + (1.0 if vj > 0.0 else (-1.0 if vj < 0.0 else 0.0)) * d
            x = x if x > lo else lo
            out.append(x if x < hi else hi)
        return np.array(out)

    def step(self, target: np.ndarray, elapsed: float | None = None) -> np.ndarray:
        """Advance one cycle toward ``target`` (n,) rad (clamped into the inset limits); returns the
        reference. ``elapsed`` (s): the time since the previous target was sampled, when it was not
        one nominal period (a late cycle, skipped ticks): the target's velocity is its change over
        that time. Taken per nominal period instead, every skipped tick doubled or tripled the
        velocity fed forward, and the reference overshot the end of a trajectory (134 / 340 mrad
        with 20 % / 50 % of the cycles 1-3 ticks late, replayed offline on the PA10's limits; now 0,
        see docs/can_driver.md, "One cycle").

        Raises:
            InvalidInputError: ``target`` holds NaN or inf (the commands are checked before they get
                here: a bug).
        """
        if self.r is None:
            self.reset(target)
            return self.r.copy()  # type: ignore[union-attr]
        # The law joint by joint on floats: on an arm's seven joints, the four dozen numpy calls of its
        # vector form cost several times more, 250 times a second. Same operations in the same order,
        # so the same numbers; a clip is numpy's: ``x if x > lo else lo``, then ``y if y < hi else hi``.
        tq = np.asarray(target, dtype=float).tolist()
        if not math.isfinite(sum(tq)) and not all(map(math.isfinite, tq)):
            raise InvalidInputError("shaper target contains NaN or inf", field="target", value=tq)
        lower, upper = self._lower, self._upper
        g = []
        for x, lo, hi in zip(tq, lower, upper, strict=True):
            x = x if x > lo else lo
            g.append(x if x < hi else hi)
        g_prev = self._g_prev
        r = self.r.tolist()  # type: ignore[union-attr]
        v = self.v.tolist()
        if not any(v) and g == r and (g_prev is None or g == g_prev):
            # At rest on a target that stands still (a held arm, 250 times a second): the law below
            # gives the same reference and zero velocity; skip it.
            self._g_prev = g
            return self.r.copy()  # type: ignore[union-attr]
        dt = self.dt
        h = dt if elapsed is None else max(float(elapsed), 0.25 * dt)
        self._g_prev = g
        speed = braking_speed_scalar
        r_out: list[float] = []
        v_out: list[float] = []
        joints = zip(g, r, v, self._acc, self._vmax, self._acc_dt, strict=True)
        for j, (gj, rj, vj, a, vmax, adt) in enumerate(joints):
            if g_prev is None:
                u = 0.0
            else:
                u = (gj - g_prev[j]) / h
                u = u if u > -vmax else -vmax
                u = u if u < vmax else vmax
            # Tracking error against where the target was: with u fed forward, r then lands on g.
            e = (gj - u * dt) - rj
            sign_e = 1.0 if e > 0.0 else (-1.0 if e < 0.0 else 0.0)
            vd = u + sign_e * speed(abs(e), a, dt)
            vd = vd if vd > -vmax else -vmax
            vd = vd if vd < vmax else vmax
            # Approach the nearest point where the target can stop (braking at max_acc from u) no
            # faster than allows stopping on it: a reference that lags (skipped ticks) catches up
            # without its catch-up speed adding to the target's own, which carried it beyond a
            # trajectory's end.
            ahead = gj + u * abs(u) / (2.0 * a) - rj
            cap = speed(abs(ahead), a, dt)
            lo = -cap if ahead < 0.0 else -vmax
            hi = cap if ahead > 0.0 else vmax
            vd = vd if vd > lo else lo
            vd = vd if vd < hi else hi
            # Never faster toward a limit than allows stopping on it (exact discrete law: no overshoot).
            lo = -speed(rj - lower[j], a, dt)
            hi = speed(upper[j] - rj, a, dt)
            vd = vd if vd > lo else lo
            vd = vd if vd < hi else hi
            dv = vd - vj
            dv = dv if dv > -adt else -adt
            dv = dv if dv < adt else adt
            r_new = rj + (vj + dv) * dt
            # Land exactly on a stationary target instead of dithering around it, but only with a
            # step the acceleration limit allows both now and for the stop in the next cycle.
            step = (gj - rj) / dt
            if abs(step - vj) <= adt and abs(step) <= adt and u == 0.0:
                r_new = gj
            r_new = r_new if r_new > lower[j] else lower[j]
            r_new = r_new if r_new < upper[j] else upper[j]
            r_out.append(r_new)
            # The velocity is the step actually sent (landing, clipping), so the next cycle's
            # acceleration limit holds on the positions the modules receive.
            v_out.append((r_new - rj) / dt)
        self.r = np.array(r_out)
        self.v = np.array(v_out)
        return self.r.copy()


#: Bin width (s) of the since-start histogram of period errors, and its number of bins (errors beyond
#: the last bin go into it): 0.05 ms bins up to 1 s.
_HIST_BIN_S = 5e-5
_HIST_BINS = 20000


class PeriodStats:
    """Achieved cycle timing against the nominal period (window of the last ``window`` cycles).

    :meth:`start` is called with every cycle's start time; the period between two cycles is a
    sample unless ticks were skipped in between (an overrun, counted separately). The achieved
    rate counts every cycle over the window's time span, overruns included. Separately, every
    start-to-start period since the start (or :meth:`reset_totals`), overruns and pauses between
    runs of cycles excluded only by :meth:`reset`, goes into a histogram: :meth:`totals` gives its
    p99 and max (what a long soak test reports).
    """

    def __init__(self, period_s: float, window: int = 2500) -> None:
        self.period_s = float(period_s)
        self._periods: deque[float] = deque(maxlen=window)
        self._starts: deque[float] = deque(maxlen=window)
        self._busy: deque[float] = deque(maxlen=window)
        self._lock = threading.Lock()
        self.cycles = 0
        self.overruns = 0  # ticks skipped because a cycle ended after the next deadline
        self._hist = [0] * (_HIST_BINS + 1)
        self._hist_max = 0.0

    def start(self, t: float, *, after_overrun: bool = False, after_pause: bool = False) -> None:
        """Record a cycle starting at ``t`` (s); ``after_overrun``: ticks were skipped before it;
        ``after_pause``: cycling resumed after a pause (init, halt, reconnect): no period at all."""
        with self._lock:
            if self._starts and not after_pause:
                p = t - self._starts[-1]
                if not after_overrun:
                    self._periods.append(p)
                err = abs(p - self.period_s)
                self._hist[min(int(err / _HIST_BIN_S), _HIST_BINS)] += 1
                if err > self._hist_max:
                    self._hist_max = err
            self._starts.append(t)
            self.cycles += 1

    def totals(self) -> dict[str, float]:
        """Since the start: ``periods`` counted, ``period_err_p99_ms`` (bin resolution 0.05 ms) and
        ``period_err_max_ms`` of every start-to-start period, overruns included."""
        with self._lock:
            hist, worst = np.array(self._hist, dtype=np.int64), self._hist_max
        total = int(hist.sum())
        p99 = 0.0
        if total:
            i = int(np.searchsorted(np.cumsum(hist), 0.99 * total))
            p99 = (i + 1) * _HIST_BIN_S
        return {"periods": float(total), "period_err_p99_ms": p99 * 1e3, "period_err_max_ms": worst * 1e3}

    def reset_totals(self) -> None:
        """Start the since-start histogram afresh."""
        with self._lock:
            self._hist = [0] * (_HIST_BINS + 1)
            self._hist_max = 0.0

    def busy(self, seconds: float) -> None:
        """Record how long one cycle's work took (s): sending, waiting for replies, publishing."""
        with self._lock:
            self._busy.append(seconds)

    def add(self, period_s: float) -> None:
        """Record one measured period (s) directly (no start time)."""
        with self._lock:
            self._periods.append(period_s)

    def add_overrun(self, skipped: int) -> None:
        """Record ``skipped`` ticks that were dropped because the loop fell behind."""
        with self._lock:
            self.overruns += int(skipped)

    def reset(self) -> None:
        """Forget the window (counters and the since-start histogram stay)."""
        with self._lock:
            self._periods.clear()
            self._starts.clear()
            self._busy.clear()

    def summary(self) -> dict[str, float]:
        """``rate_hz`` (cycles per second over the window), absolute period errors in ms
        (``period_err_median_ms``, ``period_err_p99_ms``, ``period_err_max_ms``), ``samples``, and
        the time a cycle's work took (``busy_median_ms``, ``busy_p99_ms``)."""
        with self._lock:
            p = np.fromiter(self._periods, dtype=float)
            starts = list(self._starts)
            busy = np.fromiter(self._busy, dtype=float) * 1e3
        rate = 0.0
        if len(starts) >= 2 and starts[-1] > starts[0]:
            rate = (len(starts) - 1) / (starts[-1] - starts[0])
        elif p.size:
            rate = float(1.0 / p.mean())
        out = {"busy_median_ms": float(np.median(busy)) if busy.size else 0.0,
               "busy_p99_ms": float(np.percentile(busy, 99)) if busy.size else 0.0}
        if p.size == 0:
            return {"rate_hz": rate, "period_err_median_ms": 0.0, "period_err_p99_ms": 0.0,
                    "period_err_max_ms": 0.0, "samples": 0, **out}
        err = np.abs(p - self.period_s) * 1e3
        return {
            "rate_hz": float(rate),
            "period_err_median_ms": float(np.median(err)),
            "period_err_p99_ms": float(np.percentile(err, 99)),
            "period_err_max_ms": float(err.max()),
            "samples": int(p.size),
            **out,
        }


class Backoff:
    """Exponential backoff delays: ``first`` s doubling up to ``maximum`` s; :meth:`reset` after success."""

    def __init__(self, first: float = 0.1, maximum: float = 2.0) -> None:
        self.first = float(first)
        self.maximum = float(maximum)
        self._next = self.first

    def next_delay(self) -> float:
        """The delay to wait before the next attempt (and advance)."""
        d = self._next
        self._next = min(self._next * 2.0, self.maximum)
        return d

    def reset(self) -> None:
        """Start again from ``first``."""
        self._next = self.first


# ------------------------------------------------------------------------------------------------
# The loop thread
# ------------------------------------------------------------------------------------------------


class ArmDriver(Protocol):
    """What :class:`DriverLoop` needs from an arm driver (:class:`~redarm_ros.can.driver_core.
    PowerCubeArmDriver` implements it; tests may pass stand-ins). Units: rad, s."""

    n: int
    limits: JointLimits
    state: DriverState
    fault: Fault | None
    stats: Sequence[ModuleStats]

    @property
    def frames_per_cycle(self) -> int:
        """Frames one :meth:`cycle` puts on the bus."""

    def discover(self) -> DiscoveryReport:
        """Scan for the modules."""

    def read_state(self) -> ArmState:
        """Read positions and states (no motion)."""

    def init(self) -> ArmState:
        """Configure, reset and home; READY, holding."""

    def halt(self) -> list[int]:
        """Halt every module; HALTED."""

    def request_halt(self) -> None:
        """Any thread: stop an init/recover in progress at once (it halts every module and raises)."""

    def clear_halt_request(self) -> None:
        """Forget a :meth:`request_halt` whose halt will not be run."""

    def recover(self) -> ArmState:
        """Reset and reconfigure; READY, holding."""

    def reconnect(self) -> ArmState:
        """Reopen the bus, re-read, hold."""

    def cycle(self, q_target: np.ndarray | None, dt_s: float) -> CycleResult:
        """One cycle toward ``q_target`` (None: hold)."""


class LoopState(enum.Enum):
    """State of :class:`DriverLoop` (reported on /diagnostics)."""

    CONNECTING = "connecting"  # bus not open (start-up or lost): retrying with backoff
    IDLE = "idle"  # bus open, modules not initialised: state polled, no motion sent
    RUNNING = "running"  # cyclic FSTEP stream at rate_hz, following commands or holding
    HALTED = "halted"  # halted by request or fault: state polled, no motion until recover
    STOPPED = "stopped"  # loop thread ended


#: The loop's state while the bus is up is the driver's, seen through this one table (no second
#: state machine to keep in step): a lost bus shows CONNECTING and keeps the driver's state, so the
#: loop comes back to where it was (holding the measured position if it was running).
LOOP_STATE_OF: dict[DriverState, LoopState] = {
    DriverState.UNINITIALIZED: LoopState.IDLE,
    DriverState.READY: LoopState.RUNNING,
    DriverState.HALTED: LoopState.HALTED,
    DriverState.FAULT: LoopState.HALTED,
}


@dataclass(frozen=True)
class LoopConfig:
    """Settings of :class:`DriverLoop`.

    ``rate_hz`` cycle rate, ``poll_hz`` state polling when not running, ``hold_on_stream_stop_s``
    stream timeout, reconnect backoff (s), ``auto_init`` after connecting, ``limit_margin_rad`` kept
    from each joint limit by the reference (:data:`DEFAULT_LIMIT_MARGIN`), ``realtime_priority``
    (SCHED_FIFO priority for the loop thread, 0 = normal scheduling; see
    :func:`redarm_ros.can.realtime.raise_priority`), ``slice_ms`` (time slice the loop thread asks for
    at normal scheduling, 0 = the kernel's default; :func:`redarm_ros.can.realtime.request_slice`),
    ``quiet_gc`` (freeze the garbage collector at
    start and collect young objects only in spare time between cycles; for a process of its own).
    ``park`` is the park posture (rad, one per joint; None: ``park`` is refused), ``park_tolerance_rad``
    how close every measured joint must come to it before ``park`` reports success,
    ``park_speed_scale`` the fraction of the velocity and acceleration limits the park move plans with,
    and ``park_after_init`` starts that move after every successful ``init`` (homing leaves the arm at
    its home position, 0 rad; the arm then comes to rest in park).
    """

    rate_hz: float = 250.0
    poll_hz: float = 10.0
    hold_on_stream_stop_s: float = 0.5
    reconnect_first_s: float = 0.1
    reconnect_max_s: float = 2.0
    auto_init: bool = False
    clamp_log_interval_s: float = 1.0
    limit_margin_rad: float = DEFAULT_LIMIT_MARGIN
    realtime_priority: int = 0
    slice_ms: float = 0.0
    quiet_gc: bool = False
    park: tuple[float, ...] | None = None
    park_tolerance_rad: float = 2e-3
    park_speed_scale: float = 0.9
    park_after_init: bool = False


@dataclass
class CycleSample:
    """What one cycle (or state poll) measured: ``stamp`` (``time.time()`` s), ``positions`` (n,) rad,
    ``velocities`` (n,) rad/s or None, ``target`` (n,) rad sent this cycle or None when polling."""

    stamp: float
    positions: np.ndarray
    velocities: np.ndarray | None
    target: np.ndarray | None


@dataclass
class LoopSnapshot:
    """A consistent copy of the loop's status for diagnostics (picklable)."""

    state: LoopState
    reason: str
    period: dict[str, float]
    cycles: int
    overruns: int
    connects: int
    bus_losses: int
    clamps: int
    command_mode: CommandMode
    missing_modules: list[int]
    module_stats: list[ModuleStatsView]  # per joint (empty before the first connection)
    last_result: CycleResult | None
    positions: np.ndarray | None
    fault: Fault | None = None  # why the loop is HALTED, as data (None: not halted by a fault)
    latency: dict[str, float] | None = None  # reply latency over the window: median/p99/max ms
    frames_tx: int = 0  # frames sent by cycles (FSTEP per joint, STARTMOVE, watchdog refresh)
    frames_rx: int = 0  # replies received by cycles
    frames_per_s: float = 0.0  # (tx + rx) per second over the last snapshot interval
    implausible: int = 0  # measured positions refused by the plausibility check, all modules
    priority: str = ""  # the scheduling the loop thread got (one line)
    totals: dict[str, float] | None = None  # since the start: PeriodStats.totals()


#: The loop's reason on /diagnostics while running, by what the command source follows: the reason of
#: the request or event that made it run ("init done", "reconnected") stayed while it followed commands.
RUNNING_REASON: dict[CommandMode, str] = {
    CommandMode.HOLD: "holding position",
    CommandMode.TRAJECTORY: "following a trajectory (its last point held at its end)",
    CommandMode.STREAM: "following streamed targets",
    CommandMode.PARK: "park move (the park posture held at its end)",
}

#: How long (s) every measured joint must stay within the park tolerance before ``park`` succeeds.
PARK_SETTLE_S = 0.1

#: A refused state poll (e.g. a restarted module's implausible position) is logged at most this often (s).
POLL_WARN_INTERVAL_S = 5.0

#: The requests :meth:`DriverLoop.request` serves.
ACTIONS = ("init", "halt", "recover", "park")


@dataclass(frozen=True)
class _ParkMove:
    generation: int  # the command source's generation the move was set with
    target: np.ndarray  # (n,) rad: the park posture, inside the reference's inset limits
    duration_s: float


class _Request:
    def __init__(self, action: str, timeout: float) -> None:
        self.action = action
        self.deadline = time.monotonic() + timeout  # the caller stops waiting then
        self.done = threading.Event()
        self.ok = False
        self.message = ""
        self.park: _ParkMove | None = None  # set when a park move was started


LogFn = Callable[[int, str], None]
StateFn = Callable[[LoopState, str, Fault | None], None]


def _default_log(level: int, message: str) -> None:
    _LOG.log(level, "%s", message)


class DriverLoop:
    """The dedicated driver thread: connect, poll or cycle at absolute deadlines, serve requests.

    Args:
        driver_factory: ``f(bus) -> ArmDriver`` building the driver for an open bus (a
            :class:`~redarm_ros.can.driver_core.PowerCubeArmDriver`).
        open_bus: ``f() -> bus`` opening the CAN bus (raises :class:`BusError` when it cannot).
            If the bus is a :class:`~redarm_ros.can.bus.ReopenableBus` (a
            :class:`~redarm_ros.can.bus.ReconnectingBus`), a lost bus is reopened in place and the
            driver kept, else it is shut down, opened anew and a new driver built.
        n: joint count.
        config: see :class:`LoopConfig`.
        on_sample: called from the loop thread after every cycle / poll (keep it short: publish).
        on_state: called from the loop thread whenever the state, reason or fault changes.
        log: ``f(level, message)`` with :mod:`logging` levels (the node forwards to its logger).

    The loop owns the bus: ``init``/``halt``/``recover`` run on its thread via :meth:`request`;
    commands go to :attr:`commands` from any thread, but are only accepted while RUNNING.

    Failure behaviour: a module that stops answering, reports an error or implausible positions
    -> everything halted (by the driver), state HALTED with the :class:`Fault` until ``recover``.
    The bus lost (:class:`BusError`) -> CONNECTING, reopened with backoff; if the driver was READY
    it resumes holding the *measured* position (the command it was following is dropped, never
    replayed).
    """

    def __init__(
        self,
        driver_factory: Callable[[can.BusABC], ArmDriver],
        open_bus: Callable[[], can.BusABC],
        n: int,
        config: LoopConfig = LoopConfig(),  # noqa: B008 - frozen dataclass, safe default
        *,
        on_sample: Callable[[CycleSample], None] | None = None,
        on_state: StateFn | None = None,
        log: LogFn = _default_log,
    ) -> None:
        self._driver_factory = driver_factory
        self._open_bus = open_bus
        self.n = int(n)
        self.config = config
        self.period_s = 1.0 / float(config.rate_hz)
        self.commands = JointCommandSource(self.n, config.hold_on_stream_stop_s)
        self.stats = PeriodStats(self.period_s)
        self._on_sample = on_sample
        self._on_state = on_state
        self._log = log
        self._lock = threading.Lock()
        self._requests: queue.Queue[_Request] = queue.Queue()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._started = threading.Event()
        self._thread: threading.Thread | None = None
        self.bus: can.BusABC | None = None
        self.driver: ArmDriver | None = None
        self._connected = False
        self._stopped = False
        self._reason = "starting"
        self._fault: Fault | None = None
        self._published: tuple[LoopState, str, Fault | None] | None = None
        self._connects = 0
        self._bus_losses = 0
        self._clamps = 0
        self._missing: list[int] = []
        self._last_result: CycleResult | None = None
        self._q_meas: np.ndarray | None = None
        self._q_ref: np.ndarray | None = None
        # The reference shaper survives a pause for a request that keeps the arm running (park), so
        # a move in progress continues at its velocity; init, halt, recover, faults and reconnects
        # drop it (the next run of cycles starts from rest at the reference).
        self._shaper: ReferenceShaper | None = None
        self._last_clamp_log = -1e9
        self._last_poll_warn = -1e9
        self._priority = ""
        # Reply latencies (s) of the last 500 cycles, all joints (small: diagnostics run in
        # another thread and numpy holds the GIL while it sorts), and frame counters.
        self._latencies: deque[float] = deque(maxlen=500 * self.n)
        self._frames_tx = 0
        self._frames_rx = 0
        self._fps_mark = (time.monotonic(), 0)

    # -- public API (any thread) ------------------------------------------------------------------
    @property
    def state(self) -> LoopState:
        """The current state (see :data:`LOOP_STATE_OF`)."""
        with self._lock:
            return self._state_locked()

    def _state_locked(self) -> LoopState:
        if self._stopped:
            return LoopState.STOPPED
        if not self._connected or self.driver is None:
            return LoopState.CONNECTING
        return LOOP_STATE_OF[self.driver.state]

    @property
    def fault(self) -> Fault | None:
        """Why the loop is HALTED, if a fault halted it."""
        with self._lock:
            return self._fault_locked()[0]

    def _fault_locked(self) -> tuple[Fault | None, str]:
        """(fault, reason): the loop's own, or the driver's when the driver has just faulted and the
        loop thread has not caught up yet (the state is derived from the driver, so is this)."""
        drv = self.driver
        if self._fault is None and drv is not None and drv.state is DriverState.FAULT:
            if drv.fault is not None:
                return drv.fault, drv.fault.message
        return self._fault, self._reason

    def start(self) -> DriverLoop:
        """Start the loop thread; returns self."""
        if self._thread is None:
            self._stopped = False
            self._thread = threading.Thread(target=self._run, name="can-driver-loop", daemon=True)
            self._thread.start()
            self._started.set()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread and close the bus (modules keep their last, finished FSTEP)."""
        self._stop.set()
        self._wake.set()
        self._started.set()  # release requests waiting for a start
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self._close_bus()
        with self._lock:
            self._stopped = True
            self._reason = "stopped"
        self._publish_state()

    def request(self, action: str, timeout: float = 60.0) -> tuple[bool, str]:
        """Run ``init``, ``halt``, ``recover`` or ``park`` on the loop thread; returns (success, message).

        ``park`` answers when the move is finished: every joint's reference on the park posture and
        every measured position within ``park_tolerance_rad`` of it for :data:`PARK_SETTLE_S`. It fails
        at once when the loop is not running (not initialised, halted, bus lost) or the arm has no park
        posture, and fails later when the move is interrupted (halt, fault, bus loss, any new command)
        or not finished within ``timeout`` s (the move itself keeps going then).
        """
        if action not in ACTIONS:
            return False, f"unknown action {action!r}"
        t0 = time.monotonic()
        if not self._stopped:
            self._started.wait(timeout)  # a request made before start() waits for it
        thread = self._thread
        if thread is None or not thread.is_alive():
            return False, "driver loop is not running"
        timeout = max(0.0, timeout - (time.monotonic() - t0))
        req = _Request(action, timeout)
        if action == "halt":
            # An init (homing) or recover in progress holds the loop thread for seconds: tell the
            # driver directly, so it halts every module now instead of after the request.
            drv = self.driver
            if drv is not None:
                drv.request_halt()
        self._requests.put(req)
        self._wake.set()
        if not req.done.wait(timeout):
            return False, f"{action} did not finish within {timeout:.0f} s"
        if req.ok and req.park is not None:
            return self._wait_parked(req.park, req.deadline, timeout)
        return req.ok, req.message

    def _wait_parked(self, move: _ParkMove, deadline: float, timeout: float) -> tuple[bool, str]:
        """Wait (caller's thread) until the park move has arrived, was interrupted, or the caller's
        ``deadline`` (monotonic s; ``timeout`` s after the request) has passed."""
        tol = self.config.park_tolerance_rad
        settled_since: float | None = None  # the measured positions must stay within tol for a while
        while True:
            with self._lock:
                state = self._state_locked()
                reason = self._fault_locked()[1]
                q_meas, q_ref = self._q_meas, self._q_ref
            if state is not LoopState.RUNNING:
                return False, f"park interrupted: driver is {state.value} ({reason})"
            if self.commands.generation != move.generation:
                return False, f"park interrupted by a new command (now {self.commands.mode.value})"
            now = time.monotonic()
            if (q_meas is not None and q_ref is not None
                    and float(np.max(np.abs(q_ref - move.target))) <= 1e-6
                    and float(np.max(np.abs(q_meas - move.target))) <= tol):
                settled_since = now if settled_since is None else settled_since
                if now - settled_since >= PARK_SETTLE_S:
                    return True, (f"parked at {np.round(q_meas, 4).tolist()} (move planned for "
                                  f"{move.duration_s:.2f} s)")
            else:
                settled_since = None
            if now > deadline:
                return False, (f"park did not finish within {timeout:.0f} s (still moving; measured "
                               f"{np.round(q_meas, 4).tolist() if q_meas is not None else None})")
            time.sleep(0.01)

    def reset_measurements(self) -> None:
        """Start fresh timing and latency windows and period totals (counters such as cycles stay)."""
        self.stats.reset()
        self.stats.reset_totals()
        with self._lock:
            self._latencies.clear()

    def accepting_commands(self) -> tuple[bool, str]:
        """Whether a new command would be followed now, and why not."""
        with self._lock:
            state = self._state_locked()
            if state is LoopState.RUNNING:
                return True, ""
            return False, f"driver is {state.value} ({self._fault_locked()[1]}); command ignored"

    def snapshot(self) -> LoopSnapshot:
        """A copy of the status for diagnostics. While running, the reason says what the arm does now
        (:data:`RUNNING_REASON`), not what the last request or event was."""
        with self._lock:
            state = self._state_locked()
            fault, reason = self._fault_locked()
            if state is LoopState.RUNNING:
                reason = RUNNING_REASON[self.commands.mode]
            last = self._last_result
            q = None if self._q_meas is None else self._q_meas.copy()
            missing = list(self._missing)
            connects, losses, clamps = self._connects, self._bus_losses, self._clamps
            lat = np.fromiter(self._latencies, dtype=float)
            tx, rx = self._frames_tx, self._frames_rx
            now = time.monotonic()
            t_prev, f_prev = self._fps_mark
            fps = (tx + rx - f_prev) / (now - t_prev) if now > t_prev else 0.0
            self._fps_mark = (now, tx + rx)
        drv = self.driver
        mstats = [s.view() for s in drv.stats] if drv is not None else []
        latency = None
        if lat.size:
            latency = {"median_ms": float(np.median(lat) * 1e3),
                       "p99_ms": float(np.percentile(lat, 99) * 1e3), "max_ms": float(lat.max() * 1e3)}
        # A keyword-built record: alike in shape only to other records' construction (IKAnswer).
        return LoopSnapshot(
            state=state,
            reason=reason,
            period=self.stats.summary(),
            cycles=self.stats.cycles,
            overruns=self.stats.overruns,
            connects=connects,
            bus_losses=losses,
            clamps=clamps,
            command_mode=self.commands.mode,
            missing_modules=missing,
            module_stats=mstats,
            last_result=last,
            positions=q,
            fault=fault,
            latency=latency,
            frames_tx=tx,
            frames_rx=rx,
            frames_per_s=fps,
            implausible=sum(s.implausible for s in mstats),
            priority=self._priority,
            totals=self.stats.totals(),
        )

    # -- loop thread ------------------------------------------------------------------------------
    def _set_reason(self, reason: str, fault: Fault | None = None) -> None:
        with self._lock:
            self._reason, self._fault = reason, fault

    def _publish_state(self) -> None:
        """Tell ``on_state`` about a change of state, reason or fault (loop thread)."""
        if self._on_state is None:
            return
        with self._lock:
            fault, reason = self._fault_locked()
            now = (self._state_locked(), reason, fault)
        if now != self._published:
            self._published = now
            try:
                self._on_state(*now)
            except Exception as exc:  # reporting must never stop the loop
                self._log(logging.ERROR, f"on_state failed: {exc!r}")

    def _run(self) -> None:
        realtime.name_thread("can-cycle")
        cfg = self.config
        if cfg.realtime_priority > 0:
            prio = realtime.raise_priority(cfg.realtime_priority, who="can_driver cycle thread")
            self._priority = prio.message
            self._log(logging.INFO if prio.realtime else logging.WARNING, prio.message)
        if cfg.slice_ms > 0:  # woken by every reply: a short slice gets it a CPU sooner
            got = realtime.request_slice(cfg.slice_ms, who="can_driver cycle thread")
            self._priority = f"{self._priority}; {got.message}" if self._priority else got.message
            self._log(logging.WARNING if got.refused else logging.INFO, got.message)
        if cfg.quiet_gc:
            realtime.quiet_gc()
        backoff = Backoff(cfg.reconnect_first_s, cfg.reconnect_max_s)
        try:
            while not self._stop.is_set():
                try:
                    if not self._connected:
                        if not self._connect():
                            delay = backoff.next_delay()
                            # Before the first connection requests wait for it (a client calling
                            # ~/init right after start-up); later, during an outage, they are refused.
                            self._serve_requests(refuse=f"CAN bus not connected ({self._reason})",
                                                 hold=self._connects == 0)
                            self._publish_state()
                            self._stop.wait(delay)
                            continue
                        backoff.reset()
                        self._publish_state()
                        continue
                    self._serve_requests()
                    self._publish_state()
                    if self.state is LoopState.RUNNING:
                        self._run_cycles()
                    else:
                        self._poll_once()
                        if cfg.quiet_gc:
                            realtime.collect_young()
                        self._wake.wait(1.0 / cfg.poll_hz)
                        self._wake.clear()
                except BusTimeoutError as exc:
                    # A silent module: the driver core has already halted every module.
                    self._halted_by(self._fault_of_timeout(exc), halt=False)
                except BusError as exc:
                    self._bus_lost(exc)
                except Exception as exc:  # a bug must not leave the arm moving: halt and report
                    self._log(logging.ERROR, f"driver loop error: {exc!r}")
                    self._halted_by(Fault(FaultKind.INTERNAL, (), f"internal error: {exc!r}"))
                    self._stop.wait(0.1)
                self._publish_state()
            self._serve_requests(refuse="driver stopping")
        finally:
            if cfg.quiet_gc:
                realtime.restore_gc()

    def _fault_of_timeout(self, exc: BusTimeoutError) -> Fault:
        drv = self.driver
        if drv is not None and drv.fault is not None:
            base = drv.fault
            return Fault(base.kind, base.module_ids, f"module {exc.module_id} stopped answering: {exc}",
                         base.bits)
        mids = (exc.module_id,) if exc.module_id is not None else ()
        return Fault(FaultKind.SILENT, mids, f"module {exc.module_id} stopped answering: {exc}")

    def _connect(self) -> bool:
        """Open (or reopen) the bus and discover the modules; False means retry later."""
        drv = self.driver
        was_ready = drv is not None and drv.state is DriverState.READY
        try:
            if drv is not None and isinstance(self.bus, ReopenableBus):
                if was_ready:
                    # Reopen, re-read the positions and hold them: nothing from before is replayed.
                    drv.reconnect()
                else:
                    self.bus.reopen()
            else:
                self._close_bus()
                self.bus = self._open_bus()
                drv = self.driver = self._driver_factory(self.bus)
                was_ready = False
            report = drv.discover()
        except BusError as exc:  # includes BusTimeoutError: modules not (yet) answering
            self._retry_reason(f"CAN bus not usable yet: {exc}")
            return False
        except RedarmError as exc:  # e.g. implausible positions on reconnect: halt and report
            with self._lock:
                self._connected = True
            mid = getattr(exc, "module_id", None)
            self._halted_by(Fault(FaultKind.IMPLAUSIBLE, (mid,) if mid is not None else (),
                                  f"after reconnecting: {exc}"))
            return True
        missing = list(report.missing)
        if len(missing) == self.n:
            self._retry_reason(f"CAN bus open, but no module answers discovery ({NO_ANSWER_ADVICE})")
            return False
        with self._lock:
            self._connects += 1
            self._missing = missing
            self._connected = True
        if missing:
            self._log(logging.ERROR, f"modules not answering discovery: {missing}")
        else:
            self._log(logging.INFO, f"CAN bus connected, all {self.n} modules found")
        self._q_meas = None
        self._q_ref = None
        self._shaper = None
        if was_ready and not missing:
            self.commands.clear(None)
            self._set_reason("reconnected; holding measured position")
            self._log(logging.WARNING, "CAN bus reconnected: holding the measured position")
        elif was_ready:
            self._halted_by(Fault(FaultKind.MISSING, tuple(missing),
                                  f"modules {missing} missing after reconnect"))
        elif drv.state is not DriverState.UNINITIALIZED:
            # Halted before the loss: still halted, for the same reason.
            fault = self._fault
            self._set_reason(fault.message if fault is not None else "halted", fault)
        else:
            self._set_reason("not initialised (call ~/init)")
            if self.config.auto_init and not missing:
                self._publish_state()
                ok, msg = self._do("init")
                self._log(logging.INFO if ok else logging.ERROR, f"auto init: {msg}")
        return True

    def _retry_reason(self, reason: str) -> None:
        with self._lock:
            first = self._reason != reason
            self._reason = reason
        if first:  # log each distinct reason once, not every retry
            self._log(logging.WARNING, f"{reason}; retrying with backoff")

    def _read_positions(self) -> np.ndarray:
        assert self.driver is not None
        q = np.asarray(self.driver.read_state().positions, dtype=float).reshape(self.n)
        with self._lock:
            self._q_meas = q
        return q

    def _poll_once(self) -> None:
        try:
            q = self._read_positions()
        except BusTimeoutError:
            return  # a silent module while halted: keep polling quietly; state stays
        except BusError:
            raise
        except ForeignHostError as exc:  # the driver core has halted every module
            self._halted_by(exc.fault, halt=False)
            return
        except RedarmError as exc:  # an implausible position: not published, reported
            now = time.monotonic()
            if now - self._last_poll_warn >= POLL_WARN_INTERVAL_S:  # it repeats at poll_hz
                self._last_poll_warn = now
                self._log(logging.WARNING, f"state poll refused: {exc}")
            return
        self._emit(CycleSample(time.time(), q, None, None))

    def _emit(self, sample: CycleSample) -> None:
        if self._on_sample is not None:
            try:
                self._on_sample(sample)
            except Exception as exc:  # publishing must never stop the loop
                self._log(logging.ERROR, f"on_sample failed: {exc!r}")

    def _run_cycles(self) -> None:
        """Cycle at absolute deadlines until the state changes, a request arrives, or stop."""
        period = self.period_s
        drv = self.driver
        assert drv is not None
        q_meas = self._q_meas if self._q_meas is not None else self._read_positions()
        q_ref = self._q_ref if self._q_ref is not None else q_meas
        shaper = self._shaper
        if shaper is None:
            shaper = self._shaper = ReferenceShaper(drv.limits, period, self.config.limit_margin_rad)
            shaper.reset(q_ref)
        lo_list, hi_list = drv.limits.lower.tolist(), drv.limits.upper.tolist()
        frames_per_cycle = drv.frames_per_cycle
        gc_every = max(1, int(round(0.2 / period)))  # young-generation collection about 5 times a second
        quiet_gc = self.config.quiet_gc
        next_t = time.monotonic()
        gap = False
        first = True  # the first cycle after a pause (init, halt, reconnect) has no period
        prev_now: float | None = None  # when the previous cycle sampled its target
        seen_generation = self.commands.generation
        k = 0
        prev_lost = 0  # missed replies of the previous cycle (a run of misses is logged once)
        while not self._stop.is_set() and self._requests.empty():
            now = time.monotonic()
            if now < next_t:
                time.sleep(next_t - now)
                now = time.monotonic()
            self.stats.start(now, after_overrun=gap, after_pause=first)
            gap = first = False
            target = self.commands.sample(now, q_ref, q_meas, shaper.stopping_point())
            if self.commands.generation != seen_generation:
                seen_generation = self.commands.generation
                if self.commands.mode is CommandMode.HOLD:
                    shaper.hold_still()  # the jump to a hold point is no target velocity to feed forward
            # Into the limits joint by joint on floats (numpy's clip, NaN passed on: the shaper refuses it).
            clipped_list: list[float] = []
            outside: list[int] = []
            for j, (x, low, high) in enumerate(zip(target.tolist(), lo_list, hi_list, strict=True)):
                y = x if x > low or x != x else low
                y = y if y < high or y != y else high
                clipped_list.append(y)
                if y != x:
                    outside.append(j)
            clipped = np.array(clipped_list)
            beyond = tuple(outside)
            # (the park move advances per cycle run, not per wall-clock second: one period each)
            # None = one nominal period: the first cycle after a pause has none of its own
            elapsed = None if prev_now is None or self.commands.mode is CommandMode.PARK else now - prev_now
            ref = shaper.step(clipped, elapsed)
            prev_now = now
            result = drv.cycle(ref, period)
            q_meas = result.positions
            q_ref = result.targets
            ok = [x for x in result.latency_s.tolist() if math.isfinite(x)]
            with self._lock:
                self._q_meas = q_meas
                self._q_ref = q_ref
                self._last_result = result
                self._frames_tx += frames_per_cycle
                self._latencies.extend(ok)
                self._frames_rx += len(ok)
            if beyond or result.clamped:
                self._note_clamps(result, now, beyond)
            if result.lost and not prev_lost:  # the first cycle of a run of misses: when, and who
                missing = [drv.module_ids[j] for j in np.flatnonzero(~result.replied)]
                started = time.time() - (time.monotonic() - now)
                self._log(logging.WARNING, f"missed replies from modules {missing} in the cycle started at "
                          f"wall time {started:.4f}")
            prev_lost = result.lost
            self._emit(CycleSample(time.time(), q_meas, result.velocities, q_ref))
            if result.fault is not None:
                self._halted_by(result.fault, halt=False)  # the driver core has halted every module
                return
            end = time.monotonic()
            self.stats.busy(end - now)
            next_t += period
            k += 1
            if quiet_gc and k % gc_every == 0 and next_t - end > 0.25 * period:
                realtime.collect_young()  # in the slack before the next deadline
                end = time.monotonic()
            # A cycle that ran into the next tick delays that tick (it starts at once); only
            # ticks missed entirely are skipped, so the grid is kept and no burst follows.
            behind = end - next_t
            if behind >= period:
                skipped = int(behind // period)
                next_t += skipped * period
                self.stats.add_overrun(skipped)
                gap = True  # the gap is an overrun, not a period sample

    def _note_clamps(self, result: CycleResult, now: float, beyond: tuple[int, ...] = ()) -> None:
        clamped = tuple(sorted(set(beyond) | set(result.clamped)))
        if not clamped:
            return
        with self._lock:
            self._clamps += 1
        if now - self._last_clamp_log >= self.config.clamp_log_interval_s:
            self._last_clamp_log = now
            self._log(logging.WARNING, f"joint target clamped to the joint or speed limits: joints {clamped}")

    def _halted_by(self, fault: Fault, *, halt: bool = True) -> None:
        """Halt everything (unless the driver core already did) and stay halted until recover."""
        self._shaper = None
        try:
            if halt and self.driver is not None:
                self.driver.halt()
        except BusError as exc:
            self._log(logging.ERROR, f"halt after fault failed: {exc}")
        self.commands.clear(None)
        self._set_reason(fault.message, fault)
        self._log(logging.ERROR, f"HALTED: {fault.message} (call ~/recover)")
        self._publish_state()

    def _bus_lost(self, exc: BaseException) -> None:
        self._shaper = None
        with self._lock:
            self._bus_losses += 1
            self._connected = False
        self.commands.clear(None)
        self._set_reason(f"CAN bus lost: {exc}", self._fault)
        self._log(logging.ERROR, f"CAN bus lost ({exc}); reconnecting with backoff")
        self._publish_state()

    def _close_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:  # a dead transport may complain; it is closed either way
                self._log(logging.INFO, f"ignoring error closing the bus: {exc!r}")

    def _refuse(self, req: _Request, message: str) -> None:
        """Answer ``req`` as refused; a refused halt also withdraws its early request to the driver (no
        halt follows, and the next init must not stop on it)."""
        req.ok, req.message = False, message
        if req.action == "halt" and self.driver is not None:
            self.driver.clear_halt_request()

    def _serve_requests(self, refuse: str | None = None, *, hold: bool = False) -> None:
        """Run the queued requests; with ``refuse``, answer them with that instead; with ``hold``,
        keep them queued (dropping those whose caller gave up)."""
        if hold:
            keep = []
            while True:
                try:
                    req = self._requests.get_nowait()
                except queue.Empty:
                    break
                if time.monotonic() < req.deadline:
                    keep.append(req)
                else:
                    self._refuse(req, f"{req.action}: {refuse}")
                    req.done.set()
            for req in keep:
                self._requests.put(req)
            return
        while True:
            try:
                req = self._requests.get_nowait()
            except queue.Empty:
                return
            if time.monotonic() >= req.deadline and req.action != "halt":
                req.ok, req.message = False, "the caller stopped waiting"
                req.done.set()
                continue  # never run a request nobody waits for any more (but always halt)
            if refuse is not None:
                self._refuse(req, refuse)
            else:
                if req.action == "park":
                    req.ok, req.message, req.park = self._start_park()
                else:
                    req.ok, req.message = self._do(req.action)
            self._publish_state()  # the caller learns the new state no later than the answer
            req.done.set()

    def _start_park(self) -> tuple[bool, str, _ParkMove | None]:
        """Start the synchronised move to the park posture from the current reference (loop thread)."""
        drv = self.driver
        assert drv is not None
        park = self.config.park
        if park is None:
            return False, "park refused: this arm has no park posture (park: in its arm YAML)", None
        if drv.state is DriverState.UNINITIALIZED:
            return False, "park refused: not initialised (call ~/init first)", None
        if drv.state is not DriverState.READY:
            with self._lock:
                reason = self._fault_locked()[1]
            return False, f"park refused: driver is halted ({reason}); call ~/recover first", None
        limits = drv.limits.inset(self.config.limit_margin_rad)
        target = limits.clip(np.asarray(park, dtype=float).reshape(self.n))
        q0 = self._q_ref if self._q_ref is not None else self._read_positions()
        times, points = synchronized_move(limits.clip(q0), target, limits, self.period_s,
                                          self.config.park_speed_scale)
        gen = self.commands.set_park(times, points, self.period_s)
        self._set_reason("moving to the park posture")
        self._log(logging.INFO, f"park: moving to {np.round(target, 4).tolist()} in {times[-1]:.2f} s")
        return True, "park started", _ParkMove(gen, target, float(times[-1]))

    def _do(self, action: str) -> tuple[bool, str]:
        drv = self.driver
        assert drv is not None
        self._shaper = None  # init, halt and recover: the next cycles start from rest
        try:
            if action == "halt":
                acked = drv.halt()
                self.commands.clear(None)
                self._set_reason("halted on request")
                return True, f"all modules halted (acknowledged by {acked})"
            st = drv.init() if action == "init" else drv.recover()
        except RequestRefusedError as exc:  # refused before anything was sent: nothing to halt
            return False, str(exc)
        except BusTimeoutError as exc:
            mids = (exc.module_id,) if exc.module_id is not None else ()
            self._halted_by(Fault(FaultKind.REQUEST_FAILED, mids,
                                  f"{action} failed: module {exc.module_id} did not answer: {exc}"))
            return False, f"{action} failed: {exc}"
        except BusError as exc:
            self._bus_lost(exc)
            return False, f"{action} failed: {exc}"
        except RedarmError as exc:  # e.g. ModuleFaultError: a module still in error
            mid = getattr(exc, "module_id", None)
            self._halted_by(Fault(FaultKind.REQUEST_FAILED, (mid,) if mid is not None else (),
                                  f"{action} failed: {exc}"))
            return False, f"{action} failed: {exc}"
        q = np.asarray(st.positions, dtype=float).reshape(self.n)
        with self._lock:
            self._q_meas = q
            self._missing = []
        # Fresh start: hold the measured position, drop whatever was commanded before.
        self.commands.clear(q)
        self._q_ref = q
        self._set_reason(f"{action} done; holding position")
        note = ""
        if action == "init" and self.config.park_after_init:
            ok, msg, _move = self._start_park()
            note = "; moving to the park posture" if ok else f"; {msg}"
        return True, f"{action} done; holding position {np.round(q, 4).tolist()}{note}"
