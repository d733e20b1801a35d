"""Tests of the ROS-free driver loop pieces: command source, period statistics, backoff."""

from __future__ import annotations

import struct
import threading
import time

import can
import numpy as np
import pytest
from support.loop_rig import AMAX, LOWER, Q0, UPPER, VMAX, loop_rig
from support.waits import wait_until

from redarm_ros.can import protocol
from redarm_ros.can.driver_loop import (
    Backoff,
    CommandMode,
    DriverLoop,
    JointCommandSource,
    LoopConfig,
    LoopState,
    PeriodStats,
    ReferenceShaper,
    braking_speed,
)
from redarm_ros.can.module_emulator import EmulatedArm
from redarm_ros.can.protocol import Command
from redarm_ros.errors import BusError, InvalidInputError
from redarm_ros.motion import JointLimits, braking_distance

N = 3


def test_hold_uses_measured_position_until_a_command_arrives() -> None:
    src = JointCommandSource(N)
    meas = np.array([0.1, 0.2, 0.3])
    q = src.sample(0.0, q_ref=np.zeros(N), q_measured=meas)
    np.testing.assert_allclose(q, meas)
    # Later measurements do not move a hold: the arm stays where it was.
    q = src.sample(1.0, q_ref=np.zeros(N), q_measured=meas + 1)
    np.testing.assert_allclose(q, meas)
    assert src.mode is CommandMode.HOLD


def test_trajectory_interpolates_from_the_reference_and_keeps_the_last_point() -> None:
    src = JointCommandSource(N)
    ref = np.array([0.0, 1.0, 2.0])
    # Joints 2 and 0 (in that order), two points.
    src.set_trajectory([2, 0], [1.0, 3.0], np.array([[3.0, 1.0], [1.0, -1.0]]), start=10.0)
    np.testing.assert_allclose(src.sample(9.0, ref, ref), ref)  # before start: the reference
    ref_later = ref + 5  # a changed reference after the first sample must not matter
    np.testing.assert_allclose(src.sample(10.5, ref_later, ref), [0.5, 1.0, 2.5])
    np.testing.assert_allclose(src.sample(11.0, ref_later, ref), [1.0, 1.0, 3.0])
    np.testing.assert_allclose(src.sample(12.0, ref_later, ref), [0.0, 1.0, 2.0])
    np.testing.assert_allclose(src.sample(99.0, ref_later, ref), [-1.0, 1.0, 1.0])
    assert src.mode is CommandMode.TRAJECTORY


def test_trajectory_point_at_time_zero_is_a_step() -> None:
    src = JointCommandSource(N)
    src.set_trajectory([0, 1, 2], [0.0], np.array([[1.0, 2.0, 3.0]]), start=0.0)
    np.testing.assert_allclose(src.sample(0.001, np.zeros(N), np.zeros(N)), [1, 2, 3])


@pytest.mark.parametrize(
    ("index", "times", "points"),
    [
        ([0], [1.0], np.array([[np.nan]])),
        ([0], [2.0, 1.0], np.array([[0.0], [1.0]])),
        ([0], [-1.0], np.array([[0.0]])),
        ([0, 0], [1.0], np.array([[0.0, 1.0]])),
        ([5], [1.0], np.array([[0.0]])),
        ([0, 1], [1.0], np.array([[0.0]])),
        ([], [], np.zeros((0, 0))),
    ],
)
def test_bad_trajectories_are_refused_and_do_not_replace_the_command(index, times, points) -> None:
    src = JointCommandSource(N)
    src.set_trajectory([0], [1.0], np.array([[0.5]]), start=0.0)
    gen = src.generation
    with pytest.raises(InvalidInputError):
        src.set_trajectory(index, times, points, start=0.0)
    assert src.generation == gen
    assert src.mode is CommandMode.TRAJECTORY


def test_stream_follows_then_holds_measured_position_when_it_stops() -> None:
    src = JointCommandSource(N, stream_timeout_s=0.5)
    ref = np.array([0.0, 0.0, 0.0])
    src.set_stream_target([1], [0.7], now=1.0)
    np.testing.assert_allclose(src.sample(1.2, ref, ref), [0.0, 0.7, 0.0])
    meas = np.array([0.0, 0.4, 0.0])  # the arm has not got there yet
    q = src.sample(1.6, np.array([0.0, 0.7, 0.0]), meas)
    np.testing.assert_allclose(q, meas)
    assert src.mode is CommandMode.HOLD
    np.testing.assert_allclose(src.sample(5.0, ref, ref + 3), meas)
    with pytest.raises(InvalidInputError):
        src.set_stream_target([0], [np.inf], now=2.0)


def test_clear_drops_the_command() -> None:
    src = JointCommandSource(N)
    src.set_trajectory([0], [1.0], np.array([[2.0]]), start=0.0)
    src.clear(np.array([9.0, 9.0, 9.0]))
    np.testing.assert_allclose(src.sample(5.0, np.zeros(N), np.zeros(N)), 9.0)
    src.clear(None)
    np.testing.assert_allclose(src.sample(5.0, np.zeros(N), np.ones(N)), 1.0)


