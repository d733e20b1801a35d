"""From reference to command: the command follows the reference within the joint velocity,
acceleration and position limits (time-optimal per joint, the reference's velocity fed forward) and
passes the collision guard; braking, holding, and making the reference the command again.

Also this step's local scene (the broad phase, :class:`SceneView`). :class:`CommandShaper` is the part
of :class:`~redarm_ros.control.reach_controller.ReachController` that does it; its methods take the
controller's :class:`~redarm_ros.control.state.CoreState`. Units: m, rad, s.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from redarm_ros.control.guard import CollisionGuard, describe
from redarm_ros.control.ik_step import IKStep, pose_of
from redarm_ros.control.joint_limits import JointBounds, track_step
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.redundancy import Redundancy
from redarm_ros.control.state import (
    ZERO3,
    CoreState,
    Mode,
)
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import GoalKind, Phase
from redarm_ros.geometry.broadphase import LocalScene, SceneIndex
from redarm_ros.geometry.obstacles import Clearance, Scene
from redarm_ros.kinematics.protocols import ControlledArm
from redarm_ros.kinematics.quaternion import quat_angle, rotvec_between

LOG = logging.getLogger(__name__)
#: m: a reference hand step longer than this is motion (restarts the settle dwell of the swivel)
HAND_STILL_STEP = 1e-6
SMALL_SCENE = 4  # obstacles within reach up to which every step uses them all (no per-step culling)


@dataclass
class SceneView:
    """The scene as the controller's parts see it: the broad phase's ``index`` of the whole scene (set
    with the scene) and this step's ``local`` scene (set by every step)."""

    index: SceneIndex
    local: LocalScene

    @classmethod
    def of(cls, index: SceneIndex) -> SceneView:
        """The view of ``index`` before the first step: every obstacle within reach."""
        return cls(index, index.reach_scene)


