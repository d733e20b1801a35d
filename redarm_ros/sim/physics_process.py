"""The simulated arm's physics stepped in real time, in the simulator's process or in one of its own.

Why a process of its own, in a session of its own: the simulator's bus thread answers the modules'
requests and needs the CPU for a moment per driver cycle; the physics needs it steadily (a quarter of
a core at 1 kHz). In one process the bus thread waits for the physics twice over. Where the kernel
shares the CPU between sessions (autogroup, the default of desktop kernels), the physics' CPU time
used up the session's share, and a woken bus thread waited in the run queue behind other sessions
(traced on a busy 2-core machine: 20-80 ms, with the bus server prompt: the host's replies timed
out). And CPython runs one thread of a process at a time: pybullet keeps the interpreter lock while
it steps, so a physics thread preempted mid-step holds up every reply until it runs again. In a
process and session of its own the physics stands between no request and its reply; a late physics
step only makes the reported position older.

Pieces:

* :class:`RealTimeStepper`: the real-time pacing of one plant (batches of steps per wake-up, fewer
  wake-ups at rest, late steps caught up in bursts, a large backlog dropped as a resync, the spin guard
  of a real-time loop); used by the in-process physics thread of
  :class:`~redarm_ros.sim.hardware.HardwareSim` and by the physics process alike.
* :class:`PhysicsProcess`: the handle the bus side holds. It has the plant's surface as the module
  emulation and the status see it (``arm``, ``n``, ``joint(i)``, ``q``, ``dq``, ``q_setpoint``,
  ``steps``, ``sim_time``, ``tool_pose()``, ``motion_state()``, ``snapshot_png()``, ``close()``).
  Joint commands are
  queued and written to a pipe once per burst of requests (:meth:`PhysicsProcess.flush`, a write
  that never waits: with the process stopped they wait in the queue), and applied before the
  process's next batch of steps (within
  :data:`~redarm_ros.sim.hardware.MOVING_WAKE_S`, 10 steps at rest, as in the thread); the state
  comes back through shared memory that the bus side reads without waiting for anything: one
  writer, per-value reads of aligned doubles, and a sequence counter around each write for a
  consistent copy of the whole (:meth:`PhysicsProcess.state`).
* :func:`build_plant`: what the process runs to build its plant (picklable with
  :func:`functools.partial`; tests pass their own factory).

The process ignores SIGINT and SIGTERM (the simulator stops it, after its final snapshot; signals to
the simulator's process group do not reach its session anyway) and dies with the simulator
(``PR_SET_PDEATHSIG``, and at the end of its pipe).
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import itertools
import logging
import multiprocessing as mp
import os
import pickle
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from redarm_ros.can import realtime
from redarm_ros.errors import RedarmError
from redarm_ros.sim.plant import MOTION_EPS, PybulletPlant

_LOG = logging.getLogger("redarm_ros.sim.physics")

MAX_BURST = 50  # steps caught up at once; a larger backlog is dropped (resync)
# While the arm rests (no setpoint moving, every joint slower than REST_SPEED_RAD_S) the loop wakes
# every REST_BATCH steps and steps them at once: a still arm is the same arm a few ms later, and each
# wake-up costs more than a step. A command that starts a motion takes effect within those steps.
REST_BATCH = 10
REST_SPEED_RAD_S = 1e-4
# While it moves, the loop wakes every MOVING_WAKE_S (as many steps as fit, at least one: 2 at 1 kHz):
# a command takes effect within that time, well inside a 250 Hz host's 4 ms cycle.
MOVING_WAKE_S = 2e-3
# The physics process, once a host streams steps (FSTEP durations), wakes once per step instead, within
# [MOVING_WAKE_S, MAX_MOVING_WAKE_S]: a command still takes effect within the host's own cycle, and a
# 250 Hz host's arm costs half the wake-ups (each costs more than the steps it takes: caches gone cold on
# a shared machine). Measured on a stream played at 0.8 rad/s, the setpoint then lags the host's steps
# by at most 2.3 mrad more, within the acceleration limit everywhere.
MAX_MOVING_WAKE_S = 4e-3
# With real-time priority the loop must never keep a core: if it has not slept for this long
# (stepping slower than real time), it drops back to normal scheduling.
RT_SPIN_LIMIT_S = 0.5
#: A wake-up this late (s) is logged with its wall time (see :class:`RealTimeStepper`).
LAG_EVENT_S = 0.005
LAG_LOGS_PER_S = 20
START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0
SNAPSHOT_TIMEOUT_S = 30.0
OUTBOX_MAX = 4096  # commands waiting for a stopped process; beyond that the oldest are dropped
PIPE_ATOMIC_BYTES = 4096  # PIPE_BUF on Linux: a write of at most this many bytes is never split
_PR_SET_PDEATHSIG = 1


@dataclass
class PacingCounters:
    """How well the physics kept real time (monotonic counts since start)."""

    overruns: int = 0  # wake-ups with more steps due than planned
    resyncs: int = 0  # backlogs of more than MAX_BURST steps dropped
    max_lag_ms: float = 0.0  # the latest wake-up after its deadline
    lag_spikes: int = 0  # wake-ups LAG_EVENT_S or more late


class RealTimeStepper:
    """Steps ``plant`` at ``rate_hz`` against the monotonic clock.

    Call :meth:`start`, then per wake-up :meth:`advance` and :meth:`sleep`; :meth:`rebase` after a
    deliberate pause (a rendered snapshot) so it counts as neither overrun nor spin. ``realtime``: the
    thread runs under SCHED_FIFO (the spin guard applies). ``on_lag(ms, now)`` hears of every wake-up
    :data:`LAG_EVENT_S` or more late.
    """

    def __init__(self, plant: Any, rate_hz: float, *, realtime_sched: bool = False,
                 on_lag: Callable[[float, float], None] | None = None) -> None:
        self.plant = plant
        self.period = 1.0 / float(rate_hz)
        self.rate_hz = float(rate_hz)
        self.moving_batch = max(1, int(MOVING_WAKE_S * rate_hz + 1e-9))  # steps per wake while moving
        self.realtime = realtime_sched
        self.counters = PacingCounters()
        self._on_lag = on_lag
        self._last_setpoint: np.ndarray | None = None
        self.t0 = self.last_sleep = 0.0
        self.k = 0
        self.batch = 1  # steps per wake-up: moving_batch, or REST_BATCH at rest (planned, not late)

    def host_step(self, duration_s: float) -> None:
        """A host streams steps of ``duration_s`` s: while moving, wake once per step (within
        :data:`MOVING_WAKE_S` and :data:`MAX_MOVING_WAKE_S`), from the next wake-up on."""
        wake = min(max(float(duration_s), MOVING_WAKE_S), MAX_MOVING_WAKE_S)
        self.moving_batch = max(1, int(wake * self.rate_hz + 1e-9))

    def start(self) -> None:
        self.t0 = self.last_sleep = time.monotonic()
        self.k = 0

    def _resting(self) -> bool:
        """Nothing moves: no setpoint moved since the last call and every joint is (nearly) still. (A
        driver holding the arm keeps the setpoint generators active with the same target each cycle.)"""
        sp = self.plant.q_setpoint
        held = self._last_setpoint is not None and np.array_equal(sp, self._last_setpoint)
        self._last_setpoint = sp
        return held and float(np.max(np.abs(self.plant.dq))) < REST_SPEED_RAD_S

    def advance(self, now: float) -> int:
        """Step what is due at ``now``; returns the steps taken."""
        c = self.counters
        due = int((now - self.t0) / self.period) - self.k
        if due <= 0:
            return 0
        lag = (now - (self.t0 + (self.k + self.batch) * self.period)) * 1e3
        if lag > c.max_lag_ms:
            c.max_lag_ms = lag
        if lag >= LAG_EVENT_S * 1e3:
            c.lag_spikes += 1
            if self._on_lag is not None:
                self._on_lag(lag, now)
        if due > MAX_BURST:
            c.resyncs += 1
            c.overruns += 1
            self.t0 += (due - 1) * self.period  # forget the backlog: simulated time lags wall time
            due = 1
        elif due > self.batch:
            c.overruns += 1
        self.plant.step(due)
        self.k += due
        self.batch = REST_BATCH if self._resting() else self.moving_batch
        return due

    def rebase(self) -> None:
        """Continue from now as if on time (after a deliberate pause)."""
        self.t0 = time.monotonic() - self.k * self.period
        self.last_sleep = time.monotonic()

    def sleep(self, wake: Callable[[float], object] = time.sleep) -> None:
        """Sleep until the next batch is due (``wake(seconds)`` does the waiting); drop real-time
        priority if the loop has not slept for :data:`RT_SPIN_LIMIT_S`."""
        delay = self.t0 + (self.k + self.batch) * self.period - time.monotonic()
        if delay > 0:
            wake(delay)
            self.last_sleep = time.monotonic()
        elif self.realtime and time.monotonic() - self.last_sleep > RT_SPIN_LIMIT_S:
            realtime.drop_priority()
            self.realtime = False
            _LOG.warning("physics cannot keep up with --rate %g Hz: dropped real-time priority "
                         "(a real-time loop that never sleeps would take a core from everyone)", self.rate_hz)


def build_plant(arm: Any, *, time_step: float, initial_q: Sequence[float] | None = None, gui: bool = False,
                scene: Mapping[str, Any] | None = None) -> PybulletPlant:
    """The simulator's plant: ``arm`` (a kinematics model) in a new pybullet client, with ``scene``."""
    plant = PybulletPlant.create(arm, gui=gui, time_step=time_step, initial_q=initial_q)
    if scene:
        plant.add_scene(scene)
    return plant


