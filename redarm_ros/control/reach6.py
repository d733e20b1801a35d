"""The reaching controller for the 6-DOF PowerCube arm: the 7-DOF controller's heading, speed and
orientation dynamics, no swivel.

:class:`ReachController6` is what :func:`~redarm_ros.control.make.make_controller` builds for a
``powercube6`` arm. Everything
that moves the hand is the 7-DOF controller's (:mod:`~redarm_ros.control.attractor_law` for point goals,
:mod:`~redarm_ros.control.servo_law` for streams and twists, :mod:`~redarm_ros.control.command` for the
joint limits and the collision guard); what differs:

* **IK**: the analytic 6-DOF IK at every step, on the branch of the current configuration, the
  orientation projected onto the reachable ones (:mod:`~redarm_ros.control.ik_step6`). There is no
  self-motion, so obstacles are avoided through the heading alone (the heading's repellers and the
  sliding along obstacle surfaces); the elbow goes where the IK puts it.
* **Collision guard**: lever arms for the 6-DOF chain (base yaw about the base axis, shoulder, elbow,
  wrist) in :class:`CollisionGuard6`; self-collision (the paper's L1-L56 and L23-L56 pairs) and the
  robot's deck as ground plane, as for every arm.
* **Goal check** (:func:`check_goal6`): every IK solution of the goal (up to 4: two azimuths, two
  elbows), in the limits, free of the scene, of itself and of the ground; a rejection for reach or
  limits carries the base-move suggestion.
* **Elbow choice**: a goal whose straight route cannot be followed on the current branch (e.g. it is
  reachable only with the other elbow, or the route leaves the workspace) is reached by a joint-space
  move to the cheapest collision-free goal configuration (:class:`Planner6`: straight joint segment,
  else through the park posture), checked by the guard's sphere tracing, spread over control steps;
  the attractor then finishes on the new branch.

Units: m, rad, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Generator
from typing import Any

import numpy as np

from redarm_ros.control.base import pose_of
from redarm_ros.control.elbow import ArmGeometry, ElbowCircle
from redarm_ros.control.guard import CollisionGuard, describe
from redarm_ros.control.ik_step import pose_matrix
from redarm_ros.control.ik_step6 import IKStepper6, branch, check_route6, fixed_circle, is_6dof
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.reach_controller import ReachController
from redarm_ros.control.replan import PathSearch, move_time
from redarm_ros.control.state import ZERO3, Command, CoreState, Reference
from redarm_ros.control.stream import StreamEstimator
from redarm_ros.control.types import GoalCheck, GoalStatus
from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.broadphase import SceneIndex
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics.protocols import ControlledArm
from redarm_ros.kinematics.result import IKStatus

LOG = logging.getLogger(__name__)

__all__ = ["CollisionGuard6", "Planner6", "ReachController6", "check_goal6"]


class CollisionGuard6(CollisionGuard):
    """The collision guard with the lever arms of the 6-DOF chain: joint 1 (base yaw) turns every point
    about the base axis, joints 2-3 about the shoulder, joint 4 about the elbow, joints 5-6 about the
    wrist (key points base, shoulder, elbow, wrist, tool)."""

    def levers(self, q: np.ndarray, kp: np.ndarray | None = None) -> np.ndarray:
        k = self.key_points(q) if kp is None else kp
        r = self._rmax
        base = max(float(np.linalg.norm(k[i] - k[0])) for i in (1, 2, 3, 4)) + r
        sh = max(float(np.linalg.norm(k[i] - k[1])) for i in (2, 3, 4)) + r
        el = max(float(np.linalg.norm(k[i] - k[2])) for i in (3, 4)) + r
        wr = float(np.linalg.norm(k[4] - k[3])) + r
        return np.array([base, sh, sh, el, wr, wr])

    def max_levers(self) -> np.ndarray:
        if self._max_levers is None:
            L1, L23, L4, L56 = self.arm.link_lengths
            r = self._rmax
            self._max_levers = np.array([L1 + L23 + L4 + L56 + r] + [L23 + L4 + L56 + r] * 2
                                        + [L4 + L56 + r] + [L56 + r] * 2)
        return self._max_levers


def check_goal6(arm: Any, guard: CollisionGuard, T: Any, scene: Scene, q_seed: np.ndarray) -> GoalCheck:
    """Check goal pose ``T`` (4x4, base frame) of the 6-DOF arm: reachable with joint 3 locked, some IK
    solution in the limits and clear of the scene, of the arm itself and of the ground (``guard``'s
    clearance). ``free_swivels`` of an accepted goal counts the free solutions."""
    try:
        Tn = np.asarray(arm.check_pose(T), float)
    except InvalidInputError as exc:
        return GoalCheck(GoalStatus.INVALID_INPUT, str(exc))
    p = Tn[:3, 3]
    for j, o in enumerate(scene.obstacles):
        if o.signed_distance(p) < 0.0:
            return GoalCheck(GoalStatus.IN_COLLISION, f"goal position lies inside obstacle {j} "
                             f"{o.name or type(o).__name__.lower()!r}")
    sols = np.asarray(arm.ik(Tn), float).reshape(-1, arm.n)
    if sols.shape[0] == 0:
        _, info = arm.ik_nearest(Tn, q_seed)
        if info.status is IKStatus.NO_SOLUTION_IN_LIMITS:
            return GoalCheck(GoalStatus.NO_SOLUTION_IN_LIMITS, f"no IK solution within the joint limits "
                             f"({info.message})")
        return GoalCheck(GoalStatus.OUT_OF_REACH, f"goal out of reach: {info.message}")
    free = 0
    worst = None
    for q in sols:
        c = guard.clearance(q, scene)
        if c.distance > 0.0:
            free += 1
        elif worst is None or c.distance < worst.distance:
            worst = c
    if free == 0:
        assert worst is not None
        return GoalCheck(GoalStatus.IN_COLLISION, f"every one of the {len(sols)} IK solutions collides "
                         f"(e.g. {describe(worst, scene)})")
    return GoalCheck(GoalStatus.ACCEPTED, "", free, None)


class Planner6:
    """A joint-space path to a goal configuration of the 6-DOF arm, searched in slices (the interface
    of :class:`~redarm_ros.control.replan.JointPlanner`: :meth:`work` until it returns True, then
    ``path`` (waypoints, rad) or None and ``reason``).

    Goal configurations: every IK solution of the goal (both elbows, both azimuths) whose clearance
    (scene, self, ground) is positive, cheapest first by the time of a synchronised joint move. For
    each: the straight joint segment, then the segments through the arm's park posture, then through
    up to ``vias`` random via configurations (uniform in the limits, seeded by ``seed``, collision-free);
    each segment checked by the guard's sphere tracing keeping ``need`` m."""

    def __init__(self, arm: Any, guard: CollisionGuard, scene: Scene, q0: np.ndarray, T: np.ndarray,
                 need: float, work_per_step: int, vias: int = 0, seed: int = 0) -> None:
        self.path: list[np.ndarray] | None = None
        self.reason = ""
        self._work = max(1, int(work_per_step))
        self._vias = max(0, int(vias))
        self._rng = np.random.default_rng(seed)
        self._gen = self._search(arm, guard, scene, q0, T, need)

    def work(self) -> bool:
        """Do one slice of the search; True when it is over."""
        for _ in range(self._work):
            try:
                next(self._gen)
            except StopIteration:
                return True
        return False

    def _search(self, arm: Any, guard: CollisionGuard, scene: Scene, q0: np.ndarray, T: np.ndarray,
                need: float) -> Generator[None, None, None]:
        max_vel = np.asarray(arm.max_vel, float)
        max_acc = np.asarray(arm.max_acc, float)
        sols = [np.asarray(q, float) for q in np.asarray(arm.ik(T), float).reshape(-1, arm.n)]
        sols.sort(key=lambda q: move_time(q - q0, max_vel, max_acc))
        goals = []
        for q in sols:
            yield None
            if guard.clearance(q, scene).distance > 0.0:
                goals.append(q)
        if not goals:
            self.reason = "no collision-free goal configuration"
            return
        park = getattr(arm, "park", None)
        lower, upper = np.asarray(arm.lower, float), np.asarray(arm.upper, float)
        for n, qg in enumerate(goals):
            routes = [[q0, qg]]
            if park is not None:
                routes.append([q0, np.asarray(park, float), qg])
            if n == 0:  # random vias for the cheapest goal configuration only
                for _ in range(self._vias):
                    qv = self._rng.uniform(lower, upper)
                    yield None
                    if guard.clearance(qv, scene).distance > need:
                        routes.append([q0, qv, qg])
            for route in routes:
                ok = True
                for qa, qb in zip(route[:-1], route[1:], strict=True):
                    march = guard.segment_march(qa, qb, scene, need)
                    while True:
                        try:
                            next(march)
                        except StopIteration as stop:
                            ok = stop.value is not None
                            break
                        yield None
                    if not ok:
                        break
                if ok:
                    self.path = route
                    self.reason = f"to the {branch(arm, qg).describe()} solution"
                    return
        self.reason = f"no collision-free joint path to any of the {len(goals)} goal configurations"


