"""The reaching controller of an arm, built by one function.

:func:`make_controller` picks what the arm needs: ``ReachController``
(:mod:`~redarm_ros.control.reach_controller`) for a 7-DOF swivel arm, ``ReachController6``
(:mod:`~redarm_ros.control.reach6`) for the 6-DOF PowerCube arm, ``JointMappedController`` for a URDF
arm that is a swivel model up to joint signs and offsets. Each class refuses an arm it cannot run with
a :class:`~redarm_ros.errors.ConfigError` that names this function.
"""

from __future__ import annotations

from redarm_ros.control.ik_step6 import is_6dof
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.reach6 import ReachController6
from redarm_ros.control.reach_controller import JointMappedController, ReachController, controller_refusal
from redarm_ros.errors import ConfigError
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics.protocols import ControlledArm

__all__ = ["make_controller"]


def make_controller(arm: ControlledArm, scene: Scene | None = None,
                    params: ControllerParams | None = None) -> ReachController | JointMappedController:
    """The reaching controller of ``arm`` in ``scene`` (default: none) with ``params`` (default: the table's).

    Raises:
        ConfigError: the arm is neither a 7-DOF swivel arm (spherical shoulder and wrist, in the model's
            frames) nor the 6-DOF PowerCube arm; the message says why.
    """
    refused = controller_refusal(arm)
    if refused:
        raise ConfigError(refused, field="arm")
    if getattr(arm, "kind", "") == "swivel7_urdf":
        return JointMappedController(arm, scene, params)
    if is_6dof(arm):
        return ReachController6(arm, scene, params)
    return ReachController(arm, scene, params)
