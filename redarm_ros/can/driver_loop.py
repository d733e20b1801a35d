"""The cyclic driver loop around :class:`~redarm_ros.can.driver_core.PowerCubeArmDriver` (ROS-free).

The ROS node (``redarm_ros.nodes.can_driver``) is wiring only; everything that
decides *what* is sent and *when* lives here so it can be tested and
benchmarked without ROS:

* :class:`JointCommandSource` turns incoming commands (a timed trajectory, or a
  stream of position targets) into one joint target per cycle, and holds
  position when there is nothing to follow.
* :class:`PeriodStats` measures the achieved cycle period against the nominal.
* :class:`Backoff` spaces reconnect attempts.
* :class:`DriverLoop` is the dedicated thread: absolute deadlines at
  ``rate_hz``, one ``driver.cycle()`` per tick, a state machine for faults
  (a silent module halts all until ``recover``; a lost bus is reopened with
  backoff and never resumes a stale command), and a request queue so that
  init/halt/recover run on the loop thread (the bus has exactly one user).

Units: seconds, radians; times are ``time.monotonic()`` seconds.
"""

from __future__ import annotations

import enum
import threading
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from redarm_ros.errors import InvalidInputError

__all__ = [
    "Backoff",
    "CommandMode",
    "JointCommandSource",
    "PeriodStats",
]


class CommandMode(enum.Enum):
    """What the command source is following."""

    HOLD = "hold"  # keep the held position (after start, init, recover, reconnect, stream stop)
    TRAJECTORY = "trajectory"  # interpolate a timed trajectory, then keep its last point
    STREAM = "stream"  # follow streamed targets; hold if they stop arriving


@dataclass
class _Trajectory:
    index: np.ndarray  # (m,) model joint indices the trajectory commands
    times: np.ndarray  # (k,) s from start, non-decreasing, >= 0
    points: np.ndarray  # (k, m) rad
    start: float  # monotonic s at which time 0 falls
    q_start: np.ndarray | None = None  # (n,) reference captured at the first sample


