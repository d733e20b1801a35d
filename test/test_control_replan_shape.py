"""The joint-space re-plan's shape: the goal configuration whose straight joint segment gives the
straightest hand path (among the cheap ones), and the minimum-jerk timing of the joint path."""

from __future__ import annotations

import numpy as np
import pytest

from redarm_ros.control import replan
from redarm_ros.control.elbow import ArmGeometry
from redarm_ros.control.guard import CollisionGuard
from redarm_ros.control.ik_step import IKStepper
from redarm_ros.control.params import ReplanParams
from redarm_ros.control.replan import JointPath, goal_candidates, move_time
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
    monkeypatch.setattr(replan, "BEND_COST", 0.0)  # by the move's time alone
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
