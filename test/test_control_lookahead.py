"""The plan ahead within the joints' acceleration limits (control/lookahead.py, servo.plan_horizon): the
box-constrained QP, the plan itself, and the fast circle over the PA10's shoulder, in-process.

At 0.314 m/s (100 Hz) that circle asks joint 2 for 1.36 times its acceleration limit where it reverses;
clipped step by step the arm fell about 180 mm behind and never caught up (the least error any motion
within the limits allows is about 4 mm: benchmarks/results/track_bench.md).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from support.benches import load_bench

from redarm_ros.control.lookahead import JointLookahead, box_qp, growing_blocks
from redarm_ros.control.params import ControllerParams
from redarm_ros.kinematics import load_arm

track = load_bench("track_bench")
PA10 = load_arm("pa10")
SHOULDER_CENTRE = (0.55, 0.0, 0.65)


def _box_qp_by_enumeration(H: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The exact optimum: every pattern of free, lower and upper variables, the best feasible one."""
    n = len(g)
    best, best_x = np.inf, None
    for pattern in itertools.product((0, 1, 2), repeat=n):
        x = np.where(np.array(pattern) == 1, lo, np.where(np.array(pattern) == 2, hi, 0.0))
        free = np.array(pattern) == 0
        if free.any():
            x[free] = np.linalg.solve(H[np.ix_(free, free)], -(g[free] + H[np.ix_(free, ~free)] @ x[~free]))
        if np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12):
            f = 0.5 * x @ H @ x + g @ x
            if f < best:
                best, best_x = f, x
    assert best_x is not None
    return best_x


def test_box_qp_finds_the_optimum_from_any_start() -> None:
    rng = np.random.default_rng(5)
    for _ in range(40):
        n = int(rng.integers(2, 6))
        M = rng.normal(size=(n, n))
        H = M @ M.T + 0.05 * np.eye(n)
        g = rng.normal(size=n) * 3.0
        lo, hi = -rng.uniform(0.1, 1.0, n), rng.uniform(0.1, 1.0, n)
        want = _box_qp_by_enumeration(H, g, lo, hi)
        for x0 in (np.linalg.solve(H, -g), rng.uniform(lo, hi), hi.copy()):
            got = box_qp(H, g, lo, hi, x0)
            assert np.all(got >= lo) and np.all(got <= hi)
            assert 0.5 * got @ H @ got + g @ got == pytest.approx(0.5 * want @ H @ want + g @ want, abs=1e-9)
            assert got == pytest.approx(want, abs=1e-6)


def test_growing_blocks_cover_the_horizon() -> None:
    assert growing_blocks(0.01, 0.04, 1.5, 0.8) == [4, 6, 9, 14, 20, 27]
    for dt, first, growth, horizon in ((0.01, 0.04, 1.25, 0.8), (0.02, 0.05, 1.5, 0.3),
                                       (0.01, 0.04, 1.5, 0.4)):
        blocks = growing_blocks(dt, first, growth, horizon)
        assert sum(blocks) == round(horizon / dt) and min(blocks) >= 1


def test_a_feasible_path_is_followed_exactly_and_an_infeasible_one_within_the_limits() -> None:
    dt, max_acc = 0.01, np.array([2.0, 4.0])
    la = JointLookahead(dt, [4, 6, 9, 14, 20, 27], max_acc)
    t = la.times()
    # joint 1 on a slow sine (0.5 of its limit), joint 2 on a fast one (3 times its limit)
    targets = np.stack([0.5 * 2.0 / 4.0 * np.sin(2.0 * t), 3.0 * 4.0 / 100.0 * np.sin(10.0 * t)], axis=1)
    v0 = np.array([0.5 * 2.0 / 2.0, 3.0 * 4.0 / 10.0])
    plan = la.plan(np.zeros(2), v0, targets)
    assert plan.bound
    assert np.all(np.abs(plan.acc) <= 0.98 * max_acc[None, :] + 1e-12)
    assert plan.qd == pytest.approx(v0 + dt * plan.acc[0])
    assert plan.q == pytest.approx(dt * plan.qd)
    # joint 1 alone is feasible: its plan is the path's own motion, nearly (sampled in blocks), without
    # accelerations ringing from block to block (the path's own are at most 1 rad/s^2, 0 at t = 0)
    la1 = JointLookahead(dt, [4, 6, 9, 14, 20, 27], max_acc[:1])
    p1 = la1.plan(np.zeros(1), v0[:1], targets[:, :1])
    assert not p1.bound
    assert float(np.max(np.abs(p1.acc))) <= 1.2
    assert p1.acc[0, 0] == pytest.approx(0.0, abs=0.15)


