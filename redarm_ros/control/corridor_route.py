"""The straight route of a point goal through the swivel corridor: the hand on the line at a minimum-jerk
pace, the elbow on the corridor's swivel schedule.

When a point goal is set with the hand at rest, :func:`plan_route` asks the kinematics for
the swivel corridor of the straight route (:func:`redarm_ros.kinematics.swivel_corridor`: every swivel at
which the arm can follow the line within the joint limits and away from the shoulder, elbow and wrist
singularities, and a continuous schedule nearest the preferred swivel), once per goal. If there is one,
the hand moves along the line (orientation by slerp) with the progress

    u(t) = 10 x^3 - 15 x^4 + 6 x^5,  x = t / T        (Flash & Hogan's minimum-jerk profile)

and the swivel follows the schedule at the hand's progress. The profile runs in the route's *pace*
sigma when in u it would be too slow: sigma grows with the time the joints need per unit of progress
(each joint's |dq/du| over its velocity limit, the hand's length over its speed, the turn and the
swivel over their rates), so where the line passes near a singularity and joints 1 and 3 swing fast the
hand slows there only, instead of the whole route slowing to that stretch's pace. Its speed would then
have more than one peak: if time allows (``pace_after``), the paced profile is retimed to keep one
peak (:func:`single_peaked_clock`: the hand does not speed up again after the slow stretch, or reaches
its speed before it), else it runs in the pace. The duration T is the least that keeps
every joint's velocity and acceleration (and the hand, orientation and swivel rates) within ``share``
of their limits along that profile. The duration is set by the joint that needs the most time per unit
progress, so a slow route (or none) of the straight route is planned again with the schedule on the
corridor's speed guide (:func:`plan_route` with ``fast``). Units: m, rad, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from redarm_ros.control.guard import CollisionGuard
from redarm_ros.geometry.obstacles import Clearance, Scene
from redarm_ros.kinematics.corridor import SwivelCorridor, route_pose
from redarm_ros.kinematics.protocols import CorridorArm
from redarm_ros.kinematics.quaternion import (
    matrix_from_quat,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    rotvec_between,
)
from redarm_ros.motion.min_jerk import PEAK_RATE, min_jerk, min_jerk_inverse

#: shortest route (s)
MIN_DURATION = 0.3
#: :func:`plan_route` with ``fast``: the speed guide is tried for a route that takes over GUIDE_AFTER times
#: the hand's own time; its swivel rate bound (rad per unit progress; the guide weighs the swivel's own
#: speed against the joints', so it is not held to the low bound of :func:`route_margins`). The joint-limit
#: margin is not lowered for it: a route within a few mrad of a limit leaves the line where the command's
#: limiter brakes the joint (powercube7, margin 0.01 rad: path ratio 1.12, seven speed peaks).
GUIDE_AFTER = 1.5
GUIDE_RATE = 10.0
#: half-width (progress) of the schedule smoothing of the straight route (the via legs keep 0.08, which
#: keeps more of them within the margins): near the shoulder singularity joints 1 and 3 follow the swivel
#: many times over, and at 0.08 a bend of the schedule still asked up to 5 times their acceleration limit
#: (the command lags, the hand's speed ripples). free45 single-peaked, powercube7: 92 -> 95 % (seed
#: 3200), 91 -> 97 % (seed 3300); pa10 about the same
STRAIGHT_WINDOW = 0.12


@dataclass
class CorridorRoute:
    """A point goal's straight route through the swivel corridor, and how far along it the reference is.

    ``p0``, ``p1`` (m) the ends of the line, ``rot0`` the start orientation (w, x, y, z) and ``turn`` the
    rotation vector (rad) to the goal's, ``corridor`` the schedule, ``duration`` (s), ``t`` (s) the
    time along the profile.
    """

    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    rot0: tuple[float, float, float, float]
    turn: tuple[float, float, float]
    corridor: SwivelCorridor
    duration: float
    t: float = 0.0
    t_moved: float = 0.0  # controller time (s) when the route's clock last advanced
    pace_u: np.ndarray | None = None  # u at evenly spaced pace values (None: the pace is u)
    # u at evenly spaced time shares: the single-peaked pace (:func:`single_peaked_clock`), which the
    # minimum-jerk profile does not time (None: the profile in the pace)
    clock_u: np.ndarray | None = None

    def progress_at(self, t: float) -> float:
        """The progress u at time t (s) along the route."""
        if self.clock_u is not None:
            return float(np.interp(t / self.duration, np.linspace(0.0, 1.0, len(self.clock_u)), self.clock_u))
        sig = min_jerk(t / self.duration)
        if self.pace_u is None:
            return sig
        return float(np.interp(sig, np.linspace(0.0, 1.0, len(self.pace_u)), self.pace_u))

    def time_at(self, u: float) -> float:
        """The time (s) along the route at which the progress is u (the inverse of :meth:`progress_at`)."""
        if self.clock_u is not None:
            return self.duration * float(np.interp(u, self.clock_u, np.linspace(0.0, 1.0, len(self.clock_u))))
        sig = u if self.pace_u is None else \
            float(np.interp(u, self.pace_u, np.linspace(0.0, 1.0, len(self.pace_u))))
        return self.duration * min_jerk_inverse(sig)

    def pose(self, u: float) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """Position and orientation at progress u."""
        p0, p1, w = self.p0, self.p1, self.turn
        pos = (p0[0] + u * (p1[0] - p0[0]), p0[1] + u * (p1[1] - p0[1]), p0[2] + u * (p1[2] - p0[2]))
        rot = quat_normalize(quat_mul(quat_from_rotvec((u * w[0], u * w[1], u * w[2])), self.rot0))
        return pos, rot

    def message(self) -> str:
        """What ``~/state`` says while the hand is on the route."""
        return "straight through the swivel corridor"

    def progress_of(self, pos: tuple[float, float, float], rot: tuple[float, float, float, float]) -> float:
        """The progress of a pose on the route: by position on the line, or by the orientation's turn
        when the route is (nearly) a pure rotation."""
        d = np.subtract(self.p1, self.p0)
        L2 = float(d @ d)
        if L2 > 1e-8:
            return min(max(float(np.subtract(pos, self.p0) @ d) / L2, 0.0), 1.0)
        ang = math.sqrt(sum(c * c for c in self.turn))
        if ang < 1e-9:
            return 1.0
        w = rotvec_between(self.rot0, rot)
        return min(max(sum(a * b for a, b in zip(w, self.turn, strict=True)) / (ang * ang), 0.0), 1.0)


#: samples of the pace table (sigma evenly spaced) and of the timing check
PACE_SAMPLES = 201
#: half-width (in progress u) of the moving average that smooths the pace, so the hand's speed changes
#: smoothly where the joints' need changes
PACE_WINDOW = 0.05


def route_pace(corridor: SwivelCorridor, length: float, angle: float, v_max: float, w_max: float,
               s_rate: float, max_vel: np.ndarray) -> np.ndarray:
    """The progress u (increasing, 0..1) at PACE_SAMPLES evenly spaced values of the pace sigma: sigma
    grows with the time per unit of progress that the slowest of the joints, the hand, the turn and the
    swivel needs at its velocity limit (see the module docstring)."""
    u = np.linspace(0.0, 1.0, PACE_SAMPLES)
    need = np.full(len(u), max(length / v_max, angle / w_max, 1e-6))
    if len(corridor.u) >= 2:
        Q = np.stack([np.interp(u, corridor.u, corridor.q[:, j]) for j in range(corridor.q.shape[1])], axis=1)
        S = np.interp(u, corridor.u, corridor.swivel)
        need = np.maximum(need, np.max(np.abs(np.gradient(Q, u, axis=0)) / max_vel, axis=1))
        need = np.maximum(need, np.abs(np.gradient(S, u)) / s_rate)
        W = np.maximum(0.0, 1.0 - np.abs(u[:, None] - u[None, :]) / PACE_WINDOW)
        need = np.maximum((W @ need) / W.sum(axis=1), 1e-6)
    sigma = np.concatenate(([0.0], np.cumsum(0.5 * (need[1:] + need[:-1]) * np.diff(u))))
    sigma /= sigma[-1]
    return np.interp(np.linspace(0.0, 1.0, PACE_SAMPLES), sigma, u)


#: samples of the single-peaked clock (time shares evenly spaced) and of the rate it is made from
CLOCK_SAMPLES = 1001
BELL_SAMPLES = 401


def single_peaked(rate: np.ndarray, step: np.ndarray | float) -> np.ndarray:
    """The largest single-peaked lower bound of ``rate`` (progress per s at samples ``step`` progress
    apart): up to the peak the least rate still to come before it, after it the least rate so far, the
    peak placed where the progress takes least time (the sum of step / rate)."""
    best, best_time = rate, math.inf
    w = np.broadcast_to(np.asarray(step, float), rate.shape)
    for m in range(1, len(rate) - 1):
        g = np.concatenate((np.minimum.accumulate(rate[m::-1])[::-1], np.minimum.accumulate(rate[m:])[1:]))
        time = float(np.sum(np.where(g > 1e-12, w / np.maximum(g, 1e-12), 0.0)))
        if time < best_time:
            best, best_time = g, time
    return best


def single_peaked_clock(pace_u: np.ndarray) -> np.ndarray:
    """The minimum-jerk profile in the pace ``pace_u`` retimed so that the progress rate (the hand's
    speed) rises to one peak and falls: the rate is cut down to its largest single-peaked lower bound
    (up to the peak the least rate still to come before it, after it the least rate so far), the peak
    placed where that takes least time. Where the paced rate dips as the joints swing, the hand keeps the
    dip's speed from the peak on (or up to it) instead of speeding up again; it is nowhere faster than in
    the pace. Returns u at CLOCK_SAMPLES evenly spaced shares of the new duration."""
    x = np.linspace(0.0, 1.0, BELL_SAMPLES)
    u = np.interp(min_jerk(x), np.linspace(0.0, 1.0, len(pace_u)), pace_u)
    v = np.maximum(np.gradient(u, x), 0.0)
    g = single_peaked(v, v)
    # the new time per unit x is the stretch v / g (1 at the ends, where both vanish)
    stretch = np.where(g > 1e-12, v / np.maximum(g, 1e-12), 1.0)
    t = np.concatenate(([0.0], np.cumsum(0.5 * (stretch[1:] + stretch[:-1]) * np.diff(x))))
    clock = np.interp(np.linspace(0.0, 1.0, CLOCK_SAMPLES), t / t[-1], u)
    return clock + np.linspace(0.0, 1e-9, CLOCK_SAMPLES)  # (strictly increasing, for the inverse)


#: samples of the progress at which :func:`fast_clock` solves the route's joints and bounds its pace
FAST_SAMPLES = 401


def route_joints(arm: CorridorArm, route: CorridorRoute, u: np.ndarray) -> np.ndarray:
    """The joints (len(u), n) the route commands at progress values ``u`` (ascending): the pose at u on
    the schedule's swivel (:meth:`SwivelCorridor.swivel_at`), on the corridor's flip pattern, each the 2 pi
    copy nearest the one before (from the corridor's start)."""
    cor = route.corridor
    Q = np.empty((len(u), cor.q.shape[1]))
    q_prev = cor.q[0]
    for i, x in enumerate(u):
        pos, rot = route.pose(float(x))
        T = np.eye(4)
        T[:3, :3] = matrix_from_quat(rot)
        T[:3, 3] = pos
        row = arm.ik(T, cor.swivel_at(float(x)), limits=False)[cor.pattern]
        Q[i] = q_prev = row + 2.0 * math.pi * np.round((q_prev - row) / (2.0 * math.pi))
    return Q


#: :func:`route_clearance`: progress samples checked first, and the most the check may take in all
CLEAR_SAMPLES = 65
CLEAR_BUDGET = 4000
#: m: :func:`route_clearance`'s sample spacing (lever-weighted joint travel) where an end of the route is
#: closer to the scene than the margin
CLEAR_FINE = 1e-3


def route_clearance(arm: CorridorArm, guard: CollisionGuard, route: CorridorRoute, scene: Scene,
                    need: float) -> Clearance:
    """The smallest clearance of the arm along ``route`` against ``scene`` and itself (the guard's
    capsules and self-collision pairs) where the route keeps ``need`` (m), else a clearance below
    ``need`` (where it was found, or the check's budget spent).

    A sample of clearance ``c`` proves every configuration within ``c - need`` of joint travel (weighted
    by the guard's levers) clear: an interval between two samples passes when its travel is at most the
    smaller clearance less ``need`` (the chord taken for the arc, which it approaches as the interval
    halves), else it is halved. An end closer than ``need`` (a goal near the table) must get clear
    without coming closer than it is: samples CLEAR_FINE of travel apart (between two the clearance
    drops at most half that), each within CLEAR_FINE / 2 of the end's clearance or farther, up to the
    first of the first samples that keeps ``need``."""
    lev = guard.max_levers()
    u = np.linspace(0.0, 1.0, CLEAR_SAMPLES)
    Q = route_joints(arm, route, u)
    used = len(u)

    def at(x: np.ndarray, q_near: np.ndarray) -> np.ndarray:
        rows = route_joints(arm, route, x)
        return rows + 2.0 * math.pi * np.round((q_near - rows) / (2.0 * math.pi))

    clear = [guard.clearance(q, scene) for q in Q]
    dist = np.array([c.distance for c in clear])
    ok = np.flatnonzero(dist >= need)
    if len(ok) == 0:
        return min(clear, key=lambda c: c.distance)
    worst = min((clear[k] for k in range(ok[0], ok[-1] + 1)), key=lambda c: c.distance)
    if worst.distance < need:
        return worst
    for k_end, k_clear in ((0, int(ok[0])), (len(u) - 1, int(ok[-1]))):
        if k_end == k_clear:
            continue
        # the dense march from the end to the first sample that keeps need
        lo, hi = sorted((k_end, k_clear))
        travel = float(np.sum(np.abs(np.diff(Q[lo:hi + 1], axis=0)) @ lev))
        n = min(int(math.ceil(2.0 * travel / CLEAR_FINE)) + 2, CLEAR_BUDGET)
        x = np.linspace(u[k_end], u[k_clear], n)
        floor = dist[k_end] - 0.5 * CLEAR_FINE
        if floor < 0.0:  # (an arm in contact is the re-planner's)
            return clear[k_end]
        for q in at(x, Q[k_end]):
            c = guard.clearance(q, scene)
            used += 1
            if c.distance < floor or used > CLEAR_BUDGET:
                return Clearance(min(c.distance, need - 1e-9), c.link, c.obstacle)
    stack = [(float(u[k]), Q[k], clear[k], float(u[k + 1]), Q[k + 1], clear[k + 1])
             for k in range(int(ok[0]), int(ok[-1]))]
    while stack:
        ua, qa, ca, ub, qb, cb = stack.pop()
        if float(lev @ np.abs(qb - qa)) <= min(ca.distance, cb.distance) - need:
            continue
        um = 0.5 * (ua + ub)
        qm = at(np.array([um]), qa)[0]
        cm = guard.clearance(qm, scene)
        used += 1
        if cm.distance < need or used > CLEAR_BUDGET:
            return Clearance(min(cm.distance, need - 1e-9), cm.link, cm.obstacle)
        worst = min(worst, cm, key=lambda c: c.distance)
        stack += [(um, qm, cm, ub, qb, cb), (ua, qa, ca, um, qm, cm)]
    return worst


def fast_clock(arm: CorridorArm, route: CorridorRoute, length: float, angle: float, v_max: float,
               w_max: float, s_rate: float, max_vel: np.ndarray, max_acc: np.ndarray,
               share: float) -> tuple[np.ndarray, float]:
    """The single-peaked clock of ``route`` that keeps the joints at their limits along the path: the
    progress rate r(u) is the greatest whose joints keep ``share`` of their velocity and acceleration
    limits (and the hand, turn and swivel their rates), found on the phase plane (r^2 over u: forward at
    the most acceleration from rest, backward at the most deceleration to rest, below the velocity bound,
    the speed from which each joint still stops before its limit (:func:`braking_need`) and the bound
    where an acceleration within the limits exists at all) under a single-peaked ceiling
    (:func:`single_peaked`). Where joints 1 and 3 swing near the shoulder singularity the hand slows
    there; it keeps that speed to the end, or reaches it before. Returns u at CLOCK_SAMPLES evenly spaced
    shares of the duration, and the duration (s), stretched where a step of the result still asks a
    joint for more than its share."""
    # (the corridor's own samples too: the schedule's curvature changes there, and near a singularity the
    # joints follow it many times over)
    u = np.unique(np.concatenate((np.linspace(0.0, 1.0, FAST_SAMPLES), route.corridor.u)))
    n = len(u)
    du = np.diff(u)
    Q = route_joints(arm, route, u)
    S = np.array([route.corridor.swivel_at(float(x)) for x in u])
    dQ = np.gradient(Q, u, axis=0)
    ddQ = np.gradient(dQ, u, axis=0)
    vel, acc = share * np.asarray(max_vel, float), share * np.asarray(max_acc, float)
    need = np.maximum(np.max(np.abs(dQ) / vel, axis=1), np.abs(np.gradient(S, u)) / s_rate)
    need = np.maximum(need, max(length / v_max, angle / w_max, 1e-9))
    limits = (np.asarray(arm.lower, float), np.asarray(arm.upper, float))
    need = np.maximum(need, braking_need(Q, dQ, acc, limits))
    ceiling = 1.0 / need**2  # (r^2)

    def acc_range(k: int, x: float) -> tuple[float, float]:
        """The progress accelerations (1/s^2) at sample k and r^2 = x that keep every joint's
        |dq/du u'' + d2q/du2 x| within its limit (lo > hi: none)."""
        d, dd = dQ[k], ddQ[k]
        moving = np.abs(d) > 1e-9
        if np.any(np.abs(dd[~moving]) * x > acc[~moving]):
            return 1.0, -1.0
        if not moving.any():
            return -math.inf, math.inf
        e1 = (-acc[moving] - dd[moving] * x) / d[moving]
        e2 = (acc[moving] - dd[moving] * x) / d[moving]
        return float(np.max(np.minimum(e1, e2))), float(np.min(np.maximum(e1, e2)))

    for k in range(n):  # the bound where some acceleration keeps the limits (x = 0 has one)
        lo, hi = acc_range(k, float(ceiling[k]))
        if lo > hi:
            a, b = 0.0, float(ceiling[k])
            for _ in range(40):
                m = 0.5 * (a + b)
                lo, hi = acc_range(k, m)
                a, b = (m, b) if lo <= hi else (a, m)
            ceiling[k] = a
    # per step between two samples (at its midpoint, where the result is checked): dq/du and d2q/du2
    dQm, ddQm = 0.5 * (dQ[1:] + dQ[:-1]), 0.5 * (ddQ[1:] + ddQ[:-1])
    # single-peaked first: where the rate is flat (no progress acceleration) the joints' accelerations
    # are d2q/du2 r^2 alone
    with np.errstate(divide="ignore"):
        flat_step = np.min(acc / np.abs(ddQm), axis=1)
    flat = np.minimum(np.append(flat_step, math.inf), np.insert(flat_step, 0, math.inf))
    weight = np.gradient(u)  # (the progress each sample stands for)
    ceiling = np.minimum(ceiling, single_peaked(np.sqrt(np.minimum(ceiling, flat)), weight) ** 2)

    def reach(j: int, x_from: float, sign: float) -> float:
        """The largest r^2 at the end of step j reached from r^2 = ``x_from`` at its start (``sign`` 1:
        forward, from the sample before; -1: backward, from the sample after) at the most progress
        acceleration (deceleration) the joints allow at the step's midpoint. Implicit (the new r^2 in
        the bound): near the singularity d2q/du2 is large, and an explicit step would overshoot to rest.
        Per joint the midpoint's acceleration is c x + e (x the new r^2), kept within +-acc on the side
        the progress acceleration pushes it (sign dq/du)."""
        d = sign * dQm[j]
        c = 0.5 * ddQm[j] + d / (2.0 * du[j])
        e = x_from * (0.5 * ddQm[j] - d / (2.0 * du[j]))
        k = j + 1 if sign > 0.0 else j
        with np.errstate(divide="ignore", invalid="ignore"):
            ups = np.where((d > 0.0) & (c > 0.0), (acc - e) / c,
                           np.where((d < 0.0) & (c < 0.0), (-acc - e) / c, math.inf))
        return max(0.0, min(float(ceiling[k]), float(np.min(ups))))

    x = ceiling.copy()
    x[0] = x[-1] = 0.0
    for k in range(1, n):
        x[k] = min(x[k], reach(k - 1, float(x[k - 1]), 1.0))
    for k in range(n - 2, -1, -1):
        x[k] = min(x[k], reach(k, float(x[k + 1]), -1.0))
    best = single_peaked(np.sqrt(x), weight)
    t = np.concatenate(([0.0], np.cumsum(2.0 * du / np.maximum(best[1:] + best[:-1], 1e-12))))
    # the joints along the result, per step at its midpoint: the duration stretched to keep every one
    # within the limits (the passes are exact only to their step)
    x = best * best
    ud2 = (np.diff(x) / (2.0 * du))[:, None]
    mid = 0.5 * (x[1:] + x[:-1])[:, None]
    vel_ratio = np.max(np.abs(dQ) * best[:, None] / vel)
    acc_ratio = np.max(np.abs(dQm * ud2 + ddQm * mid) / acc)
    stretch = max(1.0, float(vel_ratio), math.sqrt(float(acc_ratio)))
    # within a step the progress acceleration is constant: u is quadratic in time there (a step taken at
    # constant speed would stop dead at the end, where the last step can take a few tenths of a second)
    tq = np.linspace(0.0, t[-1], CLOCK_SAMPLES)
    k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, n - 2)
    tau = tq - t[k]
    clock = np.minimum(u[k] + best[k] * tau + 0.5 * ud2[k, 0] * tau * tau, u[k + 1])
    clock[-1] = 1.0
    return clock + np.linspace(0.0, 1e-9, CLOCK_SAMPLES), float(t[-1]) * stretch


