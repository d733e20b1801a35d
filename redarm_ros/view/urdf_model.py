"""A small URDF reader: the link tree, primitive visuals and forward kinematics by joint name.

Enough of URDF for drawing an arm and computing its ``/tf`` from ``/joint_states``, with numpy only
(no ROS, no viewer): links, joints (``revolute``, ``continuous``, ``prismatic``; everything else is
treated as ``fixed``), joint ``origin`` (xyz + fixed-axis roll/pitch/yaw) and ``axis``, and each
link's visuals of type ``sphere``, ``cylinder`` (along its local z, centred), ``box`` and ``mesh``
(kept by file name; callers may skip it), with colours from inline or top-level named materials.

Frames follow URDF: ``T_parent_child(q) = origin @ motion(axis, q)``; :meth:`UrdfModel.link_transforms`
returns every link's pose in the root link's frame. Units: m, rad.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.urdf_chain import UrdfJoint, parse_urdf

MOVABLE = ("revolute", "continuous", "prismatic")
DEFAULT_RGBA = (0.7, 0.7, 0.72, 1.0)


@dataclass(frozen=True)
class Visual:
    """One visual of a link: ``kind`` sphere | cylinder | box | mesh, ``size`` as URDF gives it
    (sphere ``(r,)``, cylinder ``(r, length)``, box ``(x, y, z)``, mesh ``scale``), ``origin`` 4x4 in
    the link frame, ``rgba`` 0..1, ``filename`` for meshes."""

    kind: str
    size: tuple[float, ...]
    origin: np.ndarray
    rgba: tuple[float, float, float, float] = DEFAULT_RGBA
    filename: str = ""


@dataclass(frozen=True)
class Joint:  # test/urdf_chain.py keeps its own URDF reader on purpose: an independent oracle
    """A URDF joint: ``origin`` 4x4 parent -> joint frame at zero, unit ``axis`` in the joint frame."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    lower: float = -math.inf
    upper: float = math.inf

    @classmethod
    def from_urdf(cls, j: UrdfJoint) -> Joint:
        """The joint the kinematics' URDF reader found; a continuous joint or an absent limit is unbounded."""
        bounded = j.type != "continuous"
        lower = j.lower if bounded and j.lower is not None else -math.inf
        upper = j.upper if bounded and j.upper is not None else math.inf
        return cls(j.name, j.type, j.parent, j.child, j.origin, j.axis, lower, upper)

    @property
    def movable(self) -> bool:
        """True for revolute, continuous and prismatic joints."""
        return self.type in MOVABLE

    def transform(self, value: float = 0.0) -> np.ndarray:
        """Parent -> child transform (4x4) at joint value ``value`` (rad or m)."""
        if not self.movable or value == 0.0:
            return self.origin.copy()
        M = np.eye(4)
        if self.type == "prismatic":
            M[:3, 3] = self.axis * value
        else:
            M[:3, :3] = axis_angle(self.axis, value)
        return self.origin @ M


