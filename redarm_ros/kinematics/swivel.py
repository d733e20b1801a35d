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
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.kinematics.model import LIMIT_TOL, Arm, Joint
from redarm_ros.kinematics.result import IKInfo, IKStatus

__all__ = ["SwivelArm", "FLIP_PATTERNS"]

PI = math.pi
TWO_PI = 2.0 * math.pi
REACH_TOL = 1e-9  # m; a wrist this far beyond the reach sphere still counts as (just) reachable
DEGEN_SIN = 1e-12  # |sin theta| below which the arm plane / a ZYZ decomposition is degenerate
ZOOM_SIN = 0.1  # ik_nearest zooms in when |sin theta2| or |sin theta6| of its best candidate is below
RHO_DEGEN = 1e-7  # m; below this elbow-circle radius swivel(q) uses the degenerate definition
SING_WIDTH = 0.35  # rad; ik_nearest searches closely where theta2 or theta6 gets this near 0 or pi
AXIS_TOL2 = 1e-24  # (1e-12)^2: a wrist within 1e-12 * D of the base axis counts as on it (n = +-k)

# flip pattern k -> (f2, f4, f6); per joint which of the two alternatives (base, flipped) to use
FLIP_PATTERNS = [((k >> 2) & 1, (k >> 1) & 1, k & 1) for k in range(8)]
_ALT_INDEX = np.array([[f2, f2, f2 ^ f4, f4, f4 ^ f6, f6, f6] for f2, f4, f6 in FLIP_PATTERNS])
_ALT_INDEX_L = _ALT_INDEX.tolist()
# the same flips as affine maps: angle -> sign * angle + shift (shift a multiple of pi, not wrapped)
_J7 = np.arange(7)[None, :]
# alternatives per joint as affine maps angle -> sign * angle + shift: (7, 2), column 1 = flipped
_ALT_SIGN = np.array([[1.0, 1.0 if j % 2 == 0 else -1.0] for j in range(7)])
_ALT_SHIFT = np.array([[0.0, PI if j % 2 == 0 else 0.0] for j in range(7)])
# per flip pattern the affine map of each joint (lists for the scalar path)
_ALT_SIGN_L = [[float(_ALT_SIGN[j, k]) for j, k in enumerate(row)] for row in _ALT_INDEX.tolist()]
_ALT_SHIFT_L = [[float(_ALT_SHIFT[j, k]) for j, k in enumerate(row)] for row in _ALT_INDEX.tolist()]


def _wrap(x: float) -> float:
    """x (within (-3pi, 3pi]) wrapped into (-pi, pi]."""
    if x > PI:
        return x - TWO_PI
    if x <= -PI:
        return x + TWO_PI
    return x


