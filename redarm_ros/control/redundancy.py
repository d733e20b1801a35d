"""What the arm's redundancy adds to the controller, as one strategy object per arm type.

:class:`Redundancy` is what :class:`~redarm_ros.control.reach_controller.ReachController` asks of it:
the arm's IK stepper and collision guard, the reference at a reset or resync, the swivel law of every
step (the attractor's and the servo's), the route check and the joint-space planner of a point goal,
the goal check, and the swivel corridor. :class:`SwivelRedundancy` is the 7-DOF swivel arm's: the swivel
dynamics (eq. 31 of the swivel paper) or the attractor paper's eq. 22-24, the elbow's rest swivel at a
point goal, the pose-following swivel law while tracking, and the straight route through the swivel
corridor (without one, two straight legs through a via pose: :mod:`~redarm_ros.control.via_route`);
the 6-DOF arm's (no self-motion) is :class:`~redarm_ros.control.reach6.NoRedundancy`.
Methods take the controller's :class:`~redarm_ros.control.state.CoreState` and parameters. Units: m,
rad, s.
"""

from __future__ import annotations

import copy
import math
import struct
from collections.abc import Callable
from dataclasses import replace
from typing import Protocol

import numpy as np

from redarm_ros.control.corridor_route import (
    STRAIGHT_WINDOW,
    CorridorRoute,
    plan_route,
    route_clearance,
    route_joints,
    timed_route,
)
from redarm_ros.control.elbow import ArmGeometry, ElbowCircle, elbow_circle
from redarm_ros.control.goal_check import check_goal, stream_feasibility
from redarm_ros.control.goal_hint import BaseMoveHints
from redarm_ros.control.guard import CollisionGuard, describe
from redarm_ros.control.ik_step import IKStep, IKStepper, SwivelFn, pose_matrix, pose_of
from redarm_ros.control.ik_step6 import IKStepper6
from redarm_ros.control.joint_limits import JointBounds, braking_speed, joint_share_acc
from redarm_ros.control.paper_redundancy import MODE as PAPER_MODE
from redarm_ros.control.paper_redundancy import PaperSwivel
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.replan import JointPlanner, PathSearch, check_route, move_time
from redarm_ros.control.state import REST_SPEED_SHARE, CoreState, Mode, Reference
from redarm_ros.control.stream_swivel import (
    OFFSET_EPS,
    closing_acc,
    offset_rate,
    shoulder_sine,
    time_to_axis,
    wrap_offset,
)
from redarm_ros.control.swivel_dynamics import SwivelDynamics, SwivelForces, wrap_angle
from redarm_ros.control.types import GoalCheck, Phase, Quat, Vec3
from redarm_ros.control.via_route import VIA_SLACK, ViaRoute, ViaSearch, plan_via_route
from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.geometry.broadphase import SceneIndex
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics.protocols import ControlledSwivelArm

#: swivels sampled along the goal's in-limit swivel interval to find where the elbow can rest
REST_SAMPLES = 64

#: a corridor route whose minimum-jerk profile in progress would take longer than this many times a
#: joint-space move (or SLOW_SLACK s more) is paced (:func:`~redarm_ros.control.corridor_route.route_pace`)
PACE_AFTER = 4.0
#: s: the least extra time a corridor route may take beyond a joint-space move (replan.corridor_max_slowdown)
SLOW_SLACK = 8.0

#: rad: near obstacles a corridor route is taken only if it ends this near the preferred swivel (the swivel
#: dynamics would turn the elbow on after it, the phase going back from REACHED)
REST_OFFSET = 0.05

#: the planning of a corridor route, run in a worker thread: the route, or None and why there is none
CorridorJob = Callable[[], tuple[CorridorRoute | None, str]]
#: the goal's poses predicted up to a horizon (s) ahead: (tau s, 4x4) each
PosesAhead = Callable[[float], list[tuple[float, np.ndarray]]]


