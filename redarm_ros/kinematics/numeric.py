"""Numeric IK for any arm model: damped least squares (full 6-D) and the thesis "Flow" update.

* :func:`solve_dls`: Levenberg-Marquardt style damped least squares on the 6-D error [position (m);
  rotation vector (rad)], joint-limit clamping after every step, random restarts within the limits
  when it stalls (seeded: deterministic), iteration / tolerance / timeout parameters.
* :func:`solve_flow`: Ghotbi's "Flow" algorithm (M.Eng thesis 2009, Sec. 3.1): for every joint
  ``Drive_i = K (p_des - p_end) . (z_i x (p_end - o_i))``, position only. ``variant="sequential"``
  updates joint by joint from the end effector to the base, refreshing the end-effector position after
  each joint (as the thesis' text implies: a Gauss-Seidel Jacobian transpose); ``variant="batch"``
  updates all joints from one FK evaluation, i.e. the Jacobian-transpose step ``dq = K J_v^T e``.
  The thesis leaves K, the tolerance and the stall count open; here ``gain="auto"`` takes the
  step that minimises the linearised error along the update (Buss' alpha for batch, 1/|v_i|^2 per joint
  for sequential), and ``normalize=True`` projects on the unit vector v_i/|v_i| as the thesis' prose says.
  Unreachable targets end after ``stall_iters`` iterations without progress (Sec. 3.3).

Both return ``(q or None, IKInfo)``; orientation errors are angles in rad. Quaternions are not used here.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.quaternion import rotation_error
from redarm_ros.kinematics.result import IKInfo, IKStatus

if TYPE_CHECKING:  # the model imports this module for its ik_nearest fallback
    from redarm_ros.kinematics.model import Arm

__all__ = ["solve_dls", "solve_dls_multistart", "solve_flow", "fk_jacobian", "fk_jacobian_batch"]


def fk_jacobian(arm: Arm, q: Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R (3, 3), p (3,), J (6, n)) of the tool at q: the model's :meth:`Arm.fk_jacobian`."""
    return arm.fk_jacobian(q)


def _errors(R: np.ndarray, p: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, float, float]:
    ep = T[:3, 3] - p
    er = rotation_error(R, T[:3, :3])
    return np.concatenate([ep, er]), float(np.linalg.norm(ep)), float(np.linalg.norm(er))


