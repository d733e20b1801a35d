"""The swivel while tracking (control/stream_swivel.py, servo.swivel_law pose, the default): the offset
law alone, and a circle streamed over the PA10's shoulder, lap after lap, in-process.

The circle (r 0.1 m, tool down, centre (0.55, 0, 0.65)) is where the highest elbow passes the vertical
above the shoulder: with the swivel dynamics (eq. 31) the hand stalled and fell 0.7 m behind there.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.benches import load_bench

from redarm_ros.control.elbow import ArmGeometry, elbow_circle
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.stream_swivel import closing_acc, offset_rate, shoulder_sine, time_to_axis
from redarm_ros.kinematics import load_arm

track = load_bench("track_bench")
PA10 = load_arm("pa10")
SHOULDER_CENTRE = (0.55, 0.0, 0.65)


def test_the_offset_lands_on_zero_in_finite_time_within_its_bounds() -> None:
    dt, acc, max_rate = 0.01, 2.0, 1.0
    for e0 in (0.3, -0.1, 1e-4):
        e, rate, steps = e0, 0.0, 0
        while abs(e) >= 1e-15:
            new = offset_rate(e, rate, 0.0, acc, max_rate, 4.0, dt)
            assert abs(new) <= max_rate + 1e-12 and abs(new - rate) <= 4.0 * dt + 1e-12
            e, rate, steps = e + new * dt, new, steps + 1
            assert e * e0 >= -1e-15  # never past 0
            assert steps < 200, f"offset {e0} not closed after 2 s: {e}"
        assert steps * dt <= 2.0 * math.sqrt(abs(e0) / acc) + 0.1 + (max_rate / acc if abs(e0) > 0.2 else 0.0)
    # a push (obstacle, limit) holds the offset away from 0: no snap onto it
    assert offset_rate(1e-4, 0.0, 0.5, acc, max_rate, 4.0, dt) > 0.0
    # towards 0 the rate speeds up at the closing acceleration, not at the joints' whole share
    assert offset_rate(0.3, 0.0, 0.0, acc, max_rate, 4.0, dt) == pytest.approx(-acc * dt)
    # closing acceleration 0 (the hand needs the joints' whole acceleration): the offset holds, no faster
    # towards 0 than it goes, and still lands on 0 braking at the joints' share, never past it
    assert offset_rate(0.3, -0.1, 0.0, 0.0, max_rate, 4.0, dt) == pytest.approx(-0.1)
    assert offset_rate(0.3, 0.0, 0.0, 0.0, max_rate, 4.0, dt) == 0.0
    assert offset_rate(0.3, 0.1, 0.0, 0.0, max_rate, 4.0, dt) == pytest.approx(0.1 - 4.0 * dt)
    e, rate = 0.004, -0.3
    while abs(e) > 1e-15:
        rate = offset_rate(e, rate, 0.0, 0.0, max_rate, 4.0, dt)
        e += rate * dt
        assert e >= -1e-15


def test_closing_acc_meets_the_deadline_within_its_bounds() -> None:
    assert closing_acc(0.1, 0.2, 1.0, 50.0) == pytest.approx(10.0)
    assert closing_acc(0.1, 1.0, 1.0, 50.0) == 1.0  # already in time at the least
    assert closing_acc(0.1, 0.01, 1.0, 50.0) == 50.0
    assert closing_acc(0.1, 0.0, 1.0, 50.0) == 50.0


def _laps(v: float, rate: float, laps: int, method: str):
    """Laps of the over-the-shoulder circle with track_bench's ``method`` (servo: the defaults, servo-dyn:
    servo.swivel_law dynamics), from where the controller settles at the start (0.1 rad off the preferred
    swivel: the rest swivel of a point goal is one of 64 samples)."""
    lp = track.lap_circle("over-the-shoulder", SHOULDER_CENTRE, v, track.R_DOWN, laps=laps)
    q0 = track.settle_start(PA10, lp.path, track.Q_HINT)
    msgs = track.make_stream(lp.path.duration, rate, "clean", seed=int(rate))
    run = track.run_method(method, PA10, lp.path, msgs, q0)
    return track.lap_scores(PA10, lp, run), run


def test_a_circle_over_the_shoulder_is_followed_exactly_and_the_same_way_every_lap() -> None:
    # (with the defaults: the swivel dynamics law stalled here and fell 0.7 m behind)
    sc, run = _laps(0.157, 50.0, 3, "servo")
    assert max(sc.stall) == 0.0 and not sc.stalls
    assert max(sc.p95) <= 5.0, sc.p95
    assert min(sc.min_q2) < 0.01  # it does pass over the shoulder
    assert sc.joint_diff[2] <= 0.01, sc.joint_diff  # lap 3 as lap 2 (lap 1 starts off the preferred swivel)
    # the elbow stays in the vertical plane through the wrist: joint 3 at 0 once the offset is closed
    assert float(np.max(np.abs(run.q[len(run.q) // 3:, 2]))) < 1e-3


def test_the_pose_law_is_the_default_and_the_swivel_dynamics_law_still_runs() -> None:
    assert ControllerParams().servo.swivel_law == "pose"
    sc, _ = _laps(0.157, 50.0, 1, "servo-dyn")
    assert len(sc.p95) == 1  # (it runs; over the shoulder it stalls: benchmarks/results/track_bench.md)


def test_shoulder_sine_is_that_of_joint_2_and_the_look_ahead_finds_the_axis() -> None:
    geom = ArmGeometry.from_arm(PA10)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(PA10.lower, PA10.upper) * 0.8
        T = PA10.fk(q)
        c = elbow_circle(geom, T)
        assert shoulder_sine(c, PA10.swivel(q)) == pytest.approx(abs(math.sin(q[1])), abs=1e-9)
    # along the over-the-shoulder circle the highest elbow comes within 0.01 of the axis: found at the
    # first predicted pose below the margin, and never with a margin no elbow gets below

    def high(c) -> float:
        return math.atan2(-c.b[2], -c.a[2]) + math.pi

    lp = track.lap_circle("over-the-shoulder", SHOULDER_CENTRE, 0.157, track.R_DOWN, laps=1)
    poses = [(float(t), lp.path.pose(float(t))) for t in np.linspace(0.0, lp.path.duration, 200)]
    sines = [shoulder_sine(elbow_circle(geom, T), high(elbow_circle(geom, T))) for _, T in poses]
    first = next(i for i, x in enumerate(sines) if x < 0.05)
    assert time_to_axis(geom, poses, 0.0, high, 0.05) == poses[first][0]
    assert time_to_axis(geom, poses, 0.0, high, 1e-6) is None


def test_the_pose_law_follows_a_fast_circle_streamed_at_10_hz_as_closely_as_the_swivel_dynamics() -> None:
    # circle-0.30 at 10 Hz (track_bench): the joints' acceleration limits bind while the estimate jumps at
    # each message; the pose law's offset holds meanwhile instead of costing the hand acceleration
    path = track.circle(0.30)
    q0 = track.settle_start(PA10, path)
    msgs = track.make_stream(path.duration, 10.0, "clean", seed=10 * 7 + 5)
    p95 = {m: float(np.percentile(track.score(PA10, path, track.run_method(m, PA10, path, msgs, q0)).pos, 95))
           for m in ("servo", "servo-dyn")}
    assert p95["servo"] <= p95["servo-dyn"] + 0.5, p95
