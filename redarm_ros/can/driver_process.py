"""The CAN cycle in a process of its own: a :class:`~redarm_ros.can.driver_loop.DriverLoop` that the rest
of the machine (and the ROS executor next to it) cannot starve.

Why a process: in one Python process the cycle thread shares the interpreter lock and the garbage
collector with the ROS executor; a long callback, a module import or a full collection in the
node would delay the cycle, and a delayed cycle makes the modules' watchdog or the driver's own
silence check halt the arm. In its own process the cycle runs with

* real-time scheduling (``SCHED_FIFO`` at ``realtime_priority``) when permitted, else the highest
  nice level allowed, with one log line saying which (:func:`redarm_ros.can.realtime.raise_priority`);
* the garbage collector frozen after start-up and only young objects collected, in the slack
  between cycles (:func:`redarm_ros.can.realtime.quiet_gc`);
* nothing but numpy, python-can and this package imported (no rclpy).

:class:`DriverProcess` is the parent's handle, with the same surface the node uses on a
:class:`~redarm_ros.can.driver_loop.DriverLoop` (``commands``, ``request``, ``snapshot``,
``accepting_commands``, ``state``, ``start``, ``stop``). The child is
``python -m redarm_ros.can.driver_process --fd N``, talking over a socket pair with pickled tuples:
commands, requests and snapshot queries one way; every cycle's sample, state changes, log lines and
answers the other way. The cycle thread writes each sample itself, never waiting (a full socket: the
sample is dropped and counted); while the socket is busy or samples wait, through a bounded queue and
a sender thread, so a slow parent loses samples but never stalls the cycle. A parent reader that fell
behind hands on only the newest sample queued (``samples_skipped`` counts the others), so what it
publishes is never older than its own delay. The child ignores SIGINT and SIGTERM (the parent
stops it) and ends when the parent's end of the socket closes, so a killed node takes its cycle
with it: the modules' watchdog then halts the arm.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import os
import queue
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.can import realtime
from redarm_ros.can.driver_core import DEFAULT_PLAUSIBILITY_MARGIN, Fault, PowerCubeArmDriver
from redarm_ros.can.driver_loop import (
    ACTIONS,
    CommandMode,
    CycleSample,
    DriverLoop,
    LoopConfig,
    LoopSnapshot,
    LoopState,
    check_stream_target,
    check_trajectory,
)
from redarm_ros.errors import RedarmError
from redarm_ros.procs import die_with_parent_preexec

_LOG = logging.getLogger(__name__)

__all__ = ["DEFAULT_SAMPLE_RATE_HZ", "DEFAULT_STILL_SAMPLE_RATE_HZ", "DriverProcess", "DriverSpec",
           "SampleThrottle", "build_loop"]

#: Samples that may wait for the parent; beyond that new ones are dropped (counted).
SAMPLE_QUEUE = 256
#: Default rate (Hz) of the samples handed on (the node's /joint_states): every cycle is more than a
#: controller at 100 Hz or a viewer needs, and each sample costs a message in every subscriber.
DEFAULT_SAMPLE_RATE_HZ = 100.0
#: Default rate (Hz) of the samples handed on while the arm stands still: a heartbeat that shows the
#: driver alive (and fresh to a stale-state check) without costing every subscriber 100 messages/s.
DEFAULT_STILL_SAMPLE_RATE_HZ = 10.0
#: A joint that moved less than this (rad) since the last sample handed on stands still.
STILL_EPSILON_RAD = 1e-5


@dataclass(frozen=True)
class DriverSpec:
    """Everything needed to build the driver and its loop (picklable; units rad, rad/s, rad/s^2, s).

    ``can_kwargs`` are python-can keywords for :func:`redarm_ros.can.bus.open_bus`;
    ``realtime_priority`` is the SCHED_FIFO priority asked for (0: normal scheduling).
    """

    module_ids: tuple[int, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    max_vel: tuple[float, ...]
    max_acc: tuple[float, ...]
    can_kwargs: dict[str, Any] = field(default_factory=dict)
    loop: LoopConfig = LoopConfig()  # noqa: RUF009 - frozen dataclass, safe default
    reply_timeout_s: float = 0.02
    max_missed: int = 5
    watchdog: bool = True
    plausibility_margin_rad: float = DEFAULT_PLAUSIBILITY_MARGIN
    realtime_priority: int = 0
    sample_rate_hz: float = 0.0  # samples handed on per second (0: every cycle)
    still_sample_rate_hz: float = 0.0  # ... while the arm stands still (0: as sample_rate_hz)

    @property
    def n(self) -> int:
        """Joint count."""
        return len(self.module_ids)


def build_loop(
    spec: DriverSpec,
    *,
    on_sample: Callable[[CycleSample], None] | None = None,
    on_state: Callable[[LoopState, str, Fault | None], None] | None = None,
    log: Callable[[int, str], None] | None = None,
    open_bus: Callable[[], Any] | None = None,
) -> DriverLoop:
    """The :class:`DriverLoop` of ``spec`` (not started): a PowerCube driver on the configured bus.

    ``open_bus`` overrides how the bus is opened (default: :func:`redarm_ros.can.bus.open_bus` with
    ``spec.can_kwargs``).
    """
    from redarm_ros.can.bus import open_bus as _open_bus

    def make_driver(bus: Any) -> PowerCubeArmDriver:
        return PowerCubeArmDriver(
            bus, spec.module_ids, spec.lower, spec.upper, spec.max_vel, spec.max_acc,
            reply_timeout_s=spec.reply_timeout_s, max_missed=spec.max_missed,
            watchdog_refresh=spec.watchdog, enable_watchdog=spec.watchdog,
            plausibility_margin_rad=spec.plausibility_margin_rad,
        )

    opener = open_bus if open_bus is not None else (lambda: _open_bus(**spec.can_kwargs))
    if on_sample is not None and (spec.sample_rate_hz > 0.0 or spec.still_sample_rate_hz > 0.0):
        on_sample = SampleThrottle(spec.sample_rate_hz, spec.loop.rate_hz,
                                   spec.still_sample_rate_hz).wrap(on_sample)
    kwargs: dict[str, Any] = {"on_sample": on_sample, "on_state": on_state}
    if log is not None:
        kwargs["log"] = log
    return DriverLoop(make_driver, opener, spec.n, spec.loop, **kwargs)


class SampleThrottle:
    """Hands on cycle samples at ``rate_hz`` on average (by their stamps), from a loop at ``cycle_hz``;
    while the cycle runs and the arm stands still, at ``still_rate_hz`` only (0: always at ``rate_hz``).

    A sample is due half a cycle before its time, so a rate that is no divisor of the cycle's is kept
    on average (100 Hz from 250 Hz: 8 and 12 ms apart in turn); after a gap the schedule restarts.
    Standing still: no position moved by more than :data:`STILL_EPSILON_RAD` and the target did not
    change since the last sample handed on. The first sample that moved goes on at the full rate's
    schedule again, so a motion is seen within one full-rate period.
    """

    def __init__(self, rate_hz: float, cycle_hz: float, still_rate_hz: float = 0.0) -> None:
        self.period = 1.0 / rate_hz if rate_hz > 0.0 else 0.0
        self.still_period = 1.0 / still_rate_hz if still_rate_hz > 0.0 else 0.0
        self._slack = 0.5 / cycle_hz
        self._next: float | None = None
        self._last_sent: float | None = None
        self._last_q: np.ndarray | None = None
        self._last_target: np.ndarray | None = None

    def _still(self, positions: np.ndarray | None, target: np.ndarray | None) -> bool:
        q0, target0 = self._last_q, self._last_target
        if positions is None or target is None or q0 is None or target0 is None:
            return False  # polls (no target) keep their own rate
        if q0.shape != positions.shape:
            return False
        if not np.array_equal(target, target0):
            return False
        return float(np.max(np.abs(positions - q0))) <= STILL_EPSILON_RAD

    def due(self, stamp: float, positions: np.ndarray | None = None,
            target: np.ndarray | None = None) -> bool:
        """True if the sample stamped ``stamp`` (s), measuring ``positions`` (rad) while sending
        ``target`` (rad; None when polling), is to be handed on (without positions: as moving)."""
        nxt = self._next
        if nxt is not None and stamp < nxt - self._slack:
            return False
        last = self._last_sent
        if self.still_period > self.period and last is not None and stamp - last < self.still_period \
                - self._slack and self._still(positions, target):
            return False
        self._next = stamp + self.period if nxt is None or stamp - nxt > self.period else nxt + self.period
        self._last_sent = stamp
        if positions is not None:
            self._last_q = np.array(positions, dtype=float)
            self._last_target = None if target is None else np.array(target, dtype=float)
        return True

    def wrap(self, on_sample: Callable[[CycleSample], None]) -> Callable[[CycleSample], None]:
        """``on_sample`` called only for the samples that are due."""
        def throttled(s: CycleSample) -> None:
            if self.due(s.stamp, s.positions, s.target):
                on_sample(s)

        return throttled


# --------------------------------------------------------------------------------------------------
# Parent side
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _NoAnswer:
    why: str


class RemoteCommands:
    """The parent's stand-in for the child's :class:`~redarm_ros.can.driver_loop.JointCommandSource`:
    validates here (a bad command raises :class:`~redarm_ros.errors.InvalidInputError` at once) and
    forwards to the child."""

    def __init__(self, owner: DriverProcess, n: int, stream_timeout_s: float) -> None:
        self._owner = owner
        self.n = n
        self._stream_timeout_s = float(stream_timeout_s)
        self.mode = CommandMode.HOLD  # as last reported by a snapshot

    @property
    def stream_timeout_s(self) -> float:
        """A stream older than this (s) is dropped and the measured position held."""
        return self._stream_timeout_s

    @stream_timeout_s.setter
    def stream_timeout_s(self, value: float) -> None:
        self._stream_timeout_s = float(value)
        self._owner._send(("stream_timeout", float(value)))

    def set_trajectory(self, index: Sequence[int], times_s: Sequence[float], points: np.ndarray,
                       start: float) -> None:
        """See :meth:`JointCommandSource.set_trajectory` (``start`` on the shared monotonic clock)."""
        idx, t, p = check_trajectory(self.n, index, times_s, points)
        self._owner._send(("traj", idx, t, p, float(start)))

    def set_stream_target(self, index: Sequence[int], q: Sequence[float], now: float) -> None:
        """See :meth:`JointCommandSource.set_stream_target`."""
        idx, qq = check_stream_target(self.n, index, q)
        self._owner._send(("stream", idx, qq, float(now)))

    def clear(self, hold_q: np.ndarray | None) -> None:
        """See :meth:`JointCommandSource.clear`."""
        self._owner._send(("clear", None if hold_q is None else np.asarray(hold_q, dtype=float)))


class DriverProcess:
    """Handle of a :class:`DriverLoop` running in a child process (see the module docstring).

    Args:
        spec: what to drive and how.
        on_sample: called (from a reader thread of this process) with every cycle's sample, or only
                the newest of those queued when the reader fell behind.
        log: ``f(level, message)`` for the child's log lines.
        python: interpreter of the child (default: this one).

    Nothing is started by the constructor; :meth:`start` spawns the child.
    """

    def __init__(
        self,
        spec: DriverSpec,
        *,
        on_sample: Callable[[CycleSample], None] | None = None,
        log: Callable[[int, str], None] | None = None,
        python: str | None = None,
    ) -> None:
        self.spec = spec
        self.config = spec.loop
        self.n = spec.n
        self._on_sample = on_sample
        self._log = log or (lambda level, msg: _LOG.log(level, "%s", msg))
        self._python = python or sys.executable
        self.commands = RemoteCommands(self, self.n, spec.loop.hold_on_stream_stop_s)
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._state = LoopState.CONNECTING
        self._reason = "starting"
        self._fault: Fault | None = None
        self._ids = itertools.count(1)
        self._pending: dict[int, tuple[threading.Event, list[Any]]] = {}
        self._conn: Connection | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None
        self._stopping = False
        self._started = threading.Event()
        self.samples_skipped = 0  #: samples not handed on: a newer one was already queued behind them

    # -- life cycle -------------------------------------------------------------------------------
    def start(self) -> DriverProcess:
        """Spawn the child and hand it the spec; returns self."""
        if self._proc is not None:
            return self
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        pkg_root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = os.pathsep.join(p for p in (pkg_root, env.get("PYTHONPATH", "")) if p)
        try:
            self._proc = subprocess.Popen(
                [self._python, "-m", "redarm_ros.can.driver_process", "--fd", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), env=env, stdin=subprocess.DEVNULL,
                preexec_fn=die_with_parent_preexec(),  # no real-time orphan if the node is killed
            )
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._send(("spec", self.spec))
        self._send(("stream_timeout", self.commands.stream_timeout_s))  # a change made before start()
        self._reader = threading.Thread(target=self._read, name="can-driver-process-reader", daemon=True)
        self._reader.start()
        self._started.set()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the child's loop (it closes the bus) and wait for it to exit; kill it if it does not."""
        self._stopping = True
        self._started.set()  # release requests waiting for a start that will not come
        proc = self._proc
        if proc is not None and proc.poll() is None:
            try:
                self._send(("stop",))
                proc.wait(timeout)
            except (OSError, subprocess.TimeoutExpired):
                proc.kill()
                proc.wait(5.0)
        # The child has exited: the reader sees the end of the socket; close it only afterwards.
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(2.0)
        if self._conn is not None:
            self._conn.close()
        with self._lock:
            self._state, self._reason = LoopState.STOPPED, "stopped"
        self._fail_pending("driver process stopped")

    @property
    def pid(self) -> int | None:
        """Process id of the child (None before :meth:`start`)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def alive(self) -> bool:
        """True while the child runs."""
        return self._proc is not None and self._proc.poll() is None

    # -- what the node uses ------------------------------------------------------------------------
    @property
    def state(self) -> LoopState:
        """The loop's state as last reported by the child."""
        with self._lock:
            return self._state

    @property
    def fault(self) -> Fault | None:
        """Why the loop is halted, as last reported."""
        with self._lock:
            return self._fault

    def accepting_commands(self) -> tuple[bool, str]:
        """Whether a new command would be followed now, and why not."""
        with self._lock:
            if self._state is LoopState.RUNNING:
                return True, ""
            return False, f"driver is {self._state.value} ({self._reason}); command ignored"

    def request(self, action: str, timeout: float = 60.0) -> tuple[bool, str]:
        """Run ``init``, ``halt``, ``recover`` or ``park`` in the child (see
        :meth:`DriverLoop.request`); returns (success, message)."""
        if action not in ACTIONS:
            return False, f"unknown action {action!r}"
        # A request made before the child runs (the node's start timer) waits for it, as the loop
        # makes a request made before the first connection wait for that.
        t0 = time.monotonic()
        if not self._started.wait(timeout):
            return False, f"{action}: the CAN cycle did not start within {timeout:.0f} s"
        timeout = max(0.0, timeout - (time.monotonic() - t0))
        reply = self._ask(("req", action, float(timeout)), timeout + 5.0)
        if reply is None:
            return False, f"{action} did not finish within {timeout:.0f} s"
        if isinstance(reply, _NoAnswer):
            return False, f"{action} failed: {reply.why}"
        ok, message = reply
        return bool(ok), str(message)

    def snapshot(self, timeout: float = 2.0) -> LoopSnapshot:
        """The child's status (a :class:`LoopSnapshot`); raises :class:`RedarmError` if it does not answer."""
        snap = self._ask(("snap",), timeout)
        if snap is None or isinstance(snap, _NoAnswer):
            why = snap.why if isinstance(snap, _NoAnswer) else f"no answer within {timeout} s"
            raise RedarmError(f"driver process status unavailable: {why}")
        self.commands.mode = snap.command_mode
        return snap

    def reset_measurements(self) -> None:
        """Start fresh timing and latency windows in the child."""
        self._send(("reset_meas",))

    # -- plumbing ------------------------------------------------------------------------------
    def _send(self, item: tuple[Any, ...]) -> None:
        conn = self._conn
        if conn is None or conn.closed:
            return
        with self._send_lock:
            try:
                conn.send(item)
            except OSError as exc:
                self._log(logging.ERROR, f"driver process unreachable: {exc}")

    def _ask(self, item: tuple[Any, ...], timeout: float) -> Any:
        if not self.alive:
            return _NoAnswer("driver process not running")
        rid = next(self._ids)
        done, box = threading.Event(), []
        with self._lock:
            self._pending[rid] = (done, box)
        self._send((item[0], rid, *item[1:]))
        done.wait(timeout)
        with self._lock:
            self._pending.pop(rid, None)
        return box[0] if box else None

    def _fail_pending(self, why: str) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
        for done, box in pending.values():
            box.append(_NoAnswer(why))
            done.set()

    def _deliver(self, msg: tuple[Any, ...]) -> None:
        if self._on_sample is None:
            return
        _, stamp, q, v, target = msg
        try:
            self._on_sample(CycleSample(stamp, q, v, target))
        except Exception as exc:  # publishing must never stop the reader
            self._log(logging.ERROR, f"on_sample failed: {exc!r}")

    def _read(self) -> None:
        # A reader that fell behind (a starved node process) hands on only the newest of the samples
        # queued in the socket: publishing each would make every one as old as the backlog (measured:
        # /joint_states 0.34-0.40 s stale on a loaded 2-core machine, and the controller re-planning
        # against an arm it saw where it had been). The skipped ones are counted.
        conn = self._conn
        assert conn is not None
        newest: tuple[Any, ...] | None = None
        try:
            while True:
                msg = conn.recv()
                kind = msg[0]
                if kind == "sample":
                    if newest is not None:
                        self.samples_skipped += 1
                    newest = msg
                elif kind == "state":
                    with self._lock:
                        self._state, self._reason, self._fault = msg[1], msg[2], msg[3]
                elif kind == "log":
                    self._log(msg[1], msg[2])
                elif kind == "answer":
                    with self._lock:
                        entry = self._pending.get(msg[1])
                    if entry is not None:
                        entry[1].append(msg[2])
                        entry[0].set()
                if newest is not None and not conn.poll(0):
                    self._deliver(newest)
                    newest = None
        except (EOFError, OSError, TypeError):  # TypeError: the connection was closed under us
            pass
        if not self._stopping:
            code = self._proc.wait(5.0) if self._proc is not None else None
            self._log(logging.ERROR, f"can_driver cycle process ended unexpectedly (exit code {code}); "
                      "the modules' watchdog halts the arm")
        with self._lock:
            self._state, self._reason = LoopState.STOPPED, "driver process ended"
        self._fail_pending("driver process ended")