def solve_dls(
    arm: Arm,
    T: np.ndarray,
    q0: Sequence[float],
    *,
    tol: float = 1e-5,
    max_iter: int = 1000,
    timeout_s: float | None = 5e-3,
    damping: float = 1e-3,
    restarts: bool = True,
    stall_iters: int = 12,
    progress: float = 0.05,
    rng_seed: int = 0,
) -> tuple[np.ndarray | None, IKInfo]:
    """Damped least squares with full 6-D orientation for any arm.

    T: 4x4 target (base frame). q0: start (rad). Converged when the position error < ``tol`` (m) and
    the orientation error < ``tol`` (rad). ``damping``: initial Levenberg-Marquardt lambda (adapted:
    /3 after a good step, x4 after a rejected one). After every step q is clamped into the limits
    (locked joints, lower == upper, stay put). With ``restarts`` a random in-limit start (numpy
    generator seeded with ``rng_seed``) replaces a run that made no progress for ``stall_iters``
    iterations (progress: the best squared error shrinks by the fraction ``progress``). Stops at
    ``max_iter`` iterations or ``timeout_s`` seconds (None: no timeout).
    Returns (q or None, IKInfo) with status SUCCESS, TIMEOUT (budget exhausted: errors of the best q
    found) or INVALID_INPUT.
    """
    t0 = time.perf_counter()
    try:
        Tl = arm.check_pose(T)
        q = arm.check_q(q0, "q0").copy()
    except InvalidInputError as exc:
        return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
    Td = np.array(Tl)
    lo, up = arm.lower, arm.upper
    free = (up - lo) > 0.0
    q = np.clip(q, lo, up)
    rng = np.random.default_rng(rng_seed)
    R, p, J = arm.fk_jacobian(q)
    e, pe, re = _errors(R, p, Td)
    cost = float(e @ e)
    lam = damping
    best = (cost, q.copy(), pe, re)
    since_progress = 0
    it = 0
    n_restart = 0
    status = IKStatus.TIMEOUT
    while it < max_iter:
        if pe < tol and re < tol:
            status = IKStatus.SUCCESS
            break
        if timeout_s is not None and (it & 3) == 0 and time.perf_counter() - t0 > timeout_s:
            break
        it += 1
        dq = np.zeros(arm.n)
        act = free
        try:
            for _ in range(2):
                Jf = J[:, act]
                A = Jf @ Jf.T
                A[np.diag_indices(6)] += lam * lam
                dq[:] = 0.0
                dq[act] = Jf.T @ np.linalg.solve(A, e)
                # a joint at a limit that the step pushes further out is held there and the step solved
                # again without it (active set): clamping alone would waste the step's share on it
                out = act & (((q <= lo) & (dq < 0.0)) | ((q >= up) & (dq > 0.0)))
                if not out.any():
                    break
                act = act & ~out
        except np.linalg.LinAlgError:  # rank-deficient J with tiny damping: damp more
            lam = min(lam * 4.0, 1e3)
            since_progress += 1
            continue
        qn = np.clip(q + dq, lo, up)
        Rn, pn, Jn = arm.fk_jacobian(qn)
        en, pen, ren = _errors(Rn, pn, Td)
        cn = float(en @ en)
        if cn < cost:
            q, R, p, J, e, pe, re, cost = qn, Rn, pn, Jn, en, pen, ren, cn
            lam = max(lam / 3.0, 1e-7)
            if cost < best[0] * (1.0 - progress):
                since_progress = 0
            else:
                since_progress += 1
            if cost < best[0]:
                best = (cost, q.copy(), pe, re)
        else:
            lam = min(lam * 4.0, 1e3)
            since_progress += 1
        if restarts and since_progress >= stall_iters:
            n_restart += 1
            q = rng.uniform(lo, up)
            R, p, J = arm.fk_jacobian(q)
            e, pe, re = _errors(R, p, Td)
            cost = float(e @ e)
            lam = damping
            since_progress = 0
            best = min(best, (cost, q.copy(), pe, re), key=lambda b: b[0])
    if status is IKStatus.SUCCESS:
        return q, IKInfo(
            IKStatus.SUCCESS, "ok", pos_err=pe, rot_err=re, iterations=it, candidates=n_restart + 1
        )
    why = "timeout" if it < max_iter else "max_iter"
    return None, IKInfo(
        IKStatus.TIMEOUT,
        f"no convergence to tol {tol:g} ({why} after {it} iterations, {n_restart} restarts)",
        pos_err=best[2],
        rot_err=best[3],
        iterations=it,
        candidates=n_restart + 1,
    )


