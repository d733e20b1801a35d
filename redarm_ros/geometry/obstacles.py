"""Obstacles, table-top scenes, the capsule model of the arm and minimum distances.

Units are metres and radians; every position is in the arm base frame (REP-103, z up).

Shapes (their ``center`` is the geometric centre, the same convention as RViz markers):

* :class:`Sphere` -- ``center``, ``radius``.
* :class:`Cylinder` -- vertical (axis parallel to z): ``center``, ``radius``, ``height``.
* :class:`Box` -- ``center``, full edge lengths ``size`` (x, y, z) in its own frame, ``yaw`` about z.

A :class:`Scene` is a list of shapes plus an optional table top at ``z = table_height``. The arm is
modelled as one capsule per link between consecutive key points (base, shoulder, elbow, wrist, tool);
see :class:`ArmCapsules`. Distances are signed: positive is free space between the capsule surface and
the obstacle, negative means the capsule penetrates the obstacle (by that depth, for spheres exactly;
for boxes and cylinders the most negative signed distance of the link axis minus the radius).

Performance: the per-pair distance code is scalar ``math`` on tuples because a controller step needs
a few dozen segment/shape distances and numpy's per-call overhead would dominate at that size.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.arm import KeyPointArm
from redarm_ros.param_table import declared

Vec3 = tuple[float, float, float]

#: ``Clearance.obstacle`` value that designates the table top.
TABLE = -1

# Number of golden-section iterations used only when a link axis passes through a box or a
# cylinder (to get a negative, informative penetration depth); 0.618**40 ~ 4e-9.
_GOLDEN_ITERS = 40
_INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0


def _vec3(value: Any, field_name: str) -> Vec3:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{field_name} must be 3 numbers, got {value!r}", field=field_name,
                                value=value) from exc
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{field_name} must be 3 finite numbers, got {value!r}", field=field_name,
                                value=value)
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _positive(value: Any, field_name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{field_name} must be a number, got {value!r}", field=field_name,
                                value=value) from exc
    if not math.isfinite(v) or v <= 0.0:
        raise InvalidInputError(f"{field_name} must be finite and > 0, got {value!r}", field=field_name,
                                value=value)
    return v


# ----------------------------------------------------------------------------------------------
# Shapes
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Footprint:
    """How a shape's footprint (its projection on the xy plane) is seen from a point (top view).

    direction: azimuth (rad) of the middle of the footprint's angular extent; half_angle: half of that
    extent (rad; pi/2 when the point is over the footprint); near / far: smallest and largest
    horizontal distance (m) from the point to the footprint.
    """

    direction: float
    half_angle: float
    near: float
    far: float


def _circle_footprint(cx: float, cy: float, r: float, x: float, y: float) -> Footprint:
    dx, dy = cx - x, cy - y
    d = math.hypot(dx, dy)
    direction = math.atan2(dy, dx) if d > 1e-12 else 0.0
    if d <= r:
        return Footprint(direction, 0.5 * math.pi, 0.0, d + r)
    return Footprint(direction, math.asin(r / d), d - r, d + r)


class _Round:
    """A shape that is a circle seen from above (a sphere, a vertical cylinder): its checked
    ``center`` and ``radius`` and its top view."""

    center: Vec3
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        object.__setattr__(self, "radius", _positive(self.radius, "radius"))

    @property
    def footprint_radius(self) -> float:
        """Radius (m) of a vertical circle around ``center`` that covers the shape seen from above."""
        return self.radius

    def footprint(self, x: float, y: float) -> Footprint:
        """Top view of the shape from (x, y) (m)."""
        return _circle_footprint(self.center[0], self.center[1], self.radius, x, y)


@dataclass(frozen=True)
class Sphere(_Round):
    """Sphere: ``center`` (m, base frame), ``radius`` (m)."""

    center: Vec3
    radius: float
    name: str = ""

    @property
    def top(self) -> float:
        """Highest z of the shape (m)."""
        return self.center[2] + self.radius

    def signed_distance(self, p: Sequence[float]) -> float:
        """Signed distance (m) from point ``p`` to the surface (negative inside)."""
        c = self.center
        return math.sqrt((p[0] - c[0]) ** 2 + (p[1] - c[1]) ** 2 + (p[2] - c[2]) ** 2) - self.radius

    def segment_distance(self, a: Sequence[float], b: Sequence[float]) -> float:
        """Signed distance (m) from segment ``a``-``b`` to the sphere (exact)."""
        return _point_segment_distance(self.center, a, b) - self.radius

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict form (the YAML schema)."""
        return {"type": "sphere", "center": list(self.center), "radius": self.radius, "name": self.name}


