"""A point goal's route through a via pose, when the straight route has no swivel corridor: two straight
legs, start -> via -> goal, each through its own swivel corridor, the hand passing the via without
stopping.

Where the straight route closes (a joint limit, or a singularity margin, that no swivel avoids along a
stretch of the line) a short detour usually opens it: the elbow's joint 4 is fixed by the distance from
the shoulder to the wrist, so a line that passes too near the shoulder (or too far) is blocked at every
swivel, and a via a few centimetres off it is not. :func:`plan_via_route` looks for the via that leaves
the line least:

* candidates (:func:`via_candidates`): the pose at progress ``at`` of the straight route (position on
  the line, orientation by slerp), moved perpendicular to the line in ``VIA_DIRECTIONS`` directions by
  the offset that gives each path ratio of ``VIA_RATIOS`` (the two legs' length over the line's), in
  order of that ratio;
* a candidate is screened first (:func:`~redarm_ros.kinematics.corridor.corridor_screen`: the corridor's
  forward pass at coarse samples, milliseconds): leg 1 from the start, leg 2 from the via at
  ``VIA_SWIVELS`` swivels (nearest the start's first); the first ``MAX_PLANS`` that pass are planned in
  full (:func:`~redarm_ros.control.corridor_route.plan_route`: leg 1 preferring the via swivel that
  passed, leg 2 from leg 1's last configuration, so both keep the start's flip pattern), and the first
  whose two corridors exist (and whose route is not too slow) is taken; one whose route is paced (the
  hand's speed with several peaks, see :func:`~redarm_ros.control.corridor_route.timed_route`) only if
  no later one is single-peaked.

The route (:class:`ViaRoute`) is one minimum-jerk profile over both legs, the progress proportional
to the hand's path length, the swivel on the two schedules joined. Around the via the corner is cut by
a quadratic Bezier arc over ``BLEND`` of the shorter leg (at most ``BLEND_MAX`` m), tangent to both
legs, so the hand's velocity is continuous; the joints along the arc are solved in closed form on the
schedule's swivel and must keep the limits (``limit_margin`` / 2) and stay continuous, else the arc is
halved (up to ``BLEND_TRIES`` times) and, failing that, the candidate is dropped. Units: m, rad, s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from redarm_ros.control.corridor_route import CorridorRoute, RouteMargins, route_margins, smoothed_along
from redarm_ros.control.ik_step import pose_matrix
from redarm_ros.kinematics.corridor import SharedSamples, SwivelCorridor, corridor_screen, route_pose
from redarm_ros.kinematics.protocols import CorridorArm
from redarm_ros.kinematics.quaternion import quat_from_rotvec, quat_mul, quat_normalize, rotvec_between

#: path ratios (both legs' length over the straight line's) of the candidates, in the order tried
VIA_RATIOS = (1.01, 1.03, 1.06, 1.10, 1.15, 1.22)
#: progress of the straight route at which a candidate leaves it, in the order tried per ratio
VIA_AT = (0.5, 0.3, 0.7)
#: directions perpendicular to the line per ratio and progress (evenly spaced around it)
VIA_DIRECTIONS = 8
#: candidates planned in full (two corridor calls each) after passing the screen, and screens of a leg
#: in all (a screen takes milliseconds, a full plan up to seconds)
MAX_PLANS = 3
MAX_SCREENS = 100
#: s: a via route takes at most this much longer than a joint-space move (and no longer than a straight
#: corridor route may): a detour is worth less patience than the straight route
VIA_SLACK = 6.5
#: route samples of the screen per leg
SCREEN_SAMPLES = 16
#: swivels at the via (evenly spaced, nearest the start's first) from which leg 2 is screened
VIA_SWIVELS = 6
#: the corner arc: its half-length as a share of the shorter leg, at most BLEND_MAX (m); halved up to
#: BLEND_TRIES times where its joints leave the limits
BLEND = 0.3
BLEND_MAX = 0.06
BLEND_TRIES = 3
#: half-width (progress) of the swivel's moving average around the via
SMOOTH_WINDOW = 0.08
#: samples of the table from progress to the nominal progress of the legs (see ``_by_length``)
ARC_SAMPLES = 1001
#: joint samples along the corner arc, and the largest joint change (rad) between two of them
BLEND_SAMPLES = 16
BLEND_JOINT_STEP = 0.15

#: plans the corridor route of one leg: (T_start, T_goal, q_start, preferred swivel or None: the start's)
#: -> (route or None, why not)
LegPlanner = Callable[[np.ndarray, np.ndarray, np.ndarray, float | None], tuple[CorridorRoute | None, str]]
#: gives a leg its duration: (route with its corridor, hand path length m, turn rad) -> timed route
LegTimer = Callable[[CorridorRoute, float, float], CorridorRoute]


@dataclass(frozen=True)
class ViaCandidate:
    """A via pose ``T`` (4x4) at progress ``at`` of the straight route, ``offset`` (m) off the line in
    ``direction`` (unit vector), giving the hand path ``ratio`` (both legs over the line)."""

    T: np.ndarray
    at: float
    offset: float
    direction: np.ndarray
    ratio: float


def offset_for_ratio(length: float, at: float, ratio: float) -> float:
    """The offset h (m) from the line at progress ``at`` of a line of ``length`` (m) at which the two legs
    through it are ``ratio`` times as long as the line: sqrt(a^2 + h^2) + sqrt(b^2 + h^2) = ratio L with
    a = at L, b = (1 - at) L (closed form)."""
    if ratio < 1.0 or not 0.0 < at < 1.0:
        raise ValueError(f"ratio must be >= 1 and at in (0, 1), got {ratio}, {at}")
    a, b, R = at * length, (1.0 - at) * length, ratio * length
    leg_a = (R * R - b * b + a * a) / (2.0 * R)  # the first leg's length
    return math.sqrt(max(leg_a * leg_a - a * a, 0.0))


def via_candidates(T0: np.ndarray, T1: np.ndarray, ratios: tuple[float, ...] = VIA_RATIOS,
                   ats: tuple[float, ...] = VIA_AT, directions: int = VIA_DIRECTIONS) -> list[ViaCandidate]:
    """The via candidates of the straight route T0 -> T1 in the order tried: by path ratio, then by
    progress in the order of ``ats``, then by direction (the first one up, away from the table)."""
    p0, p1 = np.asarray(T0, float)[:3, 3], np.asarray(T1, float)[:3, 3]
    length = float(np.linalg.norm(p1 - p0))
    if length < 1e-6:
        return []
    e = (p1 - p0) / length
    up = np.array([0.0, 0.0, 1.0]) - e[2] * e  # the vertical's part across the line
    if np.linalg.norm(up) < 1e-3:
        up = np.array([1.0, 0.0, 0.0]) - e[0] * e
    up /= np.linalg.norm(up)
    side = np.cross(e, up)
    out = []
    for ratio in ratios:
        for at in ats:
            h = offset_for_ratio(length, at, ratio)
            for k in range(directions):
                ang = 2.0 * math.pi * k / directions
                d = math.cos(ang) * up + math.sin(ang) * side
                T = route_pose(T0, T1, at)
                T[:3, 3] = p0 + at * (p1 - p0) + h * d
                out.append(ViaCandidate(T, at, h, d, ratio))
    return out


@dataclass
class ViaRoute(CorridorRoute):
    """A :class:`CorridorRoute` through a via: ``legs`` the two legs' routes, ``share`` the progress at the
    via (leg 1's share of the path length), ``blend`` the corner arc's half-width in progress (0: none),
    ``via`` the candidate. ``corridor`` is both schedules joined on the route's progress (the arc's
    samples solved on it); ``p0``, ``p1``, ``rot0``, ``turn`` are the whole move's."""

    legs: tuple[CorridorRoute, ...] = ()
    share: float = 0.5
    blend: float = 0.0
    via: ViaCandidate | None = field(default=None, repr=False)
    why: str = ""  # why the straight route has no corridor
    arc_u: np.ndarray | None = field(default=None, repr=False)  # see _by_length

    def message(self) -> str:
        """What ``~/state`` says while the hand is on the route: the via, and why not straight."""
        off = self.via.offset if self.via is not None else 0.0
        return f"via a pose {off:.2f} m off the line: the straight route has no corridor ({self.why})"

    def pose(self, u: float) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """Position and orientation at progress u: on leg 1, the corner arc, leg 2."""
        return self._pose_nominal(self._nominal(u))

    def progress_of(self, pos: tuple[float, float, float], rot: tuple[float, float, float, float]) -> float:
        """The progress of a pose: by the position's projection on the nearer leg."""
        w = self.share
        leg1, leg2 = self.legs
        u1, u2 = leg1.progress_of(pos, rot), leg2.progress_of(pos, rot)
        d1 = math.dist(pos, leg1.pose(u1)[0])
        d2 = math.dist(pos, leg2.pose(u2)[0])
        un = w + u2 * (1.0 - w) if u2 > 0.0 and (d2 < d1 or u1 >= 1.0) else u1 * w
        if self.arc_u is None:
            return un
        return float(np.interp(un, self.arc_u, np.linspace(0.0, 1.0, len(self.arc_u))))

    def _nominal(self, u: float) -> float:
        """The nominal progress (leg 1 on [0, share], leg 2 on [share, 1]) at progress u."""
        if self.arc_u is None:
            return u
        return float(np.interp(u, np.linspace(0.0, 1.0, len(self.arc_u)), self.arc_u))

    def _pose_nominal(self, u: float) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        w, b = self.share, self.blend
        leg1, leg2 = self.legs
        pos, rot = leg1.pose(u / w) if u <= w else leg2.pose((u - w) / (1.0 - w))
        if b > 0.0 and w - b < u < w + b:
            a = np.array(leg1.pose((w - b) / w)[0])
            c = np.array(leg2.pose(b / (1.0 - w))[0])
            tau = (u - (w - b)) / (2.0 * b)
            p = (1.0 - tau) ** 2 * a + 2.0 * tau * (1.0 - tau) * np.array(leg1.p1) + tau * tau * c
            pos = (float(p[0]), float(p[1]), float(p[2]))
        return pos, rot


