"""Arm models: a serial chain of revolute joints (FK, Jacobian, validation); no configuration here.

A model is the chain ``frame_i = frame_{i-1} @ origin_i @ Rot(axis_i, q_i)`` (frame_0 = base), with
the tool fixed to the last joint frame: ``fk(q) = frame_n @ tool``. This is URDF's joint semantics, so
the same data drives the simulator. Units: metres, radians, rad/s, rad/s^2. Quaternions, where they
appear, are (w, x, y, z).

:class:`Arm` holds everything that works for any chain (FK, frames, key points, geometric Jacobian,
input validation, numeric IK as the fallback for ``ik_nearest``). :mod:`.swivel` adds the closed-form
swivel IK of 7-DOF spherical-shoulder/wrist arms, :mod:`.powercube6` the analytic IK of the 6-DOF
PowerCube arm. :mod:`.loader` builds models from ``config/arms/*.yaml`` (``load_arm``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.kinematics.numeric import solve_dls
from redarm_ros.kinematics.protocols import SwivelKinematics
from redarm_ros.kinematics.quaternion import matrix_to_quat, rotation_error
from redarm_ros.kinematics.result import IKInfo, IKStatus

_log = logging.getLogger(__name__)

__all__ = [
    "Joint",
    "Arm",
    "rot_axis",
    "pose_error",
    "transform_from_xyz_rpy",
    "check_finite_array",
    "check_scalar",
    "ORTHO_TOL",
    "LIMIT_TOL",
    "POSITION_RANGE",
    "ANGLE_RANGE",
]

ORTHO_TOL = 1e-6  # how far R^T R may be from I before a pose is rejected
LIMIT_TOL = 1e-10  # rad; solutions this close outside a limit are clipped onto it
POSITION_RANGE = 1e6  # m; a coordinate beyond this is refused as out of range (not a real target)
ANGLE_RANGE = 1e6  # rad; a joint angle, swivel or seed beyond this is refused (2*pi copies lose meaning)


def _describe_bad(a: np.ndarray) -> str:
    """What is wrong with a float array that failed the finite check: NaN or inf, and where."""
    bad = np.argwhere(~np.isfinite(a))
    idx = tuple(int(v) for v in bad[0]) if len(bad) else ()
    v = float(a[idx]) if len(bad) else math.nan
    where = f" at index {idx[0] if len(idx) == 1 else idx}" if idx else ""
    return f"{'NaN' if math.isnan(v) else 'inf'}{where}"


def check_finite_array(
    x: Any, field: str, shape: tuple[int | None, ...] | None = None, limit: float | None = None
) -> np.ndarray:
    """``x`` as a float ndarray, or :class:`InvalidInputError` saying what is wrong with it.

    ``shape``: required shape (None entries match any length). ``limit``: largest accepted absolute
    value (a finite value beyond it is "out of range", not "NaN or inf"). Complex, ragged and
    non-numeric input is refused with the reason.
    """
    if isinstance(x, np.ndarray) and x.dtype.kind == "f":
        a = x if x.dtype == np.float64 else x.astype(float)
    else:
        try:
            a0 = np.asarray(x)
        except (TypeError, ValueError) as exc:  # nested sequences of different lengths
            raise InvalidInputError(f"{field} is ragged: {exc}", field=field, value=x) from exc
        if a0.dtype.kind == "c":
            raise InvalidInputError(f"{field} must be real, got complex values", field=field, value=x)
        try:
            a = a0.astype(float)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"{field} is not numeric: {exc}", field=field, value=x) from exc
    if shape is not None and (
        a.ndim != len(shape)
        or any(want is not None and got != want for got, want in zip(a.shape, shape, strict=True))
    ):
        want_s = (
            "(" + ", ".join("m" if v is None else str(v) for v in shape) + ("," if len(shape) == 1 else "")
        )
        raise InvalidInputError(f"{field} must have shape {want_s}), got {a.shape}", field=field, value=x)
    if not np.isfinite(a).all():
        raise InvalidInputError(f"{field} contains {_describe_bad(a)}", field=field, value=x)
    if limit is not None and a.size and float(np.max(np.abs(a))) > limit:
        big = float(np.max(np.abs(a)))
        raise InvalidInputError(
            f"{field} is out of range: |value| {big:.3g} > {limit:.3g}", field=field, value=x
        )
    return a


def check_scalar(x: Any, field: str, limit: float | None = None) -> float:
    """``x`` as a finite real float (bools refused), or :class:`InvalidInputError` with the reason."""
    if isinstance(x, bool) or isinstance(x, complex) or np.iscomplexobj(x):
        raise InvalidInputError(f"{field} must be a real number, got {x!r}", field=field, value=x)
    try:
        v = float(x)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{field} must be a number, got {x!r}", field=field, value=x) from exc
    if math.isnan(v):
        raise InvalidInputError(f"{field} is NaN", field=field, value=x)
    if math.isinf(v):
        raise InvalidInputError(f"{field} is {v} (must be finite)", field=field, value=x)
    if limit is not None and abs(v) > limit:
        raise InvalidInputError(
            f"{field} = {v:.6g} is out of range (|{field}| <= {limit:g})", field=field, value=x
        )
    return v


@dataclass(frozen=True)
class Joint:
    """One revolute joint.

    ``origin``: 4x4 fixed transform parent joint frame -> this joint frame at q = 0 (m).
    ``axis``: (3,) unit rotation axis in this joint frame. Limits in rad, rad/s, rad/s^2.
    """

    name: str
    origin: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    max_vel: float
    max_acc: float


def rot_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (rad) about the unit vector ``axis`` (Rodrigues)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    C = 1.0 - c
    return np.array(
        [
            [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
            [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
            [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
        ]
    )


def _rot_axis_batch(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(m,3,3) rotations about one unit axis by m angles."""
    x, y, z = axis
    c, s = np.cos(angles), np.sin(angles)
    C = 1.0 - c
    R = np.empty(angles.shape + (3, 3))
    R[..., 0, 0] = c + x * x * C
    R[..., 0, 1] = x * y * C - z * s
    R[..., 0, 2] = x * z * C + y * s
    R[..., 1, 0] = y * x * C + z * s
    R[..., 1, 1] = c + y * y * C
    R[..., 1, 2] = y * z * C - x * s
    R[..., 2, 0] = z * x * C - y * s
    R[..., 2, 1] = z * y * C + x * s
    R[..., 2, 2] = c + z * z * C
    return R


