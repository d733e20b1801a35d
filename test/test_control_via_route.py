"""Point goals without a straight swivel corridor through a via pose (control/via_route.py): the
candidates' geometry, the joined route checked against a brute-force solve of its poses, and the
controller taking the via route before the joint-space re-planner."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.corridor_route import plan_route, timed_route
from redarm_ros.control.ik_step import pose_matrix
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.reach_controller import Phase
from redarm_ros.control.via_route import ViaRoute, offset_for_ratio, plan_via_route, via_candidates
from redarm_ros.kinematics import load_arm

# PA10: a straight route that folds the elbow past joint 4's limit at every swivel near u = 0.07
# (joint 2 at its lower limit, where the move before ended)
Q_START = np.array([0.006735970635362243, -1.5882496193148399, 0.9950009710785493, -2.3464817640115982,
                    0.5543778069823624, 1.3664557845561192, 0.2809461362914547])
T_GOAL = np.array([[-0.14379795546544819, 0.757779596197395, -0.6364685629242578, 0.005747265527642348],
                   [0.9599282290229729, -0.04952006437670331, -0.27583610776862777, -0.52860599528731],
                   [-0.24054093857132916, -0.6506288087773551, -0.7202931417556218, 0.9497045964875802],
                   [0.0, 0.0, 0.0, 1.0]])
MARGIN_SING, MARGIN_LIMIT = 0.15, 0.05


def _orthonormal(T: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    return out


def _legs(arm):
    timing = (0.4, 1.5, 1.0, np.asarray(arm.max_vel), np.asarray(arm.max_acc), 0.7)

    def leg(Ta, Tb, qa, preferred):
        return plan_route(arm, Ta, Tb, qa, preferred, MARGIN_SING, MARGIN_LIMIT, *timing)

    def timer(route, length, angle):
        return timed_route(route, length, angle, *timing, pace_after=math.inf)

    return leg, timer


@pytest.mark.parametrize("at", [0.3, 0.5, 0.7])
@pytest.mark.parametrize("ratio", [1.0, 1.01, 1.1, 1.4])
def test_offset_for_ratio_gives_that_path_ratio(at, ratio):
    """Brute force: the two legs through the point at the offset are ``ratio`` times the line."""
    L = 0.37
    h = offset_for_ratio(L, at, ratio)
    assert math.hypot(at * L, h) + math.hypot((1.0 - at) * L, h) == pytest.approx(ratio * L, rel=1e-9)


def test_via_candidates_lie_across_the_line_in_order_of_path_ratio():
    T0 = np.eye(4)
    T0[:3, 3] = [0.4, -0.2, 0.3]
    T1 = np.eye(4)
    T1[:3, 3] = [-0.1, 0.3, 0.5]
    T1[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    cands = via_candidates(T0, T1)
    p0, p1 = T0[:3, 3], T1[:3, 3]
    ratios = [(np.linalg.norm(c.T[:3, 3] - p0) + np.linalg.norm(p1 - c.T[:3, 3])) / np.linalg.norm(p1 - p0)
              for c in cands]
    assert np.allclose(ratios, [c.ratio for c in cands], atol=1e-9)
    assert ratios == sorted(ratios) or np.all(np.diff([c.ratio for c in cands]) >= 0.0)
    for c in cands:
        foot = p0 + c.at * (p1 - p0)
        assert abs(float((c.T[:3, 3] - foot) @ (p1 - p0))) < 1e-9  # perpendicular to the line
        assert np.allclose(c.T[:3, :3] @ c.T[:3, :3].T, np.eye(3), atol=1e-9)
    assert cands[0].direction[2] > 0.0  # the first one up


def test_no_straight_corridor_but_a_via_route_checked_by_brute_force():
    """PA10: the straight route closes on joint 4's limit; a via route exists whose hand path is at most
    1.06 times the line. Brute force over 400 poses of the route: each solved in closed form at the
    schedule's swivel on the start's flip pattern keeps every joint within its limits and moves no joint
    more than 0.1 rad from the pose before; the poses run from the start through the via to the goal,
    continuously."""
    arm = load_arm("pa10")
    T0, T1 = np.asarray(arm.fk(Q_START)), _orthonormal(T_GOAL)
    leg, timer = _legs(arm)
    straight, why = leg(T0, T1, Q_START, None)
    assert straight is None and "joint 4" in why, why
    route, search = plan_via_route(arm, T0, T1, Q_START, MARGIN_SING, MARGIN_LIMIT, leg, timer)
    assert isinstance(route, ViaRoute), search
    assert search.planned <= 3
    us = np.linspace(0.0, 1.0, 401)
    P = np.array([route.pose(float(u))[0] for u in us])
    assert np.allclose(P[0], T0[:3, 3], atol=1e-9) and np.allclose(P[-1], T1[:3, 3], atol=1e-6)
    ratio = float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1)) / np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    assert ratio <= min(route.via.ratio, 1.06) + 1e-6
    assert float(np.max(np.linalg.norm(np.diff(P, axis=0), axis=1))) < 0.01  # continuous
    q_prev = Q_START
    pattern = route.corridor.pattern
    for u in us[1:]:
        pos, rot = route.pose(float(u))
        rows = arm.ik(pose_matrix(pos, rot), route.corridor.swivel_at(float(u)), limits=False)
        q = rows[pattern] + 2.0 * math.pi * np.round((q_prev - rows[pattern]) / (2.0 * math.pi))
        assert np.all(q >= np.asarray(arm.lower) - 1e-9) and np.all(q <= np.asarray(arm.upper) + 1e-9), u
        assert float(np.max(np.abs(q - q_prev))) < 0.1, u
        q_prev = q
    # the progress of a pose on the route is found again (off the corner arc)
    for u in (0.1, 0.3, 0.9):
        assert route.progress_of(*route.pose(u)) == pytest.approx(u, abs=1e-6)
    # the progress is proportional to the path length, the corner arc included (a minimum-jerk profile
    # in progress is one in the hand's speed: a single peak)
    step = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert route.blend > 0.0
    assert float(step.max() / step.min()) < 1.02, (step.min(), step.max())


def test_the_controller_takes_the_via_route_before_the_joint_space_planner():
    """The same goal as a point goal, corridor on: the state names the via and why the straight route
    has none, the hand reaches the goal without re-planning in joint space, its path at most 1.08 times
    the line, its speed single-peaked (no stop at the via)."""
    arm = load_arm("pa10")
    ctl = make_controller(arm, params=ControllerParams.from_dict({"replan": {"corridor": True}}))
    ctl.reset(Q_START)
    T1 = _orthonormal(T_GOAL)
    assert ctl.set_goal(T1).accepted
    ctl._st.corridor_plan.result(timeout=300)  # noqa: SLF001
    pos = [np.asarray(arm.fk(Q_START))[:3, 3]]
    phases, first = set(), None
    for _ in range(3000):
        r = ctl.step(0.01)
        first = first or r.message
        pos.append(np.asarray(r.position))
        phases.add(r.phase)
        if r.phase is Phase.REACHED:
            break
    assert first.startswith("via a pose 0."), first
    assert "m off the line: the straight route has no corridor (" in first, first
    assert "joint 4" in first, first
    assert r.phase is Phase.REACHED and Phase.REPLANNING not in phases
    P = np.array(pos)
    steps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert float(np.sum(steps) / np.linalg.norm(P[-1] - P[0])) <= 1.08
    v = steps / 0.01
    peak = int(np.argmax(v))
    rise, fall = v[: peak + 1], v[peak:]
    assert np.all(np.diff(rise) >= -0.1 * v[peak]) and np.all(np.diff(fall) <= 0.1 * v[peak])
    assert np.all(ctl.q >= arm.lower) and np.all(ctl.q <= arm.upper)


def test_the_progress_is_proportional_to_the_path_length_round_the_corner():
    """A via 1.22 times the line (a sharp corner): the Bezier parameter alone would slow the
    hand at the corner by cos(turn / 2); the route's progress is proportional to the path length, so
    the hand's speed follows the minimum-jerk profile there too."""
    arm = load_arm("pa10")
    T0, T1 = np.asarray(arm.fk(Q_START)), _orthonormal(T_GOAL)
    leg, timer = _legs(arm)
    route, search = plan_via_route(arm, T0, T1, Q_START, MARGIN_SING, MARGIN_LIMIT, leg, timer,
                                   candidates=via_candidates(T0, T1, ratios=(1.22,)))
    assert isinstance(route, ViaRoute), search
    assert route.blend > 0.0
    P = np.array([route.pose(float(u))[0] for u in np.linspace(0.0, 1.0, 2001)])
    step = np.linalg.norm(np.diff(P, axis=0), axis=1)
    assert float(step.max() / step.min()) < 1.02, (step.min(), step.max())


