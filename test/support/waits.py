"""Polling waits for tests that run threads (driver loops, emulators) beside the test, and the time
budget of calls whose tests judge the answer, not the speed."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from redarm_ros.procs import poll_until

#: Time budget (s) for a solver or search whose test judges the answer, not the speed: it only
#: bounds a hang, so a starved machine cannot turn a correct answer into a TIMEOUT.
HANG_BUDGET_S = 30.0


def wait_until(pred: Callable[[], object], timeout: float = 5.0, step: float = 0.01) -> bool:
    """Poll ``pred`` every ``step`` s until it is true (True) or ``timeout`` s have passed (False)."""
    return poll_until(pred, timeout, step)


def spin_until(ex: Any, pred: Callable[[], object], timeout: float, spin_s: float = 0.02) -> bool:
    """Spin the rclpy executor ``ex`` (``spin_s`` s per turn) until ``pred`` is true or ``timeout``
    s have passed."""
    from redarm_ros.nodes._common import spin_until as spin  # the runtime's own (needs rclpy)

    return spin(ex, pred, timeout, spin_s)
