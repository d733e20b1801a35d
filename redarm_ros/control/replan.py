"""Re-planning: when the Cartesian route to a point goal is a dead end, move in joint space instead.

The attractor dynamics steers the hand along a (nearly) straight Cartesian path and keeps the joints
continuous through the closed-form IK. For some goals that route has no continuous in-limit solution
(a wide joint wound onto its limit, the wrist or elbow folding through a limit, the stretched arm
after homing); a reactive method then stops for good. This module supplies the way out:

* :func:`route_dead_end` marches the straight route (position line, orientation slerp, swivel towards
  the preferred one) through the IK step's continuity rule and says where it breaks ('' if it
  does not): such a goal goes to the planner at once instead of running into the dead end.
* :func:`goal_candidates` picks goal configurations among all in-limit IK solutions (every swivel
  sample, every branch, every 2 pi copy of the wide joints): cost = time of a synchronised
  joint-space move at the velocity/acceleration limits + a penalty for limit margins below
  ``limit_margin`` + a little for a swivel far from the preferred one + a little for a clearance below
  ``clearance``; colliding ones are dropped. In free space also the time the elbow takes to settle
  on its preferred swivel after the move (at ``SETTLE_RATE``) and ``GOAL_BEND_COST``
  per unit of the hand path's excess length on the straight joint segment (the straightest reach
  among the branches and swivels).
* :class:`JointPlanner` searches a collision-free joint path to one of them, cheapest first: the
  straight joint segment, then through the "fold" posture (shoulder up, elbow bent, as after an
  unfold) above the start and above the goal, then through random via configurations (seeded).
  Every segment is checked by sphere tracing (:meth:`CollisionGuard.segment_clearance`) with a
  clearance of ``clearance`` m. The work is done in slices of ``work_per_step`` clearance
  evaluations, one slice per control step, so the control loop stays periodic while the arm holds.
* :class:`JointPath` times the path: each segment a synchronised minimum-jerk move (rest to rest) within
  the joint velocity and acceleration limits, so the command follows it exactly; the attractor dynamics
  takes over at the goal configuration (the elbow then settles on its swivel, the hand stays).

Units: m, rad, s.
"""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from redarm_ros.control.elbow import ElbowCircle, elbow_circle
from redarm_ros.control.guard import CollisionGuard
from redarm_ros.control.ik_step import IKStepper, blend, pose_matrix
from redarm_ros.control.params import ReplanParams
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.errors import UnreachableError
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics.quaternion import quat_angle, quat_from_matrix
from redarm_ros.motion.min_jerk import PEAK_ACC, PEAK_RATE, min_jerk, min_jerk_accel, min_jerk_rate

TWO_PI = 2.0 * math.pi


class PathSearch(Protocol):
    """What the re-plan law drives (:class:`JointPlanner`, the 6-DOF arm's ``Planner6``): :meth:`work`
    once per control step until it returns True; then ``path`` holds the waypoints (rad, start first) or
    is None with ``reason`` saying why."""

    path: list[np.ndarray] | None
    reason: str

    def work(self) -> bool: ...


# ----------------------------------------------------------------------------------------------
# Route check
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Route:
    """Outcome of :func:`check_route`: ``dead_end`` ('' if the straight route is continuous) and the
    least time (s) the route needs at the hand, orientation and joint velocity limits (inf at a
    dead end); ``q_end`` the configuration it ends in; ``singular``: which singularity the route
    passes through ('' if none: the shoulder when the elbow crosses the base axis, sin q2 changes
    sign; the wrist when sin q6 does), where the attractor crawls."""

    dead_end: str
    time: float
    q_end: np.ndarray | None
    singular: str = ""


