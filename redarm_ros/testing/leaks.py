"""Leak checks for tests: CAN buses left open, child processes left running.

:class:`OpenBusTracker` records every :class:`can.BusABC` created while it is active, from any
thread, so a fixture can fail a test that leaves one open (as python-can's own suite does);
:func:`live_children` lists the live child processes of a process, so a fixture can fail a test
that leaves one running. The pytest plugin's ``redarm_no_open_buses`` and
``redarm_no_leftover_children`` fixtures are built on these. python-can is imported only when a
tracker starts.
"""

from __future__ import annotations

import functools
import os
import signal
import threading
import time
import weakref
from types import TracebackType
from typing import Any

from redarm_ros.procs import live_processes

#: Long-lived helpers that libraries start once per interpreter on purpose (not leaks).
BENIGN_CHILDREN = ("multiprocessing.resource_tracker", "multiprocessing.forkserver")


def live_children(pid: int) -> dict[int, str]:
    """Live (non-zombie) direct children of ``pid``: pid -> command line (Linux /proc scan)."""
    out: dict[int, str] = {}
    for child, (parent, _) in live_processes().items():
        if parent != pid:
            continue
        try:
            with open(f"/proc/{child}/cmdline", "rb") as f:
                out[child] = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:  # (ended meanwhile)
            continue
    return out


def leftover_children(before: set[int], grace_s: float = 3.0) -> dict[int, str]:
    """Children of this process not in ``before`` (and not benign) still alive after ``grace_s`` s
    of waiting for them to end; each is SIGKILLed and reaped. Returns them (pid -> command line)."""
    me = os.getpid()
    deadline = time.monotonic() + grace_s
    while True:
        left = {p: c for p, c in live_children(me).items()
                if p not in before and not any(b in c for b in BENIGN_CHILDREN)}
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    for p in left:
        try:
            os.kill(p, signal.SIGKILL)
            os.waitpid(p, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
    return left


class OpenBusTracker:
    """Context manager: track buses created inside it; :meth:`leaked` lists those still open."""

    def __init__(self) -> None:
        self._buses: weakref.WeakSet[Any] = weakref.WeakSet()
        self._lock = threading.Lock()
        self._original: Any = None

    def __enter__(self) -> OpenBusTracker:
        import can

        original = can.BusABC.__init__
        tracker = self

        @functools.wraps(original)
        def tracking_init(bus: Any, *args: Any, **kwargs: Any) -> None:
            original(bus, *args, **kwargs)
            with tracker._lock:
                tracker._buses.add(bus)

        self._original = original
        can.BusABC.__init__ = tracking_init  # type: ignore[method-assign]
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        import can

        can.BusABC.__init__ = self._original  # type: ignore[method-assign]

    def leaked(self) -> list[Any]:
        """Buses created while tracking that are not shut down."""
        with self._lock:
            buses = list(self._buses)
        return [b for b in buses if not getattr(b, "_is_shutdown", True)]

    def close_leaked(self) -> list[str]:
        """Shut every leaked bus down; returns their descriptions (empty when nothing leaked)."""
        out = []
        for bus in self.leaked():
            out.append(f"{type(bus).__name__}({getattr(bus, 'channel_info', '?')})")
            from redarm_ros.can.bus import safe_shutdown

            safe_shutdown(bus)
        return out
