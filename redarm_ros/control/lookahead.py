"""Joint motion planned over a receding horizon within the acceleration limits (numpy only, no ROS).

Where a streamed path asks a joint for more than its acceleration limit (an elbow passing over the
shoulder fast reverses joint 2 at up to 1.4 times its limit), clipping each step's acceleration as it
comes leaves the joint behind after the reversal, and it never catches up. Planned ahead, the joint
starts its reversal early and cuts the corner by the least it can.

**The plan.** The horizon is ``blocks`` blocks of ``block_steps`` control steps of ``dt`` s each, the
joint acceleration constant within a block. Each joint ``j`` (independently: the joints' limits do not
couple) gets the accelerations ``a`` (rad/s^2) that minimise

    sum_k (q(t_k) - r_k)^2 + w_v (v(t_N) - v_N)^2 + eps |a|^2,    |a_i| <= share * max_acc_j

from its present position and velocity, ``r_k`` the path's joints at the end of block ``k`` (the IK of
the stream's predicted poses), ``v_N`` the path's velocity at the horizon (so the plan does not end in a
state it cannot leave), integrated step by step as the controller does (``v += a dt; q += v dt``). The
problem is a small box-constrained QP per joint (``blocks`` variables, one Hessian for every joint),
solved exactly by a primal active-set method. Only the first step is taken; the next step plans again
from where the joints are, with the stream's newest estimate.

Units: rad, rad/s, rad/s^2, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: share of each joint's acceleration limit a plan uses (the command's own limiter uses all of it)
ACC_SHARE = 0.98
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
    ``growth`` times longer (the prediction they are planned on grows less certain with time)."""
    blocks: list[int] = []
    length, total = first, 0
    while total * dt < horizon - 0.5 * dt:
        n = max(1, min(round(length / dt), round(horizon / dt) - total))
        blocks.append(n)
        total += n
        length *= growth
    return blocks


class JointLookahead:
    """The receding-horizon plan of the module docstring for one step ``dt`` (s), blocks of
    ``block_steps`` steps each (at least two blocks), the joints' ``max_acc`` (rad/s^2)."""

    def __init__(self, dt: float, block_steps: list[int], max_acc: np.ndarray,
                 share: float = ACC_SHARE) -> None:
        if not dt > 0.0 or len(block_steps) < 2 or min(block_steps) < 1:
            raise ValueError(f"a plan needs dt > 0 and 2 blocks of at least 1 step, got {dt}, {block_steps}")
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
        self.vel_gain = L * dt  # velocity added per unit acceleration of each block
        last = L[-1] * dt
        self.vel_weight = last * last  # a velocity error over the last block weighs as its position error
        self.H = (self.C.T @ self.C + self.vel_weight * np.outer(self.vel_gain, self.vel_gain)
                  + ACC_REG * np.eye(N))
        self.H_inv = np.linalg.inv(self.H)

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

    def plan(self, q0: np.ndarray, v0: np.ndarray, targets: np.ndarray) -> JointPlan:
        """The plan from joints ``q0`` (n,) moving at ``v0`` (n,) towards the path's joints ``targets``
        (blocks, n) at :meth:`times`; the path's velocity at the horizon is taken from its last two
        targets."""
        dt = self.dt
        free = q0[None, :] + (self.ends * dt)[:, None] * v0[None, :]  # where the joints coast to
        v_end = (targets[-1] - targets[-2]) / (self.block_steps[-1] * dt)
        # gradient of the cost at a = 0, one column per joint
        G = self.C.T @ (free - targets) + self.vel_weight * np.outer(self.vel_gain, v0 - v_end)
        A = -self.H_inv @ G
        over = np.any(np.abs(A) > self.bound_acc[None, :], axis=0)
        n = len(self.block_steps)
        for j in np.flatnonzero(over):
            b = np.full(n, self.bound_acc[j])
            A[:, j] = box_qp(self.H, G[:, j], -b, b, A[:, j])
        qd = v0 + dt * A[0]
        return JointPlan(A, q0 + dt * qd, qd, bool(np.any(over)))
