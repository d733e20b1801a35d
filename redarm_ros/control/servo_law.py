"""The servo law of goal streams and twists: the tracking law of :mod:`~redarm_ros.control.servo`
around the IK step, with the joint-acceleration fit, the command-lag resync, sliding and the
elbow-before-hand slowdown; where a stream's path asks a joint for more than its acceleration limit,
the joints' motion planned ahead within the limits instead (:mod:`~redarm_ros.control.lookahead`).
:class:`ServoLaw` is the part of
:class:`~redarm_ros.control.reach_controller.ReachController` that moves the reference while tracking;
its methods take the controller's :class:`~redarm_ros.control.state.CoreState` and parameters. Units:
m, rad, s.
"""

from __future__ import annotations

import numpy as np

from redarm_ros.control.attractor import direction
from redarm_ros.control.command import CommandShaper, SceneView
from redarm_ros.control.ik_step import DeadEnd, IKStep, blend, pose_matrix
from redarm_ros.control.joint_limits import JointBounds
from redarm_ros.control.lookahead import JointLookahead, growing_blocks
from redarm_ros.control.params import ControllerParams, ServoParams
from redarm_ros.control.redundancy import PosesAhead, Redundancy
from redarm_ros.control.servo import ServoTarget, servo_step
from redarm_ros.control.slide import obstacle_slide, workspace_slide
from redarm_ros.control.state import ZERO3, CoreState, Mode, PlanAhead
from redarm_ros.control.stream_swivel import LOOKAHEAD_SAMPLES
from redarm_ros.control.types import GoalKind
from redarm_ros.kinematics.quaternion import (
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
)

#: s: the plan ahead's first acceleration block is about this long, and each next one PLAN_GROWTH times
#: longer
PLAN_BLOCK = 0.04
PLAN_GROWTH = 1.5
#: the plan ahead starts where the path's joints need more than this share of an acceleration limit
#: within PLAN_TRIGGER_AHEAD s (the nearer prediction: the farther one errs more; above 1: a jittered
#: stream's estimate errs by some 20 %)
PLAN_TRIGGER = 1.15
PLAN_TRIGGER_AHEAD = 0.5
#: s: while it is not needed, how often the plan ahead looks whether the path needs it
PLAN_CHECK = 0.05
#: Hz: slower streams are not planned ahead (too few samples to tell how the path turns)
PLAN_MIN_RATE = 20.0