def _mul3(R: Sequence[Sequence[float]], A: Sequence[Sequence[float]]) -> list[list[float]]:
    """R @ A for 3x3 nested lists, written out (the scalar FK of a URDF chain does one per joint: 3x
    faster than sum() over generators)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = A
    return [
        [r0 * a00 + r1 * a10 + r2 * a20, r0 * a01 + r1 * a11 + r2 * a21, r0 * a02 + r1 * a12 + r2 * a22]
        for r0, r1, r2 in R
    ]


def pose_error(T_actual: np.ndarray, T_desired: np.ndarray) -> tuple[float, float]:
    """(position error in m, orientation error in rad) between two 4x4 poses."""
    dp = float(np.linalg.norm(np.asarray(T_actual)[:3, 3] - np.asarray(T_desired)[:3, 3]))
    dr = float(np.linalg.norm(rotation_error(np.asarray(T_actual)[:3, :3], np.asarray(T_desired)[:3, :3])))
    return dp, dr


def transform_from_xyz_rpy(xyz: Sequence[float], rpy: Sequence[float]) -> np.ndarray:
    """4x4 transform: translation xyz (m), then fixed-axis roll/pitch/yaw (rad), URDF convention."""
    r, p, y = rpy
    R = rot_axis(np.array([0.0, 0.0, 1.0]), y) @ rot_axis(np.array([0.0, 1.0, 0.0]), p)
    R = R @ rot_axis(np.array([1.0, 0.0, 0.0]), r)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = xyz
    return T


class Arm:
    """A serial revolute chain with limits; the shared base of every arm model.

    Attributes: ``name``, ``n`` (joint count), ``joint_names``, ``lower``/``upper`` (rad, (n,)),
    ``max_vel`` (rad/s), ``max_acc`` (rad/s^2), ``chain`` (list of :class:`Joint`), ``tool`` (4x4
    last joint frame -> tool), ``kind`` (YAML kind), ``config`` (the YAML dict after overrides).
    """

    kind = "chain"

    def __init__(
        self,
        name: str,
        chain: Sequence[Joint],
        tool: np.ndarray,
        key_joints: Sequence[int],
        config: dict[str, Any] | None = None,
    ) -> None:
        self.name = name
        self.chain = list(chain)
        self.n = len(self.chain)
        self.tool = np.asarray(tool, dtype=float)
        self.joint_names = [j.name for j in self.chain]
        self.lower = np.array([j.lower for j in self.chain])
        self.upper = np.array([j.upper for j in self.chain])
        self.max_vel = np.array([j.max_vel for j in self.chain])
        self.max_acc = np.array([j.max_acc for j in self.chain])
        self.key_joints = tuple(int(i) for i in key_joints)
        self.config = dict(config or {})
        if len(self.key_joints) != 3 or not all(0 <= i < self.n for i in self.key_joints):
            raise ConfigError(f"{name}: key_joints must be 3 joint indices in 0..{self.n - 1}")
        self._lower_l = self.lower.tolist()
        self._upper_l = self.upper.tolist()
        # scalar FK tables: per joint (origin R as rows or None if identity, origin p or None, axis code)
        self._fast: list[tuple[Any, Any, int, tuple[float, float, float]]] = []
        for j in self.chain:
            R = j.origin[:3, :3]
            p = j.origin[:3, 3]
            Rl = None if np.allclose(R, np.eye(3), atol=0, rtol=0) else R.tolist()
            pl = None if not np.any(p) else p.tolist()
            a = j.axis
            code = -1
            for k in range(3):
                if a[k] == 1.0 and np.count_nonzero(a) == 1:
                    code = k
            self._fast.append((Rl, pl, code, tuple(float(v) for v in a)))
        self._tool_R = None if np.array_equal(self.tool[:3, :3], np.eye(3)) else self.tool[:3, :3].tolist()
        self._tool_p = self.tool[:3, 3].tolist()
        # The tool's (R rows, p) at the joints (as bytes) of the last key_points call: the controller asks
        # for the key points and then the pose of each command it commits (one FK pass for both).
        self._last_fk: tuple[bytes, list[list[float]], list[float]] | None = None
        self._setup_model()

    def _setup_model(self) -> None:
        """Per-model constants, after the chain is set up: the analytic models override this (one
        constructor signature for every model, the loader's)."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r} n={self.n} kind={self.kind}>"

    @property
    def park(self) -> np.ndarray | None:
        """The park posture (rad, (n,), inside the limits) from the YAML ``park:``, or None if none."""
        v = self.config.get("park")
        return None if v is None else np.array(v, dtype=float)

    # ------------------------------------------------------------------ validation
    def check_q(self, q: Any, field: str = "q") -> np.ndarray:
        """q as a float (n,) array (rad).

        Raises :class:`InvalidInputError` saying what is wrong: not numeric / complex / ragged, wrong
        length, NaN, inf, or a value beyond ``ANGLE_RANGE`` (out of range).
        """
        if isinstance(q, np.ndarray) and q.dtype == np.float64 and q.shape == (self.n,):
            lst = q.tolist()
            if all(-ANGLE_RANGE <= v <= ANGLE_RANGE for v in lst):  # False for NaN too
                return q
        try:
            return check_finite_array(q, field, (self.n,), ANGLE_RANGE)
        except InvalidInputError as exc:
            if exc.args[0].startswith(f"{field} must have shape"):
                raise InvalidInputError(
                    f"{exc.args[0]} (arm {self.name!r} has {self.n} joints)", field=field, value=q
                ) from None
            raise

    @staticmethod
    def check_pose(T: Any, field: str = "T") -> list[list[float]]:
        """Validate a 4x4 homogeneous transform (m) and return it as nested lists.

        Raises :class:`InvalidInputError` for a non-numeric / complex / ragged value, a wrong shape,
        NaN or inf, a position beyond ``POSITION_RANGE`` (out of range), a bottom row other than
        (0, 0, 0, 1), or a rotation part that is not orthonormal with det +1 (tolerance 1e-6).
        """
        if isinstance(T, np.ndarray) and T.shape == (4, 4) and T.dtype == np.float64:
            Tl = T.tolist()
        else:
            Tl = check_finite_array(T, field, (4, 4)).tolist()
        r0, r1, r2, r3 = Tl
        lim = POSITION_RANGE
        if not (
            -lim <= r0[3] <= lim
            and -lim <= r1[3] <= lim
            and -lim <= r2[3] <= lim
            # (written out, not all() over a generator: 1 us of ik's 20-30 on the 2-core test machine)
            and -2.0 <= r0[0] <= 2.0
            and -2.0 <= r0[1] <= 2.0
            and -2.0 <= r0[2] <= 2.0
            and -2.0 <= r1[0] <= 2.0
            and -2.0 <= r1[1] <= 2.0
            and -2.0 <= r1[2] <= 2.0
            and -2.0 <= r2[0] <= 2.0
            and -2.0 <= r2[1] <= 2.0
            and -2.0 <= r2[2] <= 2.0
        ):  # NaN fails every comparison: the slow path says exactly what is wrong
            a = check_finite_array(Tl, field, (4, 4))
            pos = np.abs(a[:3, 3])
            if float(pos.max()) > lim:
                raise InvalidInputError(
                    f"{field} position {a[:3, 3].tolist()} is out of range (|coordinate| <= {lim:g} m)",
                    field=field,
                    value=T,
                )
        if abs(r3[0]) > 1e-9 or abs(r3[1]) > 1e-9 or abs(r3[2]) > 1e-9 or abs(r3[3] - 1.0) > 1e-9:
            raise InvalidInputError(
                f"{field} bottom row must be (0, 0, 0, 1), got {r3}", field=field, value=T
            )
        a0, a1, a2 = r0[0], r1[0], r2[0]
        b0, b1, b2 = r0[1], r1[1], r2[1]
        c0, c1, c2 = r0[2], r1[2], r2[2]
        err = max(
            abs(a0 * a0 + a1 * a1 + a2 * a2 - 1.0),
            abs(b0 * b0 + b1 * b1 + b2 * b2 - 1.0),
            abs(c0 * c0 + c1 * c1 + c2 * c2 - 1.0),
            abs(a0 * b0 + a1 * b1 + a2 * b2),
            abs(a0 * c0 + a1 * c1 + a2 * c2),
            abs(b0 * c0 + b1 * c1 + b2 * c2),
        )
        det = c0 * (a1 * b2 - a2 * b1) + c1 * (a2 * b0 - a0 * b2) + c2 * (a0 * b1 - a1 * b0)
        if not (err <= ORTHO_TOL and det > 0.0):
            raise InvalidInputError(
                f"{field} rotation part is not orthonormal with det +1 "
                f"(max |R^T R - I| = {err:.3g}, det {det:.3g})",
                field=field,
                value=T,
            )
        return Tl

    @staticmethod
    def check_poses(Ts: Any, field: str = "Ts") -> np.ndarray:
        """Validate m 4x4 homogeneous transforms at once; returns them as a float (m, 4, 4) array.

        Same rules as :meth:`check_pose`, vectorised. Raises :class:`InvalidInputError` naming the first
        offending row and the reason; ``value`` holds the indices of every offending row.
        """
        a = check_finite_array(Ts, field, (None, 4, 4))
        if len(a) == 0:
            return a
        p = a[:, :3, 3]
        pos_bad = np.abs(p).max(axis=1) > POSITION_RANGE
        bottom_bad = np.abs(a[:, 3, :] - (0.0, 0.0, 0.0, 1.0)).max(axis=1) > 1e-9
        # columns c0, c1, c2 of R: unit length, mutually orthogonal, c0 x c1 . c2 > 0 (as check_pose)
        c = [[a[:, i, j] for i in range(3)] for j in range(3)]
        err = np.zeros(len(a))
        for j, k in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
            d = c[j][0] * c[k][0] + c[j][1] * c[k][1] + c[j][2] * c[k][2]
            err = np.maximum(err, np.abs(d - 1.0) if j == k else np.abs(d))
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = c
        det = c0 * (a1 * b2 - a2 * b1) + c1 * (a2 * b0 - a0 * b2) + c2 * (a0 * b1 - a1 * b0)
        rot_bad = ~((err <= ORTHO_TOL) & (det > 0.0))
        for bad, why in (
            (pos_bad, f"position out of range (|coordinate| <= {POSITION_RANGE:g} m)"),
            (bottom_bad, "bottom row is not (0, 0, 0, 1)"),
            (rot_bad, "rotation part is not orthonormal with det +1 (tolerance 1e-6)"),
        ):
            if bad.any():
                rows = np.nonzero(bad)[0]
                i = int(rows[0])
                extra = f" (and {len(rows) - 1} more rows)" if len(rows) > 1 else ""
                detail = ""
                if why.startswith("rotation"):
                    detail = f": max |R^T R - I| = {err[i]:.3g}, det {det[i]:.3g}"
                raise InvalidInputError(
                    f"{field}[{i}]: {why}{detail}{extra}", field=field, value=rows.tolist()
                )
        return a

    def nearest_copies(self, Q: Any, ref: Any) -> np.ndarray:
        """Each joint angle of Q ((n,) or (k, n), rad) moved to its in-limit 2*pi copy nearest ``ref`` (n,).

        Q's angles must have an in-limit copy (solutions from ``ik``); ``ref`` may lie outside the limits.
        A joint with a range below 2*pi has one copy; PA10 joints 5 and 7 have two or three.
        """
        Qa = check_finite_array(Q, "Q", None, ANGLE_RANGE)
        r = check_finite_array(ref, "ref", (self.n,), ANGLE_RANGE)
        lot = self.lower - LIMIT_TOL
        width = self.upper - self.lower + 2.0 * LIMIT_TOL
        X = Qa - lot
        Xm = X - 2.0 * math.pi * np.floor(X / (2.0 * math.pi))
        kmax = np.maximum(np.floor((width - Xm) / (2.0 * math.pi)), 0.0)
        V0 = Xm + lot
        k = np.clip(np.rint((r - V0) / (2.0 * math.pi)), 0.0, kmax)
        return np.clip(V0 + 2.0 * math.pi * k, self.lower, self.upper)

    def within_limits(self, q: np.ndarray, tol: float = LIMIT_TOL) -> bool:
        """True if every joint of q lies in [lower - tol, upper + tol]."""
        q = np.asarray(q, dtype=float)
        return bool(np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))

    # ------------------------------------------------------------------ forward kinematics
    def _fk_lists(
        self, q: Sequence[float], record: list[tuple[list[float], list[float]]] | None = None
    ) -> tuple[list[list[float]], list[float]]:
        """Scalar FK: (R rows, p) of the tool. q: sequence of n floats (not validated).

        If ``record`` is a list, (joint origin, joint axis) in the base frame are appended per joint.
        """
        R = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        p = [0.0, 0.0, 0.0]
        cos, sin = math.cos, math.sin
        for (Ro, po, code, ax), qi in zip(self._fast, q, strict=True):
            if po is not None:
                p = [p[i] + R[i][0] * po[0] + R[i][1] * po[1] + R[i][2] * po[2] for i in range(3)]
            if Ro is not None:
                R = _mul3(R, Ro)
            if record is not None:
                if code >= 0:
                    z = [R[0][code], R[1][code], R[2][code]]
                else:
                    z = [R[i][0] * ax[0] + R[i][1] * ax[1] + R[i][2] * ax[2] for i in range(3)]
                record.append((p, z))
            c, s = cos(qi), sin(qi)
            if code == 2:
                R = [[r[0] * c + r[1] * s, r[1] * c - r[0] * s, r[2]] for r in R]
            elif code == 1:
                R = [[r[0] * c - r[2] * s, r[1], r[0] * s + r[2] * c] for r in R]
            elif code == 0:
                R = [[r[0], r[1] * c + r[2] * s, r[2] * c - r[1] * s] for r in R]
            else:  # R @ rot_axis(ax, qi), Rodrigues written out
                x, y, z = ax
                C = 1.0 - c
                a00, a01, a02 = c + x * x * C, x * y * C - z * s, x * z * C + y * s
                a10, a11, a12 = y * x * C + z * s, c + y * y * C, y * z * C - x * s
                a20, a21, a22 = z * x * C - y * s, z * y * C + x * s, c + z * z * C
                R = _mul3(R, ((a00, a01, a02), (a10, a11, a12), (a20, a21, a22)))
        tp = self._tool_p
        p = [p[i] + R[i][0] * tp[0] + R[i][1] * tp[1] + R[i][2] * tp[2] for i in range(3)]
        if self._tool_R is not None:
            R = _mul3(R, self._tool_R)
        return R, p

    def fk(self, q: Sequence[float]) -> np.ndarray:
        """Base -> tool 4x4 transform for joint angles q (rad, shape (n,))."""
        qa = self.check_q(q)
        last = self._last_fk
        if last is not None and last[0] == qa.tobytes():
            R, p = last[1], last[2]
        else:
            R, p = self._fk_lists(qa.tolist())
        return np.array([R[0] + [p[0]], R[1] + [p[1]], R[2] + [p[2]], [0.0, 0.0, 0.0, 1.0]])

    def fk_pq(self, q: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """Tool position (3,) in m and orientation as a unit quaternion in (w, x, y, z) order (w >= 0)."""
        T = self.fk(q)
        return T[:3, 3].copy(), matrix_to_quat(T[:3, :3])

    def fk_frames(self, q: Sequence[float]) -> np.ndarray:
        """(n+1, 4, 4): base -> each joint frame (after its rotation); the last entry is the tool."""
        qa = self.check_q(q)
        out = np.empty((self.n + 1, 4, 4))
        T = np.eye(4)
        for i, (j, qi) in enumerate(zip(self.chain, qa, strict=True)):
            T = T @ j.origin
            T[:3, :3] = T[:3, :3] @ rot_axis(j.axis, float(qi))
            out[i] = T
        out[self.n] = T @ self.tool
        return out

    def fk_batch(self, Q: np.ndarray) -> np.ndarray:
        """Vectorised FK: Q (m, n) rad -> (m, 4, 4) base -> tool transforms."""
        Q = np.asarray(Q, dtype=float)
        if Q.ndim != 2 or Q.shape[1] != self.n:
            raise InvalidInputError(f"Q must have shape (m, {self.n})", field="Q", value=Q.shape)
        if not np.all(np.isfinite(Q)):
            raise InvalidInputError("Q contains NaN or inf", field="Q")
        m = Q.shape[0]
        T = np.broadcast_to(np.eye(4), (m, 4, 4)).copy()
        for i, j in enumerate(self.chain):
            T = T @ j.origin
            T[:, :3, :3] = T[:, :3, :3] @ _rot_axis_batch(j.axis, Q[:, i])
        return T @ self.tool

    def key_points(self, q: Sequence[float]) -> np.ndarray:
        """(5, 3) positions (m): base, shoulder, elbow, wrist, tool (for capsule collision models).

        Shoulder/elbow/wrist are the origins of the joint frames named by the YAML ``key_joints``.
        """
        # The scalar FK with its per-joint record (the controller asks every step; the 4x4 matrix
        # chain of fk_frames costs several times more).
        joints: list[tuple[list[float], list[float]]] = []
        qa = self.check_q(q)
        R, tool = self._fk_lists(qa.tolist(), joints)
        self._last_fk = (qa.tobytes(), R, tool)
        pts = np.empty((5, 3))
        pts[0] = 0.0
        for k, i in enumerate(self.key_joints):
            pts[k + 1] = joints[i][0]
        pts[4] = tool
        return pts

    def fk_jacobian(self, q: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R (3, 3), p (3,), J (6, n)) of the tool at q (rad): FK and the geometric Jacobian in one pass.

        J's rows are [linear velocity; angular velocity] in the base frame (the scalar FK path, cheap
        enough for the inner loop of the numeric solvers).
        """
        qa = self.check_q(q)
        rec: list[tuple[list[float], list[float]]] = []
        R, p = self._fk_lists(qa.tolist(), rec)
        Og = np.array([r[0] for r in rec])
        Z = np.array([r[1] for r in rec])
        pa = np.array(p)
        J = np.empty((6, self.n))
        J[:3] = np.cross(Z, pa - Og).T
        J[3:] = Z.T
        return np.array(R), pa, J

    def fk_axes(self, q: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(p (3,), O (n, 3), Z (n, 3)): tool position, and each joint's origin and unit axis, base frame."""
        qa = self.check_q(q)
        rec: list[tuple[list[float], list[float]]] = []
        _, p = self._fk_lists(qa.tolist(), rec)
        return np.array(p), np.array([r[0] for r in rec]), np.array([r[1] for r in rec])

    def jacobian(self, q: Sequence[float]) -> np.ndarray:
        """(6, n) geometric Jacobian in the base frame: rows [linear velocity; angular velocity]."""
        return self.fk_jacobian(q)[2]

    # ------------------------------------------------------------------ inverse kinematics (generic)
    @property
    def has_swivel(self) -> bool:
        """True if the model has the closed-form swivel IK (the same test as
        :func:`redarm_ros.kinematics.protocols.has_swivel`)."""
        return isinstance(self, SwivelKinematics)

    def swivel(self, q: Sequence[float]) -> float:
        """Swivel angle (rad). Arms without an elbow circle have no self-motion parameter: always 0.0."""
        self.check_q(q)
        return 0.0

    def ik_nearest(
        self,
        T: np.ndarray,
        q_seed: Sequence[float],
        *,
        timeout_s: float | None = 5e-3,
        tol: float = 1e-5,
        max_iter: int = 1000,
        rng_seed: int = 0,
    ) -> tuple[np.ndarray | None, IKInfo]:
        """Generic fallback: damped least squares from the seed (:func:`numeric.solve_dls`).

        ``timeout_s`` (s, None = no limit) bounds the search; when it runs out the status is TIMEOUT.
        Unknown keyword arguments raise ``TypeError``.
        """
        try:
            self.check_pose(T)
            seed = self.check_q(q_seed, "q_seed")
        except InvalidInputError as exc:
            return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
        return self._solve_numeric(np.asarray(T, dtype=float), seed, tol=tol, max_iter=max_iter,
                                   timeout_s=timeout_s, rng_seed=rng_seed)

    def _solve_numeric(
        self, T: np.ndarray, seed: np.ndarray, **options: Any
    ) -> tuple[np.ndarray | None, IKInfo]:
        """The numeric search behind :meth:`ik_nearest` (inputs checked): damped least squares from
        the seed."""
        return solve_dls(self, T, seed, **options)

    def pose_error(self, q: Sequence[float], T: np.ndarray) -> tuple[float, float]:
        """(position error m, orientation error rad) of fk(q) against T."""
        return pose_error(self.fk(q), T)
