"""Child-process tooling shared by tests, benchmarks and the bring-up (pure stdlib).

Every child started here gets the workplace DDS rules in its environment
(``FASTDDS_BUILTIN_TRANSPORTS=SHM``, a given ``ROS_DOMAIN_ID``, ``ROS_LOG_DIR``
in a temp dir, ``PYTHONUNBUFFERED=1``), so no ROS packet leaves the machine and
two test runs never see each other; also ``OPENBLAS_NUM_THREADS=1`` unless set.

Pieces:

* :func:`ros_child_env` builds such an environment.
* :class:`ManagedProcess` is one child: its stdout+stderr are read by a thread
  that forwards each line with a ``[name]`` prefix and keeps a tail for error
  messages; :meth:`ManagedProcess.wait_for_line` waits for readiness output;
  :meth:`ManagedProcess.stop` ends it with SIGINT, wait, SIGINT again, then
  SIGKILL (rclpy ignores the first SIGINT about 1 run in 12).
* :class:`ProcessGroup` is a supervisor context manager: it starts children,
  stops them in reverse order on exit, and reports any child that died
  without being asked to (:class:`ChildDiedError`).

Children run in their own session (process group), so a terminal Ctrl-C
reaches only the supervisor, which then stops them in order, and the final
SIGKILL can take the child's own descendants with it. Each child also asks the
kernel (``PR_SET_PDEATHSIG``) for SIGKILL when its parent dies, so a crashed
pytest or bring-up (kill -9) leaves no orphans behind, not even real-time ones.
"""

from __future__ import annotations

import collections
import ctypes
import logging
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import IO

from redarm_ros.errors import RedarmError

__all__ = [
    "ChildDiedError",
    "die_with_parent_preexec",
    "ManagedProcess",
    "poll_until",
    "ProcessGroup",
    "ReadinessTimeoutError",
    "python_module_cmd",
    "random_domain_id",
    "ros_child_env",
    "thread_states",
]

_LOG = logging.getLogger(__name__)

# Stop schedule in seconds: wait after the first SIGINT, after the second, after SIGKILL. A killed
# process is normally reaped within milliseconds; the last wait is long because a busy 2-core machine
# once took more than 3 s to end a 15-thread real-time node.
DEFAULT_STOP_TIMEOUTS: tuple[float, float, float] = (5.0, 3.0, 10.0)
#: A SIGKILLed child always ends, but a saturated machine took longer than the last wait to reap one
#: (the stop then raised and the bring-up skipped its "stopped" line): after that wait, this much more
#: (s), with one error line, before giving up.
KILL_REAP_EXTRA_S = 60.0
_TAIL_LINES = 200
_KEEP_LINES = 20000

LineSink = Callable[[str], None]

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent_preexec(sig: int = signal.SIGKILL) -> Callable[[], None] | None:
    """A ``preexec_fn`` that has the kernel send ``sig`` to the child when its parent dies.

    None where prctl is unavailable (not Linux). libc is loaded here, before the fork, so the
    child only makes one system call. The kernel ties the signal to the parent *thread*: a child
    started from a short-lived thread dies with that thread, so start children from a thread that
    lives as long as they should (the main thread, a supervisor).
    """
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def preexec() -> None:
        prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
        if os.getppid() != parent:  # the parent died before prctl took effect
            os._exit(1)

    return preexec