class ServoLaw:
    """The servo law of goal streams and twists (see the module docstring): the ``redundancy`` strategy
    (IK stepper and swivel), the ``command`` part, the joint ``bounds``, the ``view`` of the scene and
    the wrist ``shell`` (inner and outer radius, m) the workspace slide keeps to."""

    def __init__(self, redundancy: Redundancy, command: CommandShaper, bounds: JointBounds, view: SceneView,
                 shell: tuple[float, float]) -> None:
        self.redundancy = redundancy
        self.command = command
        self.bounds = bounds
        self.view = view
        self.shell = shell
        self._lookahead: JointLookahead | None = None  # for the last step and horizon

    @staticmethod
    def enter(st: CoreState) -> None:
        """Servo state continuous with the reference's motion (a joint-space move already ended)."""
        if st.mode is Mode.ATTRACTOR:
            e = direction(st.att.phi, st.att.theta)
            st.ref.vel = (st.att.v * e[0], st.att.v * e[1], st.att.v * e[2])
        st.mode = Mode.SERVO
        st.ref.sdot_dyn = st.ref.sdot
        st.ahead = PlanAhead()
        st.message = ""
        st.stream_note = ""

    def _target(self, st: CoreState, p: ControllerParams) -> ServoTarget:
        ref = st.ref
        goal = st.goal
        if goal is None:  # stopped or rejected while tracking: decelerate
            return ServoTarget(ref.pos, ref.rot, ZERO3, ZERO3, hold_position=False)
        if goal.kind is GoalKind.TWIST:
            tw = st.twist
            if tw is None or st.time - tw.since > p.servo.twist_timeout:
                return ServoTarget(ref.pos, ref.rot, ZERO3, ZERO3, hold_position=False)
            return ServoTarget(ref.pos, ref.rot, tw.vel, tw.w, hold_position=False)
        pred = st.stream.predict(st.time, st.time)
        if pred is None:
            return ServoTarget(goal.pos, goal.rot, ZERO3, ZERO3)
        return ServoTarget(pred.pos, pred.rot, pred.vel, pred.w)

    def step(self, st: CoreState, p: ControllerParams, dt: float) -> None:
        """One step of the reference towards the goal stream's prediction or along the twist."""
        sp: ServoParams = p.servo
        # The goal's predicted poses, once per step and horizon: the plan ahead's path and the pose law's
        # swivel both look ahead (the same goal, the same time).
        predicted: dict[float, list[tuple[float, np.ndarray]]] = {}

        def poses_ahead(horizon: float) -> list[tuple[float, np.ndarray]]:
            if horizon not in predicted:
                predicted[horizon] = self._poses_ahead(st, horizon)
            return predicted[horizon]

        if float((np.abs(st.ref.q - st.cmd.q) * self.bounds.inv_vel).max()) > sp.resync_lag:
            # The command lags (a joint at its acceleration limit, the guard): the servo goes on from
            # where the arm is, so the reference never runs off to a configuration the arm cannot
            # follow; the hand then follows as closely as the limits allow.
            self.command.resync_reference(st, keep_velocity=True)
            if self.redundancy.pose_law(p):
                self.redundancy.onto_preferred_swivel(st, p)
        if self._planned_step(st, p, dt, poses_ahead):
            return
        ref = st.ref
        target = self._target(st, p)
        # The servo's own bounds are Cartesian; the joints' velocity limits shorten the IK step below
        # and their acceleration limits bound the command (which then lags the reference).
        new_pos, new_rot, _, _ = servo_step(ref.pos, ref.rot, ref.vel, ref.w, target, dt, sp.gain, sp.acc,
                                            p.speed.v_max, sp.ori_gain, sp.ori_acc, p.max_ori_rate)
        # Slide along the workspace shells and obstacles: keep only the motion that can be made.
        d = (new_pos[0] - ref.pos[0], new_pos[1] - ref.pos[1], new_pos[2] - ref.pos[2])
        d = workspace_slide(d, ref.pos, ref.rot, self.redundancy.slide_geom(st), *self.shell,
                            p.workspace_margin, project=True)
        d = obstacle_slide(d, ref.circle, ref.s, self.view.local.scene, p.capsules, p.slide_band,
                           project=True)
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
        red = self.redundancy
        swivel = red.servo_swivel_fn(st, p, dt, self.view.local.scene, poses_ahead)
        out = red.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, new_pos, new_rot, dt, swivel,
                                  pose_swivel=red.pose_law(p))
        if isinstance(out, DeadEnd):
            self.command.hold(st, f"{self._stream_word(st)}: {out.reason}")
            ref.vel, ref.w = ZERO3, ZERO3
            self.command.track(st, dt)
            return
        limited = "joint velocity limits" if out.speed_scale < 1.0 else ""
        shaped = self._joint_acceleration_fit(st, p, out, dt)
        if shaped is not None:
            out = shaped
            limited = "joint acceleration limits"
        st.ref.acc_limited = shaped is not None
        self.command.commit(st, p, out, dt)
        if limited and not st.message:
            st.message = f"{self._stream_word(st)}: {limited}: following as closely as they allow"

    def _planned_step(self, st: CoreState, p: ControllerParams, dt: float, poses_ahead: PosesAhead) -> bool:
        """The step of a stream whose path asks a joint for nearly its acceleration limit within
        ``servo.plan_horizon`` (or did so within the last horizon, or whose plan is still held by a limit):
        the first step of each joint's motion planned ahead within the limits
        (:mod:`~redarm_ros.control.lookahead`). False (nothing done) otherwise, and where the path ahead
        cannot be followed in joint space (out of reach, a branch change, the stream ending) or an obstacle
        is within ``elbow_priority_clearance`` (the elbow's forces have the say there)."""
        goal = st.goal
        horizon = p.servo.plan_horizon
        if horizon <= 0.0 or goal is None or goal.kind is not GoalKind.STREAM \
                or st.cmd.obs_clear < p.elbow_priority_clearance or st.stream.rate() < PLAN_MIN_RATE:
            return False
        ref, ahead = st.ref, st.ahead
        planning = st.time <= ahead.until
        if not planning and st.time - ahead.checked < PLAN_CHECK - 1e-9:
            return False
        ahead.checked = st.time
        la = self._planner(dt, horizon)
        # (the reference after n steps is on the goal of st.time + (n - 1) dt)
        poses = st.stream.path_poses(st.time - dt + la.times(), st.time)
        if poses is None:
            return False
        red = self.redundancy
        if not planning:
            red.plan_offset(st, p)
        kept = (ahead.offset, ahead.rate)
        path = red.path_joints(st, p, dt, poses, la.ends, poses_ahead)
        if path is None:
            return False
        near = la.times()[1:-1] <= PLAN_TRIGGER_AHEAD  # (the path acceleration of the nearer knots)
        need = np.abs(la.path_acceleration(path))[near] / self.bounds.max_acc
        if need.size and float(np.max(need)) > PLAN_TRIGGER:
            ahead.until = st.time + la.horizon
        if st.time > ahead.until:
            ahead.offset, ahead.rate = kept  # (not planning after all: the offset stays the servo's)
            return False
        plan = la.plan(ref.q, ref.qd, path, red.stepper.arm.jacobian)
        step = red.joint_step(st, p, plan.q)
        if step is None:
            return False
        if plan.bound:  # (still cutting a corner: the plan goes on until the joints are back on the path)
            ahead.until = max(ahead.until, st.time + la.block_steps[0] * dt)
        ref.acc_limited = plan.bound
        ref.sdot_dyn = ahead.rate
        self.command.commit(st, p, step, dt)
        if plan.bound and not st.message:
            st.message = "stream: joint acceleration limits: planned ahead within them"
        return True

    def _planner(self, dt: float, horizon: float) -> JointLookahead:
        """The plan ahead for steps of ``dt`` s over ``horizon`` s (:data:`PLAN_BLOCK`, growing by
        :data:`PLAN_GROWTH`)."""
        la = self._lookahead
        if la is None or la.dt != dt or abs(la.horizon - horizon) > 0.5 * dt:
            blocks = growing_blocks(dt, PLAN_BLOCK, PLAN_GROWTH, horizon)
            if len(blocks) < 3:  # (a horizon of a few steps)
                blocks = [1, 1, 1]
            la = self._lookahead = JointLookahead(dt, blocks, self.bounds.max_acc)
        return la

    def _poses_ahead(self, st: CoreState, horizon: float) -> list[tuple[float, np.ndarray]]:
        """The goal's poses predicted up to ``horizon`` s ahead ((tau, 4x4) each): the stream's path
        (:meth:`~redarm_ros.control.stream.StreamEstimator.path_poses`), or a twist's velocity from the
        reference; none once the stream has ended."""
        goal = st.goal
        if goal is None:
            return []
        taus = horizon * np.arange(1, LOOKAHEAD_SAMPLES + 1) / LOOKAHEAD_SAMPLES
        if goal.kind is not GoalKind.TWIST:
            poses = st.stream.path_poses(st.time + taus, st.time)
            return [] if poses is None else list(zip(taus.tolist(), poses, strict=True))
        tw = st.twist
        if tw is None:
            return []
        ref = st.ref
        out: list[tuple[float, np.ndarray]] = []
        v, w = tw.vel, tw.w
        for tau in taus.tolist():
            pos = (ref.pos[0] + v[0] * tau, ref.pos[1] + v[1] * tau, ref.pos[2] + v[2] * tau)
            turn = quat_from_rotvec((w[0] * tau, w[1] * tau, w[2] * tau))
            out.append((tau, pose_matrix(pos, quat_normalize(quat_mul(turn, ref.rot)))))
        return out

    def _joint_acceleration_fit(self, st: CoreState, p: ControllerParams, step: IKStep, dt: float
                                ) -> IKStep | None:
        """If ``step`` asks a joint for more than its acceleration limit, the step that keeps as much
        of the servo's change of the hand's motion as the joints allow: a blend between coasting (the
        hand keeps its velocity) and ``step``, its share found per joint from the (nearly linear)
        joint accelerations of the two. None if ``step`` fits."""
        ref = st.ref
        amax = 0.98 * self.bounds.max_acc * dt * dt
        base = ref.q + ref.qd * dt  # where every joint would coast to
        dev = step.q - base
        if np.all(np.abs(dev) <= amax):
            return None
        v, w = ref.vel, ref.w
        c_pos = (ref.pos[0] + v[0] * dt, ref.pos[1] + v[1] * dt, ref.pos[2] + v[2] * dt)
        c_rot = quat_normalize(quat_mul(quat_from_rotvec((w[0] * dt, w[1] * dt, w[2] * dt)), ref.rot))
        red = self.redundancy
        pose_law = red.pose_law(p)
        keep = red.kept_swivel(st, p, step)
        coast = red.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, c_pos, c_rot, dt, keep, pose_law)
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
        out = red.stepper.advance(ref.pos, ref.rot, ref.s, ref.q, pos, rot, dt, keep, pose_law)
        return None if isinstance(out, DeadEnd) else out

    @staticmethod
    def _stream_word(st: CoreState) -> str:
        return "twist" if st.goal is not None and st.goal.kind is GoalKind.TWIST else "stream"

    @staticmethod
    def at_rest(st: CoreState) -> bool:
        """The reference's hand stands (its linear and angular velocity below 1e-6)."""
        v, w = st.ref.vel, st.ref.w
        return max(abs(c) for c in (*v, *w)) < 1e-6