@dataclass(frozen=True)
class Cylinder(_Round):
    """Vertical cylinder (axis parallel to z): ``center`` at mid-height, ``radius``, ``height`` (m)."""

    center: Vec3
    radius: float
    height: float
    name: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "height", _positive(self.height, "height"))

    @property
    def top(self) -> float:
        """Highest z of the shape (m)."""
        return self.center[2] + 0.5 * self.height

    def signed_distance(self, p: Sequence[float]) -> float:
        """Signed distance (m) from point ``p`` to the surface (negative inside)."""
        c = self.center
        return _sd_cyl(p[0] - c[0], p[1] - c[1], p[2] - c[2], self.radius, 0.5 * self.height)

    def segment_distance(self, a: Sequence[float], b: Sequence[float]) -> float:
        """Signed distance (m) from segment ``a``-``b`` to the cylinder (exact to ~1e-9 m)."""
        c = self.center
        ax, ay, az = a[0] - c[0], a[1] - c[1], a[2] - c[2]
        bx, by, bz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        return _segment_cylinder(ax, ay, az, bx, by, bz, self.radius, 0.5 * self.height)

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict form (the YAML schema)."""
        return {"type": "cylinder", "center": list(self.center), "radius": self.radius,
                "height": self.height, "name": self.name}


@dataclass(frozen=True)
class Box:
    """Box: ``center`` (m), full edge lengths ``size`` (m) along its own axes, ``yaw`` (rad) about z."""

    center: Vec3
    size: Vec3
    yaw: float = 0.0
    name: str = ""
    _cs: tuple[float, float] = field(default=(1.0, 0.0), repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "center"))
        size = _vec3(self.size, "size")
        for i, v in enumerate(size):
            _positive(v, f"size[{i}]")
        object.__setattr__(self, "size", size)
        yaw = float(self.yaw)
        if not math.isfinite(yaw):
            raise InvalidInputError(f"yaw must be finite, got {self.yaw!r}", field="yaw", value=self.yaw)
        object.__setattr__(self, "yaw", yaw)
        object.__setattr__(self, "_cs", (math.cos(yaw), math.sin(yaw)))

    @property
    def half(self) -> Vec3:
        """Half edge lengths (m)."""
        return (0.5 * self.size[0], 0.5 * self.size[1], 0.5 * self.size[2])

    @property
    def top(self) -> float:
        """Highest z of the shape (m)."""
        return self.center[2] + 0.5 * self.size[2]

    @property
    def footprint_radius(self) -> float:
        """Radius (m) of a vertical circle around ``center`` that covers the shape seen from above."""
        return 0.5 * math.hypot(self.size[0], self.size[1])

    def _local(self, p: Sequence[float]) -> Vec3:
        c, s = self._cs
        dx, dy = p[0] - self.center[0], p[1] - self.center[1]
        return (c * dx + s * dy, -s * dx + c * dy, p[2] - self.center[2])

    def footprint(self, x: float, y: float) -> Footprint:
        """Top view of the shape from (x, y) (m): the exact rectangle, not a covering circle."""
        lx, ly, _ = self._local((x, y, 0.0))
        hx, hy = 0.5 * self.size[0], 0.5 * self.size[1]
        ex, ey = max(abs(lx) - hx, 0.0), max(abs(ly) - hy, 0.0)
        near = math.hypot(ex, ey)
        c, s = self._cs
        dx, dy = self.center[0] - x, self.center[1] - y
        d = math.hypot(dx, dy)
        direction = math.atan2(dy, dx) if d > 1e-12 else 0.0
        far = 0.0
        lo = hi = 0.0
        for sx, sy in ((hx, hy), (hx, -hy), (-hx, hy), (-hx, -hy)):
            cx = dx + c * sx - s * sy  # corner relative to the point
            cy = dy + s * sx + c * sy
            far = max(far, math.hypot(cx, cy))
            a = math.atan2(cy, cx) - direction
            a = (a + math.pi) % (2.0 * math.pi) - math.pi
            lo, hi = min(lo, a), max(hi, a)
        if near == 0.0:
            return Footprint(direction, 0.5 * math.pi, 0.0, far)
        mid = direction + 0.5 * (lo + hi)
        return Footprint(math.atan2(math.sin(mid), math.cos(mid)), 0.5 * (hi - lo), near, far)

    def signed_distance(self, p: Sequence[float]) -> float:
        """Signed distance (m) from point ``p`` to the surface (negative inside)."""
        x, y, z = self._local(p)
        return _sd_box(x, y, z, self.half)

    def segment_distance(self, a: Sequence[float], b: Sequence[float]) -> float:
        """Signed distance (m) from segment ``a``-``b`` to the box (exact)."""
        la = self._local(a)
        lb = self._local(b)
        return _segment_box(la, (lb[0] - la[0], lb[1] - la[1], lb[2] - la[2]), self.half)

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict form (the YAML schema)."""
        return {"type": "box", "center": list(self.center), "size": list(self.size), "yaw": self.yaw,
                "name": self.name}


