"""Kinematics core (numpy only, no ROS): arm models, FK, Jacobian, swivel IK, PowerCube IK, numeric IK.

Quaternions inside this package are (w, x, y, z) unless a name says otherwise (``*_xyzw``).

    from redarm_ros.kinematics import load_arm
    arm = load_arm("pa10")
    T = arm.fk(q)                    # 4x4 base -> tool
    sols = arm.ik(T, swivel=0.3)     # (k, 7), every in-limit solution at that swivel
    ivs = arm.feasible_swivels(T)    # per flip pattern, the in-limit swivel intervals (closed form)
    q, info = arm.ik_nearest(T, q_seed)
    cor = arm.swivel_corridor(T0, T1, q0)  # the straight route's swivel corridor and a schedule

Module layering (no import cycle): ``errors``, ``result``, ``quaternion``, ``protocols`` <- ``numeric``
<- ``model`` <- ``feasible`` <- ``corridor`` <- ``swivel``, ``powercube6`` <- ``urdf_chain`` <- ``loader``
<- ``solve``, ``reachability``.

An arm from a URDF: ``load_arm("robot.urdf", base_link="base_link", tip_link="tool0")`` (or the XML text
of ``/robot_description``); :func:`describe_solver` says which IK it gets and why.
"""

from typing import TYPE_CHECKING, Any

from redarm_ros.kinematics.corridor import SwivelCorridor, route_pose, swivel_corridor
from redarm_ros.kinematics.loader import (
    arm_config_dirs,
    available_arms,
    build_arm,
    load_arm,
    load_arm_or_urdf,
)
from redarm_ros.kinematics.model import Arm, Joint, pose_error
from redarm_ros.kinematics.powercube6 import PowerCube6Arm
from redarm_ros.kinematics.protocols import AnalyticIK, SwivelKinematics, has_analytic_ik, has_swivel
from redarm_ros.kinematics.result import IKInfo, IKStatus
from redarm_ros.kinematics.swivel import SwivelArm

if TYPE_CHECKING:
    from redarm_ros.kinematics.urdf_chain import MappedSwivelArm, describe_solver, load_urdf_arm

# The URDF front end is imported on first use (it brings the geometry package's capsule model): a
# process that only loads a bundled arm does not pay for it.
_LAZY = {"MappedSwivelArm", "describe_solver", "load_urdf_arm"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from redarm_ros.kinematics import urdf_chain  # noqa: PLC0415

        return getattr(urdf_chain, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Arm",
    "Joint",
    "SwivelArm",
    "MappedSwivelArm",
    "load_urdf_arm",
    "describe_solver",
    "PowerCube6Arm",
    "AnalyticIK",
    "SwivelKinematics",
    "has_swivel",
    "has_analytic_ik",
    "IKInfo",
    "IKStatus",
    "load_arm",
    "load_arm_or_urdf",
    "build_arm",
    "available_arms",
    "arm_config_dirs",
    "pose_error",
    "SwivelCorridor",
    "swivel_corridor",
    "route_pose",
]