def test_trajectory_starting_later_is_spliced_in_at_its_start() -> None:
    """A trajectory that starts after the last sample, while another plays, waits for its start (the
    current one plays on until then); one that starts now or earlier replaces the current at once."""
    src = JointCommandSource(N)
    z = np.zeros(N)
    src.set_trajectory([0], [0.0, 1.0], np.array([[0.0], [1.0]]), start=0.0)
    np.testing.assert_allclose(src.sample(0.5, z, z)[0], 0.5)
    # Starts at 2.0 from 5.0: until then the first one plays (and holds its last point).
    src.set_trajectory([0], [0.0, 1.0], np.array([[5.0], [6.0]]), start=2.0)
    assert src.queued == 1
    np.testing.assert_allclose(src.sample(0.9, z, z)[0], 0.9)
    np.testing.assert_allclose(src.sample(1.5, z, z)[0], 1.0)
    np.testing.assert_allclose(src.sample(2.5, z, z)[0], 5.5)
    assert src.queued == 0
    # Starting before the last sample (a late message): replaces the current one at once.
    src.set_trajectory([0], [0.0, 1.0], np.array([[7.0], [8.0]]), start=2.0)
    np.testing.assert_allclose(src.sample(2.6, z, z)[0], 7.6)


def test_a_new_trajectory_replaces_those_queued_after_its_start() -> None:
    src = JointCommandSource(N)
    z = np.zeros(N)
    src.set_trajectory([0], [0.0], np.array([[1.0]]), start=0.0)
    src.sample(0.0, z, z)
    src.set_trajectory([0], [0.0], np.array([[2.0]]), start=1.0)
    src.set_trajectory([0], [0.0], np.array([[3.0]]), start=3.0)
    src.set_trajectory([0], [0.0], np.array([[4.0]]), start=2.0)  # drops the one at 3.0
    assert src.queued == 2
    assert [src.sample(t, z, z)[0] for t in (0.5, 1.5, 2.5, 3.5)] == [1.0, 2.0, 4.0, 4.0]
    src.set_trajectory([0], [0.0], np.array([[5.0]]), start=9.0)
    src.clear(None)  # a clear (halt, init) drops the queued ones too
    assert src.queued == 0


def test_stamped_segments_play_at_a_fixed_delay_whatever_their_latency() -> None:
    """Segments of a 100 Hz ramp, each stamped to end ``delay`` after its step, arriving with a latency
    of 0-15 ms (in order, as one publisher's messages are delivered): sampled at 250 Hz the target is
    the ramp delayed by ``delay`` exactly."""
    rng = np.random.default_rng(5)
    src = JointCommandSource(1)
    delay, period, speed = 0.03, 0.01, 0.5
    arrivals = [(0.0, 0.0)]
    for k in range(1, 60):
        t_step = k * period
        arrivals.append((max(arrivals[-1][0], t_step + rng.uniform(0.0, 0.015)), t_step))
    arrivals.pop(0)
    out = []
    i = 0
    q = np.zeros(1)
    for c in range(int(0.6 / 0.004)):
        now = c * 0.004
        while i < len(arrivals) and arrivals[i][0] <= now:
            t_step = arrivals[i][1]
            src.set_trajectory([0], [0.0, period], np.array([[speed * (t_step - period)], [speed * t_step]]),
                               start=t_step + delay - period)
            i += 1
        q = src.sample(now, q, q)
        if 0.1 <= now <= 0.55:
            out.append(q[0] - speed * (now - delay))
    assert np.max(np.abs(out)) < 1e-9


def test_period_stats() -> None:
    st = PeriodStats(0.004, window=100)
    assert st.summary()["samples"] == 0
    t = 0.0
    for p in [0.004] * 97 + [0.005, 0.006]:
        st.start(t)
        t += p
    st.start(t)
    s = st.summary()
    assert s["samples"] == 99
    assert s["period_err_median_ms"] == pytest.approx(0.0, abs=1e-9)
    assert s["period_err_max_ms"] == pytest.approx(2.0)
    assert 0.9 < s["period_err_p99_ms"] <= 2.0
    assert s["rate_hz"] == pytest.approx(99 / t)
    # After an overrun the gap is not a period sample, but it counts against the rate.
    st.start(t + 0.012, after_overrun=True)
    st.add_overrun(2)
    s2 = st.summary()
    assert s2["samples"] == 99 and st.overruns == 2
    assert s2["rate_hz"] < s["rate_hz"]


def test_period_totals_count_every_period_since_the_start() -> None:
    st = PeriodStats(0.004, window=10)
    t = 0.0
    st.start(t)
    for p in [0.004] * 198 + [0.0045, 0.012]:
        t += p
        st.start(t, after_overrun=p > 0.01)
    tot = st.totals()
    assert tot["periods"] == 200  # the window holds 10, the totals all of them, the overrun too
    assert tot["period_err_max_ms"] == pytest.approx(8.0)
    assert tot["period_err_p99_ms"] <= 0.55  # 99 % of the periods are within one 0.05 ms bin or two
    st.start(t + 5.0, after_pause=True)  # cycling resumed after a pause: no period
    assert st.totals()["period_err_max_ms"] == pytest.approx(8.0)
    st.reset_totals()
    assert st.totals()["periods"] == 0


