"""Quaternion helpers, (w, x, y, z) order."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.quaternion import (
    from_xyzw,
    matrix_to_quat,
    pose_to_matrix,
    qconj,
    qmul,
    qrotate,
    quat_to_matrix,
    qy,
    qz,
    rotation_error,
    shortest_rotation,
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
