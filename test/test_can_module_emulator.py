"""Emulated PowerCube modules: scripted frame-by-frame behaviour on a fake clock, the kinematic
plant, and the runner serving an in-process virtual bus."""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Iterator

import can
import pytest

from redarm_ros.can import protocol as p
from redarm_ros.can.module_emulator import (
    PARAM_ACCESS,
    EmulatedArm,
    EmulatorRunner,
    KinematicPlant,
    ParamAccess,
    Plant,
    PowerCubeModule,
    wire_time,
)
from redarm_ros.can.protocol import ActConfig, ActState, Param
from redarm_ros.errors import InvalidInputError

S = ActState


class FakeClock:
    """A settable clock (s)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        # The plant integrates lazily up to the clock's time at its next query.
        self.t += dt


pytestmark = pytest.mark.usefixtures("no_open_buses")


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


def make_arm(clock: FakeClock, n: int = 3, **kw) -> EmulatedArm:
    return EmulatedArm.kinematic(
        [-2.0] * n, [2.0] * n, [1.0] * n, [10.0] * n, clock=clock, homed=kw.pop("homed", True), **kw
    )


def raw(msgs: list[can.Message]) -> list[tuple[int, str]]:
    return [(m.arbitration_id, bytes(m.data).hex(" ")) for m in msgs]


def decoded(msgs: list[can.Message]) -> list[p.Frame]:
    return [p.decode(m) for m in msgs]


def state_of(arm: EmulatedArm, mid: int) -> ActState:
    (reply,) = decoded(arm.handle(p.get_param(mid, Param.ACT_STATE)))
    return ActState(reply.value)


# ------------------------------------------------------------------------------------------------
# Scripted byte-by-byte exchanges
# ------------------------------------------------------------------------------------------------


def test_version_scan_answers_only_existing_ids(clock: FakeClock) -> None:
    arm = make_arm(clock, n=2)
    assert raw(arm.handle(p.get_param(1, Param.DEF_VERSION))) == [(0x0A1, "0a 1d 1a 0d")]
    assert raw(arm.handle(p.get_param(2, Param.DEF_VERSION))) == [(0x0A2, "0a 1d 1a 0d")]
    assert arm.handle(p.get_param(3, Param.DEF_VERSION)) == []


def test_simple_command_acks_are_exact(clock: FakeClock) -> None:
    arm = make_arm(clock)
    assert raw(arm.handle(p.reset(2))) == [(0x0A2, "00")]
    assert raw(arm.handle(p.home(2))) == [(0x0A2, "01")]
    assert raw(arm.handle(p.halt(2))) == [(0x0A2, "02")]
    assert raw(arm.handle(p.watchdog(2))) == [(0x0A2, "07")]
    assert raw(arm.handle(p.set_param(2, Param.ACT_FRAMPVEL, 0.5))) == [(0x0A2, "08 4f")]


def test_broadcasts_are_never_answered(clock: FakeClock) -> None:
    arm = make_arm(clock)
    for bc in (p.reset_all(), p.start_motion_all(), p.watchdog_refresh_all(), p.save_pos_all()):
        assert arm.handle(bc) == []
    # replies and state frames of other nodes are ignored, too
    assert arm.handle(p.command_ack(1, p.Command.RESET)) == []
    assert arm.handle(p.state_frame(1, S.ERROR)) == []


def test_home_sets_inprogress_then_home_ok(clock: FakeClock) -> None:
    arm = EmulatedArm.kinematic([-2.0], [2.0], [1.0], [10.0], q0=[0.8], clock=clock)
    assert not state_of(arm, 1) & S.HOME_OK
    arm.handle(p.home(1))
    st = state_of(arm, 1)
    assert st & S.INPROGRESS and st & S.MOTION and not st & S.HOME_OK
    clock.advance(5.0)
    st = state_of(arm, 1)
    assert st & S.HOME_OK and not st & S.INPROGRESS and st & S.RAMP_END
    assert arm.positions() == [0.0]


def test_fstep_ext_ack_carries_position_before_the_move(clock: FakeClock) -> None:
    arm = make_arm(clock)
    (ack,) = decoded(arm.handle(p.fstep(1, 0.3, 500)))
    assert ack == p.SetMoveExtAck(
        1, p.MoveMode.FSTEP_EXT, 0.0, p.ShortState.MOTION | p.ShortState.INPROGRESS, 0
    )
    clock.advance(2.0)
    (ack,) = decoded(arm.handle(p.fstep(1, 0.3, 10)))
    assert ack.position == pytest.approx(0.3, abs=1e-7)  # float32 of the reached position
    assert not ack.short_state & p.ShortState.ERROR


def test_plain_setmove_ack_and_framp_moves(clock: FakeClock) -> None:
    arm = make_arm(clock)
    assert raw(arm.handle(p.framp(3, -0.5))) == [(0x0A3, "0b 04")]
    clock.advance(5.0)
    assert arm.positions()[2] == pytest.approx(-0.5)
    (rep,) = decoded(arm.handle(p.get_param(3, Param.ACT_FPOS)))
    assert rep.value == pytest.approx(-0.5, abs=1e-7)


def test_soft_limit_refusal_sets_error_and_beyond_soft_until_reset(clock: FakeClock) -> None:
    arm = make_arm(clock)
    out = decoded(arm.handle(p.fstep(1, 2.5, 100)))
    ack, state_frame = out
    assert isinstance(ack, p.SetMoveExtAck) and ack.short_state & p.ShortState.ERROR
    assert state_frame == p.StateFrame(1, S.ERROR | S.BEYOND_SOFT | S.HOME_OK)
    clock.advance(1.0)
    assert arm.positions()[0] == 0.0  # refused: nothing moved
    st = state_of(arm, 1)
    assert st & S.ERROR and st & S.BEYOND_SOFT
    # ERROR refuses motion, also inside the limits
    arm.handle(p.fstep(1, 0.2, 100))
    clock.advance(1.0)
    assert arm.positions()[0] == 0.0
    # RESET clears and motion works again
    assert raw(arm.handle(p.reset(1))) == [(0x0A1, "00")]
    st = state_of(arm, 1)
    assert not st & (S.ERROR | S.BEYOND_SOFT)
    arm.handle(p.fstep(1, 0.2, 100))
    clock.advance(2.0)
    assert arm.positions()[0] == pytest.approx(0.2)


def test_limit_equal_target_in_float32_is_accepted(clock: FakeClock) -> None:
    upper = math.radians(177.0)  # not representable in float32
    arm = EmulatedArm.kinematic([-upper], [upper], [3.0], [30.0], clock=clock, homed=True)
    arm.handle(p.framp(1, upper))
    clock.advance(5.0)
    assert not state_of(arm, 1) & S.ERROR
    assert arm.positions()[0] == pytest.approx(upper, abs=1e-6)


def test_injected_fault_refuses_motion_until_reset(clock: FakeClock) -> None:
    arm = make_arm(clock)
    arm.handle(p.framp(2, 1.0))
    clock.advance(0.1)
    with arm.lock:
        arm[2].inject_fault(S.POWERFAULT)
    assert decoded(arm.tick()) == [p.StateFrame(2, S.ERROR | S.POWERFAULT | S.HOME_OK)]
    moving_at = arm.positions()[1]
    clock.advance(2.0)
    stopped_at = arm.positions()[1]
    assert stopped_at < 1.0 and stopped_at - moving_at < 0.1  # braked, did not finish the move
    st = state_of(arm, 2)
    assert st & S.ERROR and st & S.POWERFAULT
    arm.handle(p.framp(2, 1.0))
    clock.advance(3.0)
    assert arm.positions()[1] == stopped_at
    arm.handle(p.reset(2))
    arm.handle(p.framp(2, 1.0))
    clock.advance(3.0)
    assert arm.positions()[1] == pytest.approx(1.0)


def test_fault_emits_one_state_frame(clock: FakeClock) -> None:
    arm = make_arm(clock)
    with arm.lock:
        arm[1].inject_fault(S.TOW_ERROR)
        arm[1].inject_fault(S.POWERFAULT)  # already in ERROR: no second frame
    assert decoded(arm.tick()) == [p.StateFrame(1, S.ERROR | S.TOW_ERROR | S.HOME_OK)]


def test_bank_injects_a_fault_by_id(clock: FakeClock) -> None:
    arm = make_arm(clock)
    arm.inject_fault(3, S.BEYOND_SOFT)
    assert decoded(arm.tick()) == [p.StateFrame(3, S.ERROR | S.BEYOND_SOFT | S.HOME_OK)]
    with pytest.raises(InvalidInputError, match="no module with id 9"):
        arm.inject_fault(9, S.ERROR)


def test_power_cycle_brings_a_module_back_with_factory_settings(clock: FakeClock) -> None:
    arm = make_arm(clock, homed=False)
    arm.handle(p.home(2))
    clock.advance(3.0)
    arm.handle(p.set_param(2, Param.ACT_FMAXPOS, 1.0))
    arm.handle(p.framp(2, 0.8))
    clock.advance(0.2)
    arm.handle(p.set_param(2, Param.ACT_CONFIG, int(ActConfig.WATCHDOG_ENABLE)))
    assert state_of(arm, 2) & S.HOME_OK
    arm.power_cycle(2)
    at = arm.positions()[1]
    clock.advance(2.0)
    assert arm.positions()[1] - at < 0.1  # braked and held, the move not finished
    assert not state_of(arm, 2) & S.HOME_OK  # homing lost
    (cfg,) = decoded(arm.handle(p.get_param(2, Param.ACT_CONFIG)))
    (upper,) = decoded(arm.handle(p.get_param(2, Param.ACT_FMAXPOS)))
    assert cfg.value == 0 and upper.value == pytest.approx(2.0)  # factory settings: no watchdog
    clock.advance(1.0)
    assert decoded(arm.tick()) == []  # and so no watchdog to expire


def test_halt_sets_halted_and_refuses_motion_until_reset(clock: FakeClock) -> None:
    arm = make_arm(clock)
    arm.handle(p.framp(1, 1.0))
    clock.advance(0.2)
    arm.handle(p.halt(1))
    clock.advance(1.0)
    at = arm.positions()[0]
    assert 0.0 < at < 1.0
    assert state_of(arm, 1) & S.HALTED
    arm.handle(p.framp(1, 1.0))
    clock.advance(2.0)
    assert arm.positions()[0] == at
    arm.handle(p.reset(1))
    assert not state_of(arm, 1) & S.HALTED
    arm.handle(p.framp(1, 1.0))  # ... and moves again after the reset
    clock.advance(3.0)
    assert arm.positions()[0] == pytest.approx(1.0)


def test_sync_motion_waits_for_startmove_broadcast(clock: FakeClock) -> None:
    arm = make_arm(clock, config=int(ActConfig.SYNC_MOTION))
    for mid, target in ((1, 0.4), (2, -0.4)):
        (ack,) = decoded(arm.handle(p.fstep(mid, target, 400)))
        assert ack.position == 0.0
    clock.advance(1.0)
    assert arm.positions()[:2] == [0.0, 0.0]  # waiting
    assert arm.handle(p.start_motion_all()) == []
    clock.advance(2.0)
    assert arm.positions()[:2] == [pytest.approx(0.4), pytest.approx(-0.4)]
    # a second STARTMOVE without a new SETMOVE does nothing
    arm.handle(p.start_motion_all())
    clock.advance(1.0)
    assert arm.positions()[0] == pytest.approx(0.4)


def test_watchdog_refreshed_by_broadcast_then_halts(clock: FakeClock) -> None:
    arm = make_arm(clock, n=2)
    for mid in (1, 2):
        arm.handle(p.set_param(mid, Param.ACT_CONFIG, int(ActConfig.WATCHDOG_ENABLE)))
    arm.handle(p.fvel(1, 0.5))
    for _ in range(10):  # 0.5 s of refreshes every 50 ms: still running
        clock.advance(0.05)
        assert arm.handle(p.watchdog_refresh_all()) == []
        assert arm.tick() == []
    assert not state_of(arm, 1) & S.ERROR
    clock.advance(0.15)  # silence > 100 ms
    frames = decoded(arm.tick())
    assert p.StateFrame(1, S.ERROR | S.HALTED | S.COMM_ERROR | S.HOME_OK) in frames
    assert p.StateFrame(2, S.ERROR | S.HALTED | S.COMM_ERROR | S.HOME_OK) in frames
    stop_at = arm.positions()[0]
    clock.advance(1.0)
    assert arm.positions()[0] == pytest.approx(stop_at, abs=0.02)  # braked to rest
    assert state_of(arm, 1) & S.COMM_ERROR
    # RESET re-arms the watchdog; it trips again without refreshes
    arm.handle(p.reset(1))
    assert not state_of(arm, 1) & S.ERROR
    clock.advance(0.2)
    assert decoded(arm.tick())[0].state & S.COMM_ERROR


def test_watchdog_refreshed_by_any_addressed_traffic(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1, config=int(ActConfig.WATCHDOG_ENABLE))
    for _ in range(10):
        clock.advance(0.06)
        arm.handle(p.get_param(1, Param.ACT_FPOS))
    assert not state_of(arm, 1) & S.ERROR
    arm.handle(p.set_param(1, Param.ACT_CONFIG, 0))  # disarm
    clock.advance(1.0)
    assert not state_of(arm, 1) & S.ERROR


def test_watchdog_judges_the_host_by_wire_time_not_by_when_frames_are_read(clock: FakeClock) -> None:
    # The host refreshed every 50 ms, but the emulator read nothing for 300 ms (it was descheduled):
    # the frames carry when they were on the bus, so the module does not blame the host.
    m = make_arm(clock, n=1, config=int(ActConfig.WATCHDOG_ENABLE))[1]
    t_armed = clock()
    clock.advance(0.3)
    for k in range(1, 7):
        assert m.handle(p.Broadcast(p.BroadcastCommand.WATCHDOG_REFRESH, 0), t_armed + 0.05 * k) == []
    assert m.tick() == [] and not m.state() & S.ERROR  # last refresh at +0.30, deadline +0.40
    # A frame sent after a real gap (> 100 ms on the wire) is too late, however soon it is read.
    out = decoded(m.handle(p.Broadcast(p.BroadcastCommand.WATCHDOG_REFRESH, 0), t_armed + 0.45))
    assert out and out[0].state & S.COMM_ERROR


def test_halted_at_is_when_the_halt_was_on_the_bus_or_the_watchdog_ran_out(clock: FakeClock) -> None:
    """A test compares when modules halted, whenever it gets to look: a HALT counts at its wire
    time, a watchdog at its deadline however late a check noticed it; RESET clears the record."""
    arm = make_arm(clock, n=2, config=int(ActConfig.WATCHDOG_ENABLE))
    m1, m2 = arm[1], arm[2]
    t0 = clock()
    assert m1.halted_at is None and m2.halted_at is None
    clock.advance(0.03)
    m1.handle(p.CommandRequest(1, p.Command.HALT), t0 + 0.02)  # read 10 ms after it was on the bus
    m1.handle(p.Broadcast(p.BroadcastCommand.HALT_ALL, 0), t0 + 0.025)  # a second HALT changes nothing
    assert m1.halted_at == pytest.approx(t0 + 0.02)
    clock.advance(0.2)  # module 2 heard nothing since t0: its watchdog ran out at t0 + 0.1
    arm.tick()
    assert m2.sticky & S.COMM_ERROR and m2.halted_at == pytest.approx(t0 + 0.1)
    m2.handle(p.CommandRequest(2, p.Command.RESET))
    assert m2.halted_at is None
    m2.inject_fault(S.HALTED)
    assert m2.halted_at == pytest.approx(clock())


def test_a_tick_judges_time_as_of_when_the_queue_was_known_empty(clock: FakeClock) -> None:
    """The reader found its queue empty, then waited 300 ms for the CPU before ticking; the host's
    refreshes of that time are not read yet. Judged as of the empty queue, nothing expired; the
    refreshes then arrive, and the next tick (now) is fine too. Judged at the late 'now' instead,
    the module would have halted (the false watchdog expiry seen under load)."""
    m = make_arm(clock, n=1, config=int(ActConfig.WATCHDOG_ENABLE))[1]
    t_armed = clock()
    clock.advance(0.3)
    assert m.tick(behind_s=0.3) == [] and not m.sticky & S.ERROR  # (a state query would judge now)
    for k in range(1, 7):
        assert m.handle(p.Broadcast(p.BroadcastCommand.WATCHDOG_REFRESH, 0), t_armed + 0.05 * k) == []
    assert m.tick() == [] and not m.sticky & S.ERROR
    # The same wait without the frames having come meanwhile: the host really was silent.
    clock.advance(0.3)
    out = decoded(m.tick(behind_s=0.15))  # deadline +0.40; judged as of +0.45
    assert out and out[0].state & S.COMM_ERROR


class _QueueBus(can.BusABC):
    """A bus whose receive finds nothing, during which the reader is descheduled (the clock moves
    on) and the host's frames queue up; they are read by the next receive."""

    def __init__(self, clock: FakeClock, frames_during_wait: list[can.Message], wait_s: float) -> None:
        super().__init__(channel="queue")
        self._clock, self._later, self._wait = clock, list(frames_during_wait), wait_s
        self._queue: list[can.Message] = []
        self.sent: list[can.Message] = []

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._queue:
            return self._queue.pop(0), False
        if self._later:  # empty now; while the reader waits for the CPU the frames come
            self._clock.advance(self._wait)
            self._queue, self._later = self._later, []
        return None, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)