def _joined(arm: CorridorArm, route: ViaRoute, margin: float) -> ViaRoute | None:
    """``route`` with its joined corridor: the legs' schedules on the route's progress, the samples
    within the corner arc replaced by the arc's own joints (closed form at the schedule's swivel). None
    if the arc's joints leave the limits (less ``margin``) or jump."""
    w, b = route.share, route.blend
    c1, c2 = route.legs[0].corridor, route.legs[1].corridor
    u = np.concatenate((c1.u * w, w + c2.u[1:] * (1.0 - w)))
    # (leg 2 starts at leg 1's last configuration: its swivel on the same unwrapped axis)
    s2 = c2.swivel + 2.0 * math.pi * round((c1.swivel[-1] - c2.swivel[0]) / (2.0 * math.pi))
    swivel = np.concatenate((c1.swivel, s2[1:]))
    Q = np.concatenate((c1.q, c2.q[1:]))
    if b > 0.0:
        keep = (u <= w - b) | (u >= w + b)
        ua = np.linspace(w - b, w + b, BLEND_SAMPLES + 1)[1:-1]
        sa = np.interp(ua, u, swivel)
        lower, upper = np.asarray(arm.lower) + margin, np.asarray(arm.upper) - margin
        q_prev = Q[keep & (u <= w - b)][-1]
        Qa = np.empty((len(ua), Q.shape[1]))
        for i, (uk, sk) in enumerate(zip(ua, sa, strict=True)):
            pos, rot = route.pose(float(uk))
            rows = arm.ik(pose_matrix(pos, rot), float(sk), limits=False)
            if len(rows) != 8:
                return None
            q = rows[c1.pattern]
            q = q + 2.0 * math.pi * np.round((q_prev - q) / (2.0 * math.pi))
            if np.any(q < lower) or np.any(q > upper) or float(np.max(np.abs(q - q_prev))) > BLEND_JOINT_STEP:
                return None
            Qa[i], q_prev = q, q
        q_next = Q[keep & (u >= w + b)][0]
        if float(np.max(np.abs(q_next - q_prev))) > BLEND_JOINT_STEP:
            return None
        order = np.argsort(np.concatenate((u[keep], ua)), kind="stable")
        u = np.concatenate((u[keep], ua))[order]
        swivel = np.concatenate((swivel[keep], sa))[order]
        Q = np.concatenate((Q[keep], Qa))[order]
    steps = np.max(np.abs(np.diff(Q, axis=0)), axis=1)
    narrow = c1 if c1.narrowest <= c2.narrowest else c2
    cor = SwivelCorridor(True, u, swivel, Q, c1.pattern, narrow.narrowest,
                         narrow.narrowest_u * (w if narrow is c1 else 1.0 - w) + (0.0 if narrow is c1 else w),
                         None, "", float(steps.max()))
    # the swivel's rate jumps where leg 2 starts (and at the legs' own rate-bound corners): smoothed as
    # a corridor's schedule is, the closest approaches to the limits and singularities kept at least halved
    slack = float(np.min(np.minimum(Q - np.asarray(arm.lower), np.asarray(arm.upper) - Q)))
    m_sing = float(np.min(np.minimum(np.abs(np.sin(Q[:, 1])), np.abs(np.sin(Q[:, 5])))))
    # (near the via only: the legs' ends keep their swivels, the goal's joints may be near a limit)
    near = np.clip((b + 2.0 * SMOOTH_WINDOW - np.abs(u - w)) / SMOOTH_WINDOW, 0.0, 1.0)
    cor = smoothed_along(arm, lambda uk: pose_matrix(*route.pose(uk)), cor, min(2.0 * margin, slack), m_sing,
                         float(np.min(np.abs(Q[:, 3]))), SMOOTH_WINDOW, near)
    return _by_length(replace(route, corridor=cor))


