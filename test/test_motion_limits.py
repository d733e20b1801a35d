"""The shared motion limits: the discrete braking law lands exactly, its inverse, JointLimits."""

from __future__ import annotations

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.motion import (
    JointLimits,
    braking_distance,
    braking_speed,
    braking_speed_scalar,
    velocity_bounds,
)


def test_vector_and_scalar_braking_speed_agree() -> None:
    rng = np.random.default_rng(3)
    d = np.concatenate([[0.0, -1.0, 1e-12, 1e-9], rng.uniform(0, 3, 500), rng.uniform(0, 1e-4, 200)])
    a = rng.uniform(0.2, 20.0, d.size)
    for dt in (1e-3, 4e-3, 1e-2):
        v = braking_speed(d, a, dt)
        ref = np.array([braking_speed_scalar(float(x), float(y), dt) for x, y in zip(d, a, strict=True)])
        np.testing.assert_allclose(v, ref, rtol=1e-12, atol=1e-15)


def test_braking_speed_of_an_arm_s_few_joints_is_the_array_law_exactly() -> None:
    # Small arrays and scalars go through the scalar law value by value: the same numbers as the
    # numpy law, bit for bit; NaN, inf and a zero acceleration give the numpy law's answers too.
    from redarm_ros.motion.limits import _braking_speed_array

    rng = np.random.default_rng(5)
    for k in range(3000):
        n = int(rng.integers(1, 10))
        d = float(rng.choice([1e-9, 1e-4, 0.1, 3.0])) * rng.standard_normal(n)
        a = rng.uniform(0.1, 20.0, n) if k % 2 else float(rng.uniform(0.1, 20.0))
        dt = float(rng.choice([1e-3, 4e-3, 1e-2]))
        got = braking_speed(d, a, dt)
        assert np.array_equal(got, _braking_speed_array(d, np.asarray(a), dt)), (d, a, dt)
    assert braking_speed(0.3, 2.0, 0.01).shape == ()
    assert float(braking_speed(0.3, 2.0, 0.01)) == braking_speed_scalar(0.3, 2.0, 0.01)
    with np.errstate(all="ignore"):
        odd = braking_speed(np.array([np.nan, np.inf, 1.0, -np.inf]), np.array([1.0, 1.0, 0.0, 1.0]), 0.01)
        ref = _braking_speed_array(np.array([np.nan, np.inf, 1.0, -np.inf]), np.array([1.0, 1.0, 0.0, 1.0]),
                                   0.01)
    np.testing.assert_array_equal(odd, ref)


@pytest.mark.parametrize("dt", [1e-3, 4e-3])
def test_a_joint_keeping_to_the_braking_speed_stops_exactly_on_the_point(dt: float) -> None:
    rng = np.random.default_rng(11)
    for _ in range(200):
        a, vmax = rng.uniform(0.5, 12.0), rng.uniform(0.3, 6.0)
        stop = rng.uniform(1e-4, 2.0)
        p, v = 0.0, 0.0
        for _ in range(100_000):
            v = min(v + a * dt, vmax, braking_speed_scalar(stop - p, a, dt))
            p += v * dt
            assert p <= stop + 1e-12
            if v == 0.0:
                break
        assert p == pytest.approx(stop, abs=1e-12)


def test_braking_speed_never_decelerates_harder_than_the_limit() -> None:
    a, dt = 2.0, 4e-3
    d = np.linspace(0.0, 1.0, 20001)
    v = braking_speed(d, a, dt)
    # Stepping at v from d lands at d - v dt, whose braking speed is exactly v - a dt.
    nxt = braking_speed(d - v * dt, a, dt)
    np.testing.assert_allclose(nxt, np.maximum(v - a * dt, 0.0), atol=1e-12)
    assert np.all(v <= np.sqrt(2 * a * d) + 1e-12)
    assert v[-1] == pytest.approx(np.sqrt(2 * a * 1.0), rel=0.01)


def test_braking_distance_is_the_inverse() -> None:
    rng = np.random.default_rng(5)
    d = rng.uniform(0, 2.0, 1000)
    a = rng.uniform(0.5, 10, 1000)
    np.testing.assert_allclose(braking_distance(braking_speed(d, a, 4e-3), a, 4e-3), d, atol=1e-12)
    assert braking_distance(0.0, 1.0, 1e-3) == 0.0
    assert braking_distance(-2.0, 2.0, 1e-3) == braking_distance(2.0, 2.0, 1e-3)
    assert braking_distance(10.0, 2.0, 1e-5) == pytest.approx(10.0**2 / 4.0, rel=1e-3)


@pytest.mark.slow
def test_velocity_bounds_keep_a_random_walk_inside_the_limits() -> None:
    rng = np.random.default_rng(7)
    lim = JointLimits([-1.0, -0.2], [1.0, 0.3], [1.0, 2.0], [2.0, 8.0])
    q, v, dt = np.zeros(2), np.zeros(2), 4e-3
    for _ in range(20000):
        lo, hi = lim.velocity_bounds(q, v, dt)
        assert np.all(lo <= hi + 1e-12)
        v_new = rng.uniform(lo, hi)
        assert np.all(np.abs(v_new - v) <= lim.max_acc * dt + 1e-12)
        assert np.all(np.abs(v_new) <= lim.max_vel + 1e-12)
        q, v = q + v_new * dt, v_new
        assert np.all(lim.contains(q, tol=1e-12)), q


def test_velocity_bounds_let_the_position_limit_win_when_already_too_fast() -> None:
    lo, hi = velocity_bounds([0.99], [1.0], 1e-3, [-1.0], [1.0], [1.0], [2.0])
    stop = braking_speed(0.01, 2.0, 1e-3)
    assert hi[0] == pytest.approx(stop) and lo[0] == pytest.approx(stop)


def test_joint_limits_validation_and_helpers() -> None:
    lim = JointLimits([-1, -2], [1, 2], [1, 1], [2, 2])
    assert lim.n == 2
    with pytest.raises(ValueError):
        lim.lower[0] = 5.0  # read-only
    np.testing.assert_allclose(lim.clip([3, -3]), [1, -2])
    np.testing.assert_array_equal(lim.contains([1.0005, 0], tol=1e-3), [True, True])
    np.testing.assert_array_equal(lim.contains([1.0005, 0]), [False, True])
    ins = lim.inset(0.01)
    np.testing.assert_allclose(ins.lower, [-0.99, -1.99])
    np.testing.assert_allclose(ins.upper, [0.99, 1.99])
    tight = JointLimits([0.0], [0.01], [1], [1]).inset(0.1)
    assert tight.lower[0] == tight.upper[0] == pytest.approx(0.005)
    np.testing.assert_allclose(lim.max_jump(0.5, 0.02), [0.52, 0.52])
    up, down = lim.stop_speeds([0.5, 0.0], 1e-3)
    assert up[0] < up[1] and down[0] > up[0]
    for bad in (dict(lower=[0, 0], upper=[1], max_vel=[1, 1], max_acc=[1, 1]),
                dict(lower=[1], upper=[0], max_vel=[1], max_acc=[1]),
                dict(lower=[0], upper=[1], max_vel=[0], max_acc=[1]),
                dict(lower=[np.nan], upper=[1], max_vel=[1], max_acc=[1])):
        with pytest.raises(InvalidInputError):
            JointLimits(**bad)
    with pytest.raises(InvalidInputError):
        lim.inset(-1.0)