def test_runner_does_not_blame_the_host_for_frames_that_came_while_it_waited(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1, config=int(ActConfig.WATCHDOG_ENABLE))
    t_armed = clock()
    refreshes = []
    for k in range(1, 7):  # every 50 ms while the reader was descheduled for 300 ms
        msg = p.watchdog_refresh_all()
        msg.timestamp = time.time() - 0.3 + 0.05 * k  # wire time: when it was on the bus
        refreshes.append(msg)
    bus = _QueueBus(clock, refreshes, 0.3)
    runner = EmulatorRunner(bus, arm, tick_s=0.0, clock=clock)
    runner.serve_once(0.0)  # finds the queue empty; descheduled; ticks
    assert not arm[1].sticky & ActState.ERROR, "blamed the host for frames not yet read"
    assert bus.sent == []  # no unsolicited error frame either
    runner.serve_once(0.0)  # reads the six refreshes, ticks
    assert runner.frames_in == 6
    assert not arm[1].sticky & ActState.ERROR and bus.sent == []
    assert clock() - t_armed == pytest.approx(0.3)


def test_wire_time_converts_a_frame_stamp_to_the_module_clock() -> None:
    now = {"t": 100.0}
    clock = lambda: now["t"]  # noqa: E731
    msg = p.watchdog_refresh_all()
    assert wire_time(msg, clock) == 100.0  # unstamped: now
    msg.timestamp = time.time() - 0.05
    assert wire_time(msg, clock) == pytest.approx(99.95, abs=0.01)
    msg.timestamp = time.time() + 5.0  # from the future: now
    assert wire_time(msg, clock) == 100.0
    msg.timestamp = time.time() - 60.0  # far too old to be a bus time: now
    assert wire_time(msg, clock) == 100.0