def check_route(stepper: IKStepper, T0: np.ndarray, s0: float, q0: np.ndarray, T_goal: np.ndarray,
                s_des: Any, steps: int, v_max: float, w_max: float, s_rate: float) -> Route:
    """March the straight Cartesian route from (``T0``, swivel ``s0``, joints ``q0``) to ``T_goal``
    through the IK step's continuity rule. ``s_des(circle)`` is the preferred swivel at a pose; the
    swivel turns towards it at ``s_rate`` rad/s while the hand moves at ``v_max`` m/s and turns at
    ``w_max`` rad/s."""
    p0 = (float(T0[0, 3]), float(T0[1, 3]), float(T0[2, 3]))
    pg = (float(T_goal[0, 3]), float(T_goal[1, 3]), float(T_goal[2, 3]))
    r0, rg = quat_from_matrix(T0[:3, :3]), quat_from_matrix(T_goal[:3, :3])
    duration = max(math.dist(p0, pg) / v_max, quat_angle(r0, rg) / w_max, 0.05)
    dt = duration / steps
    inv_vel = stepper.inv_vel
    q, s = q0, s0
    total = 0.0
    singular = ""
    for k in range(1, steps + 1):
        pos, rot = blend(p0, r0, pg, rg, k / steps)
        T = pose_matrix(pos, rot)
        try:
            circle = elbow_circle(stepper.geom, T)
        except UnreachableError:
            return Route(f"the straight route leaves the workspace at {100 * k // steps} %", math.inf, None)
        target = s_des(circle)
        ds = wrap_angle(target - s)
        s = wrap_angle(s + max(-s_rate * dt, min(s_rate * dt, ds)))
        pick = stepper.solve(T, s, q, dt)
        if pick is None or pick[1] > stepper.flip_ratio:
            pick, s = stepper._search_swivel(T, s, q, dt)
        if pick is None:
            worst = int(np.argmin(np.minimum(q - stepper.lower, stepper.upper - q)))
            return Route(f"the straight route has no continuous in-limit solution at {100 * k // steps} % "
                         f"(joint {worst + 1} at {q[worst]:+.2f} rad, limits "
                         f"{stepper.lower[worst]:+.2f}/{stepper.upper[worst]:+.2f})", math.inf, None)
        total += max(dt, float(np.max(np.abs(pick[0] - q) * inv_vel)))
        for j, name in ((1, "shoulder"), (5, "wrist")):
            if not singular and math.sin(pick[0][j]) * math.sin(q[j]) < 0.0:
                singular = f"the straight route passes the {name} singularity at {100 * k // steps} %"
        q = pick[0]
    return Route("", total, q, singular)


# ----------------------------------------------------------------------------------------------
# Goal configurations
# ----------------------------------------------------------------------------------------------
def move_time(dq: np.ndarray, max_vel: np.ndarray, max_acc: np.ndarray) -> float:
    """Duration (s) of a synchronised rest-to-rest joint move by ``dq`` (rad) at the limits."""
    d = np.abs(dq)
    t_tri = 2.0 * np.sqrt(d / max_acc)
    t_trap = d / max_vel + max_vel / max_acc
    return float(np.max(np.where(d < max_vel * max_vel / max_acc, t_tri, t_trap)))


def _copies(q: np.ndarray, lower: np.ndarray, upper: np.ndarray, wide: list[int]) -> list[np.ndarray]:
    """Every in-limit 2 pi copy of the wide joints of ``q``."""
    out = [q]
    for j in wide:
        nxt = []
        for c in out:
            k0 = math.ceil((lower[j] - c[j]) / TWO_PI)
            k1 = math.floor((upper[j] - c[j]) / TWO_PI)
            for k in range(k0, k1 + 1):
                v = c.copy()
                v[j] = c[j] + k * TWO_PI
                nxt.append(v)
        out = nxt
    return out


#: s of goal-candidate cost per unit of the hand path's excess length (path ratio - 1) on the straight
#: joint segment to it: a hand path 10 % longer weighs as much as a move GOAL_BEND_COST / 10 s slower
#: (more, and the goal configurations far from the elbow's preferred swivel win: it settles for long)
GOAL_BEND_COST = 8.0
#: the same for the bend of the move (:func:`bend_search`, :func:`worth_bending`): a bent move may take
#: BEND_COST / 10 s longer per 10 % of the hand's path it saves
BEND_COST = 24.0
#: rad/s at which the elbow settles on its preferred swivel after a joint-space move, about: a free-space
#: goal candidate's swivel off the preferred one costs the time that takes
SETTLE_RATE = 0.3
#: samples of the straight joint segment at which its hand path is measured
BEND_SAMPLES = 12


