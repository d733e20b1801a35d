"""A reply deadline that does not count the time the waiting process was not running.

A module is judged silent when its reply has not come within a timeout. If the host process was
descheduled meanwhile (a loaded machine, a throttled container, a virtual machine whose vCPU was
taken away), the wall clock ran on while nobody listened, and on such a machine the modules'
stand-in (or the bus server) was usually stopped too. Counting that time would call a module
silent that was never given the chance to answer: its reply lost in this cycle and read as late
in the next. A wait cannot tell when inside it the process stopped, so a gap in our own running
longer than :data:`STALL_S` restarts the wait: the modules get the whole timeout from the moment
we run again. A gap is a receive that came back later than it was asked to wait (empty, or with a
frame that arrived while we were stopped) or a pause between two looks at the clock. A deadline
restarts at most :data:`MAX_RESTARTS` times: a silent module costs the stalls, which happened
anyway, plus one timeout after the last of them, and no more than ``MAX_RESTARTS + 1`` timeouts
of waiting however often the process stalls (a flooded bus on a busy machine).

On real hardware a reply that arrived during the stall is already queued and is read at once.
"""

from __future__ import annotations

from collections.abc import Callable

#: A gap in our own running longer than this [s] is a stall, not scheduling noise.
STALL_S = 0.002
#: A deadline restarts after a stall at most this often.
MAX_RESTARTS = 3


class ReplyDeadline:
    """Deadline for one round of replies; reused (no allocation per cycle).

    Usage: :meth:`start`, then per receive ``left = d.left()`` (stop when <= 0),
    ``msg = recv(left)``, ``d.waited(left)``.
    """

    __slots__ = ("_clock", "_timeout", "_at", "_mark", "_now", "_restarts", "stalled_s")

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._timeout = self._at = self._mark = self._now = 0.0
        self._restarts = 0
        self.stalled_s = 0.0  #: the stalls not counted against this deadline [s]

    def start(self, since: float, timeout_s: float) -> None:
        """Replies are due ``timeout_s`` after ``since`` (a time of the same clock, at most now)."""
        self._timeout = timeout_s
        self._at = since + timeout_s
        self._mark = self._now = since  # a stall while the requests went out counts as one too
        self._restarts = 0
        self.stalled_s = 0.0

    def left(self) -> float:
        """Seconds left to wait (<= 0: the deadline passed); the whole timeout again after a stall."""
        now = self._clock()
        stalled = now - self._mark
        if stalled > STALL_S and self._restarts < MAX_RESTARTS:
            self._restarts += 1
            self._at = now + self._timeout
            self.stalled_s += stalled
        self._now = self._mark = now
        return self._at - now

    def waited(self, asked_s: float) -> None:
        """Record a receive that was asked to wait at most ``asked_s``: whatever came back later than
        that (empty, or with a frame that arrived while we were stopped) stalled."""
        self._mark = min(self._clock(), self._now + asked_s)