def test_soft_limit_change_reaches_the_plant(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1)
    arm.handle(p.set_param(1, Param.ACT_FMAXPOS, 0.5))
    arm.handle(p.fvel(1, 1.0))
    clock.advance(3.0)
    assert 0.45 < arm.positions()[0] <= 0.5 + 1e-9  # moved, and braked before the new soft limit
    assert not state_of(arm, 1) & S.BEYOND_SOFT


def test_disable_ack_suppresses_data_free_acks_only(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1)
    assert raw(arm.handle(p.set_param(1, Param.ACT_CONFIG, int(ActConfig.DISABLE_ACK)))) == []
    assert arm.handle(p.reset(1)) == []
    assert arm.handle(p.framp(1, 0.1)) == []
    assert len(arm.handle(p.get_param(1, Param.ACT_FPOS))) == 1
    assert len(arm.handle(p.fstep(1, 0.1, 10))) == 1


def test_setparam_clamps_and_ignores_read_only(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1)

    def get(prm: Param):
        return decoded(arm.handle(p.get_param(1, prm)))[0].value

    arm.handle(p.set_param(1, Param.ACT_FMAXVEL, 5.0))
    assert get(Param.ACT_FMAXVEL) == pytest.approx(1.0)  # DEF_FMAXVEL
    arm.handle(p.set_param(1, Param.ACT_FMAXPOS, 9.0))
    assert get(Param.ACT_FMAXPOS) == pytest.approx(2.0)
    arm.handle(p.set_param(1, Param.ACT_FMAXPOS, 0.5))
    assert get(Param.ACT_FMAXPOS) == pytest.approx(0.5)
    assert raw(arm.handle(p.set_param(1, Param.DEF_VERSION, 7))) == [(0x0A1, "08 1d")]
    assert get(Param.DEF_VERSION) == 0x0D1A and arm[1].ignored_setparams == 1
    assert (
        PARAM_ACCESS[Param.DEF_VERSION] is ParamAccess.RO and PARAM_ACCESS[Param.ACT_CONFIG] is ParamAccess.RW
    )
    # the tightened soft limit refuses a move to 0.6
    arm.handle(p.framp(1, 0.6))
    assert get(Param.ACT_STATE) & S.BEYOND_SOFT


