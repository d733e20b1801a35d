"""``redarm-sim``: the hardware stand-in process (pybullet arm + one emulated PowerCube module per joint).

No ROS here: to the rest of the system this process *is* the hardware. It

* has a :class:`~redarm_ros.sim.plant.PybulletPlant` stepped in real time at ``--rate`` Hz by a
  :class:`~redarm_ros.sim.physics_process.RealTimeStepper` (default 1000; late steps are counted as
  overruns and caught up in bursts, a large backlog is dropped and counted as a resync), in a process
  of its own (:class:`~redarm_ros.sim.physics_process.PhysicsProcess`, so that no reply ever waits
  for the physics to get the interpreter lock back; ``--physics thread`` steps it in a thread here),
* emulates modules ``1..n`` (``--first-id`` shifts them) with :mod:`redarm_ros.can.module_emulator`
  on the CAN bus chosen by python-can configuration (``--can-interface``/``--can-channel``/
  ``--can-config-file`` passed through, else ``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_CONFIG``),
  answering each request from a dedicated bus thread as soon as it arrives,
* survives malformed frames (counted), a lost bus (reopened with backoff), and handler bugs (counted),
* writes a JSON status (joint positions, setpoints, tool pose from the pybullet link state, module
  states, counters) atomically to ``--status-file`` at ``--status-rate`` Hz,
* renders PNG snapshots headless into ``--snapshot-dir`` (``start.png`` after start-up, ``final.png``
  on a clean exit, and on request),
* offers fault injection for tests: ``--drop-replies FRACTION`` (seeded by ``--seed``),
  ``--delay-replies MS``, ``--silence-module ID`` (repeatable; silent modules ignore every frame),
  ``--die-after S`` (SIGKILLs itself: a crash, no clean-up), and at run time ``SIGUSR1`` (toggle
  the silence of the ``--silence-module`` set), ``SIGUSR2`` (snapshot) and ``--control-file``,
* with ``--control-port``, answers a test's requests (state now, faults in force, a module
  power-cycled or in ERROR) on 127.0.0.1 (:mod:`redarm_ros.sim.control_channel`).

See ``docs/sim.md`` for the status schema and the control file format. Exit codes: 0 clean stop
(SIGINT/SIGTERM), 2 bad arguments, 3 bus could not be opened (at once for a configuration that can
never work, else after ``--bus-wait`` seconds of retries), 4 the physics process ended, -9 (killed)
after ``--die-after``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import gc
import heapq
import json
import logging
import math
import os
import random
import signal
import sys
import threading
import time
from collections.abc import Callable, Collection, Sequence
from concurrent.futures import Future
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can

from redarm_ros.can import protocol as pc
from redarm_ros.can import realtime
from redarm_ros.can.module_emulator import wire_time
from redarm_ros.errors import BusError, RedarmError
from redarm_ros.sim.physics_process import PhysicsProcess, RealTimeStepper, build_plant
from redarm_ros.sim.plant import PybulletPlant

_LOG = logging.getLogger("redarm_ros.sim.hardware")

READY_LINE = "REDARM_SIM_READY"
CONTROL_POLL_S = 0.05
OUTBOX_MAX = 64  # replies queued while requests keep coming are sent once this many wait
SWITCH_INTERVAL_S = 5e-4
OVERRUN_REPORT_S = 5.0  # log late steps at most this often
DEFAULT_REALTIME_PRIORITY = 50
# How long a frame may have been under way (sender -> bus server -> this process) before it was
# readable here; bounds how old a frame's own stamp may make it look (s).
WIRE_TRANSIT_ALLOWANCE_S = 0.02
#: A request read this long (s) after it was sent, or answered this long after it was read, is logged
#: with its wall time (for tracing a late reply to where it waited; late physics: LAG_EVENT_S).
SLOW_EVENT_S = 0.005
SLOW_LOGS_PER_S = 20  # at most this many such lines per second
ENV_PREFIX = "REDARM_SIM_"
EXIT_BAD_ARGS = 2
EXIT_NO_BUS = 3
EXIT_PHYSICS_LOST = 4
#: How long (s) the simulator waits for its bus by default: a launch file starts the bus server beside it.
BUS_WAIT_S = 20.0


# --------------------------------------------------------------------------------------------------
# Fault injection and counters
# --------------------------------------------------------------------------------------------------


@dataclass
class Faults:
    """Fault injection settings (mutable at run time; read by the bus thread).

    ``drop_replies``: probability in [0, 1] that a reply is not sent; ``delay_replies_ms``: added
    latency of every reply; ``silenced``: module ids that ignore every frame (no state change, no
    reply), like modules cut off the bus; ``toggle_set``: the ids SIGUSR1 toggles.
    """

    drop_replies: float = 0.0
    delay_replies_ms: float = 0.0
    silenced: set[int] = field(default_factory=set)
    toggle_set: set[int] = field(default_factory=set)
    seed: int = 0

    def validate(self) -> None:
        """Raise ValueError on an out-of-range setting."""
        if not (0.0 <= self.drop_replies <= 1.0):
            raise ValueError(f"drop fraction must be in [0, 1], got {self.drop_replies}")
        if not (0.0 <= self.delay_replies_ms <= 60_000.0) or not math.isfinite(self.delay_replies_ms):
            raise ValueError(f"reply delay must be in [0, 60000] ms, got {self.delay_replies_ms}")


@dataclass
class Counters:
    """What happened on the bus and in the loop (all monotonic counts since start)."""

    frames_rx: int = 0
    requests: int = 0  # frames addressed to our modules (incl. broadcasts)
    replies_tx: int = 0
    malformed: int = 0
    foreign: int = 0  # well-formed frames not for us (other ids, replies of other devices)
    dropped_replies: int = 0
    delayed_replies: int = 0
    silenced_rx: int = 0
    handler_errors: int = 0
    send_errors: int = 0
    bus_lost: int = 0
    bus_reopened: int = 0
    overruns: int = 0
    resyncs: int = 0
    max_lag_ms: float = 0.0
    max_wire_gap_ms: float = 0.0  # longest silence between two frames for our modules, on the wire
    reply_latency_max_ms: float = 0.0
    reply_latency_sum_ms: float = 0.0
    # The garbage collector holds the interpreter lock: while it runs, no reply goes out. The longest
    # collection in the collecting thread's CPU time (time it was preempted is scheduling: max_lag_ms).
    gc_collections: int = 0
    gc_max_pause_ms: float = 0.0
    snapshots: int = 0
    control_errors: int = 0
    slow_reads: int = 0  # requests read SLOW_EVENT_S or more after their sender's stamp
    slow_replies: int = 0  # replies sent SLOW_EVENT_S or more after their request was read
    lag_spikes: int = 0  # physics wake-ups LAG_EVENT_S or more late


# --------------------------------------------------------------------------------------------------
# The process core
# --------------------------------------------------------------------------------------------------


class HardwareSim:
    """The simulated arm plus its emulated modules on ``bus``.

    ``bus`` is any python-can bus (a :class:`~redarm_ros.can.bus.ReconnectingBus` in the process, a
    ``virtual`` bus in tests); ``plant`` the pybullet plant, stepped by ``run()`` in the calling
    thread, or a :class:`~redarm_ros.sim.physics_process.PhysicsProcess`, which steps itself;
    ``module_ids`` one id per joint. ``run()`` blocks until :meth:`request_stop`; the bus is served
    by a thread.
    ``freeze_gc``: once started, freeze the garbage collector's view of every object made so far
    (:func:`redarm_ros.can.realtime.freeze_gc`; undone when ``run()`` returns), so that no full
    collection of the start-up objects holds up a reply; the process does this, a test need not.
    ``slice_ms``: time slice the bus thread asks for (:func:`redarm_ros.can.realtime.request_slice`;
    0: the kernel's default).
    """

    def __init__(
        self,
        plant: PybulletPlant | PhysicsProcess,
        bus: can.BusABC,
        *,
        module_ids: Sequence[int] | None = None,
        rate_hz: float = 1000.0,
        faults: Faults | None = None,
        status_file: str | os.PathLike[str] | None = None,
        status_rate_hz: float = 20.0,
        snapshot_dir: str | os.PathLike[str] | None = None,
        snapshot_size: tuple[int, int] = (640, 480),
        control_file: str | os.PathLike[str] | None = None,
        die_after_s: float | None = None,
        emulator_factory: Callable[..., Any] | None = None,
        freeze_gc: bool = False,
        slice_ms: float = 0.0,
    ) -> None:
        self.plant = plant
        self.bus = bus
        self.n = plant.n
        self.module_ids = list(module_ids) if module_ids is not None else list(range(1, self.n + 1))
        if len(self.module_ids) != self.n or len(set(self.module_ids)) != self.n:
            raise ValueError(f"need {self.n} distinct module ids, got {self.module_ids}")
        self.rate_hz = float(rate_hz)
        # paces the plant in run() unless it steps itself (a PhysicsProcess)
        self.stepper = RealTimeStepper(plant, self.rate_hz, on_lag=self._on_lag)
        self.moving_batch = self.stepper.moving_batch  # steps per wake-up while moving
        self.faults = faults or Faults()
        self.faults.validate()
        self.status_file = Path(status_file) if status_file else None
        if self.status_file is not None:
            self.status_file.parent.mkdir(parents=True, exist_ok=True)
        self.status_period = 1.0 / status_rate_hz if status_rate_hz > 0 else math.inf
        self.snapshot_dir = Path(snapshot_dir) if snapshot_dir else None
        self.snapshot_size = snapshot_size
        self.control_file = Path(control_file) if control_file else None
        self.die_after_s = die_after_s
        self.freeze_gc = freeze_gc
        self.slice_ms = slice_ms
        self._gc_start = 0.0
        self.counters = Counters()
        self.snapshots: list[str] = []
        self._rng = random.Random(self.faults.seed)
        self._stop = threading.Event()
        self._wake = threading.Event()  # work for run()'s thread (stop, a call)
        self._snapshot_requests: list[str | None] = []
        # work for the physics thread from other threads (the control channel's status reads)
        self._physics_calls: collections.deque[tuple[Callable[[], Any], Future[Any]]] = collections.deque()
        # faults and snapshot requests between threads; reentrant because signal handlers (which run
        # in the main thread, possibly inside a locked block) take it too
        self._lock = threading.RLock()
        self._pending: list[tuple[float, int, can.Message, float]] = []  # delayed: (due, seq, msg, t_rx)
        self._seq = 0
        self._outbox: list[tuple[can.Message, float]] = []  # replies not sent yet: (msg, t_rx)
        self._decoder = pc.FrameDecoder()
        self._last_wire: float | None = None
        self._last_empty = time.monotonic()  # the bus thread last found nothing to read
        self._known_empty = self._last_empty  # the start of the receive that found nothing to read
        self._control_sig: tuple[int, int] | None = None
        self._start = time.monotonic()
        self.physics_lost = False  # the physics process ended while serving
        self._slow_logs = realtime.PerSecondLimit(SLOW_LOGS_PER_S)
        self._slow_stamp = 0.0  # sender stamp of the last slow read logged
        # the bus thread's scheduling (opened by that thread) and its reading at the last empty receive
        self._sched = realtime.ThreadSchedstat(None)
        self._sched_empty = (0.0, 0.0)
        self.emulator = (emulator_factory or _default_emulator)(plant, self.module_ids)
        self._bus_thread = threading.Thread(target=self._bus_loop, name="sim-bus", daemon=True)
        self._status_cond = threading.Condition()
        self._status_mailbox: dict[str, Any] | None = None
        self._status_thread = threading.Thread(target=self._status_writer, name="sim-status", daemon=True)

    # -- control from other threads / signal handlers -------------------------------------------------
    def request_stop(self) -> None:
        """Ask :meth:`run` to return (safe from signal handlers and other threads)."""
        self._stop.set()
        self._wake.set()

    def request_snapshot(self, name: str | None = None) -> None:
        """Ask the physics thread to write a snapshot (``name``.png, or a numbered one)."""
        with self._lock:
            self._snapshot_requests.append(name)

    def call_in_physics(self, fn: Callable[[], Any]) -> Future[Any]:
        """Run ``fn`` on the physics thread between two steps (every pybullet call belongs to that
        thread); the future holds its result. Cancelled if the simulator stops first."""
        fut: Future[Any] = Future()
        self._physics_calls.append((fn, fut))
        self._wake.set()  # (a run() that does not step wakes only when there is something to do)
        if self._stop.is_set():
            self._run_physics_calls(cancel=True)
        return fut

    def _run_physics_calls(self, cancel: bool = False) -> None:
        while self._physics_calls:
            fn, fut = self._physics_calls.popleft()
            if cancel:
                fut.cancel()
            elif fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn())
                except Exception as exc:  # noqa: BLE001 - handed to the caller
                    fut.set_exception(exc)

    def fault_settings(self) -> dict[str, Any]:
        """The fault injection in force: ``drop_replies``, ``delay_replies_ms``, ``silenced``,
        ``toggle_set`` (the status's ``faults``)."""
        with self._lock:
            return {
                "drop_replies": self.faults.drop_replies,
                "delay_replies_ms": self.faults.delay_replies_ms,
                "silenced": sorted(self.faults.silenced),
                "toggle_set": sorted(self.faults.toggle_set),
            }

    def toggle_silence(self) -> None:
        """Silence the ``toggle_set`` modules if any of them speaks, else let them all speak again."""
        with self._lock:
            ts = self.faults.toggle_set
            if ts & self.faults.silenced == ts:
                self.faults.silenced -= ts
            else:
                self.faults.silenced |= ts
            _LOG.info("silenced modules now %s", sorted(self.faults.silenced))

    @property
    def realtime(self) -> bool:
        """This thread steps the plant under SCHED_FIFO (set by main(); the spin guard applies)."""
        return self.stepper.realtime

    @realtime.setter
    def realtime(self, value: bool) -> None:
        self.stepper.realtime = value

    def _on_lag(self, ms: float, now: float) -> None:
        self._note_slow("physics wake-up late", ms, now)

    def _note_slow(self, what: str, ms: float, at_mono: float) -> None:
        """Log a slow event (wall time of ``at_mono``), at most :data:`SLOW_LOGS_PER_S` a second."""
        wall = time.time() - (time.monotonic() - at_mono)
        if self._slow_logs.allow(wall):
            _LOG.warning("slow: %s %.1f ms at wall time %.4f", what, ms, wall)

    # -- bus side -------------------------------------------------------------------------------------
    def _send(self, msg: can.Message, t_rx: float) -> None:
        """Queue a reply; :meth:`_flush_out` sends the queue once no request waits to be read (a cycle's
        requests come in one burst: their replies go out in one write)."""
        self._outbox.append((msg, t_rx))
        if len(self._outbox) >= OUTBOX_MAX:
            self._flush_out()

    def _flush_out(self) -> None:
        flush_commands = getattr(self.plant, "flush", None)  # a PhysicsProcess: this burst's commands
        if flush_commands is not None:
            flush_commands()
        out = self._outbox
        if not out:
            return
        msgs = [m for m, _ in out]
        batch = getattr(self.bus, "send_many", None)
        c = self.counters
        try:
            if batch is not None:
                batch(msgs)
            else:
                for m in msgs:
                    self.bus.send(m)
        except (BusError, can.CanError, OSError) as exc:
            c.send_errors += len(out)
            out.clear()
            _LOG.warning("replies not sent: %r", exc)
            return
        now = time.monotonic()
        c.replies_tx += len(out)
        slowest = 0.0
        for _, t_rx in out:
            lat = (now - t_rx) * 1e3
            c.reply_latency_sum_ms += lat
            slowest = max(slowest, lat)
            if lat > c.reply_latency_max_ms:
                c.reply_latency_max_ms = lat
        if slowest >= SLOW_EVENT_S * 1e3:
            c.slow_replies += 1
            self._note_slow("request read to reply sent", slowest, now)
        out.clear()

    def _flush_pending(self, now: float) -> None:
        while self._pending and self._pending[0][0] <= now:
            _, _, msg, t_rx = heapq.heappop(self._pending)
            self._send(msg, t_rx)

    def handle_frame(self, msg: can.Message, t_rx: float) -> None:
        """Process one received frame: decode, route to the emulator, apply faults, send replies."""
        c = self.counters
        c.frames_rx += 1
        frame = self._decoder.decode(msg)
        c.malformed = self._decoder.malformed
        if frame is None:
            return
        target = _target_of(frame)
        if target is None or (target != 0 and target not in self.emulator.ids):
            c.foreign += 1
            return
        silenced, drop, delay = self._faults_now()
        if target != 0 and target in silenced:
            c.silenced_rx += 1
            return
        c.requests += 1
        sent = wire_time(msg)
        if t_rx - sent >= SLOW_EVENT_S and msg.timestamp != self._slow_stamp:  # once per burst
            self._slow_stamp = msg.timestamp
            c.slow_reads += 1
            # Where this thread spent the time since it last found nothing to read: running, or
            # waiting for a CPU; the rest it slept (in the receive, or for the interpreter lock).
            now_ran, now_queued = self._sched.read()
            ran, queued = now_ran - self._sched_empty[0], now_queued - self._sched_empty[1]
            self._note_slow(f"request sent to read (bus thread since: ran {ran:.1f} ms, run queue "
                            f"{queued:.1f} ms)", (t_rx - sent) * 1e3, sent)
        # When the frame was on the bus, by its stamp; but never earlier than the last moment this
        # thread saw the socket empty (less a transit allowance): a frame cannot have waited longer
        # than that, so a wall-clock step cannot make it look old.
        t_wire = max(sent, self._last_empty - WIRE_TRANSIT_ALLOWANCE_S)
        if self._last_wire is not None and t_wire - self._last_wire > c.max_wire_gap_ms * 1e-3:
            c.max_wire_gap_ms = (t_wire - self._last_wire) * 1e3
        self._last_wire = t_wire
        try:
            # The watchdog judges the host by when the frame was on the bus, not by when this
            # process got to read it (see module_emulator.wire_time).
            replies = self.emulator.handle(frame, silenced, t_wire)
        except Exception:  # noqa: BLE001 - a bug in one request must not take the hardware down
            c.handler_errors += 1
            _LOG.exception("error handling %s", msg)
            return
        self._emit(replies, t_rx, drop, delay)

    def _faults_now(self) -> tuple[Collection[int], float, float]:
        """The silenced ids (a copy: another thread may change them), drop fraction and reply delay in
        force; without the lock and the copy while no fault is set (the settings are only ever
        changed under the lock, by one assignment or one in-place set operation)."""
        f = self.faults
        if not f.silenced and f.drop_replies == 0.0 and f.delay_replies_ms == 0.0:
            return _NO_IDS, 0.0, 0.0
        with self._lock:
            return set(self.faults.silenced), self.faults.drop_replies, self.faults.delay_replies_ms

    def _emit(self, frames: Sequence[can.Message], t_rx: float, drop: float, delay: float) -> None:
        """Send frames now or later, or drop them, as the faults say."""
        if drop == 0.0 and delay == 0.0:
            for reply in frames:
                self._send(reply, t_rx)
            return
        c = self.counters
        for reply in frames:
            if drop > 0.0 and self._rng.random() < drop:
                c.dropped_replies += 1
                continue
            if delay > 0.0:
                c.delayed_replies += 1
                self._seq += 1
                heapq.heappush(self._pending, (t_rx + delay / 1e3, self._seq, reply, t_rx))
                continue
            self._send(reply, t_rx)

    def _tick(self, now: float) -> None:
        silenced, drop, delay = self._faults_now()
        # The watchdogs judge time as of when the queue was known empty, less the bus server's transit:
        # had this thread waited for the CPU between that receive and now, the frames sent meanwhile
        # are not read yet, and the host must not be blamed for them.
        behind = time.monotonic() - self._known_empty + WIRE_TRANSIT_ALLOWANCE_S
        try:
            frames = self.emulator.tick(silenced, behind)
        except Exception:  # noqa: BLE001 - as in handle_frame
            self.counters.handler_errors += 1
            _LOG.exception("error in module tick")
            return
        if frames:
            self._emit(frames, now, drop, delay)

    def _bus_loop(self) -> None:
        realtime.name_thread("sim-bus")
        if self.slice_ms > 0:  # woken by each request: a short slice gets it a CPU sooner
            got = realtime.request_slice(self.slice_ms, who="redarm-sim bus thread")
            (_LOG.warning if got.refused else _LOG.info)("%s", got.message)
        self._sched = realtime.ThreadSchedstat()
        self._sched_empty = self._sched.read()
        try:
            self._serve_bus()
        finally:
            self._sched.close()

    def _serve_bus(self) -> None:
        backoff = 0.05
        backlog = False
        while not self._stop.is_set():
            now = time.monotonic()
            if self._pending:
                self._flush_pending(now)
            if not backlog:
                # Tick only once the queue is drained: after this thread waited for the CPU, frames
                # that already arrived must refresh the modules' watchdogs before they are checked.
                self._tick(now)
                self._flush_out()
            timeout = 0.0 if backlog else 0.01
            if self._pending:
                timeout = max(0.0, min(timeout, self._pending[0][0] - now))
            t_check = time.monotonic()
            try:
                msg = self.bus.recv(timeout)
            except (BusError, can.CanError, OSError) as exc:
                self._on_bus_lost(exc, backoff)
                backoff = min(2.0, backoff * 2)
                continue
            backoff = 0.05
            backlog = msg is not None
            if msg is not None:
                self.handle_frame(msg, time.monotonic())
            else:
                self._last_empty = time.monotonic()
                self._known_empty = t_check
                self._sched_empty = self._sched.read()

    def _on_bus_lost(self, exc: BaseException, delay: float) -> None:
        self.counters.bus_lost += 1
        _LOG.warning("CAN bus error: %r; reopening in %.2f s", exc, delay)
        self._pending.clear()  # replies to a dead connection are stale
        self._outbox.clear()
        if self._stop.wait(delay):
            return
        reopen = getattr(self.bus, "reopen", None)
        if reopen is None:
            return
        try:
            reopen()
            self.counters.bus_reopened += 1
        except (RedarmError, can.CanError, OSError) as exc2:
            _LOG.info("reopen failed: %s", exc2)

    # -- physics side ---------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """The machine-readable status (see docs/sim.md); call from the physics thread."""
        p = self.plant
        q, dq, q_sp, pos, quat = p.motion_state()
        faults = self.fault_settings()
        self._sync_pacing()
        counters = asdict(self.counters)
        n_rep = max(1, counters["replies_tx"])
        counters["reply_latency_mean_ms"] = counters.pop("reply_latency_sum_ms") / n_rep
        return {
            "pid": os.getpid(),
            "arm": p.arm.name,
            "n": self.n,
            "module_ids": self.module_ids,
            "joint_names": list(p.arm.joint_names),
            "running": not self._stop.is_set(),
            "wall_time": time.time(),
            "uptime_s": time.monotonic() - self._start,
            "sim_time_s": p.sim_time,
            "steps": p.steps,
            "rate_hz": self.rate_hz,
            "q": q.tolist(),
            "dq": dq.tolist(),
            "q_setpoint": q_sp.tolist(),
            "tool": {"position": pos.tolist(), "quaternion_xyzw": quat.tolist()},
            "modules": self.emulator.describe(epoch=self._start),  # times on the uptime_s scale
            "faults": faults,
            "counters": counters,
            "snapshots": list(self.snapshots),
        }

    def _sync_pacing(self) -> None:
        """Copy how well the physics keeps real time into the counters."""
        steps_itself = getattr(self.plant, "steps_itself", False)
        pacing = self.plant.pacing() if steps_itself else self.stepper.counters  # type: ignore[union-attr]
        for key, value in asdict(pacing).items():
            setattr(self.counters, key, value)

    def write_status(self) -> None:
        """Write :meth:`status` to the status file atomically (temp file + rename), now."""
        if self.status_file is not None:
            self._write_status_file(self.status())

    def _write_status_file(self, status: dict[str, Any]) -> None:
        assert self.status_file is not None
        tmp = self.status_file.with_name(f".{self.status_file.name}.{os.getpid()}.tmp")
        text = json.dumps(status)  # the C encoder: json.dump's chunked one allocates 6x more (gc runs)
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, self.status_file)

    def _post_status(self) -> None:
        """Hand the current status to the writer thread (the physics thread never waits for a disk)."""
        if self.status_file is None:
            return
        with self._status_cond:
            self._status_mailbox = self.status()  # the latest wins
            self._status_cond.notify()

    def _status_writer(self) -> None:
        realtime.name_thread("sim-status")
        while True:
            with self._status_cond:
                while self._status_mailbox is None and not self._stop.is_set():
                    self._status_cond.wait(0.5)
                status, self._status_mailbox = self._status_mailbox, None
            if status is None:
                return  # stopping; run() writes the final status itself
            try:
                self._write_status_file(status)
            except OSError as exc:
                _LOG.warning("status file not written: %s", exc)

    def snapshot(self, name: str | None = None) -> str | None:
        """Render a PNG into the snapshot dir now (physics thread); returns its path."""
        if self.snapshot_dir is None:
            _LOG.warning("snapshot requested but no --snapshot-dir given")
            return None
        self.snapshot_dir.mkdir(parents=True, exist_ok=True)
        stem = name or f"snapshot_{self.counters.snapshots:04d}"
        stem = "".join(ch for ch in stem if ch.isalnum() or ch in "-_.") or "snapshot"
        path = self.snapshot_dir / (stem if stem.endswith(".png") else f"{stem}.png")
        w, h = self.snapshot_size
        self.plant.snapshot_png(path, w, h)
        self.counters.snapshots += 1
        self.snapshots.append(str(path))
        return str(path)

    def _poll_control(self) -> None:
        f = self.control_file
        if f is None:
            return
        try:
            st = f.stat()
        except FileNotFoundError:
            return
        sig = (st.st_mtime_ns, st.st_size)
        if sig == self._control_sig:
            return
        self._control_sig = sig
        try:
            data = json.loads(f.read_text(encoding="utf-8") or "{}")
            self.apply_control(data)
        except (OSError, ValueError, TypeError) as exc:
            self.counters.control_errors += 1
            _LOG.warning("control file %s ignored: %s", f, exc)

    def apply_control(self, data: dict[str, Any]) -> None:
        """Apply a control mapping: ``silence`` (list of ids), ``drop_replies``, ``delay_replies_ms``,
        ``snapshot`` (name), ``stop`` (true). Raises ValueError/TypeError on bad content."""
        if not isinstance(data, dict):
            raise TypeError("control file must hold a JSON object")
        unknown = set(data) - {"silence", "drop_replies", "delay_replies_ms", "snapshot", "stop"}
        if unknown:
            raise ValueError(f"unknown control keys {sorted(unknown)}")
        with self._lock:
            new = Faults(
                drop_replies=float(data.get("drop_replies", self.faults.drop_replies)),
                delay_replies_ms=float(data.get("delay_replies_ms", self.faults.delay_replies_ms)),
                silenced={int(i) for i in data.get("silence", self.faults.silenced)},
                toggle_set=self.faults.toggle_set,
                seed=self.faults.seed,
            )
            new.validate()
            self.faults = new
        if data.get("snapshot"):
            self.request_snapshot(str(data["snapshot"]))
        if data.get("stop"):
            self.request_stop()
        _LOG.info("control applied: %s", data)

    def _on_gc(self, phase: str, _info: dict[str, int]) -> None:
        # Runs in whichever thread triggered the collection, holding the interpreter lock.
        if phase == "start":
            self._gc_start = time.thread_time()
            return
        c = self.counters
        c.gc_collections += 1
        pause = (time.thread_time() - self._gc_start) * 1e3
        if pause > c.gc_max_pause_ms:
            c.gc_max_pause_ms = pause

    def run(self, on_ready: Callable[[], None] | None = None) -> None:
        """Serve the bus and step physics in real time (or watch the physics process step it) until
        :meth:`request_stop`."""
        self._bus_thread.start()
        self._status_thread.start()
        c = self.counters
        steps_itself = getattr(self.plant, "steps_itself", False)
        if self.snapshot_dir is not None:
            self.snapshot("start")
        self.write_status()
        if self.freeze_gc:
            realtime.freeze_gc()
        gc.callbacks.append(self._on_gc)  # the pauses while serving, not the start-up collection
        if on_ready is not None:
            on_ready()
        stepper = self.stepper
        stepper.start()
        t0 = time.monotonic()
        next_status = t0
        next_control = t0
        next_report, reported = t0 + OVERRUN_REPORT_S, 0
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if not steps_itself:
                    stepper.advance(now)
                elif not self.plant.alive():  # type: ignore[union-attr]
                    _LOG.error("the physics process ended unexpectedly: stopping")
                    self.physics_lost = True
                    break
                if self._physics_calls:
                    self._run_physics_calls()
                if self.die_after_s is not None and now - self._start >= self.die_after_s:
                    _LOG.warning("--die-after %.3f s reached: crashing on purpose", self.die_after_s)
                    os.kill(os.getpid(), signal.SIGKILL)
                if now >= next_control:
                    next_control = now + CONTROL_POLL_S
                    self._poll_control()
                    with self._lock:
                        reqs, self._snapshot_requests = self._snapshot_requests, []
                    for name in reqs:
                        self.snapshot(name)
                    if reqs:  # rendering took a while: neither overruns nor a spinning real-time loop
                        stepper.rebase()
                if now >= next_status:
                    next_status = now + self.status_period
                    self._post_status()
                if now >= next_report:
                    next_report = now + OVERRUN_REPORT_S
                    self._sync_pacing()
                    if c.overruns > reported:
                        _LOG.warning(
                            "%d late physics steps in the last %.0f s (max lag so far %.2f ms, %d resyncs)",
                            c.overruns - reported, OVERRUN_REPORT_S, c.max_lag_ms, c.resyncs,
                        )  # fmt: skip
                        reported = c.overruns
                if steps_itself:  # nothing to step: sleep until the next chore, or work arrives
                    due = min(next_control, next_status, next_report)
                    if self.die_after_s is not None:
                        due = min(due, self._start + self.die_after_s)
                    self._wake.wait(max(0.0, due - time.monotonic()))
                    self._wake.clear()
                else:
                    stepper.sleep()
        finally:
            self._stop.set()
            if self.freeze_gc:
                realtime.restore_gc()
            with contextlib.suppress(ValueError):
                gc.callbacks.remove(self._on_gc)
            self._run_physics_calls(cancel=True)
            self._bus_thread.join(timeout=2.0)
            with self._status_cond:
                self._status_cond.notify()
            self._status_thread.join(timeout=2.0)
            if self.snapshot_dir is not None:
                try:
                    self.snapshot("final")
                except Exception:  # noqa: BLE001 - never block shutdown on a picture
                    _LOG.exception("final snapshot failed")
            self.write_status()


_NO_IDS: frozenset[int] = frozenset()


def _target_of(frame: Any) -> int | None:
    """Module id a request is for, 0 for a broadcast, None for anything not a request."""
    if isinstance(frame, pc.MODULE_REQUEST_TYPES):
        return int(frame.module_id)
    if isinstance(frame, pc.Broadcast):
        return 0
    return None


def _default_emulator(plant: PybulletPlant | PhysicsProcess, module_ids: Sequence[int]) -> Any:
    from redarm_ros.sim.emulation import PlantModules

    return PlantModules(plant, module_ids)


# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def _floats(text: str) -> list[float]:
    return [float(t) for t in text.replace(",", " ").split()]


def _ids(values: Sequence[str]) -> set[int]:
    out: set[int] = set()
    for v in values:
        out |= {int(t) for t in str(v).replace(",", " ").split()}
    return out


def build_parser() -> argparse.ArgumentParser:
    """The ``redarm-sim`` argument parser (every fault flag also reads ``REDARM_SIM_<FLAG>``)."""
    env = os.environ.get
    ap = argparse.ArgumentParser(
        prog="redarm-sim",
        description="pybullet arm answering as PowerCube modules on the CAN bus (no ROS).",
    )
    ap.add_argument("--arm", default=env(ENV_PREFIX + "ARM", "pa10"), help="arm model name or YAML path")
    ap.add_argument("--urdf", default="", help="simulate the arm of this URDF file instead of --arm (the "
                    "chain --base-link -> --tip-link; its links drawn as generated cylinders and spheres)")
    ap.add_argument("--base-link", default="", help="the URDF arm's base link")
    ap.add_argument("--tip-link", default="", help="the URDF arm's tip link")
    ap.add_argument("--gui", action="store_true", help="pybullet GUI (needs a display)")
    ap.add_argument("--rate", type=float, default=1000.0, help="physics rate in Hz (default 1000)")
    ap.add_argument("--initial-q", nargs="+", default=None, help="initial joint positions (rad)")
    ap.add_argument("--start", choices=("zero", "park"), default=None,
                    help="initial posture: zero (all joints 0, the default) or park (the arm's park "
                    "posture, park: in its YAML); not with --initial-q")
    ap.add_argument("--first-id", type=int, default=1, help="module id of joint 1 (default 1)")
    ap.add_argument("--scene", default=None, help="scene name (config/scenes) or YAML path to show")
    ap.add_argument("--status-file", default=env(ENV_PREFIX + "STATUS_FILE"), help="JSON status path")
    ap.add_argument("--status-rate", type=float, default=20.0, help="status writes per second")
    ap.add_argument("--snapshot-dir", default=env(ENV_PREFIX + "SNAPSHOT_DIR"), help="PNG directory")
    ap.add_argument("--snapshot-size", default="640x480", help="snapshot WIDTHxHEIGHT")
    ap.add_argument("--control-file", default=env(ENV_PREFIX + "CONTROL_FILE"), help="JSON control file")
    ap.add_argument("--control-port", type=int, default=None, metavar="PORT",
                    help="serve the control channel (redarm_ros.sim.control_channel) on 127.0.0.1:PORT "
                    "(0: an ephemeral port, named in the ready line as control=127.0.0.1:PORT)")
    g = ap.add_argument_group("CAN bus (python-can configuration, passed through)")
    g.add_argument("--can-interface", default=None, help="python-can interface (else CAN_INTERFACE)")
    g.add_argument("--can-channel", default=None, help="python-can channel (else CAN_CHANNEL)")
    g.add_argument("--can-config-file", default=None, help="python-can config file")
    g.add_argument("--can-bitrate", type=int, default=None, help="bitrate (interfaces that take one)")
    g.add_argument("--bus-wait", type=float, default=float(env(ENV_PREFIX + "BUS_WAIT") or BUS_WAIT_S),
                   metavar="S", help="wait up to S seconds for a bus that is not there yet (a bus server "
                   f"still starting; default {BUS_WAIT_S:g}), then exit 3")
    f = ap.add_argument_group("fault injection (for tests)")
    f.add_argument(
        "--drop-replies",
        type=float,
        default=env(ENV_PREFIX + "DROP_REPLIES") or "0",  # a str default goes through type=
        metavar="FRACTION",
        help="drop this fraction of replies (seeded)",
    )
    f.add_argument(
        "--delay-replies",
        type=float,
        default=env(ENV_PREFIX + "DELAY_REPLIES") or "0",
        metavar="MS",
        help="delay every reply by MS milliseconds",
    )
    f.add_argument(
        "--silence-module",
        action="append",
        default=None,
        metavar="ID",
        help="module id(s) that ignore the bus (repeatable, comma list); SIGUSR1 toggles them",
    )
    f.add_argument(
        "--silence-initially",
        choices=("on", "off"),
        default="on",
        help="whether --silence-module ids start silent (default on)",
    )
    f.add_argument(
        "--die-after",
        type=float,
        default=env(ENV_PREFIX + "DIE_AFTER") or None,
        metavar="S",
        help="SIGKILL itself after S seconds (a crash)",
    )
    f.add_argument("--seed", type=int, default=env(ENV_PREFIX + "SEED") or "0", help="fault RNG seed")
    ap.add_argument(
        "--realtime-priority",
        type=int,
        default=int(env(ENV_PREFIX + "REALTIME_PRIORITY") or DEFAULT_REALTIME_PRIORITY),
        metavar="N",
        help="SCHED_FIFO priority of the simulator's threads (1..98, 0 = normal scheduling; "
        f"default {DEFAULT_REALTIME_PRIORITY}); falls back to a raised nice level when not permitted",
    )
    ap.add_argument(
        "--slice-ms",
        type=float,
        default=realtime.DEFAULT_SLICE_MS,
        metavar="MS",
        help="time slice of the bus thread at normal scheduling (0.1..100 ms, 0 = the kernel's default; "
        f"default {realtime.DEFAULT_SLICE_MS:g}): woken sooner, same CPU share",
    )
    ap.add_argument(
        "--physics",
        choices=("process", "thread"),
        default="process",
        help="step the physics in a process of its own (default: no reply waits for it) or in a thread "
        "of this process (replies can wait for it to release the interpreter lock)",
    )
    ap.add_argument("--log-level", default="INFO", help="logging level (DEBUG, INFO, WARNING)")
    return ap


def strip_ros_args(argv: Sequence[str]) -> list[str]:
    """Drop ``--ros-args ... [--]`` sections (``ros2 run``/launch append them; this is no ROS node)."""
    out: list[str] = []
    skipping = False
    for a in argv:
        if a == "--ros-args":
            skipping = True
        elif skipping and a == "--":
            skipping = False
        elif not skipping:
            out.append(a)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``redarm-sim`` / ``ros2 run redarm_ros sim``."""
    ap = build_parser()
    args = ap.parse_args(strip_ros_args(sys.argv[1:] if argv is None else list(argv)))
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.INFO),
        format="%(asctime)s %(levelname)s redarm-sim: %(message)s",
        stream=sys.stderr,
    )
    silence_env = os.environ.get(ENV_PREFIX + "SILENCE_MODULE")
    silence_args = (
        args.silence_module if args.silence_module is not None else ([silence_env] if silence_env else [])
    )
    try:
        toggle = _ids(silence_args)
        faults = Faults(
            drop_replies=args.drop_replies,
            delay_replies_ms=args.delay_replies,
            silenced=set(toggle) if args.silence_initially == "on" else set(),
            toggle_set=toggle,
            seed=args.seed,
        )
        faults.validate()
        w, h = (int(v) for v in str(args.snapshot_size).lower().split("x"))
        initial_q = _floats(" ".join(args.initial_q)) if args.initial_q else None
        if initial_q is not None and args.start is not None:
            raise ValueError("--start and --initial-q exclude each other")
        if args.rate <= 0 or not math.isfinite(args.rate):
            raise ValueError("--rate must be > 0")
    except ValueError as exc:
        ap.print_usage(sys.stderr)
        _LOG.error("bad arguments: %s", exc)
        return EXIT_BAD_ARGS

    from redarm_ros.kinematics import load_arm_or_urdf

    try:
        arm = load_arm_or_urdf(args.arm, args.urdf, args.base_link, args.tip_link)
        if args.start == "park":
            if arm.park is None:
                _LOG.error("--start park: arm %s has no park posture (park: in its YAML)", arm.name)
                return EXIT_BAD_ARGS
            initial_q = arm.park.tolist()
        scene = None
        if args.scene:
            from redarm_ros.geometry.obstacles import load_scene

            scene = load_scene(args.scene).to_dict()
        make_plant = functools.partial(build_plant, arm, time_step=1.0 / args.rate, initial_q=initial_q,
                                       gui=args.gui, scene=scene)
        plant: PybulletPlant | PhysicsProcess
        if args.physics == "thread":
            plant = make_plant()
        else:
            plant = PhysicsProcess(arm, make_plant, rate_hz=args.rate,
                                   realtime_priority=args.realtime_priority)
    except RedarmError as exc:
        _LOG.error("%s", exc)
        return EXIT_BAD_ARGS

    from redarm_ros.can.bus import open_bus_waiting

    try:
        bus = open_bus_waiting(
            args.bus_wait,
            log=_LOG.warning,
            interface=args.can_interface,
            channel=args.can_channel,
            config_file=args.can_config_file,
            bitrate=args.can_bitrate,
        )
    except BusError as exc:
        _LOG.error("%s", exc)
        plant.close()
        return EXIT_NO_BUS

    # The bus thread must get the GIL quickly when a frame arrives, even while the physics thread
    # computes: a shorter switch interval than the default 5 ms bounds that wait.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    # The hardware stand-in must not be starved by the rest of the machine: real-time priority for
    # the process (the bus thread created below inherits it), when permitted; one line says which.
    prio = realtime.raise_priority(args.realtime_priority, who="redarm-sim")
    (_LOG.info if prio.realtime or args.realtime_priority <= 0 else _LOG.warning)("%s", prio.message)
    ids = list(range(args.first_id, args.first_id + arm.n))
    sim = HardwareSim(
        plant,
        bus,
        module_ids=ids,
        rate_hz=args.rate,
        faults=faults,
        status_file=args.status_file,
        status_rate_hz=args.status_rate,
        snapshot_dir=args.snapshot_dir,
        snapshot_size=(w, h),
        control_file=args.control_file,
        die_after_s=args.die_after,
        freeze_gc=True,
        slice_ms=args.slice_ms,
    )
    sim.realtime = prio.realtime
    channel = None
    if args.control_port is not None:
        from redarm_ros.sim.control_channel import ControlChannel

        try:
            channel = ControlChannel(sim, port=args.control_port).start()
        except OSError as exc:
            _LOG.error("control channel on 127.0.0.1:%d: %s", args.control_port, exc)
            bus.shutdown()
            plant.close()
            return EXIT_BAD_ARGS

    def _stop(signum: int, _frame: object) -> None:
        _LOG.info("signal %d: stopping", signum)
        sim.request_stop()

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGUSR1, lambda *_: sim.toggle_silence())
    signal.signal(signal.SIGUSR2, lambda *_: sim.request_snapshot(None))

    def _ready() -> None:
        control = f" control={channel.host}:{channel.port}" if channel is not None else ""
        sys.stdout.write(
            f"{READY_LINE} arm={arm.name} modules={ids[0]}-{ids[-1]} rate={args.rate:g} pid={os.getpid()}"
            f"{control}\n"
        )
        sys.stdout.flush()

    try:
        sim.run(on_ready=_ready)
    finally:
        if channel is not None:
            channel.close()
        try:
            bus.shutdown()
        except Exception:  # noqa: BLE001 - shutting down a dead transport must not mask the exit
            _LOG.debug("bus shutdown failed", exc_info=True)
        plant.close()
    if sim.physics_lost:
        return EXIT_PHYSICS_LOST
    c = sim.counters
    _LOG.info(
        "stopped: %d frames, %d replies, %d malformed, %d overruns, max lag %.2f ms, max reply %.2f ms",
        c.frames_rx,
        c.replies_tx,
        c.malformed,
        c.overruns,
        c.max_lag_ms,
        c.reply_latency_max_ms,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