# -- shared state layout (float64 slots) ---------------------------------------------------------------
_SEQ, _APPLIED, _READY, _STEPS, _SIM_TIME, _OVERRUNS, _RESYNCS, _MAX_LAG, _LAG_SPIKES = range(9)
_HEADER = 9
_READY_FAILED = -1.0


def _layout(n: int) -> dict[str, slice]:
    q = slice(_HEADER, _HEADER + n)
    dq = slice(q.stop, q.stop + n)
    sp = slice(dq.stop, dq.stop + n)
    active = slice(sp.stop, sp.stop + n)
    pos = slice(active.stop, active.stop + 3)
    quat = slice(pos.stop, pos.stop + 4)
    return {"q": q, "dq": dq, "sp": sp, "active": active, "pos": pos, "quat": quat}


def _size(n: int) -> int:
    return _layout(n)["quat"].stop


class RemoteJoint:
    """One joint of a :class:`PhysicsProcess` seen as a PowerCube module's plant (the emulator's
    ``Plant`` protocol). Commands are sent; the state is read from shared memory. Thread-safe."""

    def __init__(self, physics: PhysicsProcess, index: int) -> None:
        self._p = physics
        self.index = index
        self._v = memoryview(physics._view)  # the shared state; an item of it is a Python float at once
        lay = physics._lay
        self._q = lay["q"].start + index
        self._dq = lay["dq"].start + index
        self._active = lay["active"].start + index
        self._motion_seq = 0  # the last motion command not yet known to be applied

    def command_position(self, target: float, vel_limit: float | None, acc_limit: float | None,
                         duration_s: float | None) -> None:
        self._motion_seq = self._p._send("position", self.index, target, vel_limit, acc_limit, duration_s)

    def command_velocity(self, velocity: float) -> None:
        self._motion_seq = self._p._send("velocity", self.index, velocity)

    def halt(self) -> None:
        self._p._send("halt", self.index)
        self._motion_seq = 0

    def set_travel_limits(self, lower: float, upper: float) -> None:
        self._p._send("limits", self.index, lower, upper)

    def position(self) -> float:
        """Measured joint position (rad) after the physics' last step."""
        return self._v[self._q]

    def velocity(self) -> float:
        """Measured joint velocity (rad/s) after the physics' last step."""
        return self._v[self._dq]

    def in_motion(self) -> bool:
        """True while the setpoint moves, the joint measurably does, or a motion command is on its way
        (a module in motion from the moment it took the command, as in the thread)."""
        v = self._v
        if self._motion_seq and v[_APPLIED] >= self._motion_seq:
            self._motion_seq = 0
        return bool(self._motion_seq) or v[self._active] > 0.5 or abs(v[self._dq]) > MOTION_EPS


