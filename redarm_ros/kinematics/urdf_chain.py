"""Arm models from a URDF: the joint chain between a base link and a tip link, as TRAC-IK and KDL take it.

:func:`load_urdf_arm` reads a URDF (a file path, or the XML text as published on ``/robot_description``),
walks the kinematic tree from ``tip_link`` up to ``base_link`` and builds the model of that chain:

* revolute and continuous joints become the model's joints (axis, origin xyz + rpy, limits, velocity
  limit); fixed joints fold into the neighbouring transforms; a prismatic joint is refused (the models
  here are revolute chains). Continuous joints get the range ``[-CONTINUOUS_RANGE, CONTINUOUS_RANGE]``.
* acceleration limits, which URDF has no field for, come from a MoveIt-style ``joint_limits`` YAML
  (``joint_limits: {<joint>: {max_acceleration: ..}}``): the one given, else ``<urdf stem>.yaml`` or
  ``joint_limits.yaml`` beside the URDF file; a joint without one gets ``ACC_PER_VEL`` x its velocity limit.
* a 7-joint chain with a spherical shoulder, a revolute elbow and a spherical wrist (axes 1-2-3 meet in
  one point, axes 5-6-7 meet in one point, axis 4 meets axis 3 and axis 5 at right angles, consecutive
  axes perpendicular; all within ``tol``) is mapped onto the canonical swivel model of
  :mod:`.swivel` (axes z,y,z,y,z,y,z, zero pose straight up): ``fk(q) = B @ fk_c(q_c) @ E`` with a fixed
  base transform B, a fixed tool transform E and ``q_c = sign * (q - offset)`` per joint. The closed-form
  IK, the feasible swivel intervals and the nearest solution then work on the URDF's own joint values.
  Where the mapping is the identity (the bundled arms' own URDFs) the model is a plain :class:`SwivelArm`.
* any other chain is a generic :class:`~.model.Arm` (numeric IK, :mod:`.numeric`) and carries one line
  saying why it is not the closed form (``arm.config["closed_form_refused"]``).

``arm.config["ik_solver"]`` names the solver in every case. No ROS here; parsing is ``xml.etree``.
Units: m, rad, rad/s, rad/s^2.
"""

from __future__ import annotations

import dataclasses
import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.obstacles import ArmCapsules
from redarm_ros.kinematics.model import ANGLE_RANGE, Arm, Joint, check_finite_array, transform_from_xyz_rpy
from redarm_ros.kinematics.numeric import solve_dls_multistart
from redarm_ros.kinematics.quaternion import rotation_error
from redarm_ros.kinematics.result import IKBatchResult, IKInfo, IKStatus
from redarm_ros.kinematics.swivel import SwivelArm, swivel_chain
from redarm_ros.yaml_safe import safe_load

__all__ = [
    "ACC_PER_VEL",
    "CONTINUOUS_RANGE",
    "STRUCTURE_TOL",
    "MappedSwivelArm",
    "NumericChainArm",
    "SwivelMap",
    "UrdfJoint",
    "chain_between",
    "chain_links",
    "load_urdf_arm",
    "parse_urdf",
    "read_urdf_text",
    "describe_solver",
    "swivel_map",
    "urdf_collision_points",
]

STRUCTURE_TOL = 1e-6  # m and rad: how far axes may miss a common point / a right angle for the closed form
CONTINUOUS_RANGE = 2.0 * math.pi  # rad: the range given to a continuous joint (+-; one turn each way)
ACC_PER_VEL = 2.0  # 1/s: max_acc = this x max_vel where no acceleration limit is given (as the PA10 YAML)
_IDENT_TOL = 1e-12  # a mapping this close to the identity is the identity (plain SwivelArm)

SOLVER_SWIVEL = "closed-form swivel IK"
SOLVER_NUMERIC = "numeric IK (damped least squares)"


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF ``<joint>``: origin (4x4 parent link -> joint frame), unit axis, limits (rad, rad/s)."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    lower: float | None
    upper: float | None
    velocity: float | None


def read_urdf_text(source: str | os.PathLike[str]) -> tuple[str, Path | None]:
    """(XML text, its file or None): ``source`` is URDF text (starts with '<') or a file path."""
    if isinstance(source, str) and source.lstrip().startswith("<"):
        return source, None
    path = Path(source)
    try:
        return path.read_text(encoding="utf-8"), path
    except OSError as exc:
        raise ConfigError(f"cannot read URDF {str(path)!r}: {exc}", field="urdf", value=str(source)) from exc


def _floats(text: str | None, count: int, default: Sequence[float], where: str) -> list[float]:
    if text is None:
        return list(default)
    try:
        vals = [float(v) for v in text.split()]
    except ValueError as exc:
        raise ConfigError(f"{where}: {text!r} is not {count} numbers", field="urdf") from exc
    if len(vals) != count or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"{where}: {text!r} is not {count} finite numbers", field="urdf")
    return vals


def _opt_float(el: ET.Element | None, key: str, where: str) -> float | None:
    if el is None or el.get(key) is None:
        return None
    try:
        v = float(el.get(key, ""))
    except ValueError as exc:
        raise ConfigError(f"{where}: {key}={el.get(key)!r} is not a number", field="urdf") from exc
    if not math.isfinite(v):
        raise ConfigError(f"{where}: {key} must be finite", field="urdf")
    return v


