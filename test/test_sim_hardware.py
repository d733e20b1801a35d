"""HardwareSim in-process on python-can's virtual bus: FSTEP streams followed, bus loss survived, controls."""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Iterator

import can
import numpy as np
import pytest
from support.sim_thread import sim_running

from redarm_ros.can import protocol as pc
from redarm_ros.can.protocol import ActState, Param
from redarm_ros.errors import BusError
from redarm_ros.kinematics import load_arm
from redarm_ros.sim.hardware import Faults, HardwareSim, build_parser, strip_ros_args
from redarm_ros.sim.physics_process import REST_BATCH
from redarm_ros.sim.plant import PybulletPlant


class FlakyBus(can.BusABC):
    """A virtual bus whose ``recv`` fails once on demand, with a ``reopen`` like ReconnectingBus."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self._inner = can.Bus(interface="virtual", channel=channel)
        self.fail_next = threading.Event()
        self.reopens = 0
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None):
        if self.fail_next.is_set():
            self.fail_next.clear()
            raise BusError("transport lost (test)")
        return self._inner.recv(timeout), False

    def reopen(self) -> None:
        self._inner.shutdown()
        self._inner = can.Bus(interface="virtual", channel=self.channel)
        self.reopens += 1

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


@pytest.fixture
def rig() -> Iterator[tuple[HardwareSim, can.BusABC, FlakyBus]]:
    channel = f"redarm-sim-test-{uuid.uuid4().hex}"
    sim_bus = FlakyBus(channel)
    host = can.Bus(interface="virtual", channel=channel)
    plant = PybulletPlant.create(load_arm("pa10"))
    sim = HardwareSim(plant, sim_bus, faults=Faults(toggle_set={4}))
    with sim_running(sim, [host.shutdown, sim_bus.shutdown, plant.close]):
        yield sim, host, sim_bus


def _collect(host: can.BusABC, want: int, timeout: float = 1.0) -> list[object]:
    out: list[object] = []
    deadline = time.monotonic() + timeout
    while len(out) < want and (left := deadline - time.monotonic()) > 0:
        m = host.recv(left)
        if m is not None and pc.IdBase.CMD_ACK < m.arbitration_id <= pc.IdBase.CMD_ACK + 31:
            out.append(pc.decode(m))
    return out


def test_streamed_fsteps_are_followed(rig):
    sim, host, _ = rig
    n, cycle = sim.n, 0.01
    amp = np.array([0.3, 0.2, 0.3, 0.3, 0.4, 0.4, 0.4])  # rad; within every joint's acc limit at 0.5 Hz
    sent = [np.zeros(n)]
    top_speed = amp * math.pi / 2.0  # of amp * (1 - cos(pi t)) / 2
    acc = load_arm("pa10").max_acc
    overshoot = 2.0 * (top_speed**2 / (2.0 * acc) + top_speed * cycle) + 2e-3
    last = np.zeros(n)
    t0 = time.monotonic()
    for k in range(150):  # 1.5 s at 100 Hz, absolute deadlines like a driver loop
        target = amp * 0.5 * (1.0 - math.cos(math.pi * (k + 1) * cycle))  # starts at rest
        for j in range(n):
            host.send(pc.fstep(j + 1, float(target[j]), int(cycle * 1000)))
        acks = _collect(host, n)
        assert len(acks) == n and all(isinstance(a, pc.SetMoveExtAck) for a in acks)
        pos = np.array([a.position for a in sorted(acks, key=lambda a: a.module_id)])
        # Followed: every reported position lies on the path of targets sent so far, this one
        # included (their range per joint). A host that runs late on a busy machine makes a pause in
        # the stream, which the module brakes for, passing the last target by up to the braking
        # distance from the path's top speed (plus one step); the steps that waited are then played at
        # the stream's rate and the next pause can add as much again: twice that is allowed, no more.
        # (Without pauses the generator never overtakes: test_sim_ramp.py, with jitter.)
        sent.append(target)
        lo, hi = np.min(sent, axis=0) - overshoot, np.max(sent, axis=0) + overshoot
        assert np.all(pos >= lo) and np.all(pos <= hi), (k, pos, lo, hi)
        last = target
        time.sleep(max(0.0, t0 + (k + 1) * cycle - time.monotonic()))
    # when the stream stops every joint settles exactly on its last target
    deadline = time.monotonic() + 5
    while np.abs(sim.plant.q - last).max() > 1e-4:
        assert time.monotonic() < deadline, sim.plant.q - last
        time.sleep(0.05)
    assert sim.counters.malformed == 0 and sim.counters.handler_errors == 0


def test_the_physics_loop_wakes_every_few_steps(rig):
    # Each wake-up costs more than a step: a moving arm is stepped two steps per wake (1 kHz), a
    # resting one REST_BATCH; late wakes catch up more at once, so a wake never steps fewer.
    sim, host, _ = rig
    calls: list[int] = []
    step = sim.plant.step

    def counting(count: int = 1) -> None:
        calls.append(count)
        step(count)

    sim.plant.step = counting
    time.sleep(0.5)
    resting = list(calls)
    for j in range(sim.n):
        host.send(pc.fstep(j + 1, 0.3, 1000))  # every joint moves for about a second
    time.sleep(0.2)
    calls.clear()
    time.sleep(0.4)
    moving = list(calls)
    assert np.abs(sim.plant.dq).max() > 0.05  # still moving
    assert sim.moving_batch == 2
    assert moving and sum(c == 1 for c in moving) <= 0.2 * len(moving), moving
    assert sorted(resting)[len(resting) // 2] >= REST_BATCH, resting


def test_bus_loss_is_survived(rig):
    sim, host, sim_bus = rig
    host.send(pc.get_param(1, Param.DEF_VERSION))
    assert len(_collect(host, 1)) == 1
    sim_bus.fail_next.set()
    deadline = time.monotonic() + 5
    while sim.counters.bus_reopened < 1:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert sim.counters.bus_lost == 1 and sim_bus.reopens == 1
    host.send(pc.get_param(2, Param.DEF_VERSION))
    got = _collect(host, 1)
    assert len(got) == 1 and got[0].module_id == 2


def test_toggle_silence_controls_and_status(rig):
    sim, host, _ = rig
    sim.toggle_silence()
    assert sim.faults.silenced == {4}
    host.send(pc.home(4))
    host.send(pc.get_param(4, Param.ACT_STATE))
    assert _collect(host, 1, timeout=0.3) == []
    sim.toggle_silence()
    host.send(pc.get_param(4, Param.ACT_STATE))
    (reply,) = _collect(host, 1)
    assert not ActState(reply.value) & ActState.HOME_OK  # the HOME sent while silent was never seen
    with pytest.raises(ValueError, match="unknown control"):
        sim.apply_control({"bogus": 1})
    with pytest.raises(ValueError):
        sim.apply_control({"drop_replies": 3})
    sim.apply_control({"silence": [1, 2], "delay_replies_ms": 5})
    assert sim.faults.silenced == {1, 2} and sim.faults.delay_replies_ms == 5
    deadline = time.monotonic() + 5
    while sim.plant.steps < 10:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    st = sim.status()
    assert st["n"] == 7 and st["module_ids"] == list(range(1, 8)) and len(st["modules"]) == 7
    assert st["faults"]["silenced"] == [1, 2]
    assert st["modules"][3]["flags"] == ["RAMP_END"]


def test_control_channel_answers_and_refuses(rig):
    from redarm_ros.errors import InvalidInputError
    from redarm_ros.sim.control_channel import ControlChannel
    from redarm_ros.testing import SimControl, SimControlError

    sim, host, _ = rig
    with pytest.raises(InvalidInputError):
        ControlChannel(sim, host="0.0.0.0")  # loopback only
    channel = ControlChannel(sim).start()
    client = SimControl(channel.host, channel.port)
    try:
        assert client.request("ping") == "pong"
        st = client.status()  # taken on the physics thread
        assert sorted(st.modules) == list(range(1, 8)) and st.q.shape == (7,)
        assert client.set_faults(silence=[2], delay_replies_ms=3)["silenced"] == [2]
        assert sim.faults.silenced == {2} and sim.faults.delay_replies_ms == 3
        client.power_cycle([2])  # back on: speaks again
        assert sim.faults.silenced == set()
        client.inject(6, ActState.TOW_ERROR)
        host.send(pc.get_param(6, Param.ACT_STATE))
        (reply,) = _collect(host, 1)
        want = ActState.ERROR | ActState.TOW_ERROR
        assert ActState(reply.value) & want == want
        refused = [({"op": "nope"}, "unknown request"),
                   ({"op": "inject", "module": 6, "bits": ["NOPE"]}, "unknown ACT_STATE flag"),
                   ({"op": "faults", "drop_replies": 2}, "drop fraction")]
        for bad, why in refused:
            with pytest.raises(SimControlError, match=why):
                client.request(**bad)
        assert channel.answer(b"{not json")["ok"] is False
        assert client.request("ping") == "pong"  # still serving
    finally:
        client.close()
        channel.close()


def test_command_line_helpers(monkeypatch):
    assert strip_ros_args(["--arm", "pa10", "--ros-args", "-r", "__node:=sim", "--", "--gui"]) == [
        "--arm",
        "pa10",
        "--gui",
    ]
    assert strip_ros_args(["--ros-args", "--log-level", "info"]) == []
    args = build_parser().parse_args(
        ["--silence-module", "2,3", "--silence-module", "5", "--initial-q", "0", "1"]
    )
    assert args.silence_module == ["2,3", "5"] and args.initial_q == ["0", "1"]
    with pytest.raises(ValueError):
        Faults(drop_replies=-0.1).validate()
    with pytest.raises(ValueError):
        Faults(delay_replies_ms=float("nan")).validate()
    monkeypatch.setenv("REDARM_SIM_DROP_REPLIES", "0.25")
    monkeypatch.setenv("REDARM_SIM_DIE_AFTER", "3")
    args = build_parser().parse_args([])
    assert (args.drop_replies, args.delay_replies, args.die_after, args.seed) == (0.25, 0.0, 3.0, 0)
    assert build_parser().parse_args(["--drop-replies", "0.5"]).drop_replies == 0.5  # flags win over env


def test_gc_frozen_after_start_up_and_its_pauses_counted():
    """With freeze_gc the start-up objects are frozen before the sim reports ready (a full collection
    then holds up no reply for tens of ms); every collection's pause is counted; run() undoes it."""
    import gc

    channel = f"redarm-sim-test-{uuid.uuid4().hex}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    plant = PybulletPlant.create(load_arm("pa10"))
    sim = HardwareSim(plant, sim_bus, freeze_gc=True)
    frozen_at_ready: list[int] = []
    ready = threading.Event()

    def on_ready() -> None:
        frozen_at_ready.append(gc.get_freeze_count())
        ready.set()

    with sim_running(sim, [sim_bus.shutdown, plant.close], on_ready=on_ready):
        assert ready.wait(10)
        assert frozen_at_ready[0] > 1000  # the arm model, pybullet, numpy: everything made so far
        before = sim.counters.gc_collections
        gc.collect()
        assert sim.counters.gc_collections > before and sim.counters.gc_max_pause_ms > 0.0
        assert "gc_max_pause_ms" in sim.call_in_physics(sim.status).result(5)["counters"]
    assert gc.get_freeze_count() == 0  # unfrozen again when run() returned
