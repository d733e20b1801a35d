"""The corridor route's clock along the joints' limits and its last margins (control/corridor_route.py):
straight reaches whose joints swing near a singularity or pass near a limit (free-space reaches of
reach_quality_bench, seeds from 3200, that went to the joint-space planner or the attractor before)."""

from __future__ import annotations

import math

import numpy as np
from test_control_corridor import assert_straight_single_peaked

from redarm_ros.control.corridor_route import (
    FALLBACK_LIMIT,
    RouteMargins,
    braking_need,
    fallback_margins,
    fast_clock,
    plan_route,
    route_joints,
)
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.replan import move_time
from redarm_ros.kinematics import load_arm


def _pose(pos, R) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, pos
    return T


#: PA10 (move 42 of free45): the line passes the shoulder axis at |sin q2| ~ 0.4, joint 1 swings about
#: 3 rad. On the minimum-jerk profile in its pace the route took 10.9 s against 1.6 s for a joint-space
#: move (refused: over 4 times and 8 s more)
SLOW_Q0 = np.array([-0.3414294099742463, -0.5231981998188813, -1.741774849994271, 0.47747043956636,
                    2.831804683958578, -2.174592827850643, -3.176603348705207])
SLOW_T = _pose([0.5005842168873313, -0.45531355500980975, 0.8009422673626642],
               [[0.9037564255872971, 0.4118339243242235, 0.11669251040826056],
                [0.4225020076654875, -0.8145220609476993, -0.3975498280066847],
                [-0.0686758817075159, 0.40859103147918197, -0.9101302062158324]])


