"""Goal streams and twists in-process: tracked like a servo, told apart from new goals, settled on
the last goal, followed as closely as the limits allow when infeasible; joint limits and the guard
hold throughout. The accuracy numbers belong to benchmarks/track_bench.py; the bounds here are
generous."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.benches import load_bench
from support.control_scenes import pose

from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import GoalKind, Phase, ReachController
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, Sphere, min_distance
from redarm_ros.kinematics import load_arm

ramp_arc = load_bench("bench_common").ramp_arc
ARM = load_arm("pa10")
DT = 0.01
HINT = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])


def circle_path(v: float, center=(0.7, 0.0, 0.2), r: float = 0.1, ramp: float = 0.5):
    """Pose at t along a horizontal circle at cruise speed v (smooth start and stop), and its
    duration (one turn)."""
    s_of, total = ramp_arc(2 * math.pi * r, v, ramp)
    c = np.asarray(center)

    def at(t: float) -> np.ndarray:
        a = s_of(t) / r
        return pose(c + r * np.array([math.cos(a), math.sin(a), 0.0]))

    return at, total


def settled(scene: Scene, T0: np.ndarray) -> ReachController:
    """A controller resting at T0 (the elbow settled)."""
    ctl = make_controller(ARM, scene)
    q0, _ = ARM.ik_nearest(T0, HINT)
    ctl.reset(q0, now=0.0)
    ctl.set_goal(T0)
    for k in range(300):
        ctl.step(DT, (k + 1) * DT)
    return ctl


def stream(
    ctl: ReachController,
    path,
    duration: float,
    rate: float,
    t0: float,
    after: float = 2.0,
    jitter: float = 0.0,
    drop: float = 0.0,
    seed: int = 0,
):
    """Send the path as a stream (stamps = sample times, optionally jittered/dropped/late), step the
    controller at 100 Hz; returns (times since the stream's start, commands, results)."""
    rng = np.random.default_rng(seed)
    msgs = []
    n = int(duration * rate)
    for i in range(n + 1):
        ts = min(i / rate, duration)
        if 0 < i < n and rng.random() < drop:
            continue
        stamp = ts + (rng.uniform(-jitter, jitter) if jitter else 0.0)
        late = 1.0 / rate if jitter and 0 < i < n and rng.random() < 0.03 else 0.0
        msgs.append((ts + late + (rng.uniform(0, jitter) if jitter else 0.0), stamp, ts))
    msgs.sort()
    times, qs, results = [], [], []
    mi = 0
    k = 0
    while k * DT < duration + after:
        k += 1
        t = k * DT
        while mi < len(msgs) and msgs[mi][0] <= t + 1e-9:
            arrive, stamp, ts = msgs[mi]
            ctl.goal_message(path(ts), t0 + stamp, t0 + arrive)
            mi += 1
        r = ctl.step(DT, t0 + t)
        times.append(t)
        qs.append(r.q)
        results.append(r)
    return np.array(times), np.array(qs), results


def errors_mm(path, times, qs, duration) -> np.ndarray:
    live = times <= duration
    return (
        np.array(
            [
                np.linalg.norm(ARM.fk(q)[:3, 3] - path(t)[:3, 3])
                for t, q in zip(times[live], qs[live], strict=True)
            ]
        )
        * 1e3
    )


def check_limits(qs: np.ndarray) -> None:
    assert np.all(qs >= ARM.lower - 1e-12) and np.all(qs <= ARM.upper + 1e-12)
    assert (np.abs(np.diff(qs, axis=0)) / (np.asarray(ARM.max_vel) * DT)).max() <= 1.0 + 1e-6
    assert (np.abs(np.diff(qs, n=2, axis=0)) / (np.asarray(ARM.max_acc) * DT * DT)).max() <= 1.0 + 1e-6


def overshoot_mm(path, duration, times, qs) -> float:
    end = path(duration)[:3, 3]
    u = end - path(duration - 0.3)[:3, 3]
    u /= np.linalg.norm(u)
    after = [ARM.fk(q)[:3, 3] for t, q in zip(times, qs, strict=True) if t > duration]
    return max(0.0, max(float((p - end) @ u) for p in after)) * 1e3


def test_circle_stream_is_tracked_and_settles_on_the_last_goal() -> None:
    path, duration = circle_path(0.16)
    ctl = settled(Scene((), 0.0), path(0.0))
    t0 = ctl.time
    times, qs, res = stream(ctl, path, duration, 50.0, t0)
    e = errors_mm(path, times, qs, duration)
    assert np.median(e) < 2.0 and np.max(e) < 10.0
    live = [r for t, r in zip(times, res, strict=True) if 0.2 < t < duration - 0.2]
    assert all(r.phase is Phase.TRACKING for r in live)
    assert all(r.stream_rate == pytest.approx(50.0, rel=0.05) for r in live)
    mid = live[len(live) // 2]
    assert math.hypot(*mid.goal_velocity) == pytest.approx(0.16, rel=0.1)
    assert ctl.goal_kind is GoalKind.STREAM
    assert res[-1].phase is Phase.REACHED
    assert overshoot_mm(path, duration, times, qs) <= 2.0
    check_limits(qs)


def test_jittered_stream_with_drops_and_late_messages_is_still_tracked() -> None:
    path, duration = circle_path(0.16)
    ctl = settled(Scene((), 0.0), path(0.0))
    times, qs, res = stream(ctl, path, duration, 50.0, ctl.time, jitter=0.005, drop=0.05, seed=3)
    e = errors_mm(path, times, qs, duration)
    assert np.median(e) < 3.0 and np.percentile(e, 95) < 8.0
    assert res[-1].phase is Phase.REACHED
    check_limits(qs)


def test_a_far_goal_during_a_stream_is_a_new_goal() -> None:
    path, duration = circle_path(0.16)
    ctl = settled(Scene((), 0.0), path(0.0))
    t0 = ctl.time
    times, qs, res = stream(ctl, path, 1.5, 50.0, t0, after=0.0)
    assert res[-1].phase is Phase.TRACKING
    far = pose((0.5, -0.3, 0.3))
    check = ctl.goal_message(far, t0 + 1.52, t0 + 1.52)
    assert check.accepted and check.kind is GoalKind.POINT
    phases = set()
    for k in range(800):
        r = ctl.step(DT, t0 + 1.52 + (k + 1) * DT)
        phases.add(r.phase)
        if r.phase is Phase.REACHED:
            break
    assert r.phase is Phase.REACHED and Phase.TRACKING not in phases
    assert np.allclose(ARM.fk(r.q)[:3, 3], far[:3, 3], atol=1e-3)


def test_a_goal_republished_at_a_rate_stays_a_point_goal() -> None:
    ctl = settled(Scene((), 0.0), pose((0.6, 0.1, 0.25)))
    t0 = ctl.time
    T = pose((0.55, -0.2, 0.3))
    phases = set()
    for k in range(600):  # (REACHED waits for the elbow to settle too: 4.7 s here)
        t = t0 + (k + 1) * DT
        if k % 10 == 0:  # 10 Hz, the same goal
            check = ctl.goal_message(T, t, t)
            assert check.kind is GoalKind.POINT and check.repeat == (k > 0)
        phases.add(ctl.step(DT, t).phase)
    assert Phase.TRACKING not in phases and ctl.phase is Phase.REACHED


def test_a_stream_too_fast_for_the_joints_is_followed_as_closely_as_they_allow() -> None:
    path, duration = circle_path(1.0)  # 1 m/s round a 0.1 m circle: far beyond the PA10's joints
    ctl = settled(Scene((), 0.0), path(0.0))
    times, qs, res = stream(ctl, path, duration, 50.0, ctl.time)
    check_limits(qs)
    notes = {r.message for r in res if r.phase is Phase.TRACKING and r.message}
    assert any("limits" in m and "following as closely" in m for m in notes), notes
    # it settles on the last goal all the same
    assert res[-1].phase in (Phase.REACHED, Phase.REACHING)
    assert np.linalg.norm(ARM.fk(qs[-1])[:3, 3] - path(duration)[:3, 3]) < 0.01


def test_a_stream_out_of_reach_is_followed_to_the_edge_and_says_so() -> None:
    T0 = pose((0.7, 0.0, 0.3))
    ctl = settled(Scene((), 0.0), T0)
    t0 = ctl.time
    res = []
    qs = [ctl.q]
    for k in range(300):  # 0.25 m/s outwards, up to 0.75 m beyond
        t = (k + 1) * DT
        if k % 2 == 0:
            ctl.goal_message(pose((0.7 + 0.25 * t, 0.0, 0.3)), t0 + t, t0 + t)
        r = ctl.step(DT, t0 + t)
        res.append(r)
        qs.append(r.q)
    assert any("out of reach" in r.message for r in res)
    assert all(r.phase is Phase.TRACKING for r in res[20:])
    check_limits(np.array(qs))
    reach = ARM.key_points(qs[-1])
    assert np.linalg.norm(reach[3] - reach[1]) > 0.9  # the wrist went to the edge of the workspace


def test_stream_beside_an_obstacle_at_the_elbow_stays_collision_free() -> None:
    """A ball 2 cm into the forearm's path near the elbow (where the arm would pass if it kept its
    elbow): the swivel turns the elbow away while the hand keeps tracking."""
    path, duration = circle_path(0.16)
    free = settled(Scene((), 0.0), path(0.0))
    q0 = free.q
    times, qs, _ = stream(free, path, duration, 50.0, free.time)
    i = int(0.75 * duration / DT)
    kp = ARM.key_points(qs[i])
    side = np.cross(kp[3] - kp[2], [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    c = kp[2] + 0.1 * (kp[3] - kp[2]) + side * (ArmCapsules().radii[2] + 0.05 - 0.02)
    scene = Scene((Sphere(tuple(c), 0.05, "ball"),), 0.0)
    assert min(min_distance(ARM, q, scene).distance for q in qs) < 0.0  # it was in the way
    ctl = make_controller(ARM, scene)
    ctl.reset(q0, now=0.0)
    times, qs, res = stream(ctl, path, duration, 50.0, 0.0)
    assert min(min_distance(ARM, q, scene).distance for q in qs) >= 0.0
    e = errors_mm(path, times, qs, duration)
    assert np.median(e) < 3.0 and np.percentile(e, 95) < 30.0
    check_limits(qs)


def test_twist_moves_the_hand_then_it_stops_when_the_twist_stops() -> None:
    T0 = pose((0.6, 0.0, 0.3))
    ctl = settled(Scene((), 0.0), T0)
    t0 = ctl.time
    p0 = ARM.fk(ctl.q)[:3, 3]
    qs = [ctl.q]
    phases = []
    for k in range(200):  # 1 s at 0.05 m/s along +y and 0.2 rad/s about z, sent at 50 Hz
        t = t0 + (k + 1) * DT
        if k < 100 and k % 2 == 0:
            ctl.set_twist((0.0, 0.05, 0.0), (0.0, 0.0, 0.2), t)
        r = ctl.step(DT, t)
        qs.append(r.q)
        phases.append(r.phase)
    p1 = ARM.fk(qs[-1])[:3, 3]
    assert p1[1] - p0[1] == pytest.approx(0.05, abs=0.01)
    assert abs(p1[0] - p0[0]) < 0.003 and abs(p1[2] - p0[2]) < 0.003
    yaw = math.atan2(ARM.fk(qs[-1])[1, 0], ARM.fk(qs[-1])[0, 0]) - math.atan2(T0[1, 0], T0[0, 0])
    assert yaw == pytest.approx(0.2, abs=0.04)
    assert Phase.TRACKING in phases and phases[-1] is Phase.IDLE
    assert np.max(np.abs(qs[-1] - qs[-2])) < 1e-9  # at rest
    check_limits(np.array(qs))


def test_twist_into_the_table_is_stopped_by_the_slide_and_the_guard() -> None:
    ctl = settled(Scene((), 0.0), pose((0.6, 0.0, 0.12)))
    t0 = ctl.time
    qs = [ctl.q]
    for k in range(200):
        t = t0 + (k + 1) * DT
        ctl.set_twist((0.0, 0.0, -0.2), (0.0, 0.0, 0.0), t)
        qs.append(ctl.step(DT, t).q)
    assert min(min_distance(ARM, q, Scene((), 0.0)).distance for q in qs) >= 0.0
    check_limits(np.array(qs))
    z = np.array([ARM.fk(q)[2, 3] for q in qs])
    assert z[-1] < z[0] - 0.02  # the hand went down with the twist ...
    assert np.max(np.abs(np.diff(z[-20:]))) < 1e-4  # ... and was stopped above the table


def test_twist_validation() -> None:
    ctl = make_controller(ARM)
    with pytest.raises(ValueError):
        ctl.set_twist((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # before reset
    ctl.reset(HINT)
    with pytest.raises(ValueError):
        ctl.set_twist((0.0, math.nan, 0.0), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError):
        ctl.set_twist((0.0, 0.0), (0.0, 0.0, 0.0))


def test_a_stream_sent_to_a_stretched_arm_is_joined_after_a_joint_space_move() -> None:
    """From the homed pose (straight up, no elbow circle) a stream starts: the controller moves in
    joint space first (REPLANNING, saying why), then tracks it (TRACKING) and settles on its end."""
    path, duration = circle_path(0.08)
    ctl = make_controller(ARM, Scene((), 0.0))
    ctl.reset(np.zeros(7), now=0.0)
    times, qs, res = stream(ctl, lambda t: path(min(t, duration)), duration + 4.0, 50.0, 0.0)
    phases = [r.phase for r in res]
    assert Phase.REPLANNING in phases and Phase.TRACKING in phases
    assert phases.index(Phase.REPLANNING) < len(phases) - 1 - phases[::-1].index(Phase.TRACKING)
    assert any("stretched" in r.message for r in res if r.phase is Phase.REPLANNING)
    check_limits(qs)
    assert np.linalg.norm(ARM.fk(qs[-1])[:3, 3] - path(duration)[:3, 3]) < 2e-3
