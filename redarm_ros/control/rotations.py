"""Small scalar rotation helpers for the controller loop (quaternions are (w, x, y, z), unit).

Scalar ``math`` on tuples on purpose: the controller handles one orientation per step, where numpy's
per-call overhead would cost more than the arithmetic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

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