def test_braking_need_is_the_pace_from_which_a_joint_still_stops_before_its_limit():
    Q = np.array([[0.9, 0.0]])
    acc = np.array([2.0, 2.0])
    limits = (np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
    # towards the upper limit 0.1 rad away: |dq| / sqrt(2 acc d); the other joint 1 rad from either
    need = braking_need(Q, np.array([[1.0, 0.5]]), acc, limits)
    assert math.isclose(float(need[0]), max(1.0 / math.sqrt(0.4), 0.5 / math.sqrt(4.0)))
    # moving away from the near limit: the far one counts (1.9 rad)
    need = braking_need(Q, np.array([[-1.0, 0.0]]), acc, limits)
    assert math.isclose(float(need[0]), 1.0 / math.sqrt(7.6))


def test_the_fallback_margins_loosen_the_limits_and_singularities_only():
    m = RouteMargins(0.05, 0.15, 0.12, 0.15, 4.0)
    f = fallback_margins(m)
    assert f.limit == FALLBACK_LIMIT and f.rate == m.rate
    assert math.isclose(f.shoulder, 0.05) and math.isclose(f.wrist, 0.04) and math.isclose(f.elbow, 0.05)
    assert fallback_margins(RouteMargins(0.01, 0.15, 0.15, 0.15, 1.0)).limit == 0.01  # (never raised)


def test_the_clock_along_the_joints_keeps_their_share_with_one_speed_peak():
    """The slow route on the clock along the joints' limits (fast_clock): sampled at 10 ms, every joint
    keeps its share (0.7) of the velocity limits and its acceleration limits (over the share only where
    the schedule's curvature jumps at a corridor sample), the hand's progress rate rises once and falls
    once, and the route takes less than 5 times the joint-space move (6.8 times on the paced profile)."""
    arm = load_arm("pa10")
    p = ControllerParams()
    rp = p.replan
    max_vel, max_acc = np.asarray(arm.max_vel, float), np.asarray(arm.max_acc, float)
    T0 = np.asarray(arm.fk(SLOW_Q0), float)
    route, why = plan_route(arm, T0, SLOW_T, SLOW_Q0, None, rp.corridor_sing_margin, rp.corridor_limit_margin,
                            p.speed.v_max, p.max_ori_rate, p.swivel.max_rate, max_vel, max_acc,
                            rp.corridor_share, pace_after=9.0, fast=True)
    assert route is not None, why
    q_near, _ = arm.ik_nearest(SLOW_T, SLOW_Q0)
    t_joint = move_time(np.asarray(q_near) - SLOW_Q0, max_vel, max_acc)
    length = float(np.linalg.norm(SLOW_T[:3, 3] - T0[:3, 3]))
    angle = math.sqrt(sum(c * c for c in route.turn))
    clock, duration = fast_clock(arm, route, length, angle, p.speed.v_max, p.max_ori_rate, p.swivel.max_rate,
                                 max_vel, max_acc, rp.corridor_share)
    assert duration < 5.0 * t_joint, (duration, t_joint)
    rate = np.diff(clock)
    top = int(np.argmax(rate))
    assert np.all(np.diff(rate[:top + 1]) >= -1e-9) and np.all(np.diff(rate[top:]) <= 1e-9)
    dt = 0.01
    t = np.arange(0.0, duration + dt, dt)
    u = np.interp(np.minimum(t, duration) / duration, np.linspace(0.0, 1.0, len(clock)), clock)
    Q = route_joints(arm, route, u)
    vel = np.abs(np.diff(Q, axis=0)) / dt
    acc = np.abs(np.diff(Q, n=2, axis=0)) / dt**2
    share = rp.corridor_share
    assert np.all(vel <= 1.02 * share * max_vel), np.max(vel / max_vel, axis=0)
    assert np.all(acc <= max_acc), np.max(acc / max_acc, axis=0)
    assert np.percentile(acc / max_acc, 99) <= 1.05 * share


def test_a_reach_whose_joints_swing_near_the_shoulder_axis_goes_straight():
    """The slow PA10 route (SLOW_Q0): timed along the joints' limits it takes about 7.6 s, under the 9.6 s
    the controller allows (4 times the joint-space move, or 8 s more); the hand goes straight with one
    speed peak (it went to the joint-space planner, hand path 1.03 times the line)."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    ctl.reset(SLOW_Q0)
    assert_straight_single_peaked(arm, ctl, SLOW_Q0, SLOW_T, max_steps=1000)


def test_a_powercube7_reach_through_the_shoulder_singularity_goes_straight():
    """PowerCube 7 (move 64): the route ends near the elbow singularity with joints 1 and 3 swinging
    until the last per cent of the line; it needed 10.7 s on the paced profile against 2.3 s for a
    joint-space move, and takes about 6.4 s timed along the joints."""
    arm = load_arm("powercube7")
    ctl = make_controller(arm)
    q0 = np.array([1.855078085560371, 0.9983548134758402, -2.0496107325780946, -1.4519889909551522,
                   -0.5121599897823828, 1.0712600160487806, 0.5005723921068521])
    ctl.reset(q0)
    T = _pose([-0.1551411579896882, -0.1291698379351304, 0.9204545791433637],
              [[0.8620381080783804, 0.27665436353994577, -0.4246794830868971],
               [0.33441645080903915, 0.3191653211112422, 0.886735098678429],
               [0.3808620979421976, -0.9064192522967863, 0.18261489921910168]])
    assert_straight_single_peaked(arm, ctl, q0, T, max_steps=1000)


def test_a_reach_that_ends_near_a_joint_limit_goes_straight_on_the_fallback_margins():
    """PA10 (move 47): joint 1 ends within 0.05 rad of its limit at every swivel the corridor reaches,
    so the corridor at the limit margin 0.05 closed at u = 0.97 and the attractor did not reach the goal
    in 10 s; at FALLBACK_LIMIT the route is straight, timed so that joint 1 can always stop before its
    limit (the command's limiter never brakes it off the line)."""
    arm = load_arm("pa10")
    ctl = make_controller(arm)
    q0 = np.array([-2.299238864670428, -0.6608738265654199, 1.4731825482828815, 2.159173831202024,
                   0.6173647925675199, -0.6915907343106525, -4.438557540564447])
    ctl.reset(q0)
    T = _pose([0.38642208429136093, -0.5310286109576087, 0.28811345405756494],
              [[0.8207831649234983, -0.5676655501185024, -0.06380297318168726],
               [0.11984630605311353, 0.2803293792006079, -0.9523929347083718],
               [0.5585265070733784, 0.7740615365496855, 0.2981222543366257]])
    assert_straight_single_peaked(arm, ctl, q0, T, max_steps=1000)


def test_a_reach_past_the_shoulder_singularity_goes_straight_on_the_fallback_margins():
    """PowerCube 7 (move 67): at |sin q2| >= 0.15 the corridor closed at u = 0.89 against the limits of
    joints 3 and 5; at a third of the singularity margins the line passes nearer the shoulder axis, and
    the hand goes straight (it went to the joint-space planner)."""
    arm = load_arm("powercube7")
    ctl = make_controller(arm)
    q0 = np.array([-0.43296693368620853, 0.4800423175167746, -2.1492069044178823, -1.6026919236133237,
                   -1.0699911944504734, 1.708629740378882, 2.304317919263421])
    ctl.reset(q0)
    T = _pose([-0.05476754552413922, 0.3225066774701042, 0.9356046087925505],
              [[0.7342716604587949, 0.6408573909127456, -0.22393510926067983],
               [-0.3452625621854835, 0.6365647051380063, 0.6896224614422577],
               [0.5844988381512825, -0.42905382026625927, 0.6886754878131857]])
    assert_straight_single_peaked(arm, ctl, q0, T, max_steps=1100)