def parse_urdf(text: str) -> tuple[str, dict[str, UrdfJoint]]:
    """(robot name, joints by child link) of URDF text. Raises :class:`ConfigError` for malformed XML,
    xacro that was not expanded, or a joint without parent / child."""
    if "xacro:" in text:
        raise ConfigError(
            "the URDF still holds xacro macros: expand it first (xacro FILE > robot.urdf)", field="urdf"
        )
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ConfigError(f"URDF is not well-formed XML: {exc}", field="urdf") from exc
    if root.tag != "robot":
        raise ConfigError(f"URDF root element is <{root.tag}>, not <robot>", field="urdf")
    by_child: dict[str, UrdfJoint] = {}
    for el in root.findall("joint"):
        name = el.get("name", "?")
        where = f"URDF joint {name!r}"
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None or not parent.get("link") or not child.get("link"):
            raise ConfigError(f"{where} needs <parent link=..> and <child link=..>", field="urdf")
        org = el.find("origin")
        xyz = _floats(None if org is None else org.get("xyz"), 3, (0, 0, 0), f"{where} origin xyz")
        rpy = _floats(None if org is None else org.get("rpy"), 3, (0, 0, 0), f"{where} origin rpy")
        ax_el = el.find("axis")
        ax = np.array(_floats(None if ax_el is None else ax_el.get("xyz"), 3, (1, 0, 0), f"{where} axis"))
        nrm = float(np.linalg.norm(ax))
        jtype = el.get("type", "")
        if jtype in ("revolute", "continuous", "prismatic") and nrm < 1e-9:
            raise ConfigError(f"{where} has a zero axis", field="urdf")
        lim = el.find("limit")
        by_child[child.get("link", "")] = UrdfJoint(
            name,
            jtype,
            parent.get("link", ""),
            child.get("link", ""),
            transform_from_xyz_rpy(xyz, rpy),
            ax / nrm if nrm > 0 else ax,
            _opt_float(lim, "lower", where),
            _opt_float(lim, "upper", where),
            _opt_float(lim, "velocity", where),
        )
    return root.get("name", "robot"), by_child


def chain_between(by_child: dict[str, UrdfJoint], base_link: str, tip_link: str) -> list[UrdfJoint]:
    """The joints from ``base_link`` down to ``tip_link`` (base first). Raises :class:`ConfigError` if the
    tip does not hang below the base."""
    links = set(by_child) | {j.parent for j in by_child.values()}
    for what, link in (("base_link", base_link), ("tip_link", tip_link)):
        if link not in links:
            raise ConfigError(
                f"{what} {link!r} is not a link of the URDF (links: {', '.join(sorted(links))})",
                field=what,
                value=link,
            )
    out: list[UrdfJoint] = []
    link = tip_link
    while link != base_link:
        j = by_child.get(link)
        if j is None:
            raise ConfigError(
                f"tip_link {tip_link!r} is not below base_link {base_link!r} in the URDF tree",
                field="tip_link",
                value=tip_link,
            )
        out.append(j)
        link = j.parent
        if len(out) > len(by_child):
            raise ConfigError("the URDF's joints form a loop", field="urdf")
    return out[::-1]


def chain_links(chain: list[UrdfJoint], base_link: str) -> list[tuple[str, int, np.ndarray]]:
    """The URDF links of a chain (:func:`chain_between`) with the model link each is rigid with: (link,
    model link index, 4x4 transform from that model link's frame to the URDF link's). Model link 0 is the
    base, i the child of the i-th moving joint; a link hanging from fixed joints belongs to the link it is
    fixed to."""
    out = [(base_link, 0, np.eye(4))]
    k, T = 0, np.eye(4)
    for j in chain:
        k, T = (k, T @ j.origin) if j.type == "fixed" else (k + 1, np.eye(4))
        out.append((j.child, k, T))
    return out


