"""The cyclic driver loop around :class:`~redarm_ros.can.driver_core.PowerCubeArmDriver` (ROS-free).

The ROS node (``redarm_ros.nodes.can_driver``) is wiring only; everything that
decides *what* is sent and *when* lives here so it can be tested and
benchmarked without ROS:

* :class:`JointCommandSource` turns incoming commands (a timed trajectory, or a
  stream of position targets) into one joint target per cycle, and holds
  position when there is nothing to follow.
* :class:`PeriodStats` measures the achieved cycle period against the nominal.
* :class:`ReferenceShaper` turns the sampled target into what is sent: velocity- and
  acceleration-limited, braking early enough to stop on a joint limit (targets beyond a limit
  are clamped to it first and reported).
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
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.can.protocol import ActState
from redarm_ros.errors import BusError, BusTimeoutError, InvalidInputError, RedarmError

_LOG = logging.getLogger(__name__)
_HOME_OK = int(ActState.HOME_OK)

__all__ = [
    "Backoff",
    "ReferenceShaper",
    "braking_speed",
    "CommandMode",
    "DriverLoop",
    "JointCommandSource",
    "LoopConfig",
    "LoopSnapshot",
    "LoopState",
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


def braking_speed(distance: np.ndarray, acc: np.ndarray, dt: float) -> np.ndarray:
    """Largest speed (rad/s) from which a reference stepping every ``dt`` s, slowing by ``acc * dt``
    per step, stops within ``distance`` (rad, >= 0): the discrete form of ``sqrt(2 a d)``."""
    d = np.maximum(distance, 0.0)
    adt = acc * dt
    return adt * (np.sqrt(0.25 + 2.0 * d / (adt * dt)) - 0.5)


class ReferenceShaper:
    """Velocity- and acceleration-limited joint reference that follows a (moving) target.

    Every cycle the reference moves toward the target with the target's own velocity fed
    forward plus a braking-law correction, so a feasible trajectory is followed without lag,
    while a jump is turned into a trapezoid. Limits enforced on the *reference* (what is sent):
    ``|v| <= max_vel``, ``|dv/dt| <= max_acc``, and the reference slows down early enough to stop
    on ``lower``/``upper`` at ``max_acc``: a target at (or clamped to) a joint limit is reached
    without overshooting it, which a stream of FSTEPs arriving at full speed would do.

    Arrays are (n,); units rad, rad/s, rad/s^2; ``dt`` is the nominal cycle period in s.
    """

    def __init__(self, lower: np.ndarray, upper: np.ndarray, max_vel: np.ndarray, max_acc: np.ndarray,
                 dt: float) -> None:
        self.lower = np.asarray(lower, dtype=float)
        self.upper = np.asarray(upper, dtype=float)
        self.max_vel = np.asarray(max_vel, dtype=float)
        self.max_acc = np.asarray(max_acc, dtype=float)
        self.dt = float(dt)
        self.r: np.ndarray | None = None
        self.v = np.zeros_like(self.lower)
        self._g_prev: np.ndarray | None = None

    def reset(self, q: np.ndarray) -> None:
        """Start from rest at ``q`` (rad): after init, recover, reconnect."""
        self.r = np.clip(np.array(q, dtype=float), self.lower, self.upper)
        self.v = np.zeros_like(self.r)
        self._g_prev = None

    def step(self, target: np.ndarray) -> np.ndarray:
        """Advance one cycle toward ``target`` (n,) rad (already within the limits); returns the reference."""
        if self.r is None:
            self.reset(target)
            return self.r.copy()  # type: ignore[union-attr]
        dt, a, vmax = self.dt, self.max_acc, self.max_vel
        g = np.clip(target, self.lower, self.upper)
        u = np.zeros_like(g) if self._g_prev is None else np.clip((g - self._g_prev) / dt, -vmax, vmax)
        self._g_prev = g
        r, v = self.r, self.v
        # Tracking error against where the target was: with u fed forward, r then lands on g.
        e = (g - u * dt) - r
        v_des = u + np.sign(e) * braking_speed(np.abs(e), a, dt)
        v_des = np.clip(v_des, -vmax, vmax)
        # Never faster toward a joint limit than allows stopping on it.
        v_des = np.minimum(v_des, braking_speed(self.upper - r, a, dt))
        v_des = np.maximum(v_des, -braking_speed(r - self.lower, a, dt))
        v_new = v + np.clip(v_des - v, -a * dt, a * dt)
        r_new = r + v_new * dt
        # Land exactly on a stationary target instead of dithering around it.
        land = (np.abs(g - r_new) <= a * dt * dt) & (np.abs(v) <= a * dt) & (u == 0)
        r_new = np.where(land, g, r_new)
        v_new = np.where(land, 0.0, v_new)
        self.r = np.clip(r_new, self.lower, self.upper)
        self.v = np.where((self.r == self.lower) | (self.r == self.upper), 0.0, v_new)
        return self.r.copy()


class PeriodStats:
    """Achieved cycle timing against the nominal period (window of the last ``window`` cycles).

    :meth:`start` is called with every cycle's start time; the period between two cycles is a
    sample unless ticks were skipped in between (an overrun, counted separately). The achieved
    rate counts every cycle over the window's time span, overruns included.
    """

    def __init__(self, period_s: float, window: int = 2500) -> None:
        self.period_s = float(period_s)
        self._periods: deque[float] = deque(maxlen=window)
        self._starts: deque[float] = deque(maxlen=window)
        self._busy: deque[float] = deque(maxlen=window)
        self._lock = threading.Lock()
        self.cycles = 0
        self.overruns = 0  # ticks skipped because a cycle ended after the next deadline

    def start(self, t: float, *, after_overrun: bool = False) -> None:
        """Record a cycle starting at ``t`` (s); ``after_overrun``: ticks were skipped before it."""
        with self._lock:
            if self._starts and not after_overrun:
                self._periods.append(t - self._starts[-1])
            self._starts.append(t)
            self.cycles += 1

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
        """Forget the window (counters stay); call when cycling resumes after a pause."""
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


class LoopState(enum.Enum):
    """State of :class:`DriverLoop` (reported on /diagnostics)."""

    CONNECTING = "connecting"  # bus not open (start-up or lost): retrying with backoff
    IDLE = "idle"  # bus open, modules not initialised: state polled, no motion sent
    RUNNING = "running"  # cyclic FSTEP stream at rate_hz, following commands or holding
    HALTED = "halted"  # halted by request or fault: state polled, no motion until recover
    STOPPED = "stopped"  # loop thread ended


@dataclass(frozen=True)
class LoopConfig:
    """Timing of :class:`DriverLoop`: ``rate_hz`` cycle rate, ``poll_hz`` state polling when not running,
    ``hold_on_stream_stop_s`` stream timeout, reconnect backoff (s), ``auto_init`` after connecting."""

    rate_hz: float = 250.0
    poll_hz: float = 10.0
    hold_on_stream_stop_s: float = 0.5
    reconnect_first_s: float = 0.1
    reconnect_max_s: float = 2.0
    auto_init: bool = False
    clamp_log_interval_s: float = 1.0


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
    """A consistent copy of the loop's status for diagnostics."""

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
    module_stats: object | None  # the driver's per-module statistics (driver-specific)
    last_result: object | None  # the driver's last CycleResult
    positions: np.ndarray | None
    latency: dict[str, float] | None = None  # reply latency over the window: median/p99/max ms
    frames_tx: int = 0  # frames sent by cycles (FSTEP per joint, STARTMOVE, watchdog refresh)
    frames_rx: int = 0  # replies received by cycles
    frames_per_s: float = 0.0  # (tx + rx) per second over the last snapshot interval