def _by_length(route: ViaRoute) -> ViaRoute:
    """``route`` with the progress proportional to the hand's path length: on the corner arc the Bezier
    parameter runs slower at the corner than at its ends, so the hand's speed would dip by up to
    1 - cos(turn / 2) there (two speed peaks). The nominal progress at ARC_SAMPLES evenly spaced
    values of the path-length share, and the schedule's samples moved to it."""
    un = np.linspace(0.0, 1.0, ARC_SAMPLES)
    P = np.array([route._pose_nominal(float(u))[0] for u in un])  # noqa: SLF001
    cum = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))))
    if cum[-1] < 1e-9:
        return route
    share = cum / cum[-1]
    cor = route.corridor
    return replace(route, arc_u=np.interp(un, share, un),
                   corridor=replace(cor, u=np.interp(cor.u, un, share),
                                    narrowest_u=float(np.interp(cor.narrowest_u, un, share))))


def join_legs(arm: CorridorArm, leg1: CorridorRoute, leg2: CorridorRoute, via: ViaCandidate, margin: float,
              timer: LegTimer) -> ViaRoute | None:
    """The route over ``leg1`` then ``leg2`` (leg 2 starting at leg 1's last configuration) through
    ``via``, with the corner arc (halved where its joints leave the limits less ``margin``) and its
    duration from ``timer``; None if no arc keeps the limits."""
    len1, len2 = math.dist(leg1.p0, leg1.p1), math.dist(leg2.p0, leg2.p1)
    ang1 = math.sqrt(sum(c * c for c in leg1.turn))
    ang2 = math.sqrt(sum(c * c for c in leg2.turn))
    w = min(max(len1 / max(len1 + len2, 1e-9), 0.05), 0.95)
    blend_m = min(BLEND * min(len1, len2), BLEND_MAX)
    base = ViaRoute(leg1.p0, leg2.p1, leg1.rot0, _total_turn(leg1, leg2), leg1.corridor, 0.0,
                    legs=(leg1, leg2), share=w, via=via)
    for k in range(BLEND_TRIES + 1):
        b = blend_m * 0.5 ** k / max(len1 + len2, 1e-9)
        route = _joined(arm, replace(base, blend=min(b, 0.9 * w, 0.9 * (1.0 - w))), margin)
        if route is not None:
            timed = timer(route, len1 + len2, ang1 + ang2)
            assert isinstance(timed, ViaRoute)
            return timed
    return None


