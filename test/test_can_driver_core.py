"""Host-side PowerCube driver: scripted frame-by-frame tests on a fake clock (no threads), then the
driver against emulated modules on a thread over an in-process virtual bus and over the loopback
remote bus (reconnect)."""

from __future__ import annotations

import math
import struct
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterator

import can
import numpy as np
import pytest

from redarm_ros import errors
from redarm_ros.can import protocol as p
from redarm_ros.can.bus import open_bus
from redarm_ros.can.bus_server import LoopbackBusServer
from redarm_ros.can.driver_core import (
    FOREIGN_REPLIES,
    FOREIGN_WINDOW_S,
    DriverState,
    FaultKind,
    ForeignHostError,
    PowerCubeArmDriver,
)
from redarm_ros.can.module_emulator import EmulatedArm, EmulatorRunner, KinematicPlant
from redarm_ros.can.protocol import ActConfig, ActState

S = ActState
N = 3
IDS = [1, 2, 3]
LOWER, UPPER = [-1.5] * N, [1.5] * N
VMAX, AMAX = [1.0] * N, [10.0] * N


pytestmark = pytest.mark.usefixtures("no_open_buses")


class FakeClock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


Responder = Callable[[can.Message], list[can.Message]]


class ScriptedBus(can.BusABC):
    """Records every sent frame as (id, hex); replies come from ``responder`` and become
    receivable ``delay_s`` later on the fake clock; a receive that has to wait advances the
    clock (so deadlines pass without sleeping)."""

    def __init__(self, clock: FakeClock, responder: Responder | None = None, delay_s: float = 0.0) -> None:
        super().__init__(channel="scripted")
        self.clock = clock
        self.responder = responder
        self.delay_s = delay_s
        self.sent: list[tuple[int, str]] = []
        self.rx: deque[can.Message] = deque()
        self._ready: deque[float] = deque()
        self.fail: BaseException | None = None

    def inject(self, msg: can.Message) -> None:
        """Queue a frame that is receivable at once."""
        self.rx.append(msg)
        self._ready.append(self.clock.t)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail is not None:
            raise self.fail
        self.sent.append((msg.arbitration_id, bytes(msg.data).hex(" ")))
        if self.responder is not None:
            for reply in self.responder(msg):
                self.rx.append(reply)
                self._ready.append(self.clock.t + self.delay_s)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail is not None:
            raise self.fail
        if self.rx:
            wait = self._ready[0] - self.clock.t
            if wait <= 0 or timeout is None or wait <= timeout:
                self.clock.t += max(0.0, wait)
                self._ready.popleft()
                return self.rx.popleft(), False
        if timeout:
            self.clock.t += timeout
        return None, False

    def recv(self, timeout: float | None = None) -> can.Message | None:
        # One wait on the fake clock: BusABC.recv would retry until *real* time ran out, advancing
        # the fake clock by the timeout on every retry.
        return self._recv_internal(timeout)[0]

    def take(self) -> list[tuple[int, str]]:
        out, self.sent = self.sent, []
        return out


def f32hex(x: float) -> str:
    return struct.pack("<f", x).hex(" ")


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def arm(clock: FakeClock) -> EmulatedArm:
    return EmulatedArm.kinematic(LOWER, UPPER, [2.0] * N, [20.0] * N, q0=[0.2, -0.1, 0.0], clock=clock)


@pytest.fixture
def scripted(clock: FakeClock, arm: EmulatedArm) -> Iterator[ScriptedBus]:
    bus = ScriptedBus(clock, arm.handle)
    yield bus
    bus.shutdown()


def make_driver(bus: can.BusABC, clock: Callable[[], float] = time.perf_counter, **kw) -> PowerCubeArmDriver:
    return PowerCubeArmDriver(bus, IDS, LOWER, UPPER, VMAX, AMAX, clock=clock, **kw)


def ready_driver(bus: can.BusABC, clock: Callable[[], float] = time.perf_counter, **kw) -> PowerCubeArmDriver:
    """``make_driver``, initialised without homing (READY at the emulated modules' positions)."""
    drv = make_driver(bus, clock, **kw)
    drv.init(home=False)
    return drv


# ------------------------------------------------------------------------------------------------
# Scripted: discovery, init, the cycle byte by byte
# ------------------------------------------------------------------------------------------------


def test_discovery_reports_a_missing_module(clock: FakeClock, arm: EmulatedArm) -> None:
    arm[3].silenced = True
    with ScriptedBus(clock, arm.handle) as bus:
        report = make_driver(bus, clock).discover()
        assert report.found == {1: 0x0D1A, 2: 0x0D1A} and report.missing == [3] and not report.complete
        # the scan, then one retry for the silent id, as the vendor library's GETPARAM DEF_VERSION
        assert bus.take() == [(0x0C1, "0a 1d"), (0x0C2, "0a 1d"), (0x0C3, "0a 1d"), (0x0C3, "0a 1d")]


def test_init_configures_resets_homes_and_holds(scripted: ScriptedBus, arm: EmulatedArm, clock) -> None:
    drv = make_driver(scripted, clock)
    with pytest.raises(errors.RedarmError, match="init"):
        drv.cycle([0.0] * N, 0.004)
    assert scripted.take() == []
    st = drv.init()
    sent = scripted.take()
    cfg_set = [s for s in sent if s[1].startswith("08 39")]
    assert cfg_set == [(0x0E0 + i, "08 39 00 00 00 08") for i in IDS]  # SYNC_MOTION on
    assert [(0x0E0 + i, "00") for i in IDS] == [s for s in sent if s[1] == "00"]  # RESET each
    assert [(0x0E0 + i, "01") for i in IDS] == [s for s in sent if s[1] == "01"]  # HOME each
    assert all(s & S.HOME_OK for s in st.states)
    assert np.allclose(st.positions, 0.0) and drv.state is DriverState.READY
    assert all(arm[i].config_bits & ActConfig.SYNC_MOTION for i in IDS)


