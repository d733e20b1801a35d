"""URDF text from a kinematic arm model (``redarm_ros.kinematics`` contract).

The model's chain is ``frame_i = frame_{i-1} @ origin_i @ Rot(axis_i, q_i)`` with the tool fixed to the
last joint frame; that is exactly URDF's joint semantics, so every revolute joint gets the model's
``origin`` (as xyz + fixed-axis roll/pitch/yaw) and ``axis``, and the tool is a fixed joint. The URDF
link frames therefore coincide with ``arm.fk_frames(q)``.

Link and joint names (``prefix`` defaults to ``"<arm.name>_"``):

* ``<prefix>base_link`` (pybullet base, index -1),
* ``<prefix>link_<i>`` for i = 1..n, child of the model's joint ``arm.joint_names[i-1]``
  (pybullet joint/link index i-1),
* ``<prefix>tool`` child of the fixed joint ``<prefix>tool_joint`` (pybullet index n).

Geometry is deliberately simple and standard-URDF only (cylinders and spheres, readable by
robot_state_publisher/RViz as well as pybullet): each link carries a sphere "motor housing" at its joint
and a cylinder from its joint to the next joint (or the tool point). Collision shapes equal the visuals,
except that ``visuals`` (:func:`urdf_visuals`: an arm's own URDF's visual elements, meshes included)
replace the generated visuals of the links they are given for.
Masses come from fixed nominal densities; inertias are the exact tensors of those solids about the link's
centre of mass (plausible, not measured). Efforts are an upper bound of the static gravity torque times a
safety factor, unless the model's joint carries an ``effort`` attribute (N m). Units: m, kg, kg m^2, rad,
rad/s, N m.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from redarm_ros.errors import InvalidInputError


def escape(data: str, entities: dict[str, str] | None = None) -> str:
    """``xml.sax.saxutils.escape``, the same replacements in the same order: that module imports
    ``urllib.request`` and ``http.client`` (~25 ms of CPU in every process that builds a URDF)."""
    data = data.replace("&", "&amp;").replace(">", "&gt;").replace("<", "&lt;")
    for key, value in (entities or {}).items():
        data = data.replace(key, value)
    return data


GRAVITY = 9.81  # m/s^2
SEGMENT_DENSITY = 1200.0  # kg/m^3, a hollow aluminium tube smeared over a solid cylinder
HOUSING_DENSITY = 2400.0  # kg/m^3, motor + gear + housing smeared over a solid sphere
EFFORT_SAFETY = 2.5  # effort = safety * worst static gravity torque
MIN_EFFORT = 20.0  # N m
TOOL_MASS = 0.2  # kg
TOOL_RADIUS = 0.025  # m
MIN_SEGMENT = 1e-6  # m; shorter link offsets get no cylinder


class JointLike(Protocol):
    """What the builder reads from one ``arm.chain`` entry."""

    name: str
    origin: Any  # (4, 4) parent -> joint frame at q = 0
    axis: Any  # (3,) unit, joint frame
    lower: float
    upper: float
    max_vel: float


class ArmLike(Protocol):
    """What the builder reads from an arm model."""

    name: str
    n: int
    chain: Sequence[JointLike]
    tool: Any  # (4, 4) last joint frame -> tool


@dataclass(frozen=True)
class LinkBody:
    """Mass properties and shapes of one generated link (all in the link frame, SI units)."""

    mass: float
    com: np.ndarray  # (3,)
    inertia: np.ndarray  # (3, 3) about the COM, link-frame axes
    housing_radius: float
    segment_end: np.ndarray  # (3,) end point of the cylinder (start is the origin)
    segment_radius: float


def link_names(arm: ArmLike, prefix: str | None = None) -> list[str]:
    """Names of the generated links: base, link_1..link_n, tool (pybullet indices -1, 0..n-1, n)."""
    p = f"{arm.name}_" if prefix is None else prefix
    return [f"{p}base_link"] + [f"{p}link_{i}" for i in range(1, arm.n + 1)] + [f"{p}tool"]


def matrix_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw (rad) of a rotation matrix, ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    At gimbal lock (pitch = +-pi/2) roll is set to 0 and yaw carries the remaining rotation.
    """
    R = np.asarray(R, dtype=float)
    cp = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], cp)
    if cp > 1e-9:
        roll = math.atan2(R[2, 1], R[2, 2])
        yaw = math.atan2(R[1, 0], R[0, 0])
    else:
        roll = 0.0
        yaw = math.atan2(-R[0, 1], R[1, 1])
    return roll, pitch, yaw


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix of URDF roll, pitch, yaw (rad): ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _z_to(d: np.ndarray) -> np.ndarray:
    """A rotation taking +z onto the unit vector ``d`` (shortest arc)."""
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, d))
    if c > 1.0 - 1e-12:
        return np.eye(3)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, d)
    s = np.linalg.norm(v)
    k = v / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _f(x: float) -> str:
    # 17 significant digits: the text round-trips the double exactly.
    v = float(x)
    return "0" if v == 0.0 else f"{v:.17g}"


