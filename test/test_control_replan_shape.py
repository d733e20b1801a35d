"""The joint-space re-plan's shape: the goal configuration whose straight joint segment gives the
straightest hand path (among the cheap ones), and the minimum-jerk timing of the joint path."""

from __future__ import annotations

import numpy as np
import pytest

from redarm_ros.control import replan
from redarm_ros.control.elbow import ArmGeometry
from redarm_ros.control.guard import CollisionGuard
from redarm_ros.control.ik_step import IKStepper
from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams, ReplanParams
from redarm_ros.control.reach_controller import Phase
from redarm_ros.control.replan import (
    JointPath,
    bend_search,
    bent_points,
    goal_candidates,
    move_time,
    paced_bend,
)
from redarm_ros.geometry.obstacles import ArmCapsules, Scene
from redarm_ros.kinematics import load_arm

ARM = load_arm("pa10")
READY = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])
DT = 0.01


def hand_ratio(q0: np.ndarray, q1: np.ndarray, samples: int = 200) -> float:
    """The hand's path length over its straight distance on the joint segment q0 -> q1."""
    P = np.array([ARM.fk(q0 + x * (q1 - q0))[:3, 3] for x in np.linspace(0.0, 1.0, samples)])
    return float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1)) / np.linalg.norm(P[-1] - P[0]))


def test_the_cheapest_goal_configuration_bends_the_hand_path_least(monkeypatch: pytest.MonkeyPatch) -> None:
    # from the ready pose the fastest goal configuration swings the hand 60 % longer than the line; one on
    # another swivel a fraction of a second slower keeps it within 20 %
    T = ARM.fk(np.array([0.03, 0.17, 3.01, 1.4, 1.09, 2.82, -3.58]))
    stepper = IKStepper(ARM, ArmGeometry.from_arm(ARM), 10.0, 0.03, 10)
    guard = CollisionGuard(ARM, ArmCapsules(), 0.0, 0.005)
    cands = goal_candidates(stepper, guard, T, READY, Scene(), ReplanParams(), None)
    assert cands and np.allclose(ARM.fk(cands[0].q), T, atol=1e-9)
    assert np.all(cands[0].q >= ARM.lower) and np.all(cands[0].q <= ARM.upper)
    assert hand_ratio(READY, cands[0].q) < 1.2
    monkeypatch.setattr(replan, "GOAL_BEND_COST", 0.0)  # by the move's time alone
    fastest = goal_candidates(stepper, guard, T, READY, Scene(), ReplanParams(), None)[0]
    assert hand_ratio(READY, fastest.q) > 1.5
    assert move_time(cands[0].q - READY, ARM.max_vel, ARM.max_acc) \
        < move_time(fastest.q - READY, ARM.max_vel, ARM.max_acc) + 1.0


def test_joint_path_segments_are_minimum_jerk_within_the_limits() -> None:
    q1 = np.array([1.0, 0.2, -0.5, 0.8, 2.0, 0.5, -3.0])
    path = JointPath([READY, q1], np.asarray(ARM.max_vel), np.asarray(ARM.max_acc))
    ts = np.arange(0.0, path.duration + DT, DT)
    q = np.array([path.sample(t)[0] for t in ts])
    assert np.all(np.abs(np.diff(q, axis=0)) <= np.asarray(ARM.max_vel) * DT)
    assert np.all(np.abs(np.diff(np.vstack([q[:1], q]), n=2, axis=0)) <= np.asarray(ARM.max_acc) * DT * DT)
    assert np.allclose(q[-1], q1)
    # the bell of a minimum-jerk move: no jump of acceleration at the ends (a trapezoid starts at full
    # acceleration), the peak rate 1.875 times the mean at half time
    speed = np.array([np.linalg.norm(path.sample(t)[1]) for t in ts])
    mean = np.linalg.norm(q1 - READY) / path.duration
    assert speed[int(0.05 * len(ts))] < 0.05 * speed.max()
    assert abs(np.linalg.norm(path.sample(0.5 * path.duration)[1]) / mean - 1.875) < 1e-6
    # and as fast as the limits allow: the slowest joint reaches 95 % of its velocity or acceleration
    qd = np.array([path.sample(t)[1] for t in ts])
    use = max(float(np.max(np.abs(qd) / np.asarray(ARM.max_vel))),
              float(np.max(np.abs(np.diff(qd, axis=0)) / DT / np.asarray(ARM.max_acc))))
    assert 0.9 < use <= 0.95 + 1e-6


