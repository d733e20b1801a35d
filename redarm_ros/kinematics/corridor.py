"""The swivel corridor of a straight hand route: every swivel at which the arm can follow it, and a schedule.

The route runs from pose ``T_start`` to ``T_goal``: the position on the line, the orientation by slerp
(``R(u) = exp(u r) R_start``, r the rotation vector from the start orientation to the goal's), for the
progress u in [0, 1]. At each pose the joint angles of a flip pattern are closed-form functions of the
swivel (:mod:`.feasible`), so the swivels where every joint keeps its constraints are an exact union of
intervals (:func:`.feasible.feasible_intervals`). The constraints, all joint-value bounds on the start
configuration's flip pattern, so the same interval machinery yields every one of them:

* the joint limits, moved in by ``limit_margin`` (rad);
* the shoulder singularity: ``|sin q2| >= shoulder_margin``. On a flip pattern q2 keeps its sign, so this
  is ``asin(m) <= |q2| <= pi - asin(m)``, a bound on q2 like a limit (likewise the wrist, ``|sin q6| >=
  wrist_margin``, and the elbow, ``|q4| >= elbow_margin`` rad).

Both singularity margins must be positive: where sin q2 (sin q6) passes 0 the pivot joints beside it jump
by pi, so a continuous schedule exists only away from it.

Joints whose range is 2 pi or wider (PA10 joints 5 and 7) fit at every swivel on some 2 pi copy; the arm
cannot jump between copies, so the corridor follows their continuous value: each piece of the corridor
carries the value of those joints at an anchor swivel, and is cut where that branch meets its limit (the
cut is a closed-form root, :func:`.feasible.roots`). The swivel is unwrapped (a schedule may run past pi).

The schedule: the reachable set is propagated forward from the start swivel, sample to sample, widened by
the rate bound ``max_rate * du`` (rad) and intersected with the next sample's corridor; then a backward
pass picks at each sample the reachable swivel nearest the preferred one within the rate bound. Where the
reachable set becomes empty the corridor is closed, and the constraints that close it are named. With
the joints' speeds given (``speed_rates``) the preferred swivel is first replaced by the speed guide
(:meth:`_Corridor.speed_guide`), a coarse grid schedule that keeps the joints' path-speed demand least.

Between samples (adaptive refinement, not a derivative bound): a step of the route is halved, down to
``min_du``, (1) where the number of corridor intervals changes or an interval end moves by more than
``end_step`` rad between neighbouring samples, so every opening and closing of the corridor up to where
it closes is located to ``min_du`` (the steps are refined as the forward pass reaches them); (2) where
the schedule's joints change by more than ``max_joint_step`` rad between neighbouring samples, or the
step's midpoint (its pose on the route and the mean swivel, solved in closed form) passes a bound by
more than MID_SHARE of its margin (a schedule riding a curved bound sags past it between samples). So
each step of the result is checked at both ends and its midpoint, with every joint moving at most
``max_joint_step``; a constraint region that rises and falls within half a refined step, between those
three points, could still be passed by. The margins are the buffer for that: the joint limits
themselves are kept (checked) at every sample. A refinement pass repeats the forward pass only from
the first sample it adds (the pass is causal).

Units: m, rad. Quaternions are (w, x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.kinematics.feasible import (
    ALT_INDEX,
    ALT_SHIFT,
    ALT_SIGN,
    INTERVAL_ROOT_TOL,
    LimitTables,
    SwivelFunctions,
    pattern_intervals,
    roots,
    sorted_unique,
)
from redarm_ros.kinematics.quaternion import (
    matrix_from_quat,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    rotvec_between,
)
from redarm_ros.motion.min_jerk import min_jerk_inverse, min_jerk_rate

if TYPE_CHECKING:
    from redarm_ros.kinematics.swivel import SwivelArm

__all__ = ["SwivelCorridor", "swivel_corridor", "corridor_screen", "route_pose", "PreferredSwivel"]

PI = math.pi
TWO_PI = 2.0 * math.pi
#: rad: a schedule joint this far beyond a bound still counts as on it (round-off of the closed form)
CHECK_TOL = 1e-9
#: most samples of the route (the refinement stops there)
MAX_SAMPLES = 2000
#: share of a bound's margin (the limit margin, the singularity margins) by which a step's midpoint may pass
#: that bound before the step is refined: a schedule that rides a curved bound of the corridor has midpoints
#: beyond it by the chord's sag, which only shrinks 4 times per halving (refining that to CHECK_TOL took
#: hundreds of samples, for a sag of thousandths of the margin)
MID_SHARE = 0.02

#: the speed guide (see :meth:`_Corridor.speed_guide`): route samples, most swivel grid step (rad), and
#: the share above the least path-speed demand that the guide may take to keep nearer the preferred swivel
GUIDE_SAMPLES = 40
GUIDE_STEP = 0.05
GUIDE_SLACK = 1.25

#: the preferred swivel (rad) at progress u and pose T (4x4), or a constant
PreferredSwivel = Callable[[float, np.ndarray], float]


@dataclass(frozen=True)
class SwivelCorridor:
    """The outcome of :func:`swivel_corridor`.

    ``found``: a continuous schedule exists from the start configuration to the goal. ``u`` (m,) the
    progress samples (0 first; up to the last sample before the corridor closed when not found),
    ``swivel`` (m,) the schedule there (rad, unwrapped: continuous, may run past pi), ``q`` (m, 7) the
    joints there (continuous, on ``pattern``, the start's flip pattern (f2, f4, f6) in binary).
    ``narrowest`` (rad): the least width of the corridor interval holding the schedule, at progress
    ``narrowest_u``. Not found: ``closed_at`` the first progress where no reachable swivel is left (or
    None) and ``reason`` which limits or singularities close it. ``max_joint_step`` (rad): the largest
    change of a joint between neighbouring samples.
    """

    found: bool
    u: np.ndarray
    swivel: np.ndarray
    q: np.ndarray
    pattern: int
    narrowest: float
    narrowest_u: float
    closed_at: float | None
    reason: str
    max_joint_step: float

    @cached_property
    def _slopes(self) -> np.ndarray:
        """d swivel / du at the samples for :meth:`swivel_at`: monotone (Fritsch-Carlson) slopes, 0 at
        a sample where the schedule turns back, one-sided at the ends."""
        h = np.maximum(np.diff(self.u), 1e-12)
        d = np.diff(self.swivel) / h
        m = np.empty(len(self.u))
        m[0], m[-1] = d[0], d[-1]
        w1, w2 = 2.0 * h[1:] + h[:-1], h[1:] + 2.0 * h[:-1]
        same = d[:-1] * d[1:] > 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            m[1:-1] = np.where(same, (w1 + w2) / (w1 / d[:-1] + w2 / d[1:]), 0.0)
        return m

    def swivel_at(self, u: float) -> float:
        """The schedule's swivel (rad, unwrapped) at progress ``u`` (clamped): a monotone cubic between
        samples (within its ends' swivels, as the linear one), so its rate has no corners at the samples
        that the joints' acceleration limits could not follow."""
        x = min(max(float(u), 0.0), 1.0)
        us, S = self.u, self.swivel
        if len(us) < 3:
            return float(np.interp(x, us, S))
        k = min(max(int(np.searchsorted(us, x, side="right")) - 1, 0), len(us) - 2)
        h = float(us[k + 1] - us[k])
        if h <= 1e-12:
            return float(S[k + 1])
        t = (x - float(us[k])) / h
        m = self._slopes
        t2, t3 = t * t, t * t * t
        return float((2.0 * t3 - 3.0 * t2 + 1.0) * S[k] + (t3 - 2.0 * t2 + t) * h * m[k]
                     + (-2.0 * t3 + 3.0 * t2) * S[k + 1] + (t3 - t2) * h * m[k + 1])


def route_pose(T_start: np.ndarray, T_goal: np.ndarray, u: float) -> np.ndarray:
    """The pose (4x4) at progress ``u`` of the straight route: position on the line, orientation by slerp."""
    q0 = quat_from_matrix(T_start[:3, :3])
    r = rotvec_between(q0, quat_from_matrix(T_goal[:3, :3]))
    return _route_pose(T_start, T_goal, q0, r, u)


def _route_pose(T0: np.ndarray, T1: np.ndarray, q0: tuple[float, ...], r: tuple[float, ...], u: float
                ) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = T0[:3, 3] + u * (T1[:3, 3] - T0[:3, 3])
    turn = quat_from_rotvec((u * r[0], u * r[1], u * r[2]))
    T[:3, :3] = matrix_from_quat(quat_normalize(quat_mul(turn, q0)))
    return T


@dataclass
class _Sample:
    """One route sample: pose, closed-form functions (None out of reach) and the corridor intervals."""

    u: float
    T: np.ndarray
    fn: SwivelFunctions | None
    intervals: np.ndarray  # (k, 2), unwrapped [start, end]
    grids: dict[Any, Any] = field(default_factory=dict)  # wide joints along a stretch (see _wide_grid)
    runs: dict[Any, Any] = field(default_factory=dict)  # their in-bounds runs per branch


@dataclass
class _Piece:
    """A reachable stretch [a, b] (rad, unwrapped) of the corridor interval ``J`` at one sample, on one
    branch of the wide joints (``shift``: see :meth:`_Corridor.wide_runs`); ``run`` the stretch of J
    where that branch keeps its bounds; ``parents`` the pieces of the previous sample it is reached from."""

    a: float
    b: float
    J: tuple[float, float]
    shift: np.ndarray
    run: tuple[float, float]
    parents: list[int]


#: corridors' samples by route, flip pattern and bounds (see :func:`corridor_screen`'s ``shared_samples``)
SharedSamples = dict[tuple[Any, ...], dict[float, _Sample]]


class _Corridor:
    """The computation behind :func:`swivel_corridor` (state of one call)."""

    def __init__(self, arm: SwivelArm, T0: np.ndarray, T1: np.ndarray, q_start: np.ndarray,
                 margins: dict[str, float],
                 max_rate: float, preferred: PreferredSwivel, max_joint_step: float, min_du: float,
                 end_step: float, shared_samples: SharedSamples | None = None) -> None:
        self.arm = arm
        self.T0, self.T1 = T0, T1
        self.q0r = quat_from_matrix(T0[:3, :3])
        self.rv = rotvec_between(self.q0r, quat_from_matrix(T1[:3, :3]))
        self.q_start = q_start
        self.m = margins
        self.max_rate = max_rate
        self.preferred = preferred
        self.max_joint_step = max_joint_step
        self.min_du = min_du
        self.end_step = end_step
        self.s0 = float(arm.swivel(q_start))
        self.pattern = self._pattern()
        b = self.pattern
        self.sign = np.array([ALT_SIGN[j, ALT_INDEX[b, j]] for j in range(7)])
        self.shift = np.array([ALT_SHIFT[j, ALT_INDEX[b, j]] for j in range(7)])
        self.lo, self.up, self.lo_tol, self.up_tol = self._bounds()
        self.tab = LimitTables.shared(self.lo, self.up, INTERVAL_ROOT_TOL) if np.all(self.lo <= self.up) \
            else None
        self.wide = [j for j in range(7) if self.up[j] - self.lo[j] >= TWO_PI - 2e-10]
        self.wide_pivots = all(j % 2 == 0 for j in self.wide)
        self.wide_rows = [j // 2 for j in self.wide] + [4 + j // 2 for j in self.wide]  # rows X, then Y
        # per-call constants of the wide joints' helpers below (the same arrays they built each call)
        self._wide_sign = self.sign[self.wide][:, None]
        self._wide_shift = self.shift[self.wide][:, None]
        self._wide_degen = [(k, j) for k, j in enumerate(self.wide) if j in (0, 4)]
        self._wide_lo_chk = self.lo[self.wide][:, None] - CHECK_TOL
        self._wide_up_chk = self.up[self.wide][:, None] + CHECK_TOL
        bounds = np.concatenate([self.lo[self.wide], self.up[self.wide]])  # (_wide_roots: lower, then upper)
        self._root_p = np.array([j // 2 for j in self.wide] * 2, dtype=int)
        self._root_sin = -np.sin(bounds)[:, None]
        self._root_cos = np.cos(bounds)[:, None]
        # grid step (rad) along a piece for the wide joints' continuous value: a pivot turns at most about
        # 1 / m rad per rad of swivel at a hinge margin m, so consecutive grid values differ by ~1.5 < pi
        self.h = min(0.05, 1.5 * min(self.m["shoulder"], self.m["wrist"]))
        # the samples by progress: a sample is a function of the route, the flip pattern and the bounds
        # alone (not of the start swivel), so corridors that share all of them may share the samples
        self.cache: dict[float, _Sample] = {} if shared_samples is None else shared_samples.setdefault(
            (T0.tobytes(), T1.tobytes(), self.pattern, self.lo.tobytes(), self.up.tobytes(), self.h), {})
        self.frontier = 0.0  # progress from which the initial steps are not refined yet (topology_grid)
        self.rows: dict[tuple[float, float], np.ndarray] = {}  # ik rows on the pattern by (u, swivel)

    # -- set-up ----------------------------------------------------------------------------------
    def _pattern(self) -> int:
        """The flip pattern (f2, f4, f6 in binary) of the start configuration."""
        rows = self.arm.ik(self.T0, self.s0, limits=False)
        if len(rows) != 8:
            raise InvalidInputError("T_start is out of reach", field="T_start")
        d = np.abs(np.remainder(rows - self.q_start + PI, TWO_PI) - PI).max(axis=1)
        b = int(np.argmin(d))
        if d[b] > 1e-6:
            raise InvalidInputError(f"q_start is not a solution of T_start (joints off by {d[b]:.3g} rad)",
                                    field="q_start", value=self.q_start)
        return b

    def _bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per joint the bounds on its value on the start's flip pattern (limits and singularity margins),
        and how far a step's midpoint may pass each (MID_SHARE of the margin that sets it)."""
        arm, m = self.arm, self.m
        lo = np.asarray(arm.lower, float) + m["limit"]
        up = np.asarray(arm.upper, float) - m["limit"]
        lo_tol, up_tol = np.full(7, MID_SHARE * m["limit"]), np.full(7, MID_SHARE * m["limit"])
        f2, f4, f6 = (self.pattern >> 2) & 1, (self.pattern >> 1) & 1, self.pattern & 1
        for j, flip, key in ((1, f2, "shoulder"), (5, f6, "wrist")):
            a = math.asin(min(m[key], 1.0))
            lo_a, up_a = (a, PI - a) if flip == 0 else (a - PI, -a)
            if lo_a > lo[j]:
                lo[j], lo_tol[j] = lo_a, MID_SHARE * a
            if up_a < up[j]:
                up[j], up_tol[j] = up_a, MID_SHARE * a
        if f4 == 0 and m["elbow"] > lo[3]:
            lo[3], lo_tol[3] = m["elbow"], MID_SHARE * m["elbow"]
        elif f4 == 1 and -m["elbow"] < up[3]:
            up[3], up_tol[3] = -m["elbow"], MID_SHARE * m["elbow"]
        return lo, up, np.maximum(lo_tol, CHECK_TOL), np.maximum(up_tol, CHECK_TOL)

    # -- per sample ------------------------------------------------------------------------------
    def sample(self, u: float) -> _Sample:
        smp = self.cache.get(u)
        if smp is not None:
            return smp
        T = _route_pose(self.T0, self.T1, self.q0r, self.rv, u)
        try:
            fn: SwivelFunctions | None = self.arm.swivel_functions(T)
        except UnreachableError:
            fn = None
        if fn is None or self.tab is None:
            ivs = np.empty((0, 2))
        else:
            ivs = pattern_intervals(fn, self.tab, self.pattern)
        smp = _Sample(u, T, fn, ivs)
        self.cache[u] = smp
        return smp

    def angles(self, fn: SwivelFunctions, s: np.ndarray) -> np.ndarray:
        """(7, M) joint values on the start's pattern at swivels s (pivot joints in (-pi, pi] + shift)."""
        return fn.angles(np.asarray(s, float)) * self.sign[:, None] + self.shift[:, None]

    def _wide_angles(self, fn: SwivelFunctions, s: np.ndarray) -> np.ndarray:
        """(len(wide), M) the wide joints' values as :meth:`angles` gives them, computed for those only
        (pivot joints: atan2 of two rows of the closed form)."""
        if not self.wide_pivots:
            return self.angles(fn, s)[self.wide]
        CS = np.empty((3, s.shape[0]))  # (the rows np.stack([ones, cos s, sin s]) made, filled in place)
        CS[0] = 1.0
        np.cos(s, out=CS[1])
        np.sin(s, out=CS[2])
        P = fn.K[self.wide_rows] @ CS
        n = len(self.wide)
        th = np.arctan2(P[n:], P[:n])
        for k, j in self._wide_degen:
            if (j == 0 and fn.deg_shoulder) or (j == 4 and fn.deg_wrist):
                th[k] = 0.0
        return th * self._wide_sign + self._wide_shift

    def _wide_roots(self, fn: SwivelFunctions, lo: float, hi: float) -> np.ndarray:
        """Swivels in [lo, hi] where a wide joint equals one of its bounds (mod pi): closed-form roots."""
        p = self._root_p
        E = self._root_sin * fn.K[p] + self._root_cos * fn.K[p + 4]
        x = np.concatenate(roots(E))
        x = x[x == x]
        base = lo + (x - lo) % TWO_PI
        out = [base[base <= hi]]
        while len(out[-1]):
            nxt = out[-1] + TWO_PI
            out.append(nxt[nxt <= hi])
        return np.concatenate(out)

    def _wide_grid(self, smp: _Sample, J: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """Along the stretch J of sample smp: the swivels (bounds roots, a grid of step h, and the mid
        point between every two) and the wide joints' continuous values there, up to a 2 pi copy each.
        Between two neighbouring swivels of the grid no wide joint crosses a bound (the roots are in it)."""
        key = (round(J[0], 12), round(J[1], 12))
        hit = smp.grids.get(key)
        if hit is not None:
            return hit
        lo, hi = J
        assert smp.fn is not None
        n = max(2, int(math.ceil((hi - lo) / self.h)) + 1)
        pts = sorted_unique(np.concatenate([np.linspace(lo, hi, n), self._wide_roots(smp.fn, lo, hi)]))
        allp = np.empty(2 * len(pts) - 1)
        allp[0::2] = pts
        allp[1::2] = 0.5 * (pts[1:] + pts[:-1])
        A = self._wide_angles(smp.fn, allp)
        V = A.copy()  # unwrapped along the grid: each step taken as the nearest 2 pi copy
        V[:, 1:] -= TWO_PI * (np.diff(A, axis=1) / TWO_PI).round().cumsum(axis=1)  # (methods: no wrapper)
        smp.grids[key] = (allp, V)
        return allp, V

    def _branch(self, smp: _Sample, J: tuple[float, float], s: float, w: np.ndarray) -> np.ndarray:
        """The 2 pi shift (per wide joint) that puts the grid values of J on the branch that has about the
        values ``w`` at swivel s (within pi)."""
        allp, V = self._wide_grid(smp, J)
        i = min(int(allp.searchsorted(s)), len(allp) - 1)
        if i > 0 and abs(allp[i - 1] - s) < abs(allp[i] - s):
            i -= 1
        return TWO_PI * ((w - V[:, i]) / TWO_PI).round()

    def wide_runs(self, smp: _Sample, J: tuple[float, float], shift: np.ndarray
                  ) -> list[tuple[float, float, float, np.ndarray]]:
        """The stretches of J where the wide joints' branch (grid values + ``shift``) keeps its bounds:
        (start, end, anchor swivel, wide values there) each. Exact ends (closed-form roots)."""
        allp, V0 = self._wide_grid(smp, J)
        key = (round(J[0], 12), round(J[1], 12), tuple(np.round(shift / TWO_PI).astype(int).tolist()))
        hit = smp.runs.get(key)
        if hit is not None:
            return hit
        V = V0 + shift[:, None]
        ok = np.logical_and.reduce((V >= self._wide_lo_chk) & (V <= self._wide_up_chk), axis=0)  # all(axis=0)
        ok_mid, ok_pt = ok[1::2], ok[0::2]
        pts = allp[0::2]
        runs: list[tuple[float, float, float, np.ndarray]] = []
        k = 0
        nseg = len(ok_mid)
        while k < nseg:
            if not ok_mid[k]:
                k += 1
                continue
            k1 = k
            while k1 + 1 < nseg and ok_mid[k1 + 1]:
                k1 += 1
            runs.append((float(pts[k]), float(pts[k1 + 1]), float(allp[2 * k + 1]), V[:, 2 * k + 1].copy()))
            k = k1 + 1
        if nseg == 0 or not runs:  # isolated points (a zero-width interval, or touching roots)
            for i in np.nonzero(ok_pt)[0]:
                runs.append((float(pts[i]), float(pts[i]), float(pts[i]), V[:, 2 * i].copy()))
        smp.runs[key] = runs
        return runs

    def wide_at(self, smp: _Sample, J: tuple[float, float], shift: np.ndarray, s: float) -> np.ndarray:
        """The wide joints' exact values at swivel s on the branch of J given by ``shift``."""
        assert smp.fn is not None
        allp, V = self._wide_grid(smp, J)
        i = min(int(allp.searchsorted(s)), len(allp) - 1)
        approx = V[:, i] + shift
        base = self._wide_angles(smp.fn, np.array([s]))[:, 0]
        return base + TWO_PI * ((approx - base) / TWO_PI).round()

    # -- refinement of the samples ---------------------------------------------------------------
    def topology_grid(self, n0: int) -> list[float]:
        """The initial samples: n0 even steps, each halved (up to 12 times, down to min_du) where the
        corridor's intervals change between its ends (:meth:`_changes`). Lazily: a step is refined when
        the forward pass reaches it (:meth:`_refine_step`), so a corridor that closes early leaves the
        rest of the route unsampled; ``frontier`` is the progress from which the steps are not refined."""
        self.frontier = 0.0
        return list(np.linspace(0.0, 1.0, n0 + 1))

    def _refine_step(self, ua: float, ub: float, n_now: int) -> list[float]:
        """The samples strictly inside the initial step [ua, ub] (see :meth:`topology_grid`): rounds of
        halving every part whose ends' intervals change."""
        us = [ua, ub]
        for _ in range(12):
            new: list[float] = []
            for a, b in zip(us[:-1], us[1:], strict=True):
                if b - a <= self.min_du or n_now + len(us) - 2 + len(new) >= MAX_SAMPLES:
                    continue
                if self._changes(self.sample(a).intervals, self.sample(b).intervals):
                    new.append(0.5 * (a + b))
            if not new:
                break
            us = sorted(us + new)
        return us[1:-1]

    def _changes(self, A: np.ndarray, B: np.ndarray) -> bool:
        if len(A) != len(B):
            return True
        if not len(A):
            return False
        d = np.abs(np.remainder(A - B + PI, TWO_PI) - PI)
        return bool(d.max() > self.end_step)

    # -- propagation -----------------------------------------------------------------------------
    def forward(self, us: list[float], prev: tuple[list[float], list[list[_Piece]], list[int]] | None = None
                ) -> tuple[list[list[_Piece]], int | None, list[int]]:
        """Reachable pieces per sample; the index of the first sample with none (None if all have some);
        the steps (index of their end) where an interval was within the rate bound of a piece but did not
        overlap the piece's own interval (to refine if the corridor closes).

        A piece at sample i reaches only swivels of sample i + 1 that lie in its own corridor interval at
        sample i too: the two samples' intervals must overlap, so a gap between two intervals that moves
        along the route is never jumped (the refinement locates where the overlap ends).

        ``prev``: the samples, levels and misses of an earlier pass over samples that ``us`` refines. The
        pass is causal (level i depends on the samples up to i only), so the levels before the first
        sample added are that pass's, unchanged."""
        if prev is not None:
            us_old, levels_old, misses_old = prev
            k = 0
            while k < min(len(us), len(us_old), len(levels_old)) and us[k] == us_old[k] and levels_old[k]:
                k += 1
            if k >= 1:
                return self._propagate(us, levels_old[:k], [i for i in misses_old if i < k])
        smp0 = self.sample(us[0])
        for a, b in smp0.intervals:
            x = a + (self.s0 - a) % TWO_PI
            if x <= b + 1e-9:
                J = (float(self.s0 - (x - a)), float(self.s0 + (b - x)))
                break
        else:
            return [[]], 0, []
        shift = np.zeros(len(self.wide))
        run = J
        if self.wide:
            shift = self._branch(smp0, J, self.s0, self.q_start[self.wide])
            runs = [r for r in self.wide_runs(smp0, J, shift) if r[0] - 1e-9 <= self.s0 <= r[1] + 1e-9]
            if not runs:
                return [[]], 0, []
            run = (runs[0][0], runs[0][1])
        return self._propagate(us, [[_Piece(self.s0, self.s0, J, shift, run, [])]], [])

    def _propagate(self, us: list[float], levels: list[list[_Piece]], misses: list[int]
                   ) -> tuple[list[list[_Piece]], int | None, list[int]]:
        """:meth:`forward` from the last of the given ``levels`` on (they and ``misses`` are extended)."""
        i = len(levels)
        while i < len(us):
            if us[i - 1] >= self.frontier:  # an initial step not refined yet (beyond every added sample)
                self.frontier = us[i]
                us[i:i] = self._refine_step(us[i - 1], us[i], len(us))
            prev = levels[-1]
            smp_p, smp = self.sample(us[i - 1]), self.sample(us[i])
            d = self.max_rate * (us[i] - us[i - 1])
            out: list[_Piece] = []
            if smp.fn is not None:
                for pi_, P in enumerate(prev):
                    e0, e1 = P.a - d, P.b + d
                    c0, c1 = max(e0, P.run[0]), min(e1, P.run[1])
                    for j0, j1 in smp.intervals:
                        for n in range(math.ceil((e0 - j1) / TWO_PI), math.floor((e1 - j0) / TWO_PI) + 1):
                            o0, o1 = max(c0, j0 + n * TWO_PI), min(c1, j1 + n * TWO_PI)
                            if o0 > o1:
                                if max(e0, j0 + n * TWO_PI) <= min(e1, j1 + n * TWO_PI):
                                    misses.append(i)
                                continue
                            J = (float(j0 + n * TWO_PI), float(j1 + n * TWO_PI))
                            self._add(out, smp_p, P, smp, J, o0, o1, pi_)
            levels.append(out)
            if not out:
                return levels, i, misses
            i += 1
        return levels, None, misses

    def _add(self, out: list[_Piece], smp_p: _Sample, P: _Piece, smp: _Sample, J: tuple[float, float],
             o0: float, o1: float, parent: int) -> None:
        """The stretch [o0, o1] of interval J at sample smp, reached from piece P of the sample before."""
        if self.wide:
            c = 0.5 * (max(o0, P.a) + min(o1, P.b)) if max(o0, P.a) <= min(o1, P.b) else min(max(P.a, o0), o1)
            sq = min(max(c, P.a), P.b)
            w_prev = self.wide_at(smp_p, P.J, P.shift, sq)
            shift = self._branch(smp, J, c, w_prev)
            runs = [(r[0], r[1]) for r in self.wide_runs(smp, J, shift)]
        else:
            shift = P.shift
            runs = [J]
        for r0, r1 in runs:
            a, b = max(o0, r0), min(o1, r1)
            if a > b:
                continue
            for Q in out:  # the same stretch of the same branch from another parent: merge
                if Q.J == J and Q.a <= b and a <= Q.b and np.array_equal(Q.shift, shift):
                    Q.a, Q.b = min(Q.a, a), max(Q.b, b)
                    if parent not in Q.parents:
                        Q.parents.append(parent)
                    break
            else:
                out.append(_Piece(a, b, J, shift, (r0, r1), [parent]))

    def backward(self, us: list[float], levels: list[list[_Piece]]) -> tuple[list[float], list[_Piece]]:
        """The schedule: at each sample the reachable swivel nearest the preferred one, within the rate."""
        N = len(us) - 1
        pref = self.preferred(us[N], self.sample(us[N]).T)
        best: tuple[float, float, _Piece] | None = None
        for P in levels[N]:
            x = P.a + (pref - P.a) % TWO_PI
            if x <= P.b:
                cand = (0.0, x, P)
            else:
                cand = min((x - P.b, P.b, P), (P.a + TWO_PI - x, P.a, P), key=lambda t: t[0])
            if best is None or cand[0] < best[0]:
                best = cand
        assert best is not None
        sched, pieces = [best[1]], [best[2]]
        for i in range(N - 1, -1, -1):
            s_next, P_next = sched[-1], pieces[-1]
            d = self.max_rate * (us[i + 1] - us[i])
            pref = self.preferred(us[i], self.sample(us[i]).T)
            x = s_next + math.remainder(pref - s_next, TWO_PI)
            choice: tuple[float, float, _Piece] | None = None
            for k in P_next.parents:
                Q = levels[i][k]
                lo, hi = max(Q.a, s_next - d), min(Q.b, s_next + d)
                if lo > hi + 1e-12:
                    continue
                s = min(max(x, lo), hi)
                if choice is None or abs(s - x) < choice[0]:
                    choice = (abs(s - x), s, Q)
            assert choice is not None, "a reachable piece without a predecessor in reach"
            sched.append(choice[1])
            pieces.append(choice[2])
        sched.reverse()
        pieces.reverse()
        sched[0] = self.s0
        return sched, pieces

    # -- the speed guide --------------------------------------------------------------------------
    def speed_guide(self, rates: np.ndarray, floor: float, n: int = GUIDE_SAMPLES) -> PreferredSwivel | None:
        """The swivel the schedule follows when it keeps the joints' path-speed demand low (see
        :func:`swivel_corridor`): on ``n`` + 1 evenly spaced samples and a swivel grid, the schedule from
        the start whose largest demand max_j |dq_j/du| / rates[j] (s per unit progress; the swivel's
        |ds/du| / rates[7] too) is least, or at most ``floor`` (s per unit progress), is found (a bottleneck
        path); among those within GUIDE_SLACK of that least demand, the one nearest the preferred swivel
        (least integral of the distance). None where a sample is out of reach or no grid path exists."""
        us = np.linspace(0.0, 1.0, n + 1)
        du = 1.0 / n
        h = min(GUIDE_STEP, self.max_rate * du)
        K = int(math.ceil(1.5 * PI / h))
        S = self.s0 + h * np.arange(-K, K + 1)
        band = max(1, int(round(self.max_rate * du / h)))
        A, ok = [], []
        for u in us:
            smp = self.sample(float(u))
            if smp.fn is None:
                return None
            A.append(self.angles(smp.fn, S))
            inside = np.zeros(len(S), bool)
            for a, b in smp.intervals:
                inside |= (b - a >= TWO_PI - 1e-9) | ((S - a) % TWO_PI <= b - a + 1e-9)
            ok.append(inside)
        offsets = range(-band, band + 1)
        # a step's demand in s of route time: per unit progress, times the minimum-jerk profile's
        # du/dx where the step lies (the route's duration is the largest of those; near the ends the
        # profile is slow, so a joint may swing faster there)
        xm = np.array([min_jerk_inverse(0.5 * (us[i] + us[i + 1])) for i in range(n)])
        pace = min_jerk_rate(xm) / du

        def edges(i: int) -> list[np.ndarray]:
            """Per offset o: the demand of the step from grid k at sample i to k + o at i + 1 (inf: none)."""
            out = []
            for o in offsets:
                src = np.arange(max(0, -o), min(len(S), len(S) - o))
                # (every joint modulo 2 pi: the closed form's copy may be 2 pi off the in-limit one)
                d = np.abs(np.remainder(A[i + 1][:, src + o] - A[i][:, src] + PI, TWO_PI) - PI)
                c = np.full(len(S), math.inf)
                c[src] = np.maximum(np.max(d / rates[:7, None], axis=0), abs(o) * h / rates[7]) * pace[i]
                c[~ok[i]] = math.inf
                c[src[~ok[i + 1][src + o]]] = math.inf
                out.append(c)
            return out

        def shifted(x: np.ndarray, o: int) -> np.ndarray:
            """x moved by o grid steps (x[k] at k + o), inf where nothing lands."""
            y = np.full_like(x, math.inf)
            if o >= 0:
                y[o:] = x[:len(x) - o]
            else:
                y[:o] = x[-o:]
            return y

        E = [edges(i) for i in range(n)]
        V = np.full(len(S), math.inf)
        V[K] = 0.0
        for i in range(n):  # the bottleneck: least largest step demand up to each grid swivel
            V = np.min([shifted(np.maximum(V, E[i][k]), o) for k, o in enumerate(offsets)], axis=0)
        best = float(V.min())
        if not math.isfinite(best):
            return None
        bound = max(GUIDE_SLACK * best, floor)

        def dev(i: int) -> np.ndarray:
            return np.abs(np.remainder(S - self.preferred(float(us[i]), self.sample(float(us[i])).T) + PI,
                                       TWO_PI) - PI) * du
        W = np.full(len(S), math.inf)
        W[K] = 0.0
        back = np.zeros((n, len(S)), int)
        for i in range(n):  # the nearest the preferred swivel with every step within the bound
            cand = np.array([shifted(np.where(E[i][k] <= bound, W, math.inf), o)
                             for k, o in enumerate(offsets)])
            j = np.argmin(cand, axis=0)
            back[i] = np.asarray(list(offsets))[j]
            W = cand[j, np.arange(len(S))] + dev(i + 1)
        k = int(np.argmin(W))
        path = np.empty(n + 1)
        for i in range(n, 0, -1):
            path[i] = S[k]
            k -= back[i - 1, k]
        path[0] = S[k]

        def guide(u: float, _T: np.ndarray) -> float:
            return float(np.interp(u, us, path))
        return guide

    # -- checks ----------------------------------------------------------------------------------
    def solve(self, u: float, s: float, q_prev: np.ndarray) -> np.ndarray:
        """The joints on the start's pattern at progress u and swivel s, the 2 pi copy nearest q_prev."""
        key = (u, s)  # (a refinement pass solves the same samples again where the schedule kept them)
        row = self.rows.get(key)
        if row is None:
            smp = self.cache.get(u)
            T = smp.T if smp is not None else _route_pose(self.T0, self.T1, self.q0r, self.rv, u)
            row = self.arm.ik(T, s, limits=False)[self.pattern]
            self.rows[key] = row
        return row + TWO_PI * np.round((q_prev - row) / TWO_PI)

    def violations(self, q: np.ndarray) -> list[str]:
        """The constraints q breaks (beyond CHECK_TOL), by name."""
        out = []
        names = {1: "the shoulder singularity margin (|sin q2|)", 3: "the elbow singularity margin (|q4|)",
                 5: "the wrist singularity margin (|sin q6|)"}
        lower, upper = np.asarray(self.arm.lower, float), np.asarray(self.arm.upper, float)
        for j in range(7):
            if q[j] < self.lo[j] - CHECK_TOL or q[j] > self.up[j] + CHECK_TOL:
                lim = self.m["limit"] - CHECK_TOL
                in_lim = lower[j] + lim <= q[j] <= upper[j] - lim
                if in_lim and j in names:
                    out.append(names[j])
                else:
                    out.append(f"the joint {j + 1} limit")
        return out

    def schedule_joints(self, us: list[float], sched: list[float]) -> tuple[np.ndarray, list[float]]:
        """Joints along the schedule, and the progress values to add (where a step's joints change by
        more than max_joint_step: as many as bring it under, about; where its midpoint breaks a bound: it)."""
        Q = np.empty((len(us), 7))
        Q[0] = self.q_start
        bad: list[float] = []
        for i in range(1, len(us)):
            Q[i] = self.solve(us[i], sched[i], Q[i - 1])
            step = float(np.max(np.abs(Q[i] - Q[i - 1])))
            mid_bad = False
            if step > 1e-12:
                um = 0.5 * (us[i - 1] + us[i])
                qm = self.solve(um, 0.5 * (sched[i - 1] + sched[i]), Q[i - 1])
                jump = float(np.max(np.abs(qm - Q[i - 1])))
                mid_bad = jump > self.max_joint_step or bool(np.any(qm < self.lo - self.lo_tol)) \
                    or bool(np.any(qm > self.up + self.up_tol))
            du = us[i] - us[i - 1]
            # (near a singularity margin the pivot joints turn up to 1 / margin times faster than the
            # swivel: these steps may go below min_du)
            if (step > self.max_joint_step or mid_bad) and du > self.min_du / 16:
                parts = min(max(2, math.ceil(1.2 * step / self.max_joint_step)),
                            math.ceil(16 * du / self.min_du))
                bad.extend(us[i - 1] + du * k / parts for k in range(1, parts))
        return Q, bad

    def why_closed(self, us: list[float], levels: list[list[_Piece]], k: int) -> str:
        """Which constraints leave no swivel at sample k within reach of the pieces of sample k - 1."""
        smp = self.sample(us[k])
        if smp.fn is None:
            return "the route leaves the workspace (the wrist point is out of reach)"
        if k == 0:
            q = self.q_start
            v = self.violations(q)
            return "the start configuration breaks " + (", ".join(v) if v else "a bound")
        d = self.max_rate * (us[k] - us[k - 1])
        counts: dict[str, int] = {}
        total = 0
        for P in levels[k - 1]:
            ss = np.linspace(P.a - d, P.b + d, 64)
            A = self.angles(smp.fn, ss)
            for c in range(A.shape[1]):
                q = A[:, c].copy()
                for j in self.wide:  # any copy of a wide joint (the branch is judged separately)
                    q[j] = self.lo[j] + (q[j] - self.lo[j]) % TWO_PI
                total += 1
                for name in set(self.violations(q)):
                    counts[name] = counts.get(name, 0) + 1
        if not counts:
            return "the wide joints' continuous branch leaves its limits"
        everywhere = [n for n, c in counts.items() if c == total]
        if everywhere:
            return "blocked at every swivel within reach by " + ", ".join(sorted(everywhere))
        ranked = sorted(counts, key=lambda n: -counts[n])
        return "no swivel within reach keeps " + " and ".join(ranked)


def swivel_corridor(
    arm: SwivelArm,
    T_start: Any,
    T_goal: Any,
    q_start: Any,
    *,
    limit_margin: float = 0.0,
    shoulder_margin: float = 0.05,
    wrist_margin: float = 0.05,
    elbow_margin: float = 0.05,
    max_rate: float = PI,
    preferred: float | PreferredSwivel | None = None,
    samples: int = 24,
    max_joint_step: float = 0.1,
    min_du: float = 1e-3,
    end_step: float = 0.05,
    speed_rates: Any = None,
    speed_floor: float = 0.0,
) -> SwivelCorridor:
    """The swivel corridor of the straight route from ``T_start`` (the pose of ``q_start``) to ``T_goal``,
    and a continuous swivel schedule through it (see the module docstring).

    Margins: ``limit_margin`` (rad) from every joint limit; ``shoulder_margin`` and ``wrist_margin``
    (> 0) the least |sin q2| and |sin q6|; ``elbow_margin`` (rad, >= 0) the least |q4|. ``max_rate``
    (rad per unit progress, > 0) bounds |ds/du|. ``preferred``: the swivel the schedule keeps nearest
    (rad), a constant or a function ``(u, T) -> swivel``; None: the start's swivel. ``samples``: the
    initial number of route steps; ``max_joint_step`` (rad), ``min_du`` and ``end_step`` (rad) steer the
    refinement. ``speed_rates`` (8 values > 0: the joints' speeds, rad/s, then the swivel's): the
    schedule then follows the speed guide instead of the preferred swivel: the grid schedule whose
    joints need the least time per unit progress (each |dq/du| over its speed), up to ``speed_floor``
    (s per unit progress, what the route takes anyway), and among those nearest the preferred swivel.

    Raises:
        InvalidInputError: malformed poses or joints, ``q_start`` not a solution of ``T_start`` (1e-6
            rad) or outside the joint limits, T_start out of reach, bad margins or parameters.
    """
    Ta = np.asarray(arm.check_pose(T_start), float)
    Tb = np.asarray(arm.check_pose(T_goal), float)
    q0 = arm.check_q(q_start, "q_start")
    if not arm.within_limits(q0, 1e-9):
        raise InvalidInputError("q_start is outside the joint limits", field="q_start", value=q_start)
    margins = {"limit": limit_margin, "shoulder": shoulder_margin, "wrist": wrist_margin,
               "elbow": elbow_margin}
    for name, v in margins.items():
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0.0):
            raise InvalidInputError(f"{name}_margin must be a finite number >= 0, got {v!r}",
                                    field=f"{name}_margin", value=v)
        margins[name] = float(v)
    for name in ("shoulder", "wrist"):
        if not 0.0 < margins[name] < 1.0:
            raise InvalidInputError(f"{name}_margin must be in (0, 1) (|sin| of the hinge joint), got "
                                    f"{margins[name]}", field=f"{name}_margin", value=margins[name])
    for name, v in (("max_rate", max_rate), ("max_joint_step", max_joint_step), ("min_du", min_du),
                    ("end_step", end_step)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
            raise InvalidInputError(f"{name} must be a finite number > 0, got {v!r}", field=name, value=v)
    if not isinstance(samples, int) or not 1 <= samples <= MAX_SAMPLES:
        raise InvalidInputError(f"samples must be an int in [1, {MAX_SAMPLES}], got {samples!r}",
                                field="samples", value=samples)
    pos_err = float(np.linalg.norm(np.asarray(arm.fk(q0))[:3, 3] - Ta[:3, 3]))
    if pos_err > 1e-6:
        raise InvalidInputError(f"T_start is not the pose of q_start ({pos_err:.3g} m apart)",
                                field="T_start")
    s_start = float(arm.swivel(q0))
    if preferred is None:
        def pref(_u: float, _T: np.ndarray) -> float:
            return s_start
    elif callable(preferred):
        pref = preferred
    else:
        value = float(preferred)
        if not math.isfinite(value):
            raise InvalidInputError("preferred must be finite", field="preferred", value=preferred)

        def pref(_u: float, _T: np.ndarray) -> float:
            return value

    cor = _Corridor(arm, Ta, Tb, q0, margins, float(max_rate), pref, float(max_joint_step), float(min_du),
                    float(end_step))
    if speed_rates is not None:
        rates = np.asarray(speed_rates, float)
        if rates.shape != (8,) or not np.all(np.isfinite(rates)) or np.any(rates <= 0.0):
            raise InvalidInputError("speed_rates must be 8 finite numbers > 0", field="speed_rates",
                                    value=speed_rates)
        if not (isinstance(speed_floor, (int, float)) and math.isfinite(speed_floor) and speed_floor >= 0.0):
            raise InvalidInputError(f"speed_floor must be a finite number >= 0, got {speed_floor!r}",
                                    field="speed_floor", value=speed_floor)
        guide = cor.speed_guide(rates, float(speed_floor))
        if guide is not None:
            cor.preferred = guide
    us = cor.topology_grid(samples)
    prev = None
    for _ in range(24):
        levels, closed, misses = cor.forward(us, prev)
        prev = (us, levels, misses)
        if closed is not None:
            # locate the closing to min_du, and resolve where an interval was lost for want of overlap
            add = {0.5 * (us[i - 1] + us[i]) for i in [*misses, closed] if 0 < i <= closed
                   and us[i] - us[i - 1] > min_du}
            if add and len(us) + len(add) <= MAX_SAMPLES:
                us = sorted(us + list(add))
                continue
            return _not_found(cor, us, levels, closed)
        sched, pieces = cor.backward(us, levels)
        Q, bad = cor.schedule_joints(us, sched)
        if bad and len(us) + len(bad) <= MAX_SAMPLES:
            us = sorted(us + bad)
            continue
        widths = np.array([P.run[1] - P.run[0] for P in pieces])
        k = int(np.argmin(widths))
        steps = np.max(np.abs(np.diff(Q, axis=0)), axis=1) if len(Q) > 1 else np.zeros(1)
        v = [cor.violations(q) for q in Q]
        if any(v) or float(steps.max()) > max_joint_step + 1e-12:
            i = next((i for i, x in enumerate(v) if x), int(np.argmax(steps)) + 1)
            return SwivelCorridor(False, np.array(us[:i]), np.array(sched[:i]), Q[:i], cor.pattern,
                                  float(widths[:max(i, 1)].min()), float(us[k]), float(us[i]),
                                  "the schedule is not continuous at the finest refinement"
                                  + (f" ({', '.join(v[i])})" if v[i] else ""),
                                  float(steps[: max(i - 1, 1)].max()))
        return SwivelCorridor(True, np.array(us), np.array(sched), Q, cor.pattern, float(widths[k]),
                              float(us[k]), None, "", float(steps.max()))
    levels, closed, _ = cor.forward(us)
    return _not_found(cor, us, levels, closed if closed is not None else len(us) - 1)


def _not_found(cor: _Corridor, us: list[float], levels: list[list[_Piece]], k: int) -> SwivelCorridor:
    """The result when no reachable swivel is left at sample k."""
    reason = cor.why_closed(us, levels, k)
    u_ok = us[:k]
    if k > 0:
        sched, pieces = cor.backward(us[:k], levels[:k])
        Q, _ = cor.schedule_joints(u_ok, sched)
        widths = [P.run[1] - P.run[0] for P in pieces]
        j = int(np.argmin(widths))
        steps = np.max(np.abs(np.diff(Q, axis=0)), axis=1) if len(Q) > 1 else np.zeros(1)
        return SwivelCorridor(False, np.array(u_ok), np.array(sched), Q, cor.pattern, float(widths[j]),
                              float(us[j]), float(us[k]), f"the corridor closes at u = {us[k]:.3f}: {reason}",
                              float(steps.max()))
    return SwivelCorridor(False, np.empty(0), np.empty(0), np.empty((0, 7)), cor.pattern, 0.0, 0.0, 0.0,
                          f"no corridor at the start: {reason}", 0.0)


def corridor_screen(
    arm: SwivelArm,
    T_start: np.ndarray,
    T_goal: np.ndarray,
    q_start: np.ndarray,
    *,
    limit_margin: float,
    shoulder_margin: float,
    wrist_margin: float,
    elbow_margin: float,
    max_rate: float,
    samples: int = 16,
    shared_samples: SharedSamples | None = None,
) -> float | None:
    """A quick screen before :func:`swivel_corridor` (same arguments, checked by the caller): the
    forward pass alone at ``samples`` + 1 evenly spaced progress values, without refinement. Returns
    the first of them with no reachable swivel, or None. Coarse: a corridor that closes between two
    samples passes the screen (the full call finds it); one that a refinement would reconnect may fail it.
    ``shared_samples``: a dict the caller keeps across screens of the same route from other start
    swivels (the route's samples are computed once; the result is the same)."""
    margins = {"limit": limit_margin, "shoulder": shoulder_margin, "wrist": wrist_margin,
               "elbow": elbow_margin}
    s0 = float(arm.swivel(q_start))
    cor = _Corridor(arm, np.asarray(T_start, float), np.asarray(T_goal, float), np.asarray(q_start, float),
                    margins, float(max_rate), lambda _u, _T: s0, 0.1, 1e-3, 0.05, shared_samples)
    us = [float(u) for u in np.linspace(0.0, 1.0, samples + 1)]
    _levels, closed, _misses = cor.forward(us)
    return None if closed is None else us[closed]
