"""Waits that return as soon as a condition holds, and say what they last saw when it never did."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

from redarm_ros.errors import RedarmError

T = TypeVar("T")

DEFAULT_PERIOD_S = 0.01


class WaitTimeoutError(RedarmError, AssertionError, TimeoutError):
    """A condition did not hold in time. ``what`` names it, ``timeout_s`` is the limit, ``last`` the
    last value seen. An ``AssertionError`` too, so pytest reports it as a failed check."""

    def __init__(self, message: str, *, what: str, timeout_s: float, last: object) -> None:
        super().__init__(message)
        self.what = what
        self.timeout_s = timeout_s
        self.last = last


def wait_for(
    observe: Callable[[], T],
    cond: Callable[[T], object],
    timeout: float,
    *,
    what: str = "condition",
    period: float = DEFAULT_PERIOD_S,
    describe: Callable[[T], str] = repr,
) -> T:
    """Call ``observe()`` every ``period`` s until ``cond(value)`` holds; return that value.

    Raises:
        WaitTimeoutError: ``timeout`` s passed; the message names ``what`` and the last value seen
            (``describe(value)``).
    """
    deadline = time.monotonic() + timeout
    while True:
        value = observe()
        if cond(value):
            return value
        if time.monotonic() >= deadline:
            raise WaitTimeoutError(f"{what}: not reached within {timeout:g} s; last seen: {describe(value)}",
                                   what=what, timeout_s=timeout, last=value)
        time.sleep(period)


def wait_until(
    cond: Callable[[], T],
    timeout: float,
    *,
    what: str = "condition",
    seen: Callable[[], object] | None = None,
    period: float = DEFAULT_PERIOD_S,
) -> T:
    """Poll ``cond()`` until it returns something true; return that. ``seen()`` (default: the last
    value of ``cond()``) says in the error what was there instead.

    Raises:
        WaitTimeoutError: ``timeout`` s passed without a true value.
    """
    last: list[object] = [None]

    def observe() -> T:
        value = cond()
        last[0] = seen() if seen is not None and not value else value
        return value

    try:
        return wait_for(observe, bool, timeout, what=what, period=period)
    except WaitTimeoutError:
        raise WaitTimeoutError(f"{what}: not reached within {timeout:g} s; last seen: {last[0]!r}",
                               what=what, timeout_s=timeout, last=last[0]) from None