def fk_jacobian_batch(arm: Arm, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R (m, 3, 3), p (m, 3), J (m, 6, n)): :meth:`Arm.fk_jacobian` for m joint vectors Q (m, n) at once."""
    tables = arm.__dict__.get("_fk_batch_tables")
    if tables is None:  # per joint: origin R, origin p, axis, and Rot(axis, t) = P + cos t C + sin t K
        tables = []
        for j in arm.chain:
            a = np.asarray(j.axis, dtype=float)
            P = np.outer(a, a)
            K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
            tables.append((j.origin[:3, :3].copy(), j.origin[:3, 3].copy(), a, P, np.eye(3) - P, K))
        arm.__dict__["_fk_batch_tables"] = tables
    m = len(Q)
    R = np.broadcast_to(np.eye(3), (m, 3, 3))
    p = np.zeros((m, 3))
    org = np.empty((arm.n, m, 3))
    Z = np.empty((arm.n, m, 3))
    C, S = np.cos(Q).T[:, :, None, None], np.sin(Q).T[:, :, None, None]
    for i, (Ro, po, a, P, Cm, K) in enumerate(tables):
        p = p + R @ po
        R = R @ Ro
        org[i] = p
        Z[i] = R @ a
        R = R @ (P + C[i] * Cm + S[i] * K)
    p = p + R @ arm.tool[:3, 3]
    R = R @ arm.tool[:3, :3]
    J = np.empty((m, 6, arm.n))
    D = p[None, :, :] - org  # (n, m, 3); z x d written out (np.cross costs 10x more on these sizes)
    J[:, 0, :] = (Z[:, :, 1] * D[:, :, 2] - Z[:, :, 2] * D[:, :, 1]).T
    J[:, 1, :] = (Z[:, :, 2] * D[:, :, 0] - Z[:, :, 0] * D[:, :, 2]).T
    J[:, 2, :] = (Z[:, :, 0] * D[:, :, 1] - Z[:, :, 1] * D[:, :, 0]).T
    J[:, 3:, :] = Z.transpose(1, 2, 0)
    return R, p, J


def _errors_batch(R: np.ndarray, p: np.ndarray, Td: np.ndarray) -> np.ndarray:
    """(m, 6) errors [position; rotation vector taking R onto the target's] of m tool poses."""
    Re = Td[:3, :3] @ R.transpose(0, 2, 1)
    v = np.stack([Re[:, 2, 1] - Re[:, 1, 2], Re[:, 0, 2] - Re[:, 2, 0], Re[:, 1, 0] - Re[:, 0, 1]], axis=1)
    c = np.clip((np.trace(Re, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    sn = 0.5 * np.linalg.norm(v, axis=1)
    ang = np.arctan2(sn, c)
    # angle / (2 sin): 1/2 at small angles; near pi the rotation vector's length is right and its axis
    # from v is poor, but the descent only needs a direction there
    k = np.where(sn > 1e-7, ang / (2.0 * np.maximum(sn, 1e-300)), 0.5)
    k = np.where((sn <= 1e-7) & (c < 0), np.pi, k)
    return np.concatenate([Td[:3, 3] - p, v * k[:, None]], axis=1)


def solve_dls_multistart(
    arm: Arm,
    T: np.ndarray,
    q0: Sequence[float],
    *,
    tol: float = 1e-5,
    timeout_s: float | None = 5e-3,
    max_iter: int = 1000,
    starts: int = 16,
    stall_iters: int = 8,
    damping: float = 1e-3,
    rng_seed: int = 0,
) -> tuple[np.ndarray | None, IKInfo]:
    """Damped least squares from the seed and from ``starts - 1`` random starts at once (vectorised).

    The seed ``q0`` and random in-limit joint vectors (numpy generator seeded with ``rng_seed``) descend
    together, each with its own damping and the active-set limit handling of :func:`solve_dls`; a random
    start that makes no progress for ``stall_iters`` iterations is replaced by a fresh one. Of the starts
    that converge in the same iteration, the one nearest the seed is returned. Ends at the first start
    within ``tol`` (m and rad), after ``max_iter`` batched iterations or at ``timeout_s`` (s; None: no
    timeout). Returns as :func:`solve_dls`. The TRAC-IK-style solver of the URDF chains without a closed
    form (:mod:`.urdf_chain`): 16 starts find a solution of a random reachable pose within 5 ms where one
    descent often stalls at a joint limit.
    """
    t0 = time.perf_counter()
    try:
        Tl = arm.check_pose(T)
        q_start = arm.check_q(q0, "q0")
    except InvalidInputError as exc:
        return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
    Td = np.array(Tl)
    lo, up = arm.lower, arm.upper
    free = (up - lo) > 0.0
    rng = np.random.default_rng(rng_seed)
    m = max(1, int(starts))
    Q = rng.uniform(lo, up, (m, arm.n))
    Q[0] = np.clip(q_start, lo, up)  # row 0 descends from the seed (and is never replaced)
    R, p, J = fk_jacobian_batch(arm, Q)
    E = _errors_batch(R, p, Td)
    cost = np.einsum("ij,ij->i", E, E)
    lam = np.full(m, damping)
    best = cost.copy()
    since = np.zeros(m, dtype=int)
    eye6 = np.eye(6)
    it = 0
    n_starts = m
    best_any = (math.inf, math.inf)
    while it < max_iter:
        pe = np.linalg.norm(E[:, :3], axis=1)
        re = np.linalg.norm(E[:, 3:], axis=1)
        done = np.nonzero((pe < tol) & (re < tol))[0]
        if len(done):  # the one nearest the seed of those converged now
            i = int(done[np.argmin(((Q[done] - q_start) ** 2).sum(axis=1))])
            return Q[i].copy(), IKInfo(IKStatus.SUCCESS, "ok", pos_err=float(pe[i]), rot_err=float(re[i]),
                                       iterations=it, candidates=n_starts)
        k = int(np.argmin(pe + re))
        if pe[k] + re[k] < sum(best_any):
            best_any = (float(pe[k]), float(re[k]))
        if timeout_s is not None and time.perf_counter() - t0 > timeout_s:
            break
        it += 1
        act = np.broadcast_to(free, Q.shape).copy()
        for _ in range(2):  # active set, as solve_dls
            Jm = J * act[:, None, :]
            A = Jm @ Jm.transpose(0, 2, 1) + (lam * lam)[:, None, None] * eye6
            dq = (Jm.transpose(0, 2, 1) @ np.linalg.solve(A, E[:, :, None]))[:, :, 0]
            out = act & (((Q <= lo) & (dq < 0.0)) | ((Q >= up) & (dq > 0.0)))
            if not out.any():
                break
            act &= ~out
        Qn = np.clip(Q + dq, lo, up)
        Rn, pn, Jn = fk_jacobian_batch(arm, Qn)
        En = _errors_batch(Rn, pn, Td)
        cn = np.einsum("ij,ij->i", En, En)
        good = cn < cost
        Q[good], J[good], E[good], cost[good] = Qn[good], Jn[good], En[good], cn[good]
        lam = np.where(good, np.maximum(lam / 3.0, 1e-7), np.minimum(lam * 4.0, 1e3))
        progress = cost < best * 0.95
        since = np.where(progress, 0, since + 1)
        best = np.minimum(best, cost)
        since[0] = 0 if since[0] < stall_iters else since[0]  # the seed's row keeps descending (or stays)
        stale = np.nonzero(since >= stall_iters)[0]
        stale = stale[stale > 0]
        if len(stale):  # fresh starts for the stalled ones
            Q[stale] = rng.uniform(lo, up, (len(stale), arm.n))
            Rs, ps, Js = fk_jacobian_batch(arm, Q[stale])
            E[stale], J[stale] = _errors_batch(Rs, ps, Td), Js
            cost[stale] = np.einsum("ij,ij->i", E[stale], E[stale])
            best[stale], since[stale], lam[stale] = cost[stale], 0, damping
            n_starts += len(stale)
    why = "timeout" if it < max_iter else "max_iter"
    return None, IKInfo(
        IKStatus.TIMEOUT,
        f"no convergence to tol {tol:g} ({why} after {it} batched iterations of {m} starts, "
        f"{n_starts} in all)",
        pos_err=best_any[0], rot_err=best_any[1], iterations=it, candidates=n_starts,
    )


def solve_flow(
    arm: Arm,
    p_des: Any,
    q0: Sequence[float],
    *,
    variant: str = "sequential",
    gain: float | str = "auto",
    normalize: bool = False,
    tol: float = 1e-5,
    max_iter: int = 2000,
    timeout_s: float | None = 5e-3,
    stall_iters: int = 50,
    clamp: bool = True,
) -> tuple[np.ndarray | None, IKInfo]:
    """Ghotbi's "Flow" (Jacobian-transpose) IK for the tool position, any arm.

    p_des: target position (3,) in m, or a 4x4 pose whose translation is used (orientation ignored:
    the Flow algorithm is position only). ``variant``: "sequential" (distal -> proximal, end effector
    refreshed after each joint) or "batch" (all joints from one FK, = Jacobian transpose).
    ``gain``: K (rad per m^2, or rad per m with ``normalize``) or "auto". ``clamp``: clip q into the
    limits after each update. Success when |p_des - p_end| < ``tol`` (m). Ends as OUT_OF_REACH after
    ``stall_iters`` iterations without error decrease (thesis Sec. 3.3), TIMEOUT at ``max_iter`` /
    ``timeout_s``. ``rot_err`` in the returned info is 0 (orientation is not part of the task).
    """
    t0 = time.perf_counter()
    try:
        q = arm.check_q(q0, "q0").copy()
        pd_arr = np.asarray(p_des, dtype=float)
        if pd_arr.shape == (4, 4):
            pd_arr = np.array(arm.check_pose(pd_arr))[:3, 3]
        if pd_arr.shape != (3,) or not np.all(np.isfinite(pd_arr)):
            raise InvalidInputError("p_des must be a finite (3,) position or a 4x4 pose", field="p_des")
        if variant not in ("sequential", "batch"):
            raise InvalidInputError(
                f"variant must be 'sequential' or 'batch', got {variant!r}", field="variant"
            )
        if not (gain == "auto" or (isinstance(gain, int | float) and math.isfinite(gain) and gain > 0)):
            raise InvalidInputError(f"gain must be 'auto' or a positive number, got {gain!r}", field="gain")
    except InvalidInputError as exc:
        return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
    lo, up = arm.lower, arm.upper
    if clamp:
        q = np.clip(q, lo, up)
    pd = pd_arr
    best_err = math.inf
    since = 0
    it = 0
    err = math.inf
    status = IKStatus.TIMEOUT
    msg = ""
    while True:
        p, Og, Z = arm.fk_axes(q)
        err = float(np.linalg.norm(pd - p))
        if err < tol:
            status, msg = IKStatus.SUCCESS, "ok"
            break
        if err < best_err * (1.0 - 1e-9):
            best_err, since = err, 0
        else:
            since += 1
            if since >= stall_iters:
                status = IKStatus.OUT_OF_REACH
                msg = f"stalled: error {err:.3g} m not decreasing for {stall_iters} iterations"
                break
        if it >= max_iter or (timeout_s is not None and time.perf_counter() - t0 > timeout_s):
            msg = f"no convergence to {tol:g} m after {it} iterations (error {err:.3g} m)"
            break
        it += 1
        if variant == "batch":
            Jv = np.cross(Z, p - Og).T  # (3, n): v_i = z_i x (p_end - o_i)
            e = pd - p
            g = Jv.T @ e
            if clamp:  # joints pinned at a limit (or locked) do not move: leave them out of the step
                g = np.where(((q <= lo) & (g < 0)) | ((q >= up) & (g > 0)), 0.0, g)
            if normalize:
                nv = np.linalg.norm(Jv, axis=0)
                g = np.where(nv > 1e-12, g / np.where(nv > 1e-12, nv, 1.0), 0.0)
            if gain == "auto":
                Jg = Jv @ g
                den = float(Jg @ Jg)
                k = float(e @ Jg) / den if den > 1e-30 else 0.0
            else:
                k = float(gain)
            q = q + k * g
            if clamp:
                q = np.clip(q, lo, up)
        else:
            pc = p.copy()
            for i in range(arm.n - 1, -1, -1):
                z = Z[i]
                r = pc - Og[i]
                v = np.cross(z, r)
                nv2 = float(v @ v)
                if nv2 < 1e-24:
                    continue
                e = pd - pc
                if gain == "auto":
                    dqi = float(e @ v) / nv2
                else:
                    dqi = float(gain) * float(e @ v) / (math.sqrt(nv2) if normalize else 1.0)
                qi = q[i] + dqi
                if clamp:
                    qi = min(max(qi, lo[i]), up[i])
                dqi = qi - q[i]
                q[i] = qi
                # the end effector turns about joint i's axis; proximal frames are unchanged
                c, s = math.cos(dqi), math.sin(dqi)
                pc = Og[i] + r * c + np.cross(z, r) * s + z * float(z @ r) * (1.0 - c)
    q_out = q if status is IKStatus.SUCCESS else None
    return q_out, IKInfo(status, msg, pos_err=err, rot_err=0.0, iterations=it, candidates=1)
