"""Host side of a PowerCube arm: discovery, init/home, halt, recover and the cyclic FSTEP stream.

ROS-free; talks to any ``can.BusABC`` (usually a :class:`~redarm_ros.can.bus.ReconnectingBus`).
One cycle (:meth:`PowerCubeArmDriver.cycle`) sends one FSTEP_EXT per joint carrying the cycle
time, then the startMotionAll broadcast (the modules run with SYNC_MOTION, so all joints start
together), optionally the watchdog refresh broadcast, and then collects the extended
acknowledgements (actual position *before* the move, short state) in one receive loop with a
deadline. Frames are pre-built once and patched in place every cycle.

Safety rules, all enforced before anything is sent:

* a target with NaN/inf or the wrong shape is refused (:class:`InvalidInputError`, nothing sent);
* targets are clamped to ``[lower, upper]`` and to a step of ``max_vel * dt`` from the previous
  commanded target; clamped joints are listed in :attr:`CycleResult.clamped`;
* every measured position (extended acknowledgement or ACT_FPOS) is checked for plausibility: a
  jump from the last accepted measurement of more than ``max_vel * (elapsed + reply_timeout_s) +
  plausibility_margin_rad``, or a position further than the braking distance from full speed plus
  ``plausibility_margin_rad`` outside the span of that measurement and the targets sent since (so
  the allowance stays bounded while a module is silent), is refused (counted per module, never
  taken as the arm's state; the cycle keeps waiting for a plausible reply from that module);
* a module that misses ``max_missed`` consecutive replies -> every module is halted, the driver
  enters FAULT and :class:`BusTimeoutError` (``module_id``, ``timeout_s``) is raised once, with
  the cycle's result in its ``cycle_result`` attribute; if the module answered only with
  implausible positions meanwhile, the fault is :attr:`FaultKind.IMPLAUSIBLE` instead (no raise);
* a module reporting ERROR (short state, or a state frame on 0x060+id) -> every module halted,
  its full ACT_STATE is read (POWERFAULT, TOW_ERROR, BEYOND_SOFT, ...) and reported in
  :attr:`CycleResult.fault` (a :class:`Fault`: kind, module ids, bits, message); the driver
  enters FAULT;
* in FAULT or HALTED a cycle only holds and polls (target = measured position, which halted
  modules refuse anyway) until :meth:`recover` (or :meth:`init`); :meth:`recover` restores
  everything a power-cycled module lost (RESET, then ACT_CONFIG with SYNC_MOTION and
  WATCHDOG_ENABLE, ACT_FMAXVEL/ACT_FMAXACC), so the watchdog is armed again afterwards;
* a transport failure raises :class:`BusError`; the caller reopens the bus with backoff
  (:meth:`reconnect`, or ``bus.reopen()`` directly). The first use after a failure re-reads
  the positions and holds them: a command from before the loss is never replayed.

The driver's state (:class:`DriverState`) changes only through one transition table
(:data:`TRANSITIONS`, events :class:`DriverEvent`); the cyclic loop's state is derived from it.

Every frame is built (and the cycle's FSTEP frames patched) by the codec,
:mod:`redarm_ros.can.protocol`, and stamped with the wall time at which it is sent
(``msg.timestamp``): buses that carry the sender's stamp (the loopback bus server) let the modules
judge the host by when it sent, not by when they got to read.

Threading: every public method takes one lock, so calls from different threads are serialised,
but the intended use is one thread owning the driver (the node's loop thread) and calling
:meth:`cycle` at a fixed rate and the other methods in between.

Units: rad, rad/s, rad/s^2, s. Times come from ``clock`` (default ``time.perf_counter``).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import Enum

import can
import numpy as np

from redarm_ros.can import protocol as p
from redarm_ros.can.protocol import POWER_STAGE_FAULTS, ActConfig, ActState, Command, Param
from redarm_ros.can.reply_deadline import ReplyDeadline
from redarm_ros.errors import (
    BusError,
    BusTimeoutError,
    ImplausibleMeasurementError,
    InvalidInputError,
    ModuleFaultError,
    RedarmError,
    RequestHaltedError,
    RequestRefusedError,
)
from redarm_ros.motion import JointLimits, LimitsView

logger = logging.getLogger(__name__)

#: Bits that make the driver halt everything and report.
FAULT_BITS = (
    ActState.ERROR
    | ActState.POWERFAULT
    | ActState.TOW_ERROR
    | ActState.BEYOND_SOFT
    | ActState.BEYOND_HARD
    | POWER_STAGE_FAULTS
)
#: Bits named in a fault report: the fault bits and COMM_ERROR (the module's watchdog ran out: it heard
#: nothing from the host for its timeout, e.g. a starved cycle).
REPORTED_BITS = FAULT_BITS | ActState.COMM_ERROR
_LATENCY_WINDOW = 1024
#: Requests outside the cycle (configure, reset, home, state reads) are sent this many times to a
#: module that has not answered, waiting ``reply_timeout_s``, then twice, then four times that:
#: 0.14 s in all at the default 0.02 s, while the watchdog (refreshed before every retry) allows 0.1 s
#: between frames.
REQUEST_ATTEMPTS = 3
#: A plausibility check allows this much (rad) beyond what the velocity limit explains.
DEFAULT_PLAUSIBILITY_MARGIN = 0.02
#: Another host on the bus shows in replies this driver did not ask for: a module answers only a
#: request, so a well-formed, plausible reply on 0x0A0+id with no request of ours waiting for it (a
#: request waits at most :data:`REQUEST_TTL_S`) was asked for by someone else. This many such replies
#: within :data:`FOREIGN_WINDOW_S` (a second driver makes hundreds a second, even idle at 0.5 Hz
#: polling 14 per second; a tool reading a parameter or a forged frame a few) halt every module.
FOREIGN_REPLIES = 10
FOREIGN_WINDOW_S = 2.0
REQUEST_TTL_S = 5.0
#: ``recover`` holds the arm where it comes to rest: it waits until no module reports MOTION and two
#: position reads in a row agree within this (rad), for at most the longest braking time plus
#: :data:`SETTLE_EXTRA_S`.
SETTLE_TOLERANCE_RAD = 1e-4
SETTLE_EXTRA_S = 1.0
#: While init or recover runs, receive waits are cut into slices this long (s), so a halt request
#: from another thread is noticed within about one cycle (4 ms at 250 Hz).
HALT_POLL_S = 0.002
# A drain before a cycle or request reads at most this many frames (a flooded bus must not stall it).
_DRAIN_MAX_FRAMES = 256
_SHORT_ERROR = int(p.ShortState.ERROR)
_LONG_ONLY = ~p.LONG_BITS_WITH_SHORT  # ACT_STATE bits a short state cannot report


class DriverState(Enum):
    """Lifecycle of :class:`PowerCubeArmDriver`."""

    UNINITIALIZED = "uninitialized"  # not yet init()/recover(): cycle() refuses
    READY = "ready"  # following targets
    HALTED = "halted"  # halt() was called: cycles hold and poll until recover()/init()
    FAULT = "fault"  # a module failed or stopped answering: cycles hold and poll until recover()


class DriverEvent(Enum):
    """What moves :class:`PowerCubeArmDriver` from one :class:`DriverState` to another."""

    INIT_STARTED = "init_started"  # init() begins: not initialised until it succeeds
    READY = "ready"  # init() or recover() succeeded
    HALT = "halt"  # halt() was called
    FAULT = "fault"  # a module stopped answering, reported an error or implausible positions


#: The driver's one state machine: (state, event) -> next state. A pair not listed leaves the
#: state unchanged (a halt while in FAULT keeps the fault until recover()).
TRANSITIONS: dict[tuple[DriverState, DriverEvent], DriverState] = {
    **{(st, DriverEvent.INIT_STARTED): DriverState.UNINITIALIZED for st in DriverState},
    **{(st, DriverEvent.READY): DriverState.READY for st in DriverState},
    **{(st, DriverEvent.FAULT): DriverState.FAULT for st in DriverState},
    (DriverState.UNINITIALIZED, DriverEvent.HALT): DriverState.HALTED,
    (DriverState.READY, DriverEvent.HALT): DriverState.HALTED,
    (DriverState.HALTED, DriverEvent.HALT): DriverState.HALTED,
}


class FaultKind(Enum):
    """Why the arm was halted without being asked to."""

    SILENT = "silent"  # a module missed max_missed replies in a row
    MODULE_ERROR = "module_error"  # a module reported ERROR (with its cause bits)
    IMPLAUSIBLE = "implausible"  # a module's positions jumped further than it can move
    REQUEST_FAILED = "request_failed"  # init or recover did not succeed
    MISSING = "missing"  # modules missing when the bus came back
    INTERNAL = "internal"  # a bug in the loop (it halts rather than keep moving)
    FOREIGN_HOST = "foreign_host"  # replies this driver did not ask for: another host drives the modules


@dataclass(frozen=True)
class Fault:
    """Why the arm was halted, as data: ``kind``, the ``module_ids`` at fault (empty: none in
    particular), their ACT_STATE fault ``bits`` (module id -> bits, for MODULE_ERROR) and a human
    ``message`` (also ``str(fault)``)."""

    kind: FaultKind
    module_ids: tuple[int, ...]
    message: str
    bits: Mapping[int, ActState] = field(default_factory=dict)

    def __str__(self) -> str:
        return self.message

    def involves(self, module_id: int) -> bool:
        """True if module ``module_id`` is one of the modules at fault."""
        return module_id in self.module_ids


class ForeignHostError(RedarmError):
    """Another host drives the modules (replies this driver did not ask for); every module was halted.
    ``fault`` is the :class:`Fault` (kind FOREIGN_HOST) the driver is in."""

    def __init__(self, fault: Fault) -> None:
        super().__init__(fault.message)
        self.fault = fault


def fault_bit_names(bits: int) -> str:
    """``"ERROR|POWERFAULT"``: names of the :data:`REPORTED_BITS` set in ``bits``."""
    return "|".join(b.name or "" for b in ActState if b & bits and b & REPORTED_BITS)


class ModuleStats:
    """Per-module statistics for diagnostics (counts since construction; latency over a window)."""

    __slots__ = (
        "module_id",
        "replies",
        "lost",
        "late",
        "malformed",
        "consecutive_misses",
        "consecutive_implausible",
        "silent",
        "implausible",
        "last_implausible",
        "last_implausible_at",
        "_lat",
        "_k",
    )

    def __init__(self, module_id: int) -> None:
        self.module_id = module_id
        self.replies = 0
        self.lost = 0  # expected replies that did not arrive before the deadline
        self.late = 0  # replies that arrived after their deadline (or twice)
        self.malformed = 0  # frames from this module that the codec refused
        self.consecutive_misses = 0
        self.consecutive_implausible = 0  # implausible positions since the last plausible one
        self.silent = False  # missed max_missed replies in a row (cleared by the next reply)
        self.implausible = 0  # measured positions refused by the plausibility check
        self.last_implausible = math.nan  # the last refused position (rad)
        self.last_implausible_at = -math.inf  # when it was refused (time.monotonic() s)
        self._lat = np.zeros(_LATENCY_WINDOW)
        self._k = 0

    def add_latency(self, seconds: float) -> None:
        """Record one reply latency (s)."""
        self._lat[self._k % _LATENCY_WINDOW] = seconds
        self._k += 1

    def _window(self) -> np.ndarray:
        return self._lat[: min(self._k, _LATENCY_WINDOW)]

    @property
    def latency_median_ms(self) -> float:
        """Median reply latency over the last replies (ms; 0 before the first)."""
        w = self._window()
        return float(np.median(w) * 1e3) if w.size else 0.0

    @property
    def latency_max_ms(self) -> float:
        """Largest reply latency over the last replies (ms; 0 before the first)."""
        w = self._window()
        return float(w.max() * 1e3) if w.size else 0.0

    def view(self) -> ModuleStatsView:
        """A frozen copy of the values (for snapshots handed to other threads or processes)."""
        return ModuleStatsView(
            module_id=self.module_id, replies=self.replies, lost=self.lost, late=self.late,
            malformed=self.malformed, implausible=self.implausible, silent=self.silent,
            latency_median_ms=self.latency_median_ms, latency_max_ms=self.latency_max_ms,
            implausible_age_s=time.monotonic() - self.last_implausible_at,
        )

    def as_dict(self) -> dict[str, float | int | bool]:
        """Plain values for logs and diagnostics."""
        return self.view().as_dict()

    def __repr__(self) -> str:
        return f"ModuleStats({self.as_dict()})"


@dataclass(frozen=True)
class ModuleStatsView:
    """The values of one module's :class:`ModuleStats` at one moment (latencies in ms)."""

    module_id: int
    replies: int
    lost: int
    late: int
    malformed: int
    implausible: int
    silent: bool
    latency_median_ms: float
    latency_max_ms: float
    implausible_age_s: float = math.inf  # since the last implausible position was refused (s)

    def as_dict(self) -> dict[str, float | int | bool]:
        """Plain values for logs and diagnostics."""
        return dict(self.__dict__)


