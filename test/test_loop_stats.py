"""LoopStats: a loop's own count of its steps, the ticks it skipped and its step durations."""

from __future__ import annotations

import math

import pytest

from redarm_ros.nodes.loop_stats import LoopStats


def test_a_punctual_loop_has_its_rate_and_misses_nothing() -> None:
    ls = LoopStats(0.01, window=1.0)
    for k in range(300):
        ls.step(5.0 + 0.01 * k, 0.009 if k == 299 else 0.003)
    s = ls.summary(5.0 + 2.995)  # half a period after the last step
    assert s.steps == 300 and s.missed == 0
    assert s.rate_hz == pytest.approx(100.0)
    assert s.clock == pytest.approx(5.0 + 2.99)
    assert s.busy_median == pytest.approx(0.003) and s.busy_max == pytest.approx(0.009)


def test_skipped_ticks_are_counted_and_lower_the_rate() -> None:
    ls = LoopStats(0.01, window=10.0)
    t = 0.0
    for k in range(100):  # every fourth step comes three periods after the previous: two ticks skipped
        t += 0.03 if k % 4 == 3 else 0.01
        ls.step(t, 0.001)
    s = ls.summary(t)
    assert s.missed == 2 * 25
    assert s.steps == 100
    assert s.rate_hz == pytest.approx(99 / (t - 0.01), rel=1e-9)
    assert s.rate_hz < 70.0


def test_jitter_within_half_a_period_is_not_a_miss() -> None:
    ls = LoopStats(0.01)
    for t in (0.0, 0.014, 0.02, 0.0345, 0.04):
        ls.step(t, 0.001)
    assert ls.summary(0.04).missed == 0


def test_before_two_steps_there_is_no_rate() -> None:
    ls = LoopStats(0.01)
    s = ls.summary(0.5)
    assert s.steps == 0 and s.rate_hz == 0.0 and math.isnan(s.clock) and math.isnan(s.busy_median)
    ls.step(1.0, 0.001)
    assert ls.summary(1.0).rate_hz == 0.0


def test_a_loop_that_stopped_stepping_shows_its_rate_falling_to_zero() -> None:
    ls = LoopStats(0.01, window=2.0)
    for k in range(300):
        ls.step(0.01 * k, 0.002)
    last = 2.99
    assert ls.summary(last + 0.005).rate_hz == pytest.approx(100.0)
    half = ls.summary(last + 1.0)  # steps in the last second only, over the 2 s window
    assert half.rate_hz == pytest.approx(100 / 2.0, rel=0.02) and half.idle_s == pytest.approx(1.0)
    gone = ls.summary(last + 3.0)
    assert gone.rate_hz == 0.0 and gone.steps == 300 and gone.idle_s == pytest.approx(3.0)
    assert math.isnan(gone.busy_median)


@pytest.mark.parametrize("period", [0.0, -0.01, math.nan, math.inf])
def test_a_bad_period_is_refused(period: float) -> None:
    with pytest.raises(ValueError, match="period"):
        LoopStats(period)


def test_a_rest_taken_on_purpose_is_no_missed_tick() -> None:
    ls = LoopStats(0.01, window=1.0)
    for k in range(10):
        ls.step(0.01 * k, 0.001)
    ls.pause()  # nothing to do: the loop rests for 5 s
    for k in range(10):
        ls.step(5.0 + 0.01 * k, 0.001)
    ls.step(5.2, 0.001)  # a gap after the rest is a miss again
    assert ls.summary(5.2).missed == 10 and ls.steps == 21
