"""The project's one rotation vocabulary: quaternions, rotation matrices, rotation vectors.

Every quaternion in this module is a length-4 sequence in **(w, x, y, z)** order (scalar first, as in
the swivel-quaternion paper). ROS messages use (x, y, z, w): convert with :func:`from_xyzw` /
:func:`to_xyzw` at the boundary. Pure quaternions (vectors) are given as (x, y, z) arrays.

Two forms of the same operations:

* numpy forms (``qmul``, ``qrotate``, ``quat_to_matrix``, ``matrix_to_quat``, ...) for the kinematics
  and for code that handles arrays;
* scalar forms on tuples (``quat_mul``, ``quat_rotate``, ``quat_from_matrix``, ``rotvec_between``, ...)
  for the controller's per-step path, where one orientation is handled at a time. Measured on the
  2-core test machine (load average 15.7, so absolute figures are inflated; the ratios are what
  matter): ``quat_rotate`` 1.1 us against ``qrotate`` 107 us, ``quat_from_matrix`` 5.6 us against
  ``matrix_to_quat`` 48 us.

The shortest rotation taking k = (0, 0, 1) onto a unit vector n (q_A of the swivel paper, eq. 14) is
written once, in :func:`shortest_rotation_xy` (with :func:`one_plus_nz` free of cancellation near
n = -k); :func:`shortest_rotation`, :func:`shortest_rotation_basis` and the swivel IK use it.
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
    "shortest_rotation_basis",
    "shortest_rotation_xy",
    "one_plus_nz",
    "quat_from_matrix",
    "quat_normalize",
    "quat_mul",
    "quat_conj",
    "matrix_from_quat",
    "rotvec_between",
    "quat_angle",
    "quat_from_rotvec",
    "quat_rotate",
    "quat_between_vectors",
    "slerp_vectors",
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


def one_plus_nz(nx: float, ny: float, nz: float) -> float:
    """1 + nz for a unit vector n, without the cancellation of ``1.0 + nz`` near n = -k.

    For nz < 0, 1 + nz = (1 - nz^2) / (1 - nz) = (nx^2 + ny^2) / (1 - nz): small nx, ny keep their
    full relative precision where ``1.0 + nz`` would keep none.
    """
    return 1.0 + nz if nz >= 0.0 else (nx * nx + ny * ny) / (1.0 - nz)


def shortest_rotation_xy(nx: float, ny: float, h: float, ux: float, uy: float) -> tuple[float, float, float]:
    """q_A u q_A* for u = (ux, uy, 0), q_A the shortest rotation k -> n, ``h`` = 1 + nz (> 0).

    q_A = (h, -ny, nx, 0) / |.|; expanded, q_A u q_A* = u + w n_xy / h + w k with w = -(n_xy . u).
    Scalar on purpose: it is on the path of every swivel ``ik`` call (about 0.9 us; the numpy
    ``qrotate(shortest_rotation(n), u)`` takes about 30 us). ``h`` from :func:`one_plus_nz`.
    """
    w = -(nx * ux + ny * uy)
    return ux + nx * w / h, uy + ny * w / h, w


def shortest_rotation(n: Sequence[float]) -> np.ndarray:
    """q_A of the paper (eq. 14): the shortest rotation taking k = (0, 0, 1) onto the unit vector n.

    Returns a (w, x, y, z) quaternion. When n = -k the shortest rotation is not unique; this function
    then returns the rotation by pi about x (the same choice as the IK solver).
    """
    nx, ny, nz = (float(c) for c in n)
    # q = (1 + k.n, k x n) normalised; k x n = (-ny, nx, 0)
    w = one_plus_nz(nx, ny, nz)
    if w < 1e-300 or (nz < 0.0 and nx * nx + ny * ny < 1e-300):
        return np.array([0.0, 1.0, 0.0, 0.0])
    q = np.array([w, -ny, nx, 0.0])
    return q / np.linalg.norm(q)


def shortest_rotation_basis(n: Sequence[float]) -> tuple[Vec3, Vec3]:
    """Columns ``a = q_A i q_A*`` and ``b = q_A j q_A*`` of the shortest rotation taking k onto unit ``n``.

    At ``n = -k`` the shortest rotation is not unique; the half turn about x (a = i, b = -j), as
    :func:`shortest_rotation`.
    """
    nx, ny, nz = (float(c) for c in n)
    h = one_plus_nz(nx, ny, nz)
    if h < 1e-300:
        return (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)
    return shortest_rotation_xy(nx, ny, h, 1.0, 0.0), shortest_rotation_xy(nx, ny, h, 0.0, 1.0)


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


# -- scalar forms (tuples, ``math``): the controller's per-step path, see the module docstring ---------
Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]


def quat_from_matrix(R: Sequence[Sequence[float]]) -> Quat:
    """Unit quaternion (w, x, y, z) of rotation matrix ``R`` (Shepperd's method), with w >= 0."""
    m00, m01, m02 = R[0][0], R[0][1], R[0][2]
    m10, m11, m12 = R[1][0], R[1][1], R[1][2]
    m20, m21, m22 = R[2][0], R[2][1], R[2][2]
    tr = m00 + m11 + m22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    q = quat_normalize(q)
    return q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])