def _total_turn(leg1: CorridorRoute, leg2: CorridorRoute) -> tuple[float, float, float]:
    """The rotation vector from leg 1's start orientation to leg 2's end."""
    r_via = quat_mul(quat_from_rotvec(leg1.turn), leg1.rot0)
    r1 = quat_normalize(quat_mul(quat_from_rotvec(leg2.turn), r_via))
    return rotvec_between(leg1.rot0, r1)


@dataclass
class ViaSearch:
    """What :func:`plan_via_route` did: candidates tried, legs screened, candidates planned in full, the
    reason the last full plan failed."""

    tried: int = 0
    screened: int = 0
    planned: int = 0
    why: str = ""

    def summary(self) -> str:
        """What ``~/state`` says when no via route was found."""
        if not self.planned:
            return f"none of {self.tried} via poses passed the screen"
        return f"{self.planned} via poses planned, the last: {self.why}"


def plan_via_route(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray, margin_sing: float,
                   margin_limit: float, plan_leg: LegPlanner, timer: LegTimer, max_duration: float = math.inf,
                   candidates: list[ViaCandidate] | None = None, max_plans: int = MAX_PLANS
                   ) -> tuple[ViaRoute | None, ViaSearch]:
    """The route from the reference (pose T0, joints q0) to T1 through the first via candidate (default
    :func:`via_candidates`) whose two legs pass the screen and then have their corridors (``plan_leg``),
    the route taking at most ``max_duration`` (s); at most ``max_plans`` candidates planned in full and
    MAX_SCREENS legs screened; and what the search did (see the module docstring). ``margin_sing`` and
    ``margin_limit`` are the corridor's; the screen keeps the loosest that :func:`route_margins` gives the
    straight route."""
    search = ViaSearch()
    fallback: ViaRoute | None = None
    cands = via_candidates(T0, T1) if candidates is None else candidates
    s0 = float(arm.swivel(q0))
    pattern = _pattern(arm, T0, q0, s0)
    if pattern is None:
        return None, search
    screen = route_margins(arm, T0, T1, q0, margin_sing, margin_limit)[-1]
    for cand in cands:
        if search.planned >= max_plans or search.screened >= MAX_SCREENS:
            break
        search.tried += 1
        search.screened += 1
        if not _screen(arm, T0, cand.T, q0, screen):
            continue
        s_via = _via_swivel(arm, cand.T, T1, q0, pattern, s0, screen, search)
        if s_via is None:
            continue
        search.planned += 1
        leg1, why = plan_leg(T0, cand.T, q0, s_via)
        if leg1 is None:
            search.why = f"the leg to the via: {why}"
            continue
        if leg1.duration > max_duration:
            search.why = f"the leg to the via needs {leg1.duration:.1f} s"
            continue
        q_via = leg1.corridor.q[-1]
        T_via = np.asarray(arm.fk(q_via), float)  # (the via pose as the joints give it)
        leg2, why = plan_leg(T_via, T1, q_via, None)
        if leg2 is None:
            search.why = f"the leg from the via: {why}"
            continue
        route = join_legs(arm, leg1, leg2, cand, 0.5 * margin_limit, timer)
        if route is None:
            search.why = "the corner arc at the via leaves the joint limits"
            continue
        if route.duration > max_duration:
            search.why = f"its route needs {route.duration:.1f} s"
            continue
        if route.pace_u is None:
            return route, search
        # in the pace the hand slows where the joints swing and speeds up again (several speed peaks):
        # kept while the next candidates are tried for a route with one
        fallback = fallback or route
        search.why = "its route is paced"
    return fallback, search