class CommandShaper:
    """The command side of the controller (see the module docstring): ``arm``'s forward kinematics,
    ``guard``, the joint ``bounds``, the ``view`` of the scene, and the ``redundancy`` strategy that
    makes the swivel part of a resynced reference."""

    def __init__(self, arm: ControlledArm, guard: CollisionGuard, bounds: JointBounds, view: SceneView,
                 redundancy: Redundancy) -> None:
        self.arm = arm
        self.guard = guard
        self.bounds = bounds
        self.view = view
        self.redundancy = redundancy

    def local_scene(self, st: CoreState, p: ControllerParams, dt: float) -> LocalScene:
        """This step's obstacles: those within reach of any distance the step may compute."""
        index = self.view.index
        if len(index.reach_scene.index) <= SMALL_SCENE:  # culling would cost more than it saves
            return index.reach_scene
        b = self.bounds
        kc = st.cmd.kp
        kr = np.asarray(st.ref.circle.key_points(st.ref.s), float) if st.ref.circle is not None \
            else self.guard.key_points(st.ref.q)
        lever = self.guard.levers(st.cmd.q, kc)
        qd = np.maximum(np.abs(st.cmd.qd), np.abs(st.ref.qd)) + b.max_acc * dt
        travel = float(np.dot(lever, qd * qd / (2.0 * b.max_acc) + 2.0 * b.max_vel * dt))
        radius = p.broad_phase_margin + travel + p.swivel.obs_influence
        return index.local((kc, kr), p.capsules.radii, radius)

    @staticmethod
    def globalise(c: Clearance, local: LocalScene) -> Clearance:
        """A clearance of the local scene with the obstacle index of the full scene."""
        return Clearance(c.distance, c.link, local.global_index(c.obstacle))

    def obstacle_clearance(self, q: np.ndarray, local: LocalScene, kp: np.ndarray) -> float:
        """The clearance (m) of the arm at ``q`` (key points ``kp``) to the obstacles of ``local`` (not the
        table; no self-check); inf without obstacles."""
        if not local.scene.obstacles:
            return math.inf
        return self.guard.clearance(q, Scene(local.scene.obstacles, None), kp, self_check=False).distance

    def speed_ratio(self, st: CoreState, q: np.ndarray, dt: float) -> float:
        """The largest joint speed over its limit of a reference step to ``q`` taking ``dt`` s."""
        return float((np.abs(q - st.ref.q) * self.bounds.inv_vel).max()) / dt

    def commit(self, st: CoreState, p: ControllerParams, step: IKStep, dt: float) -> bool:
        """Take the IK step as the new reference and move the command towards it within the velocity
        and acceleration limits, through the guard. Returns False if the guard refused the command."""
        ref = st.ref
        q, pos, rot, s = step.q, step.pos, step.rot, step.s
        moved = math.dist(pos, ref.pos)
        ref.sdot = wrap_angle(s - ref.s) / dt if p.swivel_mode != "fixed" else 0.0
        if abs(ref.sdot) > p.settle_swivel_rate or moved > HAND_STILL_STEP:
            ref.swivel_moved_at = st.time  # (a swivel that waits for the hand is not held by a limit)
        ref.w_ori = quat_angle(ref.rot, rot) / dt
        ref.vel = ((pos[0] - ref.pos[0]) / dt, (pos[1] - ref.pos[1]) / dt, (pos[2] - ref.pos[2]) / dt)
        wv = rotvec_between(ref.rot, rot)
        ref.w = (wv[0] / dt, wv[1] / dt, wv[2] / dt)
        ref.qd = (q - ref.q) / dt
        ref.q = q
        ref.pos, ref.rot, ref.s, ref.circle = pos, rot, s, step.circle
        if st.message.startswith(("collision guard", "stream", "twist", "no joint solution", "at the goal")):
            st.message = ""
        st.brake_sync = False
        if not self.track(st, dt):
            return False
        ref.v_tool = moved / dt
        if st.phase is Phase.HOLDING:
            st.phase = Phase.REACHING
        return True

    def track(self, st: CoreState, dt: float) -> bool:
        """Move the command towards the reference within the joint velocity, acceleration and
        position limits (time-optimal per joint: the reference velocity plus the speed from which the
        lag can still be braked away), then check it with the collision guard. Returns False if the
        guard refused it (then the arm brakes and holds)."""
        cmd, ref = st.cmd, st.ref
        # The lag behind where the reference was a step ago: with the reference's velocity fed
        # forward, a command on the reference stays on it (no limit cycle around a moving reference).
        q_new, qd_new = track_step(cmd.q.tolist(), cmd.qd.tolist(), ref.q.tolist(), ref.qd.tolist(), dt,
                                   self.bounds)
        return self._command(st, np.array(q_new), np.array(qd_new), dt)

    def _command(self, st: CoreState, q: np.ndarray, qd: np.ndarray, dt: float) -> bool:
        """Commit command ``q`` (rad) moving at ``qd`` (rad/s) if the guard allows it; otherwise brake."""
        local = self.view.local
        sync = st.brake_sync  # a planned path: braking keeps to it
        kp = self.guard.key_points(q)
        clear, bad = self.guard.check(q, qd, st.cmd.clear.distance, dt, local.scene, sync,
                                      on_path=st.mode is Mode.JOINT, kp=kp)
        if bad is not None:
            self._guard_stop(st, bad, dt)
            return False
        self._set_command(st, q, qd, clear, dt, kp)
        return True

    def _set_command(self, st: CoreState, q: np.ndarray, qd: np.ndarray, clear: Clearance, dt: float,
                     kp: np.ndarray | None = None) -> None:
        cmd = st.cmd
        local = self.view.local
        kp = self.guard.key_points(q) if kp is None else kp
        cmd.kp = kp
        obs = self.obstacle_clearance(q, local, kp)
        both = math.isfinite(cmd.obs_clear) and math.isfinite(obs)
        cmd.obs_rate = (cmd.obs_clear - obs) / dt if both else 0.0
        cmd.obs_clear = obs
        cmd.q = q
        cmd.qd = qd
        cmd.clear = self.globalise(clear, local)
        T = np.asarray(self.arm.fk(q), float)
        cpos, crot = pose_of(T)
        cmd.tool_speed = math.dist(cpos, cmd.pos) / dt
        cmd.pos, cmd.rot = cpos, crot
        st.history.append((q, clear.distance))

    def resync_reference(self, st: CoreState, keep_velocity: bool = False) -> None:
        """Make the reference the command's pose (after a guard stop, or to leave a joint-space move):
        pose from FK, the swivel part from the redundancy strategy; the Cartesian velocity from the
        command's when asked."""
        ref, cmd = st.ref, st.cmd
        ref.q = cmd.q.copy()
        ref.qd = cmd.qd.copy() if keep_velocity else np.zeros_like(cmd.q)
        T = np.asarray(self.arm.fk(cmd.q), float)
        ref.pos, ref.rot = pose_of(T)
        ref.w_ori = 0.0
        if keep_velocity:
            J = np.asarray(self.arm.jacobian(cmd.q), float)
            tw = J @ cmd.qd
            ref.vel = (float(tw[0]), float(tw[1]), float(tw[2]))
            ref.w = (float(tw[3]), float(tw[4]), float(tw[5]))
            ref.w_ori = math.sqrt(ref.w[0] ** 2 + ref.w[1] ** 2 + ref.w[2] ** 2)
        else:
            ref.vel, ref.w = ZERO3, ZERO3
        self.redundancy.resync(st, T, keep_velocity)
        st.att.v = 0.0 if not keep_velocity else math.sqrt(sum(c * c for c in ref.vel))
        st.att.a = 0.0

    def _guard_stop(self, st: CoreState, bad: Clearance, dt: float) -> None:
        st.progress.guard_stops.append(st.time)
        what = describe(bad, self.view.local.scene)
        braked = self.brake(st, dt)
        self.resync_reference(st)
        self.hold(st, f"collision guard: the next step would bring {what}; "
                      f"{'braking' if braked else 'holding'}")

    def brake(self, st: CoreState, dt: float) -> bool:
        """One step of the hardest allowed joint braking, if the guard lets it through; otherwise stop
        where the arm is (an emergency stop: the only command that may exceed the acceleration limit).
        Returns True if a braking step was commanded."""
        cmd = st.cmd
        if not np.any(cmd.qd != 0.0):
            return False
        out = self.guard.brake(cmd.q, cmd.qd, cmd.clear.distance, dt, self.view.local.scene, st.brake_sync)
        if out is not None:
            self._set_command(st, out[0], out[1], out[2], dt)
            return True
        LOG.warning("emergency stop: even braking would bring the arm into the scene")
        cmd.qd = np.zeros_like(cmd.q)
        return False

    @staticmethod
    def hold(st: CoreState, why: str) -> None:
        """Stop the hand (the command then brakes onto the reference) and report HOLDING with ``why``
        (for a stream or twist the phase stays TRACKING: it is followed as closely as allowed)."""
        st.att.v = 0.0
        st.att.a = 0.0
        st.ref.qd = np.zeros_like(st.ref.q)
        st.ref.vel, st.ref.w = ZERO3, ZERO3
        if st.goal is not None and st.goal.kind is GoalKind.POINT:
            st.phase = Phase.HOLDING
        st.message = why
