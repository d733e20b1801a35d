"""The servo law of goal streams and twists: the tracking law of :mod:`~redarm_ros.control.servo`
around the IK step, with the joint-acceleration fit, the command-lag resync, sliding and the
elbow-before-hand slowdown. Part of :class:`~redarm_ros.control.reach_controller.ReachController`.
Units: m, rad, s.
"""

from __future__ import annotations

import math

import numpy as np

from redarm_ros.control.attractor import direction
from redarm_ros.control.base import ControllerBase
from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.ik_step import DeadEnd, IKStep, SwivelFn, blend, pose_matrix
from redarm_ros.control.ik_step6 import is_6dof
from redarm_ros.control.params import ServoParams
from redarm_ros.control.servo import ServoTarget, servo_step
from redarm_ros.control.slide import obstacle_slide, workspace_slide
from redarm_ros.control.state import (
    ZERO3,
    Mode,
)
from redarm_ros.control.stream_swivel import (
    LOOKAHEAD_SAMPLES,
    OFFSET_EPS,
    closing_acc,
    offset_rate,
    time_to_axis,
    wrap_offset,
)
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import GoalKind
from redarm_ros.kinematics.quaternion import (
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
)


class ServoMixin(ControllerBase):
    """The servo law of goal streams and twists (see the module docstring)."""

    def _enter_servo(self) -> None:
        """Servo state continuous with the reference's motion."""
        st = self._state()
        st.route = None  # (a point goal's corridor route ends where a stream or twist begins)
        self._end_joint_motion(st)  # from a joint-space move: drop its plan (ReplanMixin)
        if st.mode is Mode.ATTRACTOR:
            e = direction(st.att.phi, st.att.theta)
            st.ref.vel = (st.att.v * e[0], st.att.v * e[1], st.att.v * e[2])
        st.mode = Mode.SERVO
        st.ref.sdot_dyn = st.ref.sdot
        st.message = ""
        st.stream_note = ""

    def _servo_target(self, dt: float) -> ServoTarget:
        st = self._state()
        ref = st.ref
        goal = st.goal
        if goal is None:  # stopped or rejected while tracking: decelerate
            return ServoTarget(ref.pos, ref.rot, ZERO3, ZERO3, hold_position=False)
        if goal.kind is GoalKind.TWIST:
            tw = st.twist
            if tw is None or st.time - tw.since > self.params.servo.twist_timeout:
                return ServoTarget(ref.pos, ref.rot, ZERO3, ZERO3, hold_position=False)
            return ServoTarget(ref.pos, ref.rot, tw.vel, tw.w, hold_position=False)
        pred = self.stream.predict(st.time, st.time)
        if pred is None:
            return ServoTarget(goal.pos, goal.rot, ZERO3, ZERO3)
        return ServoTarget(pred.pos, pred.rot, pred.vel, pred.w)

    def _servo_step(self, dt: float) -> None:
        st = self._state()
        p = self.params
        sp: ServoParams = p.servo
        if float(np.max(np.abs(st.ref.q - st.cmd.q) * self._inv_vel)) > sp.resync_lag:
            # The command lags (a joint at its acceleration limit, the guard): the servo goes on from
            # where the arm is, so the reference never runs off to a configuration the arm cannot
            # follow; the hand then follows as closely as the limits allow.
            self._resync_reference(keep_velocity=True)
            if self._pose_law():
                self._onto_preferred_swivel()
        ref = st.ref
        target = self._servo_target(dt)
        # The servo's own bounds are Cartesian; the joints' velocity limits shorten the IK step below
        # and their acceleration limits bound the command (which then lags the reference).
        new_pos, new_rot, _, _ = servo_step(ref.pos, ref.rot, ref.vel, ref.w, target, dt, sp.gain, sp.acc,
                                            p.speed.v_max, sp.ori_gain, sp.ori_acc, p.max_ori_rate)
        # Slide along the workspace shells and obstacles: keep only the motion that can be made.
        d = (new_pos[0] - ref.pos[0], new_pos[1] - ref.pos[1], new_pos[2] - ref.pos[2])
        d = workspace_slide(d, ref.pos, ref.rot, self._slide_geom(ref.pos), self._d_inner, self._d_outer,
                            p.workspace_margin, project=True)
        d = obstacle_slide(d, ref.circle, ref.s, self._local.scene, p.capsules, p.slide_band, project=True)
        # Elbow before hand: while the arm closes in on an obstacle within elbow_priority_clearance,
        # the hand slows so that the gap would last at least ``yield_time`` at the present rate; the
        # swivel meanwhile turns the elbow away (the hand catches up once the gap opens again).
        cmd = st.cmd
        if cmd.obs_rate > 0.0 and cmd.obs_clear < p.elbow_priority_clearance:
            room = max(cmd.obs_clear - p.collision_margin, 0.0)
            k = min(1.0, room / (cmd.obs_rate * sp.yield_time))
            d = (k * d[0], k * d[1], k * d[2])
            if k < 1.0:
                new_rot = ref.rot if k <= 0.0 else blend(ref.pos, ref.rot, ref.pos, new_rot, k)[1]
        new_pos = (ref.pos[0] + d[0], ref.pos[1] + d[1], ref.pos[2] + d[2])
        out = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, new_pos, new_rot, dt,
                                   self._servo_swivel_fn(dt), pose_swivel=self._pose_law())
        if isinstance(out, DeadEnd):
            self._hold(f"{self._stream_word()}: {out.reason}")
            ref.vel, ref.w = ZERO3, ZERO3
            self._track(dt)
            return
        limited = "joint velocity limits" if out.speed_scale < 1.0 else ""
        shaped = self._joint_acceleration_fit(out, dt)
        if shaped is not None:
            out = shaped
            limited = "joint acceleration limits"
        self._commit(out, dt, attractor=False)
        if limited and not st.message:
            st.message = f"{self._stream_word()}: {limited}: following as closely as they allow"

    def _pose_law(self) -> bool:
        """Does the swivel follow the pose while tracking (``servo.swivel_law`` pose, a 7-DOF arm whose
        swivel the dynamics moves)?"""
        p = self.params
        return p.servo.swivel_law == "pose" and p.swivel_mode == "dynamics" and not is_6dof(self.arm)

    def _onto_preferred_swivel(self) -> None:
        """After a resync: the reference's swivel back on the pose's preferred one (joints nearest the
        command's, on their branch) where that is continuous, so the lagging command's twist of joints 1
        and 3 near the shoulder axis does not become the offset (a circle over the shoulder at 0.25 m/s:
        lap 1 within 9 mm instead of 29 mm)."""
        st = self._state()
        ref = st.ref
        if ref.circle is None:
            return
        s_pref = self._preferred_swivel(ref.circle)
        T = pose_matrix(ref.pos, ref.rot)
        p = self.params
        pick = self.stepper.solve(T, s_pref, ref.q, p.dt)
        if pick is None or pick[1] > p.flip_ratio:  # (another branch: the offset closes on its own)
            return
        ref.q, ref.s = pick[0], s_pref

    def _servo_swivel_fn(self, dt: float) -> SwivelFn:
        """The swivel while tracking: the preferred swivel of the pose plus an offset that returns to 0
        (:mod:`~redarm_ros.control.stream_swivel`, ``servo.swivel_law`` pose), else the attractor's."""
        p = self.params
        st = self._state()
        ref = st.ref
        if not self._pose_law() or ref.circle is None:
            return self._swivel_fn(dt)
        sp, sw = p.servo, p.swivel
        pref_prev = self._preferred_swivel(ref.circle)
        offset = wrap_offset(ref.s, pref_prev)
        s_acc = self._swivel_acc_share()
        close_acc = min(sp.swivel_acc, s_acc)
        if abs(offset) > OFFSET_EPS and sp.lookahead > 0.0:
            hit = time_to_axis(self.geom, self._poses_ahead(sp.lookahead), offset, self._preferred_swivel,
                               sp.axis_margin)
            if hit is not None:
                close_acc = closing_acc(offset, 0.5 * hit, close_acc, s_acc)
        rate0 = ref.sdot_dyn

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            s_pref = self._preferred_swivel(circle)
            e0 = wrap_offset(s0, pref_prev)
            margins = self.stepper.limit_margins(T, s0, ref.q, sw.eps, sw.lim_threshold)
            f = self.swivel_dyn.forces(circle, s0, self._local.scene, p.capsules, margins)
            push = (sw.lam_obs * f.obstacle + sw.lam_lim * f.limits) / sw.tau
            rate = offset_rate(e0, rate0, push, close_acc, sw.max_rate, s_acc, dt)
            ref.sdot_dyn = rate
            ref.sdot_want = rate
            over = abs(rate) > 2.0 * p.settle_swivel_rate
            ref.want_over_since = min(ref.want_over_since, st.time) if over else math.inf
            ref.s_des = s_pref
            return wrap_angle(s_pref + e0 + rate * dt), s_pref, f.clearance < p.elbow_priority_clearance

        return swivel

    def _poses_ahead(self, horizon: float) -> list[tuple[float, np.ndarray]]:
        """The goal's poses predicted up to ``horizon`` s ahead ((tau, 4x4) each): the stream's estimate,
        or a twist's velocity from the reference; none once the stream has ended."""
        st = self._state()
        goal = st.goal
        out: list[tuple[float, np.ndarray]] = []
        if goal is None:
            return out
        ref = st.ref
        for k in range(1, LOOKAHEAD_SAMPLES + 1):
            tau = horizon * k / LOOKAHEAD_SAMPLES
            if goal.kind is GoalKind.TWIST:
                tw = st.twist
                if tw is None:
                    return out
                v, w = tw.vel, tw.w
                pos = (ref.pos[0] + v[0] * tau, ref.pos[1] + v[1] * tau, ref.pos[2] + v[2] * tau)
                turn = quat_from_rotvec((w[0] * tau, w[1] * tau, w[2] * tau))
                rot = quat_normalize(quat_mul(turn, ref.rot))
            else:
                pred = self.stream.predict(st.time + tau, st.time, clamp=False)
                if pred is None or pred.ended:
                    return out
                pos, rot = pred.pos, pred.rot
            out.append((tau, pose_matrix(pos, rot)))
        return out

    def _joint_acceleration_fit(self, step: IKStep, dt: float) -> IKStep | None:
        """If ``step`` asks a joint for more than its acceleration limit, the step that keeps as much
        of the servo's change of the hand's motion as the joints allow: a blend between coasting (the
        hand keeps its velocity) and ``step``, its share found per joint from the (nearly linear)
        joint accelerations of the two. None if ``step`` fits."""
        st = self._state()
        ref = st.ref
        amax = 0.98 * self._max_acc * dt * dt
        base = ref.q + ref.qd * dt  # where every joint would coast to
        dev = step.q - base
        if np.all(np.abs(dev) <= amax):
            return None
        v, w = ref.vel, ref.w
        c_pos = (ref.pos[0] + v[0] * dt, ref.pos[1] + v[1] * dt, ref.pos[2] + v[2] * dt)
        c_rot = quat_normalize(quat_mul(quat_from_rotvec((w[0] * dt, w[1] * dt, w[2] * dt)), ref.rot))
        keep = self._kept_swivel(step)
        pose_law = self._pose_law()
        coast = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, c_pos, c_rot, dt, keep, pose_law)
        if isinstance(coast, DeadEnd):
            return None
        d0 = coast.q - base  # joint acceleration (times dt^2) when coasting
        d1 = dev - d0  # what the servo's change adds
        lo, hi = 0.0, 1.0
        for j in range(len(d1)):
            if abs(d1[j]) < 1e-12:
                continue
            a, b = (-amax[j] - d0[j]) / d1[j], (amax[j] - d0[j]) / d1[j]
            lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
        alpha = hi if lo <= hi else (0.0 if np.max(np.abs(d0) / amax) <= np.max(np.abs(dev) / amax) else 1.0)
        alpha = min(max(alpha, 0.0), 1.0)
        if alpha >= 1.0:
            return None
        pos, rot = blend(coast.pos, coast.rot, step.pos, step.rot, alpha)
        out = self.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, pos, rot, dt, keep, pose_law)
        return None if isinstance(out, DeadEnd) else out

    def _kept_swivel(self, step: IKStep) -> SwivelFn:
        """The swivel of ``step`` for another pose of the same step: its offset from the preferred swivel
        kept (``servo.swivel_law`` pose: the elbow stays in the vertical plane through the wrist where
        the step had it there), or the swivel itself."""
        if not self._pose_law():
            return lambda c, T, s0: (step.s, step.s_des, False)
        off = wrap_offset(step.s, self._preferred_swivel(step.circle))

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            s_pref = self._preferred_swivel(circle)
            return wrap_angle(s_pref + off), s_pref, False

        return swivel

    def _stream_word(self) -> str:
        st = self._state()
        return "twist" if st.goal is not None and st.goal.kind is GoalKind.TWIST else "stream"

    def _at_rest_servo(self) -> bool:
        st = self._state()
        v, w = st.ref.vel, st.ref.w
        return max(abs(c) for c in (*v, *w)) < 1e-6
