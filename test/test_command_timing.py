"""CommandClock: when the controller's command segments are due at the driver, and the clock check."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.nodes.command_timing import CLOCK_WINDOW_S, CommandClock


def test_segments_end_the_delay_after_their_step_when_the_clocks_agree() -> None:
    clk = CommandClock(0.03)
    for k in range(20):
        clk.joint_state(stamp=100.0 + 0.004 * k, now=100.002 + 0.004 * k)  # 2 ms old: the same clock
    seg = clk.segment(t_step=100.2, dt=0.012)
    assert clk.stamping
    assert seg.duration == pytest.approx(0.012)
    assert seg.stamp is not None and seg.stamp + seg.duration == pytest.approx(100.2 + 0.03)


@pytest.mark.parametrize("offset", [5.0, 0.05, -1.0])
def test_segments_go_out_unstamped_when_the_driver_clock_differs(offset: float) -> None:
    clk = CommandClock(0.03)
    for k in range(20):
        clk.joint_state(stamp=100.0 + 0.01 * k + offset, now=100.0 + 0.01 * k)
    assert not clk.stamping
    assert clk.offset() == pytest.approx(-offset)
    seg = clk.segment(t_step=100.2, dt=0.01)
    assert seg.stamp is None and seg.duration == pytest.approx(0.01)


def test_unstamped_joint_states_or_none_mean_unstamped_segments() -> None:
    clk = CommandClock(0.03)
    assert not clk.stamping and math.isinf(clk.offset())
    assert clk.segment(t_step=50.0, dt=0.01).stamp is None  # no joint_states yet
    clk.joint_state(stamp=0.0, now=50.0)
    assert not clk.stamping
    assert clk.segment(t_step=50.0, dt=0.01).stamp is None  # an unstamped one


def test_the_check_forgets_samples_older_than_its_window() -> None:
    clk = CommandClock(0.03)
    clk.joint_state(stamp=10.0, now=10.001)
    assert clk.stamping
    # The driver's clock jumps (restarted elsewhere): after the window only the new samples count.
    clk.joint_state(stamp=3.0, now=10.0 + CLOCK_WINDOW_S + 0.1)
    assert not clk.stamping


def test_a_zero_delay_never_stamps() -> None:
    clk = CommandClock(0.0)
    clk.joint_state(stamp=10.0, now=10.001)
    assert clk.segment(10.0, 0.01).stamp is None
    with pytest.raises(ValueError):
        CommandClock(-0.1)


def test_the_offset_is_the_least_age_within_the_window() -> None:
    """Kept up to date per message: the least age of the joint_states received within the last
    CLOCK_WINDOW_S, as a search over them all would find, with ages rising, falling and unstamped."""
    rng = np.random.default_rng(7)
    clk = CommandClock(0.03)
    seen: list[tuple[float, float]] = []
    now = 50.0
    for _ in range(600):
        now += float(rng.uniform(0.0, 0.03))
        stamped = rng.random() > 0.1
        stamp = now - float(rng.uniform(-0.01, 0.3)) if stamped else 0.0
        clk.joint_state(stamp, now)
        seen.append((now, now - stamp if stamped else math.inf))
        window = [age for t, age in seen if now - t <= CLOCK_WINDOW_S]
        assert clk.offset() == min(window)