def make_shaper(dt: float = 0.004, margin: float = 0.0) -> ReferenceShaper:
    return ReferenceShaper(JointLimits([-1.5, -2.0], [1.5, 2.0], [1.0, 2.0], [2.0, 8.0]), dt, margin)


def run_shaper(sh: ReferenceShaper, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rs, vs = [], []
    for g in targets:
        rs.append(sh.step(g))
        vs.append(sh.v.copy())
    return np.array(rs), np.array(vs)


def test_braking_speed_is_the_discrete_sqrt_2ad() -> None:
    dt, a = 0.004, 2.0
    d = np.array([0.0, 1e-6, 1e-3, 0.01, 0.3, 2.0])
    v = braking_speed(d, np.full_like(d, a), dt)
    assert v[0] == 0.0 and np.all(np.diff(v) > 0)
    # Within one speed step of the continuous law, below it.
    assert np.all(v <= np.sqrt(2 * a * d) + 1e-12)
    assert np.all(np.sqrt(2 * a * d) - v <= a * dt)
    # Integer steps k: stopping from k*a*dt covers exactly a*dt^2*k(k+1)/2.
    k = 7
    dk = a * dt * dt * k * (k + 1) / 2
    assert float(braking_speed(np.array([dk]), np.array([a]), dt)[0]) == pytest.approx(k * a * dt)


def test_shaper_step_is_a_trapezoid_within_limits_without_overshoot() -> None:
    sh = make_shaper()
    sh.reset(np.zeros(2))
    goal = np.array([1.0, -1.5])
    rs, vs = run_shaper(sh, np.tile(goal, (1500, 1)))
    np.testing.assert_allclose(rs[-1], goal)
    assert np.all(np.abs(vs) <= sh.max_vel + 1e-12)
    assert np.all(np.abs(np.diff(vs, axis=0)) <= sh.max_acc * sh.dt + 1e-9)
    assert rs[:, 0].max() <= 1.0 + 1e-6 and rs[:, 1].min() >= -1.5 - 1e-6  # sub-step rounding only
    hit = rs[:, 0] >= 1.0 - 1e-9
    assert hit.any() and np.argmax(hit) * sh.dt < 1.6  # 1.5 s is the time-optimal trapezoid


def test_shaper_stops_on_a_joint_limit_from_full_speed() -> None:
    sh = make_shaper()
    sh.reset(np.zeros(2))
    # A target stream running past the upper limit at full speed, clamped to the limit as the loop does.
    t = np.arange(1500) * sh.dt
    raw = np.stack([1.0 * t, 2.0 * t], axis=1)
    rs, _ = run_shaper(sh, np.clip(raw, sh.lower, sh.upper))
    assert np.all(rs <= sh.upper + 1e-12)
    np.testing.assert_allclose(rs[-1], sh.upper)


def test_shaper_keeps_its_margin_before_each_limit() -> None:
    sh = make_shaper(margin=1e-3)
    sh.reset(np.zeros(2))
    t = np.arange(1500) * sh.dt
    raw = np.stack([1.0 * t, -2.0 * t], axis=1)  # into the upper limit of joint 0, the lower of joint 1
    rs, vs = run_shaper(sh, np.clip(raw, [-1.5, -2.0], [1.5, 2.0]))
    assert rs[:, 0].max() <= 1.5 - 1e-3 + 1e-12 and rs[:, 1].min() >= -2.0 + 1e-3 - 1e-12
    np.testing.assert_allclose(rs[-1], [1.5 - 1e-3, -2.0 + 1e-3])
    acc = np.diff(rs, n=2, axis=0) / sh.dt**2  # from the positions sent: braked, not stopped dead
    assert np.all(np.abs(acc) <= np.array([2.0, 8.0]) * (1 + 1e-6))
    assert sh.upper[0] == pytest.approx(1.5 - 1e-3) and sh.lower[1] == pytest.approx(-2.0 + 1e-3)


def test_shaper_follows_a_feasible_stream_without_lag() -> None:
    sh = make_shaper()
    sh.reset(np.zeros(2))
    t = np.arange(1, 800) * sh.dt
    stream = np.stack([0.25 * t, -0.5 * np.sin(t)], axis=1)
    rs, _ = run_shaper(sh, stream)
    assert np.max(np.abs(rs[-300:] - stream[-300:])) < 1e-4
    # When the stream stops at speed v the reference brakes at a: overshoot about v^2 / 2a.
    rs2, _ = run_shaper(sh, np.tile(stream[-1], (500, 1)))
    assert rs2[:, 0].max() - stream[-1, 0] <= 0.25**2 / (2 * 2.0) + 1e-3
    np.testing.assert_allclose(rs2[-1], stream[-1])


@pytest.mark.parametrize("late_share", [0.2, 0.5])
def test_shaper_lands_on_a_trajectory_end_when_cycles_skip_ticks(late_share: float) -> None:
    """A rest-to-rest move sampled by a loop that skips one or two ticks in ``late_share`` of its cycles
    (an overloaded machine): the reference lags, then catches up and stops on the end, never past it.
    (Feeding forward the target's change per nominal period overshot by 96 / 183 mrad.)"""
    sh = make_shaper()
    sh.reset(np.zeros(2))
    end = np.array([1.2, -1.8])
    T = 2.5  # a quintic over 2.5 s: peak speed 1.875 * end / T, within both joints' limits
    rng = np.random.default_rng(5)
    t, last, rs = 0.0, 0.0, []
    while t < 5.0:
        t += sh.dt * (1 + (rng.integers(1, 3) if rng.random() < late_share else 0))
        s = min(t / T, 1.0)
        rs.append(sh.step(end * (10 * s**3 - 15 * s**4 + 6 * s**5), t - last))
        last = t
    r = np.array(rs)
    assert np.max((r - end) * np.sign(end)) <= 1e-6  # never beyond the end (sub-step rounding only)
    np.testing.assert_allclose(r[-1], end, atol=1e-9)
    acc = np.diff(r, n=2, axis=0) / sh.dt**2  # the positions sent keep the acceleration limits
    assert np.all(np.abs(acc) <= np.array([2.0, 8.0]) * (1 + 1e-6))


def _adversarial_targets(rng: np.random.Generator, dt: float) -> np.ndarray:
    """A target stream as the loop may see it: a move sampled with late and skipped cycles, jumps,
    a stop at speed, a run into a limit."""
    kind = rng.integers(4)
    n = 400
    if kind == 0:  # a smooth move whose samples come late or skip ticks (an overloaded cycle)
        t = np.cumsum(dt * (1 + rng.choice([0, 0, 0, 1, 2], n) + rng.uniform(0, 0.5, n)))
        s = np.clip(t / t[-1] * 1.3, 0, 1)
        s = s * s * (3 - 2 * s)
        return np.outer(s, rng.uniform(-1.4, 1.4, 2))
    if kind == 1:  # jumps to random points, held for random times
        pts = rng.uniform([-1.6, -2.1], [1.6, 2.1], (8, 2))
        return np.repeat(pts, rng.integers(1, 150, 8), axis=0)
    if kind == 2:  # a ramp at speed that stops dead
        t = np.arange(n) * dt
        return np.outer(np.minimum(t, rng.uniform(0.1, 1.5)), rng.uniform(-2, 2, 2))
    return np.outer(np.arange(n) * dt, rng.uniform(-3, 3, 2))  # through a limit


def test_shaper_positions_sent_keep_the_limits_whatever_the_targets() -> None:
    for seed in range(64):
        rng = np.random.default_rng(seed)
        sh = make_shaper(margin=1e-3)
        sh.reset(np.zeros(2))
        targets = _adversarial_targets(rng, sh.dt)
        rs, _ = run_shaper(sh, np.clip(targets, [-1.5, -2.0], [1.5, 2.0]))
        rs = np.vstack([np.zeros(2), rs])  # from rest at 0
        v = np.diff(rs, axis=0) / sh.dt
        acc = np.diff(np.vstack([np.zeros(2), v]), axis=0) / sh.dt  # from rest: the first step counts
        # Judged on the positions sent (what a module executes), not on the shaper's own velocity.
        assert np.all(np.abs(v) <= sh.max_vel * (1 + 1e-9) + 1e-12), seed
        assert np.all(np.abs(acc) <= sh.max_acc * (1 + 1e-6) + 1e-9), (seed, np.max(np.abs(acc) / sh.max_acc))
        assert np.all(rs >= sh.lower - 1e-12) and np.all(rs <= sh.upper + 1e-12), seed


class _VectorShaper:
    """The reference shaper's law in its numpy form (the oracle of the joint-by-joint one)."""

    def __init__(self, limits: JointLimits, dt: float) -> None:
        self.lim, self.dt = limits, dt
        self.r = self.v = self.g_prev = None

    def stopping_point(self) -> np.ndarray:
        a, dt = self.lim.max_acc, self.dt
        if not self.v.any():
            return self.r.copy()
        d = braking_distance(np.maximum(np.abs(self.v) - a * dt, 0.0), a, dt)
        return self.lim.clip(self.r + np.sign(self.v) * d)

    def step(self, target: np.ndarray, elapsed: float | None) -> np.ndarray:
        lim, dt = self.lim, self.dt
        a, vmax = lim.max_acc, lim.max_vel
        g = lim.clip(target)
        if self.r is None:
            self.r, self.v = g, np.zeros_like(g)
            return g.copy()
        if not self.v.any() and np.array_equal(g, self.r) and (self.g_prev is None
                                                                or np.array_equal(g, self.g_prev)):
            self.g_prev = g
            return self.r.copy()
        h = dt if elapsed is None else max(float(elapsed), 0.25 * dt)
        u = np.zeros_like(g) if self.g_prev is None else np.clip((g - self.g_prev) / h, -vmax, vmax)
        self.g_prev = g
        r, v = self.r, self.v
        e = (g - u * dt) - r
        v_des = np.clip(u + np.sign(e) * braking_speed(np.abs(e), a, dt), -vmax, vmax)
        ahead = g + u * np.abs(u) / (2.0 * a) - r
        cap = braking_speed(np.abs(ahead), a, dt)
        v_des = np.clip(v_des, np.where(ahead < 0.0, -cap, -vmax), np.where(ahead > 0.0, cap, vmax))
        up, down = lim.stop_speeds(r, dt)
        v_des = np.clip(v_des, -down, up)
        r_new = r + (v + np.clip(v_des - v, -a * dt, a * dt)) * dt
        step = (g - r) / dt
        land = (np.abs(step - v) <= a * dt) & (np.abs(step) <= a * dt) & (u == 0)
        self.r = lim.clip(np.where(land, g, r_new))
        self.v = (self.r - r) / dt
        return self.r.copy()


def test_shaper_gives_the_vector_laws_numbers_bit_for_bit() -> None:
    """The shaper runs its law joint by joint on floats: the same operations in the same order as the
    law's numpy form, so the same references, velocities and stopping points, bit for bit (adversarial
    streams, late cycles, holds, signed zeros at the limits)."""
    limits = JointLimits([-1.5, -2.0], [1.5, 2.0], [1.0, 2.0], [2.0, 8.0])
    for seed in range(48):
        rng = np.random.default_rng(seed)
        sh = ReferenceShaper(limits, 0.004, 1e-3 if seed % 2 else 0.0)
        oracle = _VectorShaper(sh.limits, sh.dt)
        targets = np.clip(_adversarial_targets(rng, sh.dt), [-1.5, -2.0], [1.5, 2.0])
        if seed % 3 == 0:
            targets[rng.integers(len(targets), size=20)] = np.array([-0.0, 0.0])
        sh.reset(targets[0])
        oracle.step(targets[0], None)
        for k, g in enumerate(targets):
            if k % 97 == 50:
                sh.hold_still()
                oracle.g_prev = None
            elapsed = None if rng.random() < 0.7 else sh.dt * rng.choice([0.1, 1.0, 1.3, 2.0, 3.0])
            got, want = sh.step(g, elapsed), oracle.step(g, elapsed)
            assert got.tobytes() == want.tobytes() and sh.v.tobytes() == oracle.v.tobytes(), (seed, k)
            assert sh.stopping_point().tobytes() == oracle.stopping_point().tobytes(), (seed, k)


def test_shaper_refuses_a_target_that_is_not_finite() -> None:
    sh = make_shaper()
    sh.reset(np.zeros(2))
    for bad in ([np.nan, 0.0], [0.0, np.inf]):
        with pytest.raises(InvalidInputError):
            sh.step(np.array(bad))
    np.testing.assert_array_equal(sh.step(np.array([0.1, 0.0])), sh.r)  # still usable


def test_backoff_doubles_to_a_cap_and_resets() -> None:
    b = Backoff(0.1, 0.5)
    assert [b.next_delay() for _ in range(5)] == pytest.approx([0.1, 0.2, 0.4, 0.5, 0.5])
    b.reset()
    assert b.next_delay() == pytest.approx(0.1)


# ------------------------------------------------------------------------------------------------
# DriverLoop against the real driver core and emulated modules on an in-process virtual bus
# ------------------------------------------------------------------------------------------------


class SilenceableArm(EmulatedArm):
    """Emulated modules where chosen ids stop answering."""

    silenced: set[int]

    def handle(self, msg: can.Message) -> list[can.Message]:
        out = super().handle(msg)
        return [m for m in out if (m.arbitration_id & 0x1F) not in self.silenced]


class FlakyBus(can.BusABC):
    """A virtual bus that can be 'lost' on demand and reopened (like ReconnectingBus)."""

    def __init__(self, channel: str) -> None:
        self._channel = channel
        self._bus: can.BusABC | None = can.Bus(interface="virtual", channel=channel)
        self.lost = False
        self.refuse_reopen = False
        self.sent: list[can.Message] = []
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.lost or self._bus is None:
            raise BusError("bus lost (test)")
        self.sent.append(msg)
        self._bus.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.lost or self._bus is None:
            raise BusError("bus lost (test)")
        return self._bus.recv(timeout), False

    def reopen(self) -> None:
        if self.refuse_reopen:
            raise BusError("server still down (test)")
        if self._bus is not None:
            self._bus.shutdown()
        self._bus = can.Bus(interface="virtual", channel=self._channel)
        self.lost = False

    def shutdown(self) -> None:
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        super().shutdown()


@pytest.fixture
def rig():
    """Emulated 3-module arm served on a virtual channel, a DriverLoop on the same channel."""
    arm = SilenceableArm.kinematic(LOWER, UPPER, VMAX, AMAX, q0=Q0)
    arm.silenced = set()
    logs: list[tuple[int, str]] = []
    cfg = LoopConfig(rate_hz=100.0, poll_hz=20.0, hold_on_stream_stop_s=0.3, reconnect_first_s=0.02,
                     reconnect_max_s=0.1)
    with loop_rig(arm, cfg, FlakyBus, log=lambda lvl, msg: logs.append((lvl, msg))) as r:
        yield {**r, "logs": logs}


def start_running(rig) -> DriverLoop:
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE), loop.snapshot().reason
    ok, msg = loop.request("init", timeout=20)
    assert ok, msg
    assert loop.state is LoopState.RUNNING
    return loop


