"""Arm models: a serial chain of revolute joints loaded from ``config/arms/*.yaml``.

A model is the chain ``frame_i = frame_{i-1} @ origin_i @ Rot(axis_i, q_i)`` (frame_0 = base), with
the tool fixed to the last joint frame: ``fk(q) = frame_n @ tool``. This is URDF's joint semantics, so
the same data drives the simulator. Units: metres, radians, rad/s, rad/s^2. Quaternions, where they
appear, are (w, x, y, z).

:class:`Arm` holds everything that works for any chain (FK, frames, key points, geometric Jacobian,
input validation, numeric IK as the fallback for ``ik_nearest``). :mod:`.swivel` adds the closed-form
swivel IK of 7-DOF spherical-shoulder/wrist arms, :mod:`.powercube6` the analytic IK of the 6-DOF
PowerCube arm. :func:`load_arm` picks the class from the YAML ``kind``.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.kinematics.quaternion import matrix_to_quat, rotation_error
from redarm_ros.kinematics.result import IKInfo, IKStatus

_log = logging.getLogger(__name__)

__all__ = ["Joint", "Arm", "load_arm", "arm_config_dirs", "available_arms", "rot_axis", "pose_error"]

ORTHO_TOL = 1e-6  # how far R^T R may be from I before a pose is rejected
LIMIT_TOL = 1e-10  # rad; solutions this close outside a limit are clipped onto it


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
    has_swivel = False  # True for arms with the closed-form swivel IK (self-motion on an elbow circle)

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

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r} n={self.n} kind={self.kind}>"

    # ------------------------------------------------------------------ validation
    def check_q(self, q: Any, field: str = "q") -> np.ndarray:
        """q as a float (n,) array; raises :class:`InvalidInputError` on wrong length or NaN/inf."""
        try:
            a = np.asarray(q, dtype=float)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"{field} is not numeric: {q!r}", field=field, value=q) from exc
        if a.shape != (self.n,):
            raise InvalidInputError(
                f"{field} must have shape ({self.n},) for arm {self.name!r}, got {a.shape}",
                field=field,
                value=q,
            )
        if not np.all(np.isfinite(a)):
            raise InvalidInputError(f"{field} contains NaN or inf: {a}", field=field, value=q)
        return a

    @staticmethod
    def check_pose(T: Any, field: str = "T") -> list[list[float]]:
        """Validate a 4x4 homogeneous transform and return it as nested lists.

        Raises :class:`InvalidInputError` for a wrong shape, NaN/inf, a bottom row other than
        (0, 0, 0, 1), or a rotation part that is not orthonormal with det +1 (tolerance 1e-6).
        """
        if isinstance(T, np.ndarray) and T.shape == (4, 4):
            Tl = T.tolist()
        else:
            try:
                a = np.asarray(T, dtype=float)
            except (TypeError, ValueError) as exc:
                raise InvalidInputError(f"{field} is not a numeric 4x4 matrix", field=field, value=T) from exc
            if a.shape != (4, 4):
                raise InvalidInputError(
                    f"{field} must be a 4x4 matrix, got shape {a.shape}", field=field, value=T
                )
            Tl = a.tolist()
        r0, r1, r2, r3 = Tl
        try:
            total = math.fsum(r0) + math.fsum(r1) + math.fsum(r2) + math.fsum(r3)
        except (TypeError, OverflowError, ValueError) as exc:
            raise InvalidInputError(f"{field} contains NaN or inf", field=field, value=T) from exc
        if not math.isfinite(total) or not all(math.isfinite(v) for row in Tl for v in row):
            raise InvalidInputError(f"{field} contains NaN or inf", field=field, value=T)
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
        if err > ORTHO_TOL or det < 0.0:
            raise InvalidInputError(
                f"{field} rotation part is not orthonormal with det +1 "
                f"(max |R^T R - I| = {err:.3g}, det {det:.3g})",
                field=field,
                value=T,
            )
        return Tl

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
                R = [[sum(R[i][k] * Ro[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
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
            else:
                Rq = rot_axis(np.array(ax), qi).tolist()
                R = [[sum(R[i][k] * Rq[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        tp = self._tool_p
        p = [p[i] + R[i][0] * tp[0] + R[i][1] * tp[1] + R[i][2] * tp[2] for i in range(3)]
        if self._tool_R is not None:
            Rt = self._tool_R
            R = [[sum(R[i][k] * Rt[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
        return R, p

    def fk(self, q: Sequence[float]) -> np.ndarray:
        """Base -> tool 4x4 transform for joint angles q (rad, shape (n,))."""
        qa = self.check_q(q)
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
        F = self.fk_frames(q)
        pts = np.empty((5, 3))
        pts[0] = 0.0
        for k, i in enumerate(self.key_joints):
            pts[k + 1] = F[i, :3, 3]
        pts[4] = F[self.n, :3, 3]
        return pts

    def jacobian(self, q: Sequence[float]) -> np.ndarray:
        """(6, n) geometric Jacobian in the base frame: rows [linear velocity; angular velocity]."""
        F = self.fk_frames(q)
        p = F[self.n, :3, 3]
        J = np.empty((6, self.n))
        for i, j in enumerate(self.chain):
            z = F[i, :3, :3] @ j.axis
            J[:3, i] = np.cross(z, p - F[i, :3, 3])
            J[3:, i] = z
        return J

    # ------------------------------------------------------------------ inverse kinematics (generic)
    def ik(self, T: np.ndarray, swivel: float | None = None) -> np.ndarray:
        """Closed-form IK is not available for a generic chain; use :meth:`ik_nearest` or numeric.py."""
        raise NotImplementedError(f"arm {self.name!r} (kind {self.kind}) has no closed-form IK")

    def ik_u(self, T: np.ndarray, u: Sequence[float]) -> np.ndarray:
        """Swivel-quaternion IK; only swivel arms have it."""
        raise NotImplementedError(f"arm {self.name!r} (kind {self.kind}) has no swivel parameterisation")

    def ik_batch(self, Ts: np.ndarray, swivels: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised closed form; not available for a generic chain."""
        raise NotImplementedError(f"arm {self.name!r} (kind {self.kind}) has no closed-form IK")

    def swivel(self, q: Sequence[float]) -> float:
        """Swivel angle (rad). Arms without an elbow circle have no self-motion parameter: always 0.0."""
        self.check_q(q)
        return 0.0

    def elbow_circle(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Elbow circle (C, n, rho); only swivel arms have one."""
        raise NotImplementedError(f"arm {self.name!r} (kind {self.kind}) has no elbow circle")

    def ik_nearest(
        self, T: np.ndarray, q_seed: Sequence[float], **opts: Any
    ) -> tuple[np.ndarray | None, IKInfo]:
        """Generic fallback: damped least squares from the seed (see :func:`numeric.solve_dls`)."""
        from redarm_ros.kinematics.numeric import solve_dls

        try:
            self.check_pose(T)
            seed = self.check_q(q_seed, "q_seed")
        except InvalidInputError as exc:
            return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
        return solve_dls(self, np.asarray(T, dtype=float), seed, **opts)

    def pose_error(self, q: Sequence[float], T: np.ndarray) -> tuple[float, float]:
        """(position error m, orientation error rad) of fk(q) against T."""
        return pose_error(self.fk(q), T)


# ---------------------------------------------------------------------- loading
def arm_config_dirs() -> list[Path]:
    """Directories searched for ``<name>.yaml``, in order.

    ``$REDARM_ARMS_DIR`` (os.pathsep separated), the source tree's ``config/arms``, the installed
    ``share/redarm_ros/config/arms`` under ``sys.prefix``, and the ament index share directory if
    ``ament_index_python`` is importable.
    """
    dirs: list[Path] = []
    env = os.environ.get("REDARM_ARMS_DIR")
    if env:
        dirs.extend(Path(p) for p in env.split(os.pathsep) if p)
    dirs.append(Path(__file__).resolve().parents[2] / "config" / "arms")
    dirs.append(Path(sys.prefix) / "share" / "redarm_ros" / "config" / "arms")
    try:  # ROS install without rclpy: ament_index_python is plain Python
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("redarm_ros")) / "config" / "arms")
    except Exception:  # noqa: BLE001 - not installed the ament way; the other dirs still apply
        pass
    return dirs


def available_arms() -> list[str]:
    """Names of the arm YAML files found in :func:`arm_config_dirs`."""
    names: set[str] = set()
    for d in arm_config_dirs():
        if d.is_dir():
            names.update(p.stem for p in d.glob("*.yaml"))
    return sorted(names)


def _find_config(name: str | os.PathLike[str]) -> Path:
    p = Path(name)
    if p.suffix in (".yaml", ".yml") or os.sep in str(name):
        if p.is_file():
            return p
        raise ConfigError(f"arm config file {str(p)!r} does not exist", field="name", value=str(name))
    for d in arm_config_dirs():
        cand = d / f"{name}.yaml"
        if cand.is_file():
            return cand
    raise ConfigError(
        f"unknown arm {str(name)!r}; known arms: {', '.join(available_arms()) or '(none)'}",
        field="name",
        value=str(name),
    )


_OVERRIDE_KEYS = {
    "link_lengths",
    "lower",
    "upper",
    "max_vel",
    "max_acc",
    "joint_names",
    "name",
    "roll_fractions",
}


def load_arm(name: str | os.PathLike[str] = "pa10", **overrides: Any) -> Arm:
    """Load an arm model by name (``config/arms/<name>.yaml``) or from a YAML path.

    Keyword overrides replace YAML values: ``link_lengths`` (m), ``lower``/``upper`` (rad, (n,)),
    ``max_vel`` (rad/s), ``max_acc`` (rad/s^2), ``joint_names``, ``name``, ``roll_fractions``
    (powercube6). Raises :class:`ConfigError` for an unknown name, a broken file or a bad override.
    """
    path = _find_config(name)
    try:
        with open(path, encoding="utf-8") as fh:
            cfg = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(
            f"cannot read arm config {str(path)!r}: {exc}", field="name", value=str(name)
        ) from exc
    if not isinstance(cfg, dict):
        raise ConfigError(f"arm config {str(path)!r} is not a mapping", field="name", value=str(name))
    unknown = set(overrides) - _OVERRIDE_KEYS
    if unknown:
        raise ConfigError(
            f"unknown override(s) {sorted(unknown)}; allowed: {sorted(_OVERRIDE_KEYS)}",
            field=sorted(unknown)[0],
        )
    cfg = dict(cfg)
    cfg["_path"] = str(path)
    return build_arm(cfg, **overrides)


def _joint_specs(cfg: dict[str, Any], overrides: dict[str, Any]) -> list[dict[str, Any]]:
    name = cfg.get("name", "?")
    joints = cfg.get("joints")
    if not isinstance(joints, list) or not joints:
        raise ConfigError(f"arm {name!r}: 'joints' must be a non-empty list", field="joints")
    n = len(joints)
    specs = []
    for i, jc in enumerate(joints):
        if not isinstance(jc, dict):
            raise ConfigError(f"arm {name!r}: joint {i} must be a mapping", field="joints")
        try:
            if "limits_deg" in jc:
                lo, up = (math.radians(float(v)) for v in jc["limits_deg"])
            else:
                lo, up = (float(v) for v in jc["limits"])
            spec = {
                "name": str(jc.get("name", f"{name}_joint_{i + 1}")),
                "lower": lo,
                "upper": up,
                "max_vel": float(jc["max_vel"]),
                "max_acc": float(jc["max_acc"]),
                "axis": jc.get("axis"),
                "origin": jc.get("origin"),
            }
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(
                f"arm {name!r}: joint {i} is incomplete or malformed ({exc!r})", field="joints"
            ) from exc
        specs.append(spec)
    for key in ("lower", "upper", "max_vel", "max_acc"):
        if key in overrides:
            vals = np.asarray(overrides[key], dtype=float)
            if vals.shape != (n,) or not np.all(np.isfinite(vals)):
                raise ConfigError(
                    f"override {key} must be {n} finite numbers", field=key, value=overrides[key]
                )
            for s, v in zip(specs, vals, strict=True):
                s[key] = float(v)
    if "joint_names" in overrides:
        names = list(overrides["joint_names"])
        if len(names) != n:
            raise ConfigError(f"override joint_names must have {n} entries", field="joint_names")
        for s, v in zip(specs, names, strict=True):
            s["name"] = str(v)
    for i, s in enumerate(specs):
        if not (s["lower"] <= s["upper"]):
            raise ConfigError(
                f"arm {name!r}: joint {i} has lower > upper", field="limits", value=(s["lower"], s["upper"])
            )
        if not (s["max_vel"] > 0 and s["max_acc"] > 0):
            raise ConfigError(f"arm {name!r}: joint {i} needs positive max_vel and max_acc", field="max_vel")
    return specs


def _axis(spec: Any, where: str) -> np.ndarray:
    table = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    if isinstance(spec, str) and spec in table:
        return np.array(table[spec])
    try:
        a = np.asarray(spec, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: axis {spec!r} is not x/y/z or a 3-vector", field="axis") from exc
    if a.shape != (3,) or not np.isfinite(a).all() or np.linalg.norm(a) < 1e-9:
        raise ConfigError(f"{where}: axis {spec!r} is not x/y/z or a non-zero 3-vector", field="axis")
    return a / np.linalg.norm(a)


def _origin(spec: Any, where: str) -> np.ndarray:
    if spec is None:
        return np.eye(4)
    try:
        xyz = [float(v) for v in spec.get("xyz", (0, 0, 0))]
        rpy = [float(v) for v in spec.get("rpy", (0, 0, 0))]
        if len(xyz) != 3 or len(rpy) != 3:
            raise ValueError("xyz and rpy need 3 values")
    except (AttributeError, TypeError, ValueError) as exc:
        raise ConfigError(
            f"{where}: origin must be {{xyz: [..], rpy: [..]}} ({exc})", field="origin"
        ) from exc
    return transform_from_xyz_rpy(xyz, rpy)


def _link_lengths(cfg: dict[str, Any], overrides: dict[str, Any], count: int) -> list[float]:
    raw = overrides.get("link_lengths", cfg.get("link_lengths"))
    try:
        L = [float(v) for v in raw]
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"link_lengths must be {count} numbers, got {raw!r}", field="link_lengths") from exc
    if len(L) != count or not all(math.isfinite(v) and v > 0 for v in L):
        raise ConfigError(
            f"link_lengths must be {count} positive numbers (m), got {raw!r}", field="link_lengths", value=raw
        )
    return L


def build_arm(cfg: dict[str, Any], **overrides: Any) -> Arm:
    """Build an :class:`Arm` (or subclass) from a config mapping (the parsed YAML) plus overrides."""
    from redarm_ros.kinematics.powercube6 import PowerCube6Arm
    from redarm_ros.kinematics.swivel import SwivelArm

    kind = cfg.get("kind", "chain")
    name = str(overrides.get("name", cfg.get("name", "arm")))
    cfg = dict(cfg)
    cfg["name"] = name
    specs = _joint_specs(cfg, overrides)
    T = np.eye(4)

    def mk(s: dict[str, Any], origin: np.ndarray, axis: np.ndarray) -> Joint:
        return Joint(s["name"], origin, axis, s["lower"], s["upper"], s["max_vel"], s["max_acc"])

    if kind == "swivel7":
        if len(specs) != 7:
            raise ConfigError(f"arm {name!r}: kind swivel7 needs exactly 7 joints", field="joints")
        L1, L2, L3, L4 = _link_lengths(cfg, overrides, 4)
        cfg["link_lengths"] = [L1, L2, L3, L4]
        offsets = [0.0, L1, 0.0, L2, 0.0, L3, 0.0]
        axes = "zyzyzyz"
        chain = []
        for i, s in enumerate(specs):
            if s["axis"] is not None and _axis(s["axis"], name).tolist() != _axis(axes[i], name).tolist():
                raise ConfigError(f"arm {name!r}: swivel7 joint {i + 1} axis must be {axes[i]}", field="axis")
            o = np.eye(4)
            o[2, 3] = offsets[i]
            chain.append(mk(s, o, _axis(axes[i], name)))
        T[2, 3] = L4
        return SwivelArm(name, chain, T, (1, 3, 5), cfg)
    if kind == "powercube6":
        if len(specs) != 6:
            raise ConfigError(f"arm {name!r}: kind powercube6 needs exactly 6 joints", field="joints")
        L1, L23, L4, L56 = _link_lengths(cfg, overrides, 4)
        cfg["link_lengths"] = [L1, L23, L4, L56]
        f3, f6 = (float(v) for v in overrides.get("roll_fractions", cfg.get("roll_fractions", (0.5, 0.5))))
        if not (0.0 <= f3 <= 1.0 and 0.0 <= f6 <= 1.0):
            raise ConfigError("roll_fractions must lie in [0, 1]", field="roll_fractions")
        cfg["roll_fractions"] = [f3, f6]
        # standard DH of the paper's Tab. 1 (a = L1, L23, L4, L56; alpha1 = 90 deg) with the two roll
        # joints inserted on the link axes (x of the DH frames) where they do not change eq. (2)-(4)
        o2 = transform_from_xyz_rpy((L1, 0.0, 0.0), (math.pi / 2, 0.0, 0.0))
        o3 = transform_from_xyz_rpy((f3 * L23, 0.0, 0.0), (0.0, 0.0, 0.0))
        o4 = transform_from_xyz_rpy(((1.0 - f3) * L23, 0.0, 0.0), (0.0, 0.0, 0.0))
        o5 = transform_from_xyz_rpy((L4, 0.0, 0.0), (0.0, 0.0, 0.0))
        o6 = transform_from_xyz_rpy((f6 * L56, 0.0, 0.0), (0.0, 0.0, 0.0))
        origins = [np.eye(4), o2, o3, o4, o5, o6]
        axes6 = "zzxzzx"
        chain = [mk(s, origins[i], _axis(axes6[i], name)) for i, s in enumerate(specs)]
        T[0, 3] = (1.0 - f6) * L56
        return PowerCube6Arm(name, chain, T, (1, 3, 4), cfg)
    if kind == "chain":
        chain = []
        for i, s in enumerate(specs):
            if s["axis"] is None:
                raise ConfigError(f"arm {name!r}: joint {i} needs an axis", field="axis")
            chain.append(
                mk(s, _origin(s["origin"], f"{name} joint {i}"), _axis(s["axis"], f"{name} joint {i}"))
            )
        tool = _origin(cfg.get("tool"), f"{name} tool")
        n = len(chain)
        key = cfg.get("key_joints", [min(1, n - 1), min(n // 2, n - 1), max(n - 2, 0)])
        return Arm(name, chain, tool, key, cfg)
    raise ConfigError(
        f"arm {name!r}: unknown kind {kind!r} (swivel7, powercube6, chain)", field="kind", value=kind
    )
