"""Closed-form swivel IK of 7-DOF arms with a spherical shoulder and wrist (PA10, 7-module PowerCube).

Follows Moore & Oztop, "Redundancy parametrization for flexible motion control" step by step:

1. wrist point ``pW = p - L4 q k q*`` (eq. 10);
2. elbow circle: centre ``C`` on the shoulder-wrist line, normal ``n = unit(pW - pS)``, radius ``rho``;
3. elbow ``pE = C + rho qA u qA*`` (eq. 15) with ``qA`` the shortest rotation k -> n (eq. 14) and
   ``u = Qz(s) i Qz(s)*`` (eq. 13) the swivel quaternion of the swivel angle ``s``;
4. theta4 from the triangle pS, pE, pW;
5./6. the shoulder orientation q3 (z3 along the upper arm, x3 in the arm plane) and theta1..3 from its
   ZYZ decomposition (eq. 11/12);
7./8. q4 = q3 Qy(theta4) and theta5..7 from the ZYZ decomposition of q4* q.

The other solutions come from the paper's three sign flips (theta4 -> -theta4 with theta3, theta5 +- pi;
theta2 -> -theta2 with theta1, theta3 +- pi; theta6 -> -theta6 with theta5, theta7 +- pi), up to 8 per
swivel. Quaternions are (w, x, y, z); the swivel quaternion ``u`` is passed as its vector part (x, y, z).

Conventions and choices (also in docs/kinematics.md):

* Solutions are ordered by the flip pattern (f2, f4, f6) in binary (f2 most significant); a flipped
  theta is the negative of the base one (base theta2, theta4, theta6 >= 0).
* Angles are wrapped into the joint limits. By default each solution appears once, with every angle at
  the in-limit 2*pi copy nearest to 0 (so ``ik`` returns at most 8 rows); ``all_copies=True`` lists every
  in-limit 2*pi copy (joints with a range wider than 2*pi, e.g. the PA10's +-255 and +-360 deg joints).
  ``ik_nearest`` picks the copy nearest to the seed.
* Singular cases have defined answers, never NaN:
  - stretched or folded elbow (rho = 0, sin theta4 = 0): the arm plane is undefined; x3 = -qA u qA*, so
    the swivel still chooses how the rotation is split between theta3 and theta5 (the limit of the
    regular case from the theta4 > 0 side);
  - wrist straight below the shoulder (n = -k): qA is the rotation by pi about x;
  - elbow on the base axis (sin theta2 = 0) or wrist aligned (sin theta6 = 0): theta1 (theta5) = 0 and
    theta3 (theta7) takes the whole rotation;
  - wrist at the shoulder (only reachable when L2 = L3): n = k is taken as the reference;
  - out of reach: ``ik`` returns no rows; ``elbow_circle`` raises UnreachableError with the distance.

Over the whole circle (``feasible_swivels``, ``ik_nearest``, ``ik_nearest_batch``) the joint angles are
closed-form functions of the swivel (:mod:`.feasible`): the in-limit swivels are exact interval unions
and the nearest solution to a seed is the global optimum.
"""

from __future__ import annotations

import math
import operator
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.kinematics.corridor import SwivelCorridor, swivel_corridor
from redarm_ros.kinematics.feasible import (
    INTERVAL_ROOT_TOL,
    LimitTables,
    NearestWorkspace,
    SwivelFunctions,
    feasible_intervals,
    nearest,
    nearest_batch,
    swivel_functions,
)
from redarm_ros.kinematics.model import (
    ANGLE_RANGE,
    LIMIT_TOL,
    Arm,
    Joint,
    check_finite_array,
    check_scalar,
)
from redarm_ros.kinematics.quaternion import shortest_rotation_xy
from redarm_ros.kinematics.result import (
    BATCH_NO_SOLUTION_IN_LIMITS,
    BATCH_SUCCESS,
    IKBatchResult,
    IKInfo,
    IKStatus,
)

__all__ = ["SwivelArm", "FLIP_PATTERNS", "swivel_chain"]

PI = math.pi
TWO_PI = 2.0 * math.pi
REACH_TOL = 1e-9  # m; a wrist this far beyond the reach sphere still counts as (just) reachable
DEGEN_SIN = 1e-12  # |sin theta| below which the arm plane / a ZYZ decomposition is degenerate
RHO_DEGEN = 1e-7  # m; below this elbow-circle radius swivel(q) uses the degenerate definition
AXIS_TOL2 = 1e-24  # (1e-12)^2: a wrist within 1e-12 * D of the base axis counts as on it (n = +-k)

# flip pattern k -> (f2, f4, f6); per joint which of the two alternatives (base, flipped) to use
FLIP_PATTERNS = [((k >> 2) & 1, (k >> 1) & 1, k & 1) for k in range(8)]
_ALT_INDEX = np.array([[f2, f2, f2 ^ f4, f4, f4 ^ f6, f6, f6] for f2, f4, f6 in FLIP_PATTERNS])
_ALT_INDEX_L = _ALT_INDEX.tolist()
_J14 = np.repeat(np.arange(7), 2)  # joint of each of the 14 alternatives (row 2 j + a)
_IDX56 = np.array([2 * j + k for row in _ALT_INDEX_L for j, k in enumerate(row)])  # pattern b, joint j
# alternatives per joint as affine maps angle -> sign * angle + shift: (7, 2), column 1 = flipped
_ALT_SIGN = np.array([[1.0, 1.0 if j % 2 == 0 else -1.0] for j in range(7)])
_ALT_SHIFT = np.array([[0.0, PI if j % 2 == 0 else 0.0] for j in range(7)])
# per flip pattern the affine map of each joint (lists for the scalar path)
_ALT_SIGN_L = [[float(_ALT_SIGN[j, k]) for j, k in enumerate(row)] for row in _ALT_INDEX.tolist()]
_ALT_SHIFT_L = [[float(_ALT_SHIFT[j, k]) for j, k in enumerate(row)] for row in _ALT_INDEX.tolist()]
# per flip pattern: its row out of the 14 alternatives [t1, t1 + pi, t2, -t2, ...] (one C-level gather)
_PATTERN_GET = [operator.itemgetter(*[2 * j + k for j, k in enumerate(row)]) for row in _ALT_INDEX_L]


def swivel_chain(
    link_lengths: Sequence[float], limits: Sequence[tuple[str, float, float, float, float]]
) -> tuple[list[Joint], np.ndarray]:
    """The z,y,z,y,z,y,z chain of the swivel model and its tool transform (zero pose straight up +z).

    ``link_lengths``: L1..L4 (m); ``limits``: per joint (name, lower, upper, max_vel, max_acc) in rad,
    rad/s, rad/s^2. Joints 2, 4, 6 sit at L1, L2, L3 above the previous joint, the tool L4 above joint 7.
    """
    L1, L2, L3, L4 = (float(v) for v in link_lengths)
    offsets = (0.0, L1, 0.0, L2, 0.0, L3, 0.0)
    chain = []
    for i, (name, lo, up, vel, acc) in enumerate(limits):
        o = np.eye(4)
        o[2, 3] = offsets[i]
        axis = np.array([0.0, 1.0, 0.0]) if i % 2 else np.array([0.0, 0.0, 1.0])
        chain.append(Joint(name, o, axis, lo, up, vel, acc))
    tool = np.eye(4)
    tool[2, 3] = L4
    return chain, tool


def _wrap(x: float) -> float:
    """x (within (-3pi, 3pi]) wrapped into (-pi, pi]."""
    if x > PI:
        return x - TWO_PI
    if x <= -PI:
        return x + TWO_PI
    return x


def _zyz(ax: float, ay: float, az: float, bx: float, by: float, bz: float) -> tuple[float, float, float]:
    """ZYZ angles (t1, t2, t3) of a rotation given its third column a and first column b (eq. 11), the
    shoulder's R3 and the wrist's W alike. t1, t2 from a (t2 in [0, pi]); t3 from the residual rotation
    (Rz(t1) Ry(t2))^T b, so that it stays exact where sin t2 = 0 (there t1 = 0 by convention)."""
    r = math.sqrt(ax * ax + ay * ay)
    t2 = math.atan2(r, az)
    if r > DEGEN_SIN:
        c1, s1 = ax / r, ay / r
        t1 = math.atan2(ay, ax)
    else:
        c1, s1, t1 = 1.0, 0.0, 0.0
    b11 = c1 * bx + s1 * by
    b21 = -s1 * bx + c1 * by
    return t1, t2, math.atan2(b21, az * b11 - r * bz)