class Redundancy(Protocol):
    """What the controller core asks of an arm's redundancy (see the module docstring)."""

    @property
    def geom(self) -> ArmGeometry:
        """The arm's geometry (shoulder, upper arm and forearm lengths, wrist in the tool frame)."""
        ...

    @property
    def stepper(self) -> IKStepper | IKStepper6:
        """The IK step of the arm (the swivel arm's or the 6-DOF arm's)."""
        ...

    @property
    def guard(self) -> CollisionGuard:
        """The collision guard with the arm's lever arms."""
        ...

    def scene_index(self, scene: Scene, p: ControllerParams) -> SceneIndex:
        """The broad phase of ``scene``: the obstacles within the arm's reach."""
        ...

    def reference(self, q: np.ndarray, T: np.ndarray, pos: Vec3, rot: Quat, kp: np.ndarray) -> Reference:
        """The reference at a reset to joints ``q`` (pose ``T``, key points ``kp``)."""
        ...

    def resync(self, st: CoreState, T: np.ndarray, keep_velocity: bool) -> None:
        """The swivel part of a reference made the command's pose ``T`` (the rest is done)."""
        ...

    def elbow_circle(self, st: CoreState) -> ElbowCircle | None:
        """The elbow circle to display."""
        ...

    def slide_geom(self, st: CoreState) -> ArmGeometry:
        """The geometry the workspace slide uses at the reference."""
        ...

    def swivel_fn(self, st: CoreState, p: ControllerParams, dt: float, scene: Scene) -> SwivelFn:
        """The swivel the dynamics asks for at a proposed pose (point goals, and tracking without the
        pose law)."""
        ...

    def pose_law(self, p: ControllerParams) -> bool:
        """Does the swivel follow the pose while tracking (``servo.swivel_law`` pose)?"""
        ...

    def servo_swivel_fn(self, st: CoreState, p: ControllerParams, dt: float, scene: Scene,
                        poses_ahead: PosesAhead) -> SwivelFn:
        """The swivel while tracking."""
        ...

    def kept_swivel(self, st: CoreState, p: ControllerParams, step: IKStep) -> SwivelFn:
        """The swivel of ``step`` for another pose of the same step."""
        ...

    def onto_preferred_swivel(self, st: CoreState, p: ControllerParams) -> None:
        """After a resync while tracking: the reference's swivel back on the pose's preferred one."""
        ...

    def path_joints(self, st: CoreState, p: ControllerParams, dt: float, poses: np.ndarray,
                    ends: np.ndarray, poses_ahead: PosesAhead) -> np.ndarray | None:
        """While tracking: the joints (k, n) at the predicted ``poses`` (k, 4, 4), ``ends`` steps of ``dt`` s
        from now (ascending), along the servo's swivel law from ``st.ahead``'s offset (moved on by one
        step), continuous from the reference; None where they cannot be followed ahead (no pose law, out
        of reach, a branch change)."""
        ...

    def plan_offset(self, st: CoreState, p: ControllerParams) -> None:
        """Where the plan ahead starts: ``st.ahead``'s offset from the reference."""
        ...

    def joint_step(self, st: CoreState, p: ControllerParams, q: np.ndarray) -> IKStep | None:
        """The reference step to joints ``q`` (their pose and swivel); None at a stretched pose."""
        ...

    def route_dead_end(self, st: CoreState, p: ControllerParams, T: np.ndarray) -> str:
        """Why the attractor should not take the straight route to ``T`` ('' if it should)."""
        ...

    def corridor_asked(self, st: CoreState, p: ControllerParams, scene: Scene) -> bool:
        """Is a point goal set now planned through the swivel corridor?"""
        ...

    def corridor_job(self, st: CoreState, p: ControllerParams, T: np.ndarray, scene: Scene) -> CorridorJob:
        """The planning of the route to ``T`` through the swivel corridor, checked against ``scene``, for
        the worker thread."""
        ...

    def new_planner(self, st: CoreState, p: ControllerParams, T: np.ndarray, scene: Scene) -> PathSearch:
        """The resumable joint-space search towards tool pose ``T``."""
        ...

    def plan_message(self, st: CoreState, planner: PathSearch) -> str:
        """What ``~/state`` says once the joint path starts."""
        ...

    def check_goal(self, T: object, scene: Scene, p: ControllerParams, q_now: np.ndarray | None,
                   hints: BaseMoveHints) -> GoalCheck:
        """Check a goal pose; a goal out of reach gets the base-move suggestion of ``hints``."""
        ...

    def stream_feasibility(self, T: np.ndarray, scene: Scene, p: ControllerParams) -> str:
        """Why a stream sample cannot be followed exactly ('' if nothing is known against it)."""
        ...

    def forces(self, st: CoreState, scene: Scene, p: ControllerParams) -> SwivelForces | None:
        """Swivel forces at the reference (for plots and diagnostics)."""
        ...


def _brake_for_limit(sd: float, margins: tuple[float, float, float], eps: float, s_acc: float,
                     dt: float) -> float:
    """The swivel rate ``sd`` (rad/s) capped so that the swivel can still stop, decelerating at
    ``s_acc``, before the nearest joint reaches its limit. ``margins``: the joints' least limit margin
    (rad) at s, s + eps, s - eps. Run into a limit at speed, the IK step would stop the swivel at once,
    and the joints, braking each at its own acceleration limit, would take the hand off its pose."""
    m0, m_plus, m_minus = margins
    slope = ((m_plus if sd > 0.0 else m_minus) - m0) / eps  # margin change per rad of swivel, ahead
    if slope >= 0.0:
        return sd
    cap = float(braking_speed(max(m0, 0.0) / -slope, s_acc, dt))
    return max(-cap, min(cap, sd))


def _swivel_low(circle: ElbowCircle) -> float | None:
    """Swivel (rad) of the lowest elbow position on the circle; None if the circle is horizontal."""
    az, bz = circle.a[2], circle.b[2]
    if math.hypot(az, bz) < 0.05:
        return None
    return math.atan2(-bz, -az)


