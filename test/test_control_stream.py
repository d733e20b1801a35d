"""StreamEstimator: velocity from header stamps (exact, jittered, dropped, out of order, foreign
clock), telling a stream from a new goal, the end of a stream; and the servo law."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.params import StreamParams
from redarm_ros.control.servo import ServoTarget, servo_step
from redarm_ros.control.stream import StreamEstimator
from redarm_ros.kinematics.quaternion import quat_angle, quat_from_matrix, quat_from_rotvec

Q0 = (1.0, 0.0, 0.0, 0.0)


def line(t: float) -> tuple[float, float, float]:
    """0.2 m/s along x from (0.5, 0, 0.3)."""
    return (0.5 + 0.2 * t, 0.0, 0.3)


def circle(t: float, v: float = 0.16, r: float = 0.1) -> tuple[float, float, float]:
    a = v / r * t
    return (0.6 + r * math.cos(a), r * math.sin(a), 0.3)


def feed(est: StreamEstimator, f, times, stamps=None, arrivals=None, rot=None) -> None:
    for i, t in enumerate(times):
        stamp = t if stamps is None else stamps[i]
        arrive = t if arrivals is None else arrivals[i]
        q = Q0 if rot is None else rot(t)
        est.add(f(t), q, est.stamp_time(stamp, arrive), arrive)


def test_velocity_and_prediction_of_an_exact_line() -> None:
    est = StreamEstimator()
    feed(est, line, [k * 0.02 for k in range(10)])
    v, w = est.velocity()
    assert v == pytest.approx((0.2, 0.0, 0.0), abs=1e-9) and w == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert est.rate() == pytest.approx(50.0)
    pred = est.predict(0.19)  # 10 ms after the newest stamp (0.18)
    assert pred is not None and not pred.ended
    assert pred.pos == pytest.approx(line(0.19), abs=1e-9)


def test_circle_prediction_is_within_a_fifth_of_a_millimetre() -> None:
    est = StreamEstimator()
    times = [k * 0.02 for k in range(20)]
    feed(est, circle, times)
    for dt in (0.0, 0.01, 0.02):
        pred = est.predict(times[-1] + dt)
        assert pred is not None
        assert math.dist(pred.pos, circle(times[-1] + dt)) < 2e-4


def test_the_path_ahead_of_a_fast_circle_follows_its_turn_and_stops_with_the_stream() -> None:
    # 0.314 m/s on r 0.1 m at 100 Hz: half a second ahead the circle has turned 1.6 rad; the parabola of
    # predict() is 90 mm off there, the turn of path_poses() a few mm
    est = StreamEstimator()
    times = [k * 0.01 for k in range(100)]
    feed(est, lambda t: circle(t, 0.314), times, rot=lambda t: quat_from_rotvec((0.0, 0.0, 0.5 * t)))
    now = times[-1]
    ahead = np.array([0.1, 0.3, 0.5])
    poses = est.path_poses(now + ahead, now)
    assert poses is not None and poses.shape == (3, 4, 4)
    for T, tau in zip(poses, ahead, strict=True):
        parabola = est.predict(now + tau, now, clamp=False)
        assert parabola is not None
        truth = circle(now + tau, 0.314)
        assert math.dist(T[:3, 3], truth) < 2e-3 + 4e-3 * tau, tau
        assert math.dist(parabola.pos, truth) > 5.0 * math.dist(T[:3, 3], truth) or tau < 0.2
        R_truth = quat_from_rotvec((0.0, 0.0, 0.5 * (now + tau)))
        assert quat_angle(quat_from_matrix(T[:3, :3]), R_truth) < 1e-6
    # a straight line goes on straight; a stream whose samples stop is no longer predicted (it may stop)
    line_est = StreamEstimator()
    feed(line_est, line, times[:20])
    straight = line_est.path_poses(np.array([0.3, 0.6]), times[19])
    assert straight is not None
    assert straight[0, :3, 3] == pytest.approx(line(0.3), abs=1e-9)
    assert straight[1, :3, 3] == pytest.approx(line(0.6), abs=1e-9)
    assert line_est.path_poses(np.array([0.3]), times[19] + 0.03) is None
    assert StreamEstimator().path_poses(np.array([0.1]), 0.0) is None


def test_a_held_orientation_takes_the_short_way_with_the_same_numbers() -> None:
    """A stream that keeps its orientation (the rotation vectors all zero) gets the rotation block of
    the general Rodrigues product bit for bit, also with a -0.0 in the orientation's matrix; a turning
    stream still goes the general way."""
    from redarm_ros.control.stream import _rotvec_matrices
    from redarm_ros.kinematics.quaternion import matrix_from_quat

    rng = np.random.default_rng(7)
    for k in range(40):
        q = rng.normal(size=4)
        rot = (1.0, 0.0, 0.0, 0.0) if k == 0 else tuple(float(x) for x in q / np.linalg.norm(q))
        est = StreamEstimator()
        feed(est, circle, [i * 0.02 for i in range(12)], rot=lambda t, rot=rot: rot)
        times = 0.22 + np.arange(1, 1 + k % 9 + 1) * 0.1
        out = est.path_poses(times, 0.22)
        assert out is not None
        general = _rotvec_matrices(np.zeros((len(times), 3))) @ np.asarray(matrix_from_quat(rot))
        assert out[:, :3, :3].tobytes() == general.tobytes()
    turning = StreamEstimator()
    feed(turning, line, [i * 0.02 for i in range(10)], rot=lambda t: quat_from_rotvec((0.0, 0.0, 0.5 * t)))
    out = turning.path_poses(np.array([0.3, 0.5]), 0.18)
    assert out is not None
    assert quat_angle(quat_from_matrix(out[0, :3, :3]), quat_from_matrix(out[1, :3, :3])) > 0.05


def test_angular_velocity_from_orientations() -> None:
    est = StreamEstimator()
    rate = 0.5  # rad/s about z

    def rot(t: float):
        return quat_from_rotvec((0.0, 0.0, rate * t))

    feed(est, line, [k * 0.02 for k in range(8)], rot=rot)
    _, w = est.velocity()
    assert w == pytest.approx((0.0, 0.0, rate), abs=1e-6)
    pred = est.predict(0.16)
    assert quat_angle(pred.rot, rot(0.16)) < 1e-6


def test_jitter_drops_and_out_of_order_messages_are_averaged_out() -> None:
    """+-5 ms stamp jitter, 10 % dropped, every 7th message late (out of order): the velocity of a
    0.2 m/s line stays within 15 % and the prediction within 1 mm (seeded)."""
    rng = np.random.default_rng(4)
    times = [k * 0.02 for k in range(60) if rng.random() > 0.1]
    stamps = [t + rng.uniform(-0.005, 0.005) for t in times]
    arrivals = [t + (0.03 if i % 7 == 3 else 0.0) for i, t in enumerate(times)]
    order = np.argsort(arrivals, kind="stable")
    est = StreamEstimator()
    for i in order:
        # The pose is sampled at the true time; the stamp is off by the jitter.
        est.add(line(times[i]), Q0, est.stamp_time(stamps[i], arrivals[i]), arrivals[i])
    v, _ = est.velocity()
    assert abs(v[0] - 0.2) < 0.03 and abs(v[1]) < 0.01
    assert est.period() == pytest.approx(0.02, abs=0.004)  # a dropped message does not move it
    pred = est.predict(times[-1] + 0.01)
    assert math.dist(pred.pos, line(times[-1] + 0.01)) < 1e-3


def test_duplicate_and_stale_samples_are_ignored() -> None:
    est = StreamEstimator()
    feed(est, line, [k * 0.02 for k in range(10)])
    n = est.count
    assert not est.add(line(0.1), Q0, 0.1, 0.2)  # the same stamp again
    assert not est.add(line(-1.0), Q0, -1.0, 0.2)  # far older than the window
    assert est.count == n and est.dropped == 2


def test_stamps_on_another_clock_are_offset_zero_stamps_mean_now() -> None:
    est = StreamEstimator()
    offset = 1000.0  # e.g. simulated time vs wall time
    for k in range(10):
        t = k * 0.02
        arrive = t + offset + 0.003  # 3 ms transport
        est.add(line(t), Q0, est.stamp_time(t, arrive), arrive)
    # Predictions are asked on the receive clock: the stream is followed with the transport delay.
    pred = est.predict(0.18 + offset + 0.003)
    assert math.dist(pred.pos, line(0.18)) < 1e-6
    assert est.stamp_time(0.0, 5.0) == 5.0
    assert est.stamp_time(None, 5.0) == 5.0


def test_the_period_follows_every_sample_added() -> None:
    est = StreamEstimator()
    assert est.period() == math.inf
    feed(est, line, [0.0, 0.02, 0.04])
    assert est.period() == pytest.approx(0.02)
    feed(est, line, [0.05, 0.06, 0.07, 0.08])  # the median spacing is 0.01 s now
    assert est.period() == pytest.approx(0.01)
    assert est.rate() == pytest.approx(100.0)
    est.reset()
    assert est.period() == math.inf


def test_stream_ends_after_a_few_periods_and_the_target_is_the_last_goal() -> None:
    est = StreamEstimator(StreamParams(end_periods=3.0))
    feed(est, line, [k * 0.02 for k in range(10)])
    assert not est.ended(0.18 + 0.05)
    assert est.ended(0.18 + 0.07)
    pred = est.predict(0.3, now=0.3)
    assert pred.ended and pred.pos == pytest.approx(line(0.18)) and pred.vel == (0.0, 0.0, 0.0)


def test_extrapolation_is_clamped_after_a_missing_message() -> None:
    est = StreamEstimator(StreamParams(extrapolate_periods=1.5))
    feed(est, line, [k * 0.02 for k in range(10)])
    far = est.predict(0.18 + 0.05, now=0.18 + 0.04)  # not ended yet, but 2.5 periods on
    assert far.pos == pytest.approx(line(0.18 + 0.03), abs=1e-9)  # held at 1.5 periods
    assert far.vel == (0.0, 0.0, 0.0)


def test_continues_tells_stream_samples_from_new_goals() -> None:
    est = StreamEstimator(StreamParams(gap=0.5, jump=0.05))
    feed(est, line, [k * 0.02 for k in range(10)])
    assert est.continues(line(0.2), Q0, 0.2, 0.2)  # the next sample
    assert est.continues(line(0.3), Q0, 0.3, 0.3)  # a few dropped: still on the extrapolated line
    assert not est.continues((0.5, 0.3, 0.3), Q0, 0.2, 0.2)  # a jump elsewhere
    assert not est.continues(line(0.2), quat_from_rotvec((0.0, 0.0, 1.0)), 0.2, 0.2)  # a turn
    assert not est.continues(line(0.9), Q0, 0.9, 0.9)  # after the gap
    assert not StreamEstimator().continues(line(0.0), Q0, 0.0, 0.0)  # nothing to continue


def test_params_are_validated() -> None:
    with pytest.raises(ValueError):
        StreamParams(gap=0.0)
    with pytest.raises(ValueError):
        StreamParams(lead=-0.1)


# ------------------------------------------------------------------------------------------------
# servo law
# ------------------------------------------------------------------------------------------------
def test_servo_settles_on_a_static_target_without_overshoot() -> None:
    pos, rot, vel, w = (0.0, 0.0, 0.0), Q0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    target = ServoTarget(
        (0.05, 0.0, 0.0), quat_from_rotvec((0.0, 0.0, 0.3)), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    )
    xs = []
    for _ in range(200):
        pos, rot, vel, w = servo_step(pos, rot, vel, w, target, 0.01, 30.0, 3.0, 0.4, 20.0, 12.0, 1.5)
        xs.append(pos[0])
    assert max(xs) <= 0.05 + 1e-9
    assert xs[-1] == pytest.approx(0.05, abs=1e-6)
    assert quat_angle(rot, target.rot) < 1e-6
    acc = np.abs(np.diff(np.diff([0.0, 0.0, *xs]))) / 1e-4
    assert acc.max() <= 3.0 + 1e-6


def test_servo_with_feed_forward_tracks_a_moving_target_exactly() -> None:
    v = (0.2, -0.1, 0.0)
    pos, rot, vel, w = (0.0, 0.0, 0.0), Q0, v, (0.0, 0.0, 0.0)
    for k in range(1, 100):
        t = k * 0.01
        target = ServoTarget((v[0] * t, v[1] * t, 0.0), Q0, v, (0.0, 0.0, 0.0))
        pos, rot, vel, w = servo_step(pos, rot, vel, w, target, 0.01, 30.0, 3.0, 0.4, 20.0, 12.0, 1.5)
        assert math.dist(pos, target.pos) < 1e-12


def test_servo_speed_is_capped() -> None:
    pos, rot, vel, w = (0.0, 0.0, 0.0), Q0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    target = ServoTarget((1.0, 0.0, 0.0), Q0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    for _ in range(300):
        pos, rot, vel, w = servo_step(pos, rot, vel, w, target, 0.01, 30.0, 3.0, 0.4, 20.0, 12.0, 1.5)
        assert math.hypot(*vel) <= 0.4 + 1e-12


def test_the_lead_is_added_beyond_the_extrapolation_limit() -> None:
    est = StreamEstimator(StreamParams(extrapolate_periods=1.5, lead=0.05))
    feed(est, line, [k * 0.02 for k in range(10)])
    pred = est.predict(0.18, now=0.18)
    assert pred.pos == pytest.approx(line(0.23), abs=1e-9) and pred.vel == pytest.approx((0.2, 0.0, 0.0))
    late = est.predict(0.18 + 0.05, now=0.18 + 0.04)  # 2.5 periods after the newest: held at 1.5 + lead
    assert late.pos == pytest.approx(line(0.18 + 0.03 + 0.05), abs=1e-9) and late.vel == (0.0, 0.0, 0.0)
