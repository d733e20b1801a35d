"""Quaternion helpers, (w, x, y, z) order."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.quaternion import (
    from_xyzw,
    matrix_from_quat,
    matrix_to_quat,
    one_plus_nz,
    pose_to_matrix,
    qconj,
    qmul,
    qrotate,
    quat_angle,
    quat_conj,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_rotate,
    quat_to_matrix,
    qy,
    qz,
    rotation_error,
    rotvec_between,
    shortest_rotation,
    shortest_rotation_basis,
    shortest_rotation_xy,
    to_xyzw,
)


def _random_quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_matrix_roundtrip_and_product() -> None:
    for a, b in zip(_random_quats(50, 1), _random_quats(50, 2), strict=True):
        Ra, Rb = quat_to_matrix(a), quat_to_matrix(b)
        assert np.allclose(Ra @ Ra.T, np.eye(3), atol=1e-12)
        assert np.allclose(quat_to_matrix(qmul(a, b)), Ra @ Rb, atol=1e-12)
        back = matrix_to_quat(Ra)
        assert np.allclose(back, a if a[0] >= 0 else -a, atol=1e-12)
        v = np.array([0.3, -0.2, 0.9])
        pure = np.concatenate([[0.0], v])
        rotated = qmul(qmul(a, pure), qconj(a))
        assert np.allclose(rotated[1:], qrotate(a, v), atol=1e-12)


def test_axis_quaternions_match_paper_eq5() -> None:
    t = 0.7
    assert np.allclose(qz(t), [math.cos(t / 2), 0, 0, math.sin(t / 2)])
    assert np.allclose(qy(t), [math.cos(t / 2), 0, math.sin(t / 2), 0])
    assert np.allclose(quat_to_matrix(qz(t)) @ [1, 0, 0], [math.cos(t), math.sin(t), 0])


@pytest.mark.parametrize("n", [[0, 0, 1], [1, 0, 0], [0.3, -0.4, math.sqrt(0.75)], [1e-9, 0, -1], [0, 0, -1]])
def test_shortest_rotation_maps_k_onto_n(n: list[float]) -> None:
    n = np.asarray(n, dtype=float)
    n /= np.linalg.norm(n)
    qa = shortest_rotation(n)
    assert np.isclose(np.linalg.norm(qa), 1.0)
    assert np.allclose(qrotate(qa, [0, 0, 1]), n, atol=1e-9)
    if n[2] > -0.99:  # rotation axis is perpendicular to k and n
        assert abs(qa[3]) < 1e-12


def test_xyzw_conversion_and_pose() -> None:
    q = _random_quats(1, 3)[0]
    assert np.allclose(from_xyzw(to_xyzw(q)), q)
    T = pose_to_matrix([1, 2, 3], q)
    assert np.allclose(T[:3, :3], quat_to_matrix(q)) and np.allclose(T[:3, 3], [1, 2, 3])
    with pytest.raises(InvalidInputError):
        pose_to_matrix([1, 2, 3], [1, 1, 0, 0])
    with pytest.raises(InvalidInputError):
        pose_to_matrix([1, float("nan"), 3], q)


def test_rotation_error_is_axis_angle() -> None:
    for ang in (1e-9, 0.3, 2.0, math.pi - 1e-9):
        axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
        q = np.concatenate([[math.cos(ang / 2)], math.sin(ang / 2) * axis])
        R = quat_to_matrix(q)
        v = rotation_error(np.eye(3), R)
        assert np.isclose(np.linalg.norm(v), ang, atol=1e-7)
        assert np.allclose(v / np.linalg.norm(v), axis, atol=1e-6)


# -- scipy's Rotation as the oracle (it takes quaternions as (x, y, z, w)) ------------------------------
def _sp(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(to_xyzw(q_wxyz))


def test_numpy_and_scalar_forms_agree_with_scipy() -> None:
    rng = np.random.default_rng(21)
    for a, b in zip(_random_quats(40, 4), _random_quats(40, 5), strict=True):
        ra, rb = _sp(a), _sp(b)
        v = rng.normal(size=3)
        R = ra.as_matrix()
        np.testing.assert_allclose(quat_to_matrix(a), R, atol=1e-12)
        np.testing.assert_allclose(matrix_from_quat(tuple(a)), R, atol=1e-12)
        for q in (matrix_to_quat(R), np.array(quat_from_matrix(R.tolist()))):
            assert q[0] >= 0 and _sp(q).approx_equal(ra, atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(qmul(a, b)), (ra * rb).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(quat_mul(a, b)), (ra * rb).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(qrotate(a, v), ra.apply(v), atol=1e-12)
        np.testing.assert_allclose(quat_rotate(a, v), ra.apply(v), atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(quat_conj(a)), ra.inv().as_matrix(), atol=1e-12)
        r = rotvec_between(a, b)  # exp(r) a = b, the short way round
        np.testing.assert_allclose(r, (rb * ra.inv()).as_rotvec(), atol=1e-9)
        assert quat_angle(a, b) == pytest.approx((rb * ra.inv()).magnitude(), abs=1e-7)
        np.testing.assert_allclose(rotation_error(R, rb.as_matrix()), r, atol=1e-9)
        w = rng.normal(size=3)
        assert _sp(np.array(quat_from_rotvec(w))).approx_equal(Rotation.from_rotvec(w), atol=1e-12)


@pytest.mark.parametrize("tilt", [0.0, 0.3, 2.0, math.pi - 1e-3, math.pi - 1e-7, math.pi - 1e-12])
def test_shortest_rotation_forms_agree_with_scipy_also_near_minus_k(tilt: float) -> None:
    """k -> n: the quaternion, its basis columns and the scalar kernel are the minimal rotation (scipy's
    align_vectors of one vector pair), to full precision also when n is nearly -k."""
    n = np.array([math.sin(tilt) * math.cos(0.4), math.sin(tilt) * math.sin(0.4), math.cos(tilt)])
    ref, _ = Rotation.align_vectors([n], [[0.0, 0.0, 1.0]])
    qa = shortest_rotation(n)
    # the oracle: the rotation by `tilt` about k x n; relative precision of the tiny angle of pi - tilt
    axis = np.cross([0.0, 0.0, 1.0], n)
    oracle = Rotation.from_rotvec(axis / np.linalg.norm(axis) * tilt) if tilt > 0 else Rotation.identity()
    assert _sp(qa).approx_equal(oracle, atol=1e-12)
    assert ref.approx_equal(oracle, atol=1e-6)  # scipy's own solver, looser near the antipode
    a, b = shortest_rotation_basis(n)
    M = oracle.as_matrix()
    np.testing.assert_allclose(a, M[:, 0], atol=1e-12)
    np.testing.assert_allclose(b, M[:, 1], atol=1e-12)
    h = one_plus_nz(*n)
    np.testing.assert_allclose(shortest_rotation_xy(n[0], n[1], h, 0.6, -0.8), M @ [0.6, -0.8, 0.0],
                               atol=1e-12)


def test_shortest_rotation_at_minus_k_is_the_half_turn_about_x() -> None:
    assert np.allclose(shortest_rotation([0.0, 0.0, -1.0]), [0.0, 1.0, 0.0, 0.0])
    assert shortest_rotation_basis((0.0, 0.0, -1.0)) == ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
