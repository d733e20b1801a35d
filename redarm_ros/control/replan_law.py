"""Never stuck: stall detection of point goals, and the joint-space re-plan (brake, search with
:class:`~redarm_ros.control.replan.JointPlanner`, drive the :class:`~redarm_ros.control.replan.JointPath`,
hand back to the attractor) or BLOCKED with the reason. :class:`ReplanLaw` is the part of
:class:`~redarm_ros.control.reach_controller.ReachController` that does it; its methods take the
controller's :class:`~redarm_ros.control.state.CoreState` and parameters. Units: m, rad, s.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from redarm_ros.control.command import CommandShaper, SceneView
from redarm_ros.control.ik_step import pose_matrix
from redarm_ros.control.joint_limits import JointBounds
from redarm_ros.control.params import ControllerParams, ReplanParams
from redarm_ros.control.redundancy import Redundancy
from redarm_ros.control.replan import JointPath
from redarm_ros.control.state import CoreState, Mode
from redarm_ros.control.types import GoalKind, Phase
from redarm_ros.kinematics.quaternion import quat_angle

LOG = logging.getLogger(__name__)


class ReplanLaw:
    """Stall detection and the joint-space re-plan (see the module docstring): the ``redundancy``
    strategy (the arm's planner), the ``command`` part, the joint ``bounds`` and the ``view`` of the
    scene."""

    def __init__(self, redundancy: Redundancy, command: CommandShaper, bounds: JointBounds,
                 view: SceneView) -> None:
        self.redundancy = redundancy
        self.command = command
        self.bounds = bounds
        self.view = view

    def start(self, st: CoreState, p: ControllerParams, reason: str) -> None:
        """Re-plan in joint space (PLAN) for ``reason``; hold instead if re-planning is off, BLOCKED after
        ``max_replans``."""
        st.route = None  # (a corridor route is left for good)
        if not p.replan.enabled:
            self.command.hold(st, reason)
            return
        st.progress.replans += 1
        if st.progress.replans > p.replan.max_replans:
            self.block(st, f"gave up after {p.replan.max_replans} re-plans; last: {reason}")
            return
        LOG.info("re-planning in joint space: %s", reason)
        st.mode = Mode.PLAN
        st.planner = None
        st.path = None
        st.plan_reason = reason
        st.phase = Phase.REPLANNING
        st.message = f"re-planning in joint space: {reason}"

    @staticmethod
    def block(st: CoreState, why: str) -> None:
        """Give the goal up: hold where the command is, phase BLOCKED with ``why``."""
        LOG.warning("goal blocked: %s", why)
        st.mode = Mode.HOLD
        st.planner = None
        st.path = None
        st.phase = Phase.BLOCKED
        st.message = why
        st.ref.q = st.cmd.q.copy()
        st.ref.qd = np.zeros_like(st.ref.q)

    def end_joint_motion(self, st: CoreState) -> bool:
        """In PLAN/JOINT: drop the planner and its path, the reference goes on from its motion
        (Cartesian again); the caller picks the next mode. False (nothing done) in any other mode."""
        if st.mode not in (Mode.PLAN, Mode.JOINT):
            return False
        st.planner = None
        st.path = None
        self.command.resync_reference(st, keep_velocity=True)
        return True

    def plan_step(self, st: CoreState, p: ControllerParams, dt: float) -> None:
        """Brake to rest, then one slice of the joint-space search; its path starts JOINT."""
        if np.any(st.cmd.qd != 0.0):  # brake to rest first, through the guard
            self.command.brake(st, dt)
            return
        if st.planner is None:
            assert st.goal is not None
            st.planner = self.redundancy.new_planner(st, p, pose_matrix(st.goal.pos, st.goal.rot),
                                                     self.view.index.reach_scene.scene)
        if not st.planner.work():
            return
        planner = st.planner
        st.planner = None
        if planner.path is None:
            self.block(st, f"{planner.reason} (after: {st.plan_reason})")
            return
        st.path = JointPath(planner.path, self.bounds.max_vel, self.bounds.max_acc,
                            bends=getattr(planner, "bends", None))  # (bends: JointPlanner's, in free space)
        st.path_t = 0.0
        st.ref.q = st.cmd.q.copy()
        st.ref.qd = np.zeros_like(st.ref.q)
        st.brake_sync = True
        st.mode = Mode.JOINT
        st.message = self.redundancy.plan_message(st, planner)

    def joint_step(self, st: CoreState, p: ControllerParams, dt: float) -> bool:
        """One step along the joint path; True when it has ended at its goal (the caller picks the next
        law), the reference made the command's pose again."""
        path = st.path
        assert path is not None
        st.path_t += dt
        q_ref, _ = path.sample(st.path_t)
        st.ref.qd = (q_ref - st.ref.q) / dt
        st.ref.q = q_ref
        if not self.command.track(st, dt):
            st.path = None
            self.start(st, p, f"the collision guard stopped the joint-space move ({st.message})")
            return False
        done = st.path_t >= path.duration and float(np.max(np.abs(st.cmd.q - q_ref))) <= 1e-9 \
            and float(np.max(np.abs(st.cmd.qd))) <= 1e-9
        if done:
            st.path = None
            self.command.resync_reference(st, keep_velocity=False)
            st.ref.s_fixed = st.ref.s
            st.message = ""
            st.progress.best = math.inf
            st.progress.t_best = st.time
        return done

    def watch(self, st: CoreState, p: ControllerParams) -> None:
        """Stall detection of point goals: re-plan when :func:`stall_reason` gives a reason."""
        reason = stall_reason(st, p)
        if reason:
            self.start(st, p, reason)


def stall_reason(st: CoreState, params: ControllerParams) -> str:
    """Track the progress of a point goal in ``st.progress`` and say why to re-plan ('' = go on).

    Reasons (see :class:`~redarm_ros.control.params.ReplanParams`): held too long, stopped by the
    collision guard too often, overdue, or no progress (creeping, or a detour lasting too long). Only in
    ATTRACTOR mode towards a point goal; progress is tracked also while re-planning is off. ``st.time``
    in s.
    """
    rp: ReplanParams = params.replan
    goal = st.goal
    if goal is None or goal.kind is not GoalKind.POINT or st.mode is not Mode.ATTRACTOR:
        return ""
    pr = st.progress
    d = math.dist(st.cmd.pos, goal.pos)
    a = quat_angle(st.cmd.rot, goal.rot)
    err = d + 0.1 * a
    moving_on = (st.route is not None and st.time - st.route.t_moved < rp.hold_time) \
        or st.corridor_plan is not None
    if moving_on or (d <= params.pos_tolerance and a <= params.ori_tolerance) \
            or err < pr.best - rp.progress:
        # (a corridor route's clock runs only as the hand moves along it: it is progress; so is its
        # planning, the arm holding meanwhile)
        pr.best = err
        pr.t_best = st.time
        pr.travel = 0.0
    pr.travel += st.cmd.tool_speed * (st.time - pr.t_last) if pr.t_last else 0.0
    pr.t_last = st.time
    if st.phase is Phase.HOLDING:
        pr.hold_since = st.time if pr.hold_since is None else pr.hold_since
    else:
        pr.hold_since = None
    if not rp.enabled:
        return ""
    pr.guard_stops = [t for t in pr.guard_stops if st.time - t <= rp.stall_time * 2.0]
    if pr.hold_since is not None and st.time - pr.hold_since >= rp.hold_time:
        return f"held {rp.hold_time:.1f} s ({st.message})"
    if len(pr.guard_stops) >= rp.guard_stops:
        pr.guard_stops = []
        return (f"the collision guard stopped the arm {rp.guard_stops} times in "
                f"{2.0 * rp.stall_time:.1f} s ({st.message or 'sliding along an obstacle'})")
    if st.time > pr.due and err > 0.01:
        return f"overdue: {d * 1e3:.0f} mm, {a:.2f} rad from the goal after {st.time - goal.since:.1f} s"
    since = st.time - pr.t_best
    creeping = since >= rp.stall_time and pr.travel < rp.stall_travel
    if creeping or since >= rp.detour_time:
        why = f"; {st.message}" if st.message else ""
        return f"no progress for {since:.1f} s ({d * 1e3:.0f} mm, {a:.2f} rad from the goal{why})"
    return ""
