"""Quaternion helpers used by the kinematics core.

Every quaternion in this module is a length-4 sequence in **(w, x, y, z)** order (scalar first, as in
the swivel-quaternion paper). ROS messages use (x, y, z, w): convert with :func:`from_xyzw` /
:func:`to_xyzw` at the boundary. Pure quaternions (vectors) are given as (x, y, z) arrays.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from redarm_ros.errors import InvalidInputError

__all__ = [
    "qmul",
    "qconj",
    "qrotate",
    "qx",
    "qy",
    "qz",
    "quat_to_matrix",
    "matrix_to_quat",
    "shortest_rotation",
    "from_xyzw",
    "to_xyzw",
    "pose_to_matrix",
    "rotation_error",
]


def qmul(a: Sequence[float], b: Sequence[float]) -> np.ndarray:
    """Hamilton product a*b of two (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def qconj(q: Sequence[float]) -> np.ndarray:
    """Conjugate of a (w, x, y, z) quaternion."""
    return np.array([q[0], -q[1], -q[2], -q[3]], dtype=float)


def qrotate(q: Sequence[float], v: Sequence[float]) -> np.ndarray:
    """Rotate the vector v (x, y, z) by the unit quaternion q (w, x, y, z): q v q*."""
    return quat_to_matrix(q) @ np.asarray(v, dtype=float)


def qx(angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about x as a (w, x, y, z) quaternion."""
    return np.array([math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0])


def qy(angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about y as a (w, x, y, z) quaternion: Q_y of the paper, eq. 5."""
    return np.array([math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0])


def qz(angle: float) -> np.ndarray:
    """Rotation by ``angle`` (rad) about z as a (w, x, y, z) quaternion: Q_z of the paper, eq. 5."""
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """3x3 rotation matrix of a unit (w, x, y, z) quaternion (paper eq. 3)."""
    w, x, y, z = (float(c) for c in q)
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit (w, x, y, z) quaternion of a 3x3 rotation matrix, with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    out = np.array(q)
    out /= np.linalg.norm(out)
    return -out if out[0] < 0 else out


def shortest_rotation(n: Sequence[float]) -> np.ndarray:
    """q_A of the paper (eq. 14): the shortest rotation taking k = (0, 0, 1) onto the unit vector n.

    Returns a (w, x, y, z) quaternion. When n = -k the shortest rotation is not unique; this function
    then returns the rotation by pi about x (the same choice as the IK solver).
    """
    nx, ny, nz = (float(c) for c in n)
    # q = (1 + k.n, k x n) normalised; k x n = (-ny, nx, 0)
    w = 1.0 + nz
    if w < 1e-12 and nx * nx + ny * ny < 1e-24:
        return np.array([0.0, 1.0, 0.0, 0.0])
    q = np.array([w, -ny, nx, 0.0])
    return q / np.linalg.norm(q)


def from_xyzw(q_xyzw: Sequence[float]) -> np.ndarray:
    """(x, y, z, w) (ROS message order) -> (w, x, y, z)."""
    x, y, z, w = q_xyzw
    return np.array([w, x, y, z], dtype=float)


def to_xyzw(q_wxyz: Sequence[float]) -> np.ndarray:
    """(w, x, y, z) -> (x, y, z, w) (ROS message order)."""
    w, x, y, z = q_wxyz
    return np.array([x, y, z, w], dtype=float)


def pose_to_matrix(p: Sequence[float], q_wxyz: Sequence[float], *, tol: float = 1e-6) -> np.ndarray:
    """4x4 homogeneous transform from a position p (m) and a unit quaternion in (w, x, y, z) order.

    Raises :class:`InvalidInputError` for non-finite values or a quaternion whose norm is not 1
    within ``tol`` (a slightly off norm is renormalised).
    """
    p = np.asarray(p, dtype=float)
    q = np.asarray(q_wxyz, dtype=float)
    if p.shape != (3,) or q.shape != (4,):
        raise InvalidInputError("pose needs p of shape (3,) and q of shape (4,)", field="pose", value=(p, q))
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise InvalidInputError("pose contains NaN or inf", field="pose", value=(p, q))
    nq = float(np.linalg.norm(q))
    if abs(nq - 1.0) > tol:
        raise InvalidInputError(f"quaternion norm {nq:.6g} is not 1", field="q_wxyz", value=q)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q / nq)
    T[:3, 3] = p
    return T


def rotation_error(R_actual: np.ndarray, R_desired: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad, base frame) taking R_actual onto R_desired."""
    Re = np.asarray(R_desired) @ np.asarray(R_actual).T
    c = max(-1.0, min(1.0, (Re[0, 0] + Re[1, 1] + Re[2, 2] - 1.0) / 2.0))
    v = np.array([Re[2, 1] - Re[1, 2], Re[0, 2] - Re[2, 0], Re[1, 0] - Re[0, 1]])
    s = 0.5 * float(np.linalg.norm(v))
    angle = math.atan2(s, c)
    if s > 1e-7:
        return v * (angle / (2.0 * s))
    if c > 0:  # tiny angle: first-order
        return 0.5 * v
    # angle near pi: axis from the symmetric part
    B = (Re + np.eye(3)) / 2.0
    i = int(np.argmax(np.diag(B)))
    axis = B[:, i] / math.sqrt(max(B[i, i], 1e-300))
    axis /= np.linalg.norm(axis)
    return axis * angle