def _laps(v: float, rate: float):
    lp = track.lap_circle("over-the-shoulder", SHOULDER_CENTRE, v, track.R_DOWN, laps=3)
    q0 = track.settle_start(PA10, lp.path, track.Q_HINT)
    msgs = track.make_stream(lp.path.duration, rate, "clean", seed=int(rate))
    run = track.run_method("servo", PA10, lp.path, msgs, q0)
    return track.lap_scores(PA10, lp, run), run


def test_the_fast_circle_over_the_shoulder_is_followed_after_the_first_lap_within_the_limits() -> None:
    assert ControllerParams().servo.plan_horizon > 0.0
    sc, run = _laps(0.314, 100.0)
    # within a few times the least error any motion within the limits allows (about 4 mm), the same
    # joints every lap after the first (lap 1 starts 0.1 rad off the preferred swivel)
    assert max(sc.p95[1:]) <= 10.0, sc.p95
    assert max(sc.stall) == 0.0
    assert sc.joint_diff[2] <= 0.02, sc.joint_diff
    assert min(sc.min_q2) < 0.01  # it does pass over the shoulder
    # every command within the joint limits: position, velocity and acceleration (finite differences of
    # the commanded joints at the controller's step)
    q = run.q
    lower, upper = np.asarray(PA10.lower), np.asarray(PA10.upper)
    assert np.all(q >= lower - 1e-12) and np.all(q <= upper + 1e-12)
    vel = np.diff(q, axis=0) / track.DT
    acc = np.diff(q, n=2, axis=0) / (track.DT * track.DT)
    assert float(np.max(np.abs(vel) / np.asarray(PA10.max_vel))) <= 1.0 + 1e-9
    assert float(np.max(np.abs(acc) / np.asarray(PA10.max_acc))) <= 1.0 + 1e-6


def test_a_free_joint_makes_up_for_one_held_by_its_limit() -> None:
    # two joints moving the tool along the same direction: joint 1 is held back by its limit on a fast
    # sine; joint 2, free, moves the other way by the lag of joint 1 (the tool stays on the path)
    dt, max_acc = 0.01, np.array([1.0, 50.0])
    blocks = [4, 6, 9, 14, 20, 27]
    la = JointLookahead(dt, blocks, max_acc)
    t = la.times()
    targets = np.stack([0.05 * np.sin(10.0 * t), np.zeros_like(t)], axis=1)
    v0 = np.array([0.5, 0.0])
    J = np.zeros((6, 2))
    J[0] = (0.5, 0.5)

    held = la.plan(np.zeros(2), v0, targets)
    assert held.bound and held.acc[:, 1] == pytest.approx(0.0, abs=1e-9)  # without a Jacobian: no help
    helped = JointLookahead(dt, blocks, max_acc).plan(np.zeros(2), v0, targets, lambda q: J)
    assert np.all(np.abs(helped.acc) <= 0.98 * max_acc[None, :] + 1e-12)
    assert helped.acc[:, 0] == pytest.approx(held.acc[:, 0])  # (the held joint's plan is its own)
    ends = np.cumsum(blocks)
    tool = 0.5 * (ends * dt * v0[0] + la.C @ helped.acc[:, 0]) + 0.5 * (la.C @ helped.acc[:, 1])
    lag = 0.5 * (ends * dt * v0[0] + la.C @ held.acc[:, 0]) - 0.5 * targets[:, 0]
    assert float(np.max(np.abs(tool - 0.5 * targets[:, 0]))) < 0.3 * float(np.max(np.abs(lag)))

