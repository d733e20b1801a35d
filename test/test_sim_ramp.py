"""Setpoint generator: velocity/acceleration limits hold for any command sequence; moves land exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.sim.ramp import STREAM_BUFFER, JointRamp, RampMode, braking_speed

DT = 1e-3


def _run(r: JointRamp, steps: int) -> list[float]:
    return [r.step(DT) for _ in range(steps)]


def _vel_acc(ps: list[float]) -> tuple[np.ndarray, np.ndarray]:
    v = np.diff(ps) / DT
    return v, np.diff(v) / DT


def test_single_move_is_a_trapezoid_of_the_right_duration():
    r = JointRamp(0.0, -3, 3, max_vel=1.0, max_acc=2.0)
    r.command_position(1.0)
    ps = [r.pos]
    while r.active:
        ps.append(r.step(DT))
    v, a = _vel_acc(ps)
    assert ps[-1] == 1.0 and r.mode is RampMode.IDLE
    # trapezoid: 0.5 s up, 0.5 s cruise, 0.5 s down -> 1.5 s (plus the one-step zeroing)
    assert len(ps) - 1 == pytest.approx(1500, abs=3)
    assert v.max() == pytest.approx(1.0) and v.min() >= 0  # no overshoot
    assert np.abs(a).max() <= 2.0 * (1 + 1e-6)
    assert np.mean(np.isclose(v, 1.0)) > 0.3  # really cruises at the limit


def test_fstep_duration_caps_speed():
    r = JointRamp(0.0, -3, 3, max_vel=2.0, max_acc=10.0)
    r.command_position(-0.5, duration_s=2.0)
    ps = _run(r, 2500)
    v, _ = _vel_acc(ps)
    assert np.abs(v).max() == pytest.approx(0.25, rel=1e-6)
    assert ps[-1] == -0.5


@pytest.mark.slow
def test_random_command_sequences_respect_limits():
    rng = np.random.default_rng(5)
    for _ in range(150):
        vmax, amax = rng.uniform(0.2, 2.0), rng.uniform(0.5, 5.0)
        r = JointRamp(rng.uniform(-1, 1), -2.5, 2.5, vmax, amax)
        ps = [r.pos]
        for _ in range(6):
            kind = rng.integers(3)
            if kind == 0:
                r.command_position(rng.uniform(-3, 3), duration_s=float(rng.choice([0.0, 0.01, 1.0])))
            elif kind == 1:
                r.command_velocity(rng.uniform(-3, 3))
            else:
                r.halt()
            ps += _run(r, int(rng.integers(1, 2500)))
        v, a = _vel_acc(ps)
        assert np.abs(v).max() <= vmax * (1 + 1e-9)
        assert np.abs(a).max() <= amax * (1 + 1e-6)
        assert min(ps) >= -2.5 and max(ps) <= 2.5


def test_velocity_mode_brakes_before_the_limit_and_halt_stops():
    r = JointRamp(0.0, -1.0, 1.0, max_vel=1.0, max_acc=1.0)
    r.command_velocity(5.0)  # clamped to max_vel
    ps = [r.pos] + _run(r, 4000)
    assert r.pos == pytest.approx(1.0) and r.vel == 0.0
    v, a = _vel_acc(ps)  # it braked before the limit (no clamp onto it at speed)
    assert max(ps) <= 1.0 and np.abs(v).max() == pytest.approx(1.0)
    assert np.abs(a).max() <= 1.0 * (1 + 1e-6)
    r.command_velocity(-0.5)
    _run(r, 1000)
    assert r.vel == pytest.approx(-0.5)
    r.halt()
    _run(r, 600)
    assert r.mode is RampMode.IDLE and not r.active
    held = r.pos
    _run(r, 100)
    assert r.pos == held


def _trapezoid_stream(goal: float, vmax: float, amax: float, dt: float) -> list[float]:
    """A host's feasible stream: positions every dt of a time-optimal move from 0 to goal (discrete law)."""
    p, v, out = 0.0, 0.0, []
    while True:
        v = min(v + amax * dt, vmax, braking_speed(goal - p, amax, dt))
        p += v * dt
        out.append(p)
        if v == 0.0:
            return out