def _mesh_vertices(path: Path, scale: np.ndarray) -> np.ndarray | None:
    """(k, 3) vertices of an OBJ or STL (ASCII or binary) mesh file, scaled; None for other formats or an
    unreadable file."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    suffix = path.suffix.lower()
    pts: Any = None
    if suffix == ".obj":
        pts = [ln.split()[1:4] for ln in data.decode("utf-8", "replace").splitlines() if ln.startswith("v ")]
    elif suffix == ".stl" and data[:5] == b"solid" and b"vertex" in data[:4096]:
        pts = [ln.split()[1:4] for ln in data.decode("utf-8", "replace").splitlines()
               if ln.strip().startswith("vertex")]
    elif suffix == ".stl" and len(data) >= 84:
        count = int(np.frombuffer(data, "<u4", 1, 80)[0])
        if len(data) < 84 + 50 * count:
            return None
        rec = np.frombuffer(data, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), count, 84)
        pts = rec["v"].reshape(-1, 3)
    try:
        V = np.asarray(pts, dtype=float).reshape(-1, 3)
    except (TypeError, ValueError):
        return None
    return V * scale if len(V) and np.all(np.isfinite(V)) else None


def urdf_collision_points(
    source: str | os.PathLike[str], base_link: str, tip_link: str
) -> dict[int, tuple[np.ndarray, np.ndarray] | None]:
    """The collision geometry of a URDF chain by model link index (:func:`chain_links`): (points (k, 3) in
    the model link's frame, pads (k,)), each geometry within ``pad`` of its points: a sphere its centre
    (pad its radius), a cylinder its two end centres (pad its radius), a box its corners, a mesh (OBJ or
    STL, relative to the URDF file, ``file://`` or absolute) its vertices. None for a link with geometry
    that cannot be read (another mesh format, a missing file); links without collision geometry are
    absent."""
    text, path = read_urdf_text(source)
    _, by_child = parse_urdf(text)
    links = {el.get("name"): el for el in ET.fromstring(text).findall("link")}
    base_dir = None if path is None else path.resolve().parent
    out: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
    for name, k, T in chain_links(chain_between(by_child, base_link, tip_link), base_link):
        el = links.get(name)
        for col in [] if el is None else el.findall("collision"):
            shape = col.find("geometry/*")
            if shape is None:
                continue
            org = col.find("origin")
            where = f"URDF link {name!r} collision origin"
            xyz = _floats(None if org is None else org.get("xyz"), 3, (0, 0, 0), where)
            rpy = _floats(None if org is None else org.get("rpy"), 3, (0, 0, 0), where)
            G = T @ transform_from_xyz_rpy(xyz, rpy)
            local, pad = _geometry_points(shape, base_dir, f"URDF link {name!r} collision")
            if local is None or k in out and out[k] is None:
                out[k] = None
                continue
            pts = local @ G[:3, :3].T + G[:3, 3]
            prev = out.get(k)
            pads = np.full(len(pts), pad)
            if prev is not None:
                pts, pads = np.vstack([prev[0], pts]), np.concatenate([prev[1], pads])
            out[k] = (pts, pads)
    return out


def _geometry_points(shape: ET.Element, base_dir: Path | None, where: str) -> tuple[np.ndarray | None, float]:
    """(points (k, 3) in the geometry's frame, pad (m)) of one URDF geometry element (see
    :func:`urdf_collision_points`); (None, 0) where it cannot be read."""
    if shape.tag == "sphere":
        return np.zeros((1, 3)), _opt_float(shape, "radius", where) or 0.0
    if shape.tag == "cylinder":
        half = 0.5 * (_opt_float(shape, "length", where) or 0.0)
        return np.array([[0.0, 0.0, -half], [0.0, 0.0, half]]), _opt_float(shape, "radius", where) or 0.0
    if shape.tag == "box":
        size = np.array(_floats(shape.get("size"), 3, (0, 0, 0), f"{where} box size"))
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        return corners * size / 2.0, 0.0
    if shape.tag == "mesh":
        name = shape.get("filename", "")
        f = Path(name[len("file://"):]) if name.startswith("file://") else Path(name)
        if not f.is_absolute():
            if base_dir is None or name.startswith("package://"):
                return None, 0.0
            f = base_dir / f
        scale = np.array(_floats(shape.get("scale"), 3, (1, 1, 1), f"{where} mesh scale"))
        return _mesh_vertices(f, scale), 0.0
    return None, 0.0


def _acc_limits(path: Path | None, limits_yaml: str | os.PathLike[str] | None) -> dict[str, dict[str, Any]]:
    """The ``joint_limits`` mapping of the limits YAML (given, or found beside the URDF), or {}."""
    cands: list[Path] = []
    if limits_yaml is not None:
        cands = [Path(limits_yaml)]
        if not cands[0].is_file():
            raise ConfigError(f"joint limits file {str(limits_yaml)!r} does not exist", field="limits_yaml")
    elif path is not None:
        cands = [p for p in (path.with_suffix(".yaml"), path.parent / "joint_limits.yaml") if p.is_file()]
    if not cands:
        return {}
    try:
        data = safe_load(cands[0].read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read joint limits {str(cands[0])!r}: {exc}", field="limits_yaml") from exc
    lim = data.get("joint_limits", {}) if isinstance(data, dict) else None
    if not isinstance(lim, dict):
        raise ConfigError(
            f"{str(cands[0])!r}: joint_limits must be a mapping joint -> limits", field="limits_yaml"
        )
    return lim


def _joints(
    urdf_chain: list[UrdfJoint], acc: dict[str, dict[str, Any]], overrides: dict[str, Any]
) -> tuple[list[Joint], np.ndarray]:
    """Model joints (fixed joints folded into the next origin) and the tool transform (last joint -> tip)."""
    pending = np.eye(4)
    out: list[Joint] = []
    for j in urdf_chain:
        if j.type == "fixed":
            pending = pending @ j.origin
            continue
        if j.type == "prismatic":
            raise ConfigError(
                f"joint {j.name!r} is prismatic: only revolute chains are modelled here",
                field="urdf",
                value=j.name,
            )
        if j.type not in ("revolute", "continuous"):
            raise ConfigError(
                f"joint {j.name!r} has type {j.type!r} (revolute, continuous, fixed)",
                field="urdf",
                value=j.name,
            )
        extra = acc.get(j.name) or {}
        if j.type == "continuous":
            lo, up = -CONTINUOUS_RANGE, CONTINUOUS_RANGE
        elif j.lower is None or j.upper is None or not j.lower <= j.upper:
            raise ConfigError(
                f"revolute joint {j.name!r} needs <limit lower=.. upper=..> with lower <= upper",
                field="urdf",
                value=j.name,
            )
        else:
            lo, up = j.lower, j.upper
        vel = j.velocity if j.velocity and j.velocity > 0 else extra.get("max_velocity")
        if vel is None or not float(vel) > 0:
            raise ConfigError(
                f"joint {j.name!r} has no positive velocity limit (URDF <limit velocity=..> "
                "or max_velocity in the joint limits YAML)",
                field="urdf",
                value=j.name,
            )
        a = extra.get("max_acceleration") if extra.get("has_acceleration_limits", True) else None
        a = float(a) if a is not None and float(a) > 0 else ACC_PER_VEL * float(vel)
        out.append(Joint(j.name, pending @ j.origin, j.axis.copy(), lo, up, float(vel), a))
        pending = np.eye(4)
    if not out:
        raise ConfigError("the chain between base_link and tip_link has no moving joint", field="urdf")
    for key in ("lower", "upper", "max_vel", "max_acc"):
        if key in overrides:
            vals = check_finite_array(overrides[key], key, (len(out),))
            out = [dataclasses.replace(jt, **{key: float(v)}) for jt, v in zip(out, vals, strict=True)]
    return out, pending


# ------------------------------------------------------------------ structure of the chain
def _line_gap(p1: np.ndarray, a1: np.ndarray, p2: np.ndarray, a2: np.ndarray) -> tuple[float, np.ndarray]:
    """(distance between two lines, the midpoint of their common perpendicular); parallel lines: the
    distance of p2 from line 1 and p2's foot on it."""
    c = np.cross(a1, a2)
    sn = float(np.linalg.norm(c))
    d = p2 - p1
    if sn < 1e-9:
        foot = p1 + float(d @ a1) * a1
        return float(np.linalg.norm(p2 - foot)), foot
    b = float(a1 @ a2)
    t1 = (float(d @ a1) - b * float(d @ a2)) / (sn * sn)
    t2 = (b * float(d @ a1) - float(d @ a2)) / (sn * sn)
    x1, x2 = p1 + t1 * a1, p2 + t2 * a2
    return float(np.linalg.norm(x1 - x2)), 0.5 * (x1 + x2)


def _off_line(x: np.ndarray, p: np.ndarray, a: np.ndarray) -> float:
    d = x - p
    return float(np.linalg.norm(d - float(d @ a) * a))


def _turn(v: np.ndarray, target: np.ndarray, axis: np.ndarray) -> float:
    """Angle (rad) of the rotation about unit ``axis`` taking v (normal to the axis) to target's direction."""
    return math.atan2(float(np.cross(v, target) @ axis), float(v @ target))


@dataclass(frozen=True)
class SwivelMap:
    """How a URDF chain maps onto the canonical swivel model: ``fk(q) = base @ fk_c(q_c) @ tool`` with
    ``q_c = sign * (q - offset)``; link lengths L1..L4 (m); ``deviation`` the largest FK difference
    (m, or rad for the orientation) between the chain and the mapped model over sampled postures."""

    link_lengths: tuple[float, float, float, float]
    base: np.ndarray
    tool: np.ndarray
    sign: np.ndarray
    offset: np.ndarray
    deviation: float

    @property
    def identity(self) -> bool:
        """True where the chain is the canonical model itself (no transform, sign or offset)."""
        return bool(
            np.all(self.sign > 0)
            and np.abs(self.offset).max() <= _IDENT_TOL
            and np.abs(self.base - np.eye(4)).max() <= _IDENT_TOL
            and np.abs(self.tool - np.eye(4)).max() <= _IDENT_TOL
        )


def swivel_map(
    chain_arm: Arm, tol: float = STRUCTURE_TOL, base_point: Sequence[float] | None = None
) -> SwivelMap | str:
    """The mapping of a chain onto the canonical swivel model, or one line saying why there is none.

    Checks, at the zero posture (the relations are invariant under the joint motion): 7 joints;
    consecutive axes perpendicular; axes 1 and 2 meet (shoulder S) and axis 3 passes through S; axes 3 and
    4 meet (elbow E, no elbow offset) away from S; axes 5 and 6 meet (wrist W), axis 7 passes through W
    and axis 5 through E (no wrist offset). Distances within ``tol`` m, right angles within ``tol`` rad.
    """
    if chain_arm.n != 7:
        return f"{chain_arm.n} joints: the closed form needs 7 (spherical shoulder, elbow, spherical wrist)"
    q = np.zeros(7)
    _, P, A = chain_arm.fk_axes(q)
    problems = []
    for i in range(6):
        ang = abs(math.asin(min(1.0, abs(float(A[i] @ A[i + 1])))))
        if ang > tol:
            problems.append(
                f"axes {i + 1} and {i + 2} are not perpendicular ({math.degrees(ang):.4g} deg off)"
            )
    g12, S = _line_gap(P[0], A[0], P[1], A[1])
    g34, E = _line_gap(P[2], A[2], P[3], A[3])
    g56, W = _line_gap(P[4], A[4], P[5], A[5])
    # a point's test only where the point exists (its two axes meet): the line names causes, not echoes
    for gap, what, needs in (
        (g12, "axes 1 and 2 do not meet (shoulder)", 0.0),
        (_off_line(S, P[2], A[2]), "axis 3 misses the shoulder point of axes 1-2", g12),
        (g34, "axes 3 and 4 do not meet (elbow offset)", 0.0),
        (g56, "axes 5 and 6 do not meet (wrist)", 0.0),
        (_off_line(W, P[6], A[6]), "axis 7 misses the wrist point of axes 5-6 (wrist offset)", g56),
        (_off_line(E, P[4], A[4]), "axis 5 misses the elbow point of axes 3-4 (forearm offset)", g34),
    ):
        if gap > tol and needs <= tol:
            problems.append(f"{what} by {gap:.4g} m")
    L2, L3 = float(np.linalg.norm(E - S)), float(np.linalg.norm(W - E))
    if not problems and min(L2, L3) <= tol:
        problems.append(f"no upper arm or forearm (shoulder-elbow {L2:.4g} m, elbow-wrist {L3:.4g} m)")
    if problems:
        return "; ".join(problems) + f" (tolerance {tol:g})"
    # canonical base: origin on axis 1 at the foot of the URDF base origin, z from there to the shoulder
    bp = np.zeros(3) if base_point is None else np.asarray(base_point, dtype=float)
    origin = P[0] + float((bp - P[0]) @ A[0]) * A[0]
    L1 = float(np.linalg.norm(S - origin))
    z = (S - origin) / L1 if L1 > tol else A[0].copy()
    L1 = L1 if L1 > tol else 0.0
    sign, offset = np.ones(7), np.zeros(7)
    sign[0] = 1.0 if A[0] @ z > 0 else -1.0
    y = A[1] - float(A[1] @ z) * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    B = np.eye(4)
    B[:3, 0], B[:3, 1], B[:3, 2], B[:3, 3] = x, y, z, origin

    def nearer(v: np.ndarray, axis: np.ndarray, target: np.ndarray) -> float:
        a, b = _turn(v, target, axis), _turn(v, -target, axis)
        return a if abs(a) <= abs(b) else b

    tip = chain_arm.fk(q)[:3, 3]
    for i in range(1, 7):
        _, P, A = chain_arm.fk_axes(q)
        tip = chain_arm.fk(q)[:3, 3]
        a = A[i]
        want = y if i % 2 else z  # the direction axis i has in the canonical zero pose
        sign[i] = 1.0 if A[i] @ want > 0 else -1.0
        if i in (1, 3):  # shoulder / elbow pitch: turn the next link to point along +z
            _, E_now = _line_gap(P[2], A[2], P[3], A[3])
            _, W_now = _line_gap(P[4], A[4], P[5], A[5])
            link = (E_now - S) if i == 1 else (W_now - E_now)
            offset[i] = _turn(link - float(link @ a) * a, z, a)
        elif i == 5:  # wrist pitch: the tool's reach along axis 7 points along +z where it has one
            _, W_now = _line_gap(P[4], A[4], P[5], A[5])
            along = float((tip - W_now) @ A[6])
            v = A[6] * (1.0 if along >= 0 else -1.0)
            offset[i] = _turn(v, z, a) if abs(along) > tol else nearer(A[6], a, z)
        elif i in (2, 4):  # rolls: the next pitch axis onto +-y, whichever is nearer
            offset[i] = nearer(A[i + 1], a, y)
        q[i] = offset[i]
    _, P, A = chain_arm.fk_axes(q)
    tip = chain_arm.fk(q)[:3, 3]
    sign[6] = 1.0 if A[6] @ z > 0 else -1.0
    _, W_now = _line_gap(P[4], A[4], P[5], A[5])
    L4 = max(0.0, float((tip - W_now) @ z))
    L4 = L4 if L4 > tol else 0.0
    lengths = (L1, L2, L3, L4)
    Tc0 = np.eye(4)
    Tc0[2, 3] = sum(lengths)
    Etool = np.linalg.inv(B @ Tc0) @ chain_arm.fk(offset)
    Etool[3] = (0.0, 0.0, 0.0, 1.0)
    canon = _canonical(lengths, [(f"c{i}", -math.pi, math.pi, 1.0, 1.0) for i in range(7)])
    rng = np.random.default_rng(0)
    dev = 0.0
    for qs in rng.uniform(-math.pi, math.pi, (32, 7)):
        Tu = chain_arm.fk(qs)
        Tm = B @ canon.fk(sign * (qs - offset)) @ Etool
        dev = max(
            dev,
            float(np.abs(Tu[:3, 3] - Tm[:3, 3]).max()),
            float(np.linalg.norm(rotation_error(Tm[:3, :3], Tu[:3, :3]))),
        )
    if dev > 10.0 * tol + 1e-9:
        return f"the chain does not map onto the swivel model (FK differs by {dev:.3g})"
    return SwivelMap(lengths, B, Etool, sign, offset, dev)


def _canonical(
    lengths: Sequence[float],
    limits: Sequence[tuple[str, float, float, float, float]],
    name: str = "canonical",
    config: dict[str, Any] | None = None,
) -> SwivelArm:
    chain, tool = swivel_chain(lengths, limits)
    cfg = dict(config or {})
    cfg["link_lengths"] = list(lengths)
    cfg.setdefault("kind", "swivel7")
    cfg.setdefault("name", name)
    return SwivelArm(name, chain, tool, (1, 3, 5), cfg)


# ------------------------------------------------------------------ the numeric chain
class NumericChainArm(Arm):
    """A URDF chain without a closed form: :meth:`ik_nearest` is :func:`.numeric.solve_dls_multistart`
    (the seed and 31 random starts descending together, TRAC-IK style), within the time budget: the first
    within ``tol`` (m, rad), the nearest the seed of those converging together."""

    def _solve_numeric(
        self, T: np.ndarray, seed: np.ndarray, **options: Any
    ) -> tuple[np.ndarray | None, IKInfo]:
        return solve_dls_multistart(self, T, seed, **options)


# ------------------------------------------------------------------ the mapped swivel arm
class MappedSwivelArm(Arm):
    """A 7-DOF spherical-shoulder / spherical-wrist arm in its own (URDF) frames and joint values, solved
    by the canonical swivel model ``self.canonical``: ``fk(q) = base @ canonical.fk(q_c) @ tool_map`` with
    ``q_c = sign * (q - offset)``. FK, frames and Jacobian come from the URDF chain itself; ``ik``,
    ``ik_u``, ``ik_batch``, ``ik_nearest`` (the global optimum: the map keeps joint distances),
    ``ik_nearest_batch``, ``swivel``, ``elbow_circle`` (in this arm's base frame), ``feasible_swivels``
    and ``swivel_interval`` answer as the canonical model's do, in this arm's joint values.
    """

    kind = "swivel7_urdf"
    has_swivel = True

    def __init__(
        self, name: str, chain: Sequence[Joint], tool: np.ndarray, config: dict[str, Any], smap: SwivelMap
    ) -> None:
        self.map = smap
        self._sign, self._offset = smap.sign.copy(), smap.offset.copy()
        self._B, self._E = smap.base.copy(), smap.tool.copy()
        self._Binv, self._Einv = np.linalg.inv(smap.base), np.linalg.inv(smap.tool)
        eye = np.eye(4)
        # folded once here so that ik_nearest does no mapping it can skip: frames that are the model's
        # (the pose goes through as it is), zero offsets (sign * q_c is exact: no clip onto the limits),
        # a tool map without translation (a rigid map of the pose: the model's errors are this arm's)
        self._frames_identity = bool(
            np.abs(smap.base - eye).max() <= _IDENT_TOL and np.abs(smap.tool - eye).max() <= _IDENT_TOL
        )
        self._offset_zero = not np.any(smap.offset)
        self._errors_kept = bool(np.abs(smap.tool[:3, 3]).max() <= _IDENT_TOL)
        lims = []
        for j, s, o in zip(chain, self._sign, self._offset, strict=True):
            a, b = s * (j.lower - o), s * (j.upper - o)
            lims.append((j.name, min(a, b), max(a, b), j.max_vel, j.max_acc))
        self.canonical = _canonical(smap.link_lengths, lims, f"{name}_canonical")
        self.link_lengths = smap.link_lengths
        super().__init__(name, chain, tool, (1, 3, 5), config)

    # ---- the map
    def to_canonical(self, T: Any) -> np.ndarray:
        """Pose T (4x4, this arm's base -> tool) in the canonical model's frames: base^-1 T tool_map^-1."""
        return self._Binv @ np.array(self.check_pose(T)) @ self._Einv

    def _q(self, Qc: np.ndarray, clip: bool = True) -> np.ndarray:
        """This arm's joint values of canonical ones; ``clip``: onto the limits, which the canonical ones
        keep exactly but sign * q + offset may miss by round-off (NaN stays NaN)."""
        Q = Qc * self._sign + self._offset
        return np.clip(Q, self.lower, self.upper) if clip else Q

    def _qc(self, q: np.ndarray) -> np.ndarray:
        return (q - self._offset) * self._sign

    def to_canonical_q(self, q: Any) -> np.ndarray:
        """The canonical model's joint values (rad) of this arm's q ((n,) or (k, n)): sign * (q - offset)."""
        return self._qc(np.asarray(q, dtype=float))

    def from_canonical_q(self, q_c: Any) -> np.ndarray:
        """This arm's joint values (rad) of canonical ones, clipped onto the limits against round-off."""
        return self._q(np.asarray(q_c, dtype=float))

    @property
    def frames_are_canonical(self) -> bool:
        """True where base and tool frames are the model's own (only joint signs and offsets differ)."""
        return self._frames_identity

    @property
    def shoulder(self) -> np.ndarray:
        """Shoulder point (m, this arm's base frame)."""
        return self._B[:3, :3] @ self.canonical.shoulder + self._B[:3, 3]

    def wrist_point(self, T: np.ndarray) -> np.ndarray:
        """The wrist point (m, base frame) that pose T fixes."""
        Tc = self.to_canonical(T)
        return self._B[:3, :3] @ (Tc[:3, 3] - self.link_lengths[3] * Tc[:3, 2]) + self._B[:3, 3]

    def key_points(self, q: Sequence[float]) -> np.ndarray:
        """(5, 3): base (on axis 1), shoulder, elbow, wrist, tool (m, base frame): the joint centres."""
        qa = self.check_q(q)
        kc = self.canonical.key_points(self._qc(qa))
        pts = kc @ self._B[:3, :3].T + self._B[:3, 3]  # (the base point: the foot of axis 1)
        pts[4] = self.fk(qa)[:3, 3]
        return pts

    # ---- closed form in this arm's joint values
    def ik(
        self, T: np.ndarray, swivel: float | None = 0.0, *, all_copies: bool = False, limits: bool = True
    ) -> np.ndarray:
        """:meth:`SwivelArm.ik` in this arm's frames and joint values (rows in the same order)."""
        rows = self.canonical.ik(self.to_canonical(T), swivel, all_copies=all_copies, limits=limits)
        return self._q(rows, clip=limits is True)

    def ik_u(self, T: np.ndarray, u: Sequence[float], *, all_copies: bool = False) -> np.ndarray:
        """:meth:`SwivelArm.ik_u` in this arm's frames and joint values."""
        return self._q(self.canonical.ik_u(self.to_canonical(T), u, all_copies=all_copies))

    def ik_batch(
        self, Ts: np.ndarray, swivels: Any = 0.0, *, chunk: int = 2048
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`SwivelArm.ik_batch` in this arm's frames and joint values (NaN rows stay NaN)."""
        Tc = self._Binv @ self.check_poses(Ts) @ self._Einv
        Q, valid = self.canonical.ik_batch(Tc, swivels, chunk=chunk)
        return self._q(Q), valid

    def ik_nearest(
        self, T: np.ndarray, q_seed: Sequence[float], **kwargs: Any
    ) -> tuple[np.ndarray | None, IKInfo]:
        """:meth:`SwivelArm.ik_nearest` (same options). The errors in the info are the canonical model's
        where the tool map has no translation (the map is rigid: the same errors, to ``map.deviation``),
        else against this arm's FK."""
        try:
            Tl = self.check_pose(T)
            seed = self.check_q(q_seed, "q_seed")
        except InvalidInputError as exc:
            return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
        Ta = np.array(Tl)  # (the model checks an array much faster than nested lists)
        Tc = Ta if self._frames_identity else self._Binv @ Ta @ self._Einv
        qc, info = self.canonical.ik_nearest(Tc, self._qc(seed), **kwargs)
        if qc is None:
            return None, info
        q = self._q(qc, clip=not self._offset_zero)
        if self._errors_kept:
            return q, info
        pe, re = self.pose_error(q, T)
        return q, dataclasses.replace(info, pos_err=pe, rot_err=re)

    def ik_nearest_batch(self, Ts: np.ndarray, q_seeds: Any, **kwargs: Any) -> IKBatchResult:
        """:meth:`SwivelArm.ik_nearest_batch` in this arm's frames and joint values."""
        Tc = self._Binv @ self.check_poses(Ts) @ self._Einv
        seeds = check_finite_array(q_seeds, "q_seeds", None, ANGLE_RANGE)
        out = self.canonical.ik_nearest_batch(Tc, self._qc(seeds), **kwargs)
        out.q = self._q(out.q)
        return out

    def swivel(self, q: Sequence[float]) -> float:
        """Swivel angle (rad) of q: the canonical model's of the mapped joint values."""
        return self.canonical.swivel(self._qc(self.check_q(q)))

    def swivel_u(self, q: Sequence[float]) -> np.ndarray:
        """Swivel quaternion u of q as its vector part (x, y, z), z = 0."""
        s = self.swivel(q)
        return np.array([math.cos(s), math.sin(s), 0.0])

    def elbow_circle(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(C, n, rho) of the elbow circle in this arm's base frame (m)."""
        C, n, rho = self.canonical.elbow_circle(self.to_canonical(T))
        R = self._B[:3, :3]
        return R @ C + self._B[:3, 3], R @ n, rho

    def swivel_functions(self, T: np.ndarray) -> Any:
        """The canonical model's closed-form joint functions of pose T (canonical joint values)."""
        return self.canonical.swivel_functions(self.to_canonical(T))

    def feasible_swivels(self, T: np.ndarray) -> list[np.ndarray]:
        """:meth:`SwivelArm.feasible_swivels` (the swivel is the canonical model's, so are the intervals)."""
        return self.canonical.feasible_swivels(self.to_canonical(T))

    def swivel_interval(self, q: Sequence[float]) -> tuple[float, float] | None:
        """:meth:`SwivelArm.swivel_interval` of q."""
        return self.canonical.swivel_interval(self._qc(self.check_q(q)))


def load_urdf_arm(
    source: str | os.PathLike[str],
    base_link: str,
    tip_link: str,
    *,
    name: str | None = None,
    limits_yaml: str | os.PathLike[str] | None = None,
    tol: float = STRUCTURE_TOL,
    closed_form: bool = True,
    **overrides: Any,
) -> Arm:
    """The model of the URDF chain ``base_link`` -> ``tip_link`` (see the module docstring).

    ``source``: URDF file path or XML text. ``limits_yaml``: MoveIt-style joint limits file (acceleration
    limits); default ``<stem>.yaml`` or ``joint_limits.yaml`` beside the file. ``tol``: the structure
    tolerance (m, rad). ``closed_form=False`` builds the numeric model even for a swivel chain.
    Overrides: ``lower``, ``upper``, ``max_vel``, ``max_acc`` (one value per joint), ``park``.
    Raises :class:`ConfigError` for an unreadable or malformed URDF, unknown links or a chain that
    cannot be modelled.
    """
    unknown = set(overrides) - {"lower", "upper", "max_vel", "max_acc", "park"}
    if unknown:
        raise ConfigError(f"unknown override(s) {sorted(unknown)} for a URDF arm", field=sorted(unknown)[0])
    text, path = read_urdf_text(source)
    robot, by_child = parse_urdf(text)
    urdf_chain = chain_between(by_child, base_link, tip_link)
    joints, tool = _joints(urdf_chain, _acc_limits(path, limits_yaml), overrides)
    mount = np.eye(4)  # the link joint 1 hangs from: the fixed joints before it
    for j in urdf_chain:
        if j.type != "fixed":
            break
        mount = mount @ j.origin
    arm_name = name or robot
    cfg: dict[str, Any] = {
        "name": arm_name,
        "urdf": str(path) if path is not None else "(text)",
        "base_link": base_link,
        "tip_link": tip_link,
    }
    if overrides.get("park") is not None:
        park = check_finite_array(overrides["park"], "park", (len(joints),))
        if np.any(park < [j.lower for j in joints]) or np.any(park > [j.upper for j in joints]):
            raise ConfigError("park is outside the joint limits", field="park", value=park.tolist())
        cfg["park"] = park.tolist()
    n = len(joints)
    generic = NumericChainArm(
        arm_name, joints, tool, [min(1, n - 1), min(n // 2, n - 1), max(n - 2, 0)], dict(cfg, kind="chain")
    )
    smap = (
        swivel_map(generic, tol, mount[:3, 3])
        if closed_form
        else "closed form switched off (closed_form=False)"
    )
    if isinstance(smap, str):
        generic.config["ik_solver"] = SOLVER_NUMERIC
        generic.config["closed_form_refused"] = smap
        return generic
    cfg.update(
        kind="swivel7",
        ik_solver=SOLVER_SWIVEL,
        link_lengths=list(smap.link_lengths),
        structure_deviation=smap.deviation,
    )
    if smap.identity:  # the chain is the canonical model: the plain model, with every consumer's support
        return _canonical(
            smap.link_lengths,
            [(j.name, j.lower, j.upper, j.max_vel, j.max_acc) for j in joints],
            arm_name,
            cfg,
        )
    cfg["kind"] = MappedSwivelArm.kind
    return MappedSwivelArm(arm_name, joints, tool, cfg, smap)


def describe_solver(arm: Any) -> str:
    """One line naming the IK solver of ``arm`` (and, for a numeric URDF chain, why not the closed form)."""
    cfg = getattr(arm, "config", {}) or {}
    if cfg.get("closed_form_refused"):
        return f"{SOLVER_NUMERIC}: not closed form because {cfg['closed_form_refused']}"
    if getattr(arm, "has_swivel", False) is True:
        return SOLVER_SWIVEL
    if getattr(arm, "kind", "") == "powercube6":
        return "closed-form PowerCube 6-DOF IK"
    return SOLVER_NUMERIC


#: The model links each capsule is rigid with on a 7-joint swivel arm: the base and joint 1's link carry
#: the base capsule (joint 1 turns about it), links 2-3 the upper arm, 4-5 the forearm, 6-7 the hand.
CAPSULE_MODEL_LINKS = ((0, 1), (2, 3), (4, 5), (6, 7))


def capsules_from_urdf(arm: Any, capsules: ArmCapsules) -> ArmCapsules:
    """``capsules`` with the radii taken from the collision geometry of the URDF file a 7-joint swivel arm
    was loaded from (``arm.config["urdf"]``): the radius of a capsule is the largest distance of its links'
    geometry (:func:`urdf_collision_points`) from its segment between
    two key points. A capsule whose links have no collision geometry, or geometry that cannot be read,
    keeps its radius; so does every capsule of a bundled arm or an arm from URDF text."""
    cfg = getattr(arm, "config", None) or {}
    path = cfg.get("urdf")
    if getattr(arm, "n", 0) != 7 or not hasattr(arm, "key_points"):
        return capsules
    if not path or not Path(str(path)).is_file():
        return capsules
    try:
        geo = urdf_collision_points(str(path), str(cfg["base_link"]), str(cfg["tip_link"]))
    except (ConfigError, InvalidInputError, KeyError, ValueError):
        return capsules
    if not geo:
        return capsules
    q = (np.asarray(arm.lower, dtype=float) + np.asarray(arm.upper, dtype=float)) / 2.0  # any posture
    kp = np.asarray(arm.key_points(q))
    frames = arm.fk_frames(q)  # frames[i - 1]: model link i
    radii = list(capsules.radii)
    for c, group in enumerate(CAPSULE_MODEL_LINKS):
        found = [k for k in group if k in geo]
        if not found or any(geo[k] is None for k in found):
            continue
        a, d = kp[c], kp[c + 1] - kp[c]
        r = 0.0
        for k in found:
            pts, pads = geo[k]  # type: ignore[misc]
            F = np.eye(4) if k == 0 else frames[k - 1]
            P = pts @ F[:3, :3].T + F[:3, 3] - a
            t = np.clip(P @ d / max(float(d @ d), 1e-300), 0.0, 1.0)
            r = max(r, float((np.linalg.norm(P - t[:, None] * d, axis=1) + pads).max()))
        if r > 0.0:
            radii[c] = r
    return ArmCapsules(radii=tuple(radii), table_links=capsules.table_links,
                       obstacle_links=capsules.obstacle_links)