Obstacle = Sphere | Cylinder | Box


# ----------------------------------------------------------------------------------------------
# Scalar distance kernels
# ----------------------------------------------------------------------------------------------


def _point_segment_distance(p: Sequence[float], a: Sequence[float], b: Sequence[float]) -> float:
    bx, by, bz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    px, py, pz = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    bb = bx * bx + by * by + bz * bz
    t = 0.0 if bb <= 0.0 else (px * bx + py * by + pz * bz) / bb
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    dx, dy, dz = px - t * bx, py - t * by, pz - t * bz
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def _sd_box(x: float, y: float, z: float, h: Sequence[float]) -> float:
    qx, qy, qz = abs(x) - h[0], abs(y) - h[1], abs(z) - h[2]
    ox, oy, oz = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
    outside = math.sqrt(ox * ox + oy * oy + oz * oz)
    return outside + min(max(qx, qy, qz), 0.0)


def _sd_cyl(x: float, y: float, z: float, r: float, hz: float) -> float:
    qr = math.hypot(x, y) - r
    qz = abs(z) - hz
    orr, oz = max(qr, 0.0), max(qz, 0.0)
    return math.hypot(orr, oz) + min(max(qr, qz), 0.0)


def _golden_min(f: Any) -> float:
    """Minimum of a convex scalar function on [0, 1] (golden-section search)."""
    lo, hi = 0.0, 1.0
    x1 = hi - _INV_PHI * (hi - lo)
    x2 = lo + _INV_PHI * (hi - lo)
    f1, f2 = f(x1), f(x2)
    for _ in range(_GOLDEN_ITERS):
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - _INV_PHI * (hi - lo)
            f1 = f(x1)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + _INV_PHI * (hi - lo)
            f2 = f(x2)
    return min(f1, f2, f(0.0), f(1.0))


def _secant(t0: float, t1: float, g0: float, g1: float) -> float:
    """Zero of the line through (t0, g0) and (t1, g1)."""
    return t0 - g0 * (t1 - t0) / (g1 - g0)


def _first_rise(gprime: Any, ts: list[float], refine: Any) -> float:
    """Minimiser over [0, 1] of a convex function with derivative ``gprime``, smooth between the
    breakpoints ``ts`` (0 and 1 among them; sorted here): 0 if it rises from the start, 1 if it never
    does, else ``refine(t0, t1, g0, g1)`` on the first bracket where ``gprime`` turns >= 0."""
    ts.sort()
    prev_t, prev_g = ts[0], gprime(ts[0])
    if prev_g >= 0.0:
        return 0.0
    for t in ts[1:]:
        gt = gprime(t)
        if gt >= 0.0:
            return refine(prev_t, t, prev_g, gt)
        prev_t, prev_g = t, gt
    return 1.0