def test_init_with_a_missing_module_raises_timeout(clock: FakeClock, arm: EmulatedArm) -> None:
    arm[2].silenced = True
    with ScriptedBus(clock, arm.handle) as bus:
        t0 = clock.t
        with pytest.raises(errors.BusTimeoutError, match="module 2 did not answer .*3 requests") as info:
            make_driver(bus, clock).init()
        assert info.value.module_id == 2
        assert info.value.timeout_s == pytest.approx(0.14)
        assert clock.t - t0 < 0.5  # reported after the three waits, not later


@pytest.mark.parametrize("delay_s", [0.03, 0.05, 0.07, 0.1, 0.13])
def test_init_and_recover_wait_for_modules_that_answer_late(clock: FakeClock, arm: EmulatedArm,
                                                            delay_s: float) -> None:
    # Every reply late (a module process descheduled on a busy machine), beyond the 0.02 s a cycle
    # waits: the retries' longer waits get the answers, and the late duplicates of the retried
    # ACT_CONFIG read (the value from before the configuration) do not pass for the read-back.
    with ScriptedBus(clock, arm.handle, delay_s=delay_s) as bus:
        drv = make_driver(bus, clock, watchdog_refresh=True)
        st = drv.init()
        assert drv.state is DriverState.READY and all(s & S.HOME_OK for s in st.states)
        assert all(arm[i].config_bits & ActConfig.SYNC_MOTION for i in IDS)
        assert (0x100, "07 00") in bus.take()  # the watchdog refreshed before a retry
        drv.halt()
        drv.recover()
        assert drv.state is DriverState.READY


class FrozenMachineBus(ScriptedBus):
    """A ScriptedBus on a machine that stops now and then (a throttled container, a UML guest whose
    host is busy): :meth:`freeze` makes the next receive that has to wait sleep ``freeze_s`` longer
    than asked, with the modules' stand-in stopped too: replies due meanwhile become receivable only
    after it. That receive comes back empty (the driver's timer fired first), or, ``woken_by_frame``,
    with the first reply (the stand-in ran first), the others ``delay_s`` apart after it."""

    def __init__(self, clock: FakeClock, responder: Responder, delay_s: float) -> None:
        super().__init__(clock, responder, delay_s)
        self._freeze_s = 0.0
        self._woken_by_frame = False

    def freeze(self, freeze_s: float, *, woken_by_frame: bool = False) -> None:
        self._freeze_s, self._woken_by_frame = freeze_s, woken_by_frame

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        ready_now = bool(self.rx) and self._ready[0] <= self.clock.t
        if self._freeze_s and timeout and not ready_now:
            self.clock.t += timeout + self._freeze_s
            self._freeze_s = 0.0
            first = self.clock.t if self._woken_by_frame else self.clock.t + self.delay_s
            self._ready = deque(first + self.delay_s * i for i in range(len(self._ready)))
            if not self._woken_by_frame:
                return None, False
        return super()._recv_internal(timeout)


def test_a_stall_of_the_whole_machine_is_not_a_silent_module(clock: FakeClock, arm: EmulatedArm) -> None:
    # The driver and the modules' stand-in both stop for 0.3 s while replies are due: on waking,
    # the driver does not count the time it was not running, and the replies, sent after the stall,
    # answer this cycle (not lost now and late in the next), and the HALT's acks are collected.
    with FrozenMachineBus(clock, arm.handle, delay_s=0.005) as bus:
        drv = ready_driver(bus, clock)
        q = drv.read_state().positions
        for woken_by_frame in (False, True, False, True):
            bus.freeze(0.3, woken_by_frame=woken_by_frame)
            t0 = clock.t
            res = drv.cycle(q, 0.02)
            assert res.replied.all() and res.lost == 0, res
            assert clock.t - t0 < 0.3 + 2 * drv.reply_timeout_s
        assert drv.cycle(q, 0.02).late == 0  # nothing of the stalled cycle comes in late
        bus.freeze(0.3)
        assert drv.halt() == IDS


def test_after_a_stall_a_silent_module_is_still_found_within_a_bounded_wait(clock: FakeClock,
                                                                           arm: EmulatedArm) -> None:
    with FrozenMachineBus(clock, arm.handle, delay_s=0.005) as bus:
        drv = ready_driver(bus, clock)
        q = drv.read_state().positions
        arm[2].silenced = True
        bus.freeze(0.3)
        t0 = clock.t
        res = drv.cycle(q, 0.02)
        assert res.replied.tolist() == [True, False, True] and res.lost == 1
        # the wait asked for and the stall, which happened anyway, then the timeout once more
        assert clock.t - t0 == pytest.approx(0.3 + 2 * drv.reply_timeout_s)


def test_init_reports_a_module_that_does_not_take_its_configuration(clock: FakeClock,
                                                                    arm: EmulatedArm) -> None:
    def refusing(msg: can.Message) -> list[can.Message]:  # module 2 acks SETPARAM ACT_CONFIG, keeps 0
        if msg.arbitration_id == 0x0E2 and bytes(msg.data[:2]) == b"\x08\x39":
            return [can.Message(arbitration_id=0x0A2, data=b"\x08\x39\x64\x00", is_extended_id=False)]
        return arm.handle(msg)

    with ScriptedBus(clock, refusing) as bus:
        refused = "module 2 did not take ACT_CONFIG 0x00000000"
        with pytest.raises(errors.ModuleFaultError, match=refused) as info:
            make_driver(bus, clock).init()
        assert info.value.module_id == 2