def _zyz_np(ax: Any, ay: Any, az: Any, bx: Any, by: Any, bz: Any, out: np.ndarray) -> None:
    """Vectorised :func:`_zyz` into ``out`` (3, m)."""
    r = np.sqrt(ax * ax + ay * ay)
    out[1] = np.arctan2(r, az)
    ok = r > DEGEN_SIN
    rs = np.where(ok, r, 1.0)
    c1 = np.where(ok, ax / rs, 1.0)
    s1 = np.where(ok, ay / rs, 0.0)
    out[0] = np.where(ok, np.arctan2(ay, ax), 0.0)
    b11 = c1 * bx + s1 * by
    b21 = c1 * by - s1 * bx
    out[2] = np.arctan2(b21, az * b11 - r * bz)


# The frame formulas below are written once and evaluated on floats (the scalar ``ik`` path, where numpy's
# per-call overhead would dominate) or on (m,) arrays (``ik_batch``) alike; ``sqrt`` is math.sqrt or np.sqrt.
def _wrist_from_shoulder(rows: Sequence[Any], L: Sequence[float]) -> tuple[Any, ...]:
    """d = pW - pS (the wrist pW = p - L4 a, the shoulder pS = L1 k) from the first three rows of the tool
    pose, with |d_xy|^2 and |d|^2: (dx, dy, dz, rxy2, D2)."""
    L1, L4 = L[0], L[3]
    r0, r1, r2 = rows[0], rows[1], rows[2]
    dx = r0[3] - L4 * r0[2]
    dy = r1[3] - L4 * r1[2]
    dz = r2[3] - L4 * r2[2] - L1
    rxy2 = dx * dx + dy * dy
    return dx, dy, dz, rxy2, rxy2 + dz * dz


def _unit_x3(x3x: Any, x3y: Any, x3z: Any, zx: Any, zy: Any, zz: Any, sqrt: Any) -> tuple[Any, ...]:
    """x3 normalised, made orthogonal to z3 again and normalised (g is tiny next to f near the stretched
    elbow), and y3 = z3 x x3: (x3x, x3y, x3z, y3x, y3y, y3z)."""
    k = 1.0 / sqrt(x3x * x3x + x3y * x3y + x3z * x3z)
    x3x, x3y, x3z = x3x * k, x3y * k, x3z * k
    pd = x3x * zx + x3y * zy + x3z * zz
    x3x, x3y, x3z = x3x - pd * zx, x3y - pd * zy, x3z - pd * zz
    k = 1.0 / sqrt(x3x * x3x + x3y * x3y + x3z * x3z)
    x3x, x3y, x3z = x3x * k, x3y * k, x3z * k
    return x3x, x3y, x3z, zy * x3z - zz * x3y, zz * x3x - zx * x3z, zx * x3y - zy * x3x


def _frame4_axes(f: tuple[Any, ...]) -> tuple[Any, ...]:
    """x4 and z4 of frame 4 = frame 3 turned by theta4 about y3 (x4 = c4 x3 - s4 z3, z4 = s4 x3 + c4 z3),
    from a frame tuple of ``_frame3`` / ``_frame_np``: (x4x, x4y, x4z, z4x, z4y, z4z)."""
    zx, zy, zz, x3x, x3y, x3z, _, _, _, _, c4, s4 = f
    return (c4 * x3x - s4 * zx, c4 * x3y - s4 * zy, c4 * x3z - s4 * zz,
            s4 * x3x + c4 * zx, s4 * x3y + c4 * zy, s4 * x3z + c4 * zz)


def _wrist_entries(f: tuple[Any, ...], rows: Sequence[Any]) -> tuple[Any, ...]:
    """Entries (W13, W23, W33, W11, W21, W31) of the wrist rotation W = R4^T R_tool, from a frame tuple and
    the first three rows of the tool pose (nested lists of floats or of (m,) arrays)."""
    x4x, x4y, x4z, z4x, z4y, z4z = _frame4_axes(f)
    y3x, y3y, y3z = f[6], f[7], f[8]
    r0, r1, r2 = rows[0], rows[1], rows[2]
    ax, ay, az = r0[2], r1[2], r2[2]  # tool z (approach)
    bx, by, bz = r0[0], r1[0], r2[0]  # tool x
    return (
        x4x * ax + x4y * ay + x4z * az,
        y3x * ax + y3y * ay + y3z * az,
        z4x * ax + z4y * ay + z4z * az,
        x4x * bx + x4y * by + x4z * bz,
        y3x * bx + y3y * by + y3z * bz,
        z4x * bx + z4y * by + z4z * bz,
    )