# --------------------------------------------------------------------------------------------------
# Child side
# --------------------------------------------------------------------------------------------------


class _Child:
    """The child's main thread: applies the parent's messages to the loop; a sender thread answers."""

    def __init__(self, conn: Connection, spec: DriverSpec) -> None:
        self.conn = conn
        self.spec = spec
        self.out: queue.Queue[tuple[Any, ...] | None] = queue.Queue()
        self.samples_dropped = 0
        self._samples_waiting = 0
        self._wait_lock = threading.Lock()
        self._conn_lock = threading.Lock()  # one writer at a time on the socket
        # The same socket (a second descriptor) for the cycle thread's own sample writes, which must not
        # wait: sent with MSG_DONTWAIT, the socket itself stays blocking for the sender thread.
        self._direct = socket.socket(fileno=os.dup(conn.fileno()))
        self.sender = threading.Thread(target=self._send_loop, name="can-driver-sender", daemon=True)
        self.loop: DriverLoop | None = None

    def _send_loop(self) -> None:
        while True:
            item = self.out.get()
            if item is None:
                return
            try:
                with self._conn_lock:
                    self.conn.send(item)
            except OSError:
                return  # the parent is gone; the main thread sees EOF and stops the loop
            if item[0] == "sample":  # (counted out once written: a sample the cycle thread writes
                with self._wait_lock:  # itself never overtakes one queued before it)
                    self._samples_waiting -= 1

    def put(self, item: tuple[Any, ...]) -> None:
        self.out.put(item)

    def on_sample(self, s: CycleSample) -> None:
        item = ("sample", s.stamp, s.positions, s.velocities, s.target)
        # The cycle thread writes the sample itself when nothing waits for the sender thread and the
        # socket is free: waking that thread (and handing it the interpreter lock) for every sample cost
        # more than the write. The write never waits: a parent that stopped reading loses the sample
        # (counted), as it would beyond SAMPLE_QUEUE below.
        if not self._samples_waiting and self._conn_lock.acquire(blocking=False):
            try:
                self._send_now(item)
            finally:
                self._conn_lock.release()
            return
        # Never block the cycle on a slow parent: beyond SAMPLE_QUEUE waiting, drop and count.
        with self._wait_lock:
            if self._samples_waiting >= SAMPLE_QUEUE:
                self.samples_dropped += 1
                return
            self._samples_waiting += 1
        self.out.put(("sample", s.stamp, s.positions, s.velocities, s.target))

    def _send_now(self, item: tuple[Any, ...]) -> None:
        """Write ``item`` in the connection's framing (a length, then the pickle), without waiting."""
        payload = ForkingPickler.dumps(item)
        data = struct.pack("!i", len(payload)) + bytes(payload)
        try:
            sent = self._direct.send(data, socket.MSG_DONTWAIT)
        except BlockingIOError:
            self.samples_dropped += 1
            return
        except OSError:
            return  # the parent is gone; the main thread sees EOF and stops the loop
        if sent < len(data):  # (not seen: a write this small is queued whole or not at all)
            try:
                self._direct.sendall(data[sent:])
            except OSError:
                return

    def on_state(self, state: LoopState, reason: str, fault: Fault | None) -> None:
        self.out.put(("state", state, reason, fault))

    def log(self, level: int, message: str) -> None:
        self.out.put(("log", level, message))

    def run(self) -> int:
        # Priority first: every thread started afterwards inherits it. A helper thread at normal
        # priority could be preempted while holding the interpreter lock and stall the cycle.
        prio = realtime.raise_priority(self.spec.realtime_priority, who="can_driver cycle process")
        self.sender.start()
        self.log(logging.INFO if prio.realtime or self.spec.realtime_priority <= 0 else logging.WARNING,
                 prio.message)
        # The process already has its priority (threads inherit it): the loop only freezes the GC.
        cfg = replace(self.spec.loop, realtime_priority=0, quiet_gc=True)
        loop = self.loop = build_loop(replace(self.spec, loop=cfg), on_sample=self.on_sample,
                                      on_state=self.on_state, log=self.log)
        loop._priority = prio.message
        loop.start()
        try:
            while True:
                try:
                    msg = self.conn.recv()
                except (EOFError, OSError):
                    return 0  # the parent is gone: stop cycling (the watchdog halts the modules)
                if msg[0] == "stop":
                    return 0
                self._apply(msg)
        finally:
            loop.stop()
            self.out.put(None)
            self.sender.join(2.0)
            self._direct.close()

    def _apply(self, msg: tuple[Any, ...]) -> None:
        loop = self.loop
        assert loop is not None
        kind = msg[0]
        try:
            if kind == "traj":
                loop.commands.set_trajectory(msg[1], msg[2], msg[3], msg[4])
            elif kind == "stream":
                loop.commands.set_stream_target(msg[1], msg[2], msg[3])
            elif kind == "clear":
                loop.commands.clear(msg[1])
            elif kind == "stream_timeout":
                loop.commands.stream_timeout_s = msg[1]
            elif kind == "reset_meas":
                loop.reset_measurements()
            elif kind == "snap":
                self.put(("answer", msg[1], loop.snapshot()))
            elif kind == "req":
                # init and park may take seconds: answer from a thread so commands keep flowing meanwhile.
                rid, action, timeout = msg[1], msg[2], msg[3]
                threading.Thread(target=lambda: self.put(("answer", rid, loop.request(action, timeout))),
                                 name=f"can-driver-{action}", daemon=True).start()
        except RedarmError as exc:  # validated in the parent already; keep serving
            self.log(logging.WARNING, f"command refused: {exc}")