@dataclass(frozen=True)
class DiscoveryReport:
    """Result of :meth:`PowerCubeArmDriver.discover`: firmware version per found id, missing ids."""

    found: dict[int, int]
    missing: list[int]

    @property
    def complete(self) -> bool:
        """True when every configured module answered."""
        return not self.missing


@dataclass(frozen=True)
class ArmState:
    """Positions (n,) rad and ACT_STATE bits per joint, read with GETPARAM."""

    positions: np.ndarray
    states: list[ActState]

    @property
    def errors(self) -> dict[int, ActState]:
        """Joint index -> fault bits, for joints reporting any of :data:`FAULT_BITS`."""
        return {j: s & FAULT_BITS for j, s in enumerate(self.states) if s & FAULT_BITS}


@dataclass
class CycleResult:
    """What one :meth:`PowerCubeArmDriver.cycle` sent and measured (arrays in joint order)."""

    stamp: float  # clock time (s) when the commands went out
    positions: np.ndarray  # (n,) rad, actual positions before this cycle's move (last plausible if none)
    velocities: np.ndarray  # (n,) rad/s, finite-difference estimate between cycles
    targets: np.ndarray  # (n,) rad actually commanded (after clamps)
    states: np.ndarray  # (n,) int, ACT_STATE bits (from the short state; last known if no reply)
    replied: np.ndarray  # (n,) bool: a plausible reply arrived
    latency_s: np.ndarray  # (n,) s from a joint's command to its reply (NaN if none)
    clamped: tuple[int, ...] = ()  # joint indices whose target was clamped
    clamped_to_limits: np.ndarray | None = None  # (n,) bool: clamped into [lower, upper]
    clamped_step: np.ndarray | None = None  # (n,) bool: clamped to max_vel * dt
    lost: int = 0  # replies missing this cycle
    late: int = 0  # stale replies of earlier cycles seen this cycle
    malformed: int = 0  # malformed frames seen this cycle
    implausible: int = 0  # replies refused by the plausibility check this cycle
    fault: Fault | None = None  # why the driver halted everything this cycle (None: it did not)
    holding: bool = False  # True when the driver was not READY: the cycle only held and polled
    resynced: bool = False  # positions were re-read after a bus failure; target ignored this cycle


