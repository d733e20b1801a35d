"""joint_limits: the per-step velocity/acceleration/position limiter and braking helpers."""

from __future__ import annotations

import numpy as np
import pytest

from redarm_ros.control.joint_limits import (
    JointBounds,
    LimitMode,
    brake_step,
    braking_speed,
    limit_step,
    track_step,
    velocity_bounds,
)

DT = 0.01
VMAX = np.array([1.0, 2.0, 6.0])
AMAX = np.array([2.0, 4.0, 12.0])
LO = np.array([-1.0, -2.0, -3.0])
HI = np.array([1.0, 2.0, 3.0])


def test_exact_when_the_target_fits() -> None:
    q0 = np.zeros(3)
    v0 = np.array([0.5, -0.5, 1.0])
    target = q0 + (v0 + 0.5 * AMAX * DT) * DT
    r = limit_step(q0, v0, target, DT, VMAX, AMAX, LO, HI)
    assert r.mode is LimitMode.EXACT and np.allclose(r.q, target)


def test_scaled_keeps_the_direction() -> None:
    q0 = np.zeros(3)
    target = np.array([0.01, 0.02, 0.03])  # from rest: 1, 2, 3 rad/s asked, 0.02 .. 0.12 allowed
    r = limit_step(q0, np.zeros(3), target, DT, VMAX, AMAX, LO, HI)
    assert r.mode is LimitMode.SCALED
    assert 0.0 < r.alpha < 1.0
    assert np.allclose(r.q / np.linalg.norm(r.q), target / np.linalg.norm(target))
    assert np.all(np.abs(r.v) <= AMAX * DT + 1e-12)


def test_clipped_when_one_joint_must_brake_and_another_speed_up() -> None:
    q0 = np.zeros(3)
    v0 = np.array([1.0, 0.0, 0.0])
    target = np.array([-0.01, 0.01, 0.0])  # reverse joint 0 at once, start joint 1
    r = limit_step(q0, v0, target, DT, VMAX, AMAX, LO, HI)
    assert r.mode is LimitMode.CLIPPED
    assert np.all(np.abs(r.v - v0) <= AMAX * DT + 1e-12)
    assert r.v[0] < v0[0] and r.v[1] > 0.0  # joint 0 brakes, joint 1 starts


def test_braking_speed_stops_on_the_spot() -> None:
    for d in (0.0, 1e-6, 1e-3, 0.1, 1.0):
        v = float(braking_speed(d, 2.0, DT))
        # simulate: move at v, then brake by a*dt each step; never pass the stop point
        q, vel = 0.0, v
        while vel > 0.0:
            q += vel * DT
            vel = max(vel - 2.0 * DT, 0.0)
        assert q <= d + 1e-12
        assert q == pytest.approx(d, abs=1e-9)  # ... and stop on it: the largest such speed
        assert (v > 0.0) == (d > 0.0)


def test_random_steps_always_respect_every_limit() -> None:
    rng = np.random.default_rng(7)
    q = np.zeros(3)
    v = np.zeros(3)
    for _ in range(3000):
        target = q + rng.normal(0.0, 0.05, 3)  # including targets beyond the position limits
        r = limit_step(q, v, target, DT, VMAX, AMAX, LO, HI)
        assert np.all(r.q >= LO) and np.all(r.q <= HI)
        assert np.all(np.abs(r.v) <= VMAX + 1e-9)
        assert np.all(np.abs(r.v - v) <= AMAX * DT + 1e-9)
        # the joints can always still stop before a limit
        lo, hi = velocity_bounds(r.q, r.v, DT, VMAX, AMAX, LO, HI)
        assert np.all(lo <= hi + 1e-12)
        q, v = r.q, r.v


def test_brake_step() -> None:
    q, v = brake_step(np.zeros(3), np.array([1.0, -0.01, 0.0]), DT, AMAX, LO, HI)
    assert np.allclose(v, [1.0 - 2.0 * DT, 0.0, 0.0])
    assert np.allclose(q, v * DT)