def test_fvel_stops_at_soft_limit_without_fault(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1)
    arm.handle(p.fvel(1, 5.0))  # clamped to ACT_FMAXVEL 1 rad/s
    clock.advance(0.5)
    assert arm.positions()[0] == pytest.approx(0.45, abs=0.02)  # 0.05 s ramp at 10 rad/s^2
    clock.advance(5.0)
    assert arm.positions()[0] == pytest.approx(2.0, abs=1e-6)
    assert not state_of(arm, 1) & S.ERROR


def test_fcur_is_acknowledged_and_recorded(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1)
    assert raw(arm.handle(p.fcur(1, 1.5))) == [(0x0A1, "0b 08")]
    assert decoded(arm.handle(p.get_param(1, Param.ACT_FCUR)))[0].value == 1.5
    assert arm.positions() == [0.0]


def test_malformed_frames_are_counted_and_ignored(clock: FakeClock) -> None:
    arm = make_arm(clock, n=1)
    bad = [
        can.Message(arbitration_id=0x0E1, data=b"\x0b\x10\x00", is_extended_id=False),
        can.Message(arbitration_id=0x0C1, data=b"\x0a\x99", is_extended_id=False),
        can.Message(arbitration_id=0x0E0, data=b"\x00", is_extended_id=False),
    ]
    for m in bad:
        assert arm.handle(m) == []
    assert arm.decoder.malformed == 3
    assert raw(arm.handle(p.reset(1))) == [(0x0A1, "00")]