def test_the_swivel_rate_does_not_jump_at_the_via():
    """PowerCube 7 (the straight route closes on a joint limit at u = 0.48): leg 1 keeps its swivel, leg
    2 starts turning at once; the joined schedule is averaged around the via, so the swivel's rate (per
    unit progress) changes there by less than 0.3 between samples 0.0025 apart (1.09 unsmoothed), and
    the joints stay within their limits along it. (Near its end, at u 0.95, leg 2's own schedule has a
    rate wobble of 0.32 over 0.005 between its refined samples.)"""
    arm = load_arm("powercube7")
    q0 = np.array([-0.37709361888665444, 1.203691034840305, -1.5088488971604361, -1.387136491412343,
                   1.5481072196422472, 1.9721170546113633, 0.6283754080940991])
    T1 = _orthonormal(np.array([
        [-0.5250500890049504, -0.8481459330311965, 0.07050447020250004, -0.04661411450594505],
        [-0.818927266068361, 0.4809304886572355, -0.3131517171750985, 0.19094783851262384],
        [0.23169060603678737, -0.2221583700033701, -0.9470824260389125, 0.49295020308385684],
        [0.0, 0.0, 0.0, 1.0]]))
    T0 = np.asarray(arm.fk(q0))
    leg, timer = _legs(arm)
    assert leg(T0, T1, q0, None)[0] is None
    route, search = plan_via_route(arm, T0, T1, q0, MARGIN_SING, MARGIN_LIMIT, leg, timer)
    assert isinstance(route, ViaRoute), search
    us = np.linspace(0.0, 1.0, 401)
    rate = np.diff([route.corridor.swivel_at(float(u)) for u in us]) / np.diff(us)
    near = np.abs(us[1:-1] - route.share) < route.blend + 0.16
    assert float(np.max(np.abs(np.diff(rate))[near])) < 0.3
    Q = route.corridor.q
    assert np.all(Q >= np.asarray(arm.lower) - 1e-9) and np.all(Q <= np.asarray(arm.upper) + 1e-9)


