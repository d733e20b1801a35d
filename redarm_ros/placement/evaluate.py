"""Score base poses for a task set: exact reachability in the limits, swivel robustness, limit margin,
collisions.

For a chunk of base poses (rows of the problem's grid) and every task:

1. **Inverse reachability** (:mod:`.inverse`) keeps the (base, task) pairs that can be reachable.
2. **Exact reachability** of the kept pairs, batched: 7-DOF swivel arms get the measure of the feasible
   swivel set in closed form (:func:`~redarm_ros.kinematics.reachability.feasible_measure_poses`; a
   pose is reachable iff it has an in-limit solution); powercube6 gets its analytic IK (every solution).
3. For base poses whose footprint is clear and which reach **every** task in the limits: per task the
   in-limit solutions of all 8 flip patterns at every ``swivel_step`` of the swivel circle (7-DOF; the
   centres of the feasible intervals where that grid finds none), or every analytic solution
   (powercube6), tried in order of joint-limit margin; the first that is free of self-collision (the
   arm's capsule model and ground plane) and of the scene (world frame) gives the task's margin. A
   task with no such solution makes the base pose invalid. Collision-free is therefore decided on that
   grid of swivels: a collision-free solution only in a gap of the grid is not seen.

The result arrays are per (base pose, task) pair; :mod:`.rank` turns them into a ranking. A chunk's
result depends on the problem and the rows alone (no randomness, no shared state), so any engine that
evaluates the same chunks gives the same arrays bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from redarm_ros.geometry.obstacles import ArmCapsules, Scene, links_clearance
from redarm_ros.geometry.self_collision import collision_model, key_points_batch, self_collision_batch
from redarm_ros.kinematics.loader import load_arm
from redarm_ros.kinematics.protocols import has_swivel
from redarm_ros.kinematics.reachability import feasible_measure_poses
from redarm_ros.placement.inverse import possible_pairs
from redarm_ros.placement.problem import PlacementProblem, base_transforms

__all__ = ["ChunkResult", "evaluate_rows", "arm_of", "SWIVEL_STEP"]

SWIVEL_STEP = math.radians(10.0)  # spacing of the swivels tried per feasible interval in the collision check


@dataclass(frozen=True)
class ChunkResult:
    """Scores of base poses ``rows`` (n,) for m tasks.

    ``possible`` (n, m): kept by inverse reachability; ``reach`` (n, m): an in-limit solution exists;
    ``width`` (n, m): measure of the feasible swivel set (rad; NaN for arms without a swivel);
    ``footprint_ok`` (n,): the base footprint is clear of the scene; ``checked`` (n,): the collision
    stage ran (footprint clear and every task reachable); ``free`` (n, m): a collision-free in-limit
    solution was found (only where checked); ``margin`` (n, m): that solution's smallest distance to a
    limit of a joint that can move (rad; NaN where not checked or none found).
    """

    rows: np.ndarray
    possible: np.ndarray
    reach: np.ndarray
    width: np.ndarray
    footprint_ok: np.ndarray
    checked: np.ndarray
    free: np.ndarray
    margin: np.ndarray


@lru_cache(maxsize=8)
def arm_of(name: str) -> Any:
    """The arm model, loaded once per process (workers keep it between chunks)."""
    return load_arm(name)


def _in_base(B: np.ndarray, tasks: np.ndarray) -> np.ndarray:
    """B^-1 T for matching rows of (k, 4, 4) base frames and task poses."""
    R = B[:, :3, :3]
    Rt = np.transpose(R, (0, 2, 1))
    out = np.zeros_like(tasks)
    out[:, :3, :3] = Rt @ tasks[:, :3, :3]
    out[:, :3, 3] = np.einsum("kij,kj->ki", Rt, tasks[:, :3, 3] - B[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _exact_reach(arm: Any, Tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(reach, width) of (k, 4, 4) base-frame poses."""
    if has_swivel(arm):
        width, ok = feasible_measure_poses(arm, Tb)
        return ok, width
    ok = np.array([len(arm.ik(T)) > 0 for T in Tb], dtype=bool)
    return ok, np.full(len(Tb), np.nan)


def _footprint_ok(problem: PlacementProblem, scene: Scene | None, poses: np.ndarray) -> np.ndarray:
    """The base's footprint cylinder (radius, floor to base height) is clear of every scene obstacle."""
    ok = np.ones(len(poses), dtype=bool)
    r = problem.footprint_radius
    if scene is None or r <= 0.0 or not scene.obstacles:
        return ok
    h = max(problem.base_height, 1e-3)
    for i, (x, y, _) in enumerate(poses):
        a, b = (float(x), float(y), 0.0), (float(x), float(y), h)
        ok[i] = all(o.segment_distance(a, b) >= r for o in scene.obstacles)
    return ok


