"""The shared part of the controller core: its attributes and state access, for the mixins that
make up :class:`~redarm_ros.control.reach_controller.ReachController` (one law per module:
:mod:`~redarm_ros.control.attractor_law`, :mod:`~redarm_ros.control.servo_law`,
:mod:`~redarm_ros.control.replan_law`, and :mod:`~redarm_ros.control.command` from reference to
command). Units: m, rad, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import numpy as np

from redarm_ros.control.attractor import HeadingDynamics, SpeedProfile
from redarm_ros.control.elbow import ArmGeometry
from redarm_ros.control.guard import CollisionGuard
from redarm_ros.control.ik_step import IKStepper
from redarm_ros.control.ik_step6 import IKStepper6
from redarm_ros.control.paper_redundancy import PaperSwivel, TangentHand
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.state import CoreState
from redarm_ros.control.swivel_dynamics import SwivelDynamics
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.broadphase import LocalScene, SceneIndex
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics.protocols import ControlledArm
from redarm_ros.kinematics.quaternion import quat_from_matrix

SMALL_SCENE = 4  # obstacles within reach up to which every step uses them all (no per-step culling)


def pose_of(T: np.ndarray) -> tuple[Vec3, Quat]:
    """Position (m) and quaternion (w, x, y, z) of a 4x4 pose."""
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), quat_from_matrix(T[:3, :3])


class ControllerBase:
    """What every part of the controller shares: the arm and its limits, the parameters, the dynamics,
    the IK stepper, the guard, the scene index and this step's local scene, and the state."""

    arm: ControlledArm
    params: ControllerParams
    geom: ArmGeometry
    swivel_dyn: SwivelDynamics
    paper_swivel: PaperSwivel
    tangent_hand: TangentHand
    heading_dyn: HeadingDynamics
    speed_profile: SpeedProfile
    stepper: IKStepper | IKStepper6  # the swivel arm's or the 6-DOF arm's (ReachController6)
    guard: CollisionGuard
    scene: Scene
    _index: SceneIndex
    _local: LocalScene
    _lower: np.ndarray
    _upper: np.ndarray
    _max_vel: np.ndarray
    _inv_vel: np.ndarray
    _max_acc: np.ndarray
    _d_inner: float
    _d_outer: float
    _st: CoreState | None

    def _slide_geom(self, pos: Vec3) -> ArmGeometry:
        """The geometry the workspace slide uses at tool position ``pos`` (m): fixed for a swivel arm."""
        return self.geom

    def _state(self) -> CoreState:
        if self._st is None:
            raise InvalidInputError("reset(q) must be called first", field="q")
        return self._st