def _pattern(arm: CorridorArm, T0: np.ndarray, q0: np.ndarray, s0: float) -> int | None:
    """The flip pattern of q0 (the row of arm.ik nearest it), None out of reach."""
    rows = arm.ik(T0, s0, limits=False)
    if len(rows) != 8:
        return None
    return int(np.argmin(np.abs(np.remainder(rows - q0 + math.pi, 2.0 * math.pi) - math.pi).max(axis=1)))


def _via_swivel(arm: CorridorArm, T_via: np.ndarray, T1: np.ndarray, q0: np.ndarray, pattern: int, s0: float,
                m: RouteMargins, search: ViaSearch) -> float | None:
    """The swivel at the via, of VIA_SWIVELS nearest the start's ``s0`` first, whose joints on the flip
    ``pattern`` keep the limits and from which leg 2 passes the screen (counted in ``search``); None if
    none does."""
    shared: SharedSamples = {}  # (the screens of this leg from each swivel share its route's samples)
    for k in sorted(range(VIA_SWIVELS), key=lambda k: min(k, VIA_SWIVELS - k)):
        s = s0 + (2.0 * math.pi * k / VIA_SWIVELS if k <= VIA_SWIVELS // 2 else
                  2.0 * math.pi * (k - VIA_SWIVELS) / VIA_SWIVELS)
        rows = arm.ik(T_via, s, limits=False)
        if len(rows) != 8:
            return None
        q = rows[pattern] + 2.0 * math.pi * np.round((q0 - rows[pattern]) / (2.0 * math.pi))
        if not arm.within_limits(q, 0.0):
            continue
        search.screened += 1
        if _screen(arm, T_via, T1, q, m, shared):
            return s
    return None


def _screen(arm: CorridorArm, T0: np.ndarray, T1: np.ndarray, q0: np.ndarray, m: RouteMargins,
            shared: SharedSamples | None = None) -> bool:
    """Does the leg pass the screen (:func:`~redarm_ros.kinematics.corridor.corridor_screen`) with the
    margins ``m``? ``shared``: the route's samples kept across screens of the same leg."""
    return corridor_screen(arm, T0, T1, q0, limit_margin=m.limit, shoulder_margin=m.shoulder,
                           wrist_margin=m.wrist, elbow_margin=m.elbow, max_rate=m.rate,
                           samples=SCREEN_SAMPLES, shared_samples=shared) is None