class PhysicsProcess:
    """The plant stepped in real time by a process of its own (see the module docstring).

    ``arm``: the kinematics model (limits for the module emulation; the process builds its own plant
    with ``make_plant()``, a picklable callable, e.g. ``functools.partial(build_plant, arm, ...)``).
    ``realtime_priority``: SCHED_FIFO priority the process asks for (0: normal scheduling).

    Raises:
        RedarmError: the process did not come up (its own log says why).
    """

    steps_itself = True  # HardwareSim does not step it

    def __init__(self, arm: Any, make_plant: Callable[[], Any], *, rate_hz: float = 1000.0,
                 realtime_priority: int = 0, start_timeout_s: float = START_TIMEOUT_S) -> None:
        self.arm = arm
        self.n = int(arm.n)
        self.rate_hz = float(rate_hz)
        self._lay = _layout(self.n)
        ctx = mp.get_context("spawn")  # no fork of a process that runs threads
        self._raw = ctx.RawArray(ctypes.c_double, _size(self.n))
        self._view = np.frombuffer(self._raw, dtype=np.float64)
        recv, self._conn = ctx.Pipe(duplex=False)
        # Commands wait here until flush() writes them; the write never blocks (a full pipe: the physics
        # stopped), so the bus thread that answers the requests never waits for the process.
        os.set_blocking(self._conn.fileno(), False)
        self._outbox: collections.deque[tuple[Any, ...]] = collections.deque()
        self._outbox_lock = threading.Lock()
        self.dropped_commands = 0  # commands dropped because OUTBOX_MAX were waiting
        self._seq = 0
        self._joints = [RemoteJoint(self, i) for i in range(self.n)]
        self._proc = ctx.Process(
            target=_physics_main, name="redarm-sim-physics", daemon=True,
            args=(make_plant, self._raw, recv, self.rate_hz, int(realtime_priority),
                  logging.getLogger().getEffectiveLevel()),
        )
        with _spawn_without_main((make_plant, arm)):
            self._proc.start()
        recv.close()
        deadline = time.monotonic() + start_timeout_s
        while self._view[_READY] == 0.0 and self._proc.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        if self._view[_READY] != 1.0:
            self._kill()
            raise RedarmError("the physics process did not start (see its log above)")

    # -- commands ---------------------------------------------------------------------------------
    def _send(self, op: str, *args: Any, now: bool = False) -> int:
        """Queue a command for the process (written at the next :meth:`flush`, or ``now``); returns its
        sequence number."""
        with self._outbox_lock:
            self._seq += 1
            if len(self._outbox) >= OUTBOX_MAX:  # the process stopped taking commands: keep the newest
                self._outbox.popleft()
                self.dropped_commands += 1
            self._outbox.append((self._seq, op, *args))
            seq = self._seq
        if now:
            self.flush()
        return seq

    def flush(self) -> None:
        """Write the queued commands to the process, as many as the pipe takes now; never waits.

        The bus side calls this once per burst of requests (one write per driver cycle). Each write is
        one message of at most :data:`PIPE_ATOMIC_BYTES` bytes in the pipe's own framing (a length,
        then the pickled list of commands), which the kernel writes whole or not at all."""
        with self._outbox_lock:
            while self._outbox:
                count = len(self._outbox)
                while True:
                    batch = list(itertools.islice(self._outbox, count))
                    payload = pickle.dumps(batch, pickle.HIGHEST_PROTOCOL)
                    if len(payload) + 4 <= PIPE_ATOMIC_BYTES or count == 1:
                        break
                    count = max(1, count // 2)
                try:
                    os.write(self._conn.fileno(), struct.pack("!i", len(payload)) + payload)
                except BlockingIOError:  # the pipe is full: the process is not reading; later
                    return
                except OSError as exc:  # the process is gone: run() notices
                    _LOG.debug("physics commands not sent: %s", exc)
                    self._outbox.clear()
                    return
                for _ in range(count):
                    self._outbox.popleft()

    def _wait_applied(self, seq: int, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while self._view[_APPLIED] < seq:
            if not self._proc.is_alive() or time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    # -- the plant's surface ------------------------------------------------------------------------
    def joint(self, index: int) -> RemoteJoint:
        """Plant adapter of joint ``index`` (0-based)."""
        return self._joints[index]

    @property
    def joints(self) -> list[RemoteJoint]:
        return list(self._joints)

    def state(self) -> np.ndarray:
        """A consistent copy of the whole shared state (one write of the process, never half of two)."""
        v = self._view
        while True:
            before = v[_SEQ]
            copy = v.copy()
            if before == v[_SEQ] and int(before) % 2 == 0:
                return copy
            time.sleep(0)

    @property
    def q(self) -> np.ndarray:
        return self.state()[self._lay["q"]]

    @property
    def dq(self) -> np.ndarray:
        return self.state()[self._lay["dq"]]

    @property
    def q_setpoint(self) -> np.ndarray:
        return self.state()[self._lay["sp"]]

    @property
    def steps(self) -> int:
        return int(self._view[_STEPS])

    @property
    def sim_time(self) -> float:
        return float(self._view[_SIM_TIME])

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Tool position and quaternion (x, y, z, w) at :attr:`q`."""
        s = self.state()
        return s[self._lay["pos"]], s[self._lay["quat"]]

    def motion_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``q``, ``dq``, ``q_setpoint``, the tool position and quaternion (x, y, z, w) of one write of
        the process (read one by one, a moving arm's tool pose and joints came from different steps)."""
        s, lay = self.state(), self._lay
        return s[lay["q"]], s[lay["dq"]], s[lay["sp"]], s[lay["pos"]], s[lay["quat"]]

    def pacing(self) -> PacingCounters:
        """How well the process keeps real time."""
        s = self.state()
        return PacingCounters(overruns=int(s[_OVERRUNS]), resyncs=int(s[_RESYNCS]),
                              max_lag_ms=float(s[_MAX_LAG]), lag_spikes=int(s[_LAG_SPIKES]))

    def alive(self) -> bool:
        return self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def snapshot_png(self, path: Any, width: int = 640, height: int = 480) -> None:
        """Render a PNG to ``path`` in the process; returns once written.

        Raises:
            RedarmError: not written within :data:`SNAPSHOT_TIMEOUT_S` (the process is gone or stuck).
        """
        seq = self._send("snapshot", str(path), int(width), int(height), now=True)
        if not self._wait_applied(seq, SNAPSHOT_TIMEOUT_S):
            raise RedarmError(f"snapshot {path} not written by the physics process")

    def close(self) -> None:
        """Stop the process (after the commands sent before) and reap it."""
        deadline = time.monotonic() + STOP_TIMEOUT_S
        self._send("stop", now=True)
        while self._outbox and self._proc.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)  # a full pipe: the process reads it within its next wake-up
            self.flush()
        self._proc.join(max(0.0, deadline - time.monotonic()))
        self._kill()
        with contextlib.suppress(OSError):
            self._conn.close()

    def _kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(STOP_TIMEOUT_S)


# -- the process ---------------------------------------------------------------------------------------
def _die_with_parent() -> None:
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() == 1:  # the parent died before the line above
        os._exit(1)


def _apply(plant: Any, cmd: tuple[Any, ...], stepper: RealTimeStepper | None = None) -> bool:
    """Apply one command; False for ``stop``. A streamed step (a duration) sets ``stepper``'s wake-ups."""
    _, op, *args = cmd
    if op == "position":
        j, target, vel, acc, dur = args
        plant.joint(j).command_position(target, vel, acc, dur)
        if stepper is not None and dur is not None and dur > 0.0:
            stepper.host_step(dur)
    elif op == "velocity":
        plant.joint(args[0]).command_velocity(args[1])
    elif op == "halt":
        plant.joint(args[0]).halt()
    elif op == "limits":
        plant.joint(args[0]).set_travel_limits(args[1], args[2])
    elif op == "snapshot":
        plant.snapshot_png(args[0], args[1], args[2])
    elif op == "stop":
        return False
    else:
        raise ValueError(f"unknown physics command {op!r}")
    return True


@contextlib.contextmanager
def _spawn_without_main(pickled: Any) -> Iterator[None]:
    """While a spawn child starts, keep it from running the parent's ``__main__`` module again.

    spawn imports the parent's main module in the child (as ``__mp_main__``) so that whatever was
    pickled from it resolves. The simulator runs as ``python -m redarm_ros.sim.hardware``, whose
    imports (python-can, the protocol: ~0.15 s of CPU) the physics process never uses. When nothing the
    child is handed names ``__main__``, the main module's spec and file are hidden while the child is
    started (spawn then leaves main alone, as it does for an interactive parent); otherwise, and on any
    doubt, nothing changes.
    """
    main = sys.modules.get("__main__")
    try:
        refs_main = b"__main__" in pickle.dumps(pickled)
    except Exception:  # noqa: BLE001 - unpicklable here: let spawn report it as before
        refs_main = True
    if main is None or refs_main:
        yield
        return
    saved = {k: main.__dict__[k] for k in ("__spec__", "__file__") if k in main.__dict__}
    main.__spec__ = None
    main.__dict__.pop("__file__", None)
    try:
        yield
    finally:
        main.__dict__.pop("__spec__", None)
        main.__dict__.update(saved)


def _physics_main(make_plant: Callable[[], Any], raw: Any, conn: Connection, rate_hz: float,
                  realtime_priority: int, log_level: int) -> None:
    _die_with_parent()
    # A session of its own: where the kernel shares the CPU between sessions (autogroup), the physics'
    # CPU time is then not charged to the simulator's share, which its bus thread needs for the replies.
    with contextlib.suppress(OSError):
        os.setsid()
    realtime.name_thread("sim-physics")
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the simulator stops this process when it is done
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s redarm-sim physics: %(message)s")
    view = np.frombuffer(raw, dtype=np.float64)
    try:
        plant = make_plant()
    except Exception:  # noqa: BLE001 - reported to the parent, which exits with its own code
        _LOG.exception("could not build the plant")
        view[_READY] = _READY_FAILED
        return
    lay = _layout(int(plant.n))
    prio = realtime.raise_priority(realtime_priority, who="redarm-sim physics")
    if realtime_priority > 0:
        (_LOG.info if prio.realtime else _LOG.warning)("%s", prio.message)
    lag_logs = realtime.PerSecondLimit(LAG_LOGS_PER_S)

    def on_lag(ms: float, at: float) -> None:
        wall = time.time() - (time.monotonic() - at)
        if lag_logs.allow(wall):
            _LOG.warning("slow: physics wake-up late %.1f ms at wall time %.4f", ms, wall)

    stepper = RealTimeStepper(plant, rate_hz, realtime_sched=prio.realtime, on_lag=on_lag)
    applied = 0.0
    tool_q: np.ndarray | None = None  # the joints the tool pose in the shared state belongs to

    def publish() -> None:
        nonlocal tool_q
        q = plant.q
        view[_SEQ] += 1  # odd: a write is under way
        view[lay["q"]] = q
        view[lay["dq"]] = plant.dq
        view[lay["sp"]] = plant.q_setpoint
        view[lay["active"]] = [1.0 if plant.joint(i).ramp.active else 0.0 for i in range(plant.n)]
        if tool_q is None or not np.array_equal(q, tool_q):  # (at rest: no pybullet call)
            tool_q = q
            pos, quat = plant.tool_pose()
            view[lay["pos"]], view[lay["quat"]] = pos, quat
        c = stepper.counters
        view[_STEPS], view[_SIM_TIME] = plant.steps, plant.sim_time
        view[_OVERRUNS], view[_RESYNCS], view[_MAX_LAG], view[_LAG_SPIKES] = (
            c.overruns, c.resyncs, c.max_lag_ms, c.lag_spikes)
        view[_APPLIED] = applied
        view[_SEQ] += 1  # even: consistent

    running = True
    try:
        publish()
        view[_READY] = 1.0
        stepper.start()
        while running:
            paused = False
            try:
                while running and conn.poll():
                    for cmd in pickle.loads(conn.recv_bytes()):
                        try:
                            running = _apply(plant, cmd, stepper)
                        except Exception:  # noqa: BLE001 - one bad command must not stop the arm
                            _LOG.exception("physics command %r failed", cmd[1])
                        paused = paused or cmd[1] == "snapshot"
                        applied = float(cmd[0])
                        if not running:
                            break
            except (EOFError, OSError):  # the simulator is gone
                break
            if paused:  # rendering took a while: not an overrun, nor a spinning real-time loop
                stepper.rebase()
            now = time.monotonic()
            stepper.advance(now)
            publish()
            if running:
                stepper.sleep()
    finally:
        with contextlib.suppress(Exception):
            plant.close()