def test_the_controller_brakes_by_the_shared_motion_law() -> None:
    """One braking law for controller, driver shaper and simulator: redarm_ros.motion.limits."""
    from redarm_ros.control.joint_limits import braking_distance
    from redarm_ros.motion import limits as motion

    d = np.array([0.0, 1e-5, 0.01, 0.3, 2.0])
    np.testing.assert_array_equal(braking_speed(d, 2.0, DT), motion.braking_speed(d, 2.0, DT))
    for x in d:  # the scalar path gives the same numbers
        assert float(braking_speed(float(x), 2.0, DT)) == pytest.approx(
            float(motion.braking_speed(x, 2.0, DT)), rel=1e-12, abs=1e-15)
    np.testing.assert_allclose(braking_distance(braking_speed(d, 2.0, DT), 2.0, DT), d, atol=1e-12)
    q, v = np.full(3, 0.3), np.array([0.5, -0.2, 0.0])
    ours = velocity_bounds(q, v, DT, VMAX, AMAX, LO, HI)
    theirs = motion.velocity_bounds(q, v, DT, LO, HI, VMAX, AMAX)
    np.testing.assert_array_equal(ours[0], theirs[0])
    np.testing.assert_array_equal(ours[1], theirs[1])


def _track_step_arrays(q: np.ndarray, qd: np.ndarray, q_ref: np.ndarray, qd_ref: np.ndarray, dt: float,
                       b: JointBounds) -> tuple[np.ndarray, np.ndarray]:
    """track_step as the controller wrote it in numpy before (the reference for the float loop)."""
    u = np.clip(qd_ref, -b.max_vel, b.max_vel)
    e = q_ref - u * dt - q
    v_des = u + np.sign(e) * braking_speed(np.abs(e), b.max_acc, dt)
    e = q_ref - q
    lo, hi = velocity_bounds(q, qd, dt, b.max_vel, b.max_acc, b.lower, b.upper)
    v = np.clip(v_des, lo, hi)
    small = np.abs(e) <= 1e-12
    v = np.where(small & (np.abs(qd_ref) <= 1e-12) & (lo <= 0.0) & (hi >= 0.0), 0.0, v)
    q_new = np.clip(q + v * dt, b.lower, b.upper)
    q_new = np.where(np.abs(q_ref - q_new) <= 1e-12, q_ref, q_new)
    return q_new, (q_new - q) / dt


def test_track_step_gives_the_same_floats_as_the_array_form() -> None:
    """Bit for bit, signed zeros included: random states, and values on the limits, at rest, exactly
    on the reference and on +-0."""
    rng = np.random.default_rng(7)
    b = JointBounds(LO, HI, VMAX, 1.0 / VMAX, AMAX)
    picks = np.array([0.0, -0.0, 1e-13, -1e-13, 1.0, -1.0, 2.0, -2.0, 6.0, -6.0, 3.0, -3.0, 0.02, -0.02])
    for k in range(3000):
        if k % 2:
            q, qd, qr, vr = (rng.choice(picks, 3) for _ in range(4))
        else:
            q = rng.uniform(LO - 0.1, HI + 0.1)
            qd, vr = rng.uniform(-1.5 * VMAX, 1.5 * VMAX), rng.uniform(-1.5 * VMAX, 1.5 * VMAX)
            qr = q + rng.choice([0.0, 1e-13, 1e-3, 0.1, 1.0]) * rng.normal(size=3)
        q = np.clip(q, LO, HI)
        want_q, want_qd = _track_step_arrays(q, qd, qr, vr, DT, b)
        got_q, got_qd = track_step(q.tolist(), qd.tolist(), qr.tolist(), vr.tolist(), DT, b)
        assert np.array(got_q).tobytes() == want_q.tobytes(), (q, qd, qr, vr)
        assert np.array(got_qd).tobytes() == want_qd.tobytes(), (q, qd, qr, vr)
