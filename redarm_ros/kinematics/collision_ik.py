"""Collision-free IK: the in-limit solution of a pose nearest a seed whose links do not collide.

:func:`nearest_collision_free` searches the whole solution set of a pose for the nearest solution that
passes the self-collision and ground check of :mod:`redarm_ros.geometry.self_collision` (swivel arms:
every swivel and flip pattern; the 6-DOF PowerCube arm: its analytic solutions). The IK front end
(:mod:`.solve`) calls it when the nearest solution collides, the base-move suggestion
(:mod:`.base_placement`) when it verifies a base position. numpy only; units m, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.geometry.self_collision import CollisionModel, self_collision_batch
from redarm_ros.kinematics.protocols import has_analytic_ik, has_swivel

__all__ = ["FreeSolution", "collision_free_rows", "nearest_collision_free"]

PI = math.pi
TWO_PI = 2.0 * math.pi


@dataclass
class FreeSolution:
    """A collision-free solution found by :func:`nearest_collision_free`.

    ``q`` (rad, (n,)), ``swivel`` (rad, NaN for arms without one), ``cost`` (weighted squared distance to
    the seed, rad^2), ``clearance`` (m, >= 0), ``candidates`` (postures checked).
    """

    q: np.ndarray
    swivel: float
    cost: float
    clearance: float
    candidates: int


def collision_free_rows(arm: Any, Q: np.ndarray, model: CollisionModel) -> tuple[np.ndarray, np.ndarray]:
    """(free mask (k,), clearance (k,) in m) of the rows of Q (k, n) rad under ``model``."""
    Q = np.asarray(Q, dtype=float).reshape(-1, arm.n)
    if len(Q) == 0:
        return np.zeros(0, dtype=bool), np.zeros(0)
    res = self_collision_batch(arm, Q, model=model)
    return res.free, res.min_distance


def _wrap_pi(x: np.ndarray) -> np.ndarray:
    """Angles into [-pi, pi)."""
    return (x + PI) % TWO_PI - PI


def nearest_collision_free(
    arm: Any,
    T: np.ndarray,
    q_seed: np.ndarray,
    model: CollisionModel,
    *,
    weights: np.ndarray | None = None,
    step: float = math.radians(1.0),
    refine_rounds: int = 6,
    boundary_rounds: int = 7,
) -> FreeSolution | None:
    """The in-limit, collision-free solution of pose T nearest the seed, or None if every one collides.

    Cost ``sum(w (q - q_seed)^2)`` (rad^2; each joint at its in-limit 2*pi copy nearest the seed), as
    ``ik_nearest``. Swivel arms, all 8 flip patterns at once:

    1. a grid of swivels (``step`` rad, plus the ends and middles of the closed-form feasible intervals,
       so no interval is skipped), solved in one batched ``ik`` and checked in one batched collision test;
    2. every boundary between a collision-free and a colliding grid neighbour (inside a feasible
       interval) is narrowed ``boundary_rounds`` times on 7 interior points (8-fold each round, all
       boundaries in one batch: about 1e-8 rad for the default step), and its collision-free side
       becomes a candidate for every pattern valid there: the constrained optimum lies on such a
       boundary when the unconstrained one is in collision. The 8 patterns at one swivel share every key
       point, so collisions are tested once per swivel;
    3. the cheapest candidate, if it is a grid point, is refined ``refine_rounds`` times on 17 points
       between its neighbours (8-fold narrower each round).

    A collision-free window narrower than ``step`` lying between two colliding grid points can be missed.
    The 6-DOF PowerCube arm: its analytic solutions. Other arms (numeric IK only): None. Raises
    :class:`UnreachableError` for a pose out of reach (swivel arms).
    """
    seed = np.asarray(q_seed, dtype=float)
    w = np.ones(arm.n) if weights is None else np.asarray(weights, dtype=float)
    T = np.asarray(T, dtype=float)

    def costs(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Qn = arm.nearest_copies(Q, seed) if len(Q) else Q
        return Qn, ((Qn - seed) ** 2 * w).sum(axis=1)

    if not has_swivel(arm):
        if not has_analytic_ik(arm):
            return None
        sols = np.asarray(arm.ik(T), dtype=float).reshape(-1, arm.n)
        free, clear = collision_free_rows(arm, sols, model)
        if not free.any():
            return None
        Qn, c = costs(sols[free])
        i = int(np.argmin(c))
        return FreeSolution(Qn[i].copy(), math.nan, float(c[i]), float(clear[free][i]), len(sols))

    def solve_at(swivels: np.ndarray, branches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows (k, n), valid (k,)) of flip pattern ``branches[i]`` at ``swivels[i]``."""
        Q, valid = arm.ik_batch(np.broadcast_to(T, (len(swivels), 4, 4)), _wrap_pi(swivels))
        idx = np.arange(len(swivels))
        return Q[idx, branches], valid[idx, branches]

    ivs = arm.feasible_swivels(T)
    extra = [iv.reshape(-1) for iv in ivs if len(iv)] + [iv.mean(axis=1) for iv in ivs if len(iv)]
    if not extra:
        return None
    n_grid = max(8, int(math.ceil(TWO_PI / step)))
    grid = np.linspace(-PI, PI, n_grid, endpoint=False)
    S = np.unique(np.concatenate([grid, _wrap_pi(np.concatenate(extra))]))
    m = len(S)
    Q, valid = arm.ik_batch(np.broadcast_to(T, (m, 4, 4)), S)
    # The 8 flip patterns at one swivel share every key point (the flips turn joints, not links), so
    # the collision test runs once per swivel, on any valid pattern's row.
    anyv = valid.any(axis=1)
    rep = np.argmax(valid, axis=1)
    iv_idx = np.nonzero(anyv)[0]
    if len(iv_idx) == 0:
        return None
    free_s = np.zeros(m, dtype=bool)
    clear_s = np.full(m, -math.inf)
    free_s[iv_idx], clear_s[iv_idx] = collision_free_rows(arm, Q[iv_idx, rep[iv_idx]], model)
    checked = len(iv_idx)
    if not free_s.any():
        return None
    ii, bb = np.nonzero(valid & free_s[:, None])
    cand_q = [Q[ii, bb]]
    cand_s = [S[ii]]
    cand_b = [bb]
    cand_clear = [clear_s[ii]]
    cand_grid = [ii]
    # free/colliding boundaries between grid neighbours (circular) inside one pattern's feasible set,
    # narrowed 8-fold per round on 7 interior points, all boundaries in one batch
    nxt = np.roll(np.arange(m), -1)
    s_next = np.where(nxt == 0, S[0] + TWO_PI, S[nxt])
    both = valid & valid[nxt]
    bi = np.nonzero(both.any(axis=1) & (free_s != free_s[nxt]))[0]
    if len(bi):
        pb = np.argmax(both[bi], axis=1)  # a pattern valid along the whole grid step
        lo_free = free_s[bi]
        a = np.where(lo_free, S[bi], s_next[bi])  # collision-free end
        b = np.where(lo_free, s_next[bi], S[bi])  # colliding end
        t = np.linspace(0.0, 1.0, 9)[1:-1]
        for _ in range(boundary_rounds):
            pts = a[:, None] + t[None, :] * (b - a)[:, None]
            rows, ok = solve_at(pts.ravel(), np.repeat(pb, len(t)))
            fr = np.zeros(len(rows), dtype=bool)
            if ok.any():
                fr[ok] = collision_free_rows(arm, rows[ok], model)[0]
            checked += int(ok.sum())
            fr = fr.reshape(len(bi), len(t))
            j = np.where(fr.all(axis=1), len(t), np.argmax(~fr, axis=1))  # first colliding point
            k = np.arange(len(bi))
            new_a = np.where(j > 0, pts[k, np.maximum(j - 1, 0)], a)
            b = np.where(j < len(t), pts[k, np.minimum(j, len(t) - 1)], b)
            a = new_a
        Qa, va = arm.ik_batch(np.broadcast_to(T, (len(a), 4, 4)), _wrap_pi(a))
        has = va.any(axis=1)
        if has.any():
            ra = np.argmax(va, axis=1)
            fa, ca = collision_free_rows(arm, Qa[np.nonzero(has)[0], ra[has]], model)
            keep = np.zeros(len(a), dtype=bool)
            keep[np.nonzero(has)[0][fa]] = True
            clear_a = np.full(len(a), -math.inf)
            clear_a[np.nonzero(has)[0]] = ca
            ai, ab = np.nonzero(va & keep[:, None])
            cand_q.append(Qa[ai, ab])
            cand_s.append(a[ai])
            cand_b.append(ab)
            cand_clear.append(clear_a[ai])
            cand_grid.append(np.full(len(ai), -1))
    allq = np.concatenate(cand_q)
    Qn, c = costs(allq)
    k = int(np.argmin(c))
    best_q, best_c = Qn[k].copy(), float(c[k])
    best_clear = float(np.concatenate(cand_clear)[k])
    best_s = float(np.concatenate(cand_s)[k])
    b0 = int(np.concatenate(cand_b)[k])
    i0 = int(np.concatenate(cand_grid)[k])
    if i0 >= 0:  # a grid point: refine between its neighbours
        lo = float(S[i0 - 1]) if i0 > 0 else float(S[-1]) - TWO_PI
        hi = float(S[i0 + 1]) if i0 + 1 < m else float(S[0]) + TWO_PI
        for _ in range(refine_rounds):
            ss = np.linspace(lo, hi, 17)
            rows, ok = solve_at(ss, np.full(17, b0))
            okk = np.nonzero(ok)[0]
            checked += len(okk)
            if len(okk) == 0:
                break
            f2, cl2 = collision_free_rows(arm, rows[okk], model)
            if not f2.any():
                break
            Qn2, c2 = costs(rows[okk[f2]])
            j = int(np.argmin(c2))
            jj = int(okk[f2][j])
            if c2[j] <= best_c:
                best_q, best_c = Qn2[j].copy(), float(c2[j])
                best_clear, best_s = float(cl2[f2][j]), float(ss[jj])
            lo, hi = float(ss[max(jj - 1, 0)]), float(ss[min(jj + 1, 16)])
    s_out = math.remainder(best_s, TWO_PI)
    return FreeSolution(best_q, PI if s_out <= -PI else s_out, best_c, best_clear, checked)
