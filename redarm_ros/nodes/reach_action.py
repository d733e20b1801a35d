"""The controller's ``~/reach`` action server (redarm_interfaces/action/Reach).

Wiring only, like the node: the goal check, the motion and the stop are the controller core's
(:class:`~redarm_ros.control.reach_controller.ReachController`: ``check_goal``, ``set_goal``,
``stop``); this module turns them into an rclpy action server that follows rclpy's conventions:

* **goal**: accepted only if it passes the same check as a goal on ``goal_pose`` (frame, finite
  values, unit quaternion, then the core's reach / joint limit / obstacle check). A rejected goal
  leaves a running one alone; the reason is logged and published once on ``~/state`` (phase
  ``rejected``), as for a refused ``goal_pose`` message (an action rejection carries no text).
  A goal accepted before the first ``joint_states`` starts when the arm state is known;
* **feedback** every :data:`FEEDBACK_PERIOD_S` (20 Hz): phase, distance and orientation error of the
  commanded tool pose to the goal, swivel, clearance, the core's message;
* **result**: ``SUCCESS`` at phase ``reached``; ``BLOCKED`` / ``REJECTED`` / ``ABORTED`` with the core's
  message when the core cannot go on; ``TIMEOUT`` after ``goal.timeout``; ``CANCELED``; ``PREEMPTED``.
  Errors are those of the commanded pose (what ``reached`` is decided on). A goal that ends without
  success is dropped by the core (the arm holds where it is), so nothing moves after the result;
* **cancel** (and timeout): the core drops the goal and the arm decelerates within its joint
  velocity and acceleration limits (the core's braking); the goal is reported canceled once the
  command stands still;
* **pre-emption**: a newer Reach goal, or a goal / stream sample on ``goal_pose`` or a twist (the
  node calls :meth:`ReachActionServer.preempt`), aborts the running goal with status ``PREEMPTED``;
  the arm goes on smoothly to the new target.

The execute callback only awaits the outcome; the decisions are made by one timer in the node's
executor, so the server works with the node's single-threaded executor. Units: m, rad, s.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.task import Future
from redarm_interfaces.action import Reach
from redarm_interfaces.msg import ControllerState

from redarm_ros.control.types import GoalKind, GoalStatus, Phase
from redarm_ros.errors import InvalidInputError
from redarm_ros.nodes._common import pose_msg_to_matrix
from redarm_ros.param_table import table

if TYPE_CHECKING:
    from redarm_ros.nodes.controller import ControllerNode

ACTION_NAME = "~/reach"
FEEDBACK_PERIOD_S = 0.05  # s: feedback and outcome checks at 20 Hz (the action promises >= 10 Hz)
REST_TOLERANCE = 1e-9  # rad: a command that moved less than this between two checks stands still
SWIVEL_BOUND = table()["controller"].param("preferred_swivel").bound  # what a swivel_preference may be

# Reach result codes of a failed goal check (the core's GoalStatus).
_CHECK_CODE = {
    GoalStatus.OUT_OF_REACH: Reach.Result.OUT_OF_REACH,
    GoalStatus.NO_SOLUTION_IN_LIMITS: Reach.Result.NO_SOLUTION_IN_LIMITS,
    GoalStatus.IN_COLLISION: Reach.Result.IN_COLLISION,
    GoalStatus.INVALID_INPUT: Reach.Result.INVALID_INPUT,
    GoalStatus.NOT_READY: Reach.Result.ABORTED,
}
_PHASE_MSG = {ph: getattr(ControllerState, ph.name) for ph in Phase}
_CODE_NAME = {getattr(Reach.Result, n): n for n in dir(Reach.Result) if n.isupper()
              and isinstance(getattr(Reach.Result, n), int)}


@dataclass
class _Goal:
    """One accepted Reach goal and where it stands."""

    handle: ServerGoalHandle
    T: np.ndarray  # goal pose, 4x4, base frame
    timeout: float  # s, 0 = none
    swivel: float | None  # preferred swivel for this goal, None = the node's parameter
    accepted_at: float  # s, ROS time
    done: Future = field(default_factory=Future)  # -> (terminal event, Reach.Result)
    applied: bool = False  # handed to the core (after the first joint_states)
    steps0: int = 0  # node.steps when it was handed to the core
    stop: tuple[int, str] | None = None  # (status, message) once the arm is stopping for it
    q_seen: np.ndarray | None = None  # the command at the previous check
    steps_seen: int = 0


class ReachActionServer:
    """``~/reach`` for a :class:`~redarm_ros.nodes.controller.ControllerNode` (see the module docstring).

    The node calls :meth:`preempt` when a goal or twist arrives on its topics and :meth:`destroy`
    before it is destroyed; everything else runs from the action server's callbacks and one timer.
    """

    def __init__(self, node: ControllerNode) -> None:
        self.node = node
        self._active: _Goal | None = None
        self.server = ActionServer(
            node, Reach, ACTION_NAME, execute_callback=self._execute_unused,
            goal_callback=self._on_goal, handle_accepted_callback=self._on_accepted,
            cancel_callback=self._on_cancel,
        )
        self._timer = node.create_timer(FEEDBACK_PERIOD_S, self._check)
        self._timer.cancel()  # runs only while a goal is active

    # -- action server callbacks ----------------------------------------------------------------------
    def _on_goal(self, goal: Reach.Goal) -> GoalResponse:
        """Accept or reject (the same checks as a goal on goal_pose); say why on rejection."""
        node = self.node
        frame = goal.target.header.frame_id
        reason = ""
        if not node._frame_ok(frame):
            reason = (f"frame {frame!r} refused: give goals in "
                      f"{node.get_parameter('base_frame').value!r} (this node has no tf)")
        elif goal.use_swivel_preference and not SWIVEL_BOUND.check(goal.swivel_preference)[0]:
            reason = f"swivel_preference must be {SWIVEL_BOUND.phrase}, got {goal.swivel_preference}"
        elif not (math.isfinite(goal.timeout) and goal.timeout >= 0.0):
            reason = f"timeout must be finite and >= 0 (0 = none), got {goal.timeout}"
        else:
            try:
                T = pose_msg_to_matrix(goal.target.pose, 1e-3)
            except InvalidInputError as exc:
                reason = f"[INVALID_INPUT] {exc}"
            else:
                check = node.ctl.check_goal(T)
                if not check.accepted:
                    reason = f"[{check.status.name}] {check.message}"
        if reason:
            node._reject_message(f"Reach goal rejected: {reason}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_accepted(self, handle: ServerGoalHandle) -> None:
        req: Reach.Goal = handle.request
        g = _Goal(handle, pose_msg_to_matrix(req.target.pose, 1e-3), float(req.timeout),
                  float(req.swivel_preference) if req.use_swivel_preference else None, self.node._now())
        self.preempt("a newer Reach goal")
        self._active = g
        self.node._pending_goal = None  # a goal_pose waiting for the first joint_states is older

        async def run(_handle: ServerGoalHandle) -> Reach.Result:
            return await self._run(g)

        handle.execute(run)
        p = g.T[:3, 3]
        self.node.get_logger().info(f"Reach goal accepted: ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m")
        self._start(g)
        self._timer.reset()

    def _on_cancel(self, handle: ServerGoalHandle) -> CancelResponse:
        """Cancel requests are accepted while the goal runs; the timer then stops the arm."""
        g = self._active
        return CancelResponse.ACCEPT if g is not None and g.handle is handle else CancelResponse.REJECT

    @staticmethod
    def _execute_unused(handle: ServerGoalHandle) -> Reach.Result:  # pragma: no cover - never called
        handle.abort()
        return Reach.Result(status=Reach.Result.ABORTED, message="internal: goal executed without state")

    async def _run(self, g: _Goal) -> Reach.Result:
        """The execute callback: wait for the outcome the timer decides, then end the goal with it.

        (A pending rclpy task is resumed once per executor wake-up, i.e. at the control rate: no
        busy waiting.)"""
        event, result = await g.done
        if event == "succeed":
            g.handle.succeed()
        elif event == "canceled":
            g.handle.canceled()
        else:
            g.handle.abort()
        return result

    # -- the node's hooks -----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """A Reach goal is active and handed to the core (not one waiting for the arm state)."""
        g = self._active
        return g is not None and g.applied

    def preempt(self, by: str) -> None:
        """A newer goal arrived (``by`` says which): abort the running Reach goal, if any. The arm is
        left to the newer goal."""
        g = self._active
        if g is not None:
            self._end(g, "abort", Reach.Result.PREEMPTED, f"pre-empted by {by}")

    def destroy(self) -> None:
        """Abort a running goal and destroy the server (before the node is destroyed)."""
        g = self._active
        if g is not None:
            self._end(g, "abort", Reach.Result.ABORTED, "the controller is shutting down")
        self._timer.cancel()
        self.server.destroy()

    # -- goal life ------------------------------------------------------------------------------------
    def _start(self, g: _Goal) -> None:
        """Hand the goal to the core once the arm state is known."""
        node = self.node
        if g.applied or not node._started:
            return
        g.applied = True
        node.wake()
        if g.swivel is not None:
            node.ctl.set_preferred_swivel(g.swivel)
        check = node.ctl.set_goal(g.T)
        if not check.accepted:  # the scene changed since the goal was accepted, or it waited for the arm
            node._goal_T = None
            self._end(g, "abort", _CHECK_CODE.get(check.status, Reach.Result.ABORTED),
                      f"goal dropped [{check.status.name}]: {check.message}")
            return
        node._goal_T = g.T  # the node re-plans to it after a resync
        g.steps0 = g.steps_seen = node.steps

    def _check(self) -> None:
        """Timer: feedback, and the outcome when there is one (reached, blocked, dropped, timeout,
        cancel requested -> stop, stopped)."""
        g = self._active
        if g is None:
            self._timer.cancel()
            return
        node = self.node
        if not g.applied:
            if g.handle.is_cancel_requested:
                self._end(g, "canceled", Reach.Result.CANCELED, "canceled before the arm state was known; "
                          "nothing moved")
                return
            if g.timeout > 0.0 and node._now() - g.accepted_at > g.timeout:
                self._end(g, "abort", Reach.Result.TIMEOUT, f"no joint_states within the timeout of "
                          f"{g.timeout:g} s: the arm state is unknown; nothing moved")
                return
            self._start(g)
            if not g.applied:
                self._feedback(g, "waiting for joint_states")
                return
            if self._active is not g:
                return
        if g.stop is None:
            if g.handle.is_cancel_requested:
                self._begin_stop(g, Reach.Result.CANCELED, "canceled: the arm stopped and holds")
            elif g.timeout > 0.0 and node._now() - g.accepted_at > g.timeout:
                self._begin_stop(g, Reach.Result.TIMEOUT, f"not reached within the timeout of "
                                 f"{g.timeout:g} s: the arm stopped and holds")
        if g.stop is not None:
            if self._stopped(g):
                status, message = g.stop
                self._end(g, "canceled" if status == Reach.Result.CANCELED else "abort", status, message)
                return
        elif node.steps > g.steps0 and node._last_result is not None \
                and node._last_result.phase is node.ctl.phase:  # (else a goal/scene change since the step)
            ctl = node.ctl
            phase = ctl.phase
            msg = node._last_result.message
            if ctl.goal_kind is not GoalKind.POINT and phase is not Phase.REJECTED:
                self._end(g, "abort", Reach.Result.ABORTED, f"the controller dropped the goal "
                          f"(phase {phase.value.lower()}){': ' + msg if msg else ''}")
                return
            if phase is Phase.REACHED:
                self._end(g, "succeed", Reach.Result.SUCCESS, "reached")
                return
            if phase is Phase.BLOCKED:
                ctl.stop()  # the arm already holds; no motion after the result (e.g. on a scene change)
                node._goal_T = None
                self._end(g, "abort", Reach.Result.BLOCKED, f"blocked: {msg}")
                return
            if phase is Phase.REJECTED:
                node._goal_T = None
                self._end(g, "abort", Reach.Result.REJECTED, f"the controller dropped the goal: {msg}")
                return
        self._feedback(g)

    def _begin_stop(self, g: _Goal, status: int, message: str) -> None:
        """Drop the goal in the core: the command decelerates within the joint limits, then holds."""
        self.node.ctl.stop()
        self.node._goal_T = None
        self.node.wake()
        g.stop = (status, message)
        g.q_seen = self.node.ctl.q
        g.steps_seen = self.node.steps
        self.node.get_logger().info(f"Reach goal: {message.split(':')[0]}; stopping the arm")

    def _stopped(self, g: _Goal) -> bool:
        """The command stands still (unchanged over at least two control steps), or nothing is commanded
        (joint_states stale: the driver holds)."""
        node = self.node
        if time.monotonic() - node._t_meas > node.get_parameter("joint_states_timeout_s").value:
            return True
        q, steps = node.ctl.q, node.steps
        if q is None:
            return True
        if steps < g.steps_seen + 2:
            return False
        still = g.q_seen is not None and float(np.max(np.abs(q - g.q_seen))) <= REST_TOLERANCE
        g.q_seen, g.steps_seen = q, steps
        return still

    def _errors(self, g: _Goal) -> tuple[float, float]:
        """Position (m) and orientation (rad) error of the commanded tool pose to the goal."""
        q = self.node.ctl.q
        if q is None:
            return math.nan, math.nan
        pe, re = self.node.arm.pose_error(q, g.T)
        return float(pe), float(re)

    def _feedback(self, g: _Goal, message: str | None = None) -> None:
        fb = Reach.Feedback()
        res = self.node._last_result
        fb.phase = _PHASE_MSG[self.node.ctl.phase] if g.applied else ControllerState.IDLE
        fb.distance_to_goal, fb.orientation_error = self._errors(g)
        fb.swivel = float(res.swivel) if res is not None else math.nan
        fb.clearance = float(res.clearance) if res is not None else math.inf
        if message is not None:
            fb.message = message
        elif g.stop is not None:
            fb.message = f"stopping ({g.stop[1].split(':')[0]})"
        else:
            fb.message = res.message if res is not None else ""
        g.handle.publish_feedback(fb)

    def _end(self, g: _Goal, event: str, status: int, message: str) -> None:
        """Decide the goal's outcome (the execute callback ends it); restore the swivel preference."""
        if g.done.done():
            return
        pe, re = self._errors(g)
        result = Reach.Result(status=status, message=message, position_error=pe, orientation_error=re)
        if g.swivel is not None and g.applied:
            self.node.ctl.set_preferred_swivel(float(self.node.get_parameter("preferred_swivel").value))
            self.node.wake()
        if self._active is g:
            self._active = None
        g.done.set_result((event, result))
        text = f"Reach goal {_CODE_NAME.get(status, status)}: {message} (position error {pe:.2e} m, " \
               f"orientation error {re:.2e} rad)"
        # (rclpy ties a severity to each call site: one call per severity)
        if status in (Reach.Result.SUCCESS, Reach.Result.CANCELED):
            self.node.get_logger().info(text)
        else:
            self.node.get_logger().warning(text)


__all__ = ["ACTION_NAME", "FEEDBACK_PERIOD_S", "ReachActionServer"]
