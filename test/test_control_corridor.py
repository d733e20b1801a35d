"""Point goals through the swivel corridor (control/corridor_route.py): straight hand paths at a
minimum-jerk pace where a corridor exists, the joint-space re-planner with the reason where none does."""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
from test_control_replan_shape import READY, speed_peaks

from redarm_ros.control.corridor_route import (
    CLEAR_SAMPLES,
    CorridorRoute,
    plan_route,
    route_clearance,
    route_duration,
    route_joints,
    route_pace,
    smoothed_along,
    timed_route,
)
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.reach_controller import Phase
from redarm_ros.geometry.obstacles import Scene, Sphere, load_scene
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.corridor import SwivelCorridor
from redarm_ros.motion.min_jerk import (
    PEAK_ACC,
    PEAK_RATE,
    min_jerk,
    min_jerk_accel,
    min_jerk_inverse,
    min_jerk_rate,
)


def test_min_jerk_profile_and_its_inverse():
    assert min_jerk(0.0) == 0.0 and min_jerk(1.0) == 1.0 and abs(min_jerk(0.5) - 0.5) < 1e-12
    for u in (0.01, 0.3, 0.77):
        assert abs(min_jerk(min_jerk_inverse(u)) - u) < 1e-9


def test_min_jerk_derivatives_and_peaks_match_the_polynomial():
    x = np.linspace(-0.2, 1.2, 1401)
    u, du, ddu = min_jerk(x), min_jerk_rate(x), min_jerk_accel(x)
    assert u[0] == 0.0 and u[-1] == 1.0 and np.all(np.diff(u) >= 0.0)  # rests outside the move
    inside = (x > 0.01) & (x < 0.99)
    h = x[1] - x[0]
    assert np.allclose(np.gradient(u, h)[inside], du[inside], atol=1e-3)
    assert np.allclose(np.gradient(du, h)[inside], ddu[inside], atol=1e-2)
    assert abs(du.max() - PEAK_RATE) < 1e-9 and abs(np.abs(ddu).max() - PEAK_ACC) < 1e-3
    assert isinstance(min_jerk(0.3), float) and min_jerk(0.3) == float(min_jerk(np.array([0.3]))[0])


def wait_for_plan(ctl):
    """Wait for the worker thread's corridor plan (no wall-clock race in the tests), then step once:
    that step takes the route or the fallback. Returns its result."""
    plan = ctl._st.corridor_plan  # noqa: SLF001
    assert plan is not None
    plan.result(timeout=120)
    return ctl.step(0.01)


def run_to_rest(ctl, T, steps=3000):
    pos, phases, messages = [np.asarray(ctl.arm.fk(ctl.q))[:3, 3]], set(), set()
    for _ in range(steps):
        r = ctl.step(0.01)
        pos.append(np.asarray(r.position))
        phases.add(r.phase)
        messages.add(r.message)
        if r.phase is Phase.REACHED:
            break
    return np.array(pos), phases, messages, r


