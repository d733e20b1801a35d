"""Keep a time-critical thread or process from being starved: scheduling priority and garbage collection.

Linux only for the priority part (elsewhere it reports "not supported"). Used by the CAN driver's
cycle (:mod:`redarm_ros.can.driver_process`, :class:`~redarm_ros.can.driver_loop.DriverLoop`), the
simulator (``redarm-sim``) and the loopback bus server (``redarm-canbus``): the chain that must
answer within milliseconds while the rest of the machine may be busy.

:func:`raise_priority` asks for ``SCHED_FIFO`` at a given priority (a real-time thread runs as soon
as it is runnable, ahead of every normal task); when that is not permitted (no ``CAP_SYS_NICE``,
``RLIMIT_RTPRIO`` 0, or a container without real-time budget) it falls back to the highest nice
level it may take, and says so in the returned :class:`Priority`, whose ``message`` is the one line
to log. Threads created afterwards inherit the setting, so call it before starting helper threads.

:func:`freeze_gc` collects once and freezes everything allocated so far: start-up objects (modules,
classes, the arm model) are never scanned again, so a full collection later only looks at what was
made since, and takes a fraction of a millisecond instead of tens. :func:`quiet_gc` also turns
automatic collection off for a cycle; its owner then calls :func:`collect_young` when it has time to
spare.

:func:`request_slice` asks the kernel for a shorter time slice for a normal (SCHED_OTHER) thread
(Linux 6.12 or later, no privilege needed): a thread woken by a frame then gets the CPU sooner,
while its share of the CPU and its nice level stay as they are.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import gc
import logging
import os
import resource
import signal
import sys
from dataclasses import dataclass
from enum import Enum
from typing import Any

__all__ = [
    "DEFAULT_SLICE_MS", "Policy", "Priority", "Slice", "collect_young", "drop_priority", "freeze_gc",
    "quiet_gc", "raise_nice", "raise_priority", "raise_process_priority", "request_slice", "restore_gc",
    "scheduling_now", "thread_slice_ms",
]

_LOG = logging.getLogger(__name__)

#: The nice level tried when SCHED_FIFO is refused (-20 is the highest priority; a normal task is 0).
FALLBACK_NICE = -10
_PR_SET_NAME = 15  # <linux/prctl.h>
#: Time slice (ms) the threads on the reply path (bus server relay, simulator bus thread, driver cycle)
#: ask for unless told otherwise; 0 leaves the kernel's default (0.7 ms times 1 + log2 of the CPUs).
#: Longer than those threads' CPU per wake-up (0.1-0.4 ms), so a reply is rarely cut short, and shorter
#: than the default, so a woken thread gets a CPU sooner (benchmarks/slice_bench.py: 0.1 and 0.5 ms
#: alike on round trips of 20 ms or more, 0.1 ms slower on 1 ms of work).
DEFAULT_SLICE_MS = 0.5
_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}  # <asm/unistd.h>
_SYS_SCHED_GETATTR = {"x86_64": 315, "aarch64": 275}
_SCHED_OTHER = 0


class _SchedAttr(ctypes.Structure):
    """``struct sched_attr`` (<linux/sched/types.h>, SCHED_ATTR_SIZE_VER1: 56 bytes)."""

    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32),
                ("sched_flags", ctypes.c_uint64),
                ("sched_nice", ctypes.c_int32), ("sched_priority", ctypes.c_uint32),
                ("sched_runtime", ctypes.c_uint64), ("sched_deadline", ctypes.c_uint64),
                ("sched_period", ctypes.c_uint64), ("sched_util_min", ctypes.c_uint32),
                ("sched_util_max", ctypes.c_uint32)]


class Policy(Enum):
    """What :func:`raise_priority` obtained."""

    FIFO = "SCHED_FIFO"
    NICE = "nice"
    NORMAL = "normal"


@dataclass(frozen=True)
class Priority:
    """The scheduling a thread ended up with: ``policy``, ``value`` (FIFO priority or nice level)
    and ``message`` (one line saying what was asked for, what was obtained and why)."""

    policy: Policy
    value: int
    message: str

    @property
    def realtime(self) -> bool:
        """True for SCHED_FIFO."""
        return self.policy is Policy.FIFO


def raise_priority(fifo_priority: int, *, who: str, tid: int = 0) -> Priority:
    """Give the calling thread (or thread/process ``tid``) SCHED_FIFO at ``fifo_priority`` (1..99).

    Falls back to nice :data:`FALLBACK_NICE` (or the best level allowed), then to leaving the
    scheduling alone. ``fifo_priority`` 0 asks for nothing (normal scheduling, by choice). ``who``
    names the thread in the message.

    Never raises; the outcome is in the returned :class:`Priority` (log its ``message`` once).
    """
    prio, not_asked = _fifo_level(fifo_priority, who)
    if not_asked is not None:
        return not_asked
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(prio))
        return Priority(Policy.FIFO, prio, f"{who}: real-time scheduling SCHED_FIFO priority {prio}")
    except OSError as exc:
        fifo_error = exc
    # Fallback: the highest nice level this process may take (RLIMIT_NICE, or CAP_SYS_NICE).
    for level in range(FALLBACK_NICE, 0):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, level)
        except OSError:
            continue
        return Priority(Policy.NICE, level, (
            f"{who}: SCHED_FIFO refused ({fifo_error.strerror}); running at nice {level} instead: the cycle "
            "can be delayed when the machine is busy (grant CAP_SYS_NICE or an rtprio limit for real-time)"))
    return Priority(Policy.NORMAL, 0, (
        f"{who}: SCHED_FIFO refused ({fifo_error.strerror}) and no higher nice level allowed; running at "
        "normal priority: the cycle can be delayed when the machine is busy (grant CAP_SYS_NICE or an "
        "rtprio limit, e.g. in /etc/security/limits.conf)"))


def _fifo_level(fifo_priority: int, who: str) -> tuple[int, Priority | None]:
    """The SCHED_FIFO level to ask for (1..max), or the normal-scheduling outcome when none is to
    be asked for (0 requested, or no SCHED_FIFO on this platform)."""
    if fifo_priority <= 0:
        return 0, Priority(Policy.NORMAL, 0, f"{who}: normal scheduling (real-time priority not requested)")
    if not hasattr(os, "sched_setscheduler"):
        return 0, Priority(Policy.NORMAL, 0, f"{who}: normal scheduling (no SCHED_FIFO on this platform)")
    return max(1, min(int(fifo_priority), os.sched_get_priority_max(os.SCHED_FIFO))), None


def name_thread(name: str) -> None:
    """Give the calling thread ``name`` (at most 15 bytes) as the kernel shows it (``/proc/*/task/*/comm``,
    ``top -H``), so a scheduling trace says which thread waited. Linux only; never raises."""
    try:
        libc = ctypes.CDLL(None)
        libc.prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):
        pass


@dataclass(frozen=True)
class Slice:
    """What :func:`request_slice` obtained: ``ms`` (the thread's slice now, 0 where unknown), whether
    it is the one asked for (``applied``), whether the kernel refused or changed it (``refused``: log
    the ``message`` as a warning; otherwise as information)."""

    applied: bool
    ms: float
    message: str
    refused: bool = False


def _sched_attr_call(name: str, tid: int, attr: _SchedAttr) -> int:
    """sched_setattr / sched_getattr (no libc wrapper); 0 or the errno (ENOSYS where unknown)."""
    number = (_SYS_SCHED_SETATTR if name == "set" else _SYS_SCHED_GETATTR).get(os.uname().machine)
    if number is None or not sys.platform.startswith("linux"):
        return errno.ENOSYS
    libc = ctypes.CDLL(None, use_errno=True)
    args = (number, tid, ctypes.byref(attr), 0) if name == "set" else (
        number, tid, ctypes.byref(attr), ctypes.sizeof(attr), 0)
    return 0 if libc.syscall(*args) == 0 else ctypes.get_errno()


def thread_slice_ms(tid: int = 0) -> float:
    """The time slice (ms) of thread ``tid`` (0: the caller) as the kernel reports it (its default
    when none was asked for), or 0 where it does not say (older kernel, not Linux, real-time)."""
    attr = _SchedAttr()
    if _sched_attr_call("get", tid, attr) or attr.sched_policy != _SCHED_OTHER:
        return 0.0
    return attr.sched_runtime / 1e6


def request_slice(slice_ms: float, *, who: str, tid: int = 0) -> Slice:
    """Ask for a time slice of ``slice_ms`` (kernel range 0.1..100 ms) for thread ``tid`` (0: the
    caller; threads it starts later inherit it). For a normal (SCHED_OTHER) thread that sleeps until
    a frame arrives: Linux (6.12+, EEVDF) gives a thread with a shorter slice an earlier deadline, so
    it gets a CPU sooner when woken, at the same CPU share; policy and nice level are kept. No
    privilege is needed. ``slice_ms`` 0 asks for nothing; a real-time (SCHED_FIFO) thread is left
    alone (it has no slice). Never raises; the outcome is in the returned :class:`Slice` (log its
    ``message`` once): a kernel that refuses (older than 6.12: the value is ignored or EINVAL;
    ENOSYS; EPERM) leaves the thread as it was."""
    if slice_ms <= 0:
        return Slice(False, thread_slice_ms(tid), f"{who}: kernel's default time slice (none requested)")
    attr = _SchedAttr()
    err = _sched_attr_call("get", tid, attr)
    if err:
        return Slice(False, 0.0, f"{who}: time slice {slice_ms:g} ms not requested (sched_getattr: "
                                 f"{os.strerror(err)})", refused=True)
    if attr.sched_policy != _SCHED_OTHER:
        return Slice(False, 0.0, f"{who}: real-time scheduling, no time slice to shorten")
    want_ns = int(round(slice_ms * 1e6))
    # Policy and nice as they are (a raised nice level stays); only the slice changes.
    new = _SchedAttr(size=ctypes.sizeof(_SchedAttr), sched_policy=_SCHED_OTHER, sched_nice=attr.sched_nice,
                     sched_runtime=want_ns)
    err = _sched_attr_call("set", tid, new)
    now_ms = thread_slice_ms(tid)
    if err:
        return Slice(False, now_ms, f"{who}: time slice {slice_ms:g} ms refused ({os.strerror(err)}); "
                                    f"kernel's default ({now_ms:g} ms)", refused=True)
    if abs(now_ms * 1e6 - want_ns) > 1000:  # clamped to 0.1..100 ms, or ignored by an older kernel
        return Slice(False, now_ms, f"{who}: time slice {slice_ms:g} ms asked, the kernel set {now_ms:g} ms",
                     refused=True)
    return Slice(True, now_ms, f"{who}: time slice {now_ms:g} ms (shorter than the kernel's default: "
                               "woken sooner, same CPU share)")


class PerSecondLimit:
    """At most ``per_second`` events in each wall-clock second: for log lines about slow events, which
    come in bursts when a process is starved (the count restarts when the second changes)."""

    def __init__(self, per_second: int) -> None:
        self.per_second = per_second
        self._second = 0
        self._count = 0

    def allow(self, wall: float) -> bool:
        """Count an event at wall time ``wall`` (s); True if it is within this second's allowance."""
        second = int(wall)
        if second != self._second:
            self._second, self._count = second, 0
        self._count += 1
        return self._count <= self.per_second


class ThreadSchedstat:
    """The scheduler statistics of the thread that made it (Linux ``/proc/thread-self/schedstat``),
    read with one system call: :meth:`read` -> (ms on a CPU, ms waiting in the run queue) since that
    thread began; (0, 0) where the kernel does not say, or for ``path=None`` (a placeholder)."""

    def __init__(self, path: str | None = "/proc/thread-self/schedstat") -> None:
        self._fd: int | None = None
        if path is not None:
            with contextlib.suppress(OSError):
                self._fd = os.open(path, os.O_RDONLY)

    def read(self) -> tuple[float, float]:
        if self._fd is None:
            return 0.0, 0.0
        try:
            ran, queued = os.pread(self._fd, 96, 0).split()[:2]
            return int(ran) / 1e6, int(queued) / 1e6
        except (OSError, ValueError):
            return 0.0, 0.0

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _thread_ids() -> list[int]:
    """This process's threads (Linux), or ``[0]`` (the caller) where they cannot be listed."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


#: CPU time (s) a real-time thread of :func:`raise_process_priority` may use without blocking before
#: it is demoted (SIGXCPU, RLIMIT_RTTIME soft limit), and before the kernel kills the process (the
#: hard limit: a thread stuck in native code never runs the demoting handler). A control loop blocks
#: every period; its longest legitimate stretch (a re-planner's slice, a scene of thousands of
#: obstacles, a full garbage collection) took up to about 0.25 s on a 2-core machine.
RT_BUDGET_S = (1.0, 3.0)


def _demote_on_sigxcpu(who: str, soft_s: float) -> Any:
    """Install the SIGXCPU handler: every thread back to normal scheduling, one line on stderr.
    Returns the handler it replaced (None when it could not install one)."""
    def handler(signum: int, frame: object) -> None:
        drop_process_priority()
        with contextlib.suppress(OSError, ValueError):  # the limit no longer applies: not real-time
            resource.setrlimit(resource.RLIMIT_RTTIME, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
        _LOG.error("%s: a real-time thread ran %g s without blocking: back to normal scheduling (a "
                   "real-time loop that never sleeps would take a core from everyone)", who, soft_s)

    try:
        return signal.signal(signal.SIGXCPU, handler)
    except ValueError:  # not the main thread: no handler, the hard limit still holds
        return None


def _unguard(limit: tuple[int, int], handler: Any) -> None:
    """Undo the RLIMIT_RTTIME and SIGXCPU handler of :func:`raise_process_priority` after a refusal.
    A lowered hard limit comes back only with CAP_SYS_RESOURCE; without it the limit stays, harmless:
    it counts the CPU time of real-time threads only, and the process has none."""
    with contextlib.suppress(OSError, ValueError):
        resource.setrlimit(resource.RLIMIT_RTTIME, limit)
    if handler is not None:
        with contextlib.suppress(ValueError, TypeError):
            signal.signal(signal.SIGXCPU, handler)


def raise_process_priority(fifo_priority: int, *, who: str,
                           budget_s: tuple[float, float] = RT_BUDGET_S) -> Priority:
    """Give every thread of this process (and, inherited, those it starts later) SCHED_FIFO at
    ``fifo_priority``. For a process on the control path that already runs helper threads when it
    learns its priority (a ROS node: the middleware's threads deliver its inputs, so they must not wait
    behind ordinary work either). ``fifo_priority`` 0 asks for nothing. When refused, the threads set
    so far go back to normal scheduling and the result says ``Policy.NORMAL`` with the reason; the
    caller then falls back to :func:`raise_nice`. Never raises.

    A runaway real-time thread would take a core from everything else on the machine, so the process
    gets an RLIMIT_RTTIME of ``budget_s`` (soft, hard; s of CPU without blocking): past the soft limit
    every thread is demoted to normal scheduling with one error line; past the hard limit (a thread
    stuck in native code) the kernel kills the process. Call from the main thread (the handler)."""
    prio, not_asked = _fifo_level(fifo_priority, who)
    if not_asked is not None:
        return not_asked
    soft, hard = (int(b * 1e6) for b in budget_s)
    try:  # the guard first: no thread is real-time without it, even for a moment
        old_limit = resource.getrlimit(resource.RLIMIT_RTTIME)
        resource.setrlimit(resource.RLIMIT_RTTIME, (soft, hard))
    except (OSError, ValueError, AttributeError) as exc:  # no limit, no real time: never unguarded
        return Priority(Policy.NORMAL, 0, f"{who}: SCHED_FIFO not taken (cannot limit its CPU time: {exc})")
    old_handler = _demote_on_sigxcpu(who, budget_s[0])
    done: list[int] = []
    for tid in _thread_ids():
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(prio))
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
        except OSError as exc:
            for t in done:
                drop_priority(tid=t)
            _unguard(old_limit, old_handler)  # nothing real-time left to guard
            return Priority(Policy.NORMAL, 0, f"{who}: SCHED_FIFO refused ({exc.strerror})")
        done.append(tid)
    return Priority(Policy.FIFO, prio, f"{who}: real-time scheduling SCHED_FIFO priority {prio} "
                                       f"({len(done)} threads; demoted after {budget_s[0]:g} s without "
                                       "blocking)")


def raise_nice(level: int, *, who: str) -> Priority:
    """Run every thread of this process (and the threads it starts later) at nice ``level`` (-20..0),
    or at the highest level allowed above it. For processes that are not real-time but must not be
    starved by ordinary work beside them (the controller, the driver's ROS node). ``level`` 0 asks for
    nothing. Linux applies nice per thread, so each existing thread is set. Never raises; log the
    returned ``message`` once."""
    if level >= 0:
        return Priority(Policy.NORMAL, 0, f"{who}: normal priority (nice not requested)")
    tids = _thread_ids()
    for lvl in range(max(int(level), -20), 0):
        try:
            for tid in tids:
                with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
                    os.setpriority(os.PRIO_PROCESS, tid, lvl)
        except OSError:
            continue
        return Priority(Policy.NICE, lvl, f"{who}: running at nice {lvl} (ahead of ordinary work)")
    return Priority(Policy.NORMAL, 0, (
        f"{who}: nice {level} not permitted; running at normal priority: other work on the machine can delay "
        "it (grant CAP_SYS_NICE or a nice limit, e.g. in /etc/security/limits.conf)"))


def scheduling_now() -> str:
    """The calling thread's scheduling in words: ``SCHED_FIFO 20``, ``nice -10`` or ``normal``."""
    try:
        if hasattr(os, "sched_getscheduler") and os.sched_getscheduler(0) == os.SCHED_FIFO:
            return f"SCHED_FIFO {os.sched_getparam(0).sched_priority}"
        level = os.getpriority(os.PRIO_PROCESS, 0)
    except OSError:
        return "unknown"
    return f"nice {level}" if level else "normal"


def drop_process_priority() -> None:
    """Every thread of this process back to normal scheduling (see :func:`drop_priority`)."""
    for tid in _thread_ids():
        drop_priority(tid=tid)


def drop_priority(*, tid: int = 0) -> None:
    """Return thread ``tid`` (0: the caller) to normal scheduling (SCHED_OTHER, nice 0 if allowed)."""
    try:
        if hasattr(os, "sched_setscheduler"):
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    except OSError as exc:  # already normal, or not ours
        _LOG.debug("drop_priority: %s", exc)


def freeze_gc() -> None:
    """Collect once and freeze what exists (never scanned again); undone by :func:`restore_gc`.

    Call it once start-up is done: a process that keeps automatic collection on then never pauses
    for a full collection of its start-up objects (with pybullet, numpy and python-can loaded, tens
    of milliseconds holding the interpreter lock, which no other thread of the process survives).
    """
    gc.collect()
    gc.freeze()


def quiet_gc() -> None:
    """:func:`freeze_gc`, then turn automatic collection off.

    The caller runs :func:`collect_young` in its spare time and :func:`restore_gc` when done.
    """
    freeze_gc()
    gc.disable()


def collect_young() -> int:
    """Collect the two young generations (objects made since the last call); returns the count freed.

    Cheap (tens of microseconds for a loop's own garbage); the full collection is left to
    :func:`restore_gc` / the owner's idle time.
    """
    return gc.collect(1)


def restore_gc() -> None:
    """Undo :func:`quiet_gc`: unfreeze and turn automatic collection back on."""
    gc.unfreeze()
    gc.enable()
