"""The driver loop's ``park`` request and the synchronised move it plans (no ROS, emulated modules)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from support.loop_rig import AMAX, LOWER, Q0, UPPER, VMAX, loop_rig
from support.waits import wait_until

from redarm_ros.can.driver_loop import CommandMode, JointCommandSource, LoopConfig, LoopState
from redarm_ros.can.module_emulator import EmulatedArm
from redarm_ros.errors import InvalidInputError
from redarm_ros.motion import JointLimits
from redarm_ros.motion.sync_move import synchronized_move

PARK = (0.6, -0.8, 1.2)
LIMITS = JointLimits(LOWER, UPPER, VMAX, AMAX)


def test_synchronized_move_is_one_straight_line_within_the_scaled_limits() -> None:
    q0, q1, dt = np.array([0.1, 1.2, -1.9]), np.array([1.9, -1.0, 0.4]), 0.004
    t, p = synchronized_move(q0, q1, LIMITS, dt, scale=0.9)
    np.testing.assert_allclose(np.diff(t), dt)
    np.testing.assert_array_equal(p[-1], q1)
    full = np.vstack([q0, p])
    # One straight line: every point is q0 + s (q1 - q0) with the same s for every joint.
    s = (full - q0) / (q1 - q0)
    np.testing.assert_allclose(s, s[:, :1].repeat(3, axis=1), atol=1e-12)
    assert np.all(np.diff(s[:, 0]) >= -1e-15)  # monotone: no back and forth
    v = np.diff(full, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    assert np.all(np.abs(v) <= 0.9 * np.array(VMAX) + 1e-9)
    assert np.all(np.abs(a) <= 0.9 * np.array(AMAX) * (1 + 1e-6) + 1e-9)
    # The slowest joint goes at (nearly) its full scaled speed: the move is not needlessly slow.
    assert np.max(np.abs(v) / (0.9 * np.array(VMAX))) > 0.95


def test_synchronized_move_of_zero_length_and_bad_input() -> None:
    t, p = synchronized_move([0.1, 0.2, 0.3], [0.1, 0.2, 0.3], LIMITS, 0.01)
    assert t.tolist() == [0.01] and p.tolist() == [[0.1, 0.2, 0.3]]
    with pytest.raises(InvalidInputError):
        synchronized_move([0.0, 0.0, 0.0], [0.0, 1.6, 0.0], LIMITS, 0.01)  # beyond the limit
    with pytest.raises(InvalidInputError):
        synchronized_move([0.0, 0.0], [0.0, 0.0], LIMITS, 0.01)


def test_park_move_advances_one_planned_step_per_cycle_whatever_the_clock() -> None:
    q0 = np.array(Q0)
    times, points = synchronized_move(q0, PARK, LIMITS, 0.01, scale=0.9)
    src = JointCommandSource(3)
    src.set_park(times, points, 0.01)
    # Cycles that come late, skip ticks or bunch up (an overloaded machine): the samples are still
    # the planned points one after the other, so the move stays one synchronised line.
    rng = np.random.default_rng(3)
    now = 100.0 + np.cumsum(rng.choice([0.01, 0.01, 0.02, 0.05, 0.001], len(times) + 5))
    got = np.array([src.sample(t, q0, q0) for t in now])
    np.testing.assert_array_equal(got[0], q0)  # the first cycle starts from the reference
    np.testing.assert_allclose(got[1:len(times) + 1], points, atol=1e-12)
    np.testing.assert_array_equal(got[-1], points[-1])
    assert src.mode is CommandMode.PARK
    with pytest.raises(InvalidInputError):
        src.set_park(times, points, 0.0)


@pytest.fixture
def rig():
    """Emulated 3-module arm on a virtual channel and a DriverLoop with a park posture."""
    arm = EmulatedArm.kinematic(LOWER, UPPER, VMAX, AMAX, q0=Q0)
    cfg = LoopConfig(rate_hz=100.0, poll_hz=20.0, reconnect_first_s=0.02, reconnect_max_s=0.1, park=PARK)
    with loop_rig(arm, cfg) as r:
        yield r


def test_park_is_refused_before_init_and_while_halted(rig) -> None:
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE)
    ok, msg = loop.request("park", timeout=10)
    assert not ok and "not initialised" in msg
    ok, msg = loop.request("init", timeout=20)
    assert ok, msg
    ok, msg = loop.request("halt", timeout=10)
    assert ok, msg
    q_halted = np.array(rig["arm"].positions())
    ok, msg = loop.request("park", timeout=10)
    assert not ok and "halted" in msg and "~/recover" in msg
    time.sleep(0.3)
    np.testing.assert_allclose(rig["arm"].positions(), q_halted, atol=1e-6)  # nothing moved



def test_park_stays_refused_when_recover_is_tried_instead_of_init(rig) -> None:
    # recover must not stand in for init: the arm was never homed, so park (a move) stays refused.
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE)
    q0 = np.array(rig["arm"].positions())
    ok, msg = loop.request("recover", timeout=10)
    assert not ok and "never initialised" in msg, msg
    ok, msg = loop.request("park", timeout=10)
    assert not ok and "not initialised" in msg, msg
    assert loop.request("halt", timeout=10)[0]
    ok, msg = loop.request("recover", timeout=10)
    assert not ok and "never initialised" in msg, msg
    ok, msg = loop.request("park", timeout=10)
    assert not ok, msg
    time.sleep(0.3)
    np.testing.assert_allclose(rig["arm"].positions(), q0, atol=1e-6)  # nothing moved

def test_park_answers_when_the_arm_is_there_within_the_limits(rig) -> None:
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE)
    ok, msg = loop.request("init", timeout=20)
    assert ok, msg
    n0 = len(rig["samples"])
    ok, msg = loop.request("park", timeout=20)
    assert ok, msg
    assert "parked" in msg
    np.testing.assert_allclose(rig["arm"].positions(), PARK, atol=2e-3)  # there when it answers
    assert loop.commands.mode is CommandMode.PARK
    # The reference sent each cycle kept the velocity and acceleration limits (100 Hz cycles).
    refs = np.array([s.target for s in rig["samples"][n0:] if s.target is not None])
    assert len(refs) > 50, len(refs)  # the move took cycles (not an empty check)
    v = np.diff(refs, axis=0) * 100.0
    a = np.diff(v, axis=0) * 100.0
    assert np.all(np.abs(v) <= np.array(VMAX) + 1e-6)
    assert np.all(np.abs(a) <= np.array(AMAX) + 1e-6)
    assert np.all(refs >= np.array(LOWER)) and np.all(refs <= np.array(UPPER))


def test_park_interrupted_by_halt_reports_it(rig) -> None:
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE)
    assert loop.request("init", timeout=20)[0]
    answer: list[tuple[bool, str]] = []
    t = threading.Thread(target=lambda: answer.append(loop.request("park", timeout=20)))
    t.start()
    assert wait_until(lambda: loop.commands.mode is CommandMode.PARK)
    ok, msg = loop.request("halt", timeout=10)
    assert ok, msg
    t.join(10)
    assert answer and not answer[0][0] and "interrupted" in answer[0][1], answer
