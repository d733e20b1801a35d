"""Re-planner: route check, goal configurations, joint-path search and timing; the IK step's
continuity rule; goal sequences in-process (never stuck)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.elbow import ArmGeometry
from redarm_ros.control.guard import CollisionGuard
from redarm_ros.control.ik_step import DeadEnd, IKStepper, pose_matrix
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams, ReplanParams
from redarm_ros.control.reach_controller import Phase
from redarm_ros.control.replan import (
    JointPath,
    JointPlanner,
    check_route,
    fold_posture,
    goal_candidates,
    move_time,
)
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, Sphere, load_scene, min_distance
from redarm_ros.kinematics import load_arm

ARM = load_arm("pa10")
GEOM = ArmGeometry.from_arm(ARM)
DT = 0.01
READY = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])


def stepper() -> IKStepper:
    return IKStepper(ARM, GEOM, 10.0, 0.03, 10)


def guard() -> CollisionGuard:
    return CollisionGuard(ARM, ArmCapsules(), 0.0, 0.005)


def check_limits(q: np.ndarray, from_rest: bool = True) -> None:
    assert np.all(q >= ARM.lower - 1e-12) and np.all(q <= ARM.upper + 1e-12)
    assert (np.abs(np.diff(q, axis=0)) / (np.asarray(ARM.max_vel) * DT)).max() <= 1.0 + 1e-6
    qq = np.vstack([q[:1], q]) if from_rest else q
    assert (np.abs(np.diff(qq, n=2, axis=0)) / (np.asarray(ARM.max_acc) * DT * DT)).max() <= 1.0 + 1e-6


# ------------------------------------------------------------------------------------------------
def test_select_takes_the_two_pi_copy_of_a_wide_joint_nearest_the_previous() -> None:
    st = stepper()
    q_prev = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 5.9])  # joint 7 beyond pi
    sols = np.array([[0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 5.9 - 2 * math.pi]])  # ik's copy nearest 0
    q, ratio = st.select(sols, q_prev, DT)
    assert q[6] == pytest.approx(5.9) and ratio == pytest.approx(0.0)


def test_swivel_search_stops_at_the_limit_edge_not_a_whole_step_beyond() -> None:
    """Joint 5 exactly at its lower limit: a hair further in swivel there is no in-limit solution on the
    branch. The search finds the in-limit swivel nearest the one asked for, not one a whole search step
    (0.03 rad) back: that jump, taken as the elbow's rate, swung the elbow off and the hand 15 mm off its
    goal after REACHED."""
    st = stepper()
    q = np.array([1.5458, -1.0662, 0.8798, 0.9728, ARM.lower[4], 0.3743, 2.5382])
    T, s0 = ARM.fk(q), ARM.swivel(q)
    blocked = st.solve(T, s0 + 0.001, q, DT)
    assert blocked is None or blocked[1] > st.flip_ratio  # (the situation: no continuous solution there)
    pick, s = st._search_swivel(T, s0 + 0.001, q, DT)
    assert pick is not None
    assert -1e-3 < s - s0 <= 0.0  # at the edge, within 1 mrad (0.03 / 2^8 = 1.2e-4 rad)
    assert pick[1] <= 1.0  # a step within the velocity limits
    assert np.all(pick[0] >= ARM.lower) and np.all(pick[0] <= ARM.upper)


def test_limit_probe_sees_a_wide_joints_limit_not_its_copy_two_pi_away() -> None:
    """Joint 5 (range 8.9 rad) 1 mrad inside its lower limit: a swivel step towards the limit takes it
    beyond, where the probe must see a negative margin (the swivel brakes in time), not the in-limit
    copy of the joint 2 pi away, or another branch, far from any limit."""
    st = stepper()
    q = np.array([1.5458, -1.0662, 0.8798, 0.9728, ARM.lower[4] + 1e-3, 0.3743, 2.5382])
    T, s0 = ARM.fk(q), ARM.swivel(q)
    m0, m_plus, m_minus = st.limit_margins(T, s0, q, 0.02, 0.3)
    assert m0 == pytest.approx(1e-3)
    assert m_plus < 0.0 < m0 < m_minus  # towards the limit (+ swivel here) and away from it


def test_limit_probe_sees_a_narrow_joints_limit_not_another_branch() -> None:
    """Joint 1 (range under 2 pi) 0.5 mrad inside its upper limit, a swivel step taking it beyond: the
    probe must see a negative margin there. Among the in-limit solutions only, that branch was gone
    and another one (0.6 rad from every limit) looked like open space: the limit force pushed the
    elbow into the limit, where it balanced the attraction to a false rest (REACHED), then swung
    0.5 rad once the hand had crept off the limit (sequence benchmark, table_cylinder)."""
    st = stepper()
    q = np.array([ARM.upper[0] - 5e-4, -0.4313, -2.979, 1.0728, 1.9667, 2.2615, -4.6924])
    T, s0 = ARM.fk(q), ARM.swivel(q)
    m0, m_plus, m_minus = st.limit_margins(T, s0, q, 0.02, 0.3)
    assert m0 == pytest.approx(5e-4)
    assert m_minus < 0.0 < m0 < m_plus  # towards the limit (- swivel here) and away from it


def test_advance_shortens_a_step_that_is_too_fast_and_reports_dead_ends() -> None:
    st = stepper()
    T0 = ARM.fk(READY)
    pos0 = tuple(T0[:3, 3])
    from redarm_ros.kinematics.quaternion import quat_from_matrix

    rot0 = quat_from_matrix(T0[:3, :3])
    s0 = ARM.swivel(READY)
    far = (pos0[0], pos0[1] + 0.05, pos0[2])  # 5 cm in one 10 ms step: 5 m/s
    out = st.advance(pos0, rot0, s0, READY, far, rot0, DT, lambda c, T, s: (s0, s0, False))
    assert not isinstance(out, DeadEnd)
    assert out.speed_scale < 1.0
    assert np.max(np.abs(out.q - READY) / (np.asarray(ARM.max_vel) * DT)) <= 1.0 + 1e-9
    # Joint 1 at its limit, the hand asked to go on around the base: no continuous solution.
    q_lim = READY.copy()
    q_lim[0] = ARM.upper[0]
    T = ARM.fk(q_lim)
    p = tuple(T[:3, 3])
    r = quat_from_matrix(T[:3, :3])
    a = math.atan2(p[1], p[0]) + 0.05
    rad = math.hypot(p[0], p[1])
    beyond = (rad * math.cos(a), rad * math.sin(a), p[2])
    s = ARM.swivel(q_lim)
    out = st.advance(p, r, s, q_lim, beyond, r, 1.0, lambda c, T_, s_: (s, s, False))
    assert isinstance(out, DeadEnd) and "continuous" in out.reason


# Found by a seeded search: the straight route from Q_DEAD_0 to the pose of Q_DEAD_1 folds the
# elbow (joint 4) onto its limit a quarter of the way.
Q_DEAD_0 = np.array([-0.276, 0.847, -1.472, -1.928, -0.765, -1.563, -4.628])
Q_DEAD_1 = np.array([0.447, -0.575, 0.94, -1.293, 3.542, -0.699, -4.462])


def test_check_route_finds_a_dead_end_and_passes_an_open_route() -> None:
    s0 = ARM.swivel(Q_DEAD_0)
    route = check_route(
        stepper(), ARM.fk(Q_DEAD_0), s0, Q_DEAD_0, ARM.fk(Q_DEAD_1), lambda c: s0, 40, 0.4, 1.5, 1.0
    )
    assert "no continuous in-limit solution" in route.dead_end and "joint 4" in route.dead_end
    assert math.isinf(route.time)
    ok = check_route(
        stepper(),
        ARM.fk(READY),
        ARM.swivel(READY),
        READY,
        pose_matrix((0.6, 0.1, 0.3), (0.0, 1.0, 0.0, 0.0)),
        lambda c: ARM.swivel(READY),
        40,
        0.4,
        1.5,
        1.0,
    )
    assert ok.dead_end == "" and ok.q_end is not None and math.isfinite(ok.time)


def test_goal_candidates_are_exact_in_limits_free_and_cheapest_first() -> None:
    scene = load_scene("table_cylinder")
    T = ARM.fk(np.array([0.4, 0.9, -0.3, 1.2, 0.5, 0.9, 2.0]))
    cands = goal_candidates(stepper(), guard(), T, READY, scene, ReplanParams(), None)
    assert len(cands) >= 3
    costs = [c.cost for c in cands]
    assert costs == sorted(costs)
    for c in cands:
        assert np.allclose(ARM.fk(c.q), T, atol=1e-9)
        assert np.all(c.q >= ARM.lower) and np.all(c.q <= ARM.upper)
        assert min_distance(ARM, c.q, scene).distance >= ReplanParams().clearance
    # the cheapest is no slower to reach than ik_nearest's answer
    q_near, _ = ARM.ik_nearest(T, READY)
    mv = move_time(q_near - READY, np.asarray(ARM.max_vel), np.asarray(ARM.max_acc))
    assert move_time(cands[0].q - READY, np.asarray(ARM.max_vel), np.asarray(ARM.max_acc)) <= mv + 0.3


def test_joint_path_timing_respects_the_limits_and_ends_at_rest_on_the_goal() -> None:
    pts = [
        READY,
        np.array([1.0, 0.2, -0.5, 0.8, 2.0, 0.5, -3.0]),
        np.array([-0.5, 0.9, 0.3, 1.9, -1.0, 1.2, 4.0]),
    ]
    path = JointPath(pts, np.asarray(ARM.max_vel), np.asarray(ARM.max_acc))
    ts = np.arange(0.0, path.duration + 0.05, DT)
    q = np.array([path.sample(t)[0] for t in ts])
    check_limits(q)
    assert np.allclose(q[-1], pts[-1]) and np.allclose(path.sample(path.duration)[1], 0.0)
    # each segment is a straight line in joint space through the waypoints: every sample lies on one
    def off_path(qi: np.ndarray) -> float:
        d = math.inf
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            t = min(max(float(np.dot(qi - a, b - a) / np.dot(b - a, b - a)), 0.0), 1.0)
            d = min(d, float(np.linalg.norm(qi - (a + t * (b - a)))))
        return d

    assert max(off_path(qi) for qi in q) < 1e-9
    assert min(np.max(np.abs(qi - pts[1])) for qi in q) < 1e-3  # ... through the middle waypoint


def test_planner_goes_around_an_obstacle_in_the_direct_joint_path() -> None:
    q_start = np.array([0.9, 0.8, 0.0, 1.4, 0.0, 0.9, 0.0])
    q_goal = np.array([-0.9, 0.8, 0.0, 1.4, 0.0, 0.9, 0.0])
    mid = ARM.key_points(0.5 * (q_start + q_goal))
    scene = Scene((Sphere(tuple(0.5 * (mid[2] + mid[3])), 0.06, "ball"),), 0.0)
    g = guard()
    assert g.segment_clearance(q_start, q_goal, scene, 0.02) is None
    planner = JointPlanner(stepper(), g, scene, q_start, ARM.fk(q_goal), ReplanParams(), (0.4, 1.2, 1.0))
    for _ in range(2000):
        if planner.work():
            break
    assert planner.path is not None, planner.reason
    assert len(planner.path) >= 3  # not the direct segment
    assert np.allclose(ARM.fk(planner.path[-1]), ARM.fk(q_goal), atol=1e-9)
    for a, b in zip(planner.path[:-1], planner.path[1:], strict=True):
        for t in np.linspace(0, 1, 100):
            assert min_distance(ARM, a + t * (b - a), scene).distance >= 0.02 - 1e-9


def test_planner_reports_why_when_the_goal_is_walled_in() -> None:
    T = ARM.fk(np.array([0.0, 0.9, 0.0, 1.2, 0.0, 1.0, 0.0]))
    p = T[:3, 3]
    walls = tuple(
        Sphere(tuple(p + 0.16 * np.array(d)), 0.1, f"w{i}")
        for i, d in enumerate([(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1)])
    )
    planner = JointPlanner(
        stepper(), guard(), Scene(walls, 0.0), READY, T, ReplanParams(vias=20), (0.4, 1.2, 1.0)
    )
    for _ in range(5000):
        if planner.work():
            break
    assert planner.path is None and planner.reason


def test_fold_posture_keeps_yaw_and_rolls() -> None:
    q = np.array([1.2, 0.9, -0.4, 1.1, 0.3, 1.3, 2.0])
    f = fold_posture(q, (0.4, 1.2, 1.0), ARM.lower, ARM.upper)
    assert f[0] == q[0] and f[2] == q[2] and f[4] == q[4] and f[6] == q[6]
    assert (f[1], abs(f[3]), abs(f[5])) == pytest.approx((0.4, 1.2, 1.0))


# ------------------------------------------------------------------------------------------------
# the controller: never stuck
# ------------------------------------------------------------------------------------------------
def random_goals(scene: Scene, rng: np.random.Generator, n: int) -> list[np.ndarray]:
    probe = make_controller(ARM, scene)
    out = []
    while len(out) < n:
        q = rng.uniform(ARM.lower, ARM.upper)
        if min_distance(ARM, q, scene).distance < 0.02:
            continue
        T = ARM.fk(q)
        if probe.check_goal(T).accepted:
            out.append(T)
    return out


@pytest.mark.parametrize("scene_name", ["table_empty", "table_cylinder"])
def test_goal_sequences_from_random_postures_are_all_reached(scene_name: str) -> None:
    """Seeded sequences of goals from random in-limit postures (any orientation, both elbow
    branches, wide joints anywhere), one after the other without a reset: each is reached within
    10 s, collision-free, within every joint limit. Before the re-planner, 14 of 50 such goals were
    reached (the rest held in dead ends)."""
    scene = load_scene(scene_name)
    rng = np.random.default_rng(31 if scene_name == "table_empty" else 32)
    goals = random_goals(scene, rng, 6)
    ctl = make_controller(ARM, scene)
    ctl.reset(READY)
    qs = [ctl.q]
    for T in goals:
        assert ctl.set_goal(T).accepted
        for _ in range(1000):
            r = ctl.step(DT)
            qs.append(r.q)
            if r.phase is Phase.REACHED:
                break
        assert r.phase is Phase.REACHED, r.message
        assert np.allclose(ARM.fk(r.q)[:3, 3], T[:3, 3], atol=1e-3)
    q = np.array(qs)
    check_limits(q)
    assert min(min_distance(ARM, qi, scene).distance for qi in q) >= 0.0


@pytest.mark.parametrize("seed", [31, 33, 34])
def test_reached_means_the_arm_stays_at_the_goal(seed: int) -> None:
    """A user acts on REACHED (grasps, measures, sends the next goal later): for 2 s after it, with
    nothing new asked, the phase stays REACHED, the commanded hand stays within pos_tolerance of the
    goal and no joint turns faster than 10 % of its limit. Before, REACHED came when a joint-space move
    ended, and the elbow then swung to its preferred swivel at full joint speed: the phase went back to
    REACHING in 40-70 % of such goals, and the commanded hand left the goal by up to 12 cm."""
    scene = load_scene("table_empty")
    goals = random_goals(scene, np.random.default_rng(seed), 5)
    ctl = make_controller(ARM, scene)
    ctl.reset(READY)
    vmax = np.asarray(ARM.max_vel)
    for i, T in enumerate(goals):
        assert ctl.set_goal(T).accepted
        for _ in range(1500):
            r = ctl.step(DT)
            if r.phase is Phase.REACHED:
                break
        assert r.phase is Phase.REACHED, (i, r.message)
        q_prev = r.q
        for k in range(int(2.0 / DT)):
            r = ctl.step(DT)
            assert r.phase is Phase.REACHED, (i, k, r.phase, r.message)
            assert r.distance_to_goal <= ctl.params.pos_tolerance, (i, k, r.distance_to_goal)
            assert np.max(np.abs(r.q - q_prev) / DT / vmax) <= 0.1 + 1e-9, (i, k)
            q_prev = r.q


@pytest.mark.parametrize("corridor", [False, True])
def test_a_dead_end_is_reported_at_once_and_left_by_a_joint_move(corridor: bool) -> None:
    """The straight route folds the elbow onto its limit: the controller says so at the first step,
    the reason in the message, and reaches the goal. Without the corridor (the attractor's route
    check) it moves in joint space (REPLANNING); with it (the default) the straight route has no
    corridor for the same reason, and the hand goes round through a via pose instead."""
    ctl = make_controller(ARM, Scene(), ControllerParams.from_dict({"replan": {"corridor": corridor}}))
    ctl.reset(Q_DEAD_0)
    T = ARM.fk(Q_DEAD_1)
    assert ctl.set_goal(T).accepted
    first = ctl.step(DT)
    assert "joint 4" in first.message, first.message
    if corridor:
        assert first.phase is Phase.REACHING and first.message.startswith("via a pose"), first.message
    else:
        assert first.phase is Phase.REPLANNING
    qs = [first.q]
    for _ in range(1000):
        r = ctl.step(DT)
        qs.append(r.q)
        if r.phase is Phase.REACHED:
            break
    assert r.phase is Phase.REACHED
    assert np.allclose(ARM.fk(r.q)[:3, 3], T[:3, 3], atol=1e-3)
    check_limits(np.array(qs))


def test_a_wound_up_base_joint_is_no_trap() -> None:
    """Joint 1 at +170 deg, the goal at -170 deg (the same place behind the arm the other way
    round): reached within 10 s; when the controller re-plans it says why."""
    q0 = READY.copy()
    q0[0] = math.radians(170)
    q_goal = READY.copy()
    q_goal[0] = math.radians(-170)
    ctl = make_controller(ARM, Scene((), 0.0))
    ctl.reset(q0)
    ctl.set_goal(ARM.fk(q_goal))
    for _ in range(1000):
        r = ctl.step(DT)
        assert r.phase is not Phase.REPLANNING or r.message
        if r.phase is Phase.REACHED:
            break
    assert r.phase is Phase.REACHED


def test_a_trapped_arm_says_why_and_holds() -> None:
    """Three rings of balls around the forearm (clear of it by 12 mm): no motion gets it out. The
    controller says why within a second (the guard's stops, then REPLANNING with the reason), finds no
    joint path, reports BLOCKED with the reason and holds; no command enters a ball."""
    kp = ARM.key_points(READY)
    a, b = kp[2], kp[3]
    d = (b - a) / np.linalg.norm(b - a)
    u = np.cross(d, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    r = 0.05
    ring = ArmCapsules().radii[2] + r + 0.012
    balls = tuple(
        Sphere(tuple(a + f * (b - a) + ring * (math.cos(t) * u + math.sin(t) * v)), r, f"c{i}")
        for i, (f, t) in enumerate(
            (f, t) for f in (0.3, 0.5, 0.7) for t in np.linspace(0.0, 2 * math.pi, 7)[:-1]
        )
    )
    scene = Scene(balls, 0.0)
    assert min_distance(ARM, READY, scene).distance > 0.01
    ctl = make_controller(ARM, scene, ControllerParams(replan=ReplanParams(vias=40)))
    ctl.reset(READY)
    assert ctl.set_goal(ARM.fk(np.array([1.2, 0.8, 0.0, 1.4, 0.0, 0.9, 0.0]))).accepted
    seen = []
    qs = [ctl.q]
    for k in range(1500):
        r_ = ctl.step(DT)
        seen.append((k * DT, r_.phase, r_.message))
        qs.append(r_.q)
        if r_.phase is Phase.BLOCKED:
            break
    assert r_.phase is Phase.BLOCKED and "no collision-free joint path" in r_.message
    said = next(t for t, ph, m in seen if ph in (Phase.HOLDING, Phase.REPLANNING) and m)
    assert said <= 1.0
    assert min(min_distance(ARM, q, scene).distance for q in qs) >= 0.0
    for _ in range(50):
        again = ctl.step(DT)
    assert again.phase is Phase.BLOCKED and np.max(np.abs(again.q - r_.q)) < 1e-3


def test_stall_reason_is_a_function_of_the_state_and_the_parameters() -> None:
    """The stall detector reads the controller state and the parameters it is given, nothing else: an
    overdue point goal is a reason to re-plan, unless re-planning is off; other modes are never stalled."""
    from redarm_ros.control.replan_law import stall_reason
    from redarm_ros.control.state import Mode

    ctl = make_controller(ARM, params=ControllerParams.from_dict({"replan": {"corridor": False}}))
    q0 = np.array([0.0, 0.5, 0.0, 1.2, 0.0, 0.8, 0.0])
    ctl.reset(q0, now=0.0)
    T = ARM.fk(q0 + np.array([0.6, 0.3, 0.0, -0.4, 0.0, 0.2, 0.0]))
    assert ctl.set_goal(T).accepted
    st = ctl._st
    assert st is not None and st.mode is Mode.ATTRACTOR
    st.time = st.progress.due + 1.0
    assert stall_reason(st, ctl.params).startswith("overdue:")
    assert st.progress.t_last == st.time  # the progress was tracked
    off = ctl.params.with_(replan=ReplanParams(enabled=False))
    assert stall_reason(st, off) == ""
    st.mode = Mode.SERVO
    assert stall_reason(st, ctl.params) == ""