def test_silenced_module_does_not_answer(clock: FakeClock) -> None:
    arm = make_arm(clock, n=2)
    arm[2].silenced = True
    assert arm.handle(p.get_param(2, Param.DEF_VERSION)) == []
    assert len(arm.handle(p.get_param(1, Param.DEF_VERSION))) == 1



def test_a_silenced_set_drops_requests_and_state_frames_but_time_goes_on(clock: FakeClock) -> None:
    """The bank's ``silenced`` ids (the simulator's fault switch): requests and broadcasts change
    nothing there and get no reply, the modules' unsolicited frames are dropped, and their watchdog
    still runs out (its state frame is only withheld while silenced)."""
    arm = make_arm(clock, n=2)
    for mid in (1, 2):
        arm.handle(p.set_param(mid, Param.ACT_CONFIG, int(ActConfig.WATCHDOG_ENABLE)))
    assert arm.dispatch(p.decode(p.get_param(2, Param.DEF_VERSION)), None, {2}) == []
    reply = arm.dispatch(p.decode(p.get_param(1, Param.DEF_VERSION)), None, {2})
    assert raw(reply) == [(0x0A1, "0a 1d 1a 0d")]
    arm.dispatch(p.decode(p.fvel(2, 0.5)), None, {2})  # ignored: module 2 does not move
    clock.advance(0.05)
    assert arm.dispatch(p.decode(p.watchdog_refresh_all()), None, {2}) == []  # refreshes module 1 only
    assert arm.tick(0.0, {2}) == []
    assert arm.positions()[1] == pytest.approx(0.0)
    clock.advance(0.08)  # module 2 last heard 130 ms ago, module 1 80 ms ago
    assert arm.tick(0.0, {2}) == []  # module 2's watchdog state frame withheld
    assert state_of(arm, 2) & S.COMM_ERROR  # ... but it did run out
    assert not state_of(arm, 1) & S.ERROR