def quat_normalize(q: Sequence[float]) -> Quat:
    """q / |q|."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def quat_mul(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Hamilton product a b."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def quat_conj(q: Sequence[float]) -> Quat:
    """Conjugate (inverse of a unit quaternion)."""
    return (q[0], -q[1], -q[2], -q[3])


def matrix_from_quat(q: Sequence[float]) -> list[list[float]]:
    """3x3 rotation matrix (nested lists) of unit quaternion ``q``."""
    w, x, y, z = q
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


def rotvec_between(q_from: Sequence[float], q_to: Sequence[float]) -> Vec3:
    """Rotation vector (rad, base frame) ``r`` with ``exp(r) q_from = q_to``, shortest way."""
    e = quat_mul(q_to, quat_conj(q_from))
    if e[0] < 0.0:
        e = (-e[0], -e[1], -e[2], -e[3])
    vn = math.sqrt(e[1] * e[1] + e[2] * e[2] + e[3] * e[3])
    if vn < 1e-15:
        return (2.0 * e[1], 2.0 * e[2], 2.0 * e[3])
    angle = 2.0 * math.atan2(vn, e[0])
    f = angle / vn
    return (f * e[1], f * e[2], f * e[3])


def quat_angle(a: Sequence[float], b: Sequence[float]) -> float:
    """Rotation angle (rad, in [0, pi]) between unit quaternions ``a`` and ``b``."""
    d = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
    return 2.0 * math.acos(min(1.0, d))


def quat_from_rotvec(r: Sequence[float]) -> Quat:
    """Unit quaternion of rotation vector ``r`` (rad)."""
    angle = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    if angle < 1e-12:
        return quat_normalize((1.0, 0.5 * r[0], 0.5 * r[1], 0.5 * r[2]))
    s = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), s * r[0], s * r[1], s * r[2])


def quat_rotate(q: Sequence[float], v: Sequence[float]) -> Vec3:
    """q v q* for a 3-vector ``v``."""
    w, x, y, z = q
    # t = 2 q_vec x v; v' = v + w t + q_vec x t
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + (y * tz - z * ty),
            v[1] + w * ty + (z * tx - x * tz),
            v[2] + w * tz + (x * ty - y * tx))


def quat_between_vectors(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Shortest rotation taking unit vector ``a`` onto unit vector ``b``."""
    c = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    cx = a[1] * b[2] - a[2] * b[1]
    cy = a[2] * b[0] - a[0] * b[2]
    cz = a[0] * b[1] - a[1] * b[0]
    if c < -1.0 + 1e-12:  # opposite: half turn about any axis perpendicular to a
        ax = (0.0, -a[2], a[1]) if abs(a[0]) < 0.9 else (-a[1], a[0], 0.0)
        n = math.sqrt(ax[0] ** 2 + ax[1] ** 2 + ax[2] ** 2)
        return (0.0, ax[0] / n, ax[1] / n, ax[2] / n)
    return quat_normalize((1.0 + c, cx, cy, cz))


def slerp_vectors(a: Sequence[float], b: Sequence[float], t: float) -> Vec3:
    """Unit vector a fraction ``t`` of the way from unit ``a`` to unit ``b`` along the great circle."""
    q = quat_between_vectors(a, b)
    vn = math.sqrt(q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    angle = 2.0 * math.atan2(vn, q[0])
    if vn < 1e-15:
        return (a[0], a[1], a[2])
    f = t * angle / vn
    return quat_rotate(quat_from_rotvec((f * q[1], f * q[2], f * q[3])), a)