@pytest.mark.parametrize("jitter_ms", [0, 2, 5])
def test_streamed_steps_are_followed_without_overtaking(jitter_ms: int):
    # A host streaming one FSTEP per 10 ms cycle along a move at the joint's own limits (the hardest
    # feasible stream), each step arriving up to half a step late on the host's grid: the setpoint
    # never gets ahead of the latest target, keeps the limits, and ends exactly on the goal.
    rng = np.random.default_rng(2)
    vmax, amax = 2.0, 8.0
    stream = _trapezoid_stream(1.2, vmax, amax, 0.01)
    arrivals = [10 * k + int(rng.integers(0, jitter_ms + 1)) for k in range(len(stream))]  # ms
    r = JointRamp(0.0, -3, 3, max_vel=vmax, max_acc=amax)
    ps, ahead, latest, k = [r.pos], [], 0.0, 0
    for t_ms in range(arrivals[-1] + 600):
        while k < len(stream) and arrivals[k] <= t_ms:
            r.command_position(stream[k], duration_s=0.01)
            latest, k = stream[k], k + 1
        ps.append(r.step(DT))
        ahead.append(ps[-1] - latest)
    v, a = _vel_acc(ps)
    assert max(ahead) <= 1e-9
    assert np.abs(v).max() <= vmax * (1 + 1e-9)
    assert np.abs(a).max() <= amax * (1 + 1e-6)
    assert ps[-1] == pytest.approx(1.2, abs=1e-12) and r.mode is RampMode.IDLE


def test_smooth_stream_is_followed_one_step_behind():
    # Along a sine within the limits the setpoint is the host's trajectory one step late: each step's
    # target is reached one step after it was due.
    r = JointRamp(0.0, -3, 3, max_vel=2.0, max_acc=8.0)
    f = lambda t: 0.5 * math.sin(2 * t)  # noqa: E731
    err = []
    for k in range(300):
        r.command_position(f((k + 1) * 0.01), duration_s=0.01)  # due at the end of this step
        for i in range(10):
            r.step(DT)
            err.append(abs(r.pos - f(k * 0.01 + (i + 1) * DT - 0.01)))
    # The chord midpoint vs the curve: |f"| d^2 / 8 = 2 * 0.01^2 / 8 = 2.5e-5 rad, nothing more.
    assert max(err[1000:]) < 3e-5


def test_a_late_step_is_buffered_and_a_full_buffer_skips_the_oldest():
    r = JointRamp(0.0, -3, 3, max_vel=2.0, max_acc=8.0)
    for k in range(10):  # ten steps at once (they waited in the bus): buffered, oldest skipped
        r.command_position(0.001 * (k + 1), duration_s=0.004)
    assert r.skipped_steps == 10 - 2 - STREAM_BUFFER  # one single move, one playing, the buffer
    ps = _run(r, 1000)
    assert ps[-1] == pytest.approx(0.01) and max(ps) <= 0.01 + 1e-12


def test_a_stream_into_a_limit_brakes_in_time():
    # A host streaming steps beyond the limit at full speed (targets clamped onto the limit): the
    # setpoint brakes at the acceleration limit and stops on the limit, never slamming into it.
    vmax, amax = 1.0, 2.0
    r = JointRamp(0.0, -1.0, 1.0, max_vel=vmax, max_acc=amax)
    ps = [r.pos]
    for k in range(400):
        r.command_position(0.004 * (k + 1), duration_s=0.004)  # 1 rad/s, on past the limit
        ps += _run(r, 4)
    ps += _run(r, 500)
    v, a = _vel_acc(ps)
    assert max(ps) <= 1.0 and ps[-1] == pytest.approx(1.0)
    assert np.abs(a).max() <= amax * (1 + 1e-6)


