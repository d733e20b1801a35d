"""``/tf`` from joint states: one ``tf2_msgs/TFMessage`` per joint state, as robot_state_publisher
would publish it, as plain dicts for :meth:`redarm_ros.record.mcap_io.Ros2McapWriter.write_dict`.

Every URDF joint (movable ones at the given positions, fixed ones at their origin) becomes one
``geometry_msgs/TransformStamped`` parent link -> child link. If ``base_frame`` differs from the
URDF's root link, an identity transform ``base_frame -> root`` is added, so markers published in
``base_frame`` (the controller's) sit on the arm in Foxglove's 3-D panel. No ROS here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from redarm_ros.view.urdf_model import UrdfModel, matrix_to_quat_xyzw


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def transform_stamped(parent: str, child: str, T: np.ndarray, t_ns: int) -> dict[str, Any]:
    """A ``geometry_msgs/TransformStamped`` dict of the 4x4 ``T`` (parent -> child) at ``t_ns``."""
    x, y, z, w = matrix_to_quat_xyzw(T[:3, :3])
    return {
        "header": {"stamp": _stamp(t_ns), "frame_id": parent},
        "child_frame_id": child,
        "transform": {
            "translation": {"x": float(T[0, 3]), "y": float(T[1, 3]), "z": float(T[2, 3])},
            "rotation": {"x": x, "y": y, "z": z, "w": w},
        },
    }


def tf_message(model: UrdfModel, positions: Mapping[str, float], t_ns: int,
               base_frame: str | None = None) -> dict[str, Any]:
    """The ``tf2_msgs/TFMessage`` dict for joint ``positions`` (name -> rad or m) at ``t_ns``."""
    transforms = []
    if base_frame and base_frame != model.root:
        transforms.append(transform_stamped(base_frame, model.root, np.eye(4), t_ns))
    for joint, T in model.joint_transforms(positions):
        transforms.append(transform_stamped(joint.parent, joint.child, T, t_ns))
    return {"transforms": transforms}
