"""A :class:`~redarm_ros.sim.hardware.HardwareSim` served in a thread of the test process, and stopped."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

JOIN_TIMEOUT_S = 10.0


@contextlib.contextmanager
def sim_running(sim: Any, closers: Sequence[Callable[[], None]],
                on_ready: Callable[[], None] | None = None) -> Iterator[threading.Thread]:
    """Run ``sim.run`` in a daemon thread for the ``with`` body. On leaving: ask it to stop, join it, call
    each of ``closers`` (buses, the plant) in order, and, when the body passed, check the thread ended."""
    kwargs = {} if on_ready is None else {"on_ready": on_ready}
    runner = threading.Thread(target=sim.run, kwargs=kwargs, daemon=True)
    runner.start()
    try:
        yield runner
    finally:
        sim.request_stop()
        runner.join(timeout=JOIN_TIMEOUT_S)
        for close in closers:
            close()
    assert not runner.is_alive()