def test_position_and_velocity_moves_brake_for_moved_limits():
    r = JointRamp(0.0, -2.0, 2.0, max_vel=1.0, max_acc=2.0)
    r.command_position(1.9)
    _run(r, 700)
    assert r.vel == pytest.approx(1.0)
    r.set_limits(-2.0, 1.2)  # the soft limit moves in front of the moving joint
    ps = _run(r, 2000)
    v, a = _vel_acc(ps)
    assert max(ps) <= 1.2 and ps[-1] == pytest.approx(1.2)
    assert np.abs(a).max() <= 2.0 * (1 + 1e-6)
    # a velocity move alike
    r = JointRamp(0.0, -2.0, 2.0, max_vel=1.0, max_acc=2.0)
    r.command_velocity(1.0)
    _run(r, 700)
    assert r.vel == pytest.approx(1.0)
    r.set_limits(-2.0, 1.2)
    ps = [r.pos] + _run(r, 2000)
    v, a = _vel_acc(ps)
    assert max(ps) <= 1.2 and ps[-1] == pytest.approx(1.2) and r.vel == 0.0
    assert np.abs(a).max() <= 2.0 * (1 + 1e-6)
    with pytest.raises(ValueError):
        r.set_limits(1.0, 0.0)


def test_stream_end_brakes_within_the_acceleration_limit_and_settles_on_target():
    r = JointRamp(0.0, -3, 3, max_vel=2.0, max_acc=8.0)
    stream = [r.pos]
    for k in range(100):  # 1 rad/s ramp stream
        r.command_position(k * 0.01, duration_s=0.01)
        stream += _run(r, 10)
    ps = _run(r, 1000)
    _, a = _vel_acc(stream + ps)  # following the stream and braking at its end
    assert np.abs(a).max() <= 8.0 * (1 + 1e-6)
    overshoot = max(ps) - r.target
    assert 0 < overshoot <= 1.0**2 / (2 * 8.0) + 1e-3
    assert ps[-1] == r.target and r.mode is RampMode.IDLE
    # a later step (beyond the stream grace) is a single move from rest again: no overshoot
    r.command_position(0.5, duration_s=0.01)
    ps = _run(r, 2000)
    assert min(ps) == 0.5 and ps[-1] == 0.5  # moving down from 0.99


def test_braking_speed_is_exact():
    for dist in (1e-7, 3e-6, 0.01, 0.37, 2.0):
        r = JointRamp(0.0, -5, 5, max_vel=100.0, max_acc=3.0)
        r.vel = braking_speed(dist, 3.0, DT) + 3.0 * DT  # the first HALT step takes off one acc * dt
        r.mode = RampMode.HALT
        _run(r, 5000)
        assert r.pos == pytest.approx(dist, abs=1e-12)
    assert braking_speed(0.0, 1.0, DT) == 0.0
    with pytest.raises(ValueError):
        JointRamp(0.0, -1, 1, 0.0, 1.0)
    with pytest.raises(ValueError):
        JointRamp(0.0, -1, 1, 1.0, 1.0).command_position(float("nan"))


def _late_stream_to_the_margin(seed: int, margin: float = 1e-3) -> float:
    """The CAN driver's reference shaper driving a joint at full speed to ``upper - margin`` in 4 ms
    FSTEPs, delivered to the generator late and in bursts (a simulator running behind, 0-30 ms);
    returns how far (rad) the setpoint got past ``upper - margin`` (<= 0: never)."""
    from redarm_ros.can.driver_loop import ReferenceShaper
    from redarm_ros.motion import JointLimits

    rng = np.random.default_rng(seed)
    cycle, upper = 0.004, 1.0
    worst = -math.inf
    for _ in range(4):
        vmax, amax = rng.uniform(0.5, 2.0), rng.uniform(2.0, 10.0)
        shaper = ReferenceShaper(JointLimits([-upper], [upper], [vmax], [amax]), cycle, margin)
        shaper.reset(np.array([rng.uniform(-0.5, 0.5)]))
        r = JointRamp(float(shaper.r[0]), -upper, upper, vmax, amax)
        t_host = t_sim = 0.0
        waiting: list[tuple[float, float]] = []
        for _ in range(600):
            t_host += cycle + (rng.choice([0.0, 0.0, 0.0, 0.004, 0.008]) if rng.random() < 0.2 else 0.0)
            waiting.append((t_host, float(shaper.step(np.array([5.0]))[0])))
            lag = rng.choice([0.0, 0.0, 0.01, 0.03])
            while waiting and waiting[0][0] <= t_sim + lag:
                t, q = waiting.pop(0)
                while t_sim < t - lag:
                    worst = max(worst, r.step(DT))
                    t_sim += DT
                r.command_position(q, duration_s=cycle)
            while t_sim < t_host - lag:
                worst = max(worst, r.step(DT))
                t_sim += DT
        worst = max(worst, *_run(r, 1000))
    return worst - (upper - margin)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_late_stream_never_carries_the_setpoint_past_the_hosts_stop(seed: int) -> None:
    # The host brakes for its 1 mrad margin; however late its steps come, the setpoint stops there
    # (it used to run on to the limit itself, 1 mrad further, and the joint 0.5-0.9 mrad past).
    assert _late_stream_to_the_margin(seed) <= 1e-9


