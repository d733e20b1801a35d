"""Polling waits for tests that run threads (driver loops, emulators) beside the test."""

from __future__ import annotations

import time
from collections.abc import Callable

from support.benches import load_bench


def wait_until(pred: Callable[[], object], timeout: float = 5.0, step: float = 0.01) -> bool:
    """Poll ``pred`` every ``step`` s until it is true or ``timeout`` s have passed; its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


# Spin an rclpy executor until a predicate holds: the benches' loop, one copy for both.
spin_until = load_bench("bench_common").spin_until
