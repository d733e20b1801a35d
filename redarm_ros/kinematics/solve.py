"""The IK front end: one request in (pose, arm name, swivel or seed, options), one answer out. No ROS here.

:class:`IKFrontEnd` holds the served arm models and turns a request into the right solver call:

* swivel given (swivel arms only): every in-limit solution at that swivel (one closed-form ``ik`` call);
  the answer is the one nearest the seed, each joint at its in-limit 2*pi copy nearest the seed. If the
  swivel has no in-limit solution, the message names the nearest swivel that has one, from the
  closed-form feasible set (``feasible_swivels``: bounded work, no search, so it never exceeds the
  request's time budget);
* no swivel: ``ik_nearest`` (the global optimum over all swivels for swivel arms; the analytic solve for
  the 6-DOF PowerCube arm; damped least squares for a generic chain) within the request's time budget.

Collision filter (on unless a request turns it off): a solution whose capsules collide with each other
or go below the arm's ground plane (:mod:`redarm_ros.geometry.self_collision`) is never returned. If the
nearest solution collides, :func:`nearest_collision_free` finds the nearest one that does not (swivel
arms: every flip pattern over a grid of the closed-form feasible swivel set, refined where the cost is
lowest; the 6-DOF arm: its up to 4 analytic solutions). If every in-limit solution collides the status
is ``ALL_SOLUTIONS_COLLIDE`` and the message says which links.

Base-move suggestion: when the pose cannot be solved at all (out of reach, no in-limit or no
collision-free solution at any swivel), the answer carries the smallest planar base displacement that
makes it solvable with the elbow in the optimal region (:mod:`.base_placement`).

:meth:`IKFrontEnd.solve` never raises: malformed input is ``INVALID_INPUT``, an unreachable pose
``OUT_OF_REACH``, and an unexpected exception in a solver ``INTERNAL_ERROR`` (logged with its traceback,
never disguised as the caller's fault). Units: m, rad, s.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError, RedarmError, UnreachableError
from redarm_ros.geometry.obstacles import ArmCapsules
from redarm_ros.geometry.self_collision import CollisionModel, collision_model, self_collision
from redarm_ros.kinematics.base_placement import BasePlacement, pose_ground_clearance, suggest_base_move
from redarm_ros.kinematics.collision_ik import FreeSolution, collision_free_rows, nearest_collision_free
from redarm_ros.kinematics.model import ANGLE_RANGE, Arm, check_finite_array
from redarm_ros.kinematics.protocols import has_analytic_ik, has_swivel
from redarm_ros.kinematics.result import IKStatus
from redarm_ros.kinematics.urdf_chain import describe_solver

__all__ = ["IKAnswer", "IKFrontEnd", "FreeSolution", "nearest_collision_free", "collision_free_rows"]

_log = logging.getLogger(__name__)
PI = math.pi
TWO_PI = 2.0 * math.pi


@dataclass
class IKAnswer:
    """What a solve returns, independent of any message type.

    ``status`` an :class:`IKStatus`; ``q`` the chosen joint vector (rad) or None; ``solutions`` all
    in-limit (and, with the filter, collision-free) solutions (k, n) when asked; ``swivel`` (rad) of ``q``
    or NaN; errors in m and rad.
    """

    status: IKStatus
    message: str = ""
    q: np.ndarray | None = None
    solutions: np.ndarray | None = None
    swivel: float = math.nan
    position_error: float = math.nan
    orientation_error: float = math.nan
    joint_names: list[str] = field(default_factory=list)
    #: self-collision / ground clearance (m) of ``q`` when the collision filter ran, else NaN
    clearance: float = math.nan
    #: the base-move suggestion (on failures that a base move can fix), else None
    base_offset: BasePlacement | None = None
    #: which IK solver serves the arm (:func:`.urdf_chain.describe_solver`); empty for an unknown arm
    solver: str = ""


# statuses after which a base move may help (the pose has no usable solution at any swivel)
_BASE_MOVE_STATUSES = (IKStatus.OUT_OF_REACH, IKStatus.NO_SOLUTION_IN_LIMITS, IKStatus.ALL_SOLUTIONS_COLLIDE)


class IKFrontEnd:
    """Validates solve requests and calls the kinematics core.

    ``arms`` maps names to loaded models; ``default_arm`` answers requests that name none. ``capsules``:
    the collision model's radii (m; default the controller's). ``suggest_base_move``: attach a
    base-move suggestion to answers that a base move can fix (``base_move_yaw``: it may turn the base
    too; ``base_move_timeout_s``: its own time budget in s). ``exhaustive_nearest``: solve requests without
    a swivel with ``ik_nearest(..., exhaustive=True)`` on the 7-DOF swivel arms (2-3x the time; the
    others have no such option). Raises :class:`InvalidInputError` if
    ``default_arm`` is not among ``arms`` (:class:`~redarm_ros.errors.ConfigError` for a malformed
    ``self_collision`` entry of an arm).
    """

    def __init__(
        self,
        arms: Mapping[str, Arm],
        default_arm: str,
        *,
        capsules: ArmCapsules | None = None,
        suggest_base_move: bool = True,
        base_move_yaw: bool = True,
        base_move_timeout_s: float = 0.5,
        exhaustive_nearest: bool = False,
    ) -> None:
        if default_arm not in arms:
            raise InvalidInputError(
                f"default_arm {default_arm!r} is not among the served arms {sorted(arms)}",
                field="default_arm",
                value=default_arm,
            )
        self.arms = dict(arms)
        self.default_arm = default_arm
        self.models = {name: collision_model(arm, capsules) for name, arm in self.arms.items()}
        self.suggest_base_move = bool(suggest_base_move)
        self.base_move_yaw = bool(base_move_yaw)
        self.base_move_timeout_s = float(base_move_timeout_s)
        self.exhaustive_nearest = bool(exhaustive_nearest)

    def arm_for(self, name: str) -> Arm:
        """The model named ``name`` ('' = the default arm); InvalidInputError if not served."""
        key = name or self.default_arm
        arm = self.arms.get(key)
        if arm is None:
            raise InvalidInputError(
                f"unknown arm {key!r}; this service serves: {', '.join(sorted(self.arms))}",
                field="arm",
                value=key,
            )
        return arm

    def model_for(self, name: str) -> CollisionModel:
        """The collision model of the arm named ``name`` ('' = the default arm)."""
        key = name or self.default_arm
        if key not in self.models:
            self.models[key] = collision_model(self.arm_for(key))
        return self.models[key]

    @staticmethod
    def seed_for(arm: Arm, seed: Sequence[float]) -> np.ndarray:
        """The seed as an (n,) array (rad); mid-range when ``seed`` is empty.

        A seed is only a preference: one outside the limits is used as given (the distance is measured
        to it), not refused. Raises :class:`InvalidInputError` for a wrong length, NaN/inf or a value
        beyond 1e6 rad.
        """
        if len(seed) == 0:
            return (arm.lower + arm.upper) / 2.0
        if len(seed) != arm.n:
            raise InvalidInputError(
                f"seed has {len(seed)} values but arm {arm.name!r} has {arm.n} joints",
                field="seed",
                value=list(seed),
            )
        return check_finite_array(list(seed), "seed", (arm.n,), ANGLE_RANGE)

    def solve(
        self,
        T: np.ndarray,
        arm_name: str,
        *,
        swivel: float | None,
        seed: Sequence[float],
        all_solutions: bool,
        timeout_s: float,
        check_collisions: bool = True,
    ) -> IKAnswer:
        """Solve one request; never raises. ``swivel`` None: nearest solution to the seed over all swivels.

        T: 4x4 target (base frame, m); ``timeout_s`` (s, > 0) bounds the solver's search;
        ``check_collisions``: drop solutions whose links collide or go below the ground plane.
        """
        t0 = time.perf_counter()
        try:
            arm = self.arm_for(arm_name)
            q_seed = self.seed_for(arm, seed)
            if not (timeout_s > 0.0 and math.isfinite(timeout_s)):
                raise InvalidInputError(
                    f"timeout must be > 0 s, got {timeout_s}", field="timeout", value=timeout_s
                )
            model = self.model_for(arm_name) if check_collisions else None
            if swivel is not None:
                ans, whole_pose = self._solve_at_swivel(
                    arm, T, swivel, q_seed, all_solutions, t0 + timeout_s, model
                )
            else:
                ans = self._solve_nearest(
                    arm, T, q_seed, all_solutions, timeout_s, t0, model, self.exhaustive_nearest
                )
                whole_pose = True
            ans.joint_names = list(arm.joint_names)
            ans.solver = describe_solver(arm)
            if ans.q is not None and not math.isfinite(ans.position_error):
                ans.position_error, ans.orientation_error = arm.pose_error(ans.q, T)
            if self.suggest_base_move and whole_pose and ans.status in _BASE_MOVE_STATUSES:
                self._attach_base_move(arm, T, q_seed, model, ans)
            return ans
        except InvalidInputError as exc:
            return IKAnswer(IKStatus.INVALID_INPUT, str(exc))
        except UnreachableError as exc:
            return IKAnswer(IKStatus.OUT_OF_REACH, str(exc))
        except RedarmError as exc:  # a typed failure that is not the caller's input
            _log.exception("solver error for arm %r", arm_name)
            return IKAnswer(IKStatus.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # noqa: BLE001 - a solver bug must become an answer, not a crash
            _log.exception("internal error for arm %r", arm_name)
            return IKAnswer(IKStatus.INTERNAL_ERROR, f"internal error: {type(exc).__name__}: {exc}")

    def _attach_base_move(
        self, arm: Arm, T: np.ndarray, q_seed: np.ndarray, model: CollisionModel | None, ans: IKAnswer
    ) -> None:
        """Add the base-move suggestion to a failed answer (and one sentence to its message)."""
        try:
            bp = suggest_base_move(
                arm,
                T,
                q_seed=q_seed,
                model=model,
                check_collisions=model is not None,
                allow_yaw=self.base_move_yaw,
                timeout_s=self.base_move_timeout_s,
            )
        except InvalidInputError:
            return
        ans.base_offset = bp
        ans.message = f"{ans.message}; {bp.describe()}" if ans.message else bp.describe()

    def _solve_at_swivel(
        self,
        arm: Arm,
        T: np.ndarray,
        swivel: float,
        q_seed: np.ndarray,
        all_solutions: bool,
        deadline: float,
        model: CollisionModel | None,
    ) -> tuple[IKAnswer, bool]:
        """(answer, whole_pose): ``whole_pose`` is True when the failure holds for every swivel."""
        if not math.isfinite(swivel):
            raise InvalidInputError(f"swivel must be finite, got {swivel}", field="swivel", value=swivel)
        if abs(swivel) > ANGLE_RANGE:  # its 2*pi copy would be round-off, not the angle asked for
            raise InvalidInputError(
                f"swivel {swivel:.6g} rad is out of range (|swivel| <= {ANGLE_RANGE:g} rad)",
                field="swivel",
                value=swivel,
            )
        if not has_swivel(arm):
            raise InvalidInputError(
                f"arm {arm.name!r} has no swivel parameterisation (kind {arm.kind}); "
                "leave swivel_given false",
                field="swivel",
                value=swivel,
            )
        s = math.remainder(swivel, TWO_PI)
        s = PI if s <= -PI else s
        sols = np.asarray(arm.ik(T, s), dtype=float).reshape(-1, arm.n)  # each solution once, near 0
        if len(sols) == 0:
            reachable = self._reachable(arm, T)
            msg, any_swivel = self._no_solution_message(arm, T, s, deadline)
            status = IKStatus.NO_SOLUTION_IN_LIMITS if reachable else IKStatus.OUT_OF_REACH
            return IKAnswer(status, msg, swivel=s), not reachable or not any_swivel
        clear = np.full(len(sols), math.nan)
        if model is not None:
            free, clear = collision_free_rows(arm, sols, model)
            if not free.any():
                worst = self_collision(arm, sols[int(np.argmax(clear))], model=model)
                msg = (
                    f"all {len(sols)} in-limit solutions at swivel {s:.4f} rad collide (the best: "
                    f"{worst.describe()})"
                )
                whole = False
                if pose_ground_clearance(arm, T, model) < 0.0:
                    msg += "; the hand is below the ground plane at every swivel"
                    whole = True
                elif time.perf_counter() < deadline:
                    found = nearest_collision_free(arm, T, q_seed, model)
                    if found is None:
                        msg += "; no swivel has a collision-free solution"
                        whole = True
                    else:
                        msg += f"; the nearest collision-free solution is at swivel {found.swivel:.4f} rad"
                return IKAnswer(IKStatus.ALL_SOLUTIONS_COLLIDE, msg, swivel=s), whole
            sols, clear = sols[free], clear[free]
        # every solution at its in-limit copies nearest the seed; the answer is the nearest of them
        near = arm.nearest_copies(sols, q_seed)
        i = int(np.argmin(((near - q_seed) ** 2).sum(axis=1)))
        ans = IKAnswer(
            IKStatus.SUCCESS, "", q=near[i], solutions=sols if all_solutions else None, swivel=s,
            clearance=float(clear[i]),
        )
        return ans, False

    @staticmethod
    def _reachable(arm: Any, T: np.ndarray) -> bool:
        try:
            arm.elbow_circle(T)
        except UnreachableError:
            return False
        return True

    @staticmethod
    def _no_solution_message(arm: Any, T: np.ndarray, s: float, deadline: float) -> tuple[str, bool]:
        """Why swivel s has no in-limit solution, with the nearest swivel that has one (closed form).

        Returns (message, whether some swivel has an in-limit solution; True when unknown).
        """
        try:
            ivs = arm.feasible_swivels(T)
        except UnreachableError as exc:
            return str(exc), False
        head = f"no solution within the joint limits at swivel {s:.4f} rad"
        if time.perf_counter() > deadline:
            return head + " (time budget used up before the feasible swivels were computed)", True
        best = None
        for iv in ivs:
            for a, b in iv.tolist():
                # distance from s to [a, b] on the circle
                d = 0.0 if (s - a) % TWO_PI <= b - a else min((a - s) % TWO_PI, (s - b) % TWO_PI)
                if best is None or d < best[0]:
                    best = (d, a, b)
        if best is None:
            return head + "; no swivel has one: the pose is reachable, but not within the joint limits", False
        d, a, b = best
        return head + f"; the nearest in-limit swivels are [{a:.4f}, {b:.4f}] rad ({d:.4f} rad away)", True

    @staticmethod
    def _solve_nearest(
        arm: Arm,
        T: np.ndarray,
        q_seed: np.ndarray,
        all_solutions: bool,
        timeout_s: float,
        t0: float,
        model: CollisionModel | None,
        exhaustive: bool = False,
    ) -> IKAnswer:
        extra = {"exhaustive": True} if exhaustive and has_swivel(arm) else {}  # (only they take it)
        q, info = arm.ik_nearest(T, q_seed, timeout_s=timeout_s, **extra)
        if info.status is IKStatus.INVALID_INPUT:
            raise InvalidInputError(info.message or "invalid request")
        if q is None:
            return IKAnswer(info.status, info.message)
        q = np.asarray(q, dtype=float)
        sw = math.nan if info.swivel is None else float(info.swivel)
        status, msg = info.status, ("" if info.status is IKStatus.SUCCESS else info.message)
        pos_err, rot_err = info.pos_err, info.rot_err
        clearance = math.nan
        if model is not None:
            sc = self_collision(arm, q, model=model)
            clearance = sc.min_distance
            if sc.colliding:
                if time.perf_counter() - t0 > timeout_s:
                    return IKAnswer(
                        IKStatus.TIMEOUT,
                        f"the nearest solution collides ({sc.describe()}) and the time budget of "
                        f"{timeout_s:g} s ran out before a collision-free one was searched",
                    )
                below = pose_ground_clearance(arm, T, model) < 0.0  # no solution can lift the hand
                found = None if below else nearest_collision_free(arm, T, q_seed, model)
                if found is None:
                    what = (
                        "the numeric solution found collides and this arm's solutions cannot be enumerated"
                        if not has_analytic_ik(arm)
                        else "every in-limit solution collides"
                    )
                    return IKAnswer(
                        IKStatus.ALL_SOLUTIONS_COLLIDE, f"{what} (the nearest: {sc.describe()})"
                    )
                q, clearance = found.q, found.clearance
                sw = found.swivel if has_swivel(arm) else sw
                status, msg = IKStatus.SUCCESS, ""
                pos_err = rot_err = math.nan  # recomputed by solve()
        sols = None
        if all_solutions:
            if has_swivel(arm) and math.isfinite(sw):
                sols = np.asarray(arm.ik(T, sw), dtype=float).reshape(-1, arm.n)
            elif has_analytic_ik(arm):
                sols = np.asarray(arm.ik(T), dtype=float).reshape(-1, arm.n)
            if sols is not None and model is not None and len(sols):
                sols = sols[collision_free_rows(arm, sols, model)[0]]
            if sols is None or len(sols) == 0:
                sols = q.reshape(1, -1)
        return IKAnswer(
            status,
            msg,
            q=q,
            solutions=sols,
            swivel=sw,
            position_error=pos_err,
            orientation_error=rot_err,
            clearance=clearance,
        )