class SwivelRedundancy:
    """The redundancy of a 7-DOF swivel arm (see the module docstring): ``arm`` with ``params`` as the
    controller is built (the dynamics keep their parameters), its joint ``bounds``."""

    def __init__(self, arm: ControlledSwivelArm, params: ControllerParams, bounds: JointBounds) -> None:
        p = params
        self.arm = arm
        self.bounds = bounds
        self.geom = ArmGeometry.from_arm(arm)
        self.swivel_dyn = SwivelDynamics(p.swivel)
        self.paper_swivel = PaperSwivel(p.paper_swivel, p.capsules, p.swivel.max_rate, arm.lower, arm.upper)
        self.stepper = IKStepper(arm, self.geom, p.flip_ratio, p.swivel_search_step, p.swivel_search_count)
        self.guard = CollisionGuard(arm, p.capsules, p.collision_margin, p.guard_step)
        # swivel_acc_share's last answer: (params, the reference's pose, swivel and joints as bytes, value)
        self._acc_share: tuple[ControllerParams, bytes, float] | None = None

    # -- the reference ----------------------------------------------------------------------------
    def scene_index(self, scene: Scene, p: ControllerParams) -> SceneIndex:
        """The obstacles within reach of the shoulder."""
        g = self.geom
        reach = g.upper + g.fore + float(np.linalg.norm(g.wrist_in_tool))
        return SceneIndex(scene, g.shoulder, reach + max(p.capsules.radii), p.broad_phase_margin)

    def reference(self, q: np.ndarray, T: np.ndarray, pos: Vec3, rot: Quat, kp: np.ndarray) -> Reference:
        """The reference at joints ``q``: its swivel the desired and the fixed one; no elbow circle at a
        singular pose (arm stretched: the planner moves first)."""
        s = float(self.arm.swivel(q))
        try:
            circle: ElbowCircle | None = elbow_circle(self.geom, T)
        except UnreachableError:
            circle = None
        return Reference(q.copy(), pos, rot, s, circle, s_des=s, s_fixed=s)

    def resync(self, st: CoreState, T: np.ndarray, keep_velocity: bool) -> None:
        """Circle and swivel from FK; the swivel's rates start afresh (its rate by a step ahead when the
        velocity is kept)."""
        ref, cmd = st.ref, st.cmd
        try:
            ref.circle = elbow_circle(self.geom, T)
            ref.s = float(self.arm.swivel(cmd.q))
        except UnreachableError:
            ref.circle = None
        ref.sdot = 0.0
        ref.sdot_dyn = 0.0
        ref.sdot_want, ref.want_over_since = math.nan, math.inf
        ref.swivel_moved_at = st.time
        if keep_velocity and ref.circle is not None and np.any(cmd.qd != 0.0):  # the rate, a step ahead
            h = 1e-3
            q_h = np.clip(cmd.q + h * cmd.qd, self.bounds.lower, self.bounds.upper)
            ref.sdot = wrap_angle(float(self.arm.swivel(q_h)) - ref.s) / h

    def elbow_circle(self, st: CoreState) -> ElbowCircle | None:
        """The reference's elbow circle (None at a stretched pose)."""
        return st.ref.circle

    def slide_geom(self, st: CoreState) -> ArmGeometry:
        """Fixed for a swivel arm."""
        return self.geom

    # -- the swivel law ---------------------------------------------------------------------------
    def swivel_fn(self, st: CoreState, p: ControllerParams, dt: float, scene: Scene) -> SwivelFn:
        """The swivel the dynamics asks for at a proposed pose (see :data:`ik_step.SwivelFn`), among the
        obstacles of ``scene``."""
        # Tracking a moving goal, the preferred swivel moves with it (e.g. the highest elbow turns as the
        # wrist moves): its change is fed forward, so the elbow does not lag behind its preference
        # (a lagging elbow costs the joints much more motion than the hand needs).
        feed = st.mode is Mode.SERVO and p.swivel_mode != "fixed" and st.ref.circle is not None
        s_des_prev = self.desired_swivel(st, p, st.ref.circle) if feed and st.ref.circle is not None else 0.0
        s_acc_feed = self.swivel_acc_share(st, p) if feed else p.max_swivel_acc

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            if p.swivel_mode == "fixed":
                st.ref.sdot_want, st.ref.want_over_since = 0.0, math.inf
                return st.ref.s_fixed, st.ref.s_fixed, False
            s_des = self.desired_swivel(st, p, circle)
            margins = None
            if p.swivel_mode == PAPER_MODE:  # the attractor paper's eq. 22-24 (paper_redundancy.py)
                paper = self.paper_swivel.step(circle, T, s0, s_des, st.ref.q, dt, scene, self.stepper)
                s_new, clearance = paper.s, paper.clearance
            else:
                margins = self.stepper.limit_margins(T, s0, st.ref.q, p.swivel.eps, p.swivel.lim_threshold)
                forces = self.swivel_dyn.forces(circle, s0, scene, p.capsules, margins)
                s_new, clearance = self.swivel_dyn.step(s0, s_des, dt, forces), forces.clearance
            # The swivel rate changes by at most max_swivel_acc per second.
            sd = wrap_angle(s_new - s0) / dt
            st.ref.sdot_want = sd  # (the dynamics' own: the feed-forward is added below)
            over = abs(sd) > 2.0 * p.settle_swivel_rate
            st.ref.want_over_since = min(st.ref.want_over_since, st.time) if over else math.inf
            if feed:
                # The dynamics' own rate (attraction, obstacles, limits) within its share of the
                # joints' acceleration; the preferred swivel's motion is fed forward on top.
                sd = max(st.ref.sdot_dyn - s_acc_feed * dt, min(st.ref.sdot_dyn + s_acc_feed * dt, sd))
                st.ref.sdot_dyn = sd
                sd += wrap_angle(s_des - s_des_prev) / dt
            else:
                s_acc = joint_share_acc(abs(st.ref.sdot), p.max_swivel_acc, st.ref.qd, self.bounds.max_acc,
                                        p.joint_brake_share)
                sd = max(st.ref.sdot - s_acc * dt, min(st.ref.sdot + s_acc * dt, sd))
                if margins is not None and sd != 0.0:
                    sd = _brake_for_limit(sd, margins, p.swivel.eps, s_acc, dt)
                sd = self._settling_rate_cap(st, p, sd)
            st.ref.s_des = s_des
            return wrap_angle(s0 + sd * dt), s_des, clearance < p.elbow_priority_clearance

        return swivel

    def swivel_acc_share(self, st: CoreState, p: ControllerParams) -> float:
        """While tracking: the largest change of the swivel rate (rad/s^2) that keeps every joint within
        ``joint_brake_share`` of its acceleration limit, from how much each joint turns per radian of
        swivel at the reference (the rest is the hand's, which has priority); at most max_swivel_acc.
        (A step that plans ahead and then tracks asks twice at the same reference: the IK solve is
        done once.)"""
        ref = st.ref
        key = struct.pack("8d", *ref.pos, *ref.rot, ref.s) + ref.q.tobytes()
        last = self._acc_share
        if last is not None and last[0] is p and last[1] == key:
            return last[2]
        s_acc = p.max_swivel_acc
        T_ref = pose_matrix(ref.pos, ref.rot)
        pick = self.stepper.solve(T_ref, ref.s + 0.01, ref.q, 1.0)
        if pick is not None:
            dq_ds = np.abs(pick[0] - ref.q) / 0.01
            with np.errstate(divide="ignore"):
                lim = np.where(dq_ds > 1e-9, p.joint_brake_share * self.bounds.max_acc / dq_ds, np.inf)
            s_acc = min(s_acc, float(lim.min()))
        self._acc_share = (p, key, s_acc)
        return s_acc

    def _settling_rate_cap(self, st: CoreState, p: ControllerParams, sd: float) -> float:
        """With the hand at the goal, the swivel rate ``sd`` (rad/s) capped so that no joint turns
        faster than ``settle_speed_share`` of its velocity limit (the joint rates of the last step
        scaled with the swivel rate: with the hand still, the joints move with the swivel alone). The
        elbow's way to its preferred swivel is a self-motion nobody waits for; at full joint speed the
        joints could not follow its turns within their acceleration limits and took the hand along."""
        goal = st.goal
        if goal is None or not goal.point_at(st.ref.pos, p.pos_tolerance):
            return sd
        # Once REACHED (the user acts on it), what is left of the elbow's way is a creep that keeps the
        # arm at rest as REACHED defines it: the swivel below its settled rate, every joint below its
        # rest share (near the shoulder singularity a slow swivel turns joints 1 and 3 fast).
        reached = st.phase is Phase.REACHED
        cap = p.settle_swivel_rate if reached else math.inf
        rate = abs(st.ref.sdot)
        ratio = float((np.abs(st.ref.qd) / self.bounds.max_vel).max())
        if rate >= 1e-9 and ratio >= 1e-12:
            cap = min(cap, (REST_SPEED_SHARE if reached else p.settle_speed_share) * rate / ratio)
        return max(-cap, min(cap, sd))

    def desired_swivel(self, st: CoreState, p: ControllerParams, circle: ElbowCircle) -> float:
        """The preferred swivel at ``circle``, moved where the elbow can rest once the hand is at a point
        goal (:meth:`_feasible_at_goal`); where the circle is horizontal, the last desired swivel."""
        if p.swivel_reference != "absolute" and _swivel_low(circle) is None:
            return st.ref.s_des
        return self._feasible_at_goal(st, p, self.preferred_swivel(st, p, circle))

    def preferred_swivel(self, st: CoreState, p: ControllerParams, circle: ElbowCircle) -> float:
        """The preferred swivel (rad) at ``circle``: ``preferred_swivel`` from the highest or lowest elbow
        (``swivel_reference``), or absolute; where the circle is horizontal (no highest elbow), the last
        desired swivel."""
        if p.swivel_reference == "absolute":
            return wrap_angle(p.preferred_swivel)
        low = _swivel_low(circle)
        if low is None:
            return st.ref.s_des
        ref = low if p.swivel_reference == "low" else low + math.pi
        return wrap_angle(ref + p.preferred_swivel)

    def _feasible_at_goal(self, st: CoreState, p: ControllerParams, s_des: float) -> float:
        """With the hand at the goal (within twice ``pos_tolerance``), ``s_des`` moved to where the elbow
        can rest: the nearest of :data:`REST_SAMPLES` swivels along the in-limit interval of the arm's
        branch that holds the current swivel (closed form) at which every joint keeps the swivel
        dynamics' ``lim_threshold`` from its limits, or, if none does, the one with the widest margin. A
        preferred swivel beyond a joint limit, or within the joint-limit force's reach, pins the elbow
        where that force and the attraction meet, and it chatters there (joints at 10-15 % of their
        speed, ~2 Hz) and never settles."""
        goal = st.goal
        interval = getattr(self.arm, "swivel_interval", None)
        # (from twice the tolerance on: when REACHED is first judged, with the hand within it, the elbow's
        # wanted rate is already the one towards its rest swivel, not the one on the way)
        if goal is None or interval is None or not goal.point_at(st.ref.pos, 2.0 * p.pos_tolerance):
            return s_des
        if not goal.rest_known:  # once per goal: the hand stays there
            goal.rest_known = True
            T_goal = pose_matrix(goal.pos, goal.rot)
            # the interval at the goal pose itself (not at the hand's pose, up to 2 mm away): where a
            # joint's extreme along the circle just touches its limit, 2 mm split the interval at a limit
            # on the reference's own branch: with a joint at its limit, 2 mm can take that branch a hair
            # beyond it, and the nearest in-limit solution was another branch (a flipped wrist), whose
            # interval and rest swivel the elbow could not reach
            q_goal = self.stepper.follow(T_goal, st.ref.s, st.ref.q)
            if q_goal is not None:
                q_goal = np.clip(q_goal, self.stepper.lower, self.stepper.upper)
            goal.rest = None if q_goal is None else \
                self._rest_swivels(st, p, interval(q_goal), T_goal, q_goal)
        if goal.rest is None:
            return s_des
        a, samples, ok = goal.rest
        x = a + ((s_des - a) % (2.0 * math.pi))  # s_des on the interval's unwrapped axis
        # the nearest sample where the margins were checked (between two of them a joint may still dip
        # into the limit force's reach); the one of last step while it is within a sample spacing of
        # that: a preferred swivel midway between the two ends of a stretch near a limit had them take
        # turns as the hand settled, and the elbow turned back and forth after REACHED
        # (around the circle: a preferred swivel just below the interval's start is nearest to that
        # start, not to its far end, where x lands on the unwrapped axis)
        gap = np.abs(samples - x)
        dist = np.minimum(gap, 2.0 * math.pi - gap) + np.where(ok, 0.0, 1e3)
        k = int(np.argmin(dist))
        last = goal.rest_pick
        if last is not None and len(samples) > 1 and dist[last] <= dist[k] + (samples[1] - samples[0]):
            k = last
        goal.rest_pick = k
        return wrap_angle(float(samples[k]))

    def _rest_swivels(self, st: CoreState, p: ControllerParams, iv: tuple[float, float] | None, T: np.ndarray,
                      q0: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
        """Samples of the in-limit swivel interval ``iv`` of pose T (the interval's start, the swivels
        unwrapped from it, and which of them keep every joint ``lim_threshold`` inside its limits; if
        none does, only the one with the widest margin counts). ``q0``: the joints at T at the current
        swivel, from which the samples are followed along the elbow circle either way; a sample beyond
        one where a joint passes its limit is out of reach. The interval counts a wide joint in limits
        on any 2 pi copy, but the elbow cannot jump to another copy: a joint 5 at its limit made the
        elbow pull towards a swivel on the far side of that limit, held there, and never settle."""
        if iv is None:
            return None
        a, b = iv
        samples = np.linspace(a, b, REST_SAMPLES)
        margins = np.full(REST_SAMPLES, -math.inf)
        x0 = a + (st.ref.s - a) % (2.0 * math.pi)  # the current swivel on the interval's axis
        first_up = int(np.searchsorted(samples, x0))
        for walk in (range(first_up, REST_SAMPLES), range(first_up - 1, -1, -1)):
            q = q0
            for i in walk:
                q = self.stepper.follow(T, wrap_angle(float(samples[i])), q)
                if q is None:
                    break
                margins[i] = self.stepper.margin(q)
                if margins[i] < 0.0:
                    margins[i] = -math.inf
                    break
        if not np.isfinite(margins).any():
            return None
        ok = margins >= p.swivel.lim_threshold
        if not ok.any():
            ok = margins >= margins.max()
        return a, samples, ok

    # -- the swivel while tracking ----------------------------------------------------------------
    def pose_law(self, p: ControllerParams) -> bool:
        """Does the swivel follow the pose while tracking (``servo.swivel_law`` pose, with the swivel
        dynamics in charge of the elbow)?"""
        return p.servo.swivel_law == "pose" and p.swivel_mode == "dynamics"

    def onto_preferred_swivel(self, st: CoreState, p: ControllerParams) -> None:
        """After a resync: the reference's swivel back on the pose's preferred one (joints nearest the
        command's, on their branch) where that is continuous, so the lagging command's twist of joints 1
        and 3 near the shoulder axis does not become the offset (a circle over the shoulder at 0.25 m/s:
        lap 1 within 9 mm instead of 29 mm)."""
        ref = st.ref
        if ref.circle is None:
            return
        s_pref = self.preferred_swivel(st, p, ref.circle)
        T = pose_matrix(ref.pos, ref.rot)
        pick = self.stepper.solve(T, s_pref, ref.q, p.dt)
        if pick is None or pick[1] > p.flip_ratio:  # (another branch: the offset closes on its own)
            return
        ref.q, ref.s = pick[0], s_pref

    def servo_swivel_fn(self, st: CoreState, p: ControllerParams, dt: float, scene: Scene,
                        poses_ahead: PosesAhead) -> SwivelFn:
        """The swivel while tracking: the preferred swivel of the pose plus an offset that returns to 0
        (:mod:`~redarm_ros.control.stream_swivel`, ``servo.swivel_law`` pose; ``poses_ahead`` the goal's
        predicted poses), else the attractor's."""
        ref = st.ref
        if not self.pose_law(p) or ref.circle is None:
            return self.swivel_fn(st, p, dt, scene)
        sw = p.swivel
        pref_prev = self.preferred_swivel(st, p, ref.circle)
        offset = wrap_offset(ref.s, pref_prev)
        s_acc = self.swivel_acc_share(st, p)
        close_acc = self._offset_close_acc(st, p, offset, s_acc, poses_ahead, hold=ref.acc_limited)

        def preferred(circle: ElbowCircle) -> float:
            return self.preferred_swivel(st, p, circle)

        rate0 = ref.sdot_dyn

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            s_pref = preferred(circle)
            e0 = wrap_offset(s0, pref_prev)
            margins = self.stepper.limit_margins(T, s0, ref.q, sw.eps, sw.lim_threshold)
            f = self.swivel_dyn.forces(circle, s0, scene, p.capsules, margins)
            push = (sw.lam_obs * f.obstacle + sw.lam_lim * f.limits) / sw.tau
            rate = offset_rate(e0, rate0, push, close_acc, sw.max_rate, s_acc, dt)
            ref.sdot_dyn = rate
            ref.sdot_want = rate
            over = abs(rate) > 2.0 * p.settle_swivel_rate
            ref.want_over_since = min(ref.want_over_since, st.time) if over else math.inf
            ref.s_des = s_pref
            return wrap_angle(s_pref + e0 + rate * dt), s_pref, f.clearance < p.elbow_priority_clearance

        return swivel

    def _offset_close_acc(self, st: CoreState, p: ControllerParams, offset: float, s_acc: float,
                          poses_ahead: PosesAhead, hold: bool = False) -> float:
        """The acceleration (rad/s^2) at which the pose law's ``offset`` closes: ``servo.swivel_acc`` within
        the joints' share ``s_acc`` (0 with ``hold``: the hand needs the joints' whole acceleration), harder
        where the elbow at that offset would pass near the shoulder axis within ``servo.lookahead``."""
        sp = p.servo
        close_acc = 0.0 if hold else min(sp.swivel_acc, s_acc)
        if abs(offset) > OFFSET_EPS and sp.lookahead > 0.0:
            def preferred(circle: ElbowCircle) -> float:
                return self.preferred_swivel(st, p, circle)

            hit = time_to_axis(self.geom, poses_ahead(sp.lookahead), offset, preferred, sp.axis_margin)
            if hit is not None:
                close_acc = closing_acc(offset, 0.5 * hit, min(sp.swivel_acc, s_acc), s_acc)
        return close_acc

    def path_joints(self, st: CoreState, p: ControllerParams, dt: float, poses: np.ndarray,
                    ends: np.ndarray, poses_ahead: PosesAhead) -> np.ndarray | None:
        """The joints (k, 7) at the predicted ``poses``, ``ends`` steps of ``dt`` s from now (ascending), at
        the pose law's swivel: the preferred swivel plus the offset of ``st.ahead``, which closes as the law
        closes it without forces (``st.ahead`` moves on by one step); each the in-limit solution nearest
        the one before, starting from the reference. None without the pose law, where a pose is out of
        reach, or where the motion between two poses would change the branch."""
        ref, ahead = st.ref, st.ahead
        if not self.pose_law(p) or ref.circle is None:
            return None
        offset, rate = ahead.offset, ahead.rate
        offsets = np.zeros(len(poses))
        first = (0.0, 0.0)
        if abs(offset) > OFFSET_EPS:
            s_acc = self.swivel_acc_share(st, p)
            close_acc = self._offset_close_acc(st, p, offset, s_acc, poses_ahead)
            k = 0
            for n in range(1, int(ends[-1]) + 1):
                if offset != 0.0:
                    rate = offset_rate(offset, rate, 0.0, close_acc, p.swivel.max_rate, s_acc, dt)
                    lands = abs(rate * dt) >= abs(offset) and rate * offset < 0.0
                    offset, rate = (0.0, 0.0) if lands else (offset + rate * dt, rate)
                if n == 1:
                    first = (offset, rate)
                if n == ends[k]:
                    offsets[k] = offset
                    k += 1
        q = ref.q
        rows = np.empty((len(poses), self.arm.n))
        last = 0
        for k, T in enumerate(poses):
            try:
                circle = elbow_circle(self.geom, T)
            except UnreachableError:
                return None
            s = wrap_angle(self.preferred_swivel(st, p, circle) + float(offsets[k]))
            pick = self.stepper.solve(T, s, q, (ends[k] - last) * dt)
            if pick is None or pick[1] > p.flip_ratio:
                return None
            q = rows[k] = pick[0]
            last = ends[k]
        ahead.offset, ahead.rate = first
        return rows

    def plan_offset(self, st: CoreState, p: ControllerParams) -> None:
        """The pose law's offset and rate where the plan ahead starts: the reference's (``st.ahead``)."""
        ref = st.ref
        if ref.circle is not None:
            st.ahead.offset = wrap_offset(ref.s, self.preferred_swivel(st, p, ref.circle))
            st.ahead.rate = ref.sdot_dyn

    def joint_step(self, st: CoreState, p: ControllerParams, q: np.ndarray) -> IKStep | None:
        """The reference step to joints ``q`` (clipped into the limits): their pose, swivel and elbow
        circle; None at a stretched pose."""
        q = np.clip(q, self.bounds.lower, self.bounds.upper)
        T = np.asarray(self.arm.fk(q), float)
        try:
            circle = elbow_circle(self.geom, T)
        except UnreachableError:
            return None
        pos, rot = pose_of(T)
        s = float(self.arm.swivel(q))
        return IKStep(q, pos, rot, s, self.preferred_swivel(st, p, circle), circle, 1.0)

    def kept_swivel(self, st: CoreState, p: ControllerParams, step: IKStep) -> SwivelFn:
        """The swivel of ``step`` for another pose of the same step (the acceleration fit's coasting pose
        and blend): the swivel itself; with the pose law near the shoulder axis (the elbow within
        ``servo.axis_margin``), its offset from the preferred swivel (the elbow stays in the vertical
        plane through the wrist where the step had it there: a small offset there turns joint 1 far).
        Elsewhere the pose law's offset takes up the difference and closes once the joints have
        acceleration to spare (keeping it costs the hand more of the joints' acceleration)."""
        if not self.pose_law(p) or step.circle is None \
                or shoulder_sine(step.circle, step.s) >= p.servo.axis_margin:
            return lambda c, T, s0: (step.s, step.s_des, False)
        off = wrap_offset(step.s, self.preferred_swivel(st, p, step.circle))

        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            s_pref = self.preferred_swivel(st, p, circle)
            return wrap_angle(s_pref + off), s_pref, False

        return swivel

    # -- point goals: the route, the corridor, the joint-space planner ----------------------------
    def route_dead_end(self, st: CoreState, p: ControllerParams, T: np.ndarray) -> str:
        """Why the attractor should not take the straight route to ``T`` ('' if it should): a dead end
        on it, or joint motion along it much slower than a joint-space move to the nearest goal
        configuration (e.g. through the shoulder singularity, or the long way round a wide joint). Sets
        the point goal's due time from the route's."""
        T0 = pose_matrix(st.ref.pos, st.ref.rot)
        if p.swivel_mode == "fixed":
            def s_des(_c: ElbowCircle) -> float:
                return st.ref.s_fixed
        else:
            def s_des(c: ElbowCircle) -> float:
                return self.desired_swivel(st, p, c)
        route = check_route(self.stepper, T0, st.ref.s, st.ref.q, T, s_des, p.replan.route_steps,
                            p.speed.v_max, p.max_ori_rate, p.swivel.max_rate)
        # The attractor is given a generous multiple of the route's least time before it counts as
        # overdue (it accelerates gently, slows near obstacles and at the goal).
        st.progress.due = st.time + p.replan.overdue_factor * route.time + p.replan.overdue_slack
        if route.dead_end:
            return route.dead_end
        if route.singular:
            return route.singular
        q_near, info = self.arm.ik_nearest(T, st.ref.q)
        if q_near is None:
            return ""
        t_joint = move_time(np.asarray(q_near, float) - st.ref.q, self.bounds.max_vel, self.bounds.max_acc)
        if route.time > max(p.replan.slow_route * t_joint, t_joint + 2.0):
            return (f"the straight route needs {route.time:.1f} s of joint motion, a joint-space move "
                    f"{t_joint:.1f} s")
        return ""

    def corridor_asked(self, st: CoreState, p: ControllerParams, scene: Scene) -> bool:
        """Is a point goal set now planned through the swivel corridor? Only with the hand at rest and
        with the swivel dynamics in charge of the elbow (the route is checked against ``scene`` once
        planned: :meth:`corridor_job`)."""
        return bool(p.replan.corridor) and p.swivel_mode not in ("fixed", PAPER_MODE) \
            and st.ref.v_tool <= 0.01 and st.att.v <= 0.01 and hasattr(self.arm, "swivel_corridor")

    def corridor_job(self, st: CoreState, p: ControllerParams, T: np.ndarray, scene: Scene) -> CorridorJob:
        """The planning of the straight route to the point goal ``T`` through the swivel corridor, from
        the reference as it is now, or else of a via route: a function of copies (it runs in the worker
        thread) that returns the route, or None and why there is none. A route that does not keep the
        re-planner's clearance (``replan.clearance``) from ``scene`` and from the arm itself is refused."""
        plan = self._corridor_plan(st, p, T)
        guard, need = copy.copy(self.guard), p.replan.clearance  # (the copy counts its own evaluations)
        guard.evaluations = 0
        lower, upper = self.bounds.lower.copy(), self.bounds.upper.copy()
        try:
            s_pref = self.preferred_swivel(st, p, elbow_circle(self.geom, T))
        except UnreachableError:
            s_pref = math.nan  # (no corridor either)
        # what the rest checks read, taken now: the controller thread may set new parameters meanwhile
        arm, geom, dyn = self.arm, self.geom, copy.copy(self.swivel_dyn)
        lim_threshold, capsules = p.swivel.lim_threshold, p.capsules

        def job() -> tuple[CorridorRoute | None, str]:
            route, why = plan()
            if route is None:
                return None, why
            worst = route_clearance(arm, guard, route, scene, need)
            if worst.distance < need:
                return None, f"its route comes within {need:.2f} m: {describe(worst, scene)}"
            if scene.free_space:
                return route, why
            # near obstacles the elbow must be able to rest where the route leaves it: else the swivel
            # dynamics moves it on after the route (a long self-motion, the phase back from REACHED)
            s_end = route.corridor.swivel_at(1.0)
            rest = dyn.forces(elbow_circle(geom, T), s_end, scene, capsules)
            if rest.obstacle != 0.0:
                return None, (f"the elbow would end {rest.clearance:.2f} m from the scene, within the "
                              "obstacle force's reach")
            q_end = route_joints(arm, route, np.array([1.0]))[0]
            if np.min(np.minimum(q_end - lower, upper - q_end)) < lim_threshold:
                return None, "the route ends within the joint-limit force's reach"
            off = abs(wrap_angle(s_end - s_pref))
            if not off <= REST_OFFSET:
                return None, f"the route ends {off:.2f} rad from the preferred swivel"
            return route, why

        return job

    def _corridor_plan(self, st: CoreState, p: ControllerParams, T: np.ndarray) -> CorridorJob:
        """:meth:`corridor_job` without the collision check."""
        rp = p.replan
        arm, q0 = self.arm, st.ref.q.copy()
        # the route starts at the pose of the reference's joints: the reference pose may be off it by
        # the IK step's residual (0.15 mm seen), and the corridor starts from a solution of its start
        T0, T1 = np.asarray(arm.fk(q0), float), np.array(T, float)
        max_vel, max_acc = self.bounds.max_vel.copy(), self.bounds.max_acc.copy()

        def job() -> tuple[CorridorRoute | None, str]:
            # the longest route taken (replan.corridor_max_slowdown): a straight route is worth more
            # patience than the attractor's route. A route slower than PACE_AFTER times a joint-space move
            # in u is paced (it slows where joints 1 and 3 swing near a singularity)
            q_near, _ = arm.ik_nearest(T1, q0)
            t_most, t_pace, t_joint = math.inf, math.inf, math.nan
            if q_near is not None:
                t_joint = move_time(np.asarray(q_near, float) - q0, max_vel, max_acc)
                t_pace = max(PACE_AFTER * t_joint, t_joint + SLOW_SLACK)
                if rp.corridor_max_slowdown > 0.0:
                    t_most = max(rp.corridor_max_slowdown * t_joint, t_joint + SLOW_SLACK)
            try:
                route, why = plan_route(arm, T0, T1, q0, None, rp.corridor_sing_margin,
                                        rp.corridor_limit_margin, p.speed.v_max, p.max_ori_rate,
                                        p.swivel.max_rate, max_vel, max_acc, rp.corridor_share,
                                        pace_after=min(t_most, t_pace), fast=True, window=STRAIGHT_WINDOW)
            except (InvalidInputError, UnreachableError) as e:  # (a start the corridor cannot take)
                return None, f"the corridor cannot start here: {e}"
            if route is not None and route.duration > t_most:
                route, why = None, (f"its route needs {route.duration:.1f} s of joint motion, a joint-space "
                                    f"move {t_joint:.1f} s")
            if route is None and q_near is not None:
                # no straight corridor: two straight legs through the via pose nearest the line
                t_via = min(t_most, t_joint + VIA_SLACK)
                via, search = self._via_route(p, T0, T1, q0, max_vel, max_acc, t_via)
                if via is not None:
                    return replace(via, why=why), why
                why += f"; no via route: {search.summary()}"
            return route, why

        return job

    def _via_route(self, p: ControllerParams, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray,
                   max_vel: np.ndarray, max_acc: np.ndarray, t_most: float
                   ) -> tuple[ViaRoute | None, ViaSearch]:
        """The route from (T0, q0) to T1 through a via pose (:mod:`~redarm_ros.control.via_route`) that
        takes at most ``t_most`` s, or None; and what the search did (runs in the worker thread: no
        controller state)."""
        rp = p.replan
        timing = (p.speed.v_max, p.max_ori_rate, p.swivel.max_rate, max_vel, max_acc, rp.corridor_share)

        def leg(Ta: np.ndarray, Tb: np.ndarray, qa: np.ndarray, preferred: float | None
                ) -> tuple[CorridorRoute | None, str]:
            return plan_route(self.arm, Ta, Tb, qa, preferred, rp.corridor_sing_margin,
                              rp.corridor_limit_margin, *timing)

        def timer(route: CorridorRoute, length: float, angle: float) -> CorridorRoute:
            return timed_route(route, length, angle, *timing, pace_after=t_most)

        return plan_via_route(self.arm, T0, T1, q0, rp.corridor_sing_margin, rp.corridor_limit_margin, leg,
                              timer, max_duration=t_most)

    def new_planner(self, st: CoreState, p: ControllerParams, T: np.ndarray, scene: Scene) -> PathSearch:
        """The resumable joint-space search towards tool pose ``T`` in ``scene``, the elbow towards its
        desired swivel, retreating along the last clear commands if it must."""
        s_pref = None
        try:
            circle: ElbowCircle | None = elbow_circle(self.geom, T)
        except UnreachableError:
            circle = None
        if circle is not None and p.swivel_mode != "fixed":
            s_pref = self.desired_swivel(st, p, circle)
        clear_enough = p.replan.clearance + 2.0 * self.guard.step
        retreat = [q for q, c in reversed(st.history) if c >= clear_enough][::10]
        return JointPlanner(self.stepper, self.guard, scene, st.cmd.q.copy(), T, p.replan, p.unfold_pitch,
                            retreat, s_pref)

    def plan_message(self, st: CoreState, planner: PathSearch) -> str:
        """What ``~/state`` says once the joint path starts."""
        assert st.path is not None and planner.path is not None
        vias = len(planner.path) - 2
        bends = getattr(planner, "bends", None)
        if bends and bends[0] is not None:
            return (f"moving in joint space (bent: the hand's path {bends[0].ratio:.2f} times the line, "
                    f"{st.path.duration:.1f} s): {st.plan_reason}")
        return f"moving in joint space ({vias} via points, {st.path.duration:.1f} s): {st.plan_reason}"

    # -- goals ------------------------------------------------------------------------------------
    def check_goal(self, T: object, scene: Scene, p: ControllerParams, q_now: np.ndarray | None,
                   hints: BaseMoveHints) -> GoalCheck:
        """:func:`~redarm_ros.control.goal_check.check_goal`; a goal out of reach (or without an
        in-limit solution) says where the base should go."""
        check = check_goal(self.arm, self.geom, T, scene, p.capsules, p.goal_scan)
        return hints.annotate(check, T, q_now)

    def stream_feasibility(self, T: np.ndarray, scene: Scene, p: ControllerParams) -> str:
        """:func:`~redarm_ros.control.goal_check.stream_feasibility`."""
        return stream_feasibility(self.geom, T, scene, p.capsules)

    def forces(self, st: CoreState, scene: Scene, p: ControllerParams) -> SwivelForces | None:
        """The swivel forces at the reference; None at a stretched pose."""
        if st.ref.circle is None:
            return None
        return self.swivel_dyn.forces(st.ref.circle, st.ref.s, scene, p.capsules)
