"""Analytic IK of the 6-DOF PowerCube arm (joint 3 locked), position-only modes and nearest solution."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import IKStatus, PowerCube6Arm, load_arm

ARM = load_arm("powercube6")


def _rand_q(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(ARM.lower, ARM.upper, size=(n, 6))


def test_kind_and_contract() -> None:
    assert isinstance(ARM, PowerCube6Arm) and ARM.n == 6 and not ARM.has_swivel
    q = _rand_q(1, 0)[0]
    assert ARM.swivel(q) == 0.0
    kp = ARM.key_points(q)  # base, shoulder (L1 offset), elbow, wrist pitch, tool
    assert np.isclose(np.linalg.norm(kp[1] - kp[0]), 0.13)
    assert np.isclose(np.linalg.norm(kp[2] - kp[1]), 0.36)
    assert np.isclose(np.linalg.norm(kp[3] - kp[2]), 0.18)
    assert np.isclose(np.linalg.norm(kp[4] - kp[3]), 0.26)


def test_round_trip_full_pose() -> None:
    for q in _rand_q(300, 1):
        T = ARM.fk(q)
        sols = ARM.ik(T)
        assert 1 <= len(sols) <= 4
        assert np.any(np.all(np.abs(sols - q) < 1e-8, axis=1))
        for sol in sols:
            assert np.max(np.abs(ARM.fk(sol) - T)) < 1e-9
            assert ARM.within_limits(sol) and sol[2] == 0.0
        assert np.array_equal(ARM.ik(T, swivel=1.23), sols)  # swivel is ignored


def test_orientation_outside_the_arm_plane_is_unreachable() -> None:
    q = np.array([0.4, 0.3, 0.0, 0.8, -0.5, 0.2])
    T = ARM.fk(q)
    Rz = np.array([[math.cos(0.3), -math.sin(0.3), 0], [math.sin(0.3), math.cos(0.3), 0], [0, 0, 1]])
    T2 = T.copy()
    T2[:3, :3] = Rz @ T[:3, :3]  # approach turned out of the vertical plane through the base
    assert ARM.ik(T2).shape == (0, 6)
    qn, info = ARM.ik_nearest(T2, q)
    assert qn is None and info.status is IKStatus.OUT_OF_REACH and "joint 3" in info.message
    qp, infop = ARM.ik_nearest(T2, q, position_only=True)
    assert infop.ok and infop.pos_err < 1e-9
    assert qp is not None and np.linalg.norm(ARM.fk(qp)[:3, 3] - T2[:3, 3]) < 1e-9
    far = T.copy()
    far[:3, 3] = [2.0, 0.0, 0.0]
    qn, info = ARM.ik_nearest(far, q)
    assert qn is None and info.status is IKStatus.OUT_OF_REACH


def test_ik_nearest_picks_the_seed_branch() -> None:
    rng = np.random.default_rng(2)
    for q in _rand_q(50, 3):
        if abs(q[3]) < 0.02:  # elbow (nearly) stretched: both elbow branches are next to the seed
            continue
        qn, info = ARM.ik_nearest(ARM.fk(q), q + rng.normal(0, 0.001, 6) * [1, 1, 0, 1, 1, 1])
        assert info.ok and np.allclose(qn, q, atol=1e-8)
    qn, info = ARM.ik_nearest(ARM.fk(q), np.zeros(5))
    assert qn is None and info.status is IKStatus.INVALID_INPUT


def _pos_ok(sols: np.ndarray, p: np.ndarray) -> None:
    assert len(sols) >= 1
    for sol in sols:
        assert np.allclose(ARM.fk(sol)[:3, 3], p, atol=1e-9)
        assert ARM.within_limits(sol)


def test_position_only_modes() -> None:
    q = np.array([0.7, 0.4, 0.0, 0.6, -0.5, 0.3])
    p = ARM.fk(q)[:3, 3]
    psi = q[1] + q[3] + q[4]
    sols = ARM.ik_position(p, psi=psi, roll=0.3)
    _pos_ok(sols, p)
    assert np.any(np.all(np.abs(sols - q) < 1e-9, axis=1))
    for sol in sols:  # the approach angle is the one asked for
        assert abs(math.remainder(sol[1] + sol[3] + sol[4] - psi, 2 * math.pi)) < 1e-9
    sols = ARM.ik_position(p, phi5=q[4], roll=0.3)
    _pos_ok(sols, p)
    assert np.allclose(sols[:, 4], q[4]) and np.any(np.all(np.abs(sols - q) < 1e-9, axis=1))
    q0 = np.array([0.7, 0.4, 0.0, 0.0, -0.5, 0.0])  # phi4 = 0: the paper's optimal region
    p0 = ARM.fk(q0)[:3, 3]
    sols = ARM.ik_position(p0)
    _pos_ok(sols, p0)
    assert np.allclose(sols[:, 3], 0.0) and np.any(np.all(np.abs(sols - q0) < 1e-9, axis=1))
    assert ARM.ik_position([3.0, 0.0, 0.0]).shape == (0, 6)
    with pytest.raises(InvalidInputError):
        ARM.ik_position(p, psi=0.1, phi5=0.2)
    with pytest.raises(InvalidInputError):
        ARM.ik_position([np.nan, 0, 0])


def test_target_on_the_base_axis() -> None:
    # upper arm vertical, elbow at 90 deg, wrist pitched so that s = L1 - L4 - L56 cos(phi5) = 0
    phi5 = math.acos((0.13 - 0.18) / 0.26)
    q = np.array([0.0, math.pi / 2, 0.0, math.pi / 2, phi5, 0.0])
    T = ARM.fk(q)
    assert abs(T[0, 3]) < 1e-12 and abs(T[1, 3]) < 1e-12
    sols = ARM.ik(T)
    assert len(sols) >= 1 and np.all(np.isfinite(sols))
    for sol in sols:
        assert np.max(np.abs(ARM.fk(sol) - T)) < 1e-9


def test_batch() -> None:
    Qs = _rand_q(20, 4)
    Ts = ARM.fk_batch(Qs)
    Q, valid = ARM.ik_batch(Ts)
    assert Q.shape == (20, 4, 6) and valid.shape == (20, 4)
    for i in range(20):
        assert np.allclose(Q[i][valid[i]], ARM.ik(Ts[i]))
