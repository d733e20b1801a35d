"""The elbow circle of a spherical-shoulder/spherical-wrist arm, evaluated without IK.

For a tool pose T the elbow lies on a circle (swivel paper eq. 13-16): ``n = unit(pW - pS)``,
``qA`` the shortest rotation taking ``k`` onto ``n``, ``u = Qz(s) i Qz(s)*`` and
``pE = C + rho qA u qA*``. Writing ``a = qA i qA*`` and ``b = qA j qA*`` gives
``pE(s) = C + rho (cos s a + sin s b)`` and, in the swivel-quaternion form with ``u = (ux, uy, 0)``,
``pE(u) = C + rho (ux a + uy b)`` (no trigonometry). All five key points (base, shoulder, elbow, wrist,
tool) then follow from T and s alone, which is what the swivel dynamics needs to probe the distance
to obstacles at ``s +/- eps`` cheaply.

Units: metres, radians. Quaternions are not stored: ``a`` and ``b`` are the first two columns of the
rotation matrix of ``qA``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.geometry.obstacles import ELBOW_LINKS, ArmCapsules, Clearance, Scene, links_clearance
from redarm_ros.kinematics.protocols import ControlledArm
from redarm_ros.kinematics.quaternion import shortest_rotation_basis

Vec3 = tuple[float, float, float]

# Below this |pW - pS| (m) the circle axis is undefined (wrist at the shoulder).
_MIN_REACH = 1e-9


@dataclass(frozen=True)
class ArmGeometry:
    """Rigid facts of a swivel arm read once from its model (m).

    ``base`` and ``shoulder`` positions, ``upper`` = |elbow - shoulder|, ``fore`` = |wrist - elbow|,
    ``wrist_in_tool``: wrist centre expressed in the tool frame (constant for a spherical wrist).
    """

    base: Vec3
    shoulder: Vec3
    upper: float
    fore: float
    wrist_in_tool: Vec3

    @classmethod
    def from_arm(cls, arm: ControlledArm) -> ArmGeometry:
        """Read the geometry from ``arm.key_points`` and ``arm.fk`` at a mid-range configuration."""
        lower = np.asarray(arm.lower, float)
        upper = np.asarray(arm.upper, float)
        # Any configuration works; use one away from singularities.
        q = np.clip(np.full(arm.n, 0.3), lower, upper)
        kp = np.asarray(arm.key_points(q), float)
        T = np.asarray(arm.fk(q), float)
        w_tool = T[:3, :3].T @ (kp[3] - T[:3, 3])
        return cls(
            base=tuple(float(v) for v in kp[0]),
            shoulder=tuple(float(v) for v in kp[1]),
            upper=float(np.linalg.norm(kp[2] - kp[1])),
            fore=float(np.linalg.norm(kp[3] - kp[2])),
            wrist_in_tool=tuple(float(v) for v in w_tool),
        )

    def wrist(self, T: np.ndarray) -> Vec3:
        """Wrist centre (m) for tool pose ``T`` (4x4, base frame)."""
        return self.wrist_of_rows(np.asarray(T, dtype=float).tolist())

    def wrist_of_rows(self, rows: list[list[float]]) -> Vec3:
        """:meth:`wrist` of a pose given as its rows of plain floats (``T.tolist()``): the same
        arithmetic without numpy's cost per element (the elbow circle is computed several times a step)."""
        w = self.wrist_in_tool
        r0, r1, r2 = rows[0], rows[1], rows[2]
        return (
            r0[3] + r0[0] * w[0] + r0[1] * w[1] + r0[2] * w[2],
            r1[3] + r1[0] * w[0] + r1[1] * w[1] + r1[2] * w[2],
            r2[3] + r2[0] * w[0] + r2[1] * w[1] + r2[2] * w[2],
        )

    @property
    def reach(self) -> float:
        """Largest shoulder-wrist distance (m)."""
        return self.upper + self.fore

    @property
    def min_reach(self) -> float:
        """Smallest shoulder-wrist distance (m)."""
        return abs(self.upper - self.fore)