def _hand_paths(arm: Any, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tool positions (k, m, 3) of joint paths ``C`` (k paths of m samples, n joints) and the
    lengths (k, m - 1) of each path's steps between its samples."""
    k, m, n = C.shape
    P = np.asarray(arm.fk_batch(C.reshape(-1, n)), float)[:, :3, 3].reshape(k, m, 3)
    return P, np.linalg.norm(np.diff(P, axis=1), axis=2)


def hand_path_ratio(arm: Any, q_from: np.ndarray, Q: np.ndarray, samples: int = BEND_SAMPLES) -> np.ndarray:
    """The hand's path length over its straight distance (>= 1) on the straight joint segment from
    ``q_from`` to each row of ``Q`` (all ending at the same tool pose), at ``samples`` segment samples;
    1 where the hand hardly moves (under 1 mm)."""
    Q = np.atleast_2d(np.asarray(Q, float))
    x = np.linspace(0.0, 1.0, samples + 1)
    P, steps = _hand_paths(arm, q_from[None, None, :] + x[None, :, None] * (Q - q_from)[:, None, :])
    straight = np.linalg.norm(P[:, -1] - P[:, 0], axis=1)
    return np.where(straight > 1e-3, np.sum(steps, axis=1) / np.maximum(straight, 1e-3), 1.0)


#: the bend of a free-space joint move (see :func:`bend_search`): first step and least step (rad) of the
#: coordinate search, samples of the curve, and the least gain in path ratio worth a bend
BEND_STEP, BEND_MIN_STEP = 0.3, 0.01
BEND_CURVE_SAMPLES = 16
BEND_GAIN = 0.02
#: half-waves of the bend: joint j moves off the straight segment by sum_h bump[h, j] sin((h + 1) pi s);
#: the second lets the joints' detour lean towards either end (one half-wave is symmetric)
BEND_HARMONICS = 2


def _bend_basis(s: np.ndarray, harmonics: int, order: int = 0) -> np.ndarray:
    """The half-waves sin((h + 1) pi s) (``order`` 0) or their first or second derivative in s, at path
    parameters ``s`` (k,): (k, harmonics)."""
    w = math.pi * np.arange(1, harmonics + 1)
    ws = np.outer(s, w)
    if order == 0:
        return np.sin(ws)
    if order == 1:
        return w * np.cos(ws)
    return -w * w * np.sin(ws)


def bent_points(qa: np.ndarray, qb: np.ndarray, bend: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Joints (len(s), n) of the bent segment qa -> qb at path parameters ``s`` in [0, 1]: the straight
    segment plus the half-waves of ``bend`` ((h, n) rad, or (n,) for one: row h times sin((h + 1) pi s)),
    which are 0 at both ends."""
    bump = np.atleast_2d(bend)
    return qa + s[:, None] * (qb - qa) + _bend_basis(s, len(bump)) @ bump


def _pace_time(C: np.ndarray, lengths: np.ndarray, inv_vel: np.ndarray) -> np.ndarray:
    """About the least duration (s) of each joint curve (k, m, n samples) paced so that the hand's path
    length follows the minimum-jerk profile, at the joints' velocity limits (``inv_vel`` their
    inverse): at each of its steps (hand step ``lengths`` (k, m - 1)) the joint time the step takes
    over its share of the hand's path, times the profile's rate there."""
    joint = np.max(np.abs(np.diff(C, axis=1)) * inv_vel, axis=2)  # (k, m - 1) s at full speed
    total = np.sum(lengths, axis=1, keepdims=True)
    cum = np.cumsum(lengths, axis=1) - 0.5 * lengths
    x = np.interp(cum / np.maximum(total, 1e-12), _MJ_PROGRESS, _MJ_TIME)
    share = lengths / np.maximum(total, 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(share > 1e-9, min_jerk_rate(x) * joint / share, np.where(joint > 1e-9, np.inf, 0.0))
    return np.max(t, axis=1)


_MJ_TIME = np.linspace(0.0, 1.0, 1001)
_MJ_PROGRESS = min_jerk(_MJ_TIME)


def _bent_costs(arm: Any, qa: np.ndarray, qb: np.ndarray, bends: np.ndarray, lower: np.ndarray,
                upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hand's path ratio on each bent segment (``bends`` (k, h, n)) and its cost: about the least
    duration of its paced move plus BEND_COST per unit of excess ratio; inf where one leaves the
    limits."""
    s = np.linspace(0.0, 1.0, BEND_CURVE_SAMPLES + 1)
    base = qa + s[:, None] * (qb - qa)
    C = base[None] + np.einsum("mh,khn->kmn", _bend_basis(s, bends.shape[1]), bends)
    P, steps = _hand_paths(arm, C)
    inside = np.all((C >= lower) & (C <= upper), axis=(1, 2))
    straight = max(float(np.linalg.norm(P[0, -1] - P[0, 0])), 1e-3)
    ratio = np.where(inside, np.sum(steps, axis=1) / straight, np.inf)
    t = _pace_time(C, steps, 1.0 / np.asarray(arm.max_vel, float))
    return ratio, np.where(inside, t + BEND_COST * (ratio - 1.0), np.inf)


def bend_search(arm: Any, qa: np.ndarray, qb: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                harmonics: int = BEND_HARMONICS) -> Generator[None, None, tuple[np.ndarray, float, float]]:
    """The bend ((harmonics, n) rad, see :func:`bent_points`) of the joint segment qa -> qb that is
    cheapest (about its paced duration plus BEND_COST per unit of the hand's excess path ratio), within
    the limits: a coordinate search (each half-wave of each joint up and down by a step, the step halved
    when none is cheaper, down to BEND_MIN_STEP). A generator, one iteration per step tried; returns
    (bend, the straight segment's path ratio, the bent one's)."""
    n = len(qa)
    bend = np.zeros((harmonics, n))
    ratio0, cost0 = _bent_costs(arm, qa, qb, bend[None], lower, upper)
    straight, best = float(ratio0[0]), float(cost0[0])
    step = BEND_STEP
    moves = np.concatenate((np.eye(harmonics * n), -np.eye(harmonics * n))).reshape(-1, harmonics, n)
    while step >= BEND_MIN_STEP:
        yield None
        _, costs = _bent_costs(arm, qa, qb, bend + step * moves, lower, upper)
        k = int(np.argmin(costs))
        if costs[k] < best - 1e-3:
            bend, best = bend + step * moves[k], float(costs[k])
        else:
            step *= 0.5
    # (the samples keep the limits; between them the curve may bulge past one: shrunk until dense
    # samples keep them too)
    dense = np.linspace(0.0, 1.0, 8 * BEND_CURVE_SAMPLES + 1)
    for _ in range(30):
        C = bent_points(qa, qb, bend, dense)
        if np.all(C >= lower) and np.all(C <= upper):
            break
        bend = 0.8 * bend
    else:
        return np.zeros((harmonics, n)), straight, straight
    ratio, _ = _bent_costs(arm, qa, qb, bend[None], lower, upper)
    return bend, straight, float(ratio[0])


#: intervals of the table that paces a bent segment by the hand's path length, the finer samples per
#: interval at which that length is measured, and the least speed of the hand along the curve (share of
#: its mean) that a pace follows (slower, the joints would have to race: no pace)
PACE_SAMPLES, PACE_FINE = 128, 8
PACE_MIN_SPEED = 0.05


@dataclass(frozen=True)
class Bend:
    """A bent joint segment's shape: ``bump`` (rad, see :func:`bent_points`) and ``pace``, the path
    parameter s as a function of the share sigma of the hand's path length (so that a minimum-jerk
    profile in sigma gives the hand the bell of a minimum-jerk reach): a monotone cubic Hermite table,
    rows sigma, s and ds/dsigma at its nodes; ``ratio`` the hand path over the line."""

    bump: np.ndarray
    pace: np.ndarray
    ratio: float


#: the pace of a segment whose path parameter is the time law itself (s = sigma)
NO_PACE = np.array([[0.0, 1.0], [0.0, 1.0], [1.0, 1.0]])


def paced_bend(arm: Any, qa: np.ndarray, qb: np.ndarray, bump: np.ndarray) -> Bend:
    """The :class:`Bend` of the segment qa -> qb bent by ``bump``: its pace tabulated at PACE_SAMPLES + 1
    nodes evenly spaced in s, the hand's path length measured PACE_FINE times finer, the slopes from its
    rate along the curve (limited so that the table is monotone); no pace where the hand moves slower
    than PACE_MIN_SPEED of its mean along the curve."""
    m = PACE_SAMPLES * PACE_FINE
    s = np.linspace(0.0, 1.0, m + 1)
    Ps, steps = _hand_paths(arm, bent_points(qa, qb, bump, s)[None])
    P, cum = Ps[0], np.concatenate(([0.0], np.cumsum(steps[0])))
    total = float(cum[-1])
    ratio = total / max(float(np.linalg.norm(P[-1] - P[0])), 1e-3)
    if total < 1e-3:
        return Bend(bump, NO_PACE, ratio)
    rate = np.gradient(P, s, axis=0, edge_order=2)  # dP/ds
    speed = np.linalg.norm(rate[::PACE_FINE], axis=1)
    if float(np.min(speed)) < PACE_MIN_SPEED * total:
        return Bend(bump, NO_PACE, ratio)
    sigma, s_n = cum[::PACE_FINE] / total, s[::PACE_FINE]
    slope = total / speed
    secant = np.diff(s_n) / np.diff(sigma)
    slope[:-1] = np.minimum(slope[:-1], 3.0 * secant)  # (Fritsch-Carlson: no overshoot)
    slope[1:] = np.minimum(slope[1:], 3.0 * secant)
    return Bend(bump, np.array([sigma, s_n, slope]), ratio)


#: shares of the searched bend weighed against the straight move (a bend lengthens the joints' travel)
BEND_SCALES = (1.0, 0.75, 0.5, 0.25)


def worth_bending(arm: Any, qa: np.ndarray, qb: np.ndarray, bump: np.ndarray, straight: float) -> Bend | None:
    """The share of BEND_SCALES of ``bump`` (paced, :func:`paced_bend`) whose duration at the arm's
    limits plus BEND_COST per unit of excess path ratio is least, if less than the straight move's
    (hand path ratio ``straight``); None if the straight move is cheaper."""
    vel, acc = np.asarray(arm.max_vel, float), np.asarray(arm.max_acc, float)
    best, cost = None, min_jerk_duration(qb - qa, vel, acc) + BEND_COST * (straight - 1.0)
    for k in BEND_SCALES:
        shape = paced_bend(arm, qa, qb, k * bump)
        c = min_jerk_duration(qb - qa, vel, acc, shape) + BEND_COST * (shape.ratio - 1.0)
        if c < cost:
            best, cost = shape, c
    return best


def _pace(table: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s, ds/dsigma, d2s/dsigma2 of the pace ``table`` (see :class:`Bend`) at ``sigma`` (any shape)."""
    nodes, values, slopes = table
    x = np.clip(np.asarray(sigma, float), 0.0, 1.0)
    k = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, len(nodes) - 2)
    h = nodes[k + 1] - nodes[k]
    t = (x - nodes[k]) / h
    y0, y1, m0, m1 = values[k], values[k + 1], slopes[k] * h, slopes[k + 1] * h
    t2, t3 = t * t, t * t * t
    s = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0 + (3 * t2 - 2 * t3) * y1 + (t3 - t2) * m1
    s1 = ((6 * t2 - 6 * t) * (y0 - y1) + (3 * t2 - 4 * t + 1) * m0 + (3 * t2 - 2 * t) * m1) / h
    s2 = ((12 * t - 6) * (y0 - y1) + (6 * t - 4) * m0 + (6 * t - 2) * m1) / (h * h)
    return s, s1, s2


@dataclass(frozen=True)
class Candidate:
    """A goal configuration ``q`` (rad) at swivel ``s`` with its ``cost`` (s) and ``clearance`` (m)."""

    q: np.ndarray
    s: float
    cost: float
    clearance: float


def goal_candidates(stepper: IKStepper, guard: CollisionGuard, T: np.ndarray, q_from: np.ndarray,
                    scene: Scene, params: ReplanParams, s_pref: float | None, count: int = 6,
                    scan: int = 72) -> list[Candidate]:
    """Up to ``count`` distinct collision-free goal configurations of pose ``T``, cheapest first
    (see the module docstring); ``s_pref``: the preferred swivel (rad) or None."""
    search = goal_candidates_iter(stepper, guard, T, q_from, scene, params, s_pref, count, scan)
    while True:
        try:
            next(search)
        except StopIteration as stop:
            return stop.value


def goal_candidates_iter(stepper: IKStepper, guard: CollisionGuard, T: np.ndarray, q_from: np.ndarray,
                         scene: Scene, params: ReplanParams, s_pref: float | None, count: int = 6,
                         scan: int = 72, checks: int = 400) -> Generator[None, None, list[Candidate]]:
    """:func:`goal_candidates` as a generator: one iteration per swivel sample and per clearance
    evaluation (at most ``checks`` of them)."""
    arm = stepper.arm
    max_vel = np.asarray(arm.max_vel, float)
    max_acc = np.asarray(arm.max_acc, float)
    qs: list[np.ndarray] = []
    ss: list[float] = []
    for k in range(scan):
        s = -math.pi + TWO_PI * k / scan
        for sol in arm.ik(T, s):
            for q in _copies(np.asarray(sol, float), stepper.lower, stepper.upper, stepper.wide):
                qs.append(q)
                ss.append(s)
        yield None
    if not qs:
        return []
    Q = np.array(qs)
    S = np.array(ss)
    # Synchronised rest-to-rest move time (vectorised move_time) + margin and swivel penalties.
    d = np.abs(Q - q_from)
    t_tri = 2.0 * np.sqrt(d / max_acc)
    t_trap = d / max_vel + max_vel / max_acc
    cost = np.max(np.where(d < max_vel * max_vel / max_acc, t_tri, t_trap), axis=1)
    m = np.minimum(Q - stepper.lower, stepper.upper - Q)
    cost += 0.5 * np.sum(np.maximum(params.limit_margin - m, 0.0), axis=1) / max(params.limit_margin, 1e-9)
    free = scene.free_space
    if s_pref is not None:
        ds = np.abs(np.remainder(S - s_pref + math.pi, TWO_PI) - math.pi)
        cost += 0.2 * ds
        if free:  # (the elbow settles on its preferred swivel after the move, slowly: far costs seconds)
            cost += ds / SETTLE_RATE
    if free:  # (near obstacles the clearance comes first)
        for i in range(0, len(Q), 128):
            cost[i:i + 128] += GOAL_BEND_COST * (hand_path_ratio(arm, q_from, Q[i:i + 128]) - 1.0)
            yield None
    out: list[Candidate] = []
    for n, i in enumerate(np.argsort(cost, kind="stable")):
        if n >= checks:
            break
        q = Q[i]
        if any(float(np.max(np.abs(q - c.q))) < 0.15 for c in out):
            continue
        c = guard.clearance(q, scene).distance
        yield None
        if c <= 0.0:
            continue
        # A goal close to an obstacle is fine (the path's last segment is checked from the goal
        # backwards, first getting clear); clearer ones are preferred.
        pen = 0.5 * max(params.clearance + guard.step - c, 0.0) / (params.clearance + guard.step)
        out.append(Candidate(q, float(S[i]), float(cost[i]) + pen, c))
        if len(out) >= 2 * count:
            break
    out.sort(key=lambda cand: cand.cost)
    return out[:count]


# ----------------------------------------------------------------------------------------------
# Joint path search
# ----------------------------------------------------------------------------------------------
def fold_posture(q: np.ndarray, pitch: tuple[float, float, float], lower: np.ndarray,
                 upper: np.ndarray) -> np.ndarray:
    """``q`` with shoulder, elbow and wrist pitched to ``pitch`` (keeping the side the arm bends to,
    the base yaw and the rolls): a compact posture above the table."""
    f = q.copy()
    sign = 1.0 if q[1] >= 0.0 else -1.0
    roll3 = 1.0 if math.cos(q[2]) >= 0.0 else -1.0
    roll5 = 1.0 if math.cos(q[4]) >= 0.0 else -1.0
    f[1] = sign * pitch[0]
    f[3] = sign * roll3 * pitch[1]
    f[5] = sign * roll3 * roll5 * pitch[2]
    return np.clip(f, lower, upper)


class JointPlanner:
    """Incremental search of a collision-free joint path from ``q_start`` to a goal configuration of
    pose ``T`` (see the module docstring for the order of the search).

    When the arm starts closer to the scene than ``params.clearance`` (the guard stopped it at an
    obstacle), the path first retreats to one of ``retreat`` (configurations the arm passed through
    recently, newest first) or climbs the clearance gradient; the rest of the search starts there.

    Call :meth:`work` once per control step until it returns True; then ``path`` holds the
    waypoints (start first) or is None with ``reason`` saying why none was found.
    """

    def __init__(self, stepper: IKStepper, guard: CollisionGuard, scene: Scene, q_start: np.ndarray,
                 T: np.ndarray, params: ReplanParams, fold_pitch: tuple[float, float, float],
                 retreat: list[np.ndarray] | None = None, s_pref: float | None = None) -> None:
        self.stepper = stepper
        self.guard = guard
        self.scene = scene
        self.q_start = np.asarray(q_start, float)
        self.T = np.asarray(T, float)
        self.params = params
        self.fold_pitch = fold_pitch
        self.retreat = list(retreat or [])
        self.s_pref = s_pref
        self.goals: list[Candidate] = []
        self.path: list[np.ndarray] | None = None
        self.bends: list[Bend | None] | None = None  # per segment of path (see JointPath), None: straight
        self.reason = ""
        self.done = False
        self._rng = np.random.default_rng(params.seed)
        self._search = self._run()

    def work(self) -> bool:
        """Do ``params.work_per_step`` units of work (a unit: one clearance evaluation, or the IK of
        one swivel sample); True when finished."""
        if self.done:
            return True
        for _ in range(self.params.work_per_step):
            try:
                next(self._search)
            except StopIteration:
                self.done = True
                break
        return self.done

    def _segment(self, qa: np.ndarray, qb: np.ndarray) -> Generator[None, None, bool]:
        r = yield from self.guard.segment_march(qa, qb, self.scene, self.params.clearance,
                                                budget=8 * self.params.work_per_step)
        return r is not None

    def _chain(self, points: list[np.ndarray]) -> Generator[None, None, bool]:
        last = len(points) - 2
        for k, (a, b) in enumerate(zip(points[:-1], points[1:], strict=True)):
            # The last segment is checked from the goal backwards: a goal configuration closer to the
            # scene than the planning clearance then has to get clear first (the dense march).
            ok = yield from (self._segment(b, a) if k == last else self._segment(a, b))
            if not ok:
                return False
        return True

    def _run(self) -> Generator[None, None, None]:
        p = self.params
        g = self.guard
        self.goals = yield from goal_candidates_iter(self.stepper, g, self.T, self.q_start, self.scene, p,
                                                     self.s_pref)
        if not self.goals:
            self.reason = "no collision-free goal configuration within the joint limits"
            return
        c_start = g.clearance(self.q_start, self.scene).distance
        if c_start < 0.0:
            self.reason = f"the arm is in contact with the scene (clearance {c_start:.3f} m)"
            return
        start = self.q_start
        lo, up = g.lower, g.upper
        if self.scene.free_space:
            # free space: the direct move to the cheapest goal bent so that the hand's path is shortest,
            # checked as the polyline through its samples (from a start closer than the clearance, it
            # must get clear first, as a retreat would: the march's dense part)
            arm, q_goal = self.stepper.arm, self.goals[0].q
            bend, straight, bent = yield from bend_search(arm, start, q_goal, lo, up)
            shape = worth_bending(arm, start, q_goal, bend, straight) if bent < straight - BEND_GAIN else None
            yield None
            if shape is not None:
                s_pts = np.linspace(0.0, 1.0, BEND_CURVE_SAMPLES + 1)
                pts = list(bent_points(start, q_goal, shape.bump, s_pts))
                ok = yield from self._chain(pts)
                if ok:
                    self.path, self.bends = [start, q_goal], [shape]
                    return
        head: list[np.ndarray] = []
        if c_start < p.clearance + g.step:
            for q_r in self.retreat[:8]:
                ok = yield from self._segment(start, q_r)
                if ok:
                    head, start = [start], q_r
                    break
            else:
                esc = yield from self._escape(start, c_start)
                if esc:
                    head, start = [start, *esc[:-1]], esc[-1]
        tries: list[list[np.ndarray]] = [[start, c.q] for c in self.goals]
        f0 = fold_posture(start, self.fold_pitch, lo, up)
        tries += [[start, f0, fold_posture(c.q, self.fold_pitch, lo, up), c.q] for c in self.goals[:3]]
        for pts in tries:
            ok = yield from self._chain(pts)
            if ok:
                self.path = _dedupe(head + pts)
                return
        # Random vias, wide joints within one turn around the start (farther copies only lengthen).
        span_lo = np.maximum(lo, start - math.pi)
        span_up = np.minimum(up, start + math.pi)
        for i in range(p.vias):
            v = self._rng.uniform(span_lo, span_up)
            pts = [start, v, self.goals[i % min(3, len(self.goals))].q]
            ok = yield from self._chain(pts)
            if ok:
                self.path = _dedupe(head + pts)
                return
        self.reason = (f"no collision-free joint path found ({len(self.goals)} goal configurations, "
                       f"direct, folded and {p.vias} random vias)")

    def _escape(self, q: np.ndarray, c: float, tries: int = 12) -> Generator[None, None, list[np.ndarray]]:
        """Waypoints that climb the clearance gradient (in joint space, steps of a few mm of travel)
        from ``q`` until it clears ``params.clearance``; [] if that fails."""
        g = self.guard
        lev = g.max_levers()
        out: list[np.ndarray] = []
        need = self.params.clearance + 2.0 * g.step
        for _ in range(tries):
            h = 1e-4
            grad = np.zeros(len(q))
            for j, e in enumerate(np.eye(len(q))):
                grad[j] = (g.clearance(np.clip(q + h * e, g.lower, g.upper), self.scene).distance - c) / h
                yield None
            norm = float(np.dot(lev, np.abs(grad)))
            if norm < 1e-9:
                return []
            # grad / norm moves at most 1 m of lever travel per unit: take twice the missing clearance
            q_n = np.clip(q + grad / norm * max(need - c, 0.005) * 2.0, g.lower, g.upper)
            ok = yield from self._segment(q, q_n)
            if not ok:
                return []
            out.append(q_n)
            q = q_n
            c = g.clearance(q, self.scene).distance
            if c >= need:
                return out
        return []


def _dedupe(points: list[np.ndarray]) -> list[np.ndarray]:
    out = [points[0]]
    for p in points[1:]:
        if float(np.max(np.abs(p - out[-1]))) > 1e-9:
            out.append(p)
    return out


# ----------------------------------------------------------------------------------------------
# Timing
# ----------------------------------------------------------------------------------------------
#: samples of a bent segment's time law at which its joint rates are bounded
BEND_TIMING_SAMPLES = 1025


@dataclass(frozen=True)
class _Segment:
    qa: np.ndarray
    dq: np.ndarray
    t0: float
    duration: float
    bend: Bend | None = None


def min_jerk_duration(dq: np.ndarray, max_vel: np.ndarray, max_acc: np.ndarray,
                      bend: Bend | None = None) -> float:
    """Least duration (s) of a synchronised minimum-jerk move by ``dq`` (rad), straight or bent and paced
    by ``bend``, within the joint velocity and acceleration limits (the slowest joint sets it)."""
    if bend is None:
        d = np.abs(dq)
        return float(max(np.max(PEAK_RATE * d / max_vel), np.max(np.sqrt(PEAK_ACC * d / max_acc))))
    x = np.linspace(0.0, 1.0, BEND_TIMING_SAMPLES)[:, None]
    _, q_x, q_xx = _bent_motion(dq, bend, x)
    return float(max(np.max(np.abs(q_x) / max_vel), math.sqrt(float(np.max(np.abs(q_xx) / max_acc)))))


def _bent_motion(dq: np.ndarray, bend: Bend, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Path parameter s and the joints' first and second derivatives in the time share ``x`` (column)
    of a bent, paced segment by ``dq`` (a minimum-jerk profile sigma(x), s = pace(sigma))."""
    sig, sig1, sig2 = min_jerk(x), min_jerk_rate(x), min_jerk_accel(x)
    s, g1, g2 = _pace(bend.pace, sig)
    s_x, s_xx = g1 * sig1, g2 * sig1 * sig1 + g1 * sig2
    bump = np.atleast_2d(bend.bump)
    tangent = dq + _bend_basis(s[:, 0], len(bump), 1) @ bump  # dq/ds
    curve = _bend_basis(s[:, 0], len(bump), 2) @ bump  # d2q/ds2
    return s, tangent * s_x, tangent * s_xx + curve * s_x * s_x


class JointPath:
    """Waypoints (rad) joined by joint segments, each a synchronised rest-to-rest minimum-jerk move
    within ``share`` of every joint's velocity and acceleration limit: a straight one's progress, a bent
    one's share of the hand's path (its entry of ``bends``, :class:`Bend`; None: all straight) follows
    the minimum-jerk profile, the single-peaked bell of a human reach."""

    def __init__(self, waypoints: list[np.ndarray], max_vel: np.ndarray, max_acc: np.ndarray,
                 share: float = 0.95, bends: list[Bend | None] | None = None) -> None:
        self.waypoints = [np.asarray(w, float) for w in waypoints]
        if bends is not None and len(bends) != len(self.waypoints) - 1:
            raise ValueError(f"{len(bends)} bends for {len(self.waypoints) - 1} segments")
        segs: list[_Segment] = []
        t = 0.0
        for k, (qa, qb) in enumerate(zip(self.waypoints[:-1], self.waypoints[1:], strict=True)):
            dq = qb - qa
            if float(np.max(np.abs(dq))) <= 1e-12:
                continue
            bend = None if bends is None else bends[k]
            seg = _Segment(qa, dq, t, min_jerk_duration(dq, share * max_vel, share * max_acc, bend), bend)
            segs.append(seg)
            t += seg.duration
        self._segs = segs
        self.duration = t

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Joints (rad) and joint velocities (rad/s) at time ``t`` (s) from the start."""
        if not self._segs:
            return self.waypoints[-1].copy(), np.zeros_like(self.waypoints[-1])
        if t >= self.duration:
            last = self._segs[-1]
            return last.qa + last.dq, np.zeros_like(last.dq)
        seg = self._segs[-1]
        for sg in self._segs:
            if t < sg.t0 + sg.duration:
                seg = sg
                break
        x = min(max((t - seg.t0) / seg.duration, 0.0), 1.0)
        if seg.bend is None:
            s = min_jerk(x)
            sdot = min_jerk_rate(x) / seg.duration
            return seg.qa + s * seg.dq, sdot * seg.dq
        s_arr, q_x, _ = _bent_motion(seg.dq, seg.bend, np.array([[x]]))
        q = bent_points(seg.qa, seg.qa + seg.dq, seg.bend.bump, s_arr[0]).reshape(-1)
        return q, q_x[0] / seg.duration


def circle_or_none(geom: Any, T: np.ndarray) -> ElbowCircle | None:
    """The elbow circle of ``T``, None where it is degenerate (stretched arm)."""
    try:
        return elbow_circle(geom, T)
    except UnreachableError:
        return None