def _interval_centres(arm: Any, T: np.ndarray) -> np.ndarray:
    """In-limit solutions at the centre of every feasible swivel interval of base-frame pose T: the
    fallback that finds intervals narrower than the swivel grid."""
    rows = [arm.ik(T, 0.5 * (a + b)) for ivs in arm.feasible_swivels(T) for a, b in ivs]
    rows = [r for r in rows if len(r)]
    return np.concatenate(rows) if rows else np.empty((0, arm.n))


def _candidates(arm: Any, Tb: np.ndarray, step: float) -> list[np.ndarray]:
    """Per base-frame pose of (k, 4, 4) Tb, the in-limit solutions to try for collisions: every analytic
    solution (6-DOF), or the 8 flip patterns at every ``step`` of the swivel circle, in one batch, plus
    the interval centres where that grid finds nothing (7-DOF)."""
    if not has_swivel(arm):
        return [arm.ik(T) for T in Tb]
    S = -math.pi + step * (np.arange(int(math.ceil(2 * math.pi / step))) + 0.5)
    k, ns = len(Tb), len(S)
    Q, valid = arm.ik_batch(np.repeat(Tb, ns, axis=0), np.tile(S, k))
    Q, valid = Q.reshape(k, ns * 8, arm.n), valid.reshape(k, ns * 8)
    return [Q[i][valid[i]] if valid[i].any() else _interval_centres(arm, Tb[i]) for i in range(k)]


def _free_margins(arm: Any, Tb: np.ndarray, Bk: np.ndarray, scene: Scene | None, model: Any,
                  capsules: ArmCapsules, step: float) -> np.ndarray:
    """Per base-frame pose of (k, 4, 4) Tb (base frames Bk): the joint-limit margin (rad) of its
    best-margin solution free of self-collision and of the scene, NaN if every candidate collides."""
    cands = _candidates(arm, Tb, step)
    out = np.full(len(Tb), np.nan)
    counts = [len(c) for c in cands]
    if not sum(counts):
        return out
    Q = np.concatenate(cands)
    owner = np.repeat(np.arange(len(Tb)), counts)
    moving = arm.upper > arm.lower  # a locked joint (powercube6's joint 3) has no margin to keep
    margin = np.minimum(Q - arm.lower, arm.upper - Q)[:, moving].min(axis=1)
    if model is not None:
        clear = self_collision_batch(arm, Q, model=model).min_distance >= 0.0
    else:
        clear = np.ones(len(Q), dtype=bool)
    with_scene = scene is not None and (bool(scene.obstacles) or scene.table_height is not None)
    P = key_points_batch(arm, Q) if with_scene else None
    order = np.lexsort((-margin, owner))  # per pose, best margin first
    for c in order:
        i = owner[c]
        if not math.isnan(out[i]) or not clear[c]:
            continue
        if with_scene:
            Pw = P[c] @ Bk[i, :3, :3].T + Bk[i, :3, 3]
            if links_clearance(Pw, scene, capsules).distance < 0.0:
                continue
        out[i] = margin[c]
    return out


def evaluate_rows(problem: PlacementProblem, rows: np.ndarray, *, prune: bool = True,
                  swivel_step: float = SWIVEL_STEP) -> ChunkResult:
    """Score base poses ``rows`` (indices into ``problem.grid.poses()``) for every task (module doc).

    ``prune=False`` skips inverse reachability and checks every pair exactly (the brute-force
    reference the tests compare with).
    """
    arm = arm_of(problem.arm)
    rows = np.asarray(rows, dtype=np.int64)
    poses = problem.grid.poses()[rows]
    n, m = len(rows), len(problem.tasks)
    B = base_transforms(poses, problem.base_height)
    if prune:
        possible = possible_pairs(arm, problem.tasks, poses, problem.base_height)
    else:
        possible = np.ones((n, m), dtype=bool)
    reach = np.zeros((n, m), dtype=bool)
    width = np.full((n, m), np.nan if not has_swivel(arm) else 0.0)
    bi, tj = np.nonzero(possible)
    if len(bi):
        Tb = _in_base(B[bi], problem.tasks[tj])
        reach[bi, tj], width[bi, tj] = _exact_reach(arm, Tb)
    scene = Scene.from_dict(problem.scene) if problem.scene else None
    foot = _footprint_ok(problem, scene, poses)
    checked = foot & reach.all(axis=1)
    free = np.zeros((n, m), dtype=bool)
    margin = np.full((n, m), np.nan)
    capsules = ArmCapsules()
    model = collision_model(arm, capsules) if problem.check_collisions else None
    use_scene = scene if problem.check_collisions else None
    ci = np.nonzero(checked)[0]
    if len(ci):
        bi, tj = np.repeat(ci, m), np.tile(np.arange(m), len(ci))
        Tb = _in_base(B[bi], problem.tasks[tj])
        margin[bi, tj] = _free_margins(arm, Tb, B[bi], use_scene, model, capsules, swivel_step)
        free[ci] = ~np.isnan(margin[ci])
    return ChunkResult(rows, possible, reach, width, foot, checked, free, margin)