class ChildDiedError(RedarmError):
    """A child exited when it should still be running (``name``, ``returncode``, ``tail`` of its output)."""

    def __init__(self, message: str, *, name: str, returncode: int | None, tail: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.name = name
        self.returncode = returncode
        self.tail = list(tail)


class ReadinessTimeoutError(RedarmError, TimeoutError):
    """An expected output line did not appear in time (``name``, ``pattern``, ``timeout_s``, ``tail``)."""

    def __init__(
        self, message: str, *, name: str, pattern: str, timeout_s: float, tail: Sequence[str] = ()
    ) -> None:
        super().__init__(message)
        self.name = name
        self.pattern = pattern
        self.timeout_s = timeout_s
        self.tail = list(tail)


def poll_until(cond: Callable[[], object], timeout: float, period: float = 0.02) -> bool:
    """Poll ``cond()`` every ``period`` s until it holds (True) or ``timeout`` s passed (False): for
    callers whose rclpy executor spins in another thread, and for tests waiting on a child."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() >= deadline:
            return False
        time.sleep(period)
    return True


def random_domain_id(rng: random.Random | None = None) -> int:
    """A ROS_DOMAIN_ID in 1..200 (default: drawn from OS entropy, so parallel runs differ)."""
    r = rng if rng is not None else random.SystemRandom()
    return r.randint(1, 200)


def ros_child_env(
    domain_id: int,
    *,
    log_dir: str | os.PathLike[str] | None = None,
    base: Mapping[str, str] | None = None,
    extra: Mapping[str, str] | None = None,
    pythonpath: Sequence[str | os.PathLike[str]] = (),
) -> dict[str, str]:
    """Environment for a child that may run ROS: SHM-only Fast DDS, its own domain, its own log dir.

    ``base`` defaults to ``os.environ``; ``extra`` is applied last but can never
    weaken the DDS rules (transport, domain). ``pythonpath`` entries are put in
    front of any inherited ``PYTHONPATH``.
    """
    if not 0 <= int(domain_id) <= 232:
        raise ValueError(f"ROS_DOMAIN_ID must be 0..232, got {domain_id}")
    env = dict(os.environ if base is None else base)
    if extra:
        env.update({k: str(v) for k, v in extra.items()})
    env["FASTDDS_BUILTIN_TRANSPORTS"] = "SHM"
    env["ROS_DOMAIN_ID"] = str(int(domain_id))
    # Belt and braces: even if a transport slipped through, keep discovery local.
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
    # numpy's OpenBLAS otherwise starts a thread per core that spins idle for ~0.1 s of CPU in every
    # child that imports numpy; the children's matrices (7x7) run single-threaded in BLAS anyway.
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    if log_dir is None:
        log_dir = tempfile.mkdtemp(prefix="redarm_roslog_")
    env["ROS_LOG_DIR"] = os.fspath(log_dir)
    if pythonpath:
        parts = [os.fspath(p) for p in pythonpath]
        if env.get("PYTHONPATH"):
            parts.append(env["PYTHONPATH"])
        env["PYTHONPATH"] = os.pathsep.join(parts)
    return env


def python_module_cmd(module: str, *args: str, python: str | None = None) -> list[str]:
    """``[python, "-m", module, *args]`` with this interpreter unless ``python`` is given."""
    return [python or sys.executable, "-m", module, *map(str, args)]


def stream_sink(stream: IO[str]) -> LineSink:
    """A thread-safe line writer to ``stream`` (flushed per line; a closed stream is ignored)."""
    lock = threading.Lock()

    def sink(line: str) -> None:
        with lock:
            try:
                stream.write(line + "\n")
                stream.flush()
            except (ValueError, OSError):
                pass  # stream closed under us at interpreter/pytest teardown

    return sink


def _logging_sink(line: str) -> None:
    _LOG.info("%s", line)


class ManagedProcess:
    """One child process with forwarded, prefixed output and a staged stop.

    Do not construct directly; use :meth:`start` or :meth:`ProcessGroup.start`.
    Output lines (stdout and stderr merged) are kept (the last 20000) for
    :meth:`wait_for_line` and forwarded to ``sink`` as ``"[name] line"``.
    """

    def __init__(
        self,
        name: str,
        cmd: Sequence[str],
        *,
        env: Mapping[str, str] | None = None,
        cwd: str | os.PathLike[str] | None = None,
        sink: LineSink | IO[str] | None = None,
        on_exit: Callable[[ManagedProcess], None] | None = None,
        exits: bool = False,
    ) -> None:
        self.name = name
        self.cmd = [str(c) for c in cmd]
        if sink is None:
            self._sink: LineSink = _logging_sink
        elif callable(sink):
            self._sink = sink
        else:
            self._sink = stream_sink(sink)
        self._on_exit = on_exit
        self._cond = threading.Condition()
        self._lines: collections.deque[str] = collections.deque(maxlen=_KEEP_LINES)
        self._first_index = 0  # absolute index of self._lines[0]
        self._cursor = 0  # absolute index after the last matched line
        self._eof = False
        self._stopping = False
        self.expected_exit = exits  # set before the child runs: it may exit before start() returns
        self.started_at = time.monotonic()
        self.popen = subprocess.Popen(
            self.cmd,
            env=dict(env) if env is not None else None,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=die_with_parent_preexec(),
            text=True,
            encoding="utf-8",
            errors="replace",
            bufsize=1,
        )
        self.pid = self.popen.pid
        self._reader = threading.Thread(target=self._read, name=f"procs-reader-{name}", daemon=True)
        self._reader.start()

    @classmethod
    def start(cls, name: str, cmd: Sequence[str], **kwargs: object) -> ManagedProcess:
        """Start ``cmd`` as child ``name`` (keyword arguments as in the constructor)."""
        return cls(name, cmd, **kwargs)  # type: ignore[arg-type]

    # -- output ---------------------------------------------------------------------------------
    def _read(self) -> None:
        assert self.popen.stdout is not None
        try:
            for raw in self.popen.stdout:
                line = raw.rstrip("\n")
                with self._cond:
                    if len(self._lines) == self._lines.maxlen:
                        self._first_index += 1
                    self._lines.append(line)
                    self._cond.notify_all()
                self._sink(f"[{self.name}] {line}")
        except (ValueError, OSError):
            pass  # pipe closed during shutdown
        finally:
            # EOF: the child closed its output, normally because it exited.
            try:
                self.popen.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                pass  # it closed stdout but lives on; poll() will tell later
            with self._cond:
                self._eof = True
                self._cond.notify_all()
            rc = self.popen.poll()
            if rc is not None and not self._stopping and not self.expected_exit:
                self._sink(f"[{self.name}] ** exited unexpectedly with code {rc}")
            if self._on_exit is not None:
                self._on_exit(self)

    def tail(self, n: int = 40) -> list[str]:
        """The last ``n`` output lines."""
        with self._cond:
            return list(self._lines)[-n:]

    def output(self) -> list[str]:
        """All retained output lines (at most the last 20000)."""
        with self._cond:
            return list(self._lines)

    def wait_for_line(
        self, pattern: str | re.Pattern[str], timeout: float = 10.0, *, from_start: bool = False
    ) -> re.Match[str]:
        """Wait until an output line matches ``pattern`` (``re.search``) and return the match.

        Searching starts after the previous match (or at the first line with
        ``from_start``), so consecutive calls consume the output in order.

        Raises:
            ChildDiedError: the child exited before the line appeared.
            ReadinessTimeoutError: ``timeout`` seconds passed without a match.
        """
        rx = re.compile(pattern) if isinstance(pattern, str) else pattern
        deadline = time.monotonic() + timeout
        with self._cond:
            pos = self._first_index if from_start else max(self._cursor, self._first_index)
            while True:
                lines = self._lines
                end = self._first_index + len(lines)
                while pos < end:
                    m = rx.search(lines[pos - self._first_index])
                    pos += 1
                    if m:
                        self._cursor = pos
                        return m
                if self._eof:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise ReadinessTimeoutError(
                        f"{self.name}: no line matching {rx.pattern!r} within {timeout:.1f} s; "
                        f"last output:\n" + "\n".join(list(lines)[-20:]),
                        name=self.name,
                        pattern=rx.pattern,
                        timeout_s=timeout,
                        tail=list(lines)[-_TAIL_LINES:],
                    )
                self._cond.wait(min(remaining, 0.2))
        rc = self.popen.poll()
        raise ChildDiedError(
            f"{self.name} exited (code {rc}) before printing a line matching {rx.pattern!r}; "
            f"last output:\n" + "\n".join(self.tail(20)),
            name=self.name,
            returncode=rc,
            tail=self.tail(_TAIL_LINES),
        )

    def skip_output(self) -> None:
        """Later :meth:`wait_for_line` calls (without ``from_start``) look only at lines from now on: a
        child shared by several tests, each waiting for its own lines, not an earlier test's."""
        with self._cond:
            self._cursor = self._first_index + len(self._lines)

    # -- life cycle -----------------------------------------------------------------------------
    @property
    def returncode(self) -> int | None:
        """Exit code, or None while running (negative: killed by that signal)."""
        return self.popen.poll()

    def is_running(self) -> bool:
        """True while the child has not exited."""
        return self.popen.poll() is None

    @property
    def died_unexpectedly(self) -> bool:
        """The child exited although nobody stopped it and no exit was announced."""
        return self.popen.poll() is not None and not self._stopping and not self.expected_exit

    def expect_exit(self) -> None:
        """Announce that this child will exit on its own (e.g. a crash the test provokes)."""
        self.expected_exit = True

    def send_signal(self, sig: int) -> None:
        """Send ``sig`` to the child itself if it is still running."""
        if self.popen.poll() is None:
            try:
                self.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def kill(self) -> int:
        """SIGKILL the child and its process group now (an announced exit); returns the exit code."""
        self.expected_exit = True
        self._kill_group()
        rc = self.popen.wait(timeout=DEFAULT_STOP_TIMEOUTS[2])
        self._reader.join(timeout=2.0)
        return rc

    def _kill_group(self) -> None:
        try:
            os.killpg(self.pid, signal.SIGKILL)  # its own session: pgid == pid
        except (ProcessLookupError, PermissionError):
            self.send_signal(signal.SIGKILL)

    def stop(self, timeouts: tuple[float, float, float] = DEFAULT_STOP_TIMEOUTS) -> int:
        """Stop the child: SIGINT, wait, SIGINT again, wait, then SIGKILL (to its group); return the code.

        ``timeouts`` are the waits (s) after the first SIGINT, the second, and SIGKILL.
        Safe to call on a child that has already exited.
        """
        self._stopping = True
        t1, t2, t3 = timeouts
        for sig, wait_s in ((signal.SIGINT, t1), (signal.SIGINT, t2)):
            if self.popen.poll() is not None:
                break
            self.send_signal(sig)
            try:
                self.popen.wait(timeout=wait_s)
            except subprocess.TimeoutExpired:
                _LOG.warning("%s: still running %.1f s after SIGINT (%s)", self.name, wait_s,
                             thread_states(self.pid))
        if self.popen.poll() is None:
            _LOG.warning("%s: SIGKILL after two SIGINTs", self.name)
            self._kill_group()
            try:
                self.popen.wait(timeout=t3)
            except subprocess.TimeoutExpired:
                _LOG.error("%s: not ended %.1f s after SIGKILL (%s); waiting up to %.0f s more", self.name,
                           t3, thread_states(self.pid), KILL_REAP_EXTRA_S)
                self.popen.wait(timeout=KILL_REAP_EXTRA_S)
        # Descendants that outlived the child die with its group; they were ours. A SIGKILLed
        # process takes a moment to die (longer on a busy machine): wait for that, bounded.
        if self.group_alive():
            try:
                os.killpg(self.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        end = time.monotonic() + t3
        while self.group_alive() and time.monotonic() < end:
            time.sleep(0.01)
        if self.group_alive():
            _LOG.error("%s: its process group outlived SIGKILL by %.1f s", self.name, t3)
        self._reader.join(timeout=2.0)
        rc = self.popen.returncode
        assert rc is not None
        return rc

    def group_alive(self) -> bool:
        """True if a live (non-zombie) process remains in this child's process group.

        The child's group id is its pid (own session). Zombies are ignored: a
        killed grandchild stays a zombie until init reaps it.
        """
        return bool(group_members(self.pid))

    def __repr__(self) -> str:
        return f"<ManagedProcess {self.name} pid={self.pid} rc={self.popen.poll()}>"


class ProcessGroup:
    """Supervisor for a set of children: stop all in reverse order on exit, report unexpected deaths.

    >>> with ProcessGroup(domain_id=42) as group:          # doctest: +SKIP
    ...     bus = group.start("canbus", python_module_cmd("redarm_ros.can.bus_server"),
    ...                       ready=r"REDARM_CANBUS_PORT=(\\d+)")
    ...     group.check()     # raises ChildDiedError if a child died on its own

    Leaving the ``with`` block stops every child. If the block ended without
    an exception but a child died unannounced, :class:`ChildDiedError` is
    raised then (a crash is never silently swallowed).
    """

    def __init__(
        self,
        *,
        domain_id: int | None = None,
        env: Mapping[str, str] | None = None,
        log_dir: str | os.PathLike[str] | None = None,
        pythonpath: Sequence[str | os.PathLike[str]] = (),
        sink: LineSink | IO[str] | None = None,
        stop_timeouts: tuple[float, float, float] = DEFAULT_STOP_TIMEOUTS,
    ) -> None:
        self.domain_id = random_domain_id() if domain_id is None else int(domain_id)
        self._own_log_dir: tempfile.TemporaryDirectory[str] | None = None
        if log_dir is None:
            self._own_log_dir = tempfile.TemporaryDirectory(prefix="redarm_procs_")
            log_dir = self._own_log_dir.name
        self.log_dir = os.fspath(log_dir)
        self.env = ros_child_env(self.domain_id, log_dir=self.log_dir, base=env, pythonpath=pythonpath)
        self._sink = sink
        self.stop_timeouts = stop_timeouts
        self.children: list[ManagedProcess] = []
        self._lock = threading.Lock()
        self._deaths: list[ManagedProcess] = []
        self.on_unexpected_death: Callable[[ManagedProcess], None] | None = None

    def start(
        self,
        name: str,
        cmd: Sequence[str],
        *,
        ready: str | re.Pattern[str] | None = None,
        ready_timeout: float = 15.0,
        extra_env: Mapping[str, str] | None = None,
        cwd: str | os.PathLike[str] | None = None,
        exits: bool = False,
    ) -> ManagedProcess:
        """Start child ``name`` with the group's environment (+ ``extra_env``, DDS rules kept).

        If ``ready`` is given, wait for a matching output line; the match is
        stored on the child as ``ready_match``. On failure the child is stopped
        and the error re-raised. ``exits``: the child will exit on its own, announced before it
        runs (:meth:`ManagedProcess.expect_exit` after the start can come too late for a short one).
        """
        env = dict(self.env)
        if extra_env:
            env.update({k: str(v) for k, v in extra_env.items()})
            env["FASTDDS_BUILTIN_TRANSPORTS"] = "SHM"
            env["ROS_DOMAIN_ID"] = str(self.domain_id)
        child = ManagedProcess(name, cmd, env=env, cwd=cwd, sink=self._sink, on_exit=self._child_exited,
                               exits=exits)
        with self._lock:
            self.children.append(child)
        child.ready_match = None  # type: ignore[attr-defined]
        if ready is not None:
            try:
                child.ready_match = child.wait_for_line(ready, ready_timeout)  # type: ignore[attr-defined]
            except BaseException:
                child.stop(self.stop_timeouts)
                raise
        return child

    def _child_exited(self, child: ManagedProcess) -> None:
        if child.died_unexpectedly:
            with self._lock:
                self._deaths.append(child)
            _LOG.error("child %s (pid %d) died unexpectedly with code %s", child.name, child.pid,
                       child.returncode)
            if self.on_unexpected_death is not None:
                self.on_unexpected_death(child)

    def unexpected_deaths(self) -> list[ManagedProcess]:
        """Children that exited without being stopped or announced (so far)."""
        with self._lock:
            known = list(self._deaths)
        # The reader thread may lag behind the exit; poll too.
        for c in list(self.children):
            if c.died_unexpectedly and c not in known:
                known.append(c)
        return known

    def check(self) -> None:
        """Raise :class:`ChildDiedError` for the first child that died unexpectedly."""
        dead = self.unexpected_deaths()
        if dead:
            raise _died(dead[0])

    def stop(self, child: ManagedProcess) -> int:
        """Stop one child now (staged); returns its exit code."""
        return child.stop(self.stop_timeouts)

    def stop_all(self) -> dict[str, int]:
        """Stop every child in reverse start order; returns name -> exit code (last one wins per name)."""
        codes: dict[str, int] = {}
        for child in reversed(list(self.children)):
            try:
                codes[child.name] = child.stop(self.stop_timeouts)
            except Exception:  # keep stopping the others
                _LOG.exception("failed to stop %s", child.name)
        return codes

    def leaked(self) -> list[ManagedProcess]:
        """Children whose process group still has members (after :meth:`stop_all`, a leak)."""
        return [c for c in self.children if c.group_alive()]

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        dead = self.unexpected_deaths()
        self.stop_all()
        if self._own_log_dir is not None:
            self._own_log_dir.cleanup()
        if exc_type is None and dead:
            raise _died(dead[0])


def _died(c: ManagedProcess) -> ChildDiedError:
    """The error for child ``c`` that died unexpectedly (with its last output)."""
    return ChildDiedError(
        f"child {c.name} (pid {c.pid}) died unexpectedly with code {c.returncode}; "
        "last output:\n" + "\n".join(c.tail(20)),
        name=c.name,
        returncode=c.returncode,
        tail=c.tail(_TAIL_LINES),
    )


def group_members(pgid: int) -> list[int]:
    """Pids of live (non-zombie) processes in process group ``pgid`` (Linux /proc scan)."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return []
    except PermissionError:
        pass
    return [pid for pid, (_, group) in live_processes().items() if group == pgid]


def live_processes() -> dict[int, tuple[int, int]]:
    """Every live (non-zombie) process: pid -> (parent pid, process group) (Linux /proc scan)."""
    out: dict[int, tuple[int, int]] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat", encoding="ascii", errors="replace") as f:
                stat = f.read()
        except OSError:
            continue
        # Fields after the parenthesised command: state ppid pgrp ...
        fields = stat.rsplit(")", 1)[-1].split()
        if len(fields) >= 3 and fields[0] not in ("Z", "X"):
            out[int(entry.name)] = (int(fields[1]), int(fields[2]))
    return out


def descendants(pid: int) -> list[int]:
    """Pids of the live (non-zombie) children of ``pid``, their children, and so on, wherever their
    process group or session (Linux /proc scan)."""
    parent_of = {child: parent for child, (parent, _) in live_processes().items()}
    found: list[int] = []
    frontier = {pid}
    while frontier:
        frontier = {child for child, parent in parent_of.items() if parent in frontier}
        found.extend(sorted(frontier))
    return found


def thread_states(pid: int) -> str:
    """One line on the threads of process ``pid`` for a log: how many in each state (R running, S
    sleeping, D uninterruptible, ...) and the scheduling, kernel wait point and CPU time of every thread
    that is not sleeping. For the diagnosis of a child that does not stop (Linux /proc; '' elsewhere)."""
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return "no thread information"
    counts: dict[str, int] = {}
    busy = []
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat", encoding="ascii", errors="replace") as f:
                stat = f.read()
            with open(f"/proc/{pid}/task/{tid}/wchan", encoding="ascii", errors="replace") as f:
                wchan = f.read().strip() or "-"
        except OSError:
            continue
        name = stat[stat.find("(") + 1 : stat.rfind(")")]
        fields = stat.rsplit(")", 1)[-1].split()  # state is field 3 of stat(5), so fields[k] is k + 3
        if len(fields) < 39:
            continue
        state = fields[0]
        counts[state] = counts.get(state, 0) + 1
        if state != "S":
            cpu_s = (int(fields[11]) + int(fields[12])) / tick
            policy = {"0": "normal", "1": "FIFO", "2": "RR"}.get(fields[38], f"policy {fields[38]}")
            busy.append(f"{tid} {name!r} {state} {policy} {fields[37]} wchan {wchan} cpu {cpu_s:.2f} s")
    summary = ", ".join(f"{n} {st}" for st, n in sorted(counts.items())) or "no threads"
    return f"threads: {summary}" + (f"; not sleeping: {'; '.join(busy)}" if busy else "")


def stop_all(children: Iterable[ManagedProcess]) -> None:
    """Stop the given children in reverse order (helper for code without a group)."""
    for c in reversed(list(children)):
        c.stop()