def test_cycle_frames_byte_by_byte(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = ready_driver(scripted, clock, watchdog_refresh=True)
    scripted.take()
    q = np.array([0.201, -0.098, 0.003])
    res = drv.cycle(q, 0.004)
    assert scripted.take() == [
        (0x0E1, "0b 10 " + f32hex(0.201) + " 04 00"),
        (0x0E2, "0b 10 " + f32hex(-0.098) + " 04 00"),
        (0x0E3, "0b 10 " + f32hex(0.003) + " 04 00"),
        (0x100, "0f 00"),  # startMotionAll
        (0x100, "07 00"),  # watchdog refresh
    ]
    assert res.replied.all() and res.lost == 0 and res.malformed == 0 and res.clamped == ()
    # positions are the ones before the move (the modules had not moved yet)
    assert res.positions == pytest.approx([0.2, -0.1, 0.0], abs=1e-6)
    assert np.array_equal(res.targets, q)
    assert all(s & S.RAMP_END for s in res.states) and res.fault is None


def test_cycle_duration_is_rounded_to_ms(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = ready_driver(scripted, clock)
    scripted.take()
    drv.cycle(None, 0.0104)
    assert scripted.take()[0][1].endswith("0a 00")  # 10 ms
    drv.cycle(None, 1e-5)
    assert scripted.take()[0][1].endswith("01 00")  # at least 1 ms


def test_nan_target_is_refused_before_anything_is_sent(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = ready_driver(scripted, clock)
    scripted.take()
    for bad in ([0.0, math.nan, 0.0], [0.0, 0.0, math.inf], [0.0, 0.0]):
        with pytest.raises(errors.InvalidInputError):
            drv.cycle(bad, 0.004)
    with pytest.raises(errors.InvalidInputError):
        drv.cycle([0.0] * N, 0.0)
    assert scripted.take() == []


def test_targets_clamped_to_limits_and_speed(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = ready_driver(scripted, clock)
    res = drv.cycle([0.2, -0.1, 9.0], 0.01)  # joint 3: beyond the limit, and a 1.5 rad jump
    assert res.clamped == (2,)
    assert res.clamped_to_limits.tolist() == [False, False, True]
    assert res.clamped_step.tolist() == [False, False, True]
    assert res.targets[2] == pytest.approx(0.0 + 1.0 * 0.01)  # max_vel * dt from the held target
    res = drv.cycle([0.2, -0.1, 9.0], 0.01)
    assert res.targets[2] == pytest.approx(0.02)
    res = drv.cycle([0.2, -0.1, 0.025], 0.01)
    assert res.clamped == () and res.targets[2] == 0.025


def test_targets_are_numpys_clips_to_the_bit(scripted: ScriptedBus, clock: FakeClock) -> None:
    """The cycle clamps joint by joint on floats: exactly numpy's clip into the limits, then within
    max_vel * dt of the last target, and the masks and clamped joints of those two clips."""
    drv = ready_driver(scripted, clock)
    rng = np.random.default_rng(11)
    last = drv.cycle(None, 0.01).targets
    for k in range(40):
        dt = float(rng.choice([0.002, 0.004, 0.01]))
        target = rng.uniform(drv.lower - 0.5, drv.upper + 0.5) if k % 4 else last + rng.normal(0, 1e-3, N)
        inside = np.clip(target, drv.lower, drv.upper)
        step = drv.max_vel * dt
        want = np.clip(inside, last - step, last + step)
        res = drv.cycle(target, dt)
        assert res.targets.tobytes() == want.tobytes(), k
        assert res.clamped_to_limits.tolist() == (inside != target).tolist(), k
        assert res.clamped_step.tolist() == (want != inside).tolist(), k
        assert res.clamped == tuple(np.flatnonzero((inside != target) | (want != inside)).tolist()), k
        last = res.targets


def test_hold_when_no_target(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = ready_driver(scripted, clock)
    drv.cycle([0.21, -0.1, 0.0], 0.01)
    res = drv.cycle(None, 0.01)
    assert res.targets == pytest.approx([0.21, -0.1, 0.0])


def test_latency_and_velocity_on_the_fake_clock(clock: FakeClock, arm: EmulatedArm) -> None:
    with ScriptedBus(clock, arm.handle, delay_s=0.0005) as bus:  # every reply arrives 0.5 ms later
        drv = ready_driver(bus, clock)
        results = []
        for k in range(40):  # joint 1 ramps at 0.01 rad per cycle
            res = drv.cycle([0.2 + 0.01 * k, -0.1, 0.0], 0.01)
            results.append(res)
            clock.t += 0.01
        assert res.latency_s == pytest.approx([0.0005] * N, abs=1e-9)
        assert drv.stats[0].latency_max_ms == pytest.approx(0.5)
        assert drv.stats[0].latency_median_ms == pytest.approx(0.5)
        prev = results[-2]
        v = (res.positions - prev.positions) / (res.stamp - prev.stamp)  # finite difference
        assert res.velocities == pytest.approx(v)
        assert res.velocities[0] == pytest.approx(1.0, rel=0.01)  # catching up at ACT_FMAXVEL
        assert res.velocities[1] == pytest.approx(0.0, abs=1e-6)


# ------------------------------------------------------------------------------------------------
# Scripted: faults
# ------------------------------------------------------------------------------------------------


def _halts(sent: list[tuple[int, str]]) -> list[tuple[int, str]]:
    return [s for s in sent if s[1] in ("02", "02 00")]


def test_silenced_module_halts_all_and_raises_once(scripted: ScriptedBus, arm: EmulatedArm, clock) -> None:
    drv = ready_driver(scripted, clock, max_missed=3)
    drv.cycle(None, 0.004)
    scripted.take()
    arm[2].silenced = True
    for k in range(2):
        res = drv.cycle(None, 0.004)
        assert res.lost == 1 and res.replied.tolist() == [True, False, True]
        assert drv.stats[1].consecutive_misses == k + 1
    assert _halts(scripted.take()) == []
    with pytest.raises(errors.BusTimeoutError) as info:
        drv.cycle(None, 0.004)
    assert info.value.module_id == 2 and info.value.timeout_s == drv.reply_timeout_s
    assert str(info.value.cycle_result.fault).startswith("module 2 stopped answering")
    assert _halts(scripted.take()) == [(0x0E1, "02"), (0x0E2, "02"), (0x0E3, "02"), (0x100, "02 00")]
    assert drv.state is DriverState.FAULT and drv.stats[1].silent
    # afterwards: no second raise, the cycle only holds the measured position
    res = drv.cycle([1.0, 1.0, 1.0], 0.004)
    assert res.holding and res.targets == pytest.approx(res.positions)
    assert drv.stats[1].lost == 4
    # the module comes back: recover resets all and holds
    arm[2].silenced = False
    st = drv.recover()
    assert drv.state is DriverState.READY and not drv.stats[1].silent
    assert not any(s & S.HALTED for s in st.states)


def test_module_error_halts_all_and_reports_cause(scripted: ScriptedBus, arm: EmulatedArm, clock) -> None:
    drv = ready_driver(scripted, clock)
    drv.cycle([0.3, -0.1, 0.0], 0.004)
    with arm.lock:
        arm[1].inject_fault(S.POWERFAULT)
    scripted.take()
    res = drv.cycle([0.3, -0.1, 0.0], 0.004)
    assert str(res.fault) == "module 1: ERROR|POWERFAULT" and res.fault.kind is FaultKind.MODULE_ERROR
    assert res.fault.bits == {1: S.ERROR | S.POWERFAULT}
    assert drv.state is DriverState.FAULT
    assert _halts(scripted.take()) == [(0x0E1, "02"), (0x0E2, "02"), (0x0E3, "02"), (0x100, "02 00")]
    # ERROR refuses motion until RESET: holding cycles do not move anything
    at = arm.positions()
    clock.t += 1.0
    res = drv.cycle([0.5, 0.5, 0.5], 0.004)
    assert res.holding and res.fault is None
    assert arm.positions() == pytest.approx(at, abs=0.05)
    drv.recover()
    res = drv.cycle([0.35, -0.1, 0.0], 0.004)
    assert not res.holding and res.fault is None and drv.state is DriverState.READY


def test_tow_error_state_frame_is_a_fault(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = ready_driver(scripted, clock)
    scripted.inject(p.state_frame(3, S.ERROR | S.TOW_ERROR))  # unsolicited, before the cycle
    res = drv.cycle(None, 0.004)
    assert res.fault.bits == {3: S.ERROR | S.TOW_ERROR} and "TOW_ERROR" in str(res.fault)
    assert drv.state is DriverState.FAULT


def test_soft_limit_refusal_is_reported(clock: FakeClock) -> None:
    # Module soft limits tighter than the driver's: the module refuses, the driver reports.
    arm = EmulatedArm.kinematic([-0.5] * N, [0.5] * N, [2.0] * N, [20.0] * N, clock=clock)
    with ScriptedBus(clock, arm.handle) as bus:
        drv = ready_driver(bus, clock)
        for k in range(1, 100):
            res = drv.cycle([min(0.01 * k, 1.0), 0.0, 0.0], 0.01)
            clock.t += 0.01
            if res.fault:
                break
        assert res.fault.bits == {1: S.ERROR | S.BEYOND_SOFT}
        assert arm.positions()[0] <= 0.5
        drv.recover()  # RESET clears BEYOND_SOFT; the module is inside its limits again
        assert drv.state is DriverState.READY


def forged_ack(module_id: int, position: float) -> can.Message:
    """A well-formed FSTEP_EXT acknowledgement claiming ``position`` (what a forging node would send)."""
    return p.set_move_ext_ack(module_id, p.MoveMode.FSTEP_EXT, position, 0x20, 0)


def test_forged_reply_is_refused_and_the_genuine_one_taken(clock: FakeClock, arm: EmulatedArm) -> None:
    forge = {"on": False}

    def responder(msg: can.Message) -> list[can.Message]:
        out = arm.handle(msg)
        if forge["on"] and msg.arbitration_id == 0x0E2:
            out = [forged_ack(2, 1.4), *out]  # arrives first, 1.5 rad from where module 2 is
        return out

    with ScriptedBus(clock, responder) as bus:
        drv = ready_driver(bus, clock)
        forge["on"] = True
        res = drv.cycle(None, 0.004)
        assert res.implausible == 1 and res.replied.all() and res.fault is None
        assert res.positions[1] == pytest.approx(-0.1, abs=1e-6)  # the genuine reply, not 1.4
        assert drv.stats[1].implausible == 1 and drv.stats[1].last_implausible == pytest.approx(1.4)
        assert drv.state is DriverState.READY


def test_only_implausible_replies_are_a_fault(clock: FakeClock, arm: EmulatedArm) -> None:
    def responder(msg: can.Message) -> list[can.Message]:
        if msg.arbitration_id == 0x0E3 and bytes(msg.data[:2]) == b"\x0b\x10":
            arm.handle(msg)
            return [forged_ack(3, 1.2)]  # module 3's encoder "jumps": every reply implausible
        return arm.handle(msg)

    with ScriptedBus(clock, responder) as bus:
        drv = ready_driver(bus, clock, max_missed=3)
        faults = []
        for _ in range(3):
            res = drv.cycle(None, 0.004)
            assert res.positions[2] == pytest.approx(0.0, abs=1e-6)  # never the implausible value
            faults.append(res.fault)
        assert faults[:2] == [None, None]
        assert faults[2].kind is FaultKind.IMPLAUSIBLE and faults[2].module_ids == (3,)
        assert "implausible" in str(faults[2]) and drv.state is DriverState.FAULT
        assert all(arm[i].state() & S.HALTED for i in IDS)


def test_implausible_position_read_is_refused(clock: FakeClock, arm: EmulatedArm) -> None:
    mode = {"forge": False}

    def responder(msg: can.Message) -> list[can.Message]:
        out = arm.handle(msg)
        if mode["forge"] and (msg.arbitration_id, bytes(msg.data)) == (0x0C1, b"\x0a\x3c"):
            return [p.get_param_reply(1, p.Param.ACT_FPOS, 2.5)]  # instead of the genuine reply
        return out

    with ScriptedBus(clock, responder) as bus:
        drv = ready_driver(bus, clock)
        mode["forge"] = True
        with pytest.raises(errors.ImplausibleMeasurementError) as info:
            drv.read_state()
        assert info.value.module_id == 1 and info.value.value == pytest.approx(2.5)
        mode["forge"] = False
        assert drv.read_state().positions[0] == pytest.approx(0.2, abs=1e-6)
        # init re-establishes the positions (homing): no reference, any position accepted
        mode["forge"] = True
        with pytest.raises(errors.ImplausibleMeasurementError):
            drv.recover()


def test_recover_restores_what_a_power_cycled_module_lost(clock: FakeClock, arm: EmulatedArm) -> None:
    with ScriptedBus(clock, arm.handle) as bus:
        drv = ready_driver(bus, clock, enable_watchdog=True)
        assert arm[2].config_bits & ActConfig.WATCHDOG_ENABLE
        # "Power cycle" module 2: factory configuration, factory limits, no watchdog.
        with arm.lock:
            fresh = type(arm[2])(2, arm[2].plant, arm[2].cfg, clock=clock)
            arm.modules[2] = fresh
        assert not fresh.config_bits & (ActConfig.WATCHDOG_ENABLE | ActConfig.SYNC_MOTION)
        drv.recover()
        cfg = arm[2].config_bits
        assert cfg & ActConfig.WATCHDOG_ENABLE and cfg & ActConfig.SYNC_MOTION
        assert not cfg & ActConfig.DISABLE_ACK
        assert arm[2]._read_param(p.Param.ACT_FMAXVEL) == pytest.approx(VMAX[1])
        assert arm[2]._read_param(p.Param.ACT_FMAXACC) == pytest.approx(AMAX[1])
        # The watchdog is armed again: without refreshes the module halts by itself.
        clock.t += 1.0
        assert arm[2].state() & S.COMM_ERROR


def test_recover_while_moving_holds_where_the_arm_comes_to_rest(clock: FakeClock, arm: EmulatedArm) -> None:
    with ScriptedBus(clock, arm.handle) as bus:
        drv = ready_driver(bus, clock)
        q = np.array(arm.positions())
        for _ in range(100):  # joint 1 at its full 1 rad/s (braking distance 0.05 rad at 10 rad/s^2)
            clock.t += 0.004
            q[0] += 0.004
            drv.cycle(q, 0.004)
        assert arm[1].state() & S.MOTION
        st = drv.recover()
        clock.t += 1.0
        rest = np.array(arm.positions())
        # What recover holds is where the arm came to rest, not a reading taken while it braked (the
        # hold then drove it back by up to its braking distance).
        np.testing.assert_allclose(st.positions, rest, atol=1e-4)
        res = drv.cycle(None, 0.004)
        np.testing.assert_allclose(res.targets, rest, atol=1e-4)


def _foreign_replies(arm: EmulatedArm, bus: ScriptedBus, count: int) -> None:
    """Another host's requests answered by the modules: the replies reach this driver's bus."""
    for k in range(count):
        for reply in arm.handle(p.get_param(1 + k % N, p.Param.ACT_FPOS)):
            bus.inject(reply)


def test_replies_nobody_here_asked_for_halt_everything_as_another_host(clock: FakeClock,
                                                                        arm: EmulatedArm) -> None:
    with ScriptedBus(clock, arm.handle) as bus:
        drv = ready_driver(bus, clock)
        # A few (a tool reading a parameter) are no second driver ...
        _foreign_replies(arm, bus, 5)
        for _ in range(3):
            clock.t += 0.004
            assert drv.cycle(None, 0.004).fault is None
        # ... nor are forged replies with positions the modules cannot be at ...
        forged = p.set_move_ext_ack(2, p.MoveMode.FSTEP_EXT, 1.4, 0x20, 0)
        for _ in range(50):
            bus.inject(forged)
        clock.t += 0.004
        assert drv.cycle(None, 0.004).fault is None and drv.state is DriverState.READY
        # ... but a stream of them is another host driving the modules: everything halts.
        clock.t += FOREIGN_WINDOW_S + 0.1  # (the few above have aged out of the window)
        _foreign_replies(arm, bus, FOREIGN_REPLIES)
        bus.take()
        res = drv.cycle(None, 0.004)
        assert res.fault is not None and res.fault.kind is FaultKind.FOREIGN_HOST, res.fault
        assert "another host" in res.fault.message and set(res.fault.module_ids) == set(IDS)
        assert drv.state is DriverState.FAULT
        assert [(0x0E0 + i, "02") for i in IDS] == [s for s in bus.take() if s[1] == "02"]  # HALT each
        assert all(arm[i].state() & S.HALTED for i in IDS)


def test_another_host_is_detected_while_polling_too(clock: FakeClock, arm: EmulatedArm) -> None:
    with ScriptedBus(clock, arm.handle) as bus:
        drv = make_driver(bus, clock)  # idle: never initialised, only polling the state
        drv.read_state()
        _foreign_replies(arm, bus, FOREIGN_REPLIES)
        with pytest.raises(ForeignHostError, match="another host"):
            drv.read_state()
        assert drv.state is DriverState.FAULT and drv.fault.kind is FaultKind.FOREIGN_HOST
        # Still there: not reported again while in that fault.
        _foreign_replies(arm, bus, FOREIGN_REPLIES)
        drv.read_state()


def test_every_frame_is_stamped_with_its_send_time(clock: FakeClock, arm: EmulatedArm) -> None:
    stamps: list[float] = []

    def responder(msg: can.Message) -> list[can.Message]:
        stamps.append(msg.timestamp)
        return arm.handle(msg)

    with ScriptedBus(clock, responder) as bus:
        drv = ready_driver(bus, clock)
        n0 = len(stamps)
        t0 = time.time()
        drv.cycle(None, 0.004)
        t1 = time.time()
        cycle = stamps[n0:]  # every frame of the cycle, stamped when it was sent
        assert len(cycle) >= N + 1 and all(t0 <= t <= t1 for t in cycle), (t0, cycle, t1)


def test_a_flood_of_foreign_frames_does_not_stall_the_cycle(clock: FakeClock, arm: EmulatedArm) -> None:
    with ScriptedBus(clock, arm.handle) as bus:
        drv = ready_driver(bus, clock)
        for k in range(5000):  # a backlog far larger than one drain reads
            bus.inject(can.Message(arbitration_id=0x123, data=[k % 256], is_extended_id=False))
        res = drv.cycle(None, 0.004)  # the drain stops early; the receive loop skips the rest
        while not res.replied.all():
            res = drv.cycle(None, 0.004)
        assert res.fault is None and drv.state is DriverState.READY


def test_recover_fails_while_a_fault_persists(clock: FakeClock, arm: EmulatedArm) -> None:
    persist = {"on": False}

    def responder(msg: can.Message) -> list[can.Message]:
        out = arm.handle(msg)
        if persist["on"] and (msg.arbitration_id, bytes(msg.data)) == (0x0E2, b"\x00"):  # RESET of module 2
            with arm.lock:
                arm[2].inject_fault(S.POWERFAULT)  # the cause is still there
        return out

    with ScriptedBus(clock, responder) as bus:
        drv = make_driver(bus, clock)
        drv.init(home=False)
        persist["on"] = True
        drv.halt()
        with pytest.raises(errors.ModuleFaultError) as info:
            drv.recover()
        assert info.value.module_id == 2 and info.value.state & S.POWERFAULT
        assert drv.state is DriverState.HALTED
        with pytest.raises(errors.ModuleFaultError) as info:
            drv.init(home=False)  # init does not get past it either
        assert info.value.module_id == 2
        assert drv.state is DriverState.UNINITIALIZED


def test_recover_is_refused_unless_initialised(clock: FakeClock, arm: EmulatedArm) -> None:
    # Without a successful init the positions were never established by homing: recover must not
    # make such an arm movable, and it sends nothing.
    with ScriptedBus(clock, arm.handle) as bus:
        drv = make_driver(bus, clock)
        with pytest.raises(errors.RequestRefusedError, match="never initialised"):
            drv.recover()
        assert drv.state is DriverState.UNINITIALIZED and not bus.take()
        with pytest.raises(errors.RedarmError):
            drv.cycle(None, 0.004)
        drv.halt()  # a halted, never-initialised arm: still refused
        with pytest.raises(errors.RequestRefusedError):
            drv.recover()
        assert drv.state is DriverState.HALTED


def test_recover_is_refused_when_a_module_lost_home_ok(clock: FakeClock, arm: EmulatedArm) -> None:
    # A module restarted (power-cycled) after init has no HOME_OK and its position is not the
    # arm's any more: recover refuses, halts, and only init (re-homing) helps.
    with ScriptedBus(clock, arm.handle) as bus:
        drv = make_driver(bus, clock)
        drv.init()
        drv.halt()
        with arm.lock:
            arm[2]._st &= ~int(S.HOME_OK)  # as a power-cycled module reports
        with pytest.raises(errors.ModuleFaultError, match=r"modules \[2\] report no HOME_OK") as info:
            drv.recover()
        assert info.value.module_id == 2
        assert drv.state is DriverState.HALTED and not drv.initialised
        with pytest.raises(errors.RequestRefusedError):
            drv.recover()
        drv.init()
        assert drv.state is DriverState.READY
        drv.halt()
        drv.recover()
        assert drv.state is DriverState.READY


def test_malformed_and_late_frames_are_counted_and_ignored(clock: FakeClock, arm: EmulatedArm) -> None:
    held: list[can.Message] = []
    mode = {"delay": False, "garbage": False}

    def responder(msg: can.Message) -> list[can.Message]:
        out = arm.handle(msg)
        if mode["garbage"] and msg.arbitration_id == 0x0E2:
            junk = can.Message(arbitration_id=0x0A2, data=b"\x0b\x10\x00", is_extended_id=False)
            nan = can.Message(
                arbitration_id=0x0A2,
                data=b"\x0b\x10" + struct.pack("<f", math.nan) + b"\x00\x00",
                is_extended_id=False,
            )
            out = [junk, nan, *out]
        if mode["delay"] and msg.arbitration_id == 0x0E3:
            held.extend(out)  # answer later
            return []
        return out

    with ScriptedBus(clock, responder) as bus:
        drv = ready_driver(bus, clock, max_missed=5)
        mode["garbage"] = True
        res = drv.cycle(None, 0.004)
        assert res.malformed == 2 and res.replied.all() and drv.stats[1].malformed == 2
        mode["garbage"], mode["delay"] = False, True
        res = drv.cycle(None, 0.004)
        assert res.lost == 1 and not res.replied[2]
        mode["delay"] = False
        for m in held:  # the late reply shows up before the next cycle's
            bus.inject(m)
        res = drv.cycle(None, 0.004)
        assert res.late == 1 and res.replied.all() and drv.stats[2].late == 1


def test_bus_failure_then_resync_never_replays_the_old_target(
    scripted: ScriptedBus, clock: FakeClock
) -> None:
    drv = ready_driver(scripted, clock)
    drv.cycle([0.25, -0.1, 0.0], 0.01)
    scripted.fail = OSError(32, "Broken pipe")
    with pytest.raises(errors.BusError, match="CAN bus failed"):
        drv.cycle([0.26, -0.1, 0.0], 0.01)
    scripted.fail = None  # "reopened" by its owner
    clock.t += 1.0
    res = drv.cycle([0.3, -0.1, 0.0], 0.01)
    assert res.resynced and res.targets == pytest.approx(res.positions)  # held, not 0.3
    res = drv.cycle([0.3, -0.1, 0.0], 0.01)
    assert not res.resynced and res.targets[0] == pytest.approx(res.positions[0] + 0.01, abs=2e-3)


def test_reconnect_needs_a_reopenable_bus(scripted: ScriptedBus, clock: FakeClock) -> None:
    drv = make_driver(scripted, clock)
    with pytest.raises(errors.BusError, match="cannot be reopened"):
        drv.reconnect()


def test_constructor_validation(scripted: ScriptedBus) -> None:
    with pytest.raises(errors.InvalidInputError):
        PowerCubeArmDriver(scripted, [1, 1, 2], LOWER, UPPER, VMAX, AMAX)
    with pytest.raises(errors.InvalidInputError):
        PowerCubeArmDriver(scripted, [1, 2, 40], LOWER, UPPER, VMAX, AMAX)
    with pytest.raises(errors.InvalidInputError):
        PowerCubeArmDriver(scripted, IDS, LOWER, UPPER[:2], VMAX, AMAX)
    with pytest.raises(errors.InvalidInputError):
        PowerCubeArmDriver(scripted, IDS, UPPER, LOWER, VMAX, AMAX)
    with pytest.raises(errors.InvalidInputError):
        PowerCubeArmDriver(scripted, IDS, LOWER, UPPER, [0.0] * N, AMAX)


# ------------------------------------------------------------------------------------------------
# Against emulated modules on a thread (real time), in-process virtual bus
# ------------------------------------------------------------------------------------------------


@pytest.fixture
def live() -> Iterator[tuple[PowerCubeArmDriver, EmulatedArm]]:
    ch = f"drv-{uuid.uuid4().hex[:8]}"
    host = can.Bus(interface="virtual", channel=ch)
    dev = can.Bus(interface="virtual", channel=ch)
    arm = EmulatedArm.kinematic(
        LOWER, UPPER, [2.0] * N, [20.0] * N, q0=[0.3, -0.2, 0.1], watchdog_timeout_s=0.3
    )
    runner = EmulatorRunner(dev, arm, tick_s=0.002).start()
    drv = PowerCubeArmDriver(host, IDS, LOWER, UPPER, VMAX, AMAX, reply_timeout_s=0.2)
    try:
        yield drv, arm
    finally:
        runner.stop()
        host.shutdown()
        dev.shutdown()


class _PlantLog:
    """A module's plant that records, in order, the moves it starts and the positions it reads out.

    Judging the arm by the module's own record makes the check independent of scheduling: a module
    thread that got no CPU for a while starts its moves late and its arm lags the host's clock,
    but it still starts exactly the targets the driver sent, in order, and reports where it is.
    """

    def __init__(self, plant: KinematicPlant) -> None:
        self._plant = plant
        # ("move", target, duration) or ("read", position, None), in the module's order
        self.events: list[tuple[str, float, float | None]] = []

    def __getattr__(self, name: str) -> object:
        return getattr(self._plant, name)

    def command_position(self, target: float, vel_limit: float | None = None, acc_limit: float | None = None,
                         duration_s: float | None = None) -> None:
        self._plant.command_position(target, vel_limit, acc_limit, duration_s)
        self.events.append(("move", target, duration_s))

    def position(self) -> float:
        x = self._plant.position()
        self.events.append(("read", x, None))
        return x


def test_live_init_homes_and_follows_a_trajectory(live) -> None:
    drv, arm = live
    st = drv.init()
    assert all(s & S.HOME_OK for s in st.states) and st.positions == pytest.approx([0.0] * N, abs=1e-6)
    with arm.lock:
        logs = [_PlantLog(arm[i].plant) for i in IDS]
        for i, log in zip(IDS, logs, strict=True):
            arm[i].plant = log
    dt = 0.004
    sent, reported = [], []
    for k in range(1, 250):  # smooth start from rest: 0.3 (1 - cos(pi t)), within the limits
        target = 0.3 * (1 - math.cos(math.pi * k * dt)) * np.array([1.0, -1.0, 0.5])
        res = drv.cycle(target, dt)
        assert res.replied.all() and res.fault is None
        assert res.targets == pytest.approx(target, abs=1e-12)  # slower than VMAX: nothing clamped
        sent.append(target)
        reported.append(res.positions)
        time.sleep(dt)
    time.sleep(0.3)
    assert arm.positions() == pytest.approx(res.targets, abs=1e-6)  # arrived on the last target
    assert all(s.lost == 0 and s.replies == 249 for s in drv.stats)
    # What each module did, in its own order (its thread may have run late; that changes when, not
    # what): it started the driver's target of every cycle with the cycle's duration, and the
    # position the driver reported for cycle k is one the module read out after starting the move of
    # cycle k-1 and before starting that of cycle k (the FSTEP of a cycle is answered before its
    # STARTMOVE). A wrong sign or unit, a dropped, repeated or late command fails here at once.
    for j, log in enumerate(logs):
        moves = [(x, d) for kind, x, d in log.events if kind == "move"]
        assert len(moves) == len(sent), f"joint {j}: {len(moves)} moves started for {len(sent)} cycles"
        started = np.array(moves)
        assert np.abs(started[:, 0] - np.array(sent)[:, j]).max() < 1e-6, f"joint {j}: other targets"
        assert started[:, 1] == pytest.approx(dt), f"joint {j}: other durations"
        reads: list[list[float]] = [[]]  # positions read out between two started moves
        for kind, x, _ in log.events:
            if kind == "move":
                reads.append([])
            else:
                reads[-1].append(x)
        for k, q in enumerate(reported):
            assert any(abs(q[j] - x) <= 1e-6 for x in reads[k]), f"joint {j} cycle {k + 1}: {q[j]} never read"


def test_live_watchdog_trips_when_cycles_stop(live) -> None:
    drv, arm = live
    drv.enable_watchdog = drv.watchdog_refresh = True
    drv.init(home=False)
    for _ in range(20):
        assert drv.cycle(None, 0.01).fault is None
        time.sleep(0.01)
    time.sleep(1.0)  # host "hangs": no traffic for longer than the 0.3 s watchdog
    res = drv.cycle(None, 0.01)
    assert res.fault and all(bits & S.COMM_ERROR for bits in res.fault.bits.values())
    assert "module 1: ERROR|COMM_ERROR" in str(res.fault)  # the report says it was the watchdog
    assert drv.state is DriverState.FAULT
    drv.recover()
    assert drv.cycle(None, 0.01).fault is None


# ------------------------------------------------------------------------------------------------
# Over the loopback remote bus: the bus dies and comes back
# ------------------------------------------------------------------------------------------------


def test_remote_bus_loss_reconnect_holds_measured_position() -> None:
    server = LoopbackBusServer().start()
    port = server.port
    dev = open_bus(**server.client_config())
    host = open_bus(**server.client_config())
    arm = EmulatedArm.kinematic(LOWER, UPPER, [2.0] * N, [20.0] * N, homed=True)
    runner = EmulatorRunner(dev, arm, tick_s=0.002).start()
    try:
        drv = PowerCubeArmDriver(host, IDS, LOWER, UPPER, VMAX, AMAX, reply_timeout_s=0.5)
        drv.init(home=False)
        for k in range(1, 30):
            drv.cycle([0.004 * k, 0.0, 0.0], 0.01)
            time.sleep(0.005)
        server.stop()
        with pytest.raises(errors.BusError):
            for _ in range(50):
                drv.cycle([0.2, 0.0, 0.0], 0.01)
        with pytest.raises(errors.BusError):
            drv.reconnect()  # no server yet
        server = LoopbackBusServer(port=port).start()
        deadline = time.monotonic() + 10.0
        while True:  # the caller's backoff loop
            try:
                st = drv.reconnect()
                break
            except errors.BusError:
                assert time.monotonic() < deadline, "could not reconnect"
                time.sleep(0.05)
        held = st.positions.copy()
        res = drv.cycle([0.2, 0.0, 0.0], 0.01)
        assert not res.resynced  # reconnect() already re-read the positions
        assert res.targets[0] == pytest.approx(min(0.2, held[0] + 0.01))
        assert abs(res.targets[0] - held[0]) <= 0.01 + 1e-9  # no jump to a stale command
    finally:
        runner.stop()
        host.shutdown()
        dev.shutdown()
        server.stop()


@pytest.mark.parametrize("silence_s", [0.5, 30.0])
def test_a_position_jump_after_a_silence_is_refused(clock: FakeClock, arm: EmulatedArm,
                                                    silence_s: float) -> None:
    # A module silent for a while comes back restarted, its position lost (0.39 rad off). The velocity
    # bound alone (max_vel times the silence) would take any jump after long enough; the module
    # cannot have moved further than where it was sent plus its braking distance.
    with ScriptedBus(clock, arm.handle) as bus:
        drv = ready_driver(bus, clock, max_missed=3)
        for _ in range(3):
            drv.cycle(None, 0.004)
        arm[1].silenced = True
        with pytest.raises(errors.BusTimeoutError):
            for _ in range(5):
                drv.cycle(None, 0.004)
        clock.t += silence_s
        q1 = arm.positions()[0]
        with arm.lock:  # "power cycle" module 1 at another position
            plant = KinematicPlant(q1 - 0.39, lower=LOWER[0], upper=UPPER[0], max_vel=VMAX[0],
                                   max_acc=AMAX[0], clock=clock)
            arm.modules[1] = type(arm[1])(1, plant, arm[1].cfg, clock=clock)
        with pytest.raises(errors.ImplausibleMeasurementError, match="~/init") as info:
            drv.read_state()
        assert info.value.module_id == 1
        with pytest.raises(errors.ModuleFaultError):
            drv.recover()
        assert drv.state is not DriverState.READY
        # Back where it was (within its braking distance): accepted.
        with arm.lock:
            plant = KinematicPlant(q1 + 0.01, lower=LOWER[0], upper=UPPER[0], max_vel=VMAX[0],
                                   max_acc=AMAX[0], clock=clock)
            arm.modules[1] = type(arm[1])(1, plant, arm[1].cfg, clock=clock)
        assert drv.read_state().positions[0] == pytest.approx(q1 + 0.01, abs=1e-6)