def test_a_goal_with_a_corridor_goes_straight():
    """PA10 from its park posture to a goal the heading dynamics reaches on a curve (path ratio 1.09
    without the corridor): the hand follows the line (path ratio <= 1.02), never re-plans, and the
    state says so while it moves."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    T = arm.fk(q0 + np.array([0.5, 0.3, -0.2, -0.4, 0.3, 0.2, 0.4]))
    assert ctl.set_goal(T).accepted
    assert ctl._st.message == "planning the straight route through the swivel corridor"  # noqa: SLF001
    wait_for_plan(ctl)
    assert ctl._st.route is not None  # noqa: SLF001 (planned once, for the goal)
    P, phases, messages, r = run_to_rest(ctl, T)
    assert r.phase is Phase.REACHED and Phase.REPLANNING not in phases
    assert ctl._st.route is None  # noqa: SLF001 (REACHED only once the route's tail has run out)
    assert "straight through the swivel corridor" in messages
    d = np.linalg.norm(P[-1] - P[0])
    assert np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1)) / d <= 1.02
    assert np.all(ctl.q >= arm.lower) and np.all(ctl.q <= arm.upper)


def test_a_goal_whose_corridor_is_refused_says_which_route_and_why():
    """The corridor route timed at 1 % of the joint limits is far slower than a joint-space move: the
    goal goes to the attractor dynamics (its straight-route check passes), and the state says so and
    why while the arm moves."""
    arm = load_arm("pa10")
    params = ControllerParams.from_dict({"replan": {"corridor_share": 0.01}})
    ctl = make_controller(arm, params=params)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q0 + np.array([0.5, 0.3, -0.2, -0.4, 0.3, 0.2, 0.4]))).accepted
    r = wait_for_plan(ctl)
    assert ctl._st.route is None  # noqa: SLF001
    assert r.phase is Phase.REACHING
    assert r.message.startswith("attractor dynamics, no swivel corridor: its route needs"), r.message
    assert "a joint-space move" in r.message


def test_corridor_max_slowdown_0_takes_a_slow_corridor_route():
    """The route timed at 1 % of the joint limits (far slower than a joint-space move) is taken when
    ``replan.corridor_max_slowdown`` is 0 (no cap); with the suite's controllers waiting for their plans
    (``wait_for_plans``) the first step after the goal already follows it."""
    arm = load_arm("pa10")
    params = ControllerParams.from_dict({"replan": {"corridor_share": 0.01, "corridor_max_slowdown": 0.0}})
    ctl = make_controller(arm, params=params)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q0 + np.array([0.5, 0.3, -0.2, -0.4, 0.3, 0.2, 0.4]))).accepted
    r = ctl.step(0.01)
    route = ctl._st.route  # noqa: SLF001
    assert route is not None and route.duration > 20.0, r.message
    assert r.message == "straight through the swivel corridor"


def test_a_reference_pose_off_its_joints_is_planned_from_the_joints():
    """The reference pose may be off the pose of the reference joints by the IK step's residual (0.15 mm
    seen in a free-space sequence): the corridor starts from the joints' pose, and the goal goes
    straight (it raised in the worker thread, and the step with it, before)."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    ref = ctl._st.ref  # noqa: SLF001
    ref.pos = (ref.pos[0] + 1.5e-4, ref.pos[1], ref.pos[2])
    assert ctl.set_goal(arm.fk(q0 + np.array([0.5, 0.3, -0.2, -0.4, 0.3, 0.2, 0.4]))).accepted
    r = ctl.step(0.01)
    assert ctl._st.route is not None, r.message  # noqa: SLF001
    assert r.message == "straight through the swivel corridor"


def test_a_route_without_a_corridor_says_why():
    """PowerCube 7: a route that would fold the elbow beyond joint 4's limit at every swivel has no
    corridor route, and the reason names the closing corridor and the joint."""
    arm = load_arm("powercube7")
    T0 = np.eye(4)
    T0[:3, 3] = [0.45, -0.25, 0.3]
    q0, _ = arm.ik_nearest(T0, np.array(arm.park, float))
    T1 = T0.copy()
    T1[:3, 3] = [-0.1, 0.3, 0.3]
    route, why = plan_route(arm, T0, T1, q0, None, 0.15, 0.05, 0.4, 1.5, 1.0, np.asarray(arm.max_vel),
                            np.asarray(arm.max_acc), 0.7)
    assert route is None
    assert "corridor closes" in why and "joint 4" in why, why


def test_a_goal_near_a_limit_or_the_elbow_singularity_keeps_its_corridor():
    """PA10 goals whose joint 4 is 0.02 rad from its limit (every swivel) or 0.02 rad from the elbow
    singularity (|q4|, every swivel): the margins shrink to what the goal keeps, so the corridor reaches
    the goal instead of closing just before it, and the route ends at the goal."""
    arm = load_arm("pa10")
    for q0, q1 in (([0.379, 0.644, -0.085, 1.459, -0.223, 2.166, -1.18], [0.502, 0.242, 0.222, 2.372, 0.522,
                                                                          2.589, -0.873]),
                   ([-0.797, 0.388, 0.142, 0.898, -0.294, 1.503, -4.301], [-0.442, 0.923, -0.053, 0.019,
                                                                           -0.493, 1.279, -3.948])):
        q0 = np.array(q0)
        T0, T1 = np.asarray(arm.fk(q0)), np.asarray(arm.fk(np.array(q1)))
        route, why = plan_route(arm, T0, T1, q0, None, 0.15, 0.05, 0.4, 1.5, 1.0, np.asarray(arm.max_vel),
                                np.asarray(arm.max_acc), 0.7, pace_after=0.0)
        assert route is not None, why
        assert route.corridor.u[-1] == 1.0
        assert np.allclose(np.asarray(arm.fk(route.corridor.q[-1]))[:3, 3], T1[:3, 3], atol=1e-6)


