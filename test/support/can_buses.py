"""Test support for code that opens CAN buses (no pytest import here; the fixtures live in tests).

:class:`OpenBusTracker` records every :class:`can.BusABC` created while it is active, from any
thread, so a test fixture can fail a test that leaves one open (as python-can's own suite does)::

    @pytest.fixture(autouse=True)
    def _no_open_buses():
        with OpenBusTracker() as tracker:
            yield
        leaked = tracker.close_leaked()
        if leaked:
            pytest.fail(f"test left CAN buses open: {leaked}")
"""

from __future__ import annotations

import functools
import threading
import weakref
from types import TracebackType
from typing import Any

import can

from redarm_ros.can.bus import safe_shutdown


class OpenBusTracker:
    """Context manager: track buses created inside it; :meth:`leaked` lists those still open."""

    def __init__(self) -> None:
        self._buses: weakref.WeakSet[can.BusABC] = weakref.WeakSet()
        self._lock = threading.Lock()
        self._original: Any = None

    def __enter__(self) -> OpenBusTracker:
        original = can.BusABC.__init__
        tracker = self

        @functools.wraps(original)
        def tracking_init(bus: can.BusABC, *args: Any, **kwargs: Any) -> None:
            original(bus, *args, **kwargs)
            with tracker._lock:
                tracker._buses.add(bus)

        self._original = original
        can.BusABC.__init__ = tracking_init  # type: ignore[method-assign]
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        can.BusABC.__init__ = self._original  # type: ignore[method-assign]

    def leaked(self) -> list[can.BusABC]:
        """Buses created while tracking that are not shut down."""
        with self._lock:
            buses = list(self._buses)
        return [b for b in buses if not getattr(b, "_is_shutdown", True)]

    def close_leaked(self) -> list[str]:
        """Shut every leaked bus down; returns their descriptions (empty when nothing leaked)."""
        out = []
        for bus in self.leaked():
            out.append(f"{type(bus).__name__}({getattr(bus, 'channel_info', '?')})")
            safe_shutdown(bus)
        return out