class ReachController6(ReachController):
    """:class:`~redarm_ros.control.reach_controller.ReachController` for the 6-DOF PowerCube arm (see
    the module docstring). Build it as ``make_controller(load_arm("powercube6"), scene)`` or directly."""

    def __init__(self, arm: ControlledArm, scene: Scene | None = None,
                 params: ControllerParams | None = None) -> None:
        super().__init__(arm, scene, params)
        p = self.params
        # the laws drive it as they drive the swivel stepper; the 6-DOF route check needs it as it is
        self.stepper6 = IKStepper6(arm, p.flip_ratio, p.swivel_search_step, p.swivel_search_count)
        self.stepper = self.stepper6
        self.guard = CollisionGuard6(arm, p.capsules, p.collision_margin, p.guard_step)

    @classmethod
    def refusal(cls, arm: object) -> str | None:
        """Why this class cannot run ``arm`` (None if it can): it runs the 6-DOF PowerCube arm."""
        if is_6dof(arm):
            return None
        return (f"ReachController6 runs the 6-DOF PowerCube arm, not {getattr(arm, 'name', arm)!r}; "
                "make_controller(arm, scene, params) builds the controller of any arm")

    @property
    def elbow_circle(self) -> None:
        """No elbow circle (no self-motion): None, so a display draws none."""
        return None

    # -- set-up -----------------------------------------------------------------------------------
    def _install_scene(self, scene: Scene) -> None:
        # The shoulder turns with the base (L1 off its axis): the reach is counted from the base.
        self.scene = scene
        reach = float(sum(self.arm.link_lengths))
        self._index = SceneIndex(scene, (0.0, 0.0, 0.0), reach + max(self.params.capsules.radii),
                                 self.params.broad_phase_margin)
        self._local = self._index.reach_scene

    def reset(self, q: Any, now: float | None = None) -> None:
        """As :meth:`ReachController.reset` (no swivel: 0)."""
        qa = np.clip(self.arm.check_q(q), self._lower, self._upper)
        T = np.asarray(self.arm.fk(qa), float)
        pos, rot = pose_of(T)
        t = now if now is not None else (0.0 if self._st is None else self._st.time)
        local = self._index.reach_scene
        kp = self.guard.key_points(qa)
        clear = self.guard.clearance(qa, local.scene, kp)
        zero = np.zeros(self.arm.n)
        cmd = Command(qa.copy(), self._globalise(clear, local), pos, rot, kp, qd=zero.copy())
        cmd.obs_clear = self._obstacle_clearance(qa, local, kp)
        ref = Reference(qa.copy(), pos, rot, 0.0, fixed_circle(kp), qd=zero.copy())
        self._st = CoreState(ref, cmd, stream=StreamEstimator(self.params.stream), time=float(t))

    # -- goals ------------------------------------------------------------------------------------
    def check_goal(self, T: Any) -> GoalCheck:
        """Check a goal pose (4x4, base frame) without changing state (see :func:`check_goal6`); a goal
        out of reach or without an in-limit solution gets the base-move suggestion."""
        local = self._index.reach_scene
        seed = self._st.cmd.q if self._st is not None else (self._lower + self._upper) / 2.0
        check = check_goal6(self.arm, self.guard, T, local.scene, seed)
        return self._hints.annotate(check, T, seed)

    def _stream_feasibility(self, T: np.ndarray, scene: Scene) -> str:
        if np.asarray(self.arm.ik(T)).shape[0] == 0:
            return "stream goal out of reach (or its approach is not in the arm's plane)"
        for j, o in enumerate(scene.obstacles):
            if o.signed_distance(T[:3, 3]) < 0.0:
                return f"stream goal inside obstacle {j} {o.name or type(o).__name__.lower()!r}"
        return ""

    def _route_dead_end(self, T: np.ndarray) -> str:
        """Why the attractor should not take the straight route to ``T`` on the current branch ('' if it
        should): no continuous solution on the branch (e.g. only the other elbow reaches the goal)."""
        st = self._state()
        p = self.params
        T0 = pose_matrix(st.ref.pos, st.ref.rot)
        route = check_route6(self.stepper6, T0, st.ref.q, T, p.replan.route_steps, p.speed.v_max,
                             p.max_ori_rate)
        st.progress.due = st.time + p.replan.overdue_factor * route.time + p.replan.overdue_slack
        return route.dead_end

    # -- no swivel ----------------------------------------------------------------------------------
    def _swivel_fn(self, dt: float) -> Any:
        def swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
            return 0.0, 0.0, False

        return swivel

    def _desired_swivel(self, circle: ElbowCircle) -> float:
        return 0.0

    def forces(self) -> None:
        """No swivel, no swivel forces."""
        return None

    def _slide_geom(self, pos: Any) -> ArmGeometry:
        # The shoulder sits L1 off the base axis, in the arm's plane: where the reference has it.
        st = self._state()
        assert st.ref.circle is not None
        return dataclasses.replace(self.geom, shoulder=st.ref.circle.shoulder)

    def _resync_reference(self, keep_velocity: bool = False) -> None:
        """The reference becomes the command's pose (see ReachController); no swivel."""
        st = self._state()
        ref, cmd = st.ref, st.cmd
        ref.q = cmd.q.copy()
        ref.qd = cmd.qd.copy() if keep_velocity else np.zeros(self.arm.n)
        T = np.asarray(self.arm.fk(cmd.q), float)
        ref.pos, ref.rot = pose_of(T)
        ref.circle = fixed_circle(self.arm.key_points(cmd.q))
        ref.s = ref.sdot = ref.sdot_dyn = 0.0
        ref.w_ori = 0.0
        if keep_velocity:
            tw = np.asarray(self.arm.jacobian(cmd.q), float) @ cmd.qd
            ref.vel = (float(tw[0]), float(tw[1]), float(tw[2]))
            ref.w = (float(tw[3]), float(tw[4]), float(tw[5]))
            ref.w_ori = math.sqrt(ref.w[0] ** 2 + ref.w[1] ** 2 + ref.w[2] ** 2)
        else:
            ref.vel, ref.w = ZERO3, ZERO3
        st.att.v = 0.0 if not keep_velocity else math.sqrt(sum(c * c for c in ref.vel))
        st.att.a = 0.0

    # -- joint-space moves --------------------------------------------------------------------------
    def _new_planner(self, T: np.ndarray) -> PathSearch:
        st = self._state()
        rp = self.params.replan
        return Planner6(self.arm, self.guard, self._index.reach_scene.scene, st.cmd.q.copy(), T,
                        rp.clearance, rp.work_per_step, rp.vias, rp.seed + st.progress.replans)

    def _plan_message(self, planner: PathSearch) -> str:
        st = self._state()
        assert st.path is not None
        vias = len(planner.path) - 2
        return (f"moving in joint space {planner.reason} ({vias} via points, "
                f"{st.path.duration:.1f} s): {st.plan_reason}")