@dataclass
class UrdfModel:
    """Links, joints and visuals of one URDF, with the root link and a parent-first joint order."""

    name: str
    root: str
    links: list[str]
    joints: list[Joint]  # parent before child (a depth-first order from the root)
    visuals: dict[str, list[Visual]] = field(default_factory=dict)
    text: str = ""

    @property
    def movable_joint_names(self) -> list[str]:
        """Names of the joints that take a value from ``/joint_states``, root to tip."""
        return [j.name for j in self.joints if j.movable]

    def joint_transforms(self, positions: Mapping[str, float]) -> list[tuple[Joint, np.ndarray]]:
        """Each joint with its parent -> child transform at ``positions`` (name -> value; missing = 0)."""
        return [(j, j.transform(float(positions.get(j.name, 0.0)))) for j in self.joints]

    def link_transforms(self, positions: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Every link's 4x4 pose in the root frame at ``positions`` (name -> value; missing = 0)."""
        out = {self.root: np.eye(4)}
        for j, T in self.joint_transforms(positions):
            out[j.child] = out[j.parent] @ T
        return out

    @classmethod
    def from_string(cls, text: str) -> UrdfModel:
        """Parse URDF text.

        Raises:
            InvalidInputError: not XML, no ``<robot>``, no single root link, or a bad number.
        """
        try:
            robot = ET.fromstring(text)
        except ET.ParseError as exc:
            raise InvalidInputError(f"URDF is not valid XML: {exc}", field="urdf") from exc
        if robot.tag != "robot":
            raise InvalidInputError(f"URDF root element is <{robot.tag}>, not <robot>", field="urdf")
        materials = {m.get("name", ""): _rgba(m) for m in robot.findall("material")}
        links = [ln.get("name", "") for ln in robot.findall("link")]
        visuals = {ln.get("name", ""): _visuals(ln, materials) for ln in robot.findall("link")}
        joints = [Joint.from_urdf(j) for j in parse_urdf(text)[1].values()]
        children = {j.child for j in joints}
        roots = [ln for ln in links if ln not in children]
        if len(roots) != 1:
            raise InvalidInputError(f"URDF must have exactly one root link, found {roots}", field="urdf")
        ordered = _parent_first(joints, roots[0])
        return cls(robot.get("name", ""), roots[0], links, ordered, visuals, text)


def _parent_first(joints: list[Joint], root: str) -> list[Joint]:
    known = {root}
    out: list[Joint] = []
    pending = list(joints)
    while pending:
        progressed = False
        for j in list(pending):
            if j.parent in known:
                out.append(j)
                known.add(j.child)
                pending.remove(j)
                progressed = True
        if not progressed:  # joints whose parent is unreachable from the root: leave them out
            break
    return out


def axis_angle(axis: Sequence[float], angle: float) -> np.ndarray:
    """Rotation matrix (3x3) of ``angle`` rad about the unit ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=float)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF fixed-axis roll/pitch/yaw (rad) as a matrix: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    return axis_angle((0, 0, 1), yaw) @ axis_angle((0, 1, 0), pitch) @ axis_angle((1, 0, 0), roll)


def _floats(text: str | None, n: int, what: str, default: Sequence[float]) -> tuple[float, ...]:
    if text is None:
        return tuple(float(v) for v in default)
    try:
        vals = tuple(float(v) for v in text.split())
    except ValueError as exc:
        raise InvalidInputError(f"URDF {what}: not numbers: {text!r}", field=what, value=text) from exc
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise InvalidInputError(f"URDF {what}: expected {n} finite numbers, got {text!r}", field=what,
                                value=text)
    return vals


def _origin(el: ET.Element | None) -> np.ndarray:
    T = np.eye(4)
    if el is None:
        return T
    xyz = _floats(el.get("xyz"), 3, "origin xyz", (0, 0, 0))
    rpy = _floats(el.get("rpy"), 3, "origin rpy", (0, 0, 0))
    T[:3, :3] = rpy_matrix(*rpy)
    T[:3, 3] = xyz
    return T


def _rgba(material: ET.Element) -> tuple[float, float, float, float] | None:
    color = material.find("color")
    if color is None or color.get("rgba") is None:
        return None
    r, g, b, a = _floats(color.get("rgba"), 4, "material rgba", DEFAULT_RGBA)
    return (r, g, b, a)


def _visuals(link: ET.Element, materials: dict[str, tuple[float, float, float, float] | None]
             ) -> list[Visual]:
    out = []
    for vis in link.findall("visual"):
        geom = vis.find("geometry")
        if geom is None or len(geom) == 0:
            continue
        shape = geom[0]
        rgba: tuple[float, float, float, float] | None = None
        mat = vis.find("material")
        if mat is not None:
            rgba = _rgba(mat) or materials.get(mat.get("name", ""))
        rgba = rgba or DEFAULT_RGBA
        origin = _origin(vis.find("origin"))
        if shape.tag == "sphere":
            size: tuple[float, ...] = _floats(shape.get("radius"), 1, "sphere radius", (0.0,))
        elif shape.tag == "cylinder":
            size = _floats(shape.get("radius"), 1, "cylinder radius", (0.0,)) + _floats(
                shape.get("length"), 1, "cylinder length", (0.0,))
        elif shape.tag == "box":
            size = _floats(shape.get("size"), 3, "box size", (0, 0, 0))
        elif shape.tag == "mesh":
            size = _floats(shape.get("scale"), 3, "mesh scale", (1, 1, 1))
            out.append(Visual("mesh", size, origin, rgba, shape.get("filename", "")))
            continue
        else:
            continue
        out.append(Visual(shape.tag, size, origin, rgba))
    return out


def model_for_arm(arm_name: str) -> UrdfModel:
    """The URDF model of ``config/arms/<arm_name>.yaml`` as installed (``share/redarm_ros/urdf/<arm>.urdf``)
    and published by the description node: link names without a prefix (``base_link``, ``link_1``..,
    ``tool``)."""
    from redarm_ros.kinematics import load_arm
    from redarm_ros.sim.urdf import build_urdf

    return UrdfModel.from_string(build_urdf(load_arm(arm_name), prefix=""))


def matrix_to_quat_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation matrix (w >= 0)."""
    from redarm_ros.kinematics.quaternion import matrix_to_quat

    w, x, y, z = (float(v) for v in matrix_to_quat(np.asarray(R, dtype=float)[:3, :3]))
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    return (x, y, z, w)