def braking_need(Q: np.ndarray, dQ: np.ndarray, acc: np.ndarray, limits: tuple[np.ndarray, np.ndarray]
                 ) -> np.ndarray:
    """Per sample, the time per unit of the path parameter (s) below which a joint at ``Q`` moving at
    ``dQ`` (per unit of the parameter) towards a limit could no longer stop before it braking at ``acc``:
    |dq| / sqrt(2 acc d), d the distance to that limit. A route that keeps it never makes the command's
    limiter brake a joint onto its limit (the hand would leave the line)."""
    lower, upper = limits
    d = np.where(dQ > 0.0, upper - Q, Q - lower)
    return np.max(np.abs(dQ) / np.sqrt(2.0 * acc * np.maximum(d, 1e-12)), axis=1)


def route_duration(corridor: SwivelCorridor, length: float, angle: float, v_max: float, w_max: float,
                   s_rate: float, max_vel: np.ndarray, max_acc: np.ndarray, share: float,
                   pace_u: np.ndarray | None = None, clock_u: np.ndarray | None = None,
                   limits: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """The least duration (s) of the minimum-jerk route in the pace ``pace_u`` (None: in u), or of the
    route on the clock ``clock_u`` (:func:`single_peaked_clock`), within the limits (see the module
    docstring); given the joints' position ``limits`` (lower, upper), also slow enough that every joint
    can stop before its limit at ``share`` of its acceleration (:func:`braking_need`)."""
    # (the clock's ramps can be short: as finely as it is sampled)
    x = np.linspace(0.0, 1.0, PACE_SAMPLES if clock_u is None else CLOCK_SAMPLES)
    sig = min_jerk(x)
    if clock_u is not None:
        u = np.interp(x, np.linspace(0.0, 1.0, len(clock_u)), clock_u)
    else:
        u = sig if pace_u is None else np.interp(sig, np.linspace(0.0, 1.0, len(pace_u)), pace_u)
    # position, orientation and swivel along the profile at T = 1: a rate is the x-derivative / T
    du = np.gradient(u, x)
    T = max(MIN_DURATION, float(np.max(du)) * max(length / v_max, angle / w_max))
    if len(corridor.u) < 2:
        return T
    Q = np.stack([np.interp(u, corridor.u, corridor.q[:, j]) for j in range(corridor.q.shape[1])], axis=1)
    S = np.interp(u, corridor.u, corridor.swivel)
    dq = np.abs(np.gradient(Q, x, axis=0))
    ddq = np.abs(np.gradient(np.gradient(Q, x, axis=0), x, axis=0))
    T = max(T, float(np.max(np.abs(np.gradient(S, x)))) / s_rate)
    T = max(T, float(np.max(dq.max(axis=0) / (share * max_vel))))
    # acceleration (x-second derivative / T^2), taken at its 95th percentile per joint: the rate bound's
    # corners give a few samples a large second difference (the IK step and the command's acceleration
    # limit absorb those; the route's clock then waits for the hand)
    need = np.percentile(ddq, 95, axis=0) / (share * max_acc)
    T = max(T, math.sqrt(float(np.max(need))))
    if limits is not None:
        T = max(T, float(np.max(braking_need(Q, np.gradient(Q, x, axis=0), share * max_acc, limits))))
    return T


def smoothed(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray, cor: SwivelCorridor, m_limit: float,
             m_sing: float, m_elbow: float, window: float = 0.08) -> SwivelCorridor:
    """The schedule averaged over +-``window`` of progress (see :func:`smoothed_along`). The backward pass
    leaves corners where the rate bound starts or ends; the command cannot follow a corner within the
    joints' acceleration limits without the hand leaving the line (its speed then has several peaks)."""
    return smoothed_along(arm, lambda u: route_pose(T0, T1, u), cor, m_limit, m_sing, m_elbow, window)


#: rounds of :func:`smoothed_along`: each keeps the schedule itself around the samples the average failed
SMOOTH_ROUNDS = 4


def smoothed_along(arm: CorridorArm, pose_at: Any, cor: SwivelCorridor, m_limit: float, m_sing: float,
                   m_elbow: float, window: float = 0.08, share: np.ndarray | None = None) -> SwivelCorridor:
    """The schedule of a route whose pose (4x4) at progress u is ``pose_at(u)``, averaged over
    +-``window`` of progress (triangular weights; ``share`` (per sample, 0..1): how much of the average
    replaces the schedule there, None: all). The start is kept: the average is taken of the schedule
    extended oddly about it, so the smoothed swivel also leaves the start at the average rate (a corner
    just after the start, where the swivel first turns at the rate bound, is smoothed too). Every sample's
    joints at the new swivel must keep half the margins and stay continuous (each joint within 0.15 rad
    of the sample before); where one does not, the schedule is kept within ``window`` of it (blended in
    over the next ``window``) and the rest tried again, up to SMOOTH_ROUNDS times."""
    u, S = cor.u, cor.swivel
    if len(u) < 3:
        return cor
    du = np.gradient(u)[None, :]  # (uneven samples: weights per unit progress)
    W = np.maximum(0.0, 1.0 - np.abs(u[:, None] - u[None, :]) / window) * du
    W_odd = np.maximum(0.0, 1.0 - np.abs(u[:, None] + u[None, :] - 2.0 * u[0]) / window) * du
    S_avg = (W @ S + W_odd @ (2.0 * S[0] - S)) / (W.sum(axis=1) + W_odd.sum(axis=1))
    want = np.ones(len(u)) if share is None else np.asarray(share, float)
    lo = np.asarray(arm.lower) + 0.5 * m_limit
    up = np.asarray(arm.upper) - 0.5 * m_limit
    failed: list[float] = []
    for _ in range(SMOOTH_ROUNDS):
        keep = np.ones(len(u))
        for uf in failed:
            keep = np.minimum(keep, np.clip(np.abs(u - uf) / window - 1.0, 0.0, 1.0))
        mix = want * keep
        S_new = mix * S_avg + (1.0 - mix) * S
        S_new[0] = S[0]
        Q = np.empty_like(cor.q)
        Q[0] = cor.q[0]
        bad = None
        for i in range(1, len(u)):
            row = arm.ik(pose_at(float(u[i])), float(S_new[i]), limits=False)[cor.pattern]
            q = row + 2.0 * math.pi * np.round((Q[i - 1] - row) / (2.0 * math.pi))
            if np.any(q < lo) or np.any(q > up) or float(np.max(np.abs(q - Q[i - 1]))) > 0.15 \
                    or min(abs(math.sin(q[1])), abs(math.sin(q[5]))) < 0.5 * m_sing \
                    or abs(q[3]) < 0.5 * m_elbow:
                bad = float(u[i])
                break
            Q[i] = q
        if bad is None:
            return replace(cor, swivel=S_new, q=Q, max_joint_step=float(np.max(np.abs(np.diff(Q, axis=0)))))
        if not np.any(mix > 0.0):
            break
        failed.append(bad)
    return cor


#: swivels (evenly spaced on the circle) at which :func:`goal_keeps` looks at the goal's joints
GOAL_SWIVELS = 72


def goal_keeps(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray,
               q0: np.ndarray) -> tuple[float, float, float, float]:
    """What the goal pose ``T1`` can keep at best on the flip pattern of the start ``q0`` (pose ``T0``),
    which the corridor keeps, over the swivel circle: the distance (rad) to the nearest joint limit (joints of
    range 2 pi or wider, which fit on some copy, left out), |sin q2|, |sin q6| and |q4| (rad; q4 is the
    same at every swivel), each at its own best swivel. (inf, 1, 1, pi) where nothing is known (the
    goal out of reach)."""
    s0 = float(arm.swivel(q0))
    rows = arm.ik(T0, s0, limits=False)
    if len(rows) != 8:
        return math.inf, 1.0, 1.0, math.pi
    pattern = int(np.argmin(np.abs(np.remainder(rows - q0 + math.pi, 2.0 * math.pi) - math.pi).max(axis=1)))
    lower, upper = np.asarray(arm.lower, float), np.asarray(arm.upper, float)
    narrow = upper - lower < 2.0 * math.pi - 1e-9
    best = np.array([-math.inf, 0.0, 0.0, 0.0])
    for s in np.linspace(-math.pi, math.pi, GOAL_SWIVELS, endpoint=False):
        sol = arm.ik(T1, float(s), limits=False)
        if len(sol) != 8:
            return math.inf, 1.0, 1.0, math.pi
        q = sol[pattern]
        slack = float(np.min(np.minimum(q - lower, upper - q)[narrow])) if narrow.any() else math.inf
        best = np.maximum(best, (slack, abs(math.sin(q[1])), abs(math.sin(q[5])), abs(q[3])))
    return float(best[0]), float(best[1]), float(best[2]), float(best[3])


@dataclass(frozen=True)
class RouteMargins:
    """The margins of one corridor try (see :func:`route_margins`): ``limit`` (rad) from the joint
    limits, ``shoulder`` and ``wrist`` (least |sin q2|, |sin q6|), ``elbow`` (least |q4|, rad), ``rate``
    (swivel rad per unit progress)."""

    limit: float
    shoulder: float
    wrist: float
    elbow: float
    rate: float


def route_margins(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray, margin_sing: float,
                  margin_limit: float) -> list[RouteMargins]:
    """The margins :func:`plan_route` tries in turn, strictest first. Each margin is at most 0.9 of what
    the start configuration keeps, and of what the goal keeps at its best swivel (:func:`goal_keeps`)."""
    # the margins shrink to what the start keeps (an elbow resting near the shoulder axis may start).
    # First with three times the singularity margin: near a singularity margin joints 1 and 3 (5 and 7)
    # turn up to 1 / margin times faster than the swivel, and the route's timing slows down with them
    # Likewise to what the goal keeps at its best swivel: a goal near a limit or a singularity would
    # otherwise close the corridor just before the end
    g_slack, g_sh, g_wr, g_el = goal_keeps(arm, T0, T1, q0)
    slack = float(np.min(np.minimum(q0 - np.asarray(arm.lower), np.asarray(arm.upper) - q0)))
    m_limit = min(margin_limit, 0.9 * max(slack, 0.0), 0.9 * max(g_slack, 0.0))
    # and with a low swivel rate bound (a slow swivel keeps the joints slow), raised if that closes it
    out = []
    for sing, rate in ((min(3.0 * margin_sing, 0.5), 1.0), (margin_sing, 1.0), (margin_sing, 4.0)):
        out.append(RouteMargins(m_limit, max(min(sing, 0.9 * abs(math.sin(q0[1])), 0.9 * g_sh), 1e-3),
                                max(min(sing, 0.9 * abs(math.sin(q0[5])), 0.9 * g_wr), 1e-3),
                                min(sing, 0.9 * abs(q0[3]), 0.9 * g_el), rate))
    return out


#: :func:`fallback_margins`: the joint-limit margin (rad, at most) and the share of the singularity margins
FALLBACK_LIMIT = 0.02
FALLBACK_SING = 1.0 / 3.0


def fallback_margins(m: RouteMargins) -> RouteMargins:
    """The margins of a last try of the straight route after ``m`` (the loosest of :func:`route_margins`)
    closed: the joint limits FALLBACK_LIMIT, the singularities FALLBACK_SING of ``m``'s. A route near a
    limit is timed so that the joint can stop before it (:func:`braking_need`); near the shoulder
    singularity joints 1 and 3 swing fast, and the route's clock slows there (:func:`fast_clock`)."""
    return replace(m, limit=min(m.limit, FALLBACK_LIMIT), shoulder=FALLBACK_SING * m.shoulder,
                   wrist=FALLBACK_SING * m.wrist, elbow=FALLBACK_SING * m.elbow)


def timed_route(route: CorridorRoute, length: float, angle: float, v_max: float, w_max: float, s_rate: float,
                max_vel: np.ndarray, max_acc: np.ndarray, share: float, pace_after: float,
                arm: CorridorArm | None = None) -> CorridorRoute:
    """``route`` (of hand path ``length`` m and turn ``angle`` rad) with its duration: the minimum-jerk
    profile in u unless that takes longer than ``pace_after`` (s); then the pace (:func:`route_pace`)
    made single-peaked (:func:`single_peaked_clock`) unless that too takes longer; then (given the
    ``arm``) the clock along the joints' limits (:func:`fast_clock`); else the faster of that and the pace."""
    cor = route.corridor
    limits = None if arm is None else (np.asarray(arm.lower, float), np.asarray(arm.upper, float))
    timing = (cor, length, angle, v_max, w_max, s_rate, max_vel, max_acc, share)
    T = route_duration(*timing, limits=limits)
    if T <= pace_after:
        return replace(route, duration=T, pace_u=None, clock_u=None)
    pace_u = route_pace(cor, length, angle, v_max, w_max, s_rate, max_vel)
    clock_u = single_peaked_clock(pace_u)
    T = route_duration(*timing, clock_u=clock_u, limits=limits)
    if T <= pace_after:
        return replace(route, duration=T, pace_u=None, clock_u=clock_u)
    T = route_duration(*timing, pace_u, limits=limits)
    paced = replace(route, duration=T, pace_u=pace_u, clock_u=None)
    if arm is None or len(cor.u) < 2:
        return paced
    clock_u, T_fast = fast_clock(arm, route, length, angle, v_max, w_max, s_rate, max_vel, max_acc, share)
    if T_fast <= max(pace_after, T):
        return replace(route, duration=max(T_fast, MIN_DURATION), pace_u=None, clock_u=clock_u)
    return paced


def _slower(a: CorridorRoute, b: CorridorRoute) -> bool:
    """Is route a worse than b: in the pace where b is not (its hand speed has several peaks), or as
    paced and longer."""
    return (a.pace_u is not None, a.duration) > (b.pace_u is not None, b.duration)


def _find_corridor(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray, preferred: Any,
                   tries: list[RouteMargins], **guide: Any) -> tuple[SwivelCorridor, RouteMargins]:
    """The corridor of the first of ``tries`` that has one (else the last's), and its margins."""
    for m in tries:
        cor = arm.swivel_corridor(T0, T1, q0, limit_margin=m.limit, shoulder_margin=m.shoulder,
                                  wrist_margin=m.wrist, elbow_margin=m.elbow, max_rate=m.rate,
                                  preferred=preferred, samples=12, max_joint_step=0.1, **guide)
        if cor.found:
            break
    return cor, m


def plan_route(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray, preferred: Any,
               margin_sing: float, margin_limit: float, v_max: float, w_max: float, s_rate: float,
               max_vel: np.ndarray, max_acc: np.ndarray, share: float, pace_after: float = math.inf,
               fast: bool = False, window: float = 0.08) -> tuple[CorridorRoute | None, str]:
    """The corridor route from the reference (pose T0, joints q0) to T1, or (None, why there is none),
    with the margins of :func:`route_margins`. The minimum-jerk profile runs in
    u (a single-peaked hand speed) unless that takes longer than ``pace_after`` (s): then in the pace
    (:func:`route_pace`; the hand slows where the joints swing).

    ``fast``: without a corridor at those margins, the :func:`fallback_margins` are tried too; a route
    that takes over GUIDE_AFTER times the hand's own time, or none, is planned again with the schedule
    on the speed guide (the swivel rate bound GUIDE_RATE) and the better of the two kept (not paced, then
    the shorter); a route too slow in the pace may follow the joints' limits (:func:`timed_route`).
    ``window``: the schedule's smoothing (:func:`smoothed`)."""
    p0 = (float(T0[0, 3]), float(T0[1, 3]), float(T0[2, 3]))
    p1 = (float(T1[0, 3]), float(T1[1, 3]), float(T1[2, 3]))
    r0, r1 = quat_from_matrix(T0[:3, :3]), quat_from_matrix(T1[:3, :3])
    turn = rotvec_between(r0, r1)
    angle = math.sqrt(sum(c * c for c in turn))
    length = math.dist(p0, p1)
    timing = (length, angle, v_max, w_max, s_rate, max_vel, max_acc, share, pace_after)

    def route_of(cor: SwivelCorridor, m: RouteMargins) -> CorridorRoute:
        cor = smoothed(arm, T0, T1, cor, m.limit, min(m.shoulder, m.wrist), m.elbow, window)
        return timed_route(CorridorRoute(p0, p1, r0, turn, cor, 0.0), *timing, arm=arm if fast else None)

    tries = route_margins(arm, T0, T1, q0, margin_sing, margin_limit)
    if fast:
        tries.append(fallback_margins(tries[-1]))
    cor, m = _find_corridor(arm, T0, T1, q0, preferred, tries)
    route = route_of(cor, m) if cor.found else None
    why = cor.reason
    hand_time = PEAK_RATE * max(length / v_max, angle / w_max)
    if fast and (route is None or route.duration > GUIDE_AFTER * hand_time):
        # the schedule keeps the joints' speed demand low (the route's duration is set by its worst joint),
        # down to what the hand's own length and turn take, and else keeps near the preferred swivel
        rates = np.append(share * np.asarray(max_vel, float), s_rate)
        guide = {"speed_rates": rates, "speed_floor": hand_time}
        fast_tries = list(dict.fromkeys(replace(t, rate=max(t.rate, GUIDE_RATE)) for t in tries[1:]))
        cor, m = _find_corridor(arm, T0, T1, q0, preferred, fast_tries, **guide)
        if cor.found:
            guided = route_of(cor, m)
            if route is None or _slower(route, guided):
                route = guided
    if route is None:
        return None, why
    return route, ""