_Matcher = Callable[[p.Frame], bool]


def _is_param(param: Param) -> _Matcher:
    return lambda f: isinstance(f, p.GetParamReply) and f.param is param


def _is_setparam_ack(param: Param) -> _Matcher:
    return lambda f: isinstance(f, p.SetParamAck) and f.param is param


def _is_ack(cmd: Command) -> _Matcher:
    return lambda f: isinstance(f, p.CommandAck) and f.command is cmd


class PowerCubeArmDriver(LimitsView):  # lower, upper, max_vel, max_acc: those of self.limits
    """Drive PowerCube modules ``module_ids`` (joint order) on ``bus``.

    Args:
        bus: an open python-can bus (a :class:`~redarm_ros.can.bus.ReconnectingBus` can be
            reopened by :meth:`reconnect`).
        module_ids: CAN module id (1..31) of each joint.
        lower, upper: joint limits (rad); targets are clamped into them.
        max_vel: per-joint speed limit (rad/s); a target moves at most ``max_vel * dt`` per cycle.
        max_acc: per-joint acceleration limit (rad/s^2), written to the modules (ACT_FMAXACC) at init.
        reply_timeout_s: how long a cycle or request waits for replies.
        max_missed: consecutive missing replies after which a module counts as silent.
        watchdog_refresh: send the watchdog refresh broadcast ``0x100 [07 00]`` every cycle.
        enable_watchdog: set WATCHDOG_ENABLE on the modules at init (then refresh every cycle).
        sync_motion: set SYNC_MOTION at init so all joints start on the STARTMOVE broadcast.
        home_timeout_s: how long :meth:`init` waits for HOME_OK.
        poll_interval_s: ACT_STATE polling interval while homing.
        plausibility_margin_rad: a measured position may differ from the last accepted one by
            ``max_vel * (elapsed + reply_timeout_s)`` plus this much (rad), and lie at most the
            braking distance plus this much outside the span of the last one and the targets sent
            since; more is refused.
        clock: time source (s).

    Raises:
        InvalidInputError: bad module ids, limits, timeouts or margin.
    """

    def __init__(
        self,
        bus: can.BusABC,
        module_ids: Sequence[int],
        lower: Sequence[float],
        upper: Sequence[float],
        max_vel: Sequence[float],
        max_acc: Sequence[float],
        *,
        reply_timeout_s: float = 0.02,
        max_missed: int = 3,
        watchdog_refresh: bool = False,
        enable_watchdog: bool = False,
        sync_motion: bool = True,
        home_timeout_s: float = 30.0,
        poll_interval_s: float = 0.02,
        plausibility_margin_rad: float = DEFAULT_PLAUSIBILITY_MARGIN,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        ids = [int(i) for i in module_ids]
        n = len(ids)
        if n == 0 or len(set(ids)) != n or not all(p.MIN_MODULE_ID <= i <= p.MAX_MODULE_ID for i in ids):
            raise InvalidInputError(f"module ids must be unique ints in 1..31, got {ids}", field="module_ids")
        limits = JointLimits(lower, upper, max_vel, max_acc)
        if limits.n != n:
            raise InvalidInputError(f"limits must have {n} values, one per module", field="lower",
                                    value=lower)
        if not reply_timeout_s > 0 or max_missed < 1:
            raise InvalidInputError(
                "reply_timeout_s must be > 0 and max_missed >= 1", field="reply_timeout_s"
            )
        if not (math.isfinite(plausibility_margin_rad) and plausibility_margin_rad >= 0):
            raise InvalidInputError("plausibility_margin_rad must be >= 0", field="plausibility_margin_rad",
                                    value=plausibility_margin_rad)
        self.bus = bus
        self.module_ids = ids
        self.n = n
        self.limits = limits
        self.reply_timeout_s = float(reply_timeout_s)
        self.plausibility_margin_rad = float(plausibility_margin_rad)
        self.max_missed = int(max_missed)
        self.watchdog_refresh = bool(watchdog_refresh or enable_watchdog)
        self.enable_watchdog = bool(enable_watchdog)
        self.sync_motion = bool(sync_motion)
        self.home_timeout_s = float(home_timeout_s)
        self.poll_interval_s = float(poll_interval_s)
        self._clock = clock
        self._deadline = ReplyDeadline(clock)  # one per driver: every wait holds self._lock
        self._lock = threading.Lock()
        self.state = DriverState.UNINITIALIZED
        self.fault: Fault | None = None  # why the driver is in FAULT (None otherwise)
        self.stats = [ModuleStats(i) for i in ids]
        self.decoder = p.FrameDecoder()
        # Routing tables: reply id / state id -> joint index.
        self._reply_index = {p.IdBase.CMD_ACK + i: j for j, i in enumerate(ids)}
        self._state_index = {p.IdBase.STATE + i: j for j, i in enumerate(ids)}
        self._request_index = {**{p.IdBase.CMD_PUT + i: j for j, i in enumerate(ids)},
                               **{p.IdBase.CMD_GET + i: j for j, i in enumerate(ids)}}
        # Requests of ours waiting for their reply (send times, per joint), and the replies nobody
        # here asked for (clock time, module id): see FOREIGN_REPLIES.
        self._asked: list[deque[float]] = [deque() for _ in ids]
        self._unasked: deque[tuple[float, int]] = deque()
        # Pre-built frames, patched in place every cycle.
        self._fstep_msgs = [p.fstep(i, 0.0, 1) for i in ids]
        self._startmove = p.start_motion_all()
        self._wd_refresh = p.watchdog_refresh_all()
        self._halt_all_msg = p.halt_all()
        self._q_meas = np.zeros(n)  # last measured (plausible) positions
        self._t_meas = np.full(n, math.nan)  # clock time of each; NaN: no reference (accept any)
        self._q_cmd = np.zeros(n)  # last commanded target
        # Where each module can be: the span of its last accepted position and every target sent
        # since (a module follows its FSTEP targets, or is halted and brakes). Bounds the
        # plausibility check however long a module was silent.
        self._q_sent = np.zeros(n)  # the last target sent (holding: the measured position)
        self._reach_lo = np.zeros(n)
        self._reach_hi = np.zeros(n)
        self._brake = np.asarray(self.limits.max_vel, dtype=float) ** 2 / (
            2.0 * np.asarray(self.limits.max_acc, dtype=float))  # braking distance from max_vel (rad)
        self._states = np.zeros(n, dtype=np.int64)
        # The limits per joint as floats (the cycle clamps its targets joint by joint), and no joint.
        self._lower_list, self._upper_list = self.lower.tolist(), self.upper.tolist()
        self._max_vel_list = self.max_vel.tolist()
        self._no_joints = np.zeros(n, dtype=bool)
        self._prev_stamp: float | None = None
        self._prev_q: np.ndarray | None = None
        self._needs_resync = False
        self._pending_faults: dict[int, ActState] = {}
        # Set by request_halt() from any thread (no lock: init/recover hold it for seconds); the
        # running init/recover notices it in its receive waits and halts everything.
        self._halt_requested = threading.Event()
        self._interruptible = False  # init/recover in progress: receive waits watch _halt_requested
        # init() succeeded since construction: the positions are established by homing. recover()
        # needs it (without homing, a module's position may be anything).
        self.initialised = False
        self._home_ok_at_init = [False] * n  # HOME_OK of each module when init() ended

    @property
    def frames_per_cycle(self) -> int:
        """Frames one :meth:`cycle` sends: an FSTEP per joint, STARTMOVE, the watchdog refresh."""
        return self.n + 1 + int(self.watchdog_refresh)

    def _fire(self, event: DriverEvent, fault: Fault | None = None) -> None:
        """Apply one :data:`TRANSITIONS` entry; a FAULT records ``fault``, READY clears it."""
        self.state = TRANSITIONS.get((self.state, event), self.state)
        if event is DriverEvent.FAULT:
            self.fault = fault
        elif event is DriverEvent.READY or event is DriverEvent.INIT_STARTED:
            self.fault = None

    # ------------------------------------------------------------------------------------------
    # transport helpers (translate any failure to BusError and remember to resync)
    # ------------------------------------------------------------------------------------------

    def _lost(self, exc: BaseException, during: str) -> BusError:
        self._needs_resync = True
        if isinstance(exc, BusError):
            return exc
        err = BusError(f"CAN bus failed during {during}: {exc!r}")
        err.__cause__ = exc
        return err

    def _send(self, msg: can.Message) -> None:
        msg.timestamp = time.time()  # when it went on the bus (kept by buses that carry it)
        try:
            self.bus.send(msg)
        except InvalidInputError:
            raise
        except Exception as exc:
            raise self._lost(exc, "send") from exc
        j = self._request_index.get(msg.arbitration_id)
        if j is not None:
            self._asked[j].append(self._clock())

    def _send_many(self, msgs: Sequence[can.Message]) -> float:
        """:meth:`_send` for a batch, in one write where the bus allows it (a cycle's frames reach the
        modules together, as they would on a real bus in one burst); returns the clock time after it."""
        stamp = time.time()
        for msg in msgs:
            msg.timestamp = stamp
        batch = getattr(self.bus, "send_many", None)
        try:
            if batch is not None:
                batch(msgs)
            else:
                for msg in msgs:
                    self.bus.send(msg)
        except InvalidInputError:
            raise
        except Exception as exc:
            raise self._lost(exc, "send") from exc
        t = self._clock()
        for msg in msgs:
            j = self._request_index.get(msg.arbitration_id)
            if j is not None:
                self._asked[j].append(t)
        return t

    def _note_reply(self, j: int, t: float) -> None:
        """A well-formed, plausible reply of joint ``j`` came at clock time ``t``: it answers the oldest
        request of ours still waiting, or, with none waiting, somebody else's request."""
        asked = self._asked[j]
        while asked and t - asked[0] > REQUEST_TTL_S:
            asked.popleft()  # never answered (lost): no longer expected
        if asked:
            asked.popleft()
            return
        unasked = self._unasked
        unasked.append((t, self.module_ids[j]))
        while t - unasked[0][0] > FOREIGN_WINDOW_S:
            unasked.popleft()

    def _foreign_host_fault(self) -> Fault | None:
        """The fault when :data:`FOREIGN_REPLIES` unasked replies came within :data:`FOREIGN_WINDOW_S`
        (the evidence is then used up), else None."""
        unasked = self._unasked
        if len(unasked) < FOREIGN_REPLIES:
            return None
        t = self._clock()
        while unasked and t - unasked[0][0] > FOREIGN_WINDOW_S:
            unasked.popleft()
        if len(unasked) < FOREIGN_REPLIES:
            return None
        mids = tuple(sorted({mid for _t, mid in unasked}))
        count = len(unasked)
        unasked.clear()
        return Fault(FaultKind.FOREIGN_HOST, mids, (
            f"another host is driving these modules: {count} replies from modules {list(mids)} within "
            f"{FOREIGN_WINDOW_S:g} s that this driver did not ask for (a second driver or tool on this CAN "
            "bus, whatever its name or namespace); all modules halted. Stop the other one, then ~/recover"))

    def _check_foreign_host_locked(self) -> Fault | None:
        """Halt every module and enter FAULT if another host was seen (not again while already in
        FAULT for that); returns the fault."""
        fault = self._foreign_host_fault()
        if fault is None:
            return None
        if self.state is DriverState.FAULT and self.fault is not None \
                and self.fault.kind is FaultKind.FOREIGN_HOST:
            return None
        self._halt_all()
        self._fire(DriverEvent.FAULT, fault)
        logger.error("PowerCube fault, all modules halted: %s", fault.message)
        return fault

    def _reachable(self, j: int, x: float, t: float) -> bool:
        """Whether position ``x`` of joint ``j`` at clock time ``t`` passes the plausibility bounds
        (no counting: see :meth:`_plausible`)."""
        t0 = self._t_meas[j]
        if t0 != t0:
            return True
        bound = self.max_vel[j] * (max(0.0, t - t0) + self.reply_timeout_s) + self.plausibility_margin_rad
        slack = self._brake[j] + self.plausibility_margin_rad
        within_span = self._reach_lo[j] - slack <= x <= self._reach_hi[j] + slack
        return abs(x - self._q_meas[j]) <= bound and within_span

    def _note_frame(self, j: int, frame: p.Frame | None, t: float) -> None:
        """:meth:`_note_reply` for a decoded frame of joint ``j``; a malformed one, or one reporting a
        position the module cannot be at (a forgery), is no evidence of another host."""
        if frame is None:
            return
        if isinstance(frame, p.SetMoveExtAck):
            x = float(frame.position)
        elif isinstance(frame, p.GetParamReply) and frame.param is Param.ACT_FPOS:
            x = float(frame.value)
        else:
            self._note_reply(j, t)
            return
        if self._reachable(j, x, t):
            self._note_reply(j, t)

    def _recv(self, timeout: float) -> can.Message | None:
        if self._interruptible:
            return self._recv_interruptible(timeout)
        try:
            return self.bus.recv(timeout)
        except Exception as exc:
            raise self._lost(exc, "receive") from exc

    def _recv_interruptible(self, timeout: float) -> can.Message | None:
        # Short slices so that a halt requested meanwhile is acted on within about one cycle.
        while True:
            if self._halt_requested.is_set():
                raise RequestHaltedError("halt requested")
            chunk = min(timeout, HALT_POLL_S)
            try:
                msg = self.bus.recv(chunk)
            except Exception as exc:
                raise self._lost(exc, "receive") from exc
            timeout -= chunk
            if msg is not None or timeout <= 0:
                return msg

    def _route(self, msg: can.Message) -> int | None:
        """Joint index of a reply frame; a state frame is recorded here and, like a foreign id, gives None."""
        j = self._reply_index.get(msg.arbitration_id)
        if j is None:
            js = self._state_index.get(msg.arbitration_id)
            if js is not None:
                self._note_state_frame(msg, js)
        return j

    def _decode_counted(self, msg: can.Message, j: int) -> p.Frame | None:
        """Decode a frame of joint ``j``; a malformed one is counted and gives None."""
        frame = self.decoder.decode(msg)
        if frame is None:
            self.stats[j].malformed += 1
        return frame

    def _plausible(self, j: int, x: float, t: float) -> bool:
        """Whether position ``x`` (rad) of joint ``j`` measured at clock time ``t`` is reachable from
        the last accepted measurement; an implausible one is counted (and logged, rate-limited)."""
        # The velocity bound alone grows without limit while a module is silent; but a module only
        # goes where it was sent, or brakes to a stop when halted (or by its watchdog), so a module
        # restarted without its position is refused however long it was away (see _reachable).
        if self._reachable(j, x, t):
            return True
        t0, q0 = self._t_meas[j], self._q_meas[j]
        bound = self.max_vel[j] * (max(0.0, t - t0) + self.reply_timeout_s) + self.plausibility_margin_rad
        s = self.stats[j]
        s.implausible += 1
        s.consecutive_implausible += 1
        s.last_implausible = float(x)
        s.last_implausible_at = time.monotonic()
        if s.implausible == 1 or s.implausible % 100 == 0:
            logger.warning(
                "module %d: implausible position %.4f rad refused (last %.4f rad %.3f s before; at most "
                "%.4f rad reachable); %d so far", self.module_ids[j], x, q0, t - t0, bound, s.implausible)
        return False

    def _accept_position(self, j: int, x: float, t: float) -> None:
        self._q_meas[j] = x
        self._t_meas[j] = t
        # Following targets, the step in flight is reachable too; otherwise nothing moves it.
        sent = self._q_sent[j] if self.state is DriverState.READY else x
        self._reach_lo[j] = min(x, sent)
        self._reach_hi[j] = max(x, sent)
        self.stats[j].consecutive_implausible = 0

    def _note_state_frame(self, msg: can.Message, j: int) -> None:
        frame = self._decode_counted(msg, j)
        if isinstance(frame, p.StateFrame):
            self._states[j] = int(frame.state)
            if frame.state & FAULT_BITS:
                self._pending_faults[self.module_ids[j]] = frame.state

    def _drain(self) -> int:
        """Read what is already queued (stale replies of earlier cycles); returns late ext acks.

        At most :data:`_DRAIN_MAX_FRAMES` frames: on a flooded bus the rest is read (and skipped)
        by the receive loop that follows, which has a deadline."""
        late = 0
        for _ in range(_DRAIN_MAX_FRAMES):
            got = self._receive_reply(0.0)
            if got is None:
                break
            j, frame = got
            if isinstance(frame, p.SetMoveExtAck):
                self.stats[j].late += 1  # type: ignore[index]  (a decoded frame has its joint)
                late += 1
        return late

    def _receive_reply(self, timeout: float) -> tuple[int | None, p.Frame | None] | None:
        """Receive one frame within ``timeout`` s: None if none came; (None, None) for a frame that is no
        reply (a state frame is recorded on the way); else (joint index, decoded frame or None if it was
        malformed)."""
        msg = self._recv(timeout)
        if msg is None:
            return None
        j = self._route(msg)
        if j is None:
            return None, None
        frame = self._decode_counted(msg, j)
        self._note_frame(j, frame, self._clock())
        return j, frame

    def _transact(
        self,
        items: Sequence[tuple[Hashable, int, can.Message, _Matcher]],
        *,
        timeout_s: float | None = None,
        attempts: int = REQUEST_ATTEMPTS,
    ) -> dict[Hashable, p.Frame]:
        """Send requests and collect matching replies.

        ``items`` are (key, joint index, request, matcher); a reply from joint j answers the
        first pending item of j whose matcher accepts it. Missing replies are re-requested
        up to ``attempts`` times, each wait twice as long as the one before (a module process
        descheduled on a busy machine answers late, not never), with a watchdog refresh before
        each retry so that the modules already answered stay armed meanwhile. Returns key ->
        reply for the items that were answered.
        """
        timeout = self.reply_timeout_s if timeout_s is None else timeout_s
        results: dict[Hashable, p.Frame] = {}
        for attempt in range(attempts):
            todo = [it for it in items if it[0] not in results]
            if not todo:
                break
            self._drain()
            if attempt and self.watchdog_refresh:
                self._send(self._wd_refresh)
            for _key, _j, msg, _m in todo:
                self._send(msg)
            deadline = self._deadline
            deadline.start(self._clock(), timeout * 2**attempt)
            while len(results) < len(items):
                left = deadline.left()
                if left <= 0:
                    break
                got = self._receive_reply(left)
                deadline.waited(left)
                if got is None or got[1] is None:
                    continue
                j, frame = got
                for key, jj, _msg, match in todo:
                    if jj == j and key not in results and match(frame):
                        results[key] = frame
                        break
        return results

    def _require_all(self, results: dict[Hashable, p.Frame], keys: Sequence[Hashable], what: str) -> None:
        waited = self.reply_timeout_s * (2**REQUEST_ATTEMPTS - 1)
        for key in keys:
            if key not in results:
                j = key[0] if isinstance(key, tuple) else key
                mid = self.module_ids[int(j)]  # type: ignore[arg-type]
                raise BusTimeoutError(
                    f"module {mid} did not answer {what} ({REQUEST_ATTEMPTS} requests, "
                    f"{waited:.3f} s of waiting)",
                    module_id=mid,
                    timeout_s=waited,
                )

    def _command_all(self, cmd: Command, *, require: bool = True,
                     attempts: int = REQUEST_ATTEMPTS) -> list[int]:
        items = [(j, j, p.command(mid, cmd), _is_ack(cmd)) for j, mid in enumerate(self.module_ids)]
        res = self._transact(items, attempts=attempts)
        if require:
            self._require_all(res, list(range(self.n)), cmd.name)
        return [self.module_ids[j] for j in range(self.n) if j in res]

    def _halt_all(self) -> list[int]:
        """HALT every module (acks collected, not required) and broadcast haltAll as a backstop."""
        acked = self._command_all(Command.HALT, require=False, attempts=1)
        self._send(self._halt_all_msg)
        return acked

    def _read_state_locked(self) -> ArmState:
        items = []
        for j, mid in enumerate(self.module_ids):
            items.append(((j, "state"), j, p.get_param(mid, Param.ACT_STATE), _is_param(Param.ACT_STATE)))
            items.append(((j, "pos"), j, p.get_param(mid, Param.ACT_FPOS), self._is_plausible_fpos(j)))
        implausible0 = [s.implausible for s in self.stats]
        res = self._transact(items)
        for j in range(self.n):
            if (j, "pos") not in res and self.stats[j].implausible > implausible0[j]:
                s = self.stats[j]
                raise ImplausibleMeasurementError(
                    f"module {self.module_ids[j]} reports an implausible position "
                    f"{s.last_implausible:.4f} rad (last measured {self._q_meas[j]:.4f} rad); if the module "
                    "was power-cycled without its position, call ~/init to re-home it",
                    module_id=self.module_ids[j], value=s.last_implausible,
                )
        self._require_all(res, [it[0] for it in items], "GETPARAM ACT_STATE/ACT_FPOS")
        t = self._clock()
        for j in range(self.n):
            self._accept_position(j, float(res[(j, "pos")].value), t)  # type: ignore[attr-defined]
        states = [ActState(int(res[(j, "state")].value)) for j in range(self.n)]  # type: ignore[attr-defined]
        self._states[:] = [int(s) for s in states]
        self._needs_resync = False
        self._prev_stamp = None
        return ArmState(self._q_meas.copy(), states)

    def _is_plausible_fpos(self, j: int) -> _Matcher:
        def match(f: p.Frame) -> bool:
            return (isinstance(f, p.GetParamReply) and f.param is Param.ACT_FPOS
                    and self._plausible(j, float(f.value), self._clock()))

        return match

    def _hold_measured(self) -> None:
        self._q_cmd[:] = self._q_meas
        self._q_sent[:] = self._q_meas
        self._reach_lo[:] = self._q_meas
        self._reach_hi[:] = self._q_meas
        for s in self.stats:
            s.consecutive_misses = 0
            s.consecutive_implausible = 0
            s.silent = False

    # ------------------------------------------------------------------------------------------
    # public API
    # ------------------------------------------------------------------------------------------

    def discover(self) -> DiscoveryReport:
        """Scan the configured ids with GETPARAM DEF_VERSION (as the vendor library does).

        Raises:
            BusError: the bus failed.
        """
        with self._lock:
            items = [
                (j, j, p.get_param(mid, Param.DEF_VERSION), _is_param(Param.DEF_VERSION))
                for j, mid in enumerate(self.module_ids)
            ]
            res = self._transact(items, timeout_s=max(self.reply_timeout_s, 0.1), attempts=2)
            found = {self.module_ids[j]: int(f.value) for j, f in res.items()}  # type: ignore[attr-defined]
            missing = [mid for mid in self.module_ids if mid not in found]
            if missing:
                logger.warning("PowerCube modules not answering discovery: %s", missing)
            return DiscoveryReport(found, missing)

    def read_state(self) -> ArmState:
        """Read ACT_STATE and ACT_FPOS of every module (no motion).

        Raises:
            BusTimeoutError: a module did not answer (after :data:`REQUEST_ATTEMPTS` requests).
            BusError: the bus failed.
        """
        with self._lock:
            st = self._read_state_locked()
            fault = self._check_foreign_host_locked()
            if fault is not None:
                raise ForeignHostError(fault)
            return st

    def init(self, *, home: bool = True) -> ArmState:
        """Configure, reset and home every module, then hold the measured position.

        Sets SYNC_MOTION (and WATCHDOG_ENABLE if asked) in ACT_CONFIG, clears DISABLE_ACK, writes
        ACT_FMAXVEL/ACT_FMAXACC, RESETs, HOMEs and polls ACT_STATE until every module has
        HOME_OK (``home_timeout_s``). Homing establishes the positions anew: the plausibility
        check starts from the positions read at the end.

        :meth:`request_halt` (from another thread) stops it within about one cycle: every module is
        halted and :class:`RequestHaltedError` ("halted during homing") raised.

        Raises:
            RequestHaltedError: a halt was requested meanwhile (every module halted).
            BusTimeoutError: a module did not answer, or homing did not finish in time.
            ModuleFaultError: a module is in error after reset or homing.
            BusError: the bus failed.
        """
        with self._lock:
            self._fire(DriverEvent.INIT_STARTED)
            self.initialised = False
            self._t_meas[:] = math.nan
            with self._interruptible_locked("init"):
                self._configure_locked()
                self._command_all(Command.RESET)
            if home:
                with self._interruptible_locked("homing"):
                    self._home_locked()
            st = self._ready_locked("init", "PowerCube arm initialised at %s")
            self._home_ok_at_init = [bool(s & ActState.HOME_OK) for s in st.states]
            self.initialised = True
            return st

    def _ready_locked(self, what: str, log_format: str, *, require_home: bool = False) -> ArmState:
        """End of init/recover: read the state, refuse on module errors (``what`` names the step in
        the exception) and, with ``require_home``, on modules without HOME_OK; hold the measured
        position, clear pending faults, READY."""
        st = self._read_state_locked()
        self._raise_on_errors(st, what)
        if require_home:
            # A module that had HOME_OK after init and lacks it now was restarted (power-cycled).
            states = zip(self.module_ids, st.states, self._home_ok_at_init, strict=True)
            lost = [mid for mid, s, homed in states if homed and not s & ActState.HOME_OK]
            if lost:
                # A module without HOME_OK was power-cycled: its position is not established any more.
                self.initialised = False
                self._halt_all()
                self._fire(DriverEvent.HALT)
                raise ModuleFaultError(
                    f"{what} refused: modules {lost} report no HOME_OK (restarted without their "
                    "position?); call ~/init to home them", module_id=lost[0],
                    state=int(st.states[self.module_ids.index(lost[0])]))
        self._hold_measured()
        self._pending_faults.clear()
        self._fire(DriverEvent.READY)
        logger.info(log_format, np.round(st.positions, 4).tolist())
        return st

    def _configure_locked(self) -> None:
        want_set = ActConfig(0)
        if self.sync_motion:
            want_set |= ActConfig.SYNC_MOTION
        if self.enable_watchdog:
            want_set |= ActConfig.WATCHDOG_ENABLE
        want_clear = ActConfig.DISABLE_ACK
        if not self.sync_motion:
            want_clear |= ActConfig.SYNC_MOTION
        items = [
            (j, j, p.get_param(mid, Param.ACT_CONFIG), _is_param(Param.ACT_CONFIG))
            for j, mid in enumerate(self.module_ids)
        ]
        res = self._transact(items)
        self._require_all(res, list(range(self.n)), "GETPARAM ACT_CONFIG")
        sets = []
        for j, mid in enumerate(self.module_ids):
            cfg = (int(res[j].value) | int(want_set)) & ~int(want_clear)  # type: ignore[attr-defined]
            sets.append(
                ((j, "cfg"), j, p.set_param(mid, Param.ACT_CONFIG, cfg), _is_setparam_ack(Param.ACT_CONFIG))
            )
            sets.append(
                ((j, "vel"), j, p.set_param(mid, Param.ACT_FMAXVEL, float(self.max_vel[j])),
                 _is_setparam_ack(Param.ACT_FMAXVEL))
            )  # fmt: skip
            sets.append(
                ((j, "acc"), j, p.set_param(mid, Param.ACT_FMAXACC, float(self.max_acc[j])),
                 _is_setparam_ack(Param.ACT_FMAXACC))
            )  # fmt: skip
        # Acks may be suppressed by a DISABLE_ACK left on: verify by reading back instead. A late
        # reply to an earlier (retried) read may still be on its way with the old value: the
        # read-back waits for a value that took; only if none comes is the plain value judged.
        self._transact(sets, attempts=1)

        def took(cfg: int) -> bool:
            return (cfg & int(want_set)) == int(want_set) and not cfg & int(want_clear)

        def reads_took(f: p.Frame) -> bool:
            return isinstance(f, p.GetParamReply) and f.param is Param.ACT_CONFIG and took(int(f.value))

        res = self._transact([(j, j, msg, reads_took) for j, _j, msg, _m in items])
        res.update(self._transact([it for it in items if it[0] not in res]))  # only the ones still wrong
        self._require_all(res, list(range(self.n)), "GETPARAM ACT_CONFIG")
        for j, mid in enumerate(self.module_ids):
            cfg = int(res[j].value)  # type: ignore[attr-defined]
            if not took(cfg):
                raise ModuleFaultError(
                    f"module {mid} did not take ACT_CONFIG 0x{cfg:08x}", module_id=mid, state=cfg
                )

    def _home_locked(self) -> None:
        self._command_all(Command.HOME)
        deadline = self._clock() + self.home_timeout_s
        while True:
            if self.watchdog_refresh:
                self._send(self._wd_refresh)
            items = [
                (j, j, p.get_param(mid, Param.ACT_STATE), _is_param(Param.ACT_STATE))
                for j, mid in enumerate(self.module_ids)
            ]
            res = self._transact(items)
            self._require_all(res, list(range(self.n)), "GETPARAM ACT_STATE")
            states = [ActState(int(res[j].value)) for j in range(self.n)]  # type: ignore[attr-defined]
            self._raise_on_errors(ArmState(self._q_meas.copy(), states), "homing")
            if all(s & ActState.HOME_OK for s in states):
                return
            if self._clock() > deadline:
                slow = [self.module_ids[j] for j, s in enumerate(states) if not s & ActState.HOME_OK]
                raise BusTimeoutError(
                    f"modules {slow} did not report HOME_OK within {self.home_timeout_s} s",
                    module_id=slow[0],
                    timeout_s=self.home_timeout_s,
                )
            self._sleep(self.poll_interval_s)

    def _sleep(self, seconds: float) -> None:
        # Waiting on the bus keeps a fake clock in step in tests and drains traffic meanwhile.
        end = self._clock() + seconds
        while (left := end - self._clock()) > 0:
            msg = self._recv(left)
            if msg is not None:
                j = self._route(msg)  # records state frames; replies here are stale and dropped
                if j is not None:
                    self._note_frame(j, self._decode_counted(msg, j), self._clock())

    def _raise_on_errors(self, st: ArmState, during: str) -> None:
        errs = st.errors
        if errs:
            j, bits = next(iter(errs.items()))
            mid = self.module_ids[j]
            names = fault_bit_names(st.states[j])
            raise ModuleFaultError(
                f"module {mid} in error during {during}: {names}", module_id=mid, state=int(bits)
            )

    def halt(self) -> list[int]:
        """HALT every module (and broadcast haltAll); cycles then only hold and poll.

        Returns:
            The module ids that acknowledged the HALT.

        Raises:
            BusError: the bus failed.
        """
        with self._lock:
            acked = self._halt_all()
            self._fire(DriverEvent.HALT)
            self._halt_requested.clear()  # served: a later init/recover runs normally
            logger.warning("PowerCube arm halted (acknowledged by %s)", acked)
            return acked

    def request_halt(self) -> None:
        """Any thread, without waiting for the driver's lock: make an :meth:`init` or :meth:`recover`
        in progress (or starting next) stop within about one cycle: it HALTs every module and raises
        :class:`RequestHaltedError`. Cleared by :meth:`halt` (or :meth:`clear_halt_request`)."""
        self._halt_requested.set()

    def clear_halt_request(self) -> None:
        """Forget a :meth:`request_halt` that will not be followed by :meth:`halt` (e.g. refused)."""
        self._halt_requested.clear()

    @contextmanager
    def _interruptible_locked(self, what: str) -> Iterator[None]:
        """Run a step of init/recover so that :meth:`request_halt` stops it: every module is halted
        at once and :class:`RequestHaltedError` ("halted during ``what``") raised."""
        self._interruptible = True
        try:
            yield
        except RequestHaltedError:
            self._interruptible = False
            acked = self._halt_all()
            self._fire(DriverEvent.HALT)
            logger.warning("PowerCube arm halted during %s (acknowledged by %s)", what, acked)
            raise RequestHaltedError(f"halted during {what}; all modules halted") from None
        finally:
            self._interruptible = False

    def recover(self) -> ArmState:
        """Bring every module back as :meth:`init` left it, without homing; hold the measured position.

        HALTs every module and waits until the arm is at rest (no module reports MOTION, the
        positions settled), so what is held is where the arm stopped, not a reading taken while it
        braked. RESETs every module (clears ERROR, HALTED and the causes), then restores what a module
        that was power-cycled meanwhile has lost: ACT_CONFIG (SYNC_MOTION, WATCHDOG_ENABLE when the
        watchdog is on, no DISABLE_ACK) and ACT_FMAXVEL/ACT_FMAXACC; re-reads the positions (checked
        for plausibility) and holds them (READY again). Refused unless :meth:`init` succeeded
        before; a module that had HOME_OK after init and lacks it now (restarted, its position
        lost) makes it fail with every module halted, and only :meth:`init` (re-homing) helps.
        :meth:`request_halt` stops it at once.

        Raises:
            RequestRefusedError: never initialised (nothing was sent).
            RequestHaltedError: a halt was requested meanwhile (every module halted).
            BusTimeoutError: a module did not answer.
            ModuleFaultError: a module is still in error after the reset, refused the configuration,
                lost HOME_OK, or reports an implausible position (:class:`ImplausibleMeasurementError`).
            BusError: the bus failed.
        """
        with self._lock:
            if not self.initialised:
                # Without homing the positions are not established: never make such an arm movable.
                raise RequestRefusedError(
                    "recover refused: the arm was never initialised (homed); call ~/init")
            with self._interruptible_locked("recover"):
                # A moving arm first brakes to rest, and that rest is what is held: taken mid-brake,
                # the hold would drive the arm back by its braking distance (0.1-0.24 rad seen).
                self._halt_all()
                self._settle_locked()
                self._command_all(Command.RESET)
                self._configure_locked()
            return self._ready_locked("recover", "PowerCube arm recovered, holding %s", require_home=True)

    def _settle_locked(self) -> None:
        """Poll the modules until none reports MOTION and the positions agree with the previous read
        within :data:`SETTLE_TOLERANCE_RAD`.

        Raises:
            ModuleFaultError: still moving after the longest braking time plus :data:`SETTLE_EXTRA_S`.
            BusTimeoutError, ImplausibleMeasurementError, BusError: from the state reads.
        """
        vel, acc = np.asarray(self.limits.max_vel, dtype=float), np.asarray(self.limits.max_acc, dtype=float)
        end = self._clock() + float(np.max(vel / acc)) + SETTLE_EXTRA_S
        prev: np.ndarray | None = None
        while True:
            st = self._read_state_locked()
            moving = [mid for mid, bits in zip(self.module_ids, st.states, strict=True)
                      if bits & ActState.MOTION]
            settled = prev is not None and np.max(np.abs(st.positions - prev)) <= SETTLE_TOLERANCE_RAD
            if not moving and settled:
                return
            if self._clock() > end:
                raise ModuleFaultError(f"recover: modules {moving or self.module_ids} did not come to rest "
                                       "after the halt", module_id=(moving or self.module_ids)[0])
            prev = st.positions
            self._sleep(self.poll_interval_s)

    def reconnect(self) -> ArmState:
        """Reopen the bus (one attempt; call again with backoff) and re-read the positions.

        The held target becomes the measured position: nothing commanded before the loss is
        sent again.

        Raises:
            BusError: the bus cannot be reopened (or has no ``reopen``), or failed again.
            BusTimeoutError: a module did not answer after reopening.
        """
        with self._lock:
            reopen = getattr(self.bus, "reopen", None)
            if reopen is None:
                raise BusError("this bus cannot be reopened; open a new one and a new driver")
            self._needs_resync = True
            reopen()
            st = self._read_state_locked()
            self._hold_measured()
            return st

    # ------------------------------------------------------------------------------------------
    # the cycle
    # ------------------------------------------------------------------------------------------

    def _check_target(self, q_target: Sequence[float] | np.ndarray) -> np.ndarray:
        q = np.asarray(q_target, dtype=float)
        if q.shape != (self.n,):
            raise InvalidInputError(
                f"target must have shape ({self.n},), got {q.shape}", field="q_target", value=q
            )
        bad = ~np.isfinite(q)
        if bad.any():
            j = int(np.argmax(bad))
            raise InvalidInputError(
                f"target of joint {j} (module {self.module_ids[j]}) is not finite: {q[j]}",
                field="q_target",
                value=q,
            )
        return q

    def cycle(self, q_target: Sequence[float] | np.ndarray | None, dt_s: float) -> CycleResult:
        """One control cycle: FSTEP_EXT to every joint (duration ``dt_s``), STARTMOVE, collect replies.

        ``q_target`` (n,) rad, or None to hold the last commanded target. In HALTED/FAULT the
        target is ignored and the measured position is held (a poll).

        Raises:
            InvalidInputError: NaN/inf/wrong-shaped target or bad ``dt_s`` (nothing was sent).
            RedarmError: the driver was never initialised (call :meth:`init` or :meth:`recover`).
            BusTimeoutError: a module just reached ``max_missed`` consecutive misses (every
                module was halted; ``exc.cycle_result`` holds this cycle's result).
            BusError: the bus failed (reopen it, e.g. with :meth:`reconnect`).
        """
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
            raise InvalidInputError(f"dt_s must be a positive number of seconds, got {dt_s!r}", field="dt_s")
        q_in = None if q_target is None else self._check_target(q_target)
        with self._lock:
            if self.state is DriverState.UNINITIALIZED:
                raise RedarmError("PowerCube driver not initialised: call init() (or recover()) first")
            resynced = False
            if self._needs_resync:
                self._read_state_locked()
                self._q_cmd[:] = self._q_meas
                resynced = True
            return self._cycle_locked(q_in, float(dt_s), resynced)

    def _cycle_locked(self, q_in: np.ndarray | None, dt: float, resynced: bool) -> CycleResult:
        n = self.n
        holding = self.state is not DriverState.READY
        lim_mask = step_mask = self._no_joints
        clamped: tuple[int, ...] = ()
        if holding:
            q = self._q_meas.copy()
        elif q_in is None or resynced:
            q = self._q_cmd.copy()
        else:
            # Into the limits, then within one step at max_vel of the last target: joint by joint on
            # floats (a clip as numpy's: ``x if x > lo else lo``, then ``y if y < hi else hi``).
            q_list, at_limit, stepped = [], [], []
            joints = zip(q_in.tolist(), self._lower_list, self._upper_list, self._q_cmd.tolist(),
                         self._max_vel_list, strict=True)
            for x, lo, hi, last, vmax in joints:
                y = x if x > lo else lo
                y = y if y < hi else hi
                step = vmax * dt
                z = y if y > last - step else last - step
                z = z if z < last + step else last + step
                q_list.append(z)
                at_limit.append(y != x)
                stepped.append(z != y)
            q = np.array(q_list)
            if True in at_limit or True in stepped:
                lim_mask, step_mask = np.array(at_limit), np.array(stepped)
                clamped = tuple(j for j in range(n) if at_limit[j] or stepped[j])
        ms = min(0xFFFF, max(1, round(dt * 1000.0)))

        late = self._drain()
        malformed0 = self.decoder.malformed
        self._q_sent[:] = q
        np.minimum(self._reach_lo, q, out=self._reach_lo)
        np.maximum(self._reach_hi, q, out=self._reach_hi)
        clock = self._clock
        patch = p.patch_fstep
        batch = self._fstep_msgs[:n]
        for j, x in enumerate(q.tolist()):
            patch(batch[j], x, ms)
        batch.append(self._startmove)
        if self.watchdog_refresh:
            batch.append(self._wd_refresh)
        stamp = self._send_many(batch)

        # Per joint in lists while the replies come in (seven scalar writes each, not numpy item
        # writes); arrays once for the result.
        replied = [False] * n
        latency = [math.nan] * n
        short = [0] * n
        remaining = n
        implausible = 0
        deadline = self._deadline
        deadline.start(stamp, self.reply_timeout_s)
        fstep_ack = p.fstep_ext_ack_fields
        while remaining:
            left = deadline.left()
            if left <= 0:
                break
            msg = self._recv(left)
            deadline.waited(left)
            if msg is None:
                continue
            t = clock()
            j = self._route(msg)
            if j is None:
                continue
            fields = fstep_ack(msg)
            if fields is None:  # anything else: full decode (counts malformed frames)
                self._note_frame(j, self._decode_counted(msg, j), t)
                continue
            if replied[j]:  # a second ack in one cycle: the first was a late one
                self.stats[j].late += 1
                late += 1
                if self._reachable(j, fields[0], t):
                    self._note_reply(j, t)
                continue
            if not self._plausible(j, fields[0], t):
                implausible += 1  # never taken as the arm's state; a genuine reply may still come
                continue
            self._note_reply(j, t)
            replied[j] = True
            remaining -= 1
            self._accept_position(j, fields[0], t)
            short[j] = fields[1]
            latency[j] = t - stamp

        # bookkeeping
        lost = 0
        silent: list[int] = []
        for j, s in enumerate(self.stats):
            if replied[j]:
                s.replies += 1
                s.consecutive_misses = 0
                s.silent = False
                s.add_latency(latency[j])
                # keep the long-only bits (HOME_OK, causes) from the last full read
                self._states[j] = (int(self._states[j]) & _LONG_ONLY) | p.LONG_BITS_OF_SHORT[short[j]]
            else:
                s.lost += 1
                lost += 1
                s.consecutive_misses += 1
                if s.consecutive_misses >= self.max_missed and not s.silent:
                    s.silent = True
                    silent.append(j)
        if self._prev_stamp is not None and stamp > self._prev_stamp and self._prev_q is not None:
            vel = (self._q_meas - self._prev_q) / (stamp - self._prev_stamp)
        else:
            vel = np.zeros(n)
        self._prev_stamp = stamp
        self._prev_q = self._q_meas.copy()
        if not holding:
            self._q_cmd[:] = q

        result = CycleResult(
            stamp=stamp,
            positions=self._q_meas.copy(),
            velocities=vel,
            targets=q,
            states=self._states.copy(),
            replied=np.array(replied, dtype=bool),
            latency_s=np.array(latency),
            clamped=clamped,
            clamped_to_limits=lim_mask.copy(),
            clamped_step=step_mask.copy(),
            lost=lost,
            late=late,
            malformed=self.decoder.malformed - malformed0,
            implausible=implausible,
            holding=holding,
            resynced=resynced,
        )
        foreign = self._check_foreign_host_locked()
        if foreign is not None:
            result.fault = foreign
            self._pending_faults.clear()
            return result
        if self.state is DriverState.FAULT:
            self._pending_faults.clear()
            return result

        # faults: ERROR in a short state, or a state frame with fault bits
        faults = dict(self._pending_faults)
        self._pending_faults.clear()
        errored = [j for j in range(n) if short[j] & _SHORT_ERROR]
        if errored or faults:
            self._halt_all()
            for j in errored:
                faults.setdefault(self.module_ids[j], self._full_state(j))
            text = "; ".join(f"module {mid}: {fault_bit_names(bits)}" for mid, bits in sorted(faults.items()))
            self._raise_fault(result, Fault(FaultKind.MODULE_ERROR, tuple(sorted(faults)), text, faults))
            return result

        if silent:
            self._halt_all()
            bad = [j for j in silent if self.stats[j].consecutive_implausible > 0]
            if bad:
                mids = tuple(self.module_ids[j] for j in bad)
                st = self.stats[bad[0]]
                self._raise_fault(result, Fault(
                    FaultKind.IMPLAUSIBLE, mids,
                    f"module {mids[0]} reports implausible positions ({st.last_implausible:.4f} rad, last "
                    f"plausible {self._q_meas[bad[0]]:.4f} rad; {self.max_missed} replies refused)"))
                return result
            mid = self.module_ids[silent[0]]
            self._raise_fault(result, Fault(
                FaultKind.SILENT, tuple(self.module_ids[j] for j in silent),
                f"module {mid} stopped answering ({self.max_missed} replies missed)"))
            err = BusTimeoutError(
                f"module {mid} missed {self.max_missed} consecutive replies "
                f"(timeout {self.reply_timeout_s:.3f} s each); all modules halted",
                module_id=mid,
                timeout_s=self.reply_timeout_s,
            )
            err.cycle_result = result  # type: ignore[attr-defined]
            raise err
        return result

    def _raise_fault(self, result: CycleResult, fault: Fault) -> None:
        """Enter FAULT (every module already halted) and put ``fault`` in ``result``."""
        self._fire(DriverEvent.FAULT, fault)
        result.fault = fault
        logger.error("PowerCube fault, all modules halted: %s", fault.message)

    def _full_state(self, j: int) -> ActState:
        """ACT_STATE of joint j read with GETPARAM (to learn the cause behind a short ERROR bit)."""
        mid = self.module_ids[j]
        res = self._transact(
            [(j, j, p.get_param(mid, Param.ACT_STATE), _is_param(Param.ACT_STATE))], attempts=1
        )
        if j in res:
            st = ActState(int(res[j].value))  # type: ignore[attr-defined]
            self._states[j] = int(st)
            return st & REPORTED_BITS or ActState.ERROR
        return ActState.ERROR