def test_a_paced_via_route_is_kept_only_while_no_single_peaked_one_is_found():
    """A route in the pace (the hand slows where the joints swing and speeds up again: several speed
    peaks) is taken only if no later candidate gives a single-peaked one."""
    arm = load_arm("pa10")
    leg, _ = _legs(arm)
    calls = []
    timing = (0.4, 1.5, 1.0, np.asarray(arm.max_vel), np.asarray(arm.max_acc), 0.7)

    def first_paced(route, length, angle):
        calls.append(route.via)
        return timed_route(route, length, angle, *timing, pace_after=0.0 if len(calls) == 1 else math.inf)

    def all_paced(route, length, angle):
        return timed_route(route, length, angle, *timing, pace_after=0.0)

    T0 = arm.fk(Q_START)
    route, search = plan_via_route(arm, T0, T_GOAL, Q_START, MARGIN_SING, MARGIN_LIMIT, leg, first_paced)
    assert route is not None and route.pace_u is None
    assert len(calls) == 2 and route.via is calls[1] and search.planned == 2
    # with every route paced, the first is taken after all
    route, search = plan_via_route(arm, T0, T_GOAL, Q_START, MARGIN_SING, MARGIN_LIMIT, leg, all_paced)
    assert route is not None and route.pace_u is not None and np.allclose(route.via.T, calls[0].T)
