"""How well a periodic loop keeps its rate (ROS-free; used by the controller node's ``/diagnostics``).

A ROS timer whose callback comes more than one period late skips the ticks it missed, so a starved
or overloaded controller takes fewer steps, not longer ones. Counted by the loop itself, the steps it
took are exact, whoever listens: a subscriber that is starved in turn loses messages and would report
a lower rate than the loop achieved. Units: s.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = ["LoopStats", "LoopSummary"]


@dataclass(frozen=True)
class LoopSummary:
    """``steps`` since start (cumulative: a reader takes rates between two summaries), ``clock`` (s,
    the loop's monotonic clock at the last step), ``rate_hz`` over the window that ends at the time of
    the summary, ``missed`` ticks since start (each interval longer than 1.5 periods counts its
    skipped ticks), the step's own duration (median and max, s) over the window, and ``idle_s``, how
    long before the summary the last step started."""

    steps: int
    clock: float
    rate_hz: float
    missed: int
    busy_median: float
    busy_max: float
    idle_s: float


class LoopStats:
    """Step times and durations of a loop of nominal ``period`` (s), over a window of ``window`` s."""

    def __init__(self, period: float, window: float = 2.0) -> None:
        if not (period > 0.0 and math.isfinite(period)):
            raise ValueError(f"period must be a positive number of seconds, got {period!r}")
        self.period = period
        self.window = window
        self.steps = 0
        self.missed = 0
        self._last: float | None = None
        self._paused = False
        self._recent: deque[tuple[float, float]] = deque()  # (time, duration) of the window's steps

    def step(self, t: float, busy: float) -> None:
        """Record a step that started at ``t`` (monotonic s) and took ``busy`` s."""
        if self._last is not None and not self._paused:
            gap = t - self._last
            if gap > 1.5 * self.period:
                self.missed += int(round(gap / self.period)) - 1
        self._last = t
        self._paused = False
        self.steps += 1
        self._recent.append((t, busy))
        while self._recent and t - self._recent[0][0] > self.window:
            self._recent.popleft()

    def pause(self) -> None:
        """The loop rested on purpose (nothing to do): the gap before its next step is no missed tick."""
        self._paused = True

    def summary(self, now: float) -> LoopSummary:
        """The loop's figures at ``now`` (monotonic s, the clock of :meth:`step`): the window ends at
        ``now``, so the rate of a loop that stopped stepping falls to 0 (rate 0 and durations NaN
        before two steps)."""
        r = self._recent
        while r and now - r[0][0] > self.window:
            r.popleft()
        # The steps after the window's first one, over the time from it to now, less the part of a
        # period a punctual loop has not reached yet: a loop at its period scores its rate, a loop
        # that stopped less and less.
        span = now - r[0][0] if r else 0.0
        if r and now - r[-1][0] < self.period:
            span = r[-1][0] - r[0][0]
        rate = (len(r) - 1) / span if len(r) >= 2 and span > 0.0 else 0.0
        busy = sorted(b for _, b in r)
        med = busy[len(busy) // 2] if busy else math.nan
        last = self._last if self._last is not None else math.nan
        return LoopSummary(self.steps, last, rate, self.missed, med, busy[-1] if busy else math.nan,
                           now - last)