def test_route_progress_of_a_pose():
    route = CorridorRoute((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.5), None, 1.0)
    pos, rot = route.pose(0.25)
    assert math.isclose(route.progress_of(pos, rot), 0.25)


def _swinging_corridor() -> SwivelCorridor:
    """A schedule whose joint 1 swings 2 rad within u 0.45..0.55 (as where the line passes near the
    shoulder singularity) and stands elsewhere; the other joints stand."""
    u = np.linspace(0.0, 1.0, 101)
    q = np.zeros((101, 7))
    q[:, 0] = 2.0 * np.clip((u - 0.45) / 0.1, 0.0, 1.0)
    return SwivelCorridor(True, u, np.zeros(101), q, 0, 1.0, 0.5, None, "", 0.2)


def test_the_pace_slows_the_hand_only_where_the_joints_swing():
    """Joint 1 swinging fast over a tenth of the route: the paced route takes at most half the time of
    the route paced by u (every stretch as slow as the swing), and its progress moves slowly through
    the swing and fast elsewhere."""
    cor = _swinging_corridor()
    vel, acc = np.ones(7), np.full(7, 2.0)
    args = (cor, 0.5, 0.0, 0.4, 1.5, 1.0, vel)
    pace_u = route_pace(*args)
    assert pace_u[0] == 0.0 and pace_u[-1] == 1.0 and np.all(np.diff(pace_u) > 0.0)
    paced = route_duration(*args, acc, 0.7, pace_u)
    by_u = route_duration(*args, acc, 0.7)
    assert paced <= 0.5 * by_u, (paced, by_u)
    route = CorridorRoute((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), cor, paced,
                          pace_u=pace_u)
    t_swing = route.time_at(0.55) - route.time_at(0.45)
    assert t_swing > 0.3 * paced  # a tenth of the line, a third of the time or more
    for t in (0.1, 0.4, 0.8):
        assert math.isclose(route.time_at(route.progress_at(t * paced)), t * paced, abs_tol=1e-6)
    # joint 1 within (about) its share of the velocity limit along the paced profile, stepped at 10 ms
    ts = np.arange(0.0, paced + 1e-9, 0.01)
    q1 = np.interp([route.progress_at(t) for t in ts], cor.u, cor.q[:, 0])
    assert np.max(np.abs(np.diff(q1))) / 0.01 <= 0.75  # share 0.7, checked on PACE_SAMPLES samples


def _offset(u):
    """A bend at u = 0.3 and a sharp peak at u = 0.8."""
    return np.maximum(0.0, u - 0.3) + np.maximum(0.0, 1.0 - np.abs(u - 0.8) / 0.05)


class _OffsetArm:
    """A stand-in for smoothed_along: joint 1 is the swivel less :func:`_offset` of the progress (u in the
    pose's x), the other joints stand clear of the singularities; the lower limits at -3 rad."""

    lower, upper = np.full(7, -3.0), np.full(7, 3.0)

    def ik(self, T, s, limits=False):
        return np.tile([s - float(_offset(T[0, 3])), 1.0, 0.0, 1.0, 0.0, 1.0, 0.0], (8, 1))


def _x_pose(u):
    T = np.eye(4)
    T[0, 3] = u
    return T


