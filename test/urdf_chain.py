"""A small URDF reader for the tests: the serial chain from the root link to a tip, and its FK.

Written from the URDF specification (joint ``origin`` = xyz + fixed-axis roll/pitch/yaw,
``R = Rz(yaw) Ry(pitch) Rx(roll)``; a revolute joint rotates its child about ``axis`` in the joint
frame), independently of :mod:`redarm_ros.sim.urdf`, so it checks the generator rather than
repeating it. :func:`check_matches_fk` compares a URDF with an arm model's ``fk``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

# Both sides are float64 maths on 17-digit text; what is left is rounding in the products.
FK_TOL = 1e-9


# Alike redarm_ros.view.urdf_model.Joint on purpose: this reader is the tests' independent oracle.
@dataclass(frozen=True)
class UrdfJoint:
    """One joint of the chain: ``name``, ``type``, ``parent``/``child`` links, ``origin`` (4x4), ``axis``."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray


def _floats(text: str | None, default: tuple[float, float, float]) -> np.ndarray:
    return np.array([float(v) for v in text.split()]) if text else np.array(default, dtype=float)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _origin(elem: ET.Element | None) -> np.ndarray:
    T = np.eye(4)
    if elem is None:
        return T
    xyz = _floats(elem.get("xyz"), (0.0, 0.0, 0.0))
    roll, pitch, yaw = _floats(elem.get("rpy"), (0.0, 0.0, 0.0))
    ex, ey, ez = np.eye(3)
    T[:3, :3] = _rot(ez, yaw) @ _rot(ey, pitch) @ _rot(ex, roll)
    T[:3, 3] = xyz
    return T


def root_link(urdf: str) -> str:
    """The one link that is no joint's child."""
    root = ET.fromstring(urdf)
    children = {j.find("child").get("link") for j in root.findall("joint")}
    roots = [lk.get("name") for lk in root.findall("link") if lk.get("name") not in children]
    assert len(roots) == 1, f"URDF has roots {roots}"
    return roots[0]


def chain(urdf: str, tip: str) -> list[UrdfJoint]:
    """Joints from the root link down to link ``tip``, root first."""
    root = ET.fromstring(urdf)
    by_child: dict[str, UrdfJoint] = {}
    for j in root.findall("joint"):
        axis = _floats(j.find("axis").get("xyz") if j.find("axis") is not None else None, (1.0, 0.0, 0.0))
        uj = UrdfJoint(j.get("name"), j.get("type"), j.find("parent").get("link"),
                       j.find("child").get("link"), _origin(j.find("origin")), axis)
        assert uj.child not in by_child, f"link {uj.child} has two parents"
        by_child[uj.child] = uj
    out: list[UrdfJoint] = []
    link = tip
    while link in by_child:
        out.append(by_child[link])
        link = by_child[link].parent
    assert link == root_link(urdf), f"{tip} does not hang off the root"
    return out[::-1]


def fk(joints: list[UrdfJoint], q: np.ndarray) -> np.ndarray:
    """Root -> tip transform for the movable joints' values ``q`` (rad, in chain order)."""
    T = np.eye(4)
    qi = iter(np.asarray(q, dtype=float))
    for j in joints:
        T = T @ j.origin
        if j.type in ("revolute", "continuous"):
            R = np.eye(4)
            R[:3, :3] = _rot(j.axis, next(qi))
            T = T @ R
        elif j.type != "fixed":
            raise AssertionError(f"joint type {j.type} not handled")
    assert next(qi, None) is None, "more joint values than movable joints"
    return T


def movable(joints: list[UrdfJoint]) -> list[str]:
    """Names of the movable joints of a chain, in order."""
    return [j.name for j in joints if j.type != "fixed"]


def check_matches_fk(urdf: str, arm_name: str, count: int = 200, seed: int = 7) -> float:
    """Assert that the URDF's base -> ``tool`` transform equals ``load_arm(arm_name).fk`` (every entry
    within FK_TOL) over ``count`` random in-limit configurations, and that its movable joints are the
    model's; return the largest difference."""
    from redarm_ros.kinematics import load_arm

    arm = load_arm(arm_name)
    joints = chain(urdf, "tool")
    assert movable(joints) == list(arm.joint_names)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(count):
        q = rng.uniform(arm.lower, arm.upper)
        worst = max(worst, float(np.abs(fk(joints, q) - arm.fk(q)).max()))
    assert worst < FK_TOL, f"{arm_name}: URDF tool differs from arm.fk by {worst:.3g}"
    return worst