class SwivelArm(Arm):
    """7-DOF z,y,z,y,z,y,z arm with link lengths L1..L4 (m): closed-form swivel IK.

    ``fk`` orientation is ``Qz(t1)Qy(t2)Qz(t3)Qy(t4)Qz(t5)Qy(t6)Qz(t7)`` (w, x, y, z); shoulder at
    ``L1 k``, elbow ``pS + L2 q2 k q2*``, wrist ``pE + L3 q4 k q4*``, tool ``pW + L4 q6 k q6*``.
    """

    kind = "swivel7"
    has_swivel = True

    def __init__(
        self,
        name: str,
        chain: Sequence[Joint],
        tool: np.ndarray,
        key_joints: Sequence[int],
        config: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(name, chain, tool, key_joints, config)
        L = [float(v) for v in self.config["link_lengths"]]
        self.link_lengths = tuple(L)
        self._L = tuple(L)
        # joints whose range reaches beyond (-pi, pi]: more than one 2*pi copy may fit
        self._wide = [lo < -PI or up > PI for lo, up in zip(self._lower_l, self._upper_l, strict=True)]
        self._very_wide = [
            lo < -3 * PI or up > 3 * PI for lo, up in zip(self._lower_l, self._upper_l, strict=True)
        ]
        self._lo2 = self.lower[:, None]
        self._up2 = self.upper[:, None]
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
        L1, L2, L3, L4 = self._L
        r0, r1, r2 = Tl[0], Tl[1], Tl[2]
        dx = r0[3] - L4 * r0[2]
        dy = r1[3] - L4 * r1[2]
        dz = r2[3] - L4 * r2[2] - L1
        rxy2 = dx * dx + dy * dy
        D2 = rxy2 + dz * dz
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
    def _rot_qa(circ: tuple[float, ...], ux: float, uy: float) -> tuple[float, float, float]:
        """qA u qA* for u = (ux, uy, 0): the shortest rotation k -> n applied to u (eq. 14-15)."""
        dx, dy, dz, D, rxy2, nx, ny, nz, _ = circ
        if D == 0.0 or (dz >= 0.0 and rxy2 <= AXIS_TOL2 * D * D):
            return ux, uy, 0.0
        if dz >= 0.0:
            h = 1.0 + nz
        elif rxy2 <= AXIS_TOL2 * D * D:  # n = -k: rotation by pi about x
            return ux, -uy, 0.0
        else:  # 1 + nz without cancellation
            h = rxy2 / (D * (D - dz))
        w = -(nx * ux + ny * uy)
        return ux + nx * w / h, uy + ny * w / h, w

    @staticmethod
    def _rot_qa_inv(circ: tuple[float, ...], ex: float, ey: float, ez: float) -> tuple[float, float]:
        """(x, y) of qA* e qA: inverse of :meth:`_rot_qa` (eq. 16)."""
        dx, dy, dz, D, rxy2, nx, ny, nz, _ = circ
        if D == 0.0 or (dz >= 0.0 and rxy2 <= AXIS_TOL2 * D * D):
            return ex, ey
        if dz >= 0.0:
            h = 1.0 + nz
        elif rxy2 <= AXIS_TOL2 * D * D:
            return ex, -ey
        else:
            h = rxy2 / (D * (D - dz))
        wz = -(nx * ex + ny * ey)
        return ex - nx * ez + nx * wz / h, ey - ny * ez + ny * wz / h

    def _base_solution(self, Tl: list[list[float]], ux: float, uy: float) -> tuple[float, ...] | float:
        """The base solution (theta2, theta4, theta6 >= 0) at swivel quaternion u, or the reach violation."""
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            return circ
        return self._base_from_circle(Tl, circ, ux, uy)

    def _base_from_circle(
        self, Tl: list[list[float]], circ: tuple[float, ...], ux: float, uy: float
    ) -> tuple[float, ...]:
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
        # normalise and orthogonalise again: g is tiny next to f near the stretched elbow
        k = 1.0 / math.sqrt(x3x * x3x + x3y * x3y + x3z * x3z)
        x3x, x3y, x3z = x3x * k, x3y * k, x3z * k
        pd = x3x * zx + x3y * zy + x3z * zz
        x3x, x3y, x3z = x3x - pd * zx, x3y - pd * zy, x3z - pd * zz
        k = 1.0 / math.sqrt(x3x * x3x + x3y * x3y + x3z * x3z)
        x3x, x3y, x3z = x3x * k, x3y * k, x3z * k
        y3x, y3y, y3z = zy * x3z - zz * x3y, zz * x3x - zx * x3z, zx * x3y - zy * x3x
        # ZYZ of R3 = [x3 y3 z3] (eq. 11); theta3 from the residual so that degenerate cases stay exact
        rz = math.sqrt(zx * zx + zy * zy)
        t2 = math.atan2(rz, zz)
        if rz > DEGEN_SIN:
            c1, s1 = zx / rz, zy / rz
            t1 = math.atan2(zy, zx)
        else:
            c1, s1, t1 = 1.0, 0.0, 0.0
        a11 = c1 * x3x + s1 * x3y
        a21 = -s1 * x3x + c1 * x3y
        t3 = math.atan2(a21, zz * a11 - rz * x3z)
        # R4 = R3 Ry(theta4): x4 = c4 x3 - s4 z3, y4 = y3, z4 = s4 x3 + c4 z3
        c4, s4 = fd / fn, gn / fn
        x4x, x4y, x4z = c4 * x3x - s4 * zx, c4 * x3y - s4 * zy, c4 * x3z - s4 * zz
        z4x, z4y, z4z = s4 * x3x + c4 * zx, s4 * x3y + c4 * zy, s4 * x3z + c4 * zz
        r0, r1, r2 = Tl[0], Tl[1], Tl[2]
        ax, ay, az = r0[2], r1[2], r2[2]
        bx, by, bz = r0[0], r1[0], r2[0]
        w13 = x4x * ax + x4y * ay + x4z * az
        w23 = y3x * ax + y3y * ay + y3z * az
        w33 = z4x * ax + z4y * ay + z4z * az
        w11 = x4x * bx + x4y * by + x4z * bz
        w21 = y3x * bx + y3y * by + y3z * bz
        w31 = z4x * bx + z4y * by + z4z * bz
        rw = math.sqrt(w13 * w13 + w23 * w23)
        t6 = math.atan2(rw, w33)
        if rw > DEGEN_SIN:
            c5, s5 = w13 / rw, w23 / rw
            t5 = math.atan2(w23, w13)
        else:
            c5, s5, t5 = 1.0, 0.0, 0.0
        b11 = c5 * w11 + s5 * w21
        b21 = -s5 * w11 + c5 * w21
        t7 = math.atan2(b21, w33 * b11 - rw * w31)
        return (t1, t2, t3, t4, t5, t6, t7)

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

    def _expand(self, base: tuple[float, ...], all_copies: bool = False) -> list[list[float]]:
        """All flip combinations of a base solution that fit the limits (each joint's copy nearest 0)."""
        t1, t2, t3, t4, t5, t6, t7 = base
        alts = (
            (t1, t1 + PI),
            (t2, -t2),
            (t3, t3 + PI),
            (t4, -t4),
            (t5, t5 + PI),
            (t6, -t6),
            (t7, t7 + PI),
        )
        out: list[list[float]] = []
        if not all_copies:
            f0 = self._fit0
            fits = [(f0(j, a), f0(j, b)) for j, (a, b) in enumerate(alts)]
            for pat in _ALT_INDEX_L:
                row = [fits[0][pat[0]], fits[1][pat[1]], fits[2][pat[2]], fits[3][pat[3]]]
                row += [fits[4][pat[4]], fits[5][pat[5]], fits[6][pat[6]]]
                if None not in row:
                    out.append(row)  # type: ignore[arg-type]
            return out
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

    def ik(self, T: np.ndarray, swivel: float | None = 0.0, *, all_copies: bool = False) -> np.ndarray:
        """Every joint solution (k, 7), k <= 8, of pose T (4x4, base frame) at swivel angle ``swivel`` (rad).

        Only solutions inside the joint limits are returned, each angle wrapped to its in-limit 2*pi copy
        nearest 0 (``all_copies=True``: one row per in-limit copy). An unreachable pose gives (0, 7).
        Raises :class:`InvalidInputError` for NaN/inf, a non-orthonormal rotation or a bad swivel.
        """
        if swivel is None:
            swivel = 0.0
        try:
            s = float(swivel)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(
                f"swivel must be a number, got {swivel!r}", field="swivel", value=swivel
            ) from exc
        if not math.isfinite(s):
            raise InvalidInputError(f"swivel must be finite, got {s}", field="swivel", value=swivel)
        return self._ik_u(self.check_pose(T), math.cos(s), math.sin(s), all_copies)

    def ik_u(self, T: np.ndarray, u: Sequence[float], *, all_copies: bool = False) -> np.ndarray:
        """Like :meth:`ik` with the swivel quaternion u = Qz(s) i Qz(s)*: a pure unit quaternion in the
        xy plane given as its vector part (x, y, z). Raises :class:`InvalidInputError` if u is not unit
        (tolerance 1e-6) or has a z component."""
        try:
            ua = [float(v) for v in u]
        except (TypeError, ValueError) as exc:
            raise InvalidInputError("u must be 3 numbers (x, y, z)", field="u", value=u) from exc
        if len(ua) != 3 or not all(math.isfinite(v) for v in ua):
            raise InvalidInputError("u must be 3 finite numbers (x, y, z)", field="u", value=u)
        nu = math.hypot(ua[0], ua[1])
        if abs(ua[2]) > 1e-6 or abs(nu - 1.0) > 1e-6:
            raise InvalidInputError(f"u must be a unit vector in the xy plane, got {ua}", field="u", value=u)
        return self._ik_u(self.check_pose(T), ua[0] / nu, ua[1] / nu, all_copies)

    def _ik_u(self, Tl: list[list[float]], ux: float, uy: float, all_copies: bool) -> np.ndarray:
        base = self._base_solution(Tl, ux, uy)
        if not isinstance(base, tuple):
            return np.empty((0, 7))
        rows = self._expand(base, all_copies)
        return np.array(rows) if rows else np.empty((0, 7))

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
    def _base_np(self, P: list[Any], ux: np.ndarray, uy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised base solutions. P: 3x4 nested entries (scalars or (m,) arrays) of the poses;
        ux, uy: (m,) swivel quaternion. Returns (theta (m, 7), reachable (m,) bool)."""
        L1, L2, L3, L4 = self._L
        r0, r1, r2 = P
        dx = np.asarray(r0[3] - L4 * r0[2], dtype=float) + 0.0 * ux
        dy = r1[3] - L4 * r1[2] + 0.0 * ux
        dz = r2[3] - L4 * r2[2] - L1 + 0.0 * ux
        rxy2 = dx * dx + dy * dy
        D = np.sqrt(rxy2 + dz * dz)
        reach = (D <= L2 + L3 + REACH_TOL) & (D >= abs(L2 - L3) - REACH_TOL)
        Ds = np.where(D < 1e-12, 1.0, D)
        at_sh = D < 1e-12
        nx = np.where(at_sh, 0.0, dx / Ds)
        ny = np.where(at_sh, 0.0, dy / Ds)
        nz = np.where(at_sh, 1.0, dz / Ds)
        ca = np.clip((L2 * L2 + D * D - L3 * L3) / (2.0 * L2 * Ds), -1.0, 1.0)
        ca = np.where(at_sh, 0.0, ca)
        sa = np.sqrt(np.maximum(0.0, 1.0 - ca * ca))
        # shortest rotation k -> n applied to u
        down = (dz < 0.0) & (rxy2 <= AXIS_TOL2 * D * D)
        up = at_sh | ((dz >= 0.0) & (rxy2 <= AXIS_TOL2 * D * D))
        with np.errstate(divide="ignore", invalid="ignore"):
            h = np.where(dz >= 0.0, 1.0 + nz, rxy2 / (Ds * (Ds - dz)))
            w = -(nx * ux + ny * uy)
            rux = np.where(down | up, ux, ux + nx * w / h)
            ruy = np.where(up, uy, np.where(down, -uy, uy + ny * w / h))
            ruz = np.where(down | up, 0.0, w)
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
        fn = np.hypot(gn, fd)
        fn = np.where(fn == 0.0, 1.0, fn)
        reg = gn > DEGEN_SIN * fn
        gs = np.where(reg, gn, 1.0)
        pd = rux * zx + ruy * zy + ruz * zz
        x3x = np.where(reg, gx / gs, -(rux - pd * zx))
        x3y = np.where(reg, gy / gs, -(ruy - pd * zy))
        x3z = np.where(reg, gz / gs, -(ruz - pd * zz))
        tiny = x3x * x3x + x3y * x3y + x3z * x3z < 1e-18  # wrist at the shoulder: u along the arm
        x3x = np.where(tiny, -zz * zx, x3x)
        x3y = np.where(tiny, -zz * zy, x3y)
        x3z = np.where(tiny, 1.0 - zz * zz, x3z)
        for _ in range(2):  # normalise, orthogonalise to z3 again (g is tiny near the stretched elbow)
            k = 1.0 / np.sqrt(x3x * x3x + x3y * x3y + x3z * x3z)
            x3x, x3y, x3z = x3x * k, x3y * k, x3z * k
            pd = x3x * zx + x3y * zy + x3z * zz
            x3x, x3y, x3z = x3x - pd * zx, x3y - pd * zy, x3z - pd * zz
        k = 1.0 / np.sqrt(x3x * x3x + x3y * x3y + x3z * x3z)
        x3x, x3y, x3z = x3x * k, x3y * k, x3z * k
        y3x, y3y, y3z = zy * x3z - zz * x3y, zz * x3x - zx * x3z, zx * x3y - zy * x3x
        rz = np.sqrt(zx * zx + zy * zy)
        t2 = np.arctan2(rz, zz)
        r_ok = rz > DEGEN_SIN
        rzs = np.where(r_ok, rz, 1.0)
        c1 = np.where(r_ok, zx / rzs, 1.0)
        s1 = np.where(r_ok, zy / rzs, 0.0)
        t1 = np.where(r_ok, np.arctan2(zy, zx), 0.0)
        a11 = c1 * x3x + s1 * x3y
        a21 = -s1 * x3x + c1 * x3y
        t3 = np.arctan2(a21, zz * a11 - rz * x3z)
        c4, s4 = fd / fn, gn / fn
        x4x, x4y, x4z = c4 * x3x - s4 * zx, c4 * x3y - s4 * zy, c4 * x3z - s4 * zz
        z4x, z4y, z4z = s4 * x3x + c4 * zx, s4 * x3y + c4 * zy, s4 * x3z + c4 * zz
        ax, ay, az = r0[2], r1[2], r2[2]
        bx, by, bz = r0[0], r1[0], r2[0]
        w13 = x4x * ax + x4y * ay + x4z * az
        w23 = y3x * ax + y3y * ay + y3z * az
        w33 = z4x * ax + z4y * ay + z4z * az
        w11 = x4x * bx + x4y * by + x4z * bz
        w21 = y3x * bx + y3y * by + y3z * bz
        w31 = z4x * bx + z4y * by + z4z * bz
        rw = np.sqrt(w13 * w13 + w23 * w23)
        t6 = np.arctan2(rw, w33)
        w_ok = rw > DEGEN_SIN
        rws = np.where(w_ok, rw, 1.0)
        c5 = np.where(w_ok, w13 / rws, 1.0)
        s5 = np.where(w_ok, w23 / rws, 0.0)
        t5 = np.where(w_ok, np.arctan2(w23, w13), 0.0)
        b11 = c5 * w11 + s5 * w21
        b21 = -s5 * w11 + c5 * w21
        t7 = np.arctan2(b21, w33 * b11 - rw * w31)
        return np.stack([t1, t2, t3, t4, t5, t6, t7], axis=-1), reach

    @staticmethod
    def _flips_np(theta: np.ndarray) -> np.ndarray:
        """(m, 7) base solutions -> (m, 8, 7) flip combinations wrapped into (-pi, pi]."""
        alt = theta.copy()
        for j in (0, 2, 4, 6):
            v = theta[:, j] + PI
            alt[:, j] = np.where(v > PI, v - TWO_PI, v)
        for j in (1, 3, 5):
            alt[:, j] = -theta[:, j]
        A = np.stack([theta, alt], axis=-1)  # (m, 7, 2)
        return A[:, np.arange(7)[None, :], _ALT_INDEX]

    def _fit_np(self, Q: np.ndarray, ref: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Wrap (..., 7) angles into the limits: copy nearest ``ref`` (default 0). Returns (Q, in_limits)."""
        out = np.empty_like(Q)
        ok = np.ones(Q.shape[:-1], dtype=bool)
        for j in range(7):
            lo, up = self._lower_l[j], self._upper_l[j]
            x = Q[..., j]
            if not self._wide[j]:
                inl = (x >= lo - LIMIT_TOL) & (x <= up + LIMIT_TOL)
                out[..., j] = np.clip(x, lo, up)
                ok &= inl
                continue
            r = 0.0 if ref is None else ref[j]
            best = np.full(x.shape, np.inf)
            val = np.zeros(x.shape)
            for sft in self._shifts[j]:
                v = x + sft
                inl = (v >= lo - LIMIT_TOL) & (v <= up + LIMIT_TOL)
                d = np.where(inl, np.abs(v - r), np.inf)
                better = d < best
                val = np.where(better, v, val)
                best = np.where(better, d, best)
            out[..., j] = np.clip(val, lo, up)
            ok &= np.isfinite(best)
        return out, ok

    def ik_batch(self, Ts: np.ndarray, swivels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised closed form for m poses at m swivel angles.

        Ts: (m, 4, 4) base -> tool poses, swivels: (m,) rad (or a scalar for all).
        Returns ``(Q, valid)``: Q of shape (m, 8, 7) holding the 8 flip combinations in the same order as
        :meth:`ik` (pattern (f2, f4, f6) in binary) wrapped to the in-limit copy nearest 0, and ``valid``
        (m, 8) bool, False where the pose is out of reach or the solution violates a limit. Entries that
        are not valid hold NaN. Poses are checked for NaN/inf and shape (not for orthonormality, for speed).
        """
        Ts = np.asarray(Ts, dtype=float)
        if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
            raise InvalidInputError(f"Ts must have shape (m, 4, 4), got {Ts.shape}", field="Ts")
        m = Ts.shape[0]
        sw = np.broadcast_to(np.asarray(swivels, dtype=float), (m,))
        if not (np.all(np.isfinite(Ts)) and np.all(np.isfinite(sw))):
            raise InvalidInputError("Ts or swivels contain NaN or inf", field="Ts")
        P = [[Ts[:, i, j] for j in range(4)] for i in range(3)]
        theta, reach = self._base_np(P, np.cos(sw), np.sin(sw))
        Q, ok = self._fit_np(self._flips_np(theta))
        valid = ok & reach[:, None]
        Q[~valid] = np.nan
        return Q, valid

    # ------------------------------------------------------------------ nearest solution
    def _pose_ctx(self, Tl: list[list[float]], circ: tuple[float, ...]) -> tuple[Any, ...]:
        """Per-pose constants of a vectorised swivel sweep."""
        L1, L2, L3, L4 = self._L
        dx, dy, dz, D, rxy2, nx, ny, nz, ca = circ
        sa = math.sqrt(max(0.0, 1.0 - ca * ca))
        a0 = self._rot_qa(circ, 1.0, 0.0)
        a1 = self._rot_qa(circ, 0.0, 1.0)
        Au = np.array([[a0[0], a1[0]], [a0[1], a1[1]], [a0[2], a1[2]]])  # qA applied to (ux, uy, 0)
        zc = np.array([[ca * nx], [ca * ny], [ca * nz]])
        c4 = max(-1.0, min(1.0, (D * D - L2 * L2 - L3 * L3) / (2.0 * L2 * L3)))
        s4 = math.sqrt(max(0.0, 1.0 - c4 * c4))
        d = np.array([[dx], [dy], [dz]])
        a = np.array([Tl[0][2], Tl[1][2], Tl[2][2]])
        b = np.array([Tl[0][0], Tl[1][0], Tl[2][0]])
        return Au, sa * Au, zc, d, c4, s4, a, b

    def _singular_swivels(self, ctx: tuple[Any, ...]) -> list[float]:
        """Swivels where the elbow comes within SING_WIDTH of the base axis (sin theta2 -> 0) or the
        forearm within SING_WIDTH of the tool axis (sin theta6 -> 0).

        Both cosines are of the form c + A cos s + B sin s along the circle, so their extremes are at
        atan2(B, A) (maximum) and atan2(B, A) + pi (minimum)."""
        Au, A, zc, d, c4, s4, a, b = ctx
        L2, L3 = self._L[1], self._L[2]
        out = []
        lim = math.cos(SING_WIDTH)
        # cos theta2 = z3 . k
        c, A2, B2 = float(zc[2, 0]), float(A[2, 0]), float(A[2, 1])
        # cos theta6 = forearm . tool axis, forearm = (d - L2 z3) / L3
        c6 = (float(a @ d[:, 0]) - L2 * float(a @ zc[:, 0])) / L3
        A6, B6 = -L2 / L3 * float(a @ A[:, 0]), -L2 / L3 * float(a @ A[:, 1])
        for cc, aa, bb in ((c, A2, B2), (c6, A6, B6)):
            amp = math.hypot(aa, bb)
            if amp < 1e-12:
                continue
            sm = math.atan2(bb, aa)
            if cc + amp > lim:
                out.append(sm)
            if cc - amp < -lim:
                out.append(sm + PI)
        return out

    def _sweep(
        self, ctx: tuple[Any, ...], s: np.ndarray, seed: np.ndarray, w: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """All 8 flips at the swivels s (M,), angles at the in-limit copy nearest the seed.

        Returns (cost (M, 8), Q (M, 8, 7)); cost is inf where a solution violates a limit.
        """
        Au, A, zc, d, c4, s4, a, b = ctx
        L2 = self._L[1]
        U = np.stack([np.cos(s), np.sin(s)])
        Z = zc + A @ U  # upper-arm direction, (3, M)
        if s4 > 1e-9:
            F = d - L2 * Z
            X = F - (F * Z).sum(0) * Z
        else:  # stretched / folded elbow: the swivel picks the arm plane (as in _base_from_circle)
            Ru = Au @ U
            X = (Ru * Z).sum(0) * Z - Ru
            tiny = (X * X).sum(0) < 1e-18  # wrist at the shoulder: u along the arm
            if tiny.any():
                X = np.where(tiny, np.array([[0.0], [0.0], [1.0]]) - Z[2] * Z, X)
        X = X / np.sqrt((X * X).sum(0))
        if s4 < 1e-4:  # orthogonalise again: F - (F.Z)Z is tiny next to F near the stretched elbow
            X = X - (X * Z).sum(0) * Z
            X = X / np.sqrt((X * X).sum(0))
        z0, z1, z2 = Z
        x0, x1, x2 = X
        y0, y1, y2 = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0
        rz = np.hypot(z0, z1)
        th = np.empty((len(s), 7))
        th[:, 1] = np.arctan2(rz, z2)
        # theta1 is arbitrary (atan2 of ~0) on the base axis; theta3 from the residual keeps R3 exact
        t1 = th[:, 0] = np.arctan2(z1, z0)
        c1, s1 = np.cos(t1), np.sin(t1)
        th[:, 2] = np.arctan2(c1 * x1 - s1 * x0, z2 * (c1 * x0 + s1 * x1) - rz * x2)
        th[:, 3] = math.atan2(s4, c4)
        X4 = c4 * X - s4 * Z
        Z4 = s4 * X + c4 * Z
        w13, w33 = a @ X4, a @ Z4
        w23 = a[0] * y0 + a[1] * y1 + a[2] * y2
        w11, w31 = b @ X4, b @ Z4
        w21 = b[0] * y0 + b[1] * y1 + b[2] * y2
        rw = np.hypot(w13, w23)
        th[:, 5] = np.arctan2(rw, w33)
        t5 = th[:, 4] = np.arctan2(w23, w13)
        c5, s5 = np.cos(t5), np.sin(t5)
        th[:, 6] = np.arctan2(c5 * w21 - s5 * w11, w33 * (c5 * w11 + s5 * w21) - rw * w31)
        # per joint the two alternatives (base, flipped; unwrapped), each at the copy nearest the seed
        # and moved into the limits; the 8 flip patterns then only pick and add per-joint costs
        A2 = th[:, :, None] * _ALT_SIGN + _ALT_SHIFT  # (M, 7, 2)
        sd = seed[:, None]
        V = A2 - TWO_PI * np.round((A2 - sd) / TWO_PI)
        lo, up = self._lo2, self._up2
        V = np.where(V > up, V - TWO_PI, np.where(V < lo, V + TWO_PI, V))
        c = np.where((V >= lo - LIMIT_TOL) & (V <= up + LIMIT_TOL), (V - sd) ** 2 * w[:, None], np.inf)
        cost = c[:, _J7, _ALT_INDEX].sum(axis=-1)  # (M, 8)
        V = np.clip(V, lo, up)[:, _J7, _ALT_INDEX]
        return cost, V

    def ik_nearest(
        self,
        T: np.ndarray,
        q_seed: Sequence[float],
        *,
        weights: Sequence[float] | None = None,
        samples: int = 36,
        fine_samples: int = 720,
        refine: int = 3,
        zoom: int = 3,
        timeout_s: float | None = None,
        **_ignored: Any,
    ) -> tuple[np.ndarray | None, IKInfo]:
        """The in-limit solution of pose T nearest to ``q_seed`` over all swivel angles.

        Distance: weighted squared joint distance ``sum(w * (q - q_seed)**2)``, each joint at its in-limit
        2*pi copy nearest the seed. Search (deterministic): one vectorised sweep of all 8 flips over
        ``samples`` swivels spread over the circle plus a geometric pattern of swivels around the seed's
        own swivel (so a seed next to a solution finds it, also near singular configurations where q
        changes fast with s); a ``fine_samples`` sweep if nothing fits the limits; up to ``zoom``
        geometric zoom sweeps when the best candidate is near a shoulder/wrist singularity
        (|sin theta2| or |sin theta6| < 0.1); then up to ``refine`` steps of successive parabolic
        interpolation of the best branch's distance over s (scalar solves). ``timeout_s`` (s) stops
        the refinement early.

        Returns (q or None, :class:`IKInfo`); failure reasons: INVALID_INPUT, OUT_OF_REACH,
        NO_SOLUTION_IN_LIMITS.
        """
        t0 = time.perf_counter()
        try:
            Tl = self.check_pose(T)
            seed = self.check_q(q_seed, "q_seed")
            if weights is None:
                w = np.ones(7)
            else:
                w = np.asarray(weights, dtype=float)
                if w.shape != (7,) or not np.all(np.isfinite(w)) or np.any(w < 0):
                    raise InvalidInputError("weights must be 7 finite non-negative numbers", field="weights")
            samples = int(samples)
            if samples < 4:
                raise InvalidInputError("samples must be >= 4", field="samples", value=samples)
        except InvalidInputError as exc:
            return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
        circ = self._circle(Tl)
        if not isinstance(circ, tuple):
            return None, IKInfo(
                IKStatus.OUT_OF_REACH, f"wrist point is {circ:.6g} m outside the reachable shell"
            )
        ctx = self._pose_ctx(Tl, circ)
        s0 = self._swivel_lists(seed.tolist())
        step = TWO_PI / samples
        pattern = step * 2.0 ** -np.arange(1, 9)
        parts = [s0 + np.arange(samples) * step, s0 + pattern, s0 - pattern]
        # joint angles change fast with s where the elbow passes the base axis (theta2 -> 0) or the
        # forearm lines up with the tool axis (theta6 -> 0): look closely around those swivels too
        spat = SING_WIDTH * 2.0 ** -np.arange(0, 7)
        for sc in self._singular_swivels(ctx):
            parts += [np.array([sc]), sc + spat, sc - spat]
        s = np.concatenate(parts)
        cost, Q = self._sweep(ctx, s, seed, w)
        cands = cost.size
        if not np.isfinite(cost).any():
            s = s0 + np.arange(int(fine_samples)) * (TWO_PI / int(fine_samples))
            cost, Q = self._sweep(ctx, s, seed, w)
            cands += cost.size
            step = TWO_PI / int(fine_samples)
        if not np.isfinite(cost).any():
            return None, IKInfo(
                IKStatus.NO_SOLUTION_IN_LIMITS,
                f"reachable, but no swivel ({cands} candidates) gives a solution within the joint limits",
                candidates=cands,
            )
        i, b = divmod(int(np.argmin(cost)), 8)
        s_b, c_b, q_b = float(s[i]), float(cost[i, b]), Q[i, b]
        # near a shoulder/wrist ZYZ singularity (sin theta2 or sin theta6 small) q changes fast with s:
        # zoom with geometric patterns around the best swivel before the parabolic refinement
        h = step
        iters = 0
        zooms = 0
        while zooms < zoom and (abs(math.sin(q_b[1])) < ZOOM_SIN or abs(math.sin(q_b[5])) < ZOOM_SIN):
            if timeout_s is not None and time.perf_counter() - t0 > timeout_s:
                break
            zooms += 1
            pat = h * 2.0 ** -np.arange(0, 12)
            s = s_b + np.concatenate([[0.0], pat, -pat])
            cost, Q = self._sweep(ctx, s, seed, w)
            cands += cost.size
            i = int(np.argmin(cost[:, b]))
            if cost[i, b] <= c_b:
                s_b, c_b, q_b = float(s[i]), float(cost[i, b]), Q[i, b]
            h = max(abs(s_b - float(s[0])), h * 2.0**-11)
        # bracketed 1-D refinement of branch b's distance over s (scalar solves): parabolic steps
        # when both bracket ends are feasible, else bisection towards an infeasible end (the optimum
        # often sits at a joint limit)
        cb = cost[:, b]
        ds = np.remainder(s - s_b + PI, TWO_PI) - PI  # signed angular distance to the best sample
        left = np.where(ds < -1e-15, ds, -np.inf)
        right = np.where(ds > 1e-15, ds, np.inf)
        il, ir = int(np.argmax(left)), int(np.argmin(right))
        sa, fa = (s_b + float(ds[il]), float(cb[il])) if math.isfinite(left[il]) else (s_b - step, math.inf)
        sc, fc = (s_b + float(ds[ir]), float(cb[ir])) if math.isfinite(right[ir]) else (s_b + step, math.inf)
        seed_l = seed.tolist()
        while iters < refine and sc - sa > 1e-9:
            if timeout_s is not None and time.perf_counter() - t0 > timeout_s:
                break
            sv = math.nan
            if math.isfinite(fa) and math.isfinite(fc):
                den = (s_b - sa) * (c_b - fc) - (s_b - sc) * (c_b - fa)
                if den != 0.0:
                    sv = s_b - 0.5 * ((s_b - sa) ** 2 * (c_b - fc) - (s_b - sc) ** 2 * (c_b - fa)) / den
            if not (sa < sv < sc) or abs(sv - s_b) < 1e-10:
                left = (s_b - sa) * (2.0 if not math.isfinite(fa) else 1.0)
                right = (sc - s_b) * (2.0 if not math.isfinite(fc) else 1.0)
                sv = 0.5 * (sa + s_b) if left > right else 0.5 * (s_b + sc)
            iters += 1
            r = self._branch_eval(Tl, circ, sv, b, seed_l, w)
            cands += 1
            fv = r[1] if r is not None else math.inf
            if fv < c_b:
                if sv < s_b:
                    sc, fc = s_b, c_b
                else:
                    sa, fa = s_b, c_b
                gain = c_b - fv
                s_b, c_b, q_b = sv, fv, r[0]  # type: ignore[index]
                if gain < 1e-12 * (1.0 + c_b) and math.isfinite(fa) and math.isfinite(fc):
                    break
            elif sv < s_b:
                sa, fa = sv, fv
            else:
                sc, fc = sv, fv
        iters += zooms
        q = np.array(q_b, dtype=float)
        pe, re = self._pose_err_lists(q.tolist(), Tl)
        s_fin = math.atan2(math.sin(s_b), math.cos(s_b))
        return q, IKInfo(
            IKStatus.SUCCESS, "ok", swivel=s_fin, pos_err=pe, rot_err=re, iterations=iters, candidates=cands
        )

    def _pose_err_lists(self, q: list[float], Tl: list[list[float]]) -> tuple[float, float]:
        """(position error m, rotation error rad) of fk(q) against the nested-list pose Tl."""
        R, p = self._fk_lists(q)
        pe = math.sqrt(sum((p[i] - Tl[i][3]) ** 2 for i in range(3)))
        # residual rotation Rd R^T: angle = atan2(|skew|/2, (trace - 1)/2)
        M = [[sum(Tl[i][k] * R[j][k] for k in range(3)) for j in range(3)] for i in range(3)]
        vx, vy, vz = M[2][1] - M[1][2], M[0][2] - M[2][0], M[1][0] - M[0][1]
        re = math.atan2(
            0.5 * math.sqrt(vx * vx + vy * vy + vz * vz), 0.5 * (M[0][0] + M[1][1] + M[2][2] - 1.0)
        )
        return pe, abs(re)

    def _branch_eval(
        self,
        Tl: list[list[float]],
        circ: tuple[float, ...],
        s: float,
        branch: int,
        seed: list[float],
        w: np.ndarray,
    ) -> tuple[np.ndarray, float] | None:
        """Flip pattern ``branch`` at swivel s (scalar solve), each angle at its in-limit copy nearest the
        seed (same rule as :meth:`_sweep`). Returns (q, weighted squared distance to the seed) or None
        if a limit is violated."""
        base = self._base_from_circle(Tl, circ, math.cos(s), math.sin(s))
        sg = _ALT_SIGN_L[branch]
        sh = _ALT_SHIFT_L[branch]
        q = []
        cost = 0.0
        wl = w.tolist()
        for j, (t, r, lo, up, wj) in enumerate(
            zip(base, seed, self._lower_l, self._upper_l, wl, strict=True)
        ):
            v = t * sg[j] + sh[j]
            v -= TWO_PI * round((v - r) / TWO_PI)
            if v > up:
                v -= TWO_PI
            elif v < lo:
                v += TWO_PI
            if v < lo - LIMIT_TOL or v > up + LIMIT_TOL:
                return None
            v = min(max(v, lo), up)
            q.append(v)
            cost += wj * (v - r) ** 2
        return np.array(q), cost