def test_bad_construction() -> None:
    with pytest.raises(InvalidInputError):
        PowerCubeModule(0, KinematicPlant())
    with pytest.raises(InvalidInputError):
        EmulatedArm([KinematicPlant()], module_ids=[1, 2])
    with pytest.raises(InvalidInputError, match="duplicate"):
        EmulatedArm([KinematicPlant(), KinematicPlant()], module_ids=[3, 3])


# ------------------------------------------------------------------------------------------------
# Kinematic plant
# ------------------------------------------------------------------------------------------------


def _trace(
    plant: KinematicPlant, clock: FakeClock, seconds: float, dt: float = 0.001
) -> list[tuple[float, float]]:
    out = []
    for _ in range(round(seconds / dt)):
        clock.advance(dt)
        out.append((plant.position(), plant.velocity()))
    return out


def test_plant_trapezoid_respects_limits_and_lands(clock: FakeClock) -> None:
    plant = KinematicPlant(0.0, max_vel=1.0, max_acc=4.0, clock=clock)
    assert isinstance(plant, Plant)
    plant.command_position(1.0, 0.8, 2.0, None)
    tr = _trace(plant, clock, 2.5)
    vel = [v for _, v in tr]
    assert max(abs(v) for v in vel) <= 0.8 + 1e-9
    acc = [abs(b - a) / 0.001 for a, b in zip(vel, vel[1:], strict=False)]
    assert max(acc) <= 2.0 + 1e-6
    assert tr[-1] == (1.0, 0.0) and not plant.in_motion()
    # time-optimal-ish: 0.8/2 = 0.4 s ramps, 1.0 m at 0.8 -> about 1.65 s total
    t_arrive = next(i for i, (x, _) in enumerate(tr) if x == 1.0) * 0.001
    assert 1.6 <= t_arrive <= 1.8


