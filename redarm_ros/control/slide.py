"""Sliding along what the hand cannot pass: the workspace shells and obstacle surfaces.

Both remove, smoothly, the part of a motion that would press into a boundary, so that the hand
slides along it instead of stopping for good in an IK dead end or at the collision guard:

* :func:`workspace_slide`: within ``margin`` of the inner shell of the wrist workspace (elbow at its
  joint limit) or of the outer shell (arm stretched), the inward/outward component;
* :func:`obstacle_slide`: within ``band`` of an obstacle or the table, the component towards it
  (fully at contact).

``direction`` variants keep a unit direction (the attractor moves at its own speed along it);
``project=True`` keeps the vector's length reduced by what was removed (the servo follows as closely
as possible). Units: m.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from redarm_ros.control.elbow import ArmGeometry, ElbowCircle
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, links_clearance
from redarm_ros.kinematics.quaternion import quat_rotate


def smoothstep(x: float) -> float:
    """0 for x <= 0, 1 for x >= 1, C1 in between."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    return x * x * (3.0 - 2.0 * x)


def wrist_shell(lower4: float, upper4: float, upper: float, fore: float) -> tuple[float, float]:
    """Smallest and largest shoulder-wrist distance (m) allowed by the elbow joint's limits
    (``lower4``, ``upper4`` rad; link lengths ``upper``, ``fore`` m)."""
    bend = max(abs(lower4), abs(upper4))
    straight = 0.0 if lower4 <= 0.0 <= upper4 else min(abs(lower4), abs(upper4))
    d_in = math.sqrt(max(upper * upper + fore * fore + 2.0 * upper * fore * math.cos(min(bend, math.pi)),
                         0.0))
    d_out = math.sqrt(max(upper * upper + fore * fore + 2.0 * upper * fore * math.cos(straight), 0.0))
    return d_in, d_out


def _remove(e: Sequence[float], g: Sequence[float], f: float, project: bool) -> Vec3 | None:
    v = (e[0] - f * g[0], e[1] - f * g[1], e[2] - f * g[2])
    if project:
        return v
    n = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    if n < 1e-6:
        return None
    return (v[0] / n, v[1] / n, v[2] / n)


def workspace_slide(e: Vec3, pos: Vec3, rot: Quat, geom: ArmGeometry, d_inner: float, d_outer: float,
                    margin: float, project: bool = False) -> Vec3:
    """Remove the part of motion ``e`` that would take the wrist through a workspace shell."""
    off = quat_rotate(rot, geom.wrist_in_tool)
    ps = geom.shoulder
    r = (pos[0] + off[0] - ps[0], pos[1] + off[1] - ps[1], pos[2] + off[2] - ps[2])
    d = math.sqrt(r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
    if d < 1e-9:
        return e
    r = (r[0] / d, r[1] / d, r[2] / d)
    radial = e[0] * r[0] + e[1] * r[1] + e[2] * r[2]
    w = 0.0
    if radial < 0.0:
        w = smoothstep((d_inner + margin - d) / margin)
    elif radial > 0.0:
        w = smoothstep((d - (d_outer - margin)) / margin)
    if w <= 0.0:
        return e
    out = _remove(e, r, w * radial, project)
    return e if out is None else out


def obstacle_slide(e: Vec3, circle: ElbowCircle | None, s: float, scene: Scene, capsules: ArmCapsules,
                   band: float, project: bool = False) -> Vec3:
    """Remove the part of motion ``e`` that takes the hand (arm at ``circle``/swivel ``s``) closer
    to an obstacle or the table within ``band``."""
    if circle is None:
        return e
    kp = [tuple(float(c) for c in v) for v in circle.key_points(s)]
    c0 = links_clearance(kp, scene, capsules, (3,)).distance
    if c0 >= band:
        return e
    h = 1e-3
    g = []
    for axis in range(3):
        shifted = [list(v) for v in kp]
        shifted[3][axis] += h
        shifted[4][axis] += h
        g.append((links_clearance(shifted, scene, capsules, (3,)).distance - c0) / h)
    gn = math.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2)
    if gn < 1e-6:
        return e
    g = [gi / gn for gi in g]
    toward = e[0] * g[0] + e[1] * g[1] + e[2] * g[2]
    if toward >= 0.0:
        return e
    w = smoothstep((band - c0) / band)
    out = _remove(e, g, w * toward, project)
    return e if out is None else out