def _segment_box(a: Sequence[float], b: Sequence[float], h: Sequence[float]) -> float:
    """Exact distance from segment a + t b, t in [0, 1], to the axis-aligned box [-h, h].

    g(t) = squared distance is convex and piecewise quadratic, so g'(t) is non-decreasing and piecewise
    linear with breakpoints where a coordinate crosses a face plane: bracket the root of g' between
    sorted breakpoints, then linear interpolation inside the bracket is exact.
    """

    def gprime(t: float) -> float:
        s = 0.0
        for i in range(3):
            p = a[i] + t * b[i]
            if p > h[i]:
                s += (p - h[i]) * b[i]
            elif p < -h[i]:
                s += (p + h[i]) * b[i]
        return s

    def g(t: float) -> float:
        s = 0.0
        for i in range(3):
            p = a[i] + t * b[i]
            e = p - h[i] if p > h[i] else (-h[i] - p if p < -h[i] else 0.0)
            s += e * e
        return s

    ts = [0.0, 1.0]
    for i in range(3):
        if b[i] != 0.0:
            for plane in (h[i], -h[i]):
                t = (plane - a[i]) / b[i]
                if 0.0 < t < 1.0:
                    ts.append(t)
    tstar = _first_rise(gprime, ts, _secant)  # gprime is piecewise linear: the secant is exact
    d2 = g(tstar)
    if d2 > 0.0:
        return math.sqrt(d2)
    # The segment enters the box: report the deepest (most negative) signed distance instead.
    return _golden_min(lambda t: _sd_box(a[0] + t * b[0], a[1] + t * b[1], a[2] + t * b[2], h))


def _segment_cylinder(ax: float, ay: float, az: float, bx: float, by: float, bz: float, r: float,
                      hz: float) -> float:
    """Exact distance from segment a + t b to the vertical cylinder rho <= r, |z| <= hz (centred at 0).

    g(t) = (max(0, rho - r))^2 + (max(0, |z| - hz))^2 is convex and C1; we bracket the root of its
    derivative between breakpoints (slab and surface crossings) and finish with the Illinois method.
    """

    def gprime(t: float) -> float:
        x, y, z = ax + t * bx, ay + t * by, az + t * bz
        s = 0.0
        rho = math.hypot(x, y)
        if rho > r:
            s += (rho - r) * (x * bx + y * by) / rho
        if z > hz:
            s += (z - hz) * bz
        elif z < -hz:
            s += (z + hz) * bz
        return s

    ts = [0.0, 1.0]
    if bz != 0.0:
        for plane in (hz, -hz):
            t = (plane - az) / bz
            if 0.0 < t < 1.0:
                ts.append(t)
    qa = bx * bx + by * by
    if qa > 0.0:
        qb = ax * bx + ay * by
        qc = ax * ax + ay * ay - r * r
        disc = qb * qb - qa * qc
        if disc > 0.0:
            sq = math.sqrt(disc)
            for t in ((-qb - sq) / qa, (-qb + sq) / qa):
                if 0.0 < t < 1.0:
                    ts.append(t)
        t = -qb / qa  # closest approach of the xy line to the axis
        if 0.0 < t < 1.0:
            ts.append(t)
    tstar = _first_rise(gprime, ts, lambda t0, t1, g0, g1: _illinois(gprime, t0, t1, g0, g1))
    x, y, z = ax + tstar * bx, ay + tstar * by, az + tstar * bz
    er = max(math.hypot(x, y) - r, 0.0)
    ez = max(abs(z) - hz, 0.0)
    d2 = er * er + ez * ez
    if d2 > 1e-24:
        return math.sqrt(d2)
    return _golden_min(lambda t: _sd_cyl(ax + t * bx, ay + t * by, az + t * bz, r, hz))


def _illinois(f: Any, lo: float, hi: float, flo: float, fhi: float) -> float:
    """Root of a non-decreasing function with f(lo) < 0 <= f(hi) (Illinois regula falsi)."""
    side = 0
    t = hi
    for _ in range(60):
        t = lo - flo * (hi - lo) / (fhi - flo)
        if not lo < t < hi:  # rounding: fall back to bisection
            t = 0.5 * (lo + hi)
        ft = f(t)
        if ft == 0.0 or hi - lo < 1e-13:
            return t
        if ft < 0.0:
            lo, flo = t, ft
            if side == -1:
                fhi *= 0.5
            side = -1
        else:
            hi, fhi = t, ft
            if side == 1:
                flo *= 0.5
            side = 1
    return t


