"""ReplyDeadline: the modules get the whole timeout of our listening, however the process stalls."""

from __future__ import annotations

import pytest

from redarm_ros.can.reply_deadline import MAX_RESTARTS, STALL_S, ReplyDeadline


class Clock:
    def __init__(self) -> None:
        self.t = 10.0

    def __call__(self) -> float:
        return self.t


def started(timeout_s: float) -> tuple[Clock, ReplyDeadline]:
    c = Clock()
    d = ReplyDeadline(c)
    d.start(c.t, timeout_s)
    return c, d


def test_without_stalls_the_deadline_is_the_timeout_after_the_start() -> None:
    c, d = started(0.02)
    c.t += 0.001  # sending
    assert d.left() == pytest.approx(0.019)
    c.t += 0.019  # a receive that waited the whole time, no frame
    d.waited(0.019)
    assert d.left() <= 0 and d.stalled_s == 0.0


@pytest.mark.parametrize(("timeout_s", "came_back_after_s"), [
    (0.02, 0.52),  # asked 20 ms, ran again 0.5 s later (empty)
    (0.5, 0.665),  # a frame that came after the machine stood still for longer than the timeout
])
def test_a_receive_that_came_back_late_restarts_the_wait(timeout_s: float, came_back_after_s: float) -> None:
    c, d = started(timeout_s)
    left = d.left()
    c.t += came_back_after_s
    d.waited(left)
    assert d.left() == pytest.approx(timeout_s)
    assert d.stalled_s == pytest.approx(came_back_after_s - timeout_s)


def test_a_pause_between_two_looks_at_the_clock_restarts_it_too() -> None:
    c, d = started(0.02)
    left = d.left()
    c.t += 0.005
    d.waited(left)  # a frame after 5 ms
    c.t += 0.3  # descheduled while handling it
    assert d.left() == pytest.approx(0.02)
    c.t += STALL_S / 2  # scheduling noise is not a stall
    assert d.left() == pytest.approx(0.02 - STALL_S / 2)


def test_restarts_are_bounded_so_a_silent_module_is_still_found() -> None:
    c, d = started(0.02)
    waited = 0.0
    for _ in range(100):  # a process that stalls after every receive
        left = d.left()
        if left <= 0:
            break
        c.t += left + 0.01
        waited += left
        d.waited(left)
    assert d.left() <= 0
    assert waited == pytest.approx((MAX_RESTARTS + 1) * 0.02)