def test_the_schedule_is_smoothed_from_the_start_and_kept_only_where_the_average_fails():
    """A schedule that leaves the start at rate 5 (rad per unit progress) for 0.01, bends at u = 0.3 and
    rides joint 1's limit margin (0.1 rad) along a sharp peak at u = 0.8, where its average would pass
    half the margin: the schedule is kept at the peak and smoothed elsewhere, the start's corner too."""
    arm, u, margin = _OffsetArm(), np.linspace(0.0, 1.0, 401), 0.1
    S = -3.0 + margin + _offset(u) + 5.0 * np.minimum(u, 0.01)
    Q = np.stack([arm.ik(_x_pose(x), s)[0] for x, s in zip(u, S, strict=True)])
    cor = SwivelCorridor(True, u, S, Q, 0, 1.0, 0.5, None, "", 0.1)
    out = smoothed_along(arm, _x_pose, cor, margin, 0.1, 0.1)
    rate = np.diff(out.swivel) / np.diff(u)
    assert out.swivel[0] == S[0] and np.max(np.abs(np.diff(rate[:40]))) < 0.1  # no corner after the start
    bend = (u[:-2] > 0.2) & (u[:-2] < 0.4)
    assert np.max(np.abs(np.diff(rate)[bend])) < 0.1  # (1.0 unsmoothed)
    at_peak = np.abs(u - 0.8) < 0.03
    np.testing.assert_allclose(out.swivel[at_peak], S[at_peak])
    assert np.min(out.q[:, 0]) >= -3.0 + 0.5 * margin


def _route_speed(route: CorridorRoute) -> np.ndarray:
    """The hand's speed (m/s) along ``route``, stepped at 10 ms."""
    ts = np.arange(0.0, route.duration + 1e-9, 0.01)
    return np.diff([route.progress_at(t) for t in ts]) * math.dist(route.p0, route.p1) / 0.01


def test_a_slow_swing_mid_route_is_taken_with_one_speed_peak_when_time_allows():
    """Joint 1 swinging fast over a tenth of the route: the pace gives the hand two speed peaks (fast,
    slow through the swing, fast); allowed up to 30 s, the route keeps one peak, in at most 0.6 of the
    time the route paced by u takes, its progress and time consistent and joint 1 within (about) its
    share of the velocity limit; allowed less, it takes the pace."""
    cor = _swinging_corridor()
    vel, acc = np.ones(7), np.full(7, 2.0)
    route = CorridorRoute((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), cor, 0.0)
    timing = (0.5, 0.0, 0.4, 1.5, 1.0, vel, acc, 0.7)
    by_u = route_duration(cor, 0.5, 0.0, 0.4, 1.5, 1.0, vel, acc, 0.7)
    paced = timed_route(route, *timing, pace_after=5.0)
    assert speed_peaks(_route_speed(paced)) == 2 and paced.pace_u is not None
    bell = timed_route(route, *timing, pace_after=30.0)
    assert speed_peaks(_route_speed(bell)) == 1
    assert paced.duration < bell.duration <= min(30.0, 0.6 * by_u), (paced.duration, bell.duration, by_u)
    for t in np.array([0.05, 0.4, 0.8]) * bell.duration:
        assert math.isclose(bell.time_at(bell.progress_at(t)), t, abs_tol=1e-3)
    ts = np.arange(0.0, bell.duration + 1e-9, 0.01)
    q1 = np.interp([bell.progress_at(t) for t in ts], cor.u, cor.q[:, 0])
    assert np.max(np.abs(np.diff(q1))) / 0.01 <= 0.75


