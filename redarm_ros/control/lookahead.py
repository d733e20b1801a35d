"""Joint motion planned over a receding horizon within the acceleration limits (numpy only, no ROS).

Where a streamed path asks a joint for more than its acceleration limit (an elbow passing over the
shoulder fast reverses joint 2 at up to 1.4 times its limit), clipping each step's acceleration as it
comes leaves the joint behind after the reversal, and it never catches up. Planned ahead, the joint
starts its reversal early and cuts the corner by the least it can.

**The plan.** The horizon is ``blocks`` blocks of ``block_steps`` control steps of ``dt`` s each, the
joint acceleration constant within a block. Each joint ``j`` (independently: the joints' limits do not
couple) gets the accelerations ``a`` (rad/s^2) that minimise

    sum_k (q(t_k) - r_k)^2 + T_k^2 (v(t_k) - v_k)^2 + eps |a|^2,    |a_i| <= share * max_acc_j

from its present position and velocity, ``r_k`` the path's joints at the end of block ``k`` (the IK of
the stream's predicted poses), ``v_k`` the path's velocity there (a parabola through the neighbouring
targets; matched positions alone leave the accelerations ringing from block to block), ``T_k`` the
block's duration, integrated step by step as the controller does (``v += a dt; q += v dt``). The blocks
grow with time (the prediction grows less certain). The problem is a small box-constrained QP per joint
(``blocks`` variables, one Hessian for every joint), solved exactly by a primal active-set method from
the last plan's bounds. The joints with acceleration to spare then make up for the tool error of those
held back: their targets move by the damped least-squares answer to it (position, and orientation as
0.3 m per rad), and they are planned again (on the fast circle over the PA10's shoulder: 6.6 instead of
8.0 mm p95, 0.3 instead of 0.8 deg). Only the first step is taken; the next step plans again from where
the joints are, with the stream's newest estimate.

Units: rad, rad/s, rad/s^2, s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: share of each joint's acceleration limit a plan uses (the command's own limiter uses all of it)
ACC_SHARE = 0.98
#: weights of the tool error the free joints make up for: position (m) and orientation (rad, as 0.3 m)
COMP_WEIGHTS = np.array([1.0, 1.0, 1.0, 0.3, 0.3, 0.3])
#: m: the damping of that least-squares answer (no large joint motion for a nearly singular direction)
COMP_DAMPING = 0.02
#: weight of the acceleration regulariser (rad^2 per (rad/s^2)^2): keeps the QP strictly convex
ACC_REG = 1e-10


def box_qp(H: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, x0: np.ndarray,
           max_iter: int = 50) -> np.ndarray:
    """The minimiser of ``x^T H x / 2 + g^T x`` subject to ``lo <= x <= hi`` (``H`` positive definite,
    small): a primal active-set method from ``x0`` (e.g. the unconstrained minimiser) clipped into the
    box. Returns the best feasible point found within ``max_iter`` iterations (the optimum in every case
    met so far: it ends in a few)."""
    x = np.clip(x0, lo, hi)
    fixed = (x <= lo) | (x >= hi)
    scale = 1e-12 * (1.0 + float(np.max(np.abs(hi - lo))))
    for _ in range(max_iter):
        free = ~fixed
        target = x.copy()
        if free.any():
            rows = H[free]
            target[free] = np.linalg.solve(rows[:, free], -(g[free] + rows[:, fixed] @ x[fixed]))
        step = target - x
        if float(np.max(np.abs(step))) <= scale:
            # Stationary on this working set: release the bound whose multiplier has the wrong sign.
            grad = H @ x + g
            mult = np.where(fixed, np.where(x >= hi, -grad, grad), np.inf)  # >= 0 at an optimal bound
            i = int(np.argmin(mult))
            if mult[i] >= -1e-12 * (1.0 + float(np.max(np.abs(grad)))):
                return x
            fixed[i] = False
            continue
        # Move towards the working set's minimiser until a bound blocks.
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(step > 0.0, (hi - x) / step, np.where(step < 0.0, (lo - x) / step, np.inf))
        room[fixed] = np.inf
        i = int(np.argmin(room))
        if room[i] < 1.0:
            x = np.clip(x + max(float(room[i]), 0.0) * step, lo, hi)
            fixed[i] = True
        else:
            x = np.clip(target, lo, hi)
    return x


def _velocity_weights(t: np.ndarray) -> np.ndarray:
    """(k, k): the velocities at the times ``t`` (k >= 3, ascending) of values there, from the parabola
    through each point and its neighbours (the first and last: the nearest three)."""
    k = len(t)
    D = np.zeros((k, k))
    for i in range(k):
        j = min(max(i - 1, 0), k - 3)
        a, b, c = t[j], t[j + 1], t[j + 2]
        x = t[i]
        # derivative at x of the Lagrange basis polynomials through a, b, c
        D[i, j] = (2 * x - b - c) / ((a - b) * (a - c))
        D[i, j + 1] = (2 * x - a - c) / ((b - a) * (b - c))
        D[i, j + 2] = (2 * x - a - b) / ((c - a) * (c - b))
    return D


@dataclass(frozen=True)
class JointPlan:
    """A planned motion: the accelerations ``acc`` (blocks, n) rad/s^2, the joints ``q`` (n,) and their
    velocity ``qd`` (n,) after the first step, and whether an acceleration bound holds the plan
    (``bound``: the path asks more than the joints can, they cut the corner)."""

    acc: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    bound: bool


def growing_blocks(dt: float, first: float, growth: float, horizon: float) -> list[int]:
    """Block lengths (steps of ``dt`` s) covering ``horizon`` s: the first about ``first`` s, each next
    ``growth`` times longer (the prediction they are planned on grows less certain with time); a rest
    shorter than half a block joins the last block."""
    total = max(1, round(horizon / dt))
    blocks: list[int] = []
    length = first / dt
    while sum(blocks) < total:
        n = max(1, round(length))
        rest = total - sum(blocks) - n
        if rest < 0.5 * n * growth:
            n += rest
        blocks.append(n)
        length *= growth
    return blocks


class JointLookahead:
    """The receding-horizon plan of the module docstring for one step ``dt`` (s), blocks of
    ``block_steps`` steps each (at least two blocks), the joints' ``max_acc`` (rad/s^2)."""

    def __init__(self, dt: float, block_steps: list[int], max_acc: np.ndarray,
                 share: float = ACC_SHARE) -> None:
        if not dt > 0.0 or len(block_steps) < 3 or min(block_steps) < 1:
            raise ValueError(f"a plan needs dt > 0 and 3 blocks of at least 1 step, got {dt}, {block_steps}")
        self.dt = float(dt)
        self.block_steps = tuple(int(m) for m in block_steps)
        self.bound_acc = share * np.asarray(max_acc, float)
        L = np.asarray(self.block_steps, float)
        N = len(L)
        #: steps from now to the end of each block
        self.ends = np.cumsum(L)
        # Position at the end of block k from the accelerations: block i (L_i steps, ending at step n_i)
        # adds dt^2 a_i (L_i (L_i + 1) / 2 within it + L_i (n_k - n_i) after it).
        C = dt * dt * (L * (L + 1.0) / 2.0 + L * (self.ends[:, None] - self.ends[None, :]))
        self.C = np.tril(C)
        # Velocity at the end of block k: every block up to k adds L_i dt a_i.
        self.V = np.tril(np.broadcast_to(L * dt, (N, N)))
        # A velocity error at a block's end weighs as the position error it makes over that block (matched
        # positions alone leave the accelerations ringing from block to block).
        self.vel_weight = (L * dt) ** 2
        self.H = (self.C.T @ self.C + self.V.T @ (self.vel_weight[:, None] * self.V)
                  + ACC_REG * np.eye(N))
        self.H_inv = np.linalg.inv(self.H)
        self._velocity = _velocity_weights(self.times())
        self._warm: np.ndarray | None = None  # the last plan's accelerations: where the next one starts

    @property
    def horizon(self) -> float:
        """How far ahead (s) the plan reaches."""
        return float(self.ends[-1]) * self.dt

    def times(self) -> np.ndarray:
        """The times (s from now) of the block ends, where the path's joints are asked for."""
        return self.ends * self.dt

    def path_acceleration(self, targets: np.ndarray) -> np.ndarray:
        """The joint accelerations (blocks - 2, n) rad/s^2 of the path through ``targets`` (blocks, n) at
        :meth:`times` (second differences)."""
        h = np.diff(self.times())[:, None]
        vel = np.diff(targets, axis=0) / h
        return 2.0 * np.diff(vel, axis=0) / (h[1:] + h[:-1])

    def plan(self, q0: np.ndarray, v0: np.ndarray, targets: np.ndarray,
             jacobian: Callable[[np.ndarray], np.ndarray] | None = None) -> JointPlan:
        """The plan from joints ``q0`` (n,) moving at ``v0`` (n,) towards the path's joints ``targets``
        (blocks, n) at :meth:`times`, and their velocities (from the parabola through each target and its
        neighbours); ``jacobian(q)`` (6, n), if given, lets the free joints make up for the held ones."""
        dt = self.dt
        free = q0[None, :] + (self.ends * dt)[:, None] * v0[None, :]  # where the joints coast to
        path_vel = self._velocity @ targets
        # gradient of the cost at a = 0, one column per joint
        G = self.C.T @ (free - targets) + self.V.T @ (self.vel_weight[:, None] * (v0[None, :] - path_vel))
        A = -self.H_inv @ G
        over = np.any(np.abs(A) > self.bound_acc[None, :], axis=0)
        n = len(self.block_steps)
        warm = self._warm if self._warm is not None and self._warm.shape == A.shape else A
        for j in np.flatnonzero(over):
            b = np.full(n, self.bound_acc[j])
            # (from the last plan's active bounds: a step later they are mostly the same)
            A[:, j] = box_qp(self.H, G[:, j], -b, b, warm[:, j])
        free_j = ~over
        if jacobian is not None and np.any(over) and np.any(free_j):
            # The joints with acceleration to spare make up, where they can, for the tool error of those
            # held back: their targets move by the damped least-squares answer to it, knot by knot.
            # (a Jacobian every other knot: the arm moves little in between)
            dev = free + self.C @ A - targets  # (the free joints' own deviation is ~0)
            shifted = targets.copy()
            for k in range(n):
                if k % 2 == 0:
                    J = jacobian(targets[k]) * COMP_WEIGHTS[:, None]
                    Jf = J[:, free_j]
                    solve = np.linalg.inv(Jf @ Jf.T + COMP_DAMPING ** 2 * np.eye(J.shape[0]))
                shifted[k, free_j] -= Jf.T @ (solve @ (J[:, over] @ dev[k, over]))
            path_vel = self._velocity @ shifted
            G2 = self.C.T @ (free - shifted) + self.V.T @ (self.vel_weight[:, None]
                                                             * (v0[None, :] - path_vel))
            A2 = -self.H_inv @ G2
            for j in np.flatnonzero(free_j):
                a = A2[:, j]
                if np.any(np.abs(a) > self.bound_acc[j]):
                    b = np.full(n, self.bound_acc[j])
                    a = box_qp(self.H, G2[:, j], -b, b, warm[:, j])
                A[:, j] = a
        self._warm = A
        qd = v0 + dt * A[0]
        return JointPlan(A, q0 + dt * qd, qd, bool(np.any(over)))