@dataclass(frozen=True)
class ElbowCircle:
    """Elbow circle for one tool pose: ``center`` C, unit ``normal`` n, radius ``rho`` (m), and the
    in-plane basis ``a = qA i qA*``, ``b = qA j qA*``; plus the fixed key points of that pose."""

    center: Vec3
    normal: Vec3
    rho: float
    a: Vec3
    b: Vec3
    base: Vec3
    shoulder: Vec3
    wrist: Vec3
    tool: Vec3

    def elbow(self, s: float) -> Vec3:
        """Elbow position (m) at swivel angle ``s`` (rad)."""
        return self.elbow_u(math.cos(s), math.sin(s))

    def elbow_u(self, ux: float, uy: float) -> Vec3:
        """Elbow position (m) for the swivel quaternion ``u = ux i + uy j`` (unit, xy plane)."""
        c, a, b, r = self.center, self.a, self.b, self.rho
        return (c[0] + r * (ux * a[0] + uy * b[0]),
                c[1] + r * (ux * a[1] + uy * b[1]),
                c[2] + r * (ux * a[2] + uy * b[2]))

    def key_points(self, s: float) -> list[Vec3]:
        """Base, shoulder, elbow, wrist, tool (m) at swivel ``s`` (rad)."""
        return [self.base, self.shoulder, self.elbow(s), self.wrist, self.tool]

    def key_points_u(self, ux: float, uy: float) -> list[Vec3]:
        """Base, shoulder, elbow, wrist, tool (m) for the swivel quaternion ``(ux, uy)``."""
        return [self.base, self.shoulder, self.elbow_u(ux, uy), self.wrist, self.tool]

    def swivel_u(self, elbow: Any) -> tuple[float, float]:
        """Swivel quaternion ``(ux, uy)`` of an elbow position on (or near) the circle (eq. 16)."""
        c, a, b = self.center, self.a, self.b
        d = (elbow[0] - c[0], elbow[1] - c[1], elbow[2] - c[2])
        ux = d[0] * a[0] + d[1] * a[1] + d[2] * a[2]
        uy = d[0] * b[0] + d[1] * b[1] + d[2] * b[2]
        norm = math.hypot(ux, uy)
        if norm < 1e-15:
            return 1.0, 0.0
        return ux / norm, uy / norm

    def swivel(self, elbow: Any) -> float:
        """Swivel angle (rad, in (-pi, pi]) of an elbow position (eq. 16)."""
        ux, uy = self.swivel_u(elbow)
        return math.atan2(uy, ux)

    def elbow_height_slope(self, s: float) -> float:
        """d(elbow z)/ds (m/rad) at swivel ``s``: positive means increasing s raises the elbow."""
        return self.rho * (-math.sin(s) * self.a[2] + math.cos(s) * self.b[2])


def elbow_circle(geom: ArmGeometry, T: Any) -> ElbowCircle:
    """Elbow circle of tool pose ``T`` (4x4 homogeneous, base frame, m).

    Raises:
        InvalidInputError: T is not a finite 4x4 array.
        UnreachableError: the wrist is farther than ``upper + fore`` or closer than
            ``|upper - fore|`` to the shoulder (``distance``: how far outside, m).
    """
    T = np.asarray(T, dtype=float)
    rows = T.tolist() if T.shape == (4, 4) else None
    if rows is None or not all(map(math.isfinite, rows[0] + rows[1] + rows[2] + rows[3])):
        raise InvalidInputError("T must be a finite 4x4 homogeneous transform", field="T")
    pw = geom.wrist_of_rows(rows)
    ps = geom.shoulder
    dx, dy, dz = pw[0] - ps[0], pw[1] - ps[1], pw[2] - ps[2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    l2, l3 = geom.upper, geom.fore
    if dist > l2 + l3:
        raise UnreachableError(f"wrist {dist:.4f} m from the shoulder, reach is {l2 + l3:.4f} m",
                               distance=dist - (l2 + l3))
    if dist < abs(l2 - l3) or dist < _MIN_REACH:
        raise UnreachableError(f"wrist {dist:.4f} m from the shoulder, closer than {abs(l2 - l3):.4f} m",
                               distance=abs(l2 - l3) - dist)
    n = (dx / dist, dy / dist, dz / dist)
    along = (l2 * l2 - l3 * l3 + dist * dist) / (2.0 * dist)
    rho = math.sqrt(max(l2 * l2 - along * along, 0.0))
    center = (ps[0] + along * n[0], ps[1] + along * n[1], ps[2] + along * n[2])
    a, b = shortest_rotation_basis(n)
    tool = (rows[0][3], rows[1][3], rows[2][3])
    return ElbowCircle(center, n, rho, a, b, geom.base, ps, pw, tool)


# ----------------------------------------------------------------------------------------------
# Clearance along the circle
# ----------------------------------------------------------------------------------------------


def clearance_at_swivel(circle: ElbowCircle, s: float, scene: Scene, capsules: ArmCapsules | None = None,
                        links: Iterable[int] = (0, 1, 2, 3)) -> Clearance:
    """Clearance (m) of the arm with the tool pose of ``circle`` and swivel angle ``s`` (rad).

    No IK is needed: the key points follow from the elbow circle (see above).
    """
    return links_clearance(circle.key_points(s), scene, capsules or ArmCapsules(), links)


def clearance_at_u(circle: ElbowCircle, ux: float, uy: float, scene: Scene,
                   capsules: ArmCapsules | None = None, links: Iterable[int] = (0, 1, 2, 3)) -> Clearance:
    """As :func:`clearance_at_swivel` for the swivel quaternion ``u = ux i + uy j`` (unit)."""
    return links_clearance(circle.key_points_u(ux, uy), scene, capsules or ArmCapsules(), links)


def swivel_gradient(circle: ElbowCircle, s: float, scene: Scene, capsules: ArmCapsules | None = None,
                    eps: float = 1e-3) -> tuple[float, float]:
    """Clearance of the swivel-dependent links (upper arm, forearm) and its derivative w.r.t. ``s``.

    Returns ``(d, dd_ds)`` in m and m/rad, by the central difference over ``s +/- eps`` (rad) that the
    swivel paper uses to find the direction of the obstacle force.
    """
    caps = capsules or ArmCapsules()
    d0 = clearance_at_swivel(circle, s, scene, caps, ELBOW_LINKS).distance
    dp = clearance_at_swivel(circle, s + eps, scene, caps, ELBOW_LINKS).distance
    dm = clearance_at_swivel(circle, s - eps, scene, caps, ELBOW_LINKS).distance
    if not math.isfinite(d0):
        return d0, 0.0
    return d0, (dp - dm) / (2.0 * eps)