def held_corridor_planner() -> tuple[Any, Any, np.ndarray, threading.Event]:
    """(arm, controller with the corridor on, reset at the park posture, gate): the worker thread's plan
    finishes only once the test sets the gate."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    ctl.wait_for_plans = False  # (the node's hold; the suite's controllers wait)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    gate = threading.Event()
    job = ctl.redundancy.corridor_job

    def held_job(st, p, T, scene):
        run = job(st, p, T, scene)
        return lambda: (gate.wait(60), run())[1]

    ctl.redundancy.corridor_job = held_job
    return arm, ctl, q0, gate


def test_the_arm_holds_while_the_corridor_is_planned():
    """The route is planned in a worker thread: the step returns at once, the arm holding at rest and the
    goal REACHING (the progress watch waits), until the plan is there; a stop drops it."""
    arm, ctl, q0, gate = held_corridor_planner()
    assert ctl.set_goal(arm.fk(q0 + np.array([0.5, 0.3, -0.2, -0.4, 0.3, 0.2, 0.4]))).accepted
    for _ in range(150):  # 1.5 s: longer than the progress watch's stall time
        r = ctl.step(0.01)
        assert r.phase is Phase.REACHING and np.array_equal(r.q, q0), r.message
    assert r.message == "planning the straight route through the swivel corridor"
    gate.set()
    wait_for_plan(ctl)
    assert ctl._st.route is not None and ctl.step(0.01).phase is Phase.REACHING  # noqa: SLF001
    ctl.stop()
    assert ctl._st.corridor_plan is None  # noqa: SLF001


def test_a_goal_sent_to_the_re_planner_after_the_corridor_plan_keeps_the_command_continuous():
    """The worker thread finds no corridor worth taking (timed at 1 % of the joint limits: too slow) and
    the straight route passes the shoulder singularity: the step that takes the plan hands the goal to
    the re-planner and commands the arm in that same step (braking it), so joints still moving (an elbow
    settling after the last goal) do not stop within one step."""
    arm = load_arm("pa10")
    ctl = make_controller(arm, params=ControllerParams.from_dict({"replan": {"corridor_share": 0.01}}))
    q0 = np.array([0.8620380935781569, -0.8963437758270911, -2.6761380381656896, 0.37568770912873944,
                   0.3606396759147724, 1.7980185737534031, -0.9225085188112081])
    T = np.eye(4)
    T[:3] = [[-0.7864026088844408, 0.15554465084379385, 0.597810001868175, -0.14455671723072971],
             [0.2676521119540557, 0.9580134846094501, 0.10282271282645966, 0.675608354418444],
             [-0.5567165200587088, 0.24086515916657866, -0.7950161579448431, 0.7900308303521776]]
    ctl.reset(q0)
    qd0 = np.zeros(7)
    qd0[0] = 0.05  # rad/s, more than joint 1 may lose in one step (2 rad/s^2 * 0.01 s)
    ctl._st.cmd.qd = qd0.copy()  # noqa: SLF001
    assert ctl.set_goal(T).accepted
    r = wait_for_plan(ctl)
    assert r.phase is Phase.REPLANNING and "no swivel corridor" in r.message, r.message
    assert "; no via route: " in r.message, r.message  # (and why none)
    qd1 = (r.q - q0) / 0.01
    assert np.all(np.abs(qd1 - qd0) <= np.asarray(arm.max_acc) * 0.01 + 1e-9), qd1


PARK_GOAL = np.array([0.5, 0.3, -0.2, -0.4, 0.3, 0.2, 0.4])  # (rad) the PA10's goal from its park posture


def _line_middle(arm, q0: np.ndarray) -> tuple[float, float, float]:
    """The middle of the hand's line from ``q0`` to the PARK_GOAL offset."""
    a, b = np.asarray(arm.fk(q0))[:3, 3], np.asarray(arm.fk(q0 + PARK_GOAL))[:3, 3]
    return tuple(float(x) for x in 0.5 * (a + b))


def test_a_corridor_planned_while_the_scene_changed_is_planned_again():
    """An obstacle set on the line while the worker thread plans: the route is planned again against the
    new scene and refused there, and the state says why; an equal scene changes nothing."""
    arm, ctl, q0, gate = held_corridor_planner()
    assert ctl.set_goal(arm.fk(q0 + PARK_GOAL)).accepted
    ctl.step(0.01)
    plan = ctl._st.corridor_plan  # noqa: SLF001
    ctl.set_scene(Scene())
    assert ctl._st.corridor_plan is plan  # noqa: SLF001
    ctl.set_scene(Scene(obstacles=(Sphere(_line_middle(arm, q0), 0.03),)))
    assert ctl._st.corridor_plan is not plan  # noqa: SLF001
    gate.set()
    r = wait_for_plan(ctl)
    assert ctl._st.route is None  # noqa: SLF001
    assert "no swivel corridor: its route comes within 0.02 m: the " in r.message, r.message


