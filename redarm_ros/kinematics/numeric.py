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


def _batch_tables(arm: Arm) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per joint i the parent -> child transform as ``G_i(t) = A_i + cos t B_i + sin t C_i`` (4x4 each,
    (n, 4, 4) stacked: origin @ Rot(axis, t) with Rot = P + cos t (I - P) + sin t K) and the tool transform;
    built once per model (cached on it). Each child frame is turned by a fixed P_i that takes z onto the
    joint's axis (G_i -> P_{i-1}^T G_i P_i, tool -> P_n^T tool): the chain's products are unchanged, and
    every axis in the base frame is then the z column of its frame."""
    tables = arm.__dict__.get("_fk_batch_Gz")
    if tables is None:
        n = arm.n
        A, B, C = np.zeros((n, 4, 4)), np.zeros((n, 4, 4)), np.zeros((n, 4, 4))
        P_prev = np.eye(4)
        for i, j in enumerate(arm.chain):
            a = np.asarray(j.axis, dtype=float)
            P = np.outer(a, a)
            K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
            Ro = j.origin[:3, :3]
            Ai, Bi, Ci = np.zeros((4, 4)), np.zeros((4, 4)), np.zeros((4, 4))
            Ai[:3, :3], Ai[:3, 3], Ai[3, 3] = Ro @ P, j.origin[:3, 3], 1.0
            Bi[:3, :3], Ci[:3, :3] = Ro @ (np.eye(3) - P), Ro @ K
            Pz = np.eye(4)
            Pz[:3, :3] = _z_onto(a)
            A[i], B[i], C[i] = (P_prev.T @ M @ Pz for M in (Ai, Bi, Ci))
            P_prev = Pz
        tables = (A, B, C, P_prev.T @ arm.tool)
        arm.__dict__["_fk_batch_Gz"] = tables
    return tables


def _z_onto(a: np.ndarray) -> np.ndarray:
    """A rotation taking z onto the unit vector a."""
    v = np.array([-a[1], a[0], 0.0])  # z x a
    s, c = float(np.linalg.norm(v)), float(a[2])
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]]) / s
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def fk_jacobian_batch(arm: Arm, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R (m, 3, 3), p (m, 3), J (m, 6, n)): :meth:`Arm.fk_jacobian` for m joint vectors Q (m, n) at once.

    All joint transforms come from one expression and the chain is one 4x4 product per joint: the numpy
    call count, not the arithmetic, is the cost at these sizes."""
    A, B, C, tool = _batch_tables(arm)
    m, n = Q.shape
    G = A + np.cos(Q)[:, :, None, None] * B + np.sin(Q)[:, :, None, None] * C  # (m, n, 4, 4)
    F = np.empty((m, n, 4, 4))  # base -> joint i's (turned) frame after its rotation
    F[:, 0] = Tc = G[:, 0]
    for i in range(1, n):
        F[:, i] = Tc = Tc @ G[:, i]
    Tt = Tc @ tool
    Z = F[:, :, :3, 2]  # (m, n, 3): the axes in the base frame
    D = Tt[:, None, :3, 3] - F[:, :, :3, 3]  # joint origin -> tool
    J = np.empty((m, 6, n))
    J[:, :3, :] = (Z[..., _YZX] * D[..., _ZXY] - Z[..., _ZXY] * D[..., _YZX]).transpose(0, 2, 1)
    J[:, 3:, :] = Z.transpose(0, 2, 1)
    return Tt[:, :3, :3], Tt[:, :3, 3], J


_YZX, _ZXY = [1, 2, 0], [2, 0, 1]  # index orders of the written-out cross product
_VEE_PLUS, _VEE_MINUS = [7, 2, 3], [5, 6, 1]  # (2,1) (0,2) (1,0) and (1,2) (2,0) (0,1) of a flat 3x3


def _errors_batch(R: np.ndarray, p: np.ndarray, Td: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E (m, 6), squared position error (m,), squared rotation angle (m,)) of m tool poses: E holds the
    position error and the rotation vector taking R onto the target's."""
    Re = (Td[:3, :3] @ R.transpose(0, 2, 1)).reshape(-1, 9)  # rows of Rd R^T
    v = Re[:, _VEE_PLUS] - Re[:, _VEE_MINUS]  # the axis times 2 sin(angle)
    # (ufuncs, not np.clip: its wrapper costs more than the arithmetic at these sizes)
    c = np.minimum(np.maximum((Re[:, 0] + Re[:, 4] + Re[:, 8] - 1.0) * 0.5, -1.0), 1.0)
    sn = 0.5 * np.sqrt(np.einsum("ij,ij->i", v, v))
    ang = np.arctan2(sn, c)
    # angle / (2 sin): 1/2 at small angles; near pi the rotation vector's length is right and its axis
    # from v is poor, but the descent only needs a direction there
    k = np.where(sn > 1e-7, ang / (2.0 * np.maximum(sn, 1e-300)), np.where(c < 0, np.pi, 0.5))
    E = np.empty((len(p), 6))
    E[:, :3] = Td[:3, 3] - p
    E[:, 3:] = v * k[:, None]
    return E, np.einsum("ij,ij->i", E[:, :3], E[:, :3]), ang * ang


