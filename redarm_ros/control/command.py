"""From reference to command: the command follows the reference within the joint velocity,
acceleration and position limits (time-optimal per joint, the reference's velocity fed forward) and
passes the collision guard; braking, holding, and making the reference the command again.

Also this step's local scene (the broad phase). Part of
:class:`~redarm_ros.control.reach_controller.ReachController`. Units: m, rad, s.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from redarm_ros.control.base import SMALL_SCENE, ControllerBase, pose_of
from redarm_ros.control.elbow import elbow_circle
from redarm_ros.control.guard import describe
from redarm_ros.control.ik_step import IKStep
from redarm_ros.control.joint_limits import braking_speed, velocity_bounds
from redarm_ros.control.state import (
    ZERO3,
    Mode,
)
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import GoalKind, Phase
from redarm_ros.errors import UnreachableError
from redarm_ros.geometry.broadphase import LocalScene
from redarm_ros.geometry.obstacles import Clearance, Scene
from redarm_ros.kinematics.quaternion import quat_angle, rotvec_between

LOG = logging.getLogger(__name__)
#: m: a reference hand step longer than this is motion (restarts the settle dwell of the swivel)
HAND_STILL_STEP = 1e-6


class CommandMixin(ControllerBase):
    """The command side of the controller (see the module docstring)."""

    def _local_scene(self, dt: float) -> LocalScene:
        """This step's obstacles: those within reach of any distance the step may compute."""
        st = self._state()
        if len(self._index.reach_scene.index) <= SMALL_SCENE:  # culling would cost more than it saves
            return self._index.reach_scene
        kc = st.cmd.kp
        kr = np.asarray(st.ref.circle.key_points(st.ref.s), float) if st.ref.circle is not None \
            else self.guard.key_points(st.ref.q)
        lever = self.guard.levers(st.cmd.q, kc)
        qd = np.maximum(np.abs(st.cmd.qd), np.abs(st.ref.qd)) + self._max_acc * dt
        travel = float(np.dot(lever, qd * qd / (2.0 * self._max_acc) + 2.0 * self._max_vel * dt))
        radius = self.params.broad_phase_margin + travel + self.params.swivel.obs_influence
        return self._index.local((kc, kr), self.params.capsules.radii, radius)

    @staticmethod
    def _globalise(c: Clearance, local: LocalScene) -> Clearance:
        """A clearance of the local scene with the obstacle index of the full scene."""
        return Clearance(c.distance, c.link, local.global_index(c.obstacle))

    def _obstacle_clearance(self, q: np.ndarray, local: LocalScene, kp: np.ndarray) -> float:
        if not local.scene.obstacles:
            return math.inf
        return self.guard.clearance(q, Scene(local.scene.obstacles, None), kp, self_check=False).distance

    def _commit(self, step: IKStep, dt: float, attractor: bool) -> bool:
        """Take the IK step as the new reference and move the command towards it within the velocity
        and acceleration limits, through the guard. Returns False if the guard refused the command."""
        st = self._state()
        p = self.params
        ref = st.ref
        q, pos, rot, s = step.q, step.pos, step.rot, step.s
        moved = math.dist(pos, ref.pos)
        ratio = float(np.max(np.abs(q - ref.q) * self._inv_vel)) / dt
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
        if not self._track(dt):
            return False
        v_now = moved / dt
        ref.v_tool = v_now
        if attractor:
            self._speed_budget(ratio, v_now, dt)
        if st.phase is Phase.HOLDING:
            st.phase = Phase.REACHING
        return True

    def _track(self, dt: float) -> bool:
        """Move the command towards the reference within the joint velocity, acceleration and
        position limits (time-optimal per joint: the reference velocity plus the speed from which the
        lag can still be braked away), then check it with the collision guard. Returns False if the
        guard refused it (then the arm brakes and holds)."""
        st = self._state()
        cmd, ref = st.cmd, st.ref
        qc, qd = cmd.q, cmd.qd
        # The lag behind where the reference was a step ago: with the reference's velocity fed
        # forward, a command on the reference stays on it (no limit cycle around a moving reference).
        u = np.clip(ref.qd, -self._max_vel, self._max_vel)
        e = ref.q - u * dt - qc
        v_des = u + np.sign(e) * braking_speed(np.abs(e), self._max_acc, dt)
        e = ref.q - qc
        lo, hi = velocity_bounds(qc, qd, dt, self._max_vel, self._max_acc, self._lower, self._upper)
        v = np.clip(v_des, lo, hi)
        small = np.abs(e) <= 1e-12  # land exactly on a resting reference
        v = np.where(small & (np.abs(ref.qd) <= 1e-12) & (lo <= 0.0) & (hi >= 0.0), 0.0, v)
        q_new = np.clip(qc + v * dt, self._lower, self._upper)
        snap = np.abs(ref.q - q_new) <= 1e-12
        q_new = np.where(snap, ref.q, q_new)
        return self._command(q_new, (q_new - qc) / dt, dt)

    def _command(self, q: np.ndarray, qd: np.ndarray, dt: float) -> bool:
        """Commit command ``q`` (rad) moving at ``qd`` (rad/s) if the guard allows it; otherwise brake."""
        st = self._state()
        local = self._local
        sync = st.brake_sync  # a planned path: braking keeps to it
        kp = self.guard.key_points(q)
        clear, bad = self.guard.check(q, qd, st.cmd.clear.distance, dt, local.scene, sync,
                                      on_path=st.mode is Mode.JOINT, kp=kp)
        if bad is not None:
            self._guard_stop(bad, dt)
            return False
        self._set_command(q, qd, clear, dt, kp)
        return True

    def _set_command(self, q: np.ndarray, qd: np.ndarray, clear: Clearance, dt: float,
                     kp: np.ndarray | None = None) -> None:
        st = self._state()
        cmd = st.cmd
        local = self._local
        kp = self.guard.key_points(q) if kp is None else kp
        cmd.kp = kp
        obs = self._obstacle_clearance(q, local, kp)
        both = math.isfinite(cmd.obs_clear) and math.isfinite(obs)
        cmd.obs_rate = (cmd.obs_clear - obs) / dt if both else 0.0
        cmd.obs_clear = obs
        cmd.q = q
        cmd.qd = qd
        cmd.clear = self._globalise(clear, local)
        T = np.asarray(self.arm.fk(q), float)
        cpos, crot = pose_of(T)
        cmd.tool_speed = math.dist(cpos, cmd.pos) / dt
        cmd.pos, cmd.rot = cpos, crot
        st.history.append((q, clear.distance))

    def _resync_reference(self, keep_velocity: bool = False) -> None:
        """Make the reference the command's pose (after a guard stop, or to leave a joint-space move):
        pose, swivel and circle from FK; the Cartesian velocity from the command's when asked."""
        st = self._state()
        ref, cmd = st.ref, st.cmd
        ref.q = cmd.q.copy()
        ref.qd = cmd.qd.copy() if keep_velocity else np.zeros_like(cmd.q)
        T = np.asarray(self.arm.fk(cmd.q), float)
        ref.pos, ref.rot = pose_of(T)
        try:
            ref.circle = elbow_circle(self.geom, T)
            ref.s = float(self.arm.swivel(cmd.q))
        except UnreachableError:
            ref.circle = None
        ref.sdot = 0.0
        ref.sdot_dyn = 0.0
        ref.sdot_want, ref.want_over_since = math.nan, math.inf
        ref.swivel_moved_at = st.time
        ref.w_ori = 0.0
        if keep_velocity:
            J = np.asarray(self.arm.jacobian(cmd.q), float)
            tw = J @ cmd.qd
            ref.vel = (float(tw[0]), float(tw[1]), float(tw[2]))
            ref.w = (float(tw[3]), float(tw[4]), float(tw[5]))
            ref.w_ori = math.sqrt(ref.w[0] ** 2 + ref.w[1] ** 2 + ref.w[2] ** 2)
            if ref.circle is not None and np.any(cmd.qd != 0.0):  # the swivel rate, by a step ahead
                h = 1e-3
                q_h = np.clip(cmd.q + h * cmd.qd, self._lower, self._upper)
                ref.sdot = wrap_angle(float(self.arm.swivel(q_h)) - ref.s) / h
        else:
            ref.vel, ref.w = ZERO3, ZERO3
        st.att.v = 0.0 if not keep_velocity else math.sqrt(sum(c * c for c in ref.vel))
        st.att.a = 0.0

    def _guard_stop(self, bad: Clearance, dt: float) -> None:
        st = self._state()
        st.progress.guard_stops.append(st.time)
        local = self._local
        what = describe(bad, local.scene)
        braked = self._brake(dt)
        self._resync_reference()
        self._hold(f"collision guard: the next step would bring {what}; {'braking' if braked else 'holding'}")

    def _brake(self, dt: float) -> bool:
        """One step of the hardest allowed joint braking, if the guard lets it through; otherwise stop
        where the arm is (an emergency stop: the only command that may exceed the acceleration limit).
        Returns True if a braking step was commanded."""
        st = self._state()
        cmd = st.cmd
        if not np.any(cmd.qd != 0.0):
            return False
        local = self._local
        out = self.guard.brake(cmd.q, cmd.qd, cmd.clear.distance, dt, local.scene, st.brake_sync)
        if out is not None:
            self._set_command(out[0], out[1], out[2], dt)
            return True
        LOG.warning("emergency stop: even braking would bring the arm into the scene")
        cmd.qd = np.zeros_like(cmd.q)
        return False

    def _hold(self, why: str) -> None:
        """Stop the hand (the command then brakes onto the reference) and report HOLDING with ``why``
        (for a stream or twist the phase stays TRACKING: it is followed as closely as allowed)."""
        st = self._state()
        st.att.v = 0.0
        st.att.a = 0.0
        st.ref.qd = np.zeros_like(st.ref.q)
        st.ref.vel, st.ref.w = ZERO3, ZERO3
        if st.goal is not None and st.goal.kind is GoalKind.POINT:
            st.phase = Phase.HOLDING
        st.message = why