def test_a_corridor_route_is_left_when_the_scene_changes():
    """The route was checked against the scene it was planned in: a new scene while the hand is on it
    hands the goal to the attractor dynamics, which reaches it."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    T = arm.fk(q0 + PARK_GOAL)
    assert ctl.set_goal(T).accepted
    wait_for_plan(ctl)
    for _ in range(30):
        ctl.step(0.01)
    ctl.set_scene(Scene())
    assert ctl._st.route is not None  # noqa: SLF001 (the same scene)
    ctl.set_scene(Scene(obstacles=(Sphere((-0.6, -0.6, 0.3), 0.05),), table_height=0.0))
    assert ctl._st.route is None  # noqa: SLF001
    assert ctl.step(0.01).message == "the scene changed on the corridor route: attractor dynamics"
    assert run_to_rest(ctl, T)[3].phase is Phase.REACHED


def test_a_table_top_route_is_refused_where_the_elbow_cannot_rest_at_its_end():
    """Near obstacles the route, clear of the table, is still refused where it ends off the preferred
    swivel (the swivel dynamics would turn the elbow on after it): the attractor dynamics, and why."""
    arm = load_arm("pa10")
    ctl = make_controller(arm, load_scene("table_empty"))
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q0 + PARK_GOAL)).accepted
    r = wait_for_plan(ctl)
    assert ctl._st.route is None  # noqa: SLF001
    assert r.message.startswith("attractor dynamics, no swivel corridor: the route ends "), r.message
    assert r.message.endswith("rad from the preferred swivel"), r.message


def test_a_route_from_closer_than_the_clearance_passes_if_it_gets_clear():
    """The hand starts 1 cm above a sphere (the planning clearance is 2 cm) and the route rises from it:
    it passes (an end may be closer as long as the route comes no closer than it)."""
    arm = load_arm("pa10")
    q0 = np.array(arm.park, float)
    ctl = make_controller(arm)
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q0 + PARK_GOAL)).accepted
    wait_for_plan(ctl)
    route, guard = ctl._st.route, ctl.redundancy.guard  # noqa: SLF001
    centre = tuple(np.asarray(arm.fk(q0))[:3, 3] - np.array([0.0, 0.0, 0.1]))
    c = guard.clearance(q0, Scene(obstacles=(Sphere(centre, 0.01),))).distance
    scene = Scene(obstacles=(Sphere(centre, c),))  # (its clearance: c less what the radius grew, 1 cm)
    assert abs(guard.clearance(q0, scene).distance - 0.01) < 1e-9
    assert route_clearance(arm, guard, route, scene, 0.02).distance >= 0.02
    assert route_clearance(arm, guard, route, scene, 0.005).distance >= 0.005


def test_a_corridor_route_into_an_obstacle_is_refused():
    """A sphere on the line: the route is refused with what it would hit, and the attractor dynamics
    takes the goal."""
    arm = load_arm("pa10")
    q0 = np.array(arm.park, float)
    ctl = make_controller(arm, Scene(obstacles=(Sphere(_line_middle(arm, q0), 0.03),), table_height=0.0))
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q0 + PARK_GOAL)).accepted
    r = wait_for_plan(ctl)
    assert ctl._st.route is None and r.phase is Phase.REACHING  # noqa: SLF001
    assert r.message.startswith("attractor dynamics, no swivel corridor: its route comes within 0.02 m: "
                                "the "), r.message
    assert r.message.endswith("of obstacle 0")


def test_route_clearance_finds_the_nearest_approach_between_samples():
    """The check halves the intervals until nothing between the samples can come closer: against a
    sphere below the line (nearest the arm between two of its first samples), the route passes at a
    margin just below the least clearance of 2001 samples and fails just above it."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    q0 = np.array(arm.park, float)
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q0 + PARK_GOAL)).accepted
    wait_for_plan(ctl)
    route = ctl._st.route  # noqa: SLF001
    x = 32.5 / (CLEAR_SAMPLES - 1)
    pos = np.asarray(route.pose(x)[0]) + np.array([0.0, 0.0, -0.12])
    scene = Scene(obstacles=(Sphere(tuple(pos), 0.02),))
    dense = min(ctl.redundancy.guard.clearance(q, scene).distance
                for q in route_joints(arm, route, np.linspace(0.0, 1.0, 2001)))
    assert 0.0 < dense < 0.1
    assert route_clearance(arm, ctl.redundancy.guard, route, scene, dense - 0.002).distance >= dense - 0.002
    assert route_clearance(arm, ctl.redundancy.guard, route, scene, dense + 0.002).distance < dense + 0.002


def _pose(pos, R) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, pos
    return T


