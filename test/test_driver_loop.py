"""Tests of the ROS-free driver loop pieces: command source, period statistics, backoff."""

from __future__ import annotations

import numpy as np
import pytest

from redarm_ros.can.driver_loop import Backoff, CommandMode, JointCommandSource, PeriodStats
from redarm_ros.errors import InvalidInputError

N = 3


def test_hold_uses_measured_position_until_a_command_arrives() -> None:
    src = JointCommandSource(N)
    meas = np.array([0.1, 0.2, 0.3])
    q = src.sample(0.0, q_ref=np.zeros(N), q_measured=meas)
    np.testing.assert_allclose(q, meas)
    # Later measurements do not move a hold: the arm stays where it was.
    q = src.sample(1.0, q_ref=np.zeros(N), q_measured=meas + 1)
    np.testing.assert_allclose(q, meas)
    assert src.mode is CommandMode.HOLD


def test_trajectory_interpolates_from_the_reference_and_keeps_the_last_point() -> None:
    src = JointCommandSource(N)
    ref = np.array([0.0, 1.0, 2.0])
    # Joints 2 and 0 (in that order), two points.
    src.set_trajectory([2, 0], [1.0, 3.0], np.array([[3.0, 1.0], [1.0, -1.0]]), start=10.0)
    np.testing.assert_allclose(src.sample(9.0, ref, ref), ref)  # before start: the reference
    ref_later = ref + 5  # a changed reference after the first sample must not matter
    np.testing.assert_allclose(src.sample(10.5, ref_later, ref), [0.5, 1.0, 2.5])
    np.testing.assert_allclose(src.sample(11.0, ref_later, ref), [1.0, 1.0, 3.0])
    np.testing.assert_allclose(src.sample(12.0, ref_later, ref), [0.0, 1.0, 2.0])
    np.testing.assert_allclose(src.sample(99.0, ref_later, ref), [-1.0, 1.0, 1.0])
    assert src.mode is CommandMode.TRAJECTORY


def test_trajectory_point_at_time_zero_is_a_step() -> None:
    src = JointCommandSource(N)
    src.set_trajectory([0, 1, 2], [0.0], np.array([[1.0, 2.0, 3.0]]), start=0.0)
    np.testing.assert_allclose(src.sample(0.001, np.zeros(N), np.zeros(N)), [1, 2, 3])


@pytest.mark.parametrize(
    ("index", "times", "points"),
    [
        ([0], [1.0], np.array([[np.nan]])),
        ([0], [2.0, 1.0], np.array([[0.0], [1.0]])),
        ([0], [-1.0], np.array([[0.0]])),
        ([0, 0], [1.0], np.array([[0.0, 1.0]])),
        ([5], [1.0], np.array([[0.0]])),
        ([0, 1], [1.0], np.array([[0.0]])),
        ([], [], np.zeros((0, 0))),
    ],
)
def test_bad_trajectories_are_refused_and_do_not_replace_the_command(index, times, points) -> None:
    src = JointCommandSource(N)
    src.set_trajectory([0], [1.0], np.array([[0.5]]), start=0.0)
    gen = src.generation
    with pytest.raises(InvalidInputError):
        src.set_trajectory(index, times, points, start=0.0)
    assert src.generation == gen
    assert src.mode is CommandMode.TRAJECTORY


def test_stream_follows_then_holds_measured_position_when_it_stops() -> None:
    src = JointCommandSource(N, stream_timeout_s=0.5)
    ref = np.array([0.0, 0.0, 0.0])
    src.set_stream_target([1], [0.7], now=1.0)
    np.testing.assert_allclose(src.sample(1.2, ref, ref), [0.0, 0.7, 0.0])
    meas = np.array([0.0, 0.4, 0.0])  # the arm has not got there yet
    q = src.sample(1.6, np.array([0.0, 0.7, 0.0]), meas)
    np.testing.assert_allclose(q, meas)
    assert src.mode is CommandMode.HOLD
    np.testing.assert_allclose(src.sample(5.0, ref, ref + 3), meas)
    with pytest.raises(InvalidInputError):
        src.set_stream_target([0], [np.inf], now=2.0)


def test_clear_drops_the_command() -> None:
    src = JointCommandSource(N)
    src.set_trajectory([0], [1.0], np.array([[2.0]]), start=0.0)
    src.clear(np.array([9.0, 9.0, 9.0]))
    np.testing.assert_allclose(src.sample(5.0, np.zeros(N), np.zeros(N)), 9.0)
    src.clear(None)
    np.testing.assert_allclose(src.sample(5.0, np.zeros(N), np.ones(N)), 1.0)


def test_period_stats() -> None:
    st = PeriodStats(0.004, window=100)
    assert st.summary()["samples"] == 0
    for p in [0.004] * 98 + [0.005, 0.006]:
        st.add(p)
    s = st.summary()
    assert s["samples"] == 100
    assert s["period_err_median_ms"] == pytest.approx(0.0, abs=1e-9)
    assert s["period_err_max_ms"] == pytest.approx(2.0)
    assert 0.9 < s["period_err_p99_ms"] <= 2.0
    assert s["rate_hz"] == pytest.approx(1 / np.mean([0.004] * 98 + [0.005, 0.006]))


def test_backoff_doubles_to_a_cap_and_resets() -> None:
    b = Backoff(0.1, 0.5)
    assert [b.next_delay() for _ in range(5)] == pytest.approx([0.1, 0.2, 0.4, 0.5, 0.5])
    b.reset()
    assert b.next_delay() == pytest.approx(0.1)