def _origin(xyz: Sequence[float], R: np.ndarray | None = None) -> str:
    rpy = (0.0, 0.0, 0.0) if R is None else matrix_to_rpy(R)
    return f'<origin xyz="{" ".join(_f(v) for v in xyz)}" rpy="{" ".join(_f(v) for v in rpy)}"/>'


def _check_transform(T: Any, what: str) -> np.ndarray:
    A = np.asarray(T, dtype=float)
    if A.shape != (4, 4) or not np.all(np.isfinite(A)):
        raise InvalidInputError(f"{what} must be a finite 4x4 transform", field=what, value=T)
    R = A[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise InvalidInputError(f"{what} rotation is not orthonormal", field=what, value=T)
    return A


def _solid_cylinder(m: float, r: float, length: float, d: np.ndarray) -> np.ndarray:
    """Inertia (3, 3) of a solid cylinder about its centre, axis along unit ``d``."""
    dd = np.outer(d, d)
    i_ax = 0.5 * m * r * r
    i_perp = m * (3 * r * r + length * length) / 12.0
    return i_perp * (np.eye(3) - dd) + i_ax * dd


def _body(radius: float, end: np.ndarray) -> LinkBody:
    """Mass properties of a sphere of ``1.2 * radius`` at the origin plus a cylinder origin -> ``end``."""
    r_h = 1.2 * radius
    m_h = HOUSING_DENSITY * 4.0 / 3.0 * math.pi * r_h**3
    parts: list[tuple[float, np.ndarray, np.ndarray]] = [
        (m_h, np.zeros(3), 0.4 * m_h * r_h * r_h * np.eye(3))
    ]
    length = float(np.linalg.norm(end))
    if length > MIN_SEGMENT:
        m_s = SEGMENT_DENSITY * math.pi * radius * radius * length
        parts.append((m_s, 0.5 * end, _solid_cylinder(m_s, radius, length, end / length)))
    mass = sum(m for m, _, _ in parts)
    com = sum(m * c for m, c, _ in parts) / mass
    inertia = np.zeros((3, 3))
    for m, c, i_c in parts:
        r = c - com
        inertia += i_c + m * (float(r @ r) * np.eye(3) - np.outer(r, r))  # parallel axis
    return LinkBody(mass, com, inertia, r_h, np.asarray(end, float), radius)


def link_bodies(arm: ArmLike) -> list[LinkBody]:
    """The generated moving links' bodies (index i-1 for ``link_i``), radius tapering 6 cm -> 3.5 cm."""
    n = arm.n
    bodies = []
    for i in range(n):
        nxt = arm.chain[i + 1].origin if i + 1 < n else arm.tool
        end = np.asarray(nxt, dtype=float)[:3, 3].copy()
        radius = 0.06 - 0.025 * i / max(n - 1, 1)
        bodies.append(_body(radius, end))
    return bodies


def _zero_pose_frames(arm: ArmLike) -> list[np.ndarray]:
    T = np.eye(4)
    out = []
    for j in arm.chain:
        T = T @ np.asarray(j.origin, dtype=float)
        out.append(T.copy())
    out.append(T @ np.asarray(arm.tool, dtype=float))
    return out


def joint_efforts(arm: ArmLike, bodies: Sequence[LinkBody] | None = None) -> np.ndarray:
    """Per-joint effort limits (N m): the model's ``effort`` if given, else a static-gravity bound.

    The bound uses, for every distal body, the path length along the chain from the joint to the body's
    COM as the lever arm (an upper bound over all configurations), times ``EFFORT_SAFETY``.
    """
    bodies = link_bodies(arm) if bodies is None else bodies
    frames = _zero_pose_frames(arm)
    pts = [f[:3, 3] for f in frames]  # joint origins 1..n, then tool
    seg = [float(np.linalg.norm(pts[i + 1] - pts[i])) for i in range(arm.n)]
    out = np.empty(arm.n)
    for i, joint in enumerate(arm.chain):
        given = getattr(joint, "effort", None)
        if given is not None and float(given) > 0:
            out[i] = float(given)
            continue
        torque = 0.0
        for j in range(i, arm.n):
            lever = sum(seg[i:j]) + float(np.linalg.norm(bodies[j].com))
            torque += bodies[j].mass * GRAVITY * lever
        lever_tool = sum(seg[i:])
        torque += TOOL_MASS * GRAVITY * lever_tool
        out[i] = max(MIN_EFFORT, EFFORT_SAFETY * torque)
    return out


def _inertial(mass: float, com: Sequence[float], inertia: np.ndarray) -> str:
    m = inertia
    return (
        f'    <inertial>{_origin(com)}<mass value="{_f(mass)}"/>'
        f'<inertia ixx="{_f(m[0, 0])}" ixy="{_f(m[0, 1])}" ixz="{_f(m[0, 2])}" '
        f'iyy="{_f(m[1, 1])}" iyz="{_f(m[1, 2])}" izz="{_f(m[2, 2])}"/></inertial>'
    )


def _shapes(geoms: list[tuple[str, str]], material: str, visual: bool = True) -> list[str]:
    """Visual (unless ``visual`` is False) + collision elements for (origin xml, geometry xml) pairs."""
    lines = []
    for origin, geom in geoms:
        if visual:
            mat = f'<material name="{material}"/>'
            lines.append(f"    <visual>{origin}<geometry>{geom}</geometry>{mat}</visual>")
        lines.append(f"    <collision>{origin}<geometry>{geom}</geometry></collision>")
    return lines


def _mesh_file(filename: str, base_dir: Path | None) -> Path | None:
    """The mesh file a URDF names, if it exists: ``file://`` or absolute paths, paths relative to the URDF's
    directory, and ``package://<pkg>/..`` through the ament index where ROS is installed."""
    if filename.startswith("package://"):
        pkg, _, rest = filename[len("package://"):].partition("/")
        try:
            from ament_index_python.packages import get_package_share_directory

            cand = Path(get_package_share_directory(pkg)) / rest
        except Exception:  # noqa: BLE001 - no ament index, or no such package: no mesh
            return None
    elif filename.startswith("file://"):
        cand = Path(filename[len("file://"):])
    else:
        cand = Path(filename)
        if not cand.is_absolute():
            if base_dir is None:
                return None
            cand = base_dir / cand
    return cand.resolve() if cand.is_file() else None


def urdf_visuals(source: str | os.PathLike[str], base_link: str, tip_link: str) -> dict[int, list[str]]:
    """The visual elements of a URDF's chain ``base_link`` -> ``tip_link`` for :func:`build_urdf`, by model
    link index (0: the base, i: the child of the i-th moving joint; a link hanging from fixed joints goes to
    the link it is fixed to, its origin moved into that link's frame). Mesh paths are made absolute. A link
    gets its URDF visuals only where every mesh file it names is found; otherwise it keeps the generated
    shapes. ``source``: a URDF file or its text (then only absolute and ``package://`` meshes are found)."""
    from redarm_ros.kinematics.model import transform_from_xyz_rpy
    from redarm_ros.kinematics.urdf_chain import chain_between, chain_links, parse_urdf, read_urdf_text

    text, path = read_urdf_text(source)
    _, by_child = parse_urdf(text)
    links = {el.get("name"): el for el in ET.fromstring(text).findall("link")}
    base_dir = None if path is None else path.resolve().parent
    out: dict[int, list[str]] = {}
    missing: set[int] = set()
    for name, k, T in chain_links(chain_between(by_child, base_link, tip_link), base_link):
        el = links.get(name)
        for vis in [] if el is None else el.findall("visual"):
            geom = vis.find("geometry")
            shape = None if geom is None or len(geom) == 0 else geom[0]
            if shape is None:
                continue
            if shape.tag == "mesh":
                f = _mesh_file(shape.get("filename", ""), base_dir)
                if f is None:
                    missing.add(k)
                    continue
                shape = ET.Element("mesh", {"filename": str(f), "scale": shape.get("scale", "1 1 1")})
            org = vis.find("origin")
            xyz = [float(v) for v in (org.get("xyz", "0 0 0") if org is not None else "0 0 0").split()]
            rpy = [float(v) for v in (org.get("rpy", "0 0 0") if org is not None else "0 0 0").split()]
            Tv = T @ transform_from_xyz_rpy(xyz, rpy)
            color = vis.find("material/color")
            rgba = "" if color is None else escape(color.get("rgba", ""))
            mat = (f'<material name="urdf_{k}_{len(out.get(k, []))}"><color rgba="{rgba}"/></material>'
                   if rgba else '<material name="segment"/>')
            out.setdefault(k, []).append(f"    <visual>{_origin(Tv[:3, 3], Tv[:3, :3])}<geometry>"
                                         f"{ET.tostring(shape, encoding='unicode')}</geometry>{mat}</visual>")
    return {k: v for k, v in out.items() if k not in missing}


def _segment_geom(start: np.ndarray, end: np.ndarray, radius: float) -> tuple[str, str] | None:
    d = end - start
    length = float(np.linalg.norm(d))
    if length <= MIN_SEGMENT:
        return None
    return _origin(
        start + 0.5 * d, _z_to(d / length)
    ), f'<cylinder radius="{_f(radius)}" length="{_f(length)}"/>'


def build_urdf(
    arm: ArmLike,
    *,
    prefix: str | None = None,
    robot_name: str | None = None,
    visuals: dict[int, list[str]] | None = None,
) -> str:
    """URDF text (str) of ``arm``: fixed base, n revolute joints, fixed tool link. ``visuals``: visual
    elements by link index (0 base, i the child of joint i) in place of the generated ones.

    Raises :class:`InvalidInputError` if a transform of the model is not a finite rigid transform or an
    axis is not a unit vector.
    """
    names = link_names(arm, prefix)
    p = f"{arm.name}_" if prefix is None else prefix
    robot = escape(robot_name or arm.name, {'"': "&quot;"})
    if len(arm.chain) != arm.n:
        raise InvalidInputError("arm.chain length differs from arm.n", field="chain", value=len(arm.chain))
    for j in arm.chain:
        _check_transform(j.origin, f"{j.name}.origin")
        ax = np.asarray(j.axis, dtype=float)
        if ax.shape != (3,) or abs(float(np.linalg.norm(ax)) - 1.0) > 1e-9:
            raise InvalidInputError(f"{j.name}.axis must be a unit 3-vector", field="axis", value=j.axis)
    tool = _check_transform(arm.tool, "tool")
    bodies = link_bodies(arm)
    efforts = joint_efforts(arm, bodies)

    out = [
        '<?xml version="1.0"?>',
        f"<!-- generated by redarm_ros.sim.urdf from arm model '{escape(arm.name)}'; do not edit -->",
        f'<robot name="{robot}">',
        '  <material name="base"><color rgba="0.25 0.25 0.28 1"/></material>',
        '  <material name="housing"><color rgba="0.85 0.15 0.12 1"/></material>',
        '  <material name="segment"><color rgba="0.78 0.78 0.8 1"/></material>',
        '  <material name="tool"><color rgba="0.95 0.75 0.1 1"/></material>',
    ]

    # Base: a pedestal disk plus a post up to the first joint if it is offset.
    first = np.asarray(arm.chain[0].origin, dtype=float)[:3, 3]
    base_geoms: list[tuple[str, str]] = [(_origin([0, 0, 0.02]), '<cylinder radius="0.12" length="0.04"/>')]
    post = _segment_geom(np.zeros(3), first, 0.065)
    if post is not None:
        base_geoms.append(post)
    visuals = visuals or {}
    out.append(f'  <link name="{names[0]}">')
    out.append(_inertial(10.0, [0, 0, 0], np.diag([0.05, 0.05, 0.07])))
    out.extend(visuals.get(0, []))
    out.extend(_shapes(base_geoms, "base", visual=0 not in visuals))
    out.append("  </link>")

    for i, (joint, body) in enumerate(zip(arm.chain, bodies, strict=True)):
        parent, child = names[i], names[i + 1]
        origin = np.asarray(joint.origin, dtype=float)
        ax = np.asarray(joint.axis, dtype=float)
        out.append(f'  <joint name="{escape(joint.name)}" type="revolute">')
        out.append(f'    <parent link="{parent}"/><child link="{child}"/>')
        out.append(f"    {_origin(origin[:3, 3], origin[:3, :3])}")
        out.append(f'    <axis xyz="{" ".join(_f(v) for v in ax)}"/>')
        out.append(
            f'    <limit lower="{_f(joint.lower)}" upper="{_f(joint.upper)}" '
            f'effort="{_f(round(float(efforts[i]), 1))}" velocity="{_f(joint.max_vel)}"/>'
        )
        out.append("  </joint>")
        geoms = [(_origin([0, 0, 0]), f'<sphere radius="{_f(body.housing_radius)}"/>')]
        seg = _segment_geom(np.zeros(3), body.segment_end, body.segment_radius)
        out.append(f'  <link name="{child}">')
        out.append(_inertial(body.mass, body.com, body.inertia))
        out.extend(visuals.get(i + 1, []))
        out.extend(_shapes(geoms, "housing", visual=i + 1 not in visuals))
        if seg is not None:
            out.extend(_shapes([seg], "segment", visual=i + 1 not in visuals))
        out.append("  </link>")

    out.append(f'  <joint name="{p}tool_joint" type="fixed">')
    out.append(f'    <parent link="{names[-2]}"/><child link="{names[-1]}"/>')
    out.append(f"    {_origin(tool[:3, 3], tool[:3, :3])}")
    out.append("  </joint>")
    i_tool = 0.4 * TOOL_MASS * TOOL_RADIUS**2
    out.append(f'  <link name="{names[-1]}">')
    out.append(_inertial(TOOL_MASS, [0, 0, 0], np.diag([i_tool] * 3)))
    out.extend(_shapes([(_origin([0, 0, 0]), f'<sphere radius="{_f(TOOL_RADIUS)}"/>')], "tool"))
    out.append("  </link>")
    out.append("</robot>")
    return "\n".join(out) + "\n"


def write_urdf(arm: ArmLike, path: str, **kwargs: Any) -> str:
    """Write :func:`build_urdf` output to ``path`` (UTF-8) and return the path."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(build_urdf(arm, **kwargs))
    return path