def test_a_stream_holding_still_keeps_the_setpoint_without_evaluating_the_law(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A host holding the arm streams the same step every cycle: the setpoint stays exactly there, and
    (what a held simulated arm costs) the braking law is not evaluated for it; the next step that
    moves is followed as before."""
    import redarm_ros.sim.ramp as ramp_mod

    r = JointRamp(0.3, -3, 3, max_vel=2.0, max_acc=8.0)
    for _ in range(5):  # the stream reaches its target and settles there
        r.command_position(0.3, duration_s=0.004)
        _run(r, 4)
    calls = []
    monkeypatch.setattr(ramp_mod, "braking_speed_scalar",
                        lambda *a: calls.append(a) or braking_speed(*a))
    held = []
    for _ in range(50):
        r.command_position(0.3, duration_s=0.004)
        held += _run(r, 4)
    assert held == [0.3] * 200 and r.vel == 0.0 and r.streaming
    assert not calls
    for k in range(50):  # then a step that moves: the law runs again, the stream is followed
        r.command_position(0.3 + 0.0004 * (k + 1), duration_s=0.004)
        _run(r, 4)
    assert calls and r.pos == pytest.approx(0.32, abs=2e-3)


def test_a_jittery_stream_holding_still_keeps_the_setpoint_bit_for_bit() -> None:
    """A real host's held stream: cycles and step durations jitter. The setpoint never moves by a
    single bit (the reference's cubic used to round off an ulp now and then: a moving setpoint, and
    a simulated arm stepped as if it moved)."""
    rng = np.random.default_rng(7)
    target = float(np.float32(0.8))
    r = JointRamp(0.0, -3, 3, max_vel=2.0, max_acc=8.0)
    for k in range(400):  # stream there, and hold
        r.command_position(min(target, target * (k + 1) / 200), duration_s=float(rng.uniform(0.0036, 0.0044)))
        _run(r, int(rng.choice([3, 4, 4, 5])))
    assert r.pos == target and r.vel == 0.0
    held = []
    for _ in range(500):
        r.command_position(target, duration_s=float(rng.uniform(0.0036, 0.0044)))
        held += _run(r, int(rng.choice([3, 4, 4, 5])))
    assert set(held) == {target} and r.streaming


class _EveryBound(JointRamp):
    """The generator evaluating every speed bound, also those from farther than it could matter."""

    def _far_distance(self, a: float, dt: float) -> float:
        return math.inf


def _random_commands(r: JointRamp, rng: np.random.Generator, steps: int) -> list[tuple[float, float]]:
    """Streams (with bursts, gaps and drifts into a limit), single moves, velocity, halt, moved limits."""
    out = []
    target = r.pos
    drift = 0.003 if rng.random() < 0.5 else 0.0
    for k in range(steps):
        ev = rng.random()
        if k % 4 == 0 and ev < 0.85:
            target = min(max(target + rng.normal(0.0, 0.004) + drift, r.lower - 0.1), r.upper + 0.1)
            for _ in range(2 if rng.random() < 0.05 else 1):
                r.command_position(target, None, None if rng.random() < 0.9 else 0.5 * r.max_acc, 0.004)
        elif ev < 0.002:
            r.command_position(rng.uniform(r.lower, r.upper), rng.uniform(0.1, r.max_vel))
        elif ev < 0.003:
            r.command_velocity(rng.uniform(-r.max_vel, r.max_vel))
        elif ev < 0.0035:
            r.halt()
        elif ev < 0.0038:
            lo, hi = sorted(rng.uniform(r.lower, r.upper, 2))
            r.set_limits(lo, hi)
        out.append((r.step(DT), r.vel))
    return out


@pytest.mark.parametrize("seed", range(12))
def test_speed_bounds_from_far_away_are_skipped_without_changing_a_step(
        seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # A bound from where the braking speed is at least max_vel cannot bind (every speed is capped at
    # max_vel), nor one whose cheap lower bound is above the speed: the generator skips them, and every
    # setpoint is the one of evaluating them all.
    import redarm_ros.sim.ramp as ramp_mod

    rng = np.random.default_rng(seed)
    lo, hi = -rng.uniform(0.2, 3.0), rng.uniform(0.2, 3.0)
    args = (rng.uniform(lo, hi), lo, hi, rng.uniform(0.3, 3.0), rng.uniform(0.5, 10.0))
    fast, full = JointRamp(*args), _EveryBound(*args)
    fast_run = _random_commands(fast, np.random.default_rng(100 + seed), 3000)
    monkeypatch.setattr(ramp_mod, "_speed_cap", lambda v, d, a, dt: min(v, braking_speed(d, a, dt)))
    assert fast_run == _random_commands(full, np.random.default_rng(100 + seed), 3000)
    a = fast.acc_limit
    far = fast._far_distance(a, DT)
    assert braking_speed(far, a, DT) >= fast.max_vel > braking_speed(0.999 * far, a, DT)


def test_speed_cap_is_the_braking_law_s_min_exactly() -> None:
    """``_speed_cap`` skips the law where a cheap lower bound shows it cannot bind: on speeds just
    below, at and above the law's value (a few ulps either way), far below, 0, -0.0, negative, and
    distances 0 and below, it returns exactly what ``min(speed, law)`` does."""
    from redarm_ros.sim.ramp import _speed_cap

    rng = np.random.default_rng(3)
    for _ in range(3000):
        acc, dt = float(rng.uniform(0.1, 50.0)), float(rng.choice([1e-3, 4e-3, 1e-2]))
        d = float(rng.choice([0.0, -1e-3, 10.0 ** rng.uniform(-9, 1)]))
        law = braking_speed(d, acc, dt)
        speeds = [law, 0.0, -0.0, -law, 0.5 * law, 1e-6 * law, 2.0 * law, float(rng.normal())]
        for k in range(1, 6):
            speeds += [law + k * math.ulp(law), law - k * math.ulp(law)]
        for v in speeds:
            got = _speed_cap(v, d, acc, dt)
            assert math.copysign(1.0, got) == math.copysign(1.0, min(v, law)) and got == min(v, law)


def test_a_followed_stream_skips_most_far_side_bounds(monkeypatch: pytest.MonkeyPatch) -> None:
    """Following a smooth stream, the fence of the host's stop and the limits are evaluated only where
    they may bind: fewer than two braking-law evaluations per step (four before), and every setpoint
    the same as with each bound evaluated (test above)."""
    import redarm_ros.sim.ramp as ramp_mod

    r = JointRamp(0.0, -1.0, 1.0, max_vel=1.0, max_acc=4.0)
    calls = []
    monkeypatch.setattr(ramp_mod, "braking_speed_scalar",
                        lambda *a: calls.append(a) or braking_speed(*a))
    steps = 0
    for k in range(250):  # 1 s of a 250 Hz host stream, sine within the limits
        r.command_position(0.5 * math.sin(2.0 * math.pi * 0.5 * (k + 1) * 0.004), duration_s=0.004)
        _run(r, 4)
        steps += 4
    assert len(calls) < 2 * steps
