"""Arms written as URDF text from published facts (no third-party URDF file is copied): the demo's and the
reach-quality benchmark's iiwa14-like arm (``redarm-demo --arm iiwa14``), and the test arms of the URDF
IK benchmark (benchmarks/urdf_ik_bench.py) and the tests.

* :func:`iiwa14_urdf`: a KUKA LBR iiwa 14-like arm: axes z, y, z, -y, z, y, z (the real robot's
  alternating pitch directions), shoulder 0.36 m above the base, upper arm 0.42 m, forearm 0.40 m,
  flange 0.126 m beyond the wrist; limits +-170, +-120, +-170, +-120, +-170, +-120, +-175 deg;
  velocity limits 85, 85, 100, 75, 130, 135, 135 deg/s (the data sheet's). ``reframed=True`` writes the
  same machine with a rotated, shifted base, every link frame turned, some axes negated and the zero
  pose bent (joint offsets): another URDF of one arm, to prove the mapping onto the swivel model general.
* :func:`franka_like_urdf`: a 7R arm from Franka Emika Panda's published (modified) DH table: elbow
  offset a = 0.0825 m, wrist offset a = 0.088 m, so neither the elbow nor the wrist is spherical.

:data:`SHIPPED` names them; :func:`load_shipped` builds the model of one (its chain ``base_link`` ->
``tool0``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from redarm_ros.errors import ConfigError
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.model import Arm, rot_axis, transform_from_xyz_rpy
from redarm_ros.sim.urdf import matrix_to_rpy

IIWA_LIMITS_DEG = (170, 120, 170, 120, 170, 120, 175)
IIWA_VEL_DEG = (85, 85, 100, 75, 130, 135, 135)
# each joint's origin height above the previous joint (m), as published for the iiwa 14: shoulder
# 0.1575 + 0.2025 = 0.36, upper arm 0.2045 + 0.2155 = 0.42, forearm 0.1845 + 0.2155 = 0.40,
# flange 0.081 + 0.045 = 0.126
IIWA_Z = (0.1575, 0.2025, 0.2045, 0.2155, 0.1845, 0.2155, 0.081)
IIWA_FLANGE = 0.045
IIWA_AXES = ((0, 0, 1), (0, 1, 0), (0, 0, 1), (0, -1, 0), (0, 0, 1), (0, 1, 0), (0, 0, 1))

# Franka Emika Panda, modified DH (a_{i-1}, d_i, alpha_{i-1}) per joint, then the flange d = 0.107
FRANKA_DH = (
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
)
FRANKA_FLANGE = 0.107
FRANKA_LIMITS = (
    (-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698),
    (-2.8973, 2.8973), (-0.0175, 3.7525), (-2.8973, 2.8973),
)  # fmt: skip
FRANKA_VEL = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)


def _origin(T: np.ndarray) -> str:
    rpy = matrix_to_rpy(T[:3, :3])
    return (
        f'<origin xyz="{" ".join(f"{v:.17g}" for v in T[:3, 3])}" '
        f'rpy="{" ".join(f"{v:.17g}" for v in rpy)}"/>'
    )


def chain_urdf(
    robot: str,
    joints: Sequence[tuple[str, np.ndarray, Sequence[float], float, float, float]],
    tool: np.ndarray,
    base: np.ndarray | None = None,
) -> str:
    """URDF text: links ``base_link`` [-> fixed ``mount`` when ``base`` is given] -> ``link_1`` .. ``link_n``
    -> fixed ``tool0``. ``joints``: (name, origin 4x4, axis, lower, upper, velocity)."""
    out = ['<?xml version="1.0"?>', f'<robot name="{robot}">', '  <link name="base_link"/>']
    parent = "base_link"
    if base is not None:
        out += [
            '  <link name="mount"/>',
            '  <joint name="mount_joint" type="fixed">',
            f'    <parent link="base_link"/><child link="mount"/>{_origin(base)}',
            "  </joint>",
        ]
        parent = "mount"
    for i, (name, T, axis, lo, up, vel) in enumerate(joints, start=1):
        out += [
            f'  <link name="link_{i}"/>',
            f'  <joint name="{name}" type="revolute">',
            f'    <parent link="{parent}"/><child link="link_{i}"/>{_origin(T)}',
            f'    <axis xyz="{" ".join(f"{v:.17g}" for v in axis)}"/>',
            f'    <limit lower="{lo:.17g}" upper="{up:.17g}" effort="100" velocity="{vel:.17g}"/>',
            "  </joint>",
        ]
        parent = f"link_{i}"
    out += [
        '  <link name="tool0"/>',
        '  <joint name="tool0_joint" type="fixed">',
        f'    <parent link="{parent}"/><child link="tool0"/>{_origin(tool)}',
        "  </joint>",
        "</robot>",
    ]
    return "\n".join(out)


def _tz(z: float) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = z
    return T


def iiwa14_urdf(reframed: bool = False) -> str:
    """The iiwa14-like arm (see the module docstring); ``reframed``: the same machine, other frames."""
    lims = [math.radians(v) for v in IIWA_LIMITS_DEG]
    joints = []
    for i in range(7):
        joints.append(
            (
                f"iiwa_joint_{i + 1}",
                _tz(IIWA_Z[i]),
                np.array(IIWA_AXES[i], float),
                -lims[i],
                lims[i],
                math.radians(IIWA_VEL_DEG[i]),
            )
        )
    tool = _tz(IIWA_FLANGE)
    if not reframed:
        return chain_urdf("iiwa14_like", joints, tool)
    rng = np.random.default_rng(7)
    frames = [np.eye(4)]  # link frame re-choices (rotations about arbitrary axes)
    for _ in range(7):
        F = np.eye(4)
        F[:3, :3] = rot_axis(_unit(rng.normal(size=3)), float(rng.uniform(-math.pi, math.pi)))
        frames.append(F)
    offsets = (0.3, -0.7, 1.1, 0.5, -0.4, 0.9, 2.0)  # rad: the new zero pose is this far from straight
    flip = (False, True, False, False, True, False, True)  # axes written the other way round
    out = []
    for i, (name, Oi, axis, lo, up, vel) in enumerate(joints):
        Fp, Fc = frames[i], frames[i + 1]
        # joint value q' = s (q + d): origin' = Fp^-1 O Rot(axis, -d) Fc, axis' = s Fc^-1 axis
        Od = Oi.copy()
        Od[:3, :3] = Od[:3, :3] @ rot_axis(axis, -offsets[i])
        s = -1.0 if flip[i] else 1.0
        a2 = s * (Fc[:3, :3].T @ axis)
        lo2, up2 = sorted((s * (lo + offsets[i]), s * (up + offsets[i])))
        out.append((name, np.linalg.inv(Fp) @ Od @ Fc, a2, lo2, up2, vel))
    base = transform_from_xyz_rpy((0.4, -0.2, 0.75), (math.pi, 0.3, -0.8))  # hanging upside down, tilted
    return chain_urdf("iiwa14_like_reframed", out, np.linalg.inv(frames[7]) @ tool, base)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def franka_like_urdf() -> str:
    """The Franka-like 7R arm (modified DH from the published table; z of each joint frame is its axis)."""
    joints = []
    for i, (a, d, alpha) in enumerate(FRANKA_DH):
        T = transform_from_xyz_rpy((a, -math.sin(alpha) * d, math.cos(alpha) * d), (alpha, 0.0, 0.0))
        lo, up = FRANKA_LIMITS[i]
        joints.append((f"panda_joint{i + 1}", T, (0.0, 0.0, 1.0), lo, up, FRANKA_VEL[i]))
    return chain_urdf("franka_like", joints, _tz(FRANKA_FLANGE))


#: The arms written here, by name: (URDF text, base link, tip link).
SHIPPED = {
    "iiwa14": (iiwa14_urdf, "base_link", "tool0"),
    "franka_like": (franka_like_urdf, "base_link", "tool0"),
}


def load_shipped(name: str) -> Arm:
    """The model of the shipped URDF arm ``name`` (a key of :data:`SHIPPED`). Raises ConfigError otherwise."""
    if name not in SHIPPED:
        known = ", ".join(SHIPPED)
        raise ConfigError(f"no shipped URDF arm {name!r} (known: {known})", field="arm", value=name)
    text, base, tip = SHIPPED[name]
    return load_arm(text(), base_link=base, tip_link=tip)