def test_loop_polls_when_idle_and_refuses_commands(rig) -> None:
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE)
    assert wait_until(lambda: len(rig["samples"]) >= 2)
    np.testing.assert_allclose(rig["samples"][-1].positions, [0.3, -0.2, 0.1], atol=1e-6)
    assert rig["samples"][-1].target is None
    ok, why = loop.accepting_commands()
    assert not ok and "idle" in why


def test_loop_follows_a_trajectory_after_init(rig) -> None:
    loop = start_running(rig)
    arm = rig["arm"]
    np.testing.assert_allclose(arm.positions(), [0.0, 0.0, 0.0], atol=1e-3)  # homed to 0
    goal = np.array([0.4, -0.3, 0.5])
    loop.commands.set_trajectory([0, 1, 2], [0.5, 1.0], np.array([goal / 2, goal]), start=time.monotonic())
    assert wait_until(lambda: np.allclose(arm.positions(), goal, atol=2e-3), timeout=5)
    snap = loop.snapshot()
    assert snap.state is LoopState.RUNNING and snap.cycles > 10
    assert snap.period["rate_hz"] > 0  # (no speed assertions in tests; see benchmarks/)
    assert all(s.lost == 0 for s in snap.module_stats)


def test_limit_beyond_range_is_clamped_before_sending(rig) -> None:
    loop = start_running(rig)
    loop.commands.set_trajectory([1], [0.2], np.array([[3.0]]), start=time.monotonic())  # upper is 1.5
    arm = rig["arm"]
    assert wait_until(lambda: abs(arm.positions()[1] - 1.5) < 2e-3, timeout=5)
    time.sleep(0.2)
    assert arm.positions()[1] <= 1.5 + 1e-6
    assert loop.snapshot().clamps > 0
    assert any("clamped" in m for _l, m in rig["logs"])
    fsteps = [struct.unpack_from("<f", bytes(m.data), 2)[0] for m in list(rig["host"].sent)
              if m.arbitration_id == 0x0E2 and len(m.data) == 8 and m.data[1] == 0x10]
    assert fsteps and max(fsteps) <= 1.5 + 1e-6