class SwivelArm(Arm):
    """7-DOF z,y,z,y,z,y,z arm with link lengths L1..L4 (m): closed-form swivel IK.

    ``fk`` orientation is ``Qz(t1)Qy(t2)Qz(t3)Qy(t4)Qz(t5)Qy(t6)Qz(t7)`` (w, x, y, z); shoulder at
    ``L1 k``, elbow ``pS + L2 q2 k q2*``, wrist ``pE + L3 q4 k q4*``, tool ``pW + L4 q6 k q6*``.
    """

    kind = "swivel7"
    has_swivel = True

    def _setup_model(self) -> None:
        L = [float(v) for v in self.config["link_lengths"]]
        self.link_lengths = tuple(L)
        self._L = tuple(L)
        # joints whose range reaches beyond (-pi, pi]: more than one 2*pi copy may fit
        self._wide = [lo < -PI or up > PI for lo, up in zip(self._lower_l, self._upper_l, strict=True)]
        self._very_wide = [
            lo < -3 * PI or up > 3 * PI for lo, up in zip(self._lower_l, self._upper_l, strict=True)
        ]
        self._tables = LimitTables(self.lower, self.upper)  # the nearest search's
        self._interval_tables = LimitTables(self.lower, self.upper, INTERVAL_ROOT_TOL)  # feasible_swivels'
        # per joint (lower - tol, upper + tol, lower, upper)
        self._lims = [
            (lo - LIMIT_TOL, up + LIMIT_TOL, lo, up)
            for lo, up in zip(self._lower_l, self._upper_l, strict=True)
        ]
        self._lims14 = [lim for lim in self._lims for _ in (0, 1)]  # per alternative, for _expand
        self._wide14 = [wd for wd in self._wide for _ in (0, 1)]
        self._shifts = []
        for lo, up in zip(self._lower_l, self._upper_l, strict=True):
            kmax = int(math.ceil(max(abs(lo), abs(up)) / TWO_PI)) + 1
            self._shifts.append([k * TWO_PI for k in range(-kmax, kmax + 1)])

    # ------------------------------------------------------------------ geometry
    @property
    def shoulder(self) -> np.ndarray:
        """Shoulder position pS = L1 k (m)."""
        return np.array([0.0, 0.0, self._L[0]])

    def _circle(self, Tl: list[list[float]]) -> tuple[float, ...] | float:
        """Wrist relative to the shoulder and the elbow circle, or the (positive) reach violation in m.

        Returns (dx, dy, dz, D, rxy2, nx, ny, nz, ca) with d = pW - pS, D = |d|, n = d / D and ca the
        cosine of the angle at the shoulder between n and the upper arm.
        """
        L2, L3 = self._L[1], self._L[2]
        dx, dy, dz, rxy2, D2 = _wrist_from_shoulder(Tl, self._L)
        D = math.sqrt(D2)
        if D > L2 + L3 + REACH_TOL:
            return D - (L2 + L3)
        if D < abs(L2 - L3) - REACH_TOL:
            return abs(L2 - L3) - D
        if D < 1e-12:  # wrist at the shoulder (L2 == L3): n = k by convention
            return (dx, dy, dz, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
        inv = 1.0 / D
        ca = (L2 * L2 + D2 - L3 * L3) / (2.0 * L2 * D)
        ca = 1.0 if ca > 1.0 else (-1.0 if ca < -1.0 else ca)
        return (dx, dy, dz, D, rxy2, dx * inv, dy * inv, dz * inv, ca)

    @staticmethod
    def _qa_h(circ: tuple[float, ...]) -> float:
        """1 + nz of the circle's normal n, computed without cancellation from the unnormalised d, for the
        shortest rotation qA: k -> n; 0.0 where n = k (qA = 1), -1.0 where n = -k (qA = the rotation by pi
        about x), both within the axis tolerance."""
        dx, dy, dz, D, rxy2, nx, ny, nz, _ = circ
        if D == 0.0 or (dz >= 0.0 and rxy2 <= AXIS_TOL2 * D * D):
            return 0.0
        if dz >= 0.0:
            return 1.0 + nz
        if rxy2 <= AXIS_TOL2 * D * D:
            return -1.0
        return rxy2 / (D * (D - dz))

    @classmethod
    def _rot_qa(cls, circ: tuple[float, ...], ux: float, uy: float) -> tuple[float, float, float]:
        """qA u qA* for u = (ux, uy, 0): the shortest rotation k -> n applied to u (eq. 14-15), by
        :func:`.quaternion.shortest_rotation_xy`."""
        h = cls._qa_h(circ)
        if h <= 0.0:
            return (ux, uy, 0.0) if h == 0.0 else (ux, -uy, 0.0)
        return shortest_rotation_xy(circ[5], circ[6], h, ux, uy)

    @classmethod
    def _rot_qa_inv(cls, circ: tuple[float, ...], ex: float, ey: float, ez: float) -> tuple[float, float]:
        """(x, y) of qA* e qA: inverse of :meth:`_rot_qa` (eq. 16)."""
        h = cls._qa_h(circ)
        if h <= 0.0:
            return (ex, ey) if h == 0.0 else (ex, -ey)
        nx, ny = circ[5], circ[6]
        wz = -(nx * ex + ny * ey)
        return ex - nx * ez + nx * wz / h, ey - ny * ez + ny * wz / h

    def _base_solution(self, Tl: list[list[float]], ux: float, uy: float) -> tuple[float, ...] | float:
        """The base solution (theta2, theta4, theta6 >= 0) at swivel quaternion u, or the reach violation."""
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            return circ
        return self._base_from_circle(Tl, circ, ux, uy)

    def _frame3(self, circ: tuple[float, ...], ux: float, uy: float) -> tuple[float, ...]:
        """Shoulder frame R3 = [x3 y3 z3] and elbow angle at swivel quaternion u (base solution, theta4 >= 0).

        Returns (zx, zy, zz, x3x, x3y, x3z, y3x, y3y, y3z, t4, c4, s4): z3 along the upper arm, x3 in the
        arm plane (from the swivel when the elbow is stretched or folded), theta4 with its cosine / sine.
        """
        L1, L2, L3, L4 = self._L
        dx, dy, dz, D, rxy2, nx, ny, nz, ca = circ
        sa = math.sqrt(max(0.0, 1.0 - ca * ca))
        rux, ruy, ruz = self._rot_qa(circ, ux, uy)
        # elbow relative to the shoulder: L2 ca n + rho qA u qA*  (rho = L2 sa)
        ex = L2 * (ca * nx + sa * rux)
        ey = L2 * (ca * ny + sa * ruy)
        ez = L2 * (ca * nz + sa * ruz)
        inv = 1.0 / math.sqrt(ex * ex + ey * ey + ez * ez)
        zx, zy, zz = ex * inv, ey * inv, ez * inv  # upper-arm direction = z of frame 3
        fx, fy, fz = dx - ex, dy - ey, dz - ez  # forearm (not normalised: only directions matter)
        fd = fx * zx + fy * zy + fz * zz
        gx, gy, gz = fx - fd * zx, fy - fd * zy, fz - fd * zz
        gn = math.sqrt(gx * gx + gy * gy + gz * gz)
        t4 = math.atan2(gn, fd)
        fn = math.hypot(gn, fd)
        if gn > DEGEN_SIN * fn:
            x3x, x3y, x3z = gx, gy, gz
        else:  # stretched / folded elbow: the swivel picks the arm plane
            pd = rux * zx + ruy * zy + ruz * zz
            x3x, x3y, x3z = -(rux - pd * zx), -(ruy - pd * zy), -(ruz - pd * zz)
            if x3x * x3x + x3y * x3y + x3z * x3z < 1e-18:  # wrist at the shoulder: u along the arm
                x3x, x3y, x3z = -zz * zx, -zz * zy, 1.0 - zz * zz
        x3x, x3y, x3z, y3x, y3y, y3z = _unit_x3(x3x, x3y, x3z, zx, zy, zz, math.sqrt)
        return (zx, zy, zz, x3x, x3y, x3z, y3x, y3y, y3z, t4, fd / fn, gn / fn)

    def _base_from_circle(
        self, Tl: list[list[float]], circ: tuple[float, ...], ux: float, uy: float
    ) -> tuple[float, ...]:
        f = self._frame3(circ, ux, uy)
        t1, t2, t3 = _zyz(*f[0:6])  # shoulder: R3 = [x3 y3 z3], from z3 and x3
        t5, t6, t7 = _zyz(*_wrist_entries(f, Tl))  # wrist: W = R4^T R_tool
        return (t1, t2, t3, f[9], t5, t6, t7)

    def _fit(self, j: int, x: float) -> list[float]:
        """In-limit 2*pi copies of angle x for joint j, nearest to 0 first (empty if none)."""
        lo, up = self._lower_l[j], self._upper_l[j]
        if not self._wide[j]:
            if lo - LIMIT_TOL <= x <= up + LIMIT_TOL:
                return [min(max(x, lo), up)]
            return []
        out = []
        for sft in self._shifts[j]:
            v = x + sft
            if lo - LIMIT_TOL <= v <= up + LIMIT_TOL:
                out.append(min(max(v, lo), up))
        out.sort(key=abs)
        return out

    def _fit0(self, j: int, x: float) -> float | None:
        """In-limit 2*pi copy of angle x nearest to 0 for joint j, or None."""
        lo, up = self._lower_l[j], self._upper_l[j]
        v = x - TWO_PI * round(x / TWO_PI)
        if lo - LIMIT_TOL <= v <= up + LIMIT_TOL:
            return min(max(v, lo), up)
        if not self._wide[j]:
            return None
        if self._very_wide[j]:
            c = self._fit(j, x)
            return c[0] if c else None
        for c in (v - TWO_PI, v + TWO_PI) if v > 0 else (v + TWO_PI, v - TWO_PI):
            if lo - LIMIT_TOL <= c <= up + LIMIT_TOL:
                return min(max(c, lo), up)
        return None

    def _expand(self, base: tuple[float, ...], all_copies: bool = False) -> list[Sequence[float]]:
        """All flip combinations of a base solution that fit the limits (each joint's copy nearest 0)."""
        t1, t2, t3, t4, t5, t6, t7 = base
        out: list[Sequence[float]] = []
        if not all_copies:
            # the 14 alternatives at their in-limit copy nearest 0 (None if none), then one C-level gather
            # per pattern. The base angles are atan2 values in [-pi, pi], so they and their negations are
            # their own copy nearest 0 (round(x / 2 pi) = 0) and only the + pi alternatives are wrapped;
            # written out, not a loop over the pairs: 12 -> 7 us per call (interleaved, 2-core test machine)
            x1, x3, x5, x7 = t1 + PI, t3 + PI, t5 + PI, t7 + PI
            F: list[float | None] = [
                t1, x1 - TWO_PI * round(x1 / TWO_PI), t2, -t2,
                t3, x3 - TWO_PI * round(x3 / TWO_PI), t4, -t4,
                t5, x5 - TWO_PI * round(x5 / TWO_PI), t6, -t6,
                t7, x7 - TWO_PI * round(x7 / TWO_PI),
            ]  # fmt: skip
            i = 0
            for lot, upt, lo, up in self._lims14:
                v = F[i]
                if lot <= v <= upt:  # type: ignore[operator]
                    if v < lo:  # type: ignore[operator]
                        F[i] = lo
                    elif v > up:  # type: ignore[operator]
                        F[i] = up
                elif self._wide14[i]:
                    F[i] = self._fit0(i >> 1, (t1, x1, t2, -t2, t3, x3, t4, -t4, t5, x5, t6, -t6, t7, x7)[i])
                else:
                    F[i] = None
                i += 1
            for get in _PATTERN_GET:
                row = get(F)
                if None not in row:
                    out.append(row)
            return out
        alts = ((t1, t1 + PI), (t2, -t2), (t3, t3 + PI), (t4, -t4), (t5, t5 + PI), (t6, -t6), (t7, t7 + PI))
        fitl = [[self._fit(j, _wrap(a)) for a in pair] for j, pair in enumerate(alts)]
        for pat in _ALT_INDEX_L:
            cols = [fitl[j][pat[j]] for j in range(7)]
            if not all(cols):
                continue
            rows: list[list[float]] = [[]]
            for c in cols:
                rows = [r + [v] for r in rows for v in c]
            out.extend(rows)
        return out

    # ------------------------------------------------------------------ public IK
    def elbow_circle(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(C, n, rho): centre (m, base frame), unit normal and radius (m) of the elbow circle of pose T.

        Raises :class:`UnreachableError` (``distance`` = metres beyond the reachable shell) if the wrist
        point is out of reach, :class:`InvalidInputError` for a malformed T.
        """
        Tl = self.check_pose(T)
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            raise UnreachableError(f"wrist point is {circ:.6g} m outside the reachable shell", distance=circ)
        L2 = self._L[1]
        _, _, _, _, _, nx, ny, nz, ca = circ
        n = np.array([nx, ny, nz])
        C = self.shoulder + L2 * ca * n
        return C, n, L2 * math.sqrt(max(0.0, 1.0 - ca * ca))

    def ik(self, T: np.ndarray, swivel: float | None = 0.0, *, all_copies: bool = False,
           limits: bool = True) -> np.ndarray:
        """Every joint solution (k, 7), k <= 8, of pose T (4x4, base frame) at swivel angle ``swivel`` (rad).

        Only solutions inside the joint limits are returned, each angle wrapped to its in-limit 2*pi copy
        nearest 0 (``all_copies=True``: one row per in-limit copy). ``limits=False``: all 8 branches
        (flip patterns, in their order) whatever the limits, each angle in (-pi, pi] (``all_copies`` is
        then ignored); a controller probing how near a limit a branch runs needs the branch beyond it
        too. An unreachable pose gives (0, 7); ``swivel=None`` means 0. Raises
        :class:`InvalidInputError` for a malformed T (shape, NaN/inf, position out of range,
        non-orthonormal rotation) or a swivel that is not a finite real number within +-1e6 rad.
        """
        # (a float or numpy float64 in range, NaN fails the test: check_scalar costs 2 us, 5-10 % of ik)
        if isinstance(swivel, float) and -ANGLE_RANGE <= swivel <= ANGLE_RANGE:
            s = float(swivel)
        else:
            s = 0.0 if swivel is None else check_scalar(swivel, "swivel", ANGLE_RANGE)
        Tl = self.check_pose(T)
        if limits is False:
            return self._branches_u(Tl, math.cos(s), math.sin(s))
        if limits is not True:
            raise InvalidInputError(f"limits must be True or False, got {limits!r}", field="limits",
                                    value=limits)
        return self._ik_u(Tl, math.cos(s), math.sin(s), all_copies)

    def ik_u(self, T: np.ndarray, u: Sequence[float], *, all_copies: bool = False) -> np.ndarray:
        """Like :meth:`ik` with the swivel quaternion u = Qz(s) i Qz(s)*: a pure unit quaternion in the
        xy plane given as its vector part (x, y, z). Raises :class:`InvalidInputError` if u is not 3 finite
        real numbers, not unit (tolerance 1e-6) or has a z component."""
        ua = check_finite_array(u, "u", (3,)).tolist()
        nu = math.hypot(ua[0], ua[1])
        if abs(ua[2]) > 1e-6 or abs(nu - 1.0) > 1e-6:
            raise InvalidInputError(
                f"u must be a unit vector in the xy plane (|u| = 1, z = 0 within 1e-6), got {ua}",
                field="u",
                value=u,
            )
        return self._ik_u(self.check_pose(T), ua[0] / nu, ua[1] / nu, all_copies)

    def _ik_u(self, Tl: list[list[float]], ux: float, uy: float, all_copies: bool) -> np.ndarray:
        base = self._base_solution(Tl, ux, uy)
        if not isinstance(base, tuple):
            return np.empty((0, 7))
        rows = self._expand(base, all_copies)
        return np.array(rows) if rows else np.empty((0, 7))

    def _branches_u(self, Tl: list[list[float]], ux: float, uy: float) -> np.ndarray:
        """The 8 branches at swivel quaternion u, limits ignored, angles in (-pi, pi]; (0, 7) out of reach."""
        base = self._base_solution(Tl, ux, uy)
        if not isinstance(base, tuple):
            return np.empty((0, 7))
        t1, t2, t3, t4, t5, t6, t7 = base
        alt = [t1, _wrap(t1 + PI), t2, -t2, t3, _wrap(t3 + PI), t4, -t4, t5, _wrap(t5 + PI), t6, -t6, t7,
               _wrap(t7 + PI)]
        return np.array([get(alt) for get in _PATTERN_GET])

    def swivel(self, q: Sequence[float]) -> float:
        """Swivel angle s in (-pi, pi] of q (eq. 16): u = qA* (pE - C)/rho qA, s = atan2(u_y, u_x).

        With the elbow stretched or folded (rho < 1e-7 m) the direction -sign(theta4) x3 (the x axis of
        joint frame 3) replaces (pE - C)/rho, consistent with :meth:`ik`.
        """
        qa = self.check_q(q)
        return self._swivel_lists(qa.tolist())

    def swivel_u(self, q: Sequence[float]) -> np.ndarray:
        """Swivel quaternion u of q as its vector part (x, y, z), z = 0."""
        s = self.swivel(q)
        return np.array([math.cos(s), math.sin(s), 0.0])

    def _swivel_lists(self, q: Sequence[float]) -> float:
        L1, L2, L3, L4 = self._L
        t1, t2, t3, t4 = q[0], q[1], q[2], q[3]
        c1, s1, c2, s2 = math.cos(t1), math.sin(t1), math.cos(t2), math.sin(t2)
        c3, s3, c4, s4 = math.cos(t3), math.sin(t3), math.cos(t4), math.sin(t4)
        ex, ey, ez = L2 * c1 * s2, L2 * s1 * s2, L2 * c2
        X = c2 * c3 * s4 + s2 * c4
        Y = s3 * s4
        Z = -s2 * c3 * s4 + c2 * c4
        dx = ex + L3 * (c1 * X - s1 * Y)
        dy = ey + L3 * (s1 * X + c1 * Y)
        dz = ez + L3 * Z
        rxy2 = dx * dx + dy * dy
        D2 = rxy2 + dz * dz
        D = math.sqrt(D2)
        if D < 1e-12:
            circ = (dx, dy, dz, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
            nx = ny = 0.0
            nz = 1.0
        else:
            nx, ny, nz = dx / D, dy / D, dz / D
            circ = (dx, dy, dz, D, rxy2, nx, ny, nz, 0.0)
        ep = ex * nx + ey * ny + ez * nz
        px, py, pz = ex - ep * nx, ey - ep * ny, ez - ep * nz
        rho = math.sqrt(px * px + py * py + pz * pz)
        if rho > RHO_DEGEN:
            px, py, pz = px / rho, py / rho, pz / rho
        else:  # stretched / folded elbow: -sign(theta4) x3
            sg = -1.0 if math.copysign(1.0, t4) > 0 else 1.0
            px = sg * (c1 * c2 * c3 - s1 * s3)
            py = sg * (s1 * c2 * c3 + c1 * s3)
            pz = sg * (-s2 * c3)
        ux, uy = self._rot_qa_inv(circ, px, py, pz)
        s = math.atan2(uy, ux)
        return PI if s <= -PI else s

    # ------------------------------------------------------------------ vectorised closed form
    # These mirror the scalar _circle / _frame3 where the singular branches differ: the scalar ones are
    # plain math on floats with ifs (ik's 15 us; numpy on one pose costs 1 us a call), these run over
    # thousands of poses with np.where. The branch-free parts are shared (_wrist_from_shoulder, _unit_x3,
    # _wrist_entries: +0.7 us on ik); the tests hold both to the same answers.
    def _circle_np(self, P: list[Any]) -> tuple[Any, ...]:
        """Vectorised :meth:`_circle`: (dx, dy, dz, rxy2, D, Ds, nx, ny, nz, ca, sa, up, down, reach) with
        Ds = D (1 at the shoulder), up / down: n = +k / -k by convention. P: 3x4 nested (m,) entries."""
        L2, L3 = self._L[1], self._L[2]
        dx, dy, dz, rxy2, D2 = _wrist_from_shoulder(P, self._L)
        D = np.sqrt(D2)
        reach = (D <= L2 + L3 + REACH_TOL) & (D >= abs(L2 - L3) - REACH_TOL)
        at_sh = D < 1e-12
        Ds = np.where(at_sh, 1.0, D)
        # the same arithmetic as the scalar _circle: a stretched elbow's sin is decided by the last bit
        inv = 1.0 / Ds
        nx = np.where(at_sh, 0.0, dx * inv)
        ny = np.where(at_sh, 0.0, dy * inv)
        nz = np.where(at_sh, 1.0, dz * inv)
        ca = np.clip((L2 * L2 + D2 - L3 * L3) / (2.0 * L2 * Ds), -1.0, 1.0)
        ca = np.where(at_sh, 0.0, ca)
        sa = np.sqrt(np.maximum(0.0, 1.0 - ca * ca))
        axis = rxy2 <= AXIS_TOL2 * D * D
        down = (dz < 0.0) & axis
        up = at_sh | ((dz >= 0.0) & axis)
        return dx, dy, dz, rxy2, D, Ds, nx, ny, nz, ca, sa, up, down, reach

    @staticmethod
    def _rot_qa_np(c: tuple[Any, ...], ux: Any, uy: Any) -> tuple[Any, Any, Any]:
        """Vectorised :meth:`_rot_qa`: qA u qA* for u = (ux, uy, 0) on the circles ``c`` of _circle_np."""
        dx, dy, dz, rxy2, D, Ds, nx, ny, nz, ca, sa, up, down, reach = c
        with np.errstate(divide="ignore", invalid="ignore"):
            h = np.where(dz >= 0.0, 1.0 + nz, rxy2 / (Ds * (Ds - dz)))
            w = -(nx * ux + ny * uy)
            wh = w / h
            flat = down | up
            rux = np.where(flat, ux, ux + nx * wh)
            ruy = np.where(up, uy, np.where(down, -uy, uy + ny * wh))
            ruz = np.where(flat, 0.0, w)
        return rux, ruy, ruz

    def _frame_np(self, c: tuple[Any, ...], ux: Any, uy: Any) -> tuple[Any, ...]:
        """Vectorised :meth:`_frame3`: (zx, zy, zz, x3x, x3y, x3z, y3x, y3y, y3z, t4, c4, s4)."""
        L2 = self._L[1]
        dx, dy, dz, rxy2, D, Ds, nx, ny, nz, ca, sa, up, down, reach = c
        rux, ruy, ruz = self._rot_qa_np(c, ux, uy)
        ex = L2 * (ca * nx + sa * rux)
        ey = L2 * (ca * ny + sa * ruy)
        ez = L2 * (ca * nz + sa * ruz)
        inv = 1.0 / np.sqrt(ex * ex + ey * ey + ez * ez)
        zx, zy, zz = ex * inv, ey * inv, ez * inv
        fx, fy, fz = dx - ex, dy - ey, dz - ez
        fd = fx * zx + fy * zy + fz * zz
        gx, gy, gz = fx - fd * zx, fy - fd * zy, fz - fd * zz
        gn = np.sqrt(gx * gx + gy * gy + gz * gz)
        t4 = np.arctan2(gn, fd)
        fn = np.sqrt(gn * gn + fd * fd)
        fn = np.where(fn == 0.0, 1.0, fn)
        reg = gn > DEGEN_SIN * fn
        gs = np.where(reg, gn, 1.0)
        pd = rux * zx + ruy * zy + ruz * zz
        x3x = np.where(reg, gx / gs, -(rux - pd * zx))
        x3y = np.where(reg, gy / gs, -(ruy - pd * zy))
        x3z = np.where(reg, gz / gs, -(ruz - pd * zz))
        tiny = x3x * x3x + x3y * x3y + x3z * x3z < 1e-18  # wrist at the shoulder: u along the arm
        if tiny.any():
            x3x = np.where(tiny, -zz * zx, x3x)
            x3y = np.where(tiny, -zz * zy, x3y)
            x3z = np.where(tiny, 1.0 - zz * zz, x3z)
        x3x, x3y, x3z, y3x, y3y, y3z = _unit_x3(x3x, x3y, x3z, zx, zy, zz, np.sqrt)
        return zx, zy, zz, x3x, x3y, x3z, y3x, y3y, y3z, t4, fd / fn, gn / fn

    def _base_np(self, P: list[Any], ux: Any, uy: Any) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised base solutions. P: 3x4 nested (m,) entries of the poses; ux, uy: (m,) swivel
        quaternion. Returns (theta (7, m), reachable (m,) bool)."""
        c = self._circle_np(P)
        f = self._frame_np(c, ux, uy)
        th = np.empty((7,) + np.shape(f[0]))
        _zyz_np(*f[0:6], th[0:3])
        th[3] = f[9]
        _zyz_np(*_wrist_entries(f, P), th[4:7])
        return th, c[-1]

    def _functions_np(
        self, P: list[Any]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised :func:`feasible.swivel_functions` for m poses (P: 3x4 nested (m,) entries).

        Returns (K (m, 10, 3), t4 (m,), deg_shoulder (m,), deg_wrist (m,), reachable (m,)); rows of
        unreachable poses are meaningless.
        """
        c = self._circle_np(P)
        with np.errstate(invalid="ignore", divide="ignore"):
            zx, zy, zz, x3x, x3y, x3z, y3x, y3y, y3z, t4, c4, s4 = self._frame_np(c, 1.0, 0.0)
            a0 = np.array(self._rot_qa_np(c, 1.0, 0.0))
            a1 = np.array(self._rot_qa_np(c, 0.0, 1.0))
        mv = np.cross(a0, a1, axis=0)  # (3, m): qA k qA*, the axis of the self-motion
        z3 = np.array([zx, zy, zz])
        x3 = np.array([x3x, x3y, x3z])
        y3 = np.array([y3x, y3y, y3z])
        x4 = c4 * x3 - s4 * z3
        z4 = s4 * x3 + c4 * z3
        r0, r1, r2 = P
        tb = np.array([r0[0], r1[0], r2[0]])
        ty = np.array([r0[1], r1[1], r2[1]])
        ta = np.array([r0[2], r1[2], r2[2]])
        m = len(zx)

        def coef(v: np.ndarray, t: np.ndarray | int, sg: Any = 1.0) -> np.ndarray:
            # (3, m): sg * [(m.v)(m.t), v.t - (m.v)(m.t), (m x v).t]; t an axis index or (3, m) vectors
            mxv = np.cross(mv, v, axis=0)
            if isinstance(t, int):
                mt, vt, xt = mv[t], v[t], mxv[t]
            else:
                mt, vt, xt = (mv * t).sum(0), (v * t).sum(0), (mxv * t).sum(0)
            k0 = (mv * v).sum(0) * mt
            return np.array([k0, vt - k0, xt]) * sg

        X1, Y1, Z2 = coef(z3, 0), coef(z3, 1), coef(z3, 2)
        X5, Y5, Z6 = coef(x4, ta), coef(y3, ta), coef(z4, ta)
        deg_sh = np.sqrt(X1 * X1 + Y1 * Y1).sum(0) <= DEGEN_SIN
        deg_wr = np.sqrt(X5 * X5 + Y5 * Y5).sum(0) <= DEGEN_SIN
        X3, Y3 = coef(x3, 2, -1.0), coef(y3, 2)
        X7, Y7 = coef(z4, tb, -1.0), coef(z4, ty)
        if deg_sh.any():  # theta2 0 or pi on the whole circle: theta3 = atan2(x3y, +-x3x), as ik
            X3 = np.where(deg_sh, coef(x3, 0, np.where(Z2[0] >= 0.0, 1.0, -1.0)), X3)
            Y3 = np.where(deg_sh, coef(x3, 1), Y3)
        if deg_wr.any():
            X7 = np.where(deg_wr, coef(x4, tb, np.where(Z6[0] >= 0.0, 1.0, -1.0)), X7)
            Y7 = np.where(deg_wr, coef(y3, tb), Y7)
        K = np.empty((m, 10, 3))
        for r, row in enumerate((X1, X3, X5, X7, Y1, Y3, Y5, Y7, Z2, Z6)):
            K[:, r, :] = row.T
        return K, t4, deg_sh, deg_wr, c[-1]

    def _check_swivels(self, swivels: Any, m: int, field: str = "swivels") -> np.ndarray:
        """Swivels (rad) as a float (m,) array: a scalar or m finite real values within +-1e6 rad."""
        sw = check_finite_array(swivels, field, None, ANGLE_RANGE)
        if sw.ndim == 0:
            return np.full(m, float(sw))
        if sw.shape != (m,):
            raise InvalidInputError(
                f"{field} must be a scalar or have shape ({m},) to match the poses, got {sw.shape}",
                field=field,
                value=swivels,
            )
        return sw

    def ik_batch(
        self, Ts: np.ndarray, swivels: Any = 0.0, *, chunk: int = 2048
    ) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised closed form for m poses at m swivel angles: ``ik`` for every pose at once.

        Ts: (m, 4, 4) base -> tool poses, swivels: (m,) rad (or one value for all).
        Returns ``(Q, valid)``: Q of shape (m, 8, 7) holding the 8 flip combinations in the same order as
        :meth:`ik` (pattern (f2, f4, f6) in binary) wrapped to the in-limit copy nearest 0, and ``valid``
        (m, 8) bool, False where the pose is out of reach or the solution violates a limit. Entries that
        are not valid hold NaN. Every pose is validated as :meth:`ik` does (shape, NaN/inf, range, bottom
        row, orthonormal rotation): a malformed row raises :class:`InvalidInputError` naming it (no row is
        ever flagged valid for a pose it does not reach). ``chunk`` poses are solved per pass: 2048 keep
        the temporaries in the 2 MB cache (measured on the 2-core test machine: 8192 was 30 % slower).
        """
        Ts = self.check_poses(Ts)
        m = len(Ts)
        sw = self._check_swivels(swivels, m)
        Q = np.empty((m, 8, 7))
        valid = np.empty((m, 8), dtype=bool)
        step = max(1, int(chunk))
        for k0 in range(0, m, step):
            sl = slice(k0, min(m, k0 + step))
            T = Ts[sl]
            P = [[T[:, i, j] for j in range(4)] for i in range(3)]
            s = sw[sl]
            th, reach = self._base_np(P, np.cos(s), np.sin(s))
            self._flips_fit(th, reach, Q[sl], valid[sl])
        return Q, valid

    def _flips_fit(self, th: np.ndarray, reach: np.ndarray, Q: np.ndarray, valid: np.ndarray) -> None:
        """(7, n) base angles and reachable (n,) -> Q (n, 8, 7) at the in-limit copy nearest 0 or NaN, and
        valid (n, 8), written into the given arrays.

        Alternative-major (14, n) until the final gather: with the per-alternative constants as (14, 1)
        columns every operation runs over the n poses; the pose-major (n, 7, 2) layout it replaces made
        numpy's inner loops 2 long (measured 10x slower for those operations on the test machine).
        """
        tab = self._tables
        n = th.shape[1]
        V = th[_J14]  # row 2 j + a: alternative a of joint j
        V *= tab.sign14
        V += tab.shift_lot14  # alternative - (lower - tol)
        V -= TWO_PI * np.floor(V * (1.0 / TWO_PI))
        feas = V <= tab.width14
        V += tab.lot14  # the lowest copy >= lower - tol
        for j in tab.wide_l:  # more copies fit: the one in (-pi, pi] if it fits, as ik (else the nearest)
            Vw = V[2 * j : 2 * j + 2]
            k = np.floor((PI - Vw) * (1.0 / TWO_PI))
            np.maximum(k, 0.0, out=k)
            np.minimum(k, np.floor((tab.upt14[2 * j : 2 * j + 2] - Vw) * (1.0 / TWO_PI)), out=k)
            k *= TWO_PI
            Vw += k
        np.maximum(V, tab.lo14, out=V)
        np.minimum(V, tab.up14, out=V)
        ok = feas[_IDX56].reshape(8, 7, n).all(axis=1)
        ok &= reach
        valid[:] = ok.T
        Q.reshape(n, 56)[:] = np.ascontiguousarray(V.T)[:, _IDX56]
        Q.reshape(n * 8, 7)[np.flatnonzero(~valid.ravel())] = np.nan

    def swivel_functions(self, T: np.ndarray) -> SwivelFunctions:
        """The closed-form joint functions of pose T along the swivel circle (see :mod:`.feasible`).

        Raises :class:`InvalidInputError` for a malformed T, :class:`UnreachableError` if out of reach.
        """
        Tl = self.check_pose(T)
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            raise UnreachableError(f"wrist point is {circ:.6g} m outside the reachable shell", distance=circ)
        return swivel_functions(self, Tl, circ)

    def feasible_swivels(self, T: np.ndarray) -> list[np.ndarray]:
        """The swivels (rad) at which pose T has an in-limit solution, per flip pattern, in closed form.

        Returns 8 arrays (one per flip pattern (f2, f4, f6), in the row order of :meth:`ik`), each (k, 2):
        closed intervals [start, end] with start in [-pi, pi), start <= end <= start + 2*pi (an interval
        may run past pi; the whole circle is [-pi, pi]); zero-width rows are isolated swivels where a joint
        touches a limit. ``ik(T, s)`` has a row of pattern b exactly for s in ``feasible_swivels(T)[b]``
        (up to the 1e-10 rad limit tolerance). Raises :class:`InvalidInputError` for a malformed T and
        :class:`UnreachableError` (with ``distance``) if the wrist is out of reach.
        """
        fn = self.swivel_functions(T)
        return feasible_intervals(fn, self._interval_tables)

    def swivel_corridor(self, T_start: np.ndarray, T_goal: np.ndarray, q_start: Sequence[float],
                        **options: Any) -> SwivelCorridor:
        """The swivel corridor of the straight route from ``T_start`` (the pose of ``q_start``) to
        ``T_goal`` and a continuous schedule through it: :func:`.corridor.swivel_corridor` (the options
        and the result are documented there)."""
        return swivel_corridor(self, T_start, T_goal, q_start, **options)

    def swivel_interval(self, q: Sequence[float]) -> tuple[float, float] | None:
        """How far the elbow of configuration ``q`` can swivel, the hand held, before a joint meets its
        limit: the interval [a, b] (rad, a in [-pi, pi), a <= swivel(q) (mod 2 pi) <= b <= a + 2 pi) of
        :meth:`feasible_swivels` of q's pose, on q's flip pattern, that holds q's swivel. None if q is
        outside the limits, its elbow stretched or folded (no swivel circle), or its pattern unknown
        (a joint at a singular angle). Raises :class:`InvalidInputError` for a malformed q."""
        qa = self.check_q(q)
        if not self.within_limits(qa):
            return None
        T = self.fk(qa)
        Tl = self.check_pose(T)
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            return None
        s = self._swivel_lists(qa.tolist())
        ql = qa.tolist()
        ones = [1.0] * 7
        pattern = None
        for b in range(8):
            r = self._branch_eval(Tl, circ, s, b, ql, ones)
            if r is not None and r[1] < 1e-12:
                pattern = b
                break
        if pattern is None:
            return None
        for a0, a1 in feasible_intervals(swivel_functions(self, Tl, circ), self._interval_tables)[pattern]:
            if a0 + (s - a0) % TWO_PI <= a1 + 1e-9:
                return float(a0), float(a1)
        return None

    def ik_nearest(
        self,
        T: np.ndarray,
        q_seed: Sequence[float],
        *,
        weights: Sequence[float] | None = None,
        timeout_s: float | None = None,
        exhaustive: bool = False,
    ) -> tuple[np.ndarray | None, IKInfo]:
        """The in-limit solution of pose T nearest to ``q_seed`` over all swivel angles (the global optimum).

        Distance: ``sum(w * (q - q_seed)**2)`` (rad^2, ``weights`` w >= 0, default 1), each joint at its
        in-limit 2*pi copy nearest the seed. Minimised over every flip pattern, every copy and every
        feasible swivel interval, interval ends included (see :mod:`.feasible`): deterministic, no random
        restarts. A seed may lie outside the limits (it is only a preference).

        ``timeout_s`` (s, None = no limit): if the budget runs out before every candidate basin has been
        refined, the status is TIMEOUT and q is the best in-limit solution found so far (exact, within the
        limits, maybe not the nearest). The search is bounded (a few hundred closed-form samples and a
        Newton refinement per candidate), so a budget of a few milliseconds is never reached.

        ``exhaustive``: the candidate basins are bounded by a parabola through neighbouring samples and
        the tangent at the sample, which can miss a basin where theta2 or theta6 passes near 0
        (measured: 2 poses in 480000, at most 1.9e-2 rad^2 from the optimum). True also bounds every arc
        between samples rigorously and refines those that may hold a nearer solution: the measured
        misses are found, at 2-3 times the time.

        Returns (q or None, :class:`IKInfo`); statuses SUCCESS, TIMEOUT, INVALID_INPUT, OUT_OF_REACH,
        NO_SOLUTION_IN_LIMITS. Unknown keyword arguments raise ``TypeError``.
        """
        t0 = time.perf_counter()
        try:
            Tl = self.check_pose(T)
            seed = self.check_q(q_seed, "q_seed")
            w = self._check_weights(weights)
            deadline = None
            if timeout_s is not None:
                tmo = check_scalar(timeout_s, "timeout_s")
                if tmo < 0.0:
                    raise InvalidInputError(
                        f"timeout_s must be >= 0 s, got {tmo}", field="timeout_s", value=tmo
                    )
                deadline = t0 + tmo
        except InvalidInputError as exc:
            return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            return None, IKInfo(
                IKStatus.OUT_OF_REACH, f"wrist point is {circ:.6g} m outside the reachable shell"
            )
        fn = swivel_functions(self, Tl, circ)
        seed_l = seed.tolist()
        w_l = w.tolist()
        res = nearest(
            fn,
            self._tables,
            seed,
            w,
            self._swivel_lists(seed_l),
            deadline,
            lambda s, b, pred: self._realise(Tl, circ, s, b, pred, seed_l, w_l),
            exhaustive=bool(exhaustive),
        )
        if res.q is None:
            why = (
                "reachable, but no swivel gives a solution within the joint limits (closed-form feasible "
                "set empty for all 8 flip patterns)"
                if res.swivel is None
                else "the closed-form feasible set is a sliver the scalar solve cannot hit within 1e-10 rad "
                "of the limits (round-off)"
            )
            return None, IKInfo(IKStatus.NO_SOLUTION_IN_LIMITS, why, candidates=res.candidates)
        q, s_best, b_best = np.array(res.q), res.swivel, res.branch
        pe, re = self._pose_err_lists(res.q, Tl)
        status = IKStatus.TIMEOUT if res.timed_out else IKStatus.SUCCESS
        msg = (
            "ok"
            if not res.timed_out
            else (f"timeout_s {timeout_s:g} s ran out after {res.refined} refined candidates: best so far")
        )
        return q, IKInfo(
            status,
            msg,
            swivel=s_best,
            pos_err=pe,
            rot_err=re,
            iterations=res.evaluations,
            candidates=res.candidates,
            branch=b_best,
        )

    def _realise(
        self,
        Tl: list[list[float]],
        circ: tuple[float, ...],
        s: float,
        b: int,
        pred: float,
        seed: list[float],
        w: list[float],
    ) -> tuple[list[float], float, int, float] | None:
        """The scalar solve of a candidate (swivel s, pattern b) of the nearest search, as ``ik`` computes it:
        (q, swivel, pattern, cost) or None.

        The closed-form functions and ``ik`` agree to round-off, except exactly at a singular swivel
        (theta2 or theta6 at 0 there: ``ik`` uses its theta1 = 0 convention, the functions the limit from
        one side) and at a limit (1e-10 rad tolerance). If the solve is infeasible there or costlier than
        the prediction ``pred``, the swivels 1e-9 and 1e-7 rad to either side are tried, then those and s
        with the flip patterns that trade places with b across a singular swivel (theta2 or theta6
        passing 0 turns theta1 and theta3, or theta5 and theta7, by pi: the f2 and f6 flips); the best
        of them is returned, maybe costlier than predicted.
        """
        tol = 1e-12 * (1.0 + pred)
        r = self._branch_eval(Tl, circ, s, b, seed, w)
        if r is not None and r[1] <= pred + tol:
            return r[0], s, b, r[1]
        best = None if r is None else (r[0], s, b, r[1])
        probes = (s - 1e-9, s + 1e-9, s - 1e-7, s + 1e-7)
        for sv, bb in [(sv, b) for sv in probes] + [(sv, b ^ f) for f in (4, 1, 5) for sv in (s, *probes)]:
            r = self._branch_eval(Tl, circ, sv, bb, seed, w)
            if r is not None and (best is None or r[1] < best[3]):
                best = (r[0], math.remainder(sv, TWO_PI), bb, r[1])
                if bb == b and r[1] <= pred + tol:
                    break
        return best

    def ik_nearest_batch(
        self,
        Ts: np.ndarray,
        q_seeds: Any,
        *,
        weights: Sequence[float] | None = None,
        chunk: int = 128,
        exhaustive: bool = False,
    ) -> IKBatchResult:
        """:meth:`ik_nearest` for m poses at once, vectorised over the poses (same search, same optimum).

        Ts: (m, 4, 4); q_seeds: (m, 7) or one (7,) seed for all (rad); ``weights`` (7,) >= 0. Malformed
        input raises :class:`InvalidInputError` (naming the row). ``chunk`` poses are solved per pass
        (about 100 kB of temporaries per pose; 128 keep them in cache). Returns an
        :class:`IKBatchResult` (q NaN where no solution). ``exhaustive``: as :meth:`ik_nearest`'s, solved
        pose by pose (the rigorous arc bound is not vectorised).
        """
        Ts = self.check_poses(Ts)
        m = len(Ts)
        seeds = check_finite_array(q_seeds, "q_seeds", None, ANGLE_RANGE)
        one_seed = None
        if seeds.shape == (7,):
            one_seed = self._swivel_lists(seeds.tolist())
            seeds = np.broadcast_to(seeds, (m, 7))
        elif seeds.shape != (m, 7):
            raise InvalidInputError(
                f"q_seeds must have shape (7,) or ({m}, 7), got {seeds.shape}", field="q_seeds", value=q_seeds
            )
        w = self._check_weights(weights)
        out = IKBatchResult.unsolved(m)
        if exhaustive:
            for i in range(m):
                self._nearest_row(out, i, Ts[i], seeds[i], w, exhaustive=True)
            return out
        step = max(1, int(chunk))
        ws = NearestWorkspace(min(step, max(m, 1)), self._tables.batch_samples)
        # the closed-form functions of all poses first, in blocks of 2048 as ik_batch: their (3, poses)
        # arrays are small, so per 128-pose chunk numpy's per-call overhead was their cost (10 % of the batch)
        K_all = np.empty((m, 10, 3))
        t4_all = np.empty(m)
        dsh_all, dwr_all, reach_all = (np.empty(m, bool) for _ in range(3))
        for a0 in range(0, m, 2048):
            Tb = Ts[a0 : a0 + 2048]
            fns = self._functions_np([[Tb[:, i, j] for j in range(4)] for i in range(3)])
            for dst, src in zip((K_all, t4_all, dsh_all, dwr_all, reach_all), fns, strict=True):
                dst[a0 : a0 + 2048] = src
        for k0 in range(0, m, step):
            T = Ts[k0 : k0 + step]
            sl = slice(k0, k0 + step)
            K, t4, dsh, dwr, reach = K_all[sl], t4_all[sl], dsh_all[sl], dwr_all[sl], reach_all[sl]
            ri = np.nonzero(reach)[0]
            if len(ri) == 0:
                continue
            sd = np.ascontiguousarray(seeds[k0 + ri])
            if one_seed is not None:  # one seed for all poses: its swivel once
                s_seed = np.full(len(ri), one_seed)
            else:
                s_seed = np.array([self._swivel_lists(q) for q in sd.tolist()])
            s, b, pred, odd = nearest_batch(K[ri], t4[ri], dsh[ri], dwr[ri], self._tables, sd, w, s_seed, ws)
            gi = k0 + ri
            out.status[gi] = BATCH_NO_SOLUTION_IN_LIMITS
            b[odd] = -1  # (near-equal samples, which the scalar search merges: solved one by one below)
            for i in np.nonzero(odd)[0]:
                self._nearest_row(out, k0 + ri[i], T[ri[i]], sd[i], w)
            hit = b >= 0
            if not hit.any():
                continue
            rows = ri[hit]
            Ph = [[T[rows, i, j] for j in range(4)] for i in range(3)]
            sh, bh, sdh, ph = s[hit], b[hit], sd[hit], pred[hit]
            th, _ = self._base_np(Ph, np.cos(sh), np.sin(sh))
            q, feas, cost = self._nearest_copies(th, bh, sdh, w)
            # round-off at an interval end or a singular swivel (where ik's conventions and the closed-form
            # functions part by more than round-off, and where the scalar solve also tries the patterns
            # that trade places there): solve that pose alone, as ik_nearest does
            sing = np.minimum(np.abs(np.sin(th[1])), np.abs(np.sin(th[5]))) < 1e-6
            redo = ~feas | (cost > ph + 1e-9 * (1.0 + ph)) | sing
            for i in np.nonzero(redo)[0]:
                qi, info = self.ik_nearest(T[rows[i]], sdh[i], weights=w)
                if qi is not None and info.swivel is not None and info.branch is not None:
                    q[i], cost[i] = qi, float(np.sum(w * (qi - sdh[i]) ** 2))
                    sh[i], bh[i], feas[i] = info.swivel, info.branch, True
            g = k0 + rows[feas]
            out.q[g] = q[feas]
            out.swivel[g] = sh[feas]
            out.branch[g] = bh[feas]
            out.cost[g] = cost[feas]
            out.status[g] = BATCH_SUCCESS
        return out

    def _nearest_row(
        self,
        out: IKBatchResult,
        g: int,
        T: np.ndarray,
        seed: np.ndarray,
        w: np.ndarray,
        exhaustive: bool = False,
    ) -> None:
        """Row g of a batched nearest answer solved alone by :meth:`ik_nearest` (checked input)."""
        qi, info = self.ik_nearest(T, seed, weights=w, exhaustive=exhaustive)
        if qi is not None and info.swivel is not None and info.branch is not None:
            out.q[g], out.swivel[g], out.branch[g] = qi, info.swivel, info.branch
            out.cost[g] = float(np.sum(w * (qi - seed) ** 2))
            out.status[g] = BATCH_SUCCESS
        elif info.status == IKStatus.NO_SOLUTION_IN_LIMITS:
            out.status[g] = BATCH_NO_SOLUTION_IN_LIMITS

    def _nearest_copies(
        self, th: np.ndarray, branch: np.ndarray, seeds: np.ndarray, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(7, n) base angles, pattern (n,), seeds (n, 7) -> (q (n, 7) at the in-limit copies nearest the
        seeds, all-joints-feasible (n,), weighted squared distance (n,))."""
        tab = self._tables
        X = th[:, None, :] * tab.sign3 + tab.shift_lot
        Xm = X - TWO_PI * np.floor(X * (1.0 / TWO_PI))
        feas = Xm <= tab.width3
        E = Xm + (tab.lot3 - seeds.T[:, None, :])
        if len(tab.wide):
            wj = tab.wide
            Ew = E[wj]
            kmax = np.maximum(np.floor((tab.width3[wj] - Xm[wj]) * (1.0 / TWO_PI)), 0.0)
            E[wj] = Ew + TWO_PI * np.clip(np.rint(Ew * (-1.0 / TWO_PI)), 0.0, kmax)
        n = th.shape[1]
        alt = _ALT_INDEX[branch].T  # (7, n)
        jj = np.arange(7)[:, None]
        ii = np.arange(n)[None, :]
        q = np.clip(E[jj, alt, ii] + seeds.T, tab.lo3[:, 0], tab.up3[:, 0]).T
        ok = feas[jj, alt, ii].all(axis=0)
        return q, ok, ((q - seeds) ** 2 * w).sum(axis=1)

    def _check_weights(self, weights: Sequence[float] | None) -> np.ndarray:
        if weights is None:
            return np.ones(7)
        w = check_finite_array(weights, "weights", (7,), 1e12)
        if np.any(w < 0):
            raise InvalidInputError(f"weights must be >= 0, got {w.tolist()}", field="weights", value=weights)
        return w

    def _fk_zyz(self, q: Sequence[float]) -> tuple[tuple[float, ...], tuple[float, float, float]]:
        """Scalar FK of this z,y,z,y,z,y,z arm (same result as the generic chain FK, 3x fewer operations):
        (R as its columns x0 x1 x2 y0 y1 y2 z0 z1 z2, p). q: 7 floats (rad), not validated."""
        L1, L2, L3, L4 = self._L
        cos, sin = math.cos, math.sin
        xa, xb, xc, ya, yb, yc, za, zb, zc = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
        px, py, pz = 0.0, 0.0, L1
        for j in range(7):
            c, s = cos(q[j]), sin(q[j])
            if j % 2 == 0:  # R Rz: x' = c x + s y, y' = c y - s x
                xa, xb, xc, ya, yb, yc = (
                    c * xa + s * ya,
                    c * xb + s * yb,
                    c * xc + s * yc,
                    c * ya - s * xa,
                    c * yb - s * xb,
                    c * yc - s * xc,
                )
            else:  # R Ry: x' = c x - s z, z' = s x + c z; then the next link along z
                xa, xb, xc, za, zb, zc = (
                    c * xa - s * za,
                    c * xb - s * zb,
                    c * xc - s * zc,
                    s * xa + c * za,
                    s * xb + c * zb,
                    s * xc + c * zc,
                )
                Lk = (L2, L3, L4)[j // 2]
                px, py, pz = px + Lk * za, py + Lk * zb, pz + Lk * zc
        return (xa, xb, xc, ya, yb, yc, za, zb, zc), (px, py, pz)

    def _pose_err_lists(self, q: list[float], Tl: list[list[float]]) -> tuple[float, float]:
        """(position error m, rotation error rad) of fk(q) against the nested-list pose Tl."""
        (xa, xb, xc, ya, yb, yc, za, zb, zc), (px, py, pz) = self._fk_zyz(q)
        r0, r1, r2 = Tl[0], Tl[1], Tl[2]
        pe = math.sqrt((px - r0[3]) ** 2 + (py - r1[3]) ** 2 + (pz - r2[3]) ** 2)
        # residual rotation M = Rd R^T: angle = atan2(|skew(M)| / 2, (trace(M) - 1) / 2)
        m00 = r0[0] * xa + r0[1] * ya + r0[2] * za
        m11 = r1[0] * xb + r1[1] * yb + r1[2] * zb
        m22 = r2[0] * xc + r2[1] * yc + r2[2] * zc
        m21 = r2[0] * xb + r2[1] * yb + r2[2] * zb
        m12 = r1[0] * xc + r1[1] * yc + r1[2] * zc
        m02 = r0[0] * xc + r0[1] * yc + r0[2] * zc
        m20 = r2[0] * xa + r2[1] * ya + r2[2] * za
        m10 = r1[0] * xa + r1[1] * ya + r1[2] * za
        m01 = r0[0] * xb + r0[1] * yb + r0[2] * zb
        vx, vy, vz = m21 - m12, m02 - m20, m10 - m01
        re = math.atan2(0.5 * math.sqrt(vx * vx + vy * vy + vz * vz), 0.5 * (m00 + m11 + m22 - 1.0))
        return pe, abs(re)

    def _branch_eval(
        self,
        Tl: list[list[float]],
        circ: tuple[float, ...],
        s: float,
        branch: int,
        seed: list[float],
        w: list[float],
    ) -> tuple[list[float], float] | None:
        """Flip pattern ``branch`` at swivel s (scalar solve), each angle at its in-limit 2*pi copy nearest
        the seed (the seed may lie outside the limits). Returns (q, weighted squared distance to the seed)
        or None if a limit is violated (beyond the 1e-10 rad tolerance)."""
        base = self._base_from_circle(Tl, circ, math.cos(s), math.sin(s))
        sg = _ALT_SIGN_L[branch]
        sh = _ALT_SHIFT_L[branch]
        q = []
        cost = 0.0
        for j in range(7):
            lot, upt, lo, up = self._lims[j]
            a = base[j] * sg[j] + sh[j]
            r = seed[j]
            if self._wide[j]:  # several copies may fit: the one nearest the seed
                v0 = lot + (a - lot) % TWO_PI  # lowest copy >= lower - tol
                kmax = math.floor((upt - v0) / TWO_PI)
                if kmax < 0:
                    return None
                v = v0 + TWO_PI * min(max(round((r - v0) / TWO_PI), 0), kmax)
            else:  # one copy at most: the one nearest the middle of the range
                v = a - TWO_PI * round((a - 0.5 * (lo + up)) / TWO_PI)
                if v < lot or v > upt:
                    return None
            v = lo if v < lo else (up if v > up else v)
            q.append(v)
            cost += w[j] * (v - r) ** 2
        return q, cost