def test_bend_search_shortens_the_hand_path_within_the_limits() -> None:
    q1 = np.array([0.03, 0.17, 3.01, 1.4, 1.09, 2.82, -3.58])
    search = bend_search(ARM, READY, q1, np.asarray(ARM.lower), np.asarray(ARM.upper))
    while True:
        try:
            next(search)
        except StopIteration as stop:
            bend, straight, bent = stop.value
            break
    assert straight == pytest.approx(hand_ratio(READY, q1), abs=0.02)
    assert bent < straight - 0.1
    s = np.linspace(0.0, 1.0, 1001)
    C = bent_points(READY, q1, bend, s)
    assert np.allclose(C[0], READY) and np.allclose(C[-1], q1)
    assert np.all(C >= ARM.lower) and np.all(C <= ARM.upper)
    P = ARM.fk_batch(C)[:, :3, 3]
    assert np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1)) / np.linalg.norm(P[-1] - P[0]) < bent + 0.01
    # the bent segment as a JointPath: on the curve, within the limits, at rest at its ends
    shape = paced_bend(ARM, READY, q1, bend)
    path = JointPath([READY, q1], np.asarray(ARM.max_vel), np.asarray(ARM.max_acc), bends=[shape])
    ts = np.arange(0.0, path.duration + DT, DT)
    q = np.array([path.sample(t)[0] for t in ts])
    assert np.all(np.abs(np.diff(q, axis=0)) <= np.asarray(ARM.max_vel) * DT)
    assert np.all(np.abs(np.diff(np.vstack([q[:1], q]), n=2, axis=0)) <= np.asarray(ARM.max_acc) * DT * DT)
    assert np.all(q >= ARM.lower) and np.all(q <= ARM.upper)
    assert np.allclose(q[-1], q1) and np.allclose(path.sample(path.duration)[1], 0.0)
    # on the curve, the hand's path length following the minimum-jerk profile (its share at half time 1/2)
    for x in (0.1, 0.3, 0.5, 0.8):
        qi = path.sample(x * path.duration)[0]
        C = bent_points(READY, q1, bend, np.linspace(0.0, 1.0, 4001))
        assert np.min(np.max(np.abs(C - qi), axis=1)) < 2e-3
    P = ARM.fk_batch(q)[:, :3, 3]
    cum = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))))
    share = np.interp(0.5 * path.duration, ts, cum) / cum[-1]
    assert share == pytest.approx(0.5, abs=0.02)
    with pytest.raises(ValueError):
        JointPath([READY, q1], np.asarray(ARM.max_vel), np.asarray(ARM.max_acc), bends=[shape, shape])


def test_a_free_space_dead_end_is_left_by_a_bent_joint_move_with_a_short_hand_path() -> None:
    """The straight route folds joint 4 onto its limit; without the corridor the joint-space move is
    bent (as far as it is worth the time): the hand's path within 15 % of the line (the straight joint
    move: 1.24), one speed peak, every joint within its limits; ``~/state`` says so."""
    q0 = np.array([-0.276, 0.847, -1.472, -1.928, -0.765, -1.563, -4.628])
    Q, messages = reach(ARM, q0, np.array([0.447, -0.575, 0.94, -1.293, 3.542, -0.699, -4.462]))
    assert any(m.startswith("moving in joint space (bent: the hand's path") for m in messages), messages
    P = ARM.fk_batch(Q)[:, :3, 3]
    v = np.linalg.norm(np.diff(P, axis=0), axis=1) / DT
    assert np.sum(v) * DT / np.linalg.norm(P[-1] - P[0]) < 1.15
    assert speed_peaks(v) == 1