def test_plant_fstep_arrives_at_the_end_of_its_duration(clock: FakeClock) -> None:
    plant = KinematicPlant(0.0, max_vel=5.0, max_acc=100.0, clock=clock)
    plant.command_position(0.5, None, None, 1.0)
    tr = _trace(plant, clock, 1.5)
    # distance / duration, plus what the 5 ms acceleration ramp at the start has to make up
    assert 0.5 <= max(v for _, v in tr) <= 0.505
    t_arrive = next(i for i, (x, _) in enumerate(tr) if x == 0.5) * 0.001
    assert 0.99 <= t_arrive <= 1.02


def test_plant_follows_a_stream_of_fsteps_without_stopping(clock: FakeClock) -> None:
    plant = KinematicPlant(0.0, max_vel=2.0, max_acc=20.0, clock=clock)
    dt, errs, speeds = 0.004, [], []
    for k in range(1, 400):  # 0.4 (1 - cos(pi t)): peak 1.26 rad/s, 3.9 rad/s^2
        target = 0.4 * (1 - math.cos(math.pi * k * dt))
        plant.command_position(target, None, None, dt)
        clock.advance(dt)
        errs.append(abs(plant.position() - target))
        speeds.append(plant.velocity())
    assert max(errs) < 0.01  # on target at the end of every step, give or take the ramp
    assert min(speeds[25:225]) > 0.3  # never stops between steps (t = 0.1 .. 0.9 s)