def _straight_move(q0, T):
    """The PA10 from q0 to T with the default parameters: the messages, the hand path ratio, the
    commanded joints kept within the limits, and whether it re-planned."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    ctl.reset(np.array(q0))
    assert ctl.set_goal(T).accepted
    r = wait_for_plan(ctl)
    P, phases, messages, r_end = run_to_rest(ctl, T)
    qs_ok = bool(np.all(ctl.q >= arm.lower) and np.all(ctl.q <= arm.upper))
    ratio = np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1)) / np.linalg.norm(P[-1] - P[0])
    return r.message, r_end.phase, Phase.REPLANNING in phases, ratio, qs_ok



def assert_straight_single_peaked(arm, ctl, q0: np.ndarray, T: np.ndarray, max_steps: int) -> None:
    """From ``q0`` (the controller reset there), the goal ``T`` is reached by the straight corridor
    route: hand path ratio at most 1.05 and one hand speed peak."""
    assert ctl.set_goal(T).accepted
    assert wait_for_plan(ctl).message == "straight through the swivel corridor"
    qs = [q0]
    for _ in range(max_steps):
        r = ctl.step(0.01)
        qs.append(r.q)
        if r.phase is Phase.REACHED:
            break
    assert r.phase is Phase.REACHED
    P = arm.fk_batch(np.array(qs))[:, :3, 3]
    v = np.linalg.norm(np.diff(P, axis=0), axis=1) / 0.01
    assert np.sum(v) * 0.01 / np.linalg.norm(P[-1] - P[0]) <= 1.05
    assert speed_peaks(v) == 1


def test_a_slow_straight_route_is_made_fast_enough_by_the_speed_guide():
    """A reach whose line passes the elbow and shoulder singularities nearby: on the schedule nearest the
    start swivel the route needs about 12 s, over 4 times a joint-space move (2.5 s), and went to the
    planner; on the speed guide it takes about 8 s and the hand goes straight."""
    q0 = [-2.6524096455753536, -1.271125332459373, 0.8874459085435809, 1.0575023737399984,
          0.9537533074667197, 1.9527283615415267, 0.7299905983189493]
    T = _pose([-0.689115967142905, -0.3338769899360669, 0.8144093287119364],
              [[0.43540169321890965, 0.8643461080329122, -0.2516568518249873],
               [0.8139034536158053, -0.49740856867823924, -0.30024304154756004],
               [-0.3846901788899362, -0.07409805215943492, -0.9200668154714671]])
    message, phase, replanned, ratio, within = _straight_move(q0, T)
    assert message == "straight through the swivel corridor", message
    assert phase is Phase.REACHED and not replanned and ratio <= 1.05 and within


def test_a_route_whose_schedule_bends_sharply_keeps_one_speed_peak():
    """A PA10 reach whose schedule leaves the start at the swivel's rate bound and bends where the rate
    bound ends: the command could not follow the corners within the joints' acceleration limits (the
    hand's speed had 10 peaks); smoothed from the start and between samples, the hand goes straight
    with one speed peak."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    q0 = np.array([2.6658949544843136, -0.9060346603831069, -2.6631937104629557, 0.6793788223681327,
                   1.425603890627079, -2.289605722707155, 0.19091811029233297])
    ctl.reset(q0)
    T = _pose([-0.1664671342110127, -0.33995906338033893, 0.749007192012173],
              [[-0.015535727475606831, -0.2107575665469273, -0.9774149013162329],
               [-0.9988798993342904, -0.040424108127071326, 0.024593458236865262],
               [-0.04469438306679345, 0.9767021754994449, -0.20989347892902813]])
    assert_straight_single_peaked(arm, ctl, q0, T, max_steps=1200)


def test_a_route_from_the_ready_posture_keeps_one_speed_peak():
    """PA10 from its ready posture, the line passing near the shoulder singularity: where the schedule
    bends, joints 1 and 3 follow the swivel many times over; the straight route's schedule smoothed over
    STRAIGHT_WINDOW keeps them within the command's acceleration limits (at 0.08 the hand's speed had 2
    peaks), so the hand goes straight with one speed peak."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    ctl.reset(READY)
    T = _pose([0.3929507043394475, 0.7600314115756154, 0.4594049181314856],
              [[-0.8569785693731684, 0.3889759611626206, 0.33806128626734644],
               [0.4114140926630704, 0.911430263123888, -0.005772332296615619],
               [-0.31036458559787383, 0.13413641228069073, -0.9411063951047854]])
    assert_straight_single_peaked(arm, ctl, READY, T, max_steps=1000)