def test_silent_module_halts_all_until_recover(rig) -> None:
    loop = start_running(rig)
    arm = rig["arm"]
    loop.commands.set_trajectory([0, 1, 2], [2.0], np.array([[1.0, 1.0, 1.0]]), start=time.monotonic())
    assert wait_until(lambda: arm.positions()[0] > 0.1)
    arm.silenced = {2}
    assert wait_until(lambda: loop.state is LoopState.HALTED, timeout=3)
    snap = loop.snapshot()
    assert "module 2" in snap.reason
    q_halt = np.array(arm.positions())
    time.sleep(0.3)
    np.testing.assert_allclose(arm.positions(), q_halt, atol=0.05)  # braked, not following
    assert not loop.accepting_commands()[0]
    arm.silenced = set()
    ok, msg = loop.request("recover", timeout=10)
    assert ok, msg
    q0 = np.array(arm.positions())
    time.sleep(0.3)
    # Recovered: holding where it stopped, the old trajectory is not resumed.
    np.testing.assert_allclose(arm.positions(), q0, atol=1e-3)


def test_a_second_driver_on_the_bus_is_seen_and_everything_halts(rig) -> None:
    from redarm_ros.can.driver_core import FaultKind, ForeignHostError, PowerCubeArmDriver

    loop = start_running(rig)
    loop.commands.set_trajectory([0], [2.0], np.array([[1.0]]), start=time.monotonic())
    # Another driver (any name, any namespace: the bus does not know) polls the same modules.
    with can.Bus(interface="virtual", channel=rig["host"]._channel) as other_bus:
        other = PowerCubeArmDriver(other_bus, [1, 2, 3], LOWER, UPPER, VMAX, AMAX, reply_timeout_s=0.05)
        end = time.monotonic() + 10.0
        while loop.state is LoopState.RUNNING and time.monotonic() < end:
            try:
                other.read_state()
            except ForeignHostError:  # the other one sees our loop's replies too, as it should; go on
                pass
            time.sleep(0.02)
    assert loop.state is LoopState.HALTED
    fault = loop.snapshot().fault
    assert fault is not None and fault.kind is FaultKind.FOREIGN_HOST, fault
    assert any("another host is driving these modules" in m for _l, m in rig["logs"])
    assert all(rig["arm"][i].state() & protocol.ActState.HALTED for i in (1, 2, 3))