def segment_distance(obstacle: Obstacle, a: Sequence[float], b: Sequence[float]) -> float:
    """Signed distance (m) between segment ``a``-``b`` (3-vectors, base frame) and ``obstacle``."""
    return obstacle.segment_distance(a, b)


# ----------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------

_SHAPES: dict[str, type] = {"sphere": Sphere, "cylinder": Cylinder, "box": Box, "cube": Box}


def obstacle_from_dict(d: Mapping[str, Any]) -> Obstacle:
    """Build one shape from a plain dict (the YAML schema, see :func:`Scene.from_dict`).

    Raises:
        ConfigError: unknown type, missing or malformed field.
    """
    if not isinstance(d, Mapping):
        raise ConfigError(f"obstacle must be a mapping, got {d!r}", field="obstacles", value=d)
    kind = str(d.get("type", "")).lower()
    if kind not in _SHAPES:
        raise ConfigError(f"obstacle type must be one of sphere/cylinder/box, got {d.get('type')!r}",
                          field="type", value=d.get("type"))
    try:
        name = str(d.get("name", ""))
        if kind == "sphere":
            return Sphere(d["center"], d["radius"], name)
        if kind == "cylinder":
            return Cylinder(d["center"], d["radius"], d["height"], name)
        return Box(d["center"], d["size"], float(d.get("yaw", 0.0)), name)
    except KeyError as exc:
        raise ConfigError(f"{kind} obstacle is missing field {exc.args[0]!r}", field=str(exc.args[0]),
                          value=dict(d)) from exc
    except InvalidInputError as exc:
        raise ConfigError(f"{kind} obstacle: {exc}", field=exc.field, value=exc.value) from exc
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{kind} obstacle: {exc}", value=dict(d)) from exc


#: visualization_msgs/Marker type constants accepted by :func:`obstacle_from_marker`.
MARKER_CUBE, MARKER_SPHERE, MARKER_CYLINDER = 1, 2, 3


def obstacle_from_marker(kind: int | str, position: Sequence[float], orientation_xyzw: Sequence[float],
                         scale: Sequence[float], name: str = "", tilt_tolerance: float = 0.05) -> Obstacle:
    """Shape from the fields of a ``visualization_msgs/Marker`` (no ROS import needed).

    ``kind``: Marker type (CUBE 1, SPHERE 2, CYLINDER 3) or "cube"/"box"/"sphere"/"cylinder";
    ``position`` (m) is the centre, ``orientation_xyzw`` the quaternion in ROS order (x, y, z, w),
    ``scale`` (m) the full sizes as RViz draws them (sphere: diameter in x; cylinder: diameter in x,
    height in z). Boxes keep the yaw of the orientation; cylinders must stand upright and boxes must
    not be tilted (within ``tilt_tolerance`` rad), spheres ignore the orientation.

    Raises:
        InvalidInputError: unknown type, non-finite values, zero size, or a tilted cylinder/box.
    """
    names = {MARKER_CUBE: "box", MARKER_SPHERE: "sphere", MARKER_CYLINDER: "cylinder", "cube": "box",
             "box": "box", "sphere": "sphere", "cylinder": "cylinder"}
    key = kind.lower() if isinstance(kind, str) else int(kind)
    if key not in names:
        raise InvalidInputError(f"unsupported marker type {kind!r} (CUBE, SPHERE or CYLINDER)", field="type",
                                value=kind)
    shape = names[key]
    center = _vec3(position, "position")
    sc = _vec3(scale, "scale")
    try:
        qx, qy, qz, qw = (float(v) for v in orientation_xyzw)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError("orientation must be 4 numbers (x, y, z, w)", field="orientation",
                                value=orientation_xyzw) from exc
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not math.isfinite(n):
        raise InvalidInputError("orientation must be finite", field="orientation", value=orientation_xyzw)
    if n < 1e-9:  # RViz treats an all-zero quaternion as identity
        qx, qy, qz, qw = 0.0, 0.0, 0.0, 1.0
    else:
        qx, qy, qz, qw = qx / n, qy / n, qz / n, qw / n
    if shape == "sphere":
        return Sphere(center, 0.5 * max(sc), name)
    # Tilt = angle between the shape's z axis and the vertical.
    z_z = 1.0 - 2.0 * (qx * qx + qy * qy)
    tilt = math.acos(max(-1.0, min(1.0, abs(z_z))))
    if tilt > tilt_tolerance:
        raise InvalidInputError(f"{shape} {name!r} is tilted by {tilt:.3f} rad; only upright ones are "
                                "supported", field="orientation", value=orientation_xyzw)
    if shape == "cylinder":
        return Cylinder(center, 0.5 * max(sc[0], sc[1]), sc[2], name)
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return Box(center, sc, yaw, name)


