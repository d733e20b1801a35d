"""The reaching controller for the 6-DOF PowerCube arm: the 7-DOF controller's heading, speed and
orientation dynamics, no swivel.

:class:`ReachController6` is what :func:`~redarm_ros.control.make.make_controller` builds for a
``powercube6`` arm: the controller core with the redundancy strategy :class:`NoRedundancy`. Everything
that moves the hand is the 7-DOF controller's (:mod:`~redarm_ros.control.attractor_law` for point goals,
:mod:`~redarm_ros.control.servo_law` for streams and twists, :mod:`~redarm_ros.control.command` for the
joint limits and the collision guard); what differs (the strategy's):

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
from collections.abc import Generator
from typing import Any, cast

import numpy as np

from redarm_ros.control.elbow import ArmGeometry, ElbowCircle
from redarm_ros.control.goal_hint import BaseMoveHints
from redarm_ros.control.guard import CollisionGuard, describe
from redarm_ros.control.ik_step import IKStep, SwivelFn, pose_matrix
from redarm_ros.control.ik_step6 import IKStepper6, branch, check_route6, fixed_circle, is_6dof
from redarm_ros.control.joint_limits import JointBounds
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.reach_controller import ReachController
from redarm_ros.control.redundancy import CorridorJob, PosesAhead, Redundancy
from redarm_ros.control.replan import PathSearch, move_time
from redarm_ros.control.state import CoreState, Reference
from redarm_ros.control.swivel_dynamics import SwivelForces
from redarm_ros.control.types import GoalCheck, GoalStatus, Quat, Vec3
from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.broadphase import SceneIndex
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics.protocols import ControlledArm, ControlledArm6
from redarm_ros.kinematics.result import IKStatus

LOG = logging.getLogger(__name__)

__all__ = ["CollisionGuard6", "NoRedundancy", "Planner6", "ReachController6", "check_goal6"]


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


def check_goal6(arm: ControlledArm6, guard: CollisionGuard, T: Any, scene: Scene,
                q_seed: np.ndarray) -> GoalCheck:
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

    def __init__(self, arm: ControlledArm6, guard: CollisionGuard, scene: Scene, q0: np.ndarray,
                 T: np.ndarray,
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

    def _search(self, arm: ControlledArm6, guard: CollisionGuard, scene: Scene, q0: np.ndarray, T: np.ndarray,
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


def _no_swivel(circle: ElbowCircle, T: np.ndarray, s0: float) -> tuple[float, float, bool]:
    return 0.0, 0.0, False


class NoRedundancy:
    """The redundancy strategy of the 6-DOF arm (see the module docstring): no self-motion, so no swivel
    law, corridor or swivel forces; the 6-DOF IK stepper, guard, route check, planner and goal check.
    The elbow circle of the reference is a fixed stand-in (:func:`fixed_circle`, swivel 0) that carries
    the shoulder and elbow."""

    def __init__(self, arm: ControlledArm6, params: ControllerParams, bounds: JointBounds) -> None:
        p = params
        self.arm = arm
        self.bounds = bounds
        self.geom = ArmGeometry.from_arm(arm)
        self.stepper = IKStepper6(arm, p.flip_ratio, p.swivel_search_step, p.swivel_search_count)
        self.guard: CollisionGuard = CollisionGuard6(arm, p.capsules, p.collision_margin, p.guard_step)

    def scene_index(self, scene: Scene, p: ControllerParams) -> SceneIndex:
        """The obstacles within reach of the base: the shoulder turns with it (L1 off its axis)."""
        reach = float(sum(self.arm.link_lengths))
        return SceneIndex(scene, (0.0, 0.0, 0.0), reach + max(p.capsules.radii), p.broad_phase_margin)

    def reference(self, q: np.ndarray, T: np.ndarray, pos: Vec3, rot: Quat, kp: np.ndarray) -> Reference:
        """The reference at joints ``q``: swivel 0 on the fixed circle."""
        return Reference(q.copy(), pos, rot, 0.0, fixed_circle(kp), qd=np.zeros(self.arm.n))

    def resync(self, st: CoreState, T: np.ndarray, keep_velocity: bool) -> None:
        """The fixed circle at the command; no swivel."""
        ref = st.ref
        ref.circle = fixed_circle(self.arm.key_points(st.cmd.q))
        ref.s = ref.sdot = ref.sdot_dyn = 0.0

    def elbow_circle(self, st: CoreState) -> ElbowCircle | None:
        """No elbow circle (no self-motion): None, so a display draws none."""
        return None

    def slide_geom(self, st: CoreState) -> ArmGeometry:
        """The shoulder sits L1 off the base axis, in the arm's plane: where the reference has it."""
        assert st.ref.circle is not None
        return dataclasses.replace(self.geom, shoulder=st.ref.circle.shoulder)

    def swivel_fn(self, st: CoreState, p: ControllerParams, dt: float, scene: Scene) -> SwivelFn:
        """No swivel: 0."""
        return _no_swivel

    def pose_law(self, p: ControllerParams) -> bool:
        """No swivel to follow the pose."""
        return False

    def servo_swivel_fn(self, st: CoreState, p: ControllerParams, dt: float, scene: Scene,
                        poses_ahead: PosesAhead) -> SwivelFn:
        """No swivel: 0."""
        return _no_swivel

    def path_joints(self, st: CoreState, p: ControllerParams, dt: float, poses: np.ndarray,
                    ends: np.ndarray, poses_ahead: PosesAhead) -> np.ndarray | None:
        """Not planned ahead for the 6-DOF arm (None)."""
        return None

    def plan_offset(self, st: CoreState, p: ControllerParams) -> None:
        """No swivel: nothing."""

    def joint_step(self, st: CoreState, p: ControllerParams, q: np.ndarray) -> IKStep | None:
        """Not used (no plan ahead)."""
        return None

    def kept_swivel(self, st: CoreState, p: ControllerParams, step: IKStep) -> SwivelFn:
        """The swivel of ``step`` (0)."""
        return lambda c, T, s0: (step.s, step.s_des, False)

    def onto_preferred_swivel(self, st: CoreState, p: ControllerParams) -> None:
        """No swivel: nothing to do."""

    def route_dead_end(self, st: CoreState, p: ControllerParams, T: np.ndarray) -> str:
        """Why the attractor should not take the straight route to ``T`` on the current branch ('' if it
        should): no continuous solution on the branch (e.g. only the other elbow reaches the goal). Sets
        the point goal's due time from the route's."""
        T0 = pose_matrix(st.ref.pos, st.ref.rot)
        route = check_route6(self.stepper, T0, st.ref.q, T, p.replan.route_steps, p.speed.v_max,
                             p.max_ori_rate)
        st.progress.due = st.time + p.replan.overdue_factor * route.time + p.replan.overdue_slack
        return route.dead_end

    def corridor_asked(self, st: CoreState, p: ControllerParams, scene: Scene) -> bool:
        """No swivel corridor."""
        return False

    def corridor_job(self, st: CoreState, p: ControllerParams, T: np.ndarray, scene: Scene) -> CorridorJob:
        """No swivel corridor.

        Raises:
            ConfigError: always.
        """
        raise ConfigError("the 6-DOF arm has no swivel corridor", field="replan.corridor")

    def new_planner(self, st: CoreState, p: ControllerParams, T: np.ndarray, scene: Scene) -> PathSearch:
        """:class:`Planner6` towards tool pose ``T``."""
        rp = p.replan
        return Planner6(self.arm, self.guard, scene, st.cmd.q.copy(), T, rp.clearance, rp.work_per_step,
                        rp.vias, rp.seed + st.progress.replans)

    def plan_message(self, st: CoreState, planner: PathSearch) -> str:
        """What ``~/state`` says once the joint path starts (with the goal configuration's branch)."""
        assert st.path is not None and planner.path is not None
        vias = len(planner.path) - 2
        return (f"moving in joint space {planner.reason} ({vias} via points, "
                f"{st.path.duration:.1f} s): {st.plan_reason}")

    def check_goal(self, T: object, scene: Scene, p: ControllerParams, q_now: np.ndarray | None,
                   hints: BaseMoveHints) -> GoalCheck:
        """:func:`check_goal6` from the command (mid-range before a reset); a goal out of reach or
        without an in-limit solution gets the base-move suggestion."""
        b = self.bounds
        seed = q_now if q_now is not None else (b.lower + b.upper) / 2.0
        check = check_goal6(self.arm, self.guard, T, scene, seed)
        return hints.annotate(check, T, seed)

    def stream_feasibility(self, T: np.ndarray, scene: Scene, p: ControllerParams) -> str:
        """Why a stream sample cannot be followed exactly ('' if nothing is known against it)."""
        if np.asarray(self.arm.ik(T)).shape[0] == 0:
            return "stream goal out of reach (or its approach is not in the arm's plane)"
        for j, o in enumerate(scene.obstacles):
            if o.signed_distance(T[:3, 3]) < 0.0:
                return f"stream goal inside obstacle {j} {o.name or type(o).__name__.lower()!r}"
        return ""

    def forces(self, st: CoreState, scene: Scene, p: ControllerParams) -> SwivelForces | None:
        """No swivel, no swivel forces."""
        return None


class ReachController6(ReachController):
    """:class:`~redarm_ros.control.reach_controller.ReachController` for the 6-DOF PowerCube arm: the
    core with :class:`NoRedundancy` (see the module docstring). Build it as
    ``make_controller(load_arm("powercube6"), scene)`` or directly."""

    @classmethod
    def refusal(cls, arm: object) -> str | None:
        """Why this class cannot run ``arm`` (None if it can): it runs the 6-DOF PowerCube arm."""
        if is_6dof(arm):
            return None
        return (f"ReachController6 runs the 6-DOF PowerCube arm, not {getattr(arm, 'name', arm)!r}; "
                "make_controller(arm, scene, params) builds the controller of any arm")

    @classmethod
    def _redundancy(cls, arm: ControlledArm, params: ControllerParams, bounds: JointBounds) -> Redundancy:
        """The 6-DOF arm's: :class:`NoRedundancy`."""
        return NoRedundancy(cast(ControlledArm6, arm), params, bounds)  # (refusal() checked it)