def test_the_reason_on_diagnostics_says_what_the_arm_does_now(rig) -> None:
    loop = start_running(rig)
    assert loop.snapshot().reason == "holding position"  # (not the stale "init done; ...")
    loop.commands.set_trajectory([0], [0.3], np.array([[0.2]]), start=time.monotonic())
    assert "following a trajectory" in loop.snapshot().reason
    ok, _ = loop.request("halt")
    assert ok and loop.snapshot().reason == "halted on request"
    ok, _ = loop.request("recover")
    assert ok and loop.snapshot().reason == "holding position"
    loop.commands.set_stream_target([1], [0.1], time.monotonic())
    assert loop.snapshot().reason == "following streamed targets"


def test_a_request_made_before_start_waits_for_the_bus(rig) -> None:
    loop = rig["loop"]
    answer: list[tuple[bool, str]] = []
    t = threading.Thread(target=lambda: answer.append(loop.request("init", timeout=30)))
    t.start()  # e.g. ~/init called right after the node came up, before its cycle started
    time.sleep(0.2)
    loop.start()
    t.join(40)
    assert answer and answer[0][0], answer
    assert loop.state is LoopState.RUNNING


def test_halt_request_then_recover(rig) -> None:
    loop = start_running(rig)
    ok, msg = loop.request("halt")
    assert ok and loop.state is LoopState.HALTED, msg
    ok, msg = loop.request("recover")
    assert ok and loop.state is LoopState.RUNNING, msg
    ok, msg = loop.request("bogus")
    assert not ok