def test_plant_halt_brakes_at_max_acc(clock: FakeClock) -> None:
    plant = KinematicPlant(0.0, max_vel=1.0, max_acc=5.0, clock=clock)
    plant.command_velocity(1.0)
    _trace(plant, clock, 0.5)
    plant.halt()
    tr = _trace(plant, clock, 0.3)
    assert tr[-1][1] == 0.0 and not plant.in_motion()
    stop_dist = tr[-1][0] - tr[0][0]
    assert stop_dist == pytest.approx(1.0**2 / (2 * 5.0), abs=0.01)


def test_plant_velocity_mode_stops_before_range_end(clock: FakeClock) -> None:
    plant = KinematicPlant(0.0, lower=-0.3, upper=0.3, max_vel=2.0, max_acc=5.0, clock=clock)
    plant.command_velocity(-2.0)
    tr = _trace(plant, clock, 2.0)
    assert min(x for x, _ in tr) >= -0.3
    assert tr[-1][0] == pytest.approx(-0.3, abs=1e-3)


# ------------------------------------------------------------------------------------------------
# Runner on an in-process virtual bus
# ------------------------------------------------------------------------------------------------


@pytest.fixture
def vbus() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    ch = f"emu-{uuid.uuid4().hex[:8]}"
    host = can.Bus(interface="virtual", channel=ch)
    dev = can.Bus(interface="virtual", channel=ch)
    yield host, dev
    host.shutdown()
    dev.shutdown()


def _expect(bus: can.BusABC, timeout: float = 2.0) -> p.Frame:
    msg = bus.recv(timeout)
    assert msg is not None, "no reply"
    return p.decode(msg)


def test_runner_serves_a_virtual_bus(vbus) -> None:
    host, dev = vbus
    arm = EmulatedArm.kinematic([-1.0] * 2, [1.0] * 2, [2.0] * 2, [20.0] * 2, homed=True)
    with EmulatorRunner(dev, arm) as runner:
        host.send(p.get_param(2, Param.DEF_VERSION))
        assert _expect(host) == p.GetParamReply(2, Param.DEF_VERSION, 0x0D1A)
        host.send(p.fstep(1, 0.1, 50))
        ack = _expect(host)
        assert isinstance(ack, p.SetMoveExtAck) and ack.position == 0.0
        host.send(can.Message(arbitration_id=0x0E1, data=b"\x77", is_extended_id=False))  # malformed
        host.send(p.get_param(1, Param.ACT_STATE))
        assert isinstance(_expect(host), p.GetParamReply)
    assert runner.frames_in == 4 and runner.frames_out == 3 and arm.decoder.malformed == 1
    assert runner.errors == 0


def test_runner_watchdog_trips_on_real_time(vbus) -> None:
    host, dev = vbus
    arm = EmulatedArm.kinematic([-1.0], [1.0], [2.0], [20.0], homed=True, watchdog_timeout_s=0.05)
    with EmulatorRunner(dev, arm, tick_s=0.005):
        host.send(p.set_param(1, Param.ACT_CONFIG, int(ActConfig.WATCHDOG_ENABLE)))
        assert _expect(host) == p.SetParamAck(1, Param.ACT_CONFIG)
        # nothing more is sent: the module halts by itself and says so on 0x061
        frame = _expect(host, timeout=5.0)
        assert isinstance(frame, p.StateFrame) and frame.state & S.COMM_ERROR


def test_runner_stops_when_its_plain_bus_is_shut_down(vbus) -> None:
    host, dev = vbus
    arm = EmulatedArm.kinematic([-1.0], [1.0], [2.0], [20.0])
    runner = EmulatorRunner(dev, arm, tick_s=0.005).start()
    dev.shutdown()  # the owner closed the bus before stopping the runner
    runner.join(5.0)
    assert not runner.running and runner.errors >= 1
    runner.stop()