def solve_dls_multistart(
    arm: Arm,
    T: np.ndarray,
    q0: Sequence[float],
    *,
    tol: float = 1e-5,
    timeout_s: float | None = 5e-3,
    max_iter: int = 1000,
    starts: int = 32,
    stall_iters: int = 8,
    damping: float = 1e-3,
    max_step: float = 1.0,
    rng_seed: int = 0,
) -> tuple[np.ndarray | None, IKInfo]:
    """Damped least squares from the seed and from ``starts - 1`` random starts at once (vectorised).

    The seed ``q0`` and random in-limit joint vectors (numpy generator seeded with ``rng_seed``) descend
    together, each with its own Levenberg-Marquardt damping (initial ``damping``; /3 after a good step,
    x4 after a rejected one), steps of at most ``max_step`` rad per joint and the active-set limit
    handling of :func:`solve_dls`; a random start that makes no progress for ``stall_iters`` iterations
    is replaced by a fresh one. Of the starts that converge in the same iteration, the one nearest the
    seed is returned. Ends at the first start within ``tol`` (m and rad), after ``max_iter`` batched
    iterations or at ``timeout_s`` (s; None: no timeout). Returns as :func:`solve_dls` (on timeout the
    errors of the best current point). The TRAC-IK-style solver of the URDF chains without a closed
    form (:mod:`.urdf_chain`): one batched FK + Jacobian per iteration for all starts, fresh ones
    included, so 32 starts cost little more than one descent and find a solution of a random reachable
    pose where one descent often stalls at a joint limit.
    """
    t0 = time.perf_counter()
    try:
        Tl = arm.check_pose(T)
        q_start = arm.check_q(q0, "q0")
    except InvalidInputError as exc:
        return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
    Td = np.array(Tl)
    lo, up = arm.lower, arm.upper
    locked = (up - lo) <= 0.0
    rng = np.random.default_rng(rng_seed)
    m, n = max(1, int(starts)), arm.n
    Qc = rng.uniform(lo, up, (m, n))  # the candidates evaluated next
    Qc[0] = np.clip(q_start, lo, up)  # row 0 descends from the seed (and is never replaced)
    Q = Qc.copy()  # each row's accepted point, its Jacobian, error and squared error
    J = np.zeros((m, 6, n))
    E = np.zeros((m, 6))
    cost = np.full(m, np.inf)
    best = np.full(m, np.inf)
    lam = np.full(m, damping)
    since = np.zeros(m, dtype=int)
    diag = np.arange(6)
    tol2 = tol * tol
    it = 0
    n_starts = m
    while True:
        Rc, pc, Jc = fk_jacobian_batch(arm, Qc)
        Ec, pe2, re2 = _errors_batch(Rc, pc, Td)
        done = np.flatnonzero((pe2 < tol2) & (re2 < tol2))
        if len(done):  # the one nearest the seed of those converged now
            i = int(done[np.argmin(((Qc[done] - q_start) ** 2).sum(axis=1))])
            return Qc[i].copy(), IKInfo(IKStatus.SUCCESS, "ok", pos_err=math.sqrt(pe2[i]),
                                        rot_err=math.sqrt(re2[i]), iterations=it, candidates=n_starts)
        cc = pe2 + re2
        good = cc < cost
        np.copyto(Q, Qc, where=good[:, None])
        np.copyto(J, Jc, where=good[:, None, None])
        np.copyto(E, Ec, where=good[:, None])
        np.copyto(cost, cc, where=good)
        lam = np.minimum(np.maximum(np.where(good, lam * (1.0 / 3.0), lam * 4.0), 1e-7), 1e3)
        since += 1
        since[cost < best * 0.95] = 0
        np.minimum(best, cost, out=best)
        if it >= max_iter or (timeout_s is not None and time.perf_counter() - t0 > timeout_s):
            break
        it += 1
        Ja = J * ~locked if locked.any() else J  # locked joints (lower == upper) stay put
        for _ in range(2):  # active set, as solve_dls
            Jt = Ja.transpose(0, 2, 1)
            A = Ja @ Jt
            A[:, diag, diag] += (lam * lam)[:, None]
            dq = (Jt @ np.linalg.solve(A, E[:, :, None]))[:, :, 0]
            out = ((Q <= lo) & (dq < 0.0)) | ((Q >= up) & (dq > 0.0))
            if not out.any():
                break
            Ja = Ja * ~out[:, None, :]
        # at most max_step rad per joint: a full Gauss-Newton step from far away mostly overshoots
        big = np.abs(dq).max(axis=1)
        dq *= (max_step / np.maximum(big, max_step))[:, None]
        Qc = np.minimum(np.maximum(Q + dq, lo), up)
        stale = np.flatnonzero(since[1:] >= stall_iters) + 1  # the seed's row keeps descending
        if len(stale):  # fresh starts for the stalled ones, evaluated with the steps
            Qc[stale] = rng.uniform(lo, up, (len(stale), n))
            cost[stale] = best[stale] = np.inf
            since[stale], lam[stale] = 0, damping
            n_starts += len(stale)
    k = int(np.argmin(cost))  # the best of the current points
    why = "timeout" if it < max_iter else "max_iter"
    return None, IKInfo(
        IKStatus.TIMEOUT,
        f"no convergence to tol {tol:g} ({why} after {it} batched iterations of {m} starts, "
        f"{n_starts} in all)",
        pos_err=float(np.linalg.norm(E[k, :3])), rot_err=float(np.linalg.norm(E[k, 3:])), iterations=it,
        candidates=n_starts,
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