def main(argv: Sequence[str] | None = None) -> int:
    """Child entry point: ``python -m redarm_ros.can.driver_process --fd N``."""
    ap = argparse.ArgumentParser(prog="redarm_ros.can.driver_process")
    ap.add_argument("--fd", type=int, required=True, help="socket (pair) to the parent")
    args = ap.parse_args(argv)
    # The parent stops us. A terminal's Ctrl-C reaches both, and so does a SIGTERM to the process group
    # (systemd, a supervisor): ended by it before the parent, we made the parent's clean stop look
    # like a crash ("cycle process ended unexpectedly (exit code -15)", "Broken pipe").
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    # The cycle thread gets the interpreter back within 0.5 ms when a helper thread (status, commands)
    # runs Python, not the default 5 ms.
    sys.setswitchinterval(5e-4)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s can_driver cycle: %(message)s")
    conn = Connection(args.fd)
    try:
        spec = conn.recv()
    except (EOFError, OSError):
        return 1
    if not isinstance(spec, tuple) or spec[0] != "spec" or not isinstance(spec[1], DriverSpec):
        _LOG.error("expected a DriverSpec from the parent, got %r", spec)
        return 2
    t0 = time.monotonic()
    code = _Child(conn, spec[1]).run()
    _LOG.debug("driver process done after %.1f s", time.monotonic() - t0)
    return code


if __name__ == "__main__":
    # Run the importable module's main, not this __main__ copy: the pickled spec names the
    # classes of redarm_ros.can.driver_process.
    from redarm_ros.can.driver_process import main as _main

    sys.exit(_main())