def speed_peaks(v: np.ndarray) -> int:
    """Maxima of the speed that rise and fall by at least 10 % of its peak (ripple ignored)."""
    h = 0.1 * float(np.max(v))
    peaks, lo, hi, up = 0, float(v[0]), 0.0, False
    for x in v:
        if not up:
            lo = min(lo, x)
            up, hi = (True, x) if x - lo >= h else (False, hi)
        else:
            hi = max(hi, x)
            if hi - x >= h:
                peaks, up, lo = peaks + 1, False, x
    return peaks + up


def reach(arm: object, q0: np.ndarray, q_goal: np.ndarray) -> tuple[np.ndarray, set[str]]:
    """The commanded joints of a free-space point goal at the tool pose of ``q_goal`` from ``q0``
    (corridor routes off: the joint-space move), and the messages on the way; it must be REACHED."""
    ctl = make_controller(arm, Scene(), ControllerParams.from_dict({"replan": {"corridor": False}}))
    ctl.reset(q0)
    assert ctl.set_goal(arm.fk(q_goal)).accepted
    qs, messages = [q0], set()
    for _ in range(1500):
        r = ctl.step(DT)
        qs.append(r.q)
        messages.add(r.message)
        if r.phase is Phase.REACHED:
            break
    assert r.phase is Phase.REACHED
    Q = np.array(qs)
    assert np.all(Q >= arm.lower) and np.all(Q <= arm.upper)
    assert np.all(np.abs(np.diff(Q, axis=0)) <= np.asarray(arm.max_vel) * DT * (1 + 1e-9))
    assert np.all(np.abs(np.diff(Q, n=2, axis=0)) <= np.asarray(arm.max_acc) * DT * DT * (1 + 1e-9))
    return Q, messages


def hand_speed(arm: object, Q: np.ndarray) -> tuple[np.ndarray, float]:
    """The hand's speed (m/s) along commanded joints ``Q``, and its path over its straight distance."""
    P = arm.fk_batch(Q)[:, :3, 3]
    v = np.linalg.norm(np.diff(P, axis=0), axis=1) / DT
    return v, float(np.sum(v) * DT / np.linalg.norm(P[-1] - P[0]))


def test_a_bend_of_two_half_waves_worth_its_time_straightens_the_hand_path_to_a_single_bell() -> None:
    """The PowerCube arm's straight route to this goal runs joint 3 into its limit; the straight joint
    move swings the hand 20 % off the line. The bend is searched for what the move costs (its paced
    duration plus the hand's excess path), with two half-waves per joint: the hand's path within 5 % of
    the line, paced to one minimum-jerk bell."""
    arm = load_arm("powercube7")
    q0 = np.array([0.714231, 0.800287, 2.772471, -0.707156, 2.776215, 1.32074, 0.686244])
    q1 = np.array([-0.834395, 0.57861, 2.645131, -0.789873, 0.309778, -1.292967, 1.962486])
    Q, messages = reach(arm, q0, q1)
    assert any(m.startswith("moving in joint space (bent: the hand's path") for m in messages), messages
    v, ratio = hand_speed(arm, Q)
    assert ratio < 1.05
    assert speed_peaks(v) == 1


def test_a_start_closer_than_the_clearance_is_left_by_the_bent_move_without_a_stop() -> None:
    """The PA10 starts 14 mm from itself (the planning clearance is more): the bent move gets clear on
    its way, one bell, where a retreat first and then the move made the hand stop and start again."""
    q0 = np.array([2.235862, -1.568157, 2.048432, 1.163047, 3.429334, -0.53051, 2.101875])
    q1 = np.array([1.869266, -0.123214, -0.774378, 1.639934, 3.291239, -2.242345, -2.526043])
    Q, messages = reach(ARM, q0, q1)
    assert any(m.startswith("moving in joint space (bent: the hand's path") for m in messages), messages
    v, ratio = hand_speed(ARM, Q)
    assert speed_peaks(v) == 1
    assert ratio < 1.15