class _Request:
    def __init__(self, action: str) -> None:
        self.action = action
        self.done = threading.Event()
        self.ok = False
        self.message = ""


LogFn = Callable[[int, str], None]


def _default_log(level: int, message: str) -> None:
    _LOG.log(level, "%s", message)


class DriverLoop:
    """The dedicated driver thread: connect, poll or cycle at absolute deadlines, serve requests.

    Args:
        driver_factory: ``f(bus) -> driver`` building a
            :class:`~redarm_ros.can.driver_core.PowerCubeArmDriver` (or a stand-in with the same
            methods) for an open bus.
        open_bus: ``f() -> bus`` opening the CAN bus (raises :class:`BusError` when it cannot).
            If the bus has ``reopen()`` (a :class:`~redarm_ros.can.bus.ReconnectingBus`), a lost
            bus is reopened in place, else it is shut down and opened anew.
        n: joint count.
        config: timing, see :class:`LoopConfig`.
        on_sample: called from the loop thread after every cycle / poll (keep it short: publish).
        log: ``f(level, message)`` with :mod:`logging` levels (the node forwards to its logger).

    The loop owns the bus: ``init``/``halt``/``recover`` run on its thread via :meth:`request`;
    commands go to :attr:`commands` from any thread, but are only accepted while RUNNING.

    Failure behaviour: a module that stops answering (the driver raises
    :class:`BusTimeoutError`) or reports an error -> everything halted, state HALTED until
    ``recover``. The bus lost (:class:`BusError`) -> state CONNECTING, reopened with backoff;
    if the loop was RUNNING it resumes holding the *measured* position (the command it was
    following is dropped, never replayed).
    """

    def __init__(
        self,
        driver_factory: Callable[[Any], Any],
        open_bus: Callable[[], Any],
        n: int,
        config: LoopConfig = LoopConfig(),  # noqa: B008 - frozen dataclass, safe default
        *,
        on_sample: Callable[[CycleSample], None] | None = None,
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
        self._log = log
        self._lock = threading.Lock()
        self._requests: queue.Queue[_Request] = queue.Queue()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.bus: Any = None
        self.driver: Any = None
        self._state = LoopState.CONNECTING
        self._reason = "starting"
        self._resume = LoopState.IDLE  # state to return to after (re)connecting
        self._connects = 0
        self._bus_losses = 0
        self._clamps = 0
        self._missing: list[int] = []
        self._last_result: Any = None
        self._q_meas: np.ndarray | None = None
        self._q_ref: np.ndarray | None = None
        self._last_clamp_log = -1e9
        self._halt_reason = ""
        # Reply latencies (s) of the last 500 cycles, all joints (small: diagnostics run in
        # another thread and numpy holds the GIL while it sorts), and frame counters.
        self._latencies: deque[float] = deque(maxlen=500 * self.n)
        self._frames_tx = 0
        self._frames_rx = 0
        self._fps_mark = (time.monotonic(), 0)

    # -- public API (any thread) ------------------------------------------------------------------
    @property
    def state(self) -> LoopState:
        """The current state."""
        with self._lock:
            return self._state

    def start(self) -> DriverLoop:
        """Start the loop thread; returns self."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="can-driver-loop", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread and close the bus (modules keep their last, finished FSTEP)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self._close_bus()
        self._set_state(LoopState.STOPPED, "stopped")

    def request(self, action: str, timeout: float = 60.0) -> tuple[bool, str]:
        """Run ``init``, ``halt`` or ``recover`` on the loop thread; returns (success, message)."""
        if action not in ("init", "halt", "recover"):
            return False, f"unknown action {action!r}"
        if self._thread is None or not self._thread.is_alive():
            return False, "driver loop is not running"
        req = _Request(action)
        self._requests.put(req)
        self._wake.set()
        if not req.done.wait(timeout):
            return False, f"{action} did not finish within {timeout:.0f} s"
        return req.ok, req.message

    def reset_measurements(self) -> None:
        """Start fresh timing and latency windows (counters such as cycles and overruns stay)."""
        self.stats.reset()
        with self._lock:
            self._latencies.clear()

    def accepting_commands(self) -> tuple[bool, str]:
        """Whether a new command would be followed now, and why not."""
        with self._lock:
            if self._state is LoopState.RUNNING:
                return True, ""
            return False, f"driver is {self._state.value} ({self._reason}); command ignored"

    def snapshot(self) -> LoopSnapshot:
        """A copy of the status for diagnostics."""
        with self._lock:
            state, reason = self._state, self._reason
            last = self._last_result
            q = None if self._q_meas is None else self._q_meas.copy()
            missing = list(self._missing)
            connects, losses, clamps = self._connects, self._bus_losses, self._clamps
        drv = self.driver
        mstats = getattr(drv, "stats", None) if drv is not None else None
        with self._lock:
            lat = np.fromiter(self._latencies, dtype=float)
            tx, rx = self._frames_tx, self._frames_rx
            now = time.monotonic()
            t_prev, f_prev = self._fps_mark
            fps = (tx + rx - f_prev) / (now - t_prev) if now > t_prev else 0.0
            self._fps_mark = (now, tx + rx)
        latency = None
        if lat.size:
            latency = {"median_ms": float(np.median(lat) * 1e3),
                       "p99_ms": float(np.percentile(lat, 99) * 1e3), "max_ms": float(lat.max() * 1e3)}
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
            latency=latency,
            frames_tx=tx,
            frames_rx=rx,
            frames_per_s=fps,
        )

    # -- loop thread ------------------------------------------------------------------------------
    def _set_state(self, state: LoopState, reason: str) -> None:
        with self._lock:
            self._state, self._reason = state, reason

    def _run(self) -> None:
        backoff = Backoff(self.config.reconnect_first_s, self.config.reconnect_max_s)
        while not self._stop.is_set():
            state = self.state
            try:
                if state is LoopState.CONNECTING:
                    if not self._connect():
                        delay = backoff.next_delay()
                        self._serve_requests(refuse=f"CAN bus not connected ({self._reason})")
                        self._stop.wait(delay)
                        continue
                    backoff.reset()
                    continue
                self._serve_requests()
                if self.state is LoopState.RUNNING:
                    self._run_cycles()
                else:
                    self._poll_once()
                    self._wake.wait(1.0 / self.config.poll_hz)
                    self._wake.clear()
            except BusTimeoutError as exc:
                # The driver core has already halted every module.
                self._fault(f"module {exc.module_id} stopped answering: {exc}", halt=False)
            except BusError as exc:
                self._bus_lost(exc)
            except Exception as exc:  # a bug must not leave the arm moving: halt and report
                self._log(logging.ERROR, f"driver loop error: {exc!r}")
                self._fault(f"internal error: {exc!r}")
                self._stop.wait(0.1)
        self._serve_requests(refuse="driver stopping")

    def _connect(self) -> bool:
        """Open (or reopen) the bus and discover the modules; False means retry later."""
        resume = self._resume
        try:
            if self.driver is not None and self.bus is not None and hasattr(self.bus, "reopen"):
                if resume is LoopState.RUNNING:
                    # Reopen, re-read the positions and hold them: nothing from before is replayed.
                    self.driver.reconnect()
                else:
                    self.bus.reopen()
            else:
                self._close_bus()
                self.bus = self._open_bus()
                self.driver = self._driver_factory(self.bus)
            report = self.driver.discover()
        except BusError as exc:  # includes BusTimeoutError: modules not (yet) answering
            self._retry_reason(f"CAN bus not usable yet: {exc}")
            return False
        missing = list(getattr(report, "missing", []) or [])
        if len(missing) == self.n:
            self._retry_reason("CAN bus open, but no module answers discovery")
            return False
        with self._lock:
            self._connects += 1
            self._missing = missing
        if missing:
            self._log(logging.ERROR, f"modules not answering discovery: {missing}")
        else:
            self._log(logging.INFO, f"CAN bus connected, all {self.n} modules found")
        self._q_meas = None
        self._q_ref = None
        if resume is LoopState.RUNNING and not missing:
            self.commands.clear(None)
            self._set_state(LoopState.RUNNING, "reconnected; holding measured position")
            self._log(logging.WARNING, "CAN bus reconnected: holding the measured position")
        elif resume is LoopState.RUNNING:
            self._fault(f"modules {missing} missing after reconnect", halt=True)
        elif resume is LoopState.HALTED:
            self._set_state(LoopState.HALTED, self._halt_reason or "halted")
        else:
            self._set_state(LoopState.IDLE, "not initialised (call ~/init)")
            if self.config.auto_init and not missing:
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
        st = self.driver.read_state()
        q = np.array(_positions_of(st), dtype=float).reshape(self.n)
        with self._lock:
            self._q_meas = q
        return q

    def _poll_once(self) -> None:
        try:
            q = self._read_positions()
        except BusTimeoutError:
            return  # a silent module while halted: keep polling quietly; state stays
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
        q_meas = self._q_meas if self._q_meas is not None else self._read_positions()
        q_ref = self._q_ref if self._q_ref is not None else q_meas
        shaper = self._make_shaper()
        if shaper is not None:
            shaper.reset(q_ref)
        lo, hi = _limits_of(drv)
        frames_per_cycle = self.n + 1 + (1 if getattr(drv, "watchdog_refresh", False) else 0)
        next_t = time.monotonic()
        gap = True  # the first cycle after a pause has no period
        while not self._stop.is_set() and self._requests.empty():
            now = time.monotonic()
            if now < next_t:
                time.sleep(next_t - now)
                now = time.monotonic()
            self.stats.start(now, after_overrun=gap)
            gap = False
            target = self.commands.sample(now, q_ref, q_meas)
            beyond: tuple[int, ...] = ()
            if lo is not None and hi is not None:
                clipped = np.clip(target, lo, hi)
                if not np.array_equal(clipped, target):
                    beyond = tuple(int(j) for j in np.flatnonzero(clipped != target))
                    target = clipped
            ref = shaper.step(target) if shaper is not None else target
            result = drv.cycle(ref, period)
            q_meas = np.array(_positions_of(result), dtype=float)
            sent = _sent_target_of(result, ref)
            q_ref = sent
            lat = getattr(result, "latency_s", None)
            with self._lock:
                self._q_meas = q_meas
                self._q_ref = q_ref
                self._last_result = result
                self._frames_tx += frames_per_cycle
                if lat is not None:
                    ok = lat[np.isfinite(lat)]
                    self._latencies.extend(ok.tolist())
                    self._frames_rx += int(ok.size)
            self._note_clamps(result, now, beyond)
            self._emit(CycleSample(time.time(), q_meas, _velocities_of(result), sent))
            fault = _fault_of(result)
            if fault:
                self._fault(fault, halt=False)  # the driver core has halted every module
                return
            end = time.monotonic()
            self.stats.busy(end - now)
            next_t += period
            # A cycle that ran into the next tick delays that tick (it starts at once); only
            # ticks missed entirely are skipped, so the grid is kept and no burst follows.
            behind = end - next_t
            if behind >= period:
                skipped = int(behind // period)
                next_t += skipped * period
                self.stats.add_overrun(skipped)
                gap = True  # the gap is an overrun, not a period sample

    def _make_shaper(self) -> ReferenceShaper | None:
        drv = self.driver
        try:
            lo, hi = _limits_of(drv)
            vmax, amax = np.asarray(drv.max_vel, dtype=float), np.asarray(drv.max_acc, dtype=float)
        except AttributeError:
            return None
        if lo is None or hi is None:
            return None
        return ReferenceShaper(lo, hi, vmax, amax, self.period_s)

    def _note_clamps(self, result: Any, now: float, beyond: tuple[int, ...] = ()) -> None:
        clamped = tuple(sorted(set(beyond) | set(_clamps_of(result) or ())))
        if not clamped:
            return
        with self._lock:
            self._clamps += 1
        if now - self._last_clamp_log >= self.config.clamp_log_interval_s:
            self._last_clamp_log = now
            self._log(logging.WARNING, f"joint target clamped to the joint or speed limits: joints {clamped}")

    def _fault(self, reason: str, *, halt: bool = True) -> None:
        """Halt everything (unless the driver core already did) and stay halted until recover."""
        try:
            if halt and self.driver is not None:
                self.driver.halt()
        except BusError as exc:
            self._log(logging.ERROR, f"halt after fault failed: {exc}")
        self.commands.clear(None)
        self._halt_reason = reason
        self._resume = LoopState.HALTED
        self._set_state(LoopState.HALTED, reason)
        self._log(logging.ERROR, f"HALTED: {reason} (call ~/recover)")

    def _bus_lost(self, exc: BaseException) -> None:
        prev = self.state
        self._resume = prev if prev in (LoopState.RUNNING, LoopState.HALTED, LoopState.IDLE) else self._resume
        with self._lock:
            self._bus_losses += 1
        self.commands.clear(None)
        self._set_state(LoopState.CONNECTING, f"CAN bus lost: {exc}")
        self._log(logging.ERROR, f"CAN bus lost ({exc}); reconnecting with backoff")

    def _close_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:  # a dead transport may complain; it is closed either way
                self._log(logging.INFO, f"ignoring error closing the bus: {exc!r}")

    def _serve_requests(self, refuse: str | None = None) -> None:
        while True:
            try:
                req = self._requests.get_nowait()
            except queue.Empty:
                return
            if refuse is not None:
                req.ok, req.message = False, refuse
            else:
                req.ok, req.message = self._do(req.action)
            req.done.set()

    def _do(self, action: str) -> tuple[bool, str]:
        drv = self.driver
        try:
            if action == "halt":
                acked = drv.halt()
                self.commands.clear(None)
                self._halt_reason = "halted on request"
                self._resume = LoopState.HALTED
                self._set_state(LoopState.HALTED, self._halt_reason)
                return True, f"all modules halted (acknowledged by {acked})"
            st = drv.init() if action == "init" else drv.recover()
        except BusTimeoutError as exc:
            self._fault(f"{action} failed: module {exc.module_id} did not answer: {exc}")
            return False, f"{action} failed: {exc}"
        except BusError as exc:
            self._bus_lost(exc)
            return False, f"{action} failed: {exc}"
        except RedarmError as exc:  # e.g. ModuleFaultError: a module still in error
            self._fault(f"{action} failed: {exc}")
            return False, f"{action} failed: {exc}"
        q = np.array(_positions_of(st), dtype=float).reshape(self.n)
        with self._lock:
            self._q_meas = q
            self._missing = []
        # Fresh start: hold the measured position, drop whatever was commanded before.
        self.commands.clear(q)
        self._q_ref = q
        self._resume = LoopState.RUNNING
        self._halt_reason = ""
        self._set_state(LoopState.RUNNING, f"{action} done; holding position")
        note = ""
        states = getattr(st, "states", None)
        if states is not None and action == "recover":
            not_homed = [i + 1 for i, b in enumerate(states) if not int(b) & _HOME_OK]
            if not_homed:
                note = f"; joints {not_homed} report no HOME_OK (a restarted module? ~/init homes)"
        return True, f"{action} done; holding position {np.round(q, 4).tolist()}{note}"


# -- adapters to the driver core's result objects (kept in one place) -----------------------------
def _positions_of(obj: Any) -> np.ndarray:
    return np.asarray(getattr(obj, "positions", obj), dtype=float)


def _velocities_of(obj: Any) -> np.ndarray | None:
    v = getattr(obj, "velocities", None)
    return None if v is None else np.asarray(v, dtype=float)


def _sent_target_of(result: Any, target: np.ndarray) -> np.ndarray:
    sent = getattr(result, "targets", None)
    return np.array(target if sent is None else sent, dtype=float)


def _clamps_of(result: Any) -> Any:
    return getattr(result, "clamped", None)


def _limits_of(driver: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    lo, hi = getattr(driver, "lower", None), getattr(driver, "upper", None)
    if lo is None or hi is None:
        return None, None
    return np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)


def _fault_of(result: Any) -> str:
    return str(getattr(result, "fault", "") or "")