def test_bus_loss_reconnects_and_holds_measured_position(rig) -> None:
    loop = start_running(rig)
    arm = rig["arm"]
    host = rig["host"]
    loop.commands.set_trajectory([0], [3.0], np.array([[1.5]]), start=time.monotonic())
    assert wait_until(lambda: arm.positions()[0] > 0.2)
    host.refuse_reopen = True
    host.lost = True
    assert wait_until(lambda: loop.state is LoopState.CONNECTING, timeout=3)
    time.sleep(0.3)  # several refused reopen attempts
    host.refuse_reopen = False
    assert wait_until(lambda: loop.state is LoopState.RUNNING, timeout=5), loop.snapshot().reason
    q_back = arm.positions()[0]
    # The trajectory from before the loss is not resumed: the arm comes to rest within its braking
    # distance of where it was when the bus came back, and stays there. (Cut off mid-move, the
    # module brakes onto its last target; on a starved machine it can still be moving when the bus
    # returns, so "where it was during the gap" is not a fixed point.)
    assert wait_until(lambda: _at_rest(arm), timeout=5)
    q_rest = np.array(arm.positions())
    braking = VMAX[0] ** 2 / (2 * AMAX[0])
    assert abs(q_rest[0] - q_back) <= braking + 1e-3, (q_back, q_rest)
    time.sleep(0.5)  # the trajectory would have moved joint 0 by another 0.2 rad by now
    np.testing.assert_allclose(arm.positions(), q_rest, atol=1e-3)
    snap = loop.snapshot()
    assert snap.bus_losses == 1 and snap.connects == 2


def _at_rest(arm, window_s: float = 0.1) -> bool:
    q0 = np.array(arm.positions())
    time.sleep(window_s)
    return bool(np.all(np.abs(np.array(arm.positions()) - q0) < 1e-4))


def test_stream_stop_holds(rig) -> None:
    loop = start_running(rig)
    arm = rig["arm"]
    for k in range(20):
        loop.commands.set_stream_target([2], [0.005 * k], time.monotonic())
        time.sleep(0.01)
    assert loop.commands.mode is CommandMode.STREAM
    time.sleep(0.5)  # > hold_on_stream_stop_s
    assert loop.commands.mode is CommandMode.HOLD
    # The hold target is the measured position when the stream expired (the kinematic test plant
    # wobbles around a stream's end, so it is near, not at, the last target), and it stays put.
    hold = loop.commands.sample(time.monotonic(), np.zeros(3), np.full(3, 9.0))
    assert hold[2] == pytest.approx(0.095, abs=0.03)
    assert not np.any(hold == 9.0)
    time.sleep(1.0)
    q = np.array(arm.positions())
    np.testing.assert_allclose(q, hold, atol=2e-3)
    time.sleep(0.2)
    np.testing.assert_allclose(arm.positions(), q, atol=1e-3)


def test_stop_ends_the_thread_and_closes_the_bus(rig) -> None:
    loop = start_running(rig)
    bus = loop.bus
    assert isinstance(bus, FlakyBus) and bus._bus is not None
    loop.stop(timeout=30.0)
    assert loop.state is LoopState.STOPPED
    assert not any(t.name == "can-driver-loop" for t in threading.enumerate())
    assert loop.bus is None and bus._bus is None  # shut down by the loop, not by the rig's teardown