@dataclass(frozen=True)
class Scene:
    """Obstacles plus an optional table top (``table_height``: z of the table surface in m, or None)."""

    obstacles: tuple[Obstacle, ...] = ()
    table_height: float | None = None
    name: str = ""

    def __post_init__(self) -> None:
        obs = tuple(self.obstacles)
        for o in obs:
            if not isinstance(o, Sphere | Cylinder | Box):
                raise InvalidInputError(f"not an obstacle shape: {o!r}", field="obstacles", value=o)
        object.__setattr__(self, "obstacles", obs)
        if self.table_height is not None:
            th = float(self.table_height)
            if not math.isfinite(th):
                raise InvalidInputError("table_height must be finite", field="table_height",
                                        value=self.table_height)
            object.__setattr__(self, "table_height", th)

    def __len__(self) -> int:
        return len(self.obstacles)

    @property
    def free_space(self) -> bool:
        """No obstacle and no table: nothing but the arm itself to keep clear of."""
        return not self.obstacles and self.table_height is None

    def with_obstacles(self, obstacles: Iterable[Obstacle]) -> Scene:
        """A copy with another obstacle list (same table)."""
        return Scene(tuple(obstacles), self.table_height, self.name)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> Scene:
        """Scene from a plain dict::

            {"name": "...", "table_height": 0.0,          # or None / absent: no table
             "obstacles": [{"type": "sphere", "center": [x, y, z], "radius": r},
                           {"type": "cylinder", "center": [x, y, z], "radius": r, "height": h},
                           {"type": "box", "center": [x, y, z], "size": [sx, sy, sz], "yaw": 0.0}]}

        Raises:
            ConfigError: malformed content (the message names the field).
        """
        if d is None:
            return cls()
        if not isinstance(d, Mapping):
            raise ConfigError(f"scene must be a mapping, got {type(d).__name__}", value=d)
        unknown = set(d) - {"name", "table_height", "obstacles", "description"}
        if unknown:
            raise ConfigError(f"unknown scene field(s): {sorted(unknown)}", field=sorted(unknown)[0])
        items = d.get("obstacles") or []
        if not isinstance(items, list | tuple):
            raise ConfigError("obstacles must be a list", field="obstacles", value=items)
        th = d.get("table_height")
        try:
            return cls(tuple(obstacle_from_dict(o) for o in items),
                       None if th is None else float(th), str(d.get("name", "")))
        except (TypeError, ValueError) as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(f"bad scene: {exc}", value=dict(d)) from exc

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict form, inverse of :meth:`from_dict`."""
        return {"name": self.name, "table_height": self.table_height,
                "obstacles": [o.to_dict() for o in self.obstacles]}

    @classmethod
    def from_yaml(cls, path: str | Path) -> Scene:
        """Load a scene file (schema of :meth:`from_dict`).

        Raises:
            ConfigError: missing file, YAML syntax error or malformed content.
        """
        import yaml

        from redarm_ros.yaml_safe import safe_load

        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError(f"cannot read scene file {p}: {exc}", field="path", value=str(p)) from exc
        try:
            data = safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"scene file {p} is not valid YAML: {exc}", field="path",
                              value=str(p)) from exc
        scene = cls.from_dict(data)
        if not scene.name:
            scene = Scene(scene.obstacles, scene.table_height, p.stem)
        return scene


def scenes_dir() -> Path:
    """Directory of the bundled scene files (source tree or ament share directory)."""
    here = Path(__file__).resolve().parents[2] / "config" / "scenes"
    if here.is_dir():
        return here
    try:  # installed with colcon: share/redarm_ros/config/scenes
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("redarm_ros")) / "config" / "scenes"
    except Exception:  # noqa: BLE001 - ament index absent or package not installed
        return here


def load_scene(name_or_path: str | Path) -> Scene:
    """Load ``config/scenes/<name>.yaml`` or a path to a scene file.

    Raises:
        ConfigError: unknown name (the message lists the bundled scenes) or malformed file.
    """
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.is_file():
        return Scene.from_yaml(p)
    candidate = scenes_dir() / f"{name_or_path}.yaml"
    if candidate.is_file():
        return Scene.from_yaml(candidate)
    known = sorted(f.stem for f in scenes_dir().glob("*.yaml"))
    raise ConfigError(f"unknown scene {name_or_path!r}; bundled scenes: {known}", field="scene",
                      value=str(name_or_path))


# ----------------------------------------------------------------------------------------------
# Arm capsules and minimum distance
# ----------------------------------------------------------------------------------------------

#: Names of the capsule links, between consecutive key points.
LINK_NAMES = ("base", "upper_arm", "forearm", "hand")


@declared("capsules")
class ArmCapsules:
    """Capsules of the four links between the key points base-shoulder-elbow-wrist-tool (link indices
    0..3, named in :data:`LINK_NAMES`)."""


@dataclass(frozen=True)
class Clearance:
    """Result of :func:`min_distance`.

    ``distance``: signed clearance (m) between the closest link capsule and obstacle (inf if none);
    ``link``: index into :data:`LINK_NAMES` (-1 if nothing to check);
    ``obstacle``: index into ``scene.obstacles``, or :data:`TABLE` (-1) for the table top.
    """

    distance: float
    link: int
    obstacle: int

    @property
    def link_name(self) -> str:
        """Name of the closest link (or "" if none)."""
        return LINK_NAMES[self.link] if self.link >= 0 else ""


def _as_points(key_points: Any) -> list[tuple[float, float, float]]:
    kp = np.asarray(key_points, dtype=float)
    if kp.shape != (5, 3):
        raise InvalidInputError(f"key points must have shape (5, 3), got {kp.shape}", field="key_points")
    return [(float(r[0]), float(r[1]), float(r[2])) for r in kp]


def links_clearance(points: Sequence[Sequence[float]], scene: Scene, capsules: ArmCapsules,
                    links: Iterable[int] = (0, 1, 2, 3)) -> Clearance:
    """Minimum signed clearance (m) of the given links of the capsule arm against ``scene``.

    ``points`` are the 5 key points (base, shoulder, elbow, wrist, tool) as 3-sequences (m).
    """
    best = math.inf
    best_link = -1
    best_obs = -1
    radii = capsules.radii
    th = scene.table_height
    for link in links:
        a = points[link]
        b = points[link + 1]
        r = radii[link]
        if link in capsules.obstacle_links:
            for j, obs in enumerate(scene.obstacles):
                d = obs.segment_distance(a, b) - r
                if d < best:
                    best, best_link, best_obs = d, link, j
        if th is not None and link in capsules.table_links:
            d = min(a[2], b[2]) - th - r
            if d < best:
                best, best_link, best_obs = d, link, TABLE
    return Clearance(best, best_link, best_obs)


def min_distance(arm: KeyPointArm, q: Any, scene: Scene, capsules: ArmCapsules | None = None) -> Clearance:
    """Minimum signed clearance between the arm at joint angles ``q`` (rad) and ``scene``.

    Uses ``arm.key_points(q)`` (base, shoulder, elbow, wrist, tool, in m) and one capsule per link.
    Returns a :class:`Clearance` (distance in m, closest link, closest obstacle or :data:`TABLE`).
    """
    caps = capsules or ArmCapsules()
    return links_clearance(_as_points(arm.key_points(q)), scene, caps)


#: Links whose position depends on the swivel angle (upper arm and forearm).
ELBOW_LINKS = (1, 2)