class JointCommandSource:
    """Thread-safe holder of the current joint command; the loop samples it once per cycle.

    Subscribers call :meth:`set_trajectory` / :meth:`set_stream_target` from any
    thread; the loop calls :meth:`sample` with its current reference.

    Trajectory semantics (as ``trajectory_msgs/JointTrajectory``): time 0 is
    ``start`` (monotonic s); between the reference at time 0 and the points,
    positions are linearly interpolated per joint at each cycle; after the
    last point its position is kept. Joints the trajectory does not name
    keep the reference value they had when it started.

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
        self._stream_q: np.ndarray | None = None
        self._stream_index: np.ndarray | None = None
        self._stream_time = 0.0
        self.generation = 0  # bumps on every new command or clear (for tests/diagnostics)

    @property
    def mode(self) -> CommandMode:
        """The current mode."""
        with self._lock:
            return self._mode

    def _check_index(self, index: Sequence[int]) -> np.ndarray:
        idx = np.asarray(index, dtype=int).reshape(-1)
        if idx.size == 0:
            raise InvalidInputError("command names no joint", field="joint_names", value=list(index))
        if np.any(idx < 0) or np.any(idx >= self.n) or len(set(idx.tolist())) != idx.size:
            raise InvalidInputError(
                "joint indices out of range or repeated", field="joint_names", value=idx.tolist()
            )
        return idx

    def clear(self, hold_q: np.ndarray | None) -> None:
        """Drop any command and hold ``hold_q`` (n,) rad (None: hold the reference given to sample)."""
        with self._lock:
            self._mode = CommandMode.HOLD
            self._hold = None if hold_q is None else np.array(hold_q, dtype=float).reshape(self.n)
            self._traj = None
            self._stream_q = None
            self.generation += 1

    def set_trajectory(
        self, index: Sequence[int], times_s: Sequence[float], points: np.ndarray, start: float
    ) -> None:
        """Follow a trajectory: ``points`` (k, m) rad for model joints ``index`` (m,) at ``times_s`` (k,).

        Raises:
            InvalidInputError: empty, NaN/inf, shape mismatch, negative or decreasing times.
        """
        idx = self._check_index(index)
        t = np.asarray(times_s, dtype=float).reshape(-1)
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape != (t.size, idx.size) or t.size == 0:
            raise InvalidInputError(
                f"trajectory needs points of shape ({t.size}, {idx.size}), got {p.shape}",
                field="points",
                value=p.shape,
            )
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise InvalidInputError("trajectory contains NaN or inf", field="points")
        if t[0] < 0 or np.any(np.diff(t) < 0):
            raise InvalidInputError(
                "time_from_start must be >= 0 and non-decreasing", field="times", value=t.tolist()
            )
        with self._lock:
            self._traj = _Trajectory(idx, t, p, float(start))
            self._mode = CommandMode.TRAJECTORY
            self._stream_q = None
            self.generation += 1

    def set_stream_target(self, index: Sequence[int], q: Sequence[float], now: float) -> None:
        """Follow the streamed target ``q`` (m,) rad for model joints ``index``, received at ``now``.

        Raises:
            InvalidInputError: NaN/inf or length mismatch.
        """
        idx = self._check_index(index)
        qq = np.asarray(q, dtype=float).reshape(-1)
        if qq.size != idx.size:
            raise InvalidInputError(f"{qq.size} positions for {idx.size} joints", field="position")
        if not np.all(np.isfinite(qq)):
            raise InvalidInputError("target contains NaN or inf", field="position")
        with self._lock:
            self._stream_index = idx
            self._stream_q = qq
            self._stream_time = float(now)
            self._mode = CommandMode.STREAM
            self._traj = None
            self.generation += 1

    def sample(self, now: float, q_ref: np.ndarray, q_measured: np.ndarray) -> np.ndarray:
        """The joint target (n,) rad for the cycle at ``now``.

        ``q_ref`` is the target sent in the previous cycle (continuity for new
        commands), ``q_measured`` the latest measured position (used when a
        stream stops, or when HOLD has no position yet).
        """
        with self._lock:
            mode = self._mode
            if mode is CommandMode.TRAJECTORY:
                tr = self._traj
                assert tr is not None
                if tr.q_start is None:
                    tr.q_start = np.array(q_ref, dtype=float)
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
                self._hold = np.array(q_measured, dtype=float)
            return self._hold.copy()


def _interpolate(tr: _Trajectory, now: float) -> np.ndarray:
    assert tr.q_start is not None
    q = tr.q_start.copy()
    t = now - tr.start
    if t <= 0.0:
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


class PeriodStats:
    """Achieved cycle periods against the nominal one (window of the last ``window`` cycles)."""

    def __init__(self, period_s: float, window: int = 2500) -> None:
        self.period_s = float(period_s)
        self._periods: deque[float] = deque(maxlen=window)
        self._lock = threading.Lock()
        self.cycles = 0
        self.overruns = 0  # ticks skipped because a cycle ended after the next deadline

    def add(self, period_s: float) -> None:
        """Record one measured period (s) between consecutive cycle starts."""
        with self._lock:
            self._periods.append(period_s)
            self.cycles += 1

    def add_overrun(self, skipped: int) -> None:
        """Record ``skipped`` ticks that were dropped because the loop fell behind."""
        with self._lock:
            self.overruns += int(skipped)

    def reset(self) -> None:
        """Forget the window (counters stay)."""
        with self._lock:
            self._periods.clear()

    def summary(self) -> dict[str, float]:
        """``rate_hz``, ``period_err_median_ms``, ``period_err_p99_ms``, ``period_err_max_ms`` (abs error)."""
        with self._lock:
            p = np.fromiter(self._periods, dtype=float)
        if p.size == 0:
            return {
                "rate_hz": 0.0,
                "period_err_median_ms": 0.0,
                "period_err_p99_ms": 0.0,
                "period_err_max_ms": 0.0,
                "samples": 0,
            }
        err = np.abs(p - self.period_s) * 1e3
        return {
            "rate_hz": float(1.0 / p.mean()),
            "period_err_median_ms": float(np.median(err)),
            "period_err_p99_ms": float(np.percentile(err, 99)),
            "period_err_max_ms": float(err.max()),
            "samples": int(p.size),
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