def _halt_frames(sent: list[can.Message], since: float) -> list[float]:
    """Send times of the HALT commands (to any module 1..3) and haltAll broadcasts sent after ``since``."""
    halts = {(m.arbitration_id, bytes(m.data)) for m in
             [protocol.command(mid, Command.HALT) for mid in (1, 2, 3)] + [protocol.halt_all()]}
    return [m.timestamp for m in list(sent)
            if (m.arbitration_id, bytes(m.data)) in halts and m.timestamp >= since]


def test_halt_during_init_stops_homing_at_once() -> None:
    # Homing from far away takes seconds (ramp velocity half of VMAX): a halt meanwhile must stop the
    # modules at once, not queue behind the init; the init then fails.
    arm = EmulatedArm.kinematic(LOWER, UPPER, VMAX, AMAX, q0=[1.8, -1.2, 1.5])
    cfg = LoopConfig(rate_hz=100.0, poll_hz=20.0)
    with loop_rig(arm, cfg, FlakyBus) as r:
        loop = r["loop"].start()
        assert wait_until(lambda: loop.state is LoopState.IDLE), loop.snapshot().reason
        answer: list[tuple[bool, str]] = []
        t = threading.Thread(target=lambda: answer.append(loop.request("init", timeout=30)))
        t.start()
        assert wait_until(lambda: arm.positions()[0] < 1.6, timeout=10)  # homing under way
        t_req = time.time()
        ok, msg = loop.request("halt", timeout=10)
        t_answer = time.time()
        t.join(10)
        assert ok, msg
        assert answer and not answer[0][0] and "halted during homing" in answer[0][1], answer
        halts = _halt_frames(r["host"].sent, t_req)
        # Generous bounds (a busy machine): homing would have taken about 3 s more.
        assert halts and halts[0] - t_req < 1.0, halts[:1]
        assert t_answer - t_req < 2.0
        assert loop.state is LoopState.HALTED
        q_halt = np.array(arm.positions())
        assert q_halt[0] > 0.8  # stopped where it was, far from home (0 rad)
        time.sleep(0.3)
        np.testing.assert_allclose(arm.positions(), q_halt, atol=0.05)
        ok, msg = loop.request("recover", timeout=10)  # never homed: refused
        assert not ok and "never initialised" in msg, msg
        ok, msg = loop.request("init", timeout=30)  # the halt request is spent: init runs
        assert ok and loop.state is LoopState.RUNNING, msg


def test_recover_before_init_is_refused(rig) -> None:
    loop = rig["loop"].start()
    assert wait_until(lambda: loop.state is LoopState.IDLE)
    ok, msg = loop.request("recover", timeout=10)
    assert not ok and "never initialised" in msg and "~/init" in msg, msg
    assert loop.state is LoopState.IDLE and not loop.accepting_commands()[0]
    ok, msg = loop.request("halt", timeout=10)
    assert ok and loop.state is LoopState.HALTED, msg
    ok, msg = loop.request("recover", timeout=10)
    assert not ok and "never initialised" in msg, msg
    assert loop.state is LoopState.HALTED and not loop.accepting_commands()[0]


def test_halt_runs_even_when_its_caller_stopped_waiting(rig) -> None:
    loop = start_running(rig)
    arm = rig["arm"]
    loop.commands.set_trajectory([0], [3.0], np.array([[1.5]]), start=time.monotonic())
    assert wait_until(lambda: arm.positions()[0] > 0.1)
    loop.request("halt", timeout=0.0)  # the caller gives up at once: the halt is run all the same
    assert wait_until(lambda: loop.state is LoopState.HALTED, timeout=3), loop.snapshot().reason
    assert wait_until(lambda: _at_rest(arm), timeout=3)
    assert arm.positions()[0] < 1.0


def test_a_command_dropped_mid_motion_brakes_to_a_stop_and_never_comes_back() -> None:
    """clear(None) while the reference moves at speed (a refused command): the hold is where the
    reference comes to rest, so it brakes monotonically instead of returning to the measured position
    it had passed."""
    dt = 0.01
    shaper = make_shaper(dt)
    src = JointCommandSource(2)
    src.set_trajectory([0, 1], [2.0], np.array([[1.2, 1.8]]), start=0.0)
    q_meas = np.zeros(2)
    ref = shaper.step(src.sample(0.0, np.zeros(2), q_meas, shaper.stopping_point()))
    for k in range(1, 60):  # accelerate for 0.6 s
        ref = shaper.step(src.sample(k * dt, ref, q_meas, shaper.stopping_point()))
    assert np.all(shaper.v > 0.3)
    q_meas = ref - 0.05  # the measured position lags behind the reference
    src.clear(None)
    shaper.hold_still()  # as the loop does when the command turns into a hold
    path = [ref]
    for k in range(60, 400):
        path.append(shaper.step(src.sample(k * dt, path[-1], q_meas, shaper.stopping_point())))
    P = np.array(path)
    assert np.all(np.diff(P, axis=0) >= -1e-12), "the reference came back"
    np.testing.assert_allclose(P[-1], P[-2], atol=1e-12)  # at rest
    assert np.all(P[-1] > path[0])  # it stopped beyond where the command was dropped
