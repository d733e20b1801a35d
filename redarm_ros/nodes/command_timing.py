"""When the controller's joint commands are due at the driver (ROS-free; used by the controller node).

Each control step becomes one ``/joint_command`` segment, from the previous command to the new one over
the step's duration. Started on receipt, the segment's end reaches the driver one period plus the
message latency after the step, and both vary with the scheduling of two processes (the controller's
timer, DDS, the driver node's executor): a command-to-arm delay that varies is a tracking error of
``speed x variation``. Stamped instead, on the clock that both share, to end ``delay`` after its step,
a segment is played at a fixed time after the step whatever its latency (as long as it arrives before
it starts: the driver follows the previous segment until then, a jitter buffer). The delay is then
known, and the controller tracks a stream ``delay`` + the arm's own lag ahead (``stream_lead_s``).

The stamps are only used while the driver's clock agrees with this one: the ``joint_states`` stamps
(times of measurement on the driver's clock) must look neither from the future nor older than
``CLOCK_AGREES_S`` allows, judged by the least age over ``CLOCK_WINDOW_S``. Otherwise (another machine
without clock synchronisation, unstamped joint states) the segments go out unstamped, started on
receipt as before. Units: s.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = ["CLOCK_AGREES_S", "CLOCK_WINDOW_S", "CommandClock", "Segment"]

#: s of joint_states stamps over which the clocks are compared.
CLOCK_WINDOW_S = 1.0
#: s: the least age (receive time - stamp) of the joint_states in the window must lie in this range
#: for the clocks to count as one (a little negative: clock-read noise; positive: transport delay).
CLOCK_AGREES_S = (-0.02, 0.25)


@dataclass(frozen=True)
class Segment:
    """Timing of one command segment: ``stamp`` (s, ROS clock; None = unstamped, started on receipt)
    of its first point, and ``duration`` (s) from the previous command to the new one."""

    stamp: float | None
    duration: float


class CommandClock:
    """Stamps of the command segments and the check that the driver's clock agrees.

    Args:
        delay: how long after its step (s) a segment ends at the driver; 0 = unstamped segments.
    """

    def __init__(self, delay: float) -> None:
        if not (math.isfinite(delay) and delay >= 0.0):
            raise ValueError("delay must be a finite number >= 0")
        self.delay = float(delay)
        # (receive time, age) of the joint_states of the window that no later one undercuts: the ages
        # rise from front to back and the front is the window's least (asked for every control step,
        # kept up to date per message instead of searched).
        self._ages: deque[tuple[float, float]] = deque()

    def joint_state(self, stamp: float, now: float) -> None:
        """A joint_states message stamped ``stamp`` (s, driver's clock; 0 = unstamped) received at
        ``now`` (s, this node's ROS clock)."""
        age = now - stamp if stamp > 0.0 else math.inf
        ages = self._ages
        while ages and ages[-1][1] >= age:
            ages.pop()
        ages.append((now, age))
        while ages and now - ages[0][0] > CLOCK_WINDOW_S:
            ages.popleft()

    def offset(self) -> float:
        """Least age (s) of the recent joint_states (inf: none, or unstamped)."""
        return self._ages[0][1] if self._ages else math.inf

    def clocks_agree(self) -> bool:
        """Whether the driver's clock is this node's (see the module docstring)."""
        least = self.offset()
        return CLOCK_AGREES_S[0] <= least <= CLOCK_AGREES_S[1]

    @property
    def stamping(self) -> bool:
        """Whether segments go out stamped now."""
        return self.delay > 0.0 and self.clocks_agree()

    def segment(self, t_step: float, dt: float) -> Segment:
        """Timing of the segment of a step at ``t_step`` (s, ROS clock) that planned ``dt`` s of motion:
        it ends ``delay`` after the step (stamped), or ``dt`` after its receipt (unstamped)."""
        dt = max(dt, 1e-3)
        if not self.stamping:
            return Segment(None, dt)
        return Segment(t_step + self.delay - dt, dt)
