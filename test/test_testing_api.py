"""The public testing API (redarm_ros.testing) over the simulator process: the state read from the
simulator, every fault kind injected at run time and seen on the bus as the vendor library would see
it, the waits' messages, and the plugin's import cost."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from support.pc_host import Host

from redarm_ros.can import protocol as pc
from redarm_ros.can.protocol import ActState, Param
from redarm_ros.kinematics import load_arm
from redarm_ros.testing import (
    WATCHDOG_S,
    SimArmConfig,
    SimControlError,
    SimulatedArm,
    WaitTimeoutError,
    wait_until,
)

pytestmark = [pytest.mark.hil, pytest.mark.usefixtures("no_open_buses")]

ARM = load_arm("pa10")


@pytest.fixture
def host(redarm_arm: SimulatedArm):
    h = Host(redarm_arm.can_kwargs)
    yield h
    h.close()


def _home(host: Host, arm: SimulatedArm, ids: list[int]) -> None:
    for mid in ids:
        assert host.ask(pc.home(mid)) is not None
    arm.wait_modules(ActState.HOME_OK, ids, timeout=10.0)


def test_status_is_the_simulator_now(redarm_arm: SimulatedArm, host: Host) -> None:
    st = redarm_arm.status()
    assert sorted(st.modules) == list(range(1, ARM.n + 1))
    assert not any(m.homed for m in st.modules.values())  # powered on un-homed
    np.testing.assert_allclose(st.q, np.zeros(ARM.n), atol=1e-4)
    _home(host, redarm_arm, [2])
    assert host.ask(pc.fstep(2, 0.3, 400)) is not None
    st = redarm_arm.wait_at([0, 0.3, 0, 0, 0, 0, 0], tol=1e-4, timeout=10.0)
    np.testing.assert_allclose(st.tool, ARM.fk(st.q), atol=1e-5)
    assert st.modules[2].position == pytest.approx(0.3, abs=1e-4)
    assert redarm_arm.wait_still(window_s=0.2).modules[2].state & ActState.RAMP_END


def test_silence_and_speak_again(redarm_arm: SimulatedArm, host: Host) -> None:
    st = redarm_arm.silence(3)
    assert st.silenced == {3}
    assert host.ask(pc.get_param(3, Param.DEF_VERSION), timeout=0.2) is None
    assert host.ask(pc.get_param(1, Param.DEF_VERSION)) is not None
    redarm_arm.silence(5)
    assert redarm_arm.status().silenced == {3, 5}
    redarm_arm.unsilence(3)
    assert redarm_arm.status().silenced == {5}
    assert host.ask(pc.get_param(3, Param.DEF_VERSION)) is not None
    redarm_arm.clear_faults()
    assert host.ask(pc.get_param(5, Param.DEF_VERSION)) is not None


@pytest.mark.redarm_arm(sim_args=["--seed", "3"])
def test_drop_and_delay_replies(redarm_arm: SimulatedArm, host: Host) -> None:
    redarm_arm.drop_replies(1.0)
    assert all(host.ask(pc.get_param(1, Param.ACT_FPOS), timeout=0.1) is None for _ in range(5))
    assert redarm_arm.status().counters["dropped_replies"] >= 5
    redarm_arm.drop_replies(0.0)
    redarm_arm.delay_replies(60)
    r = host.ask(pc.get_param(1, Param.ACT_FPOS))
    assert r is not None and r[1] >= 0.055  # sent 60 ms after the request (less clock granularity)
    redarm_arm.clear_faults()
    assert redarm_arm.status().faults["delay_replies_ms"] == 0


def test_power_cycle_loses_homing_and_settings(redarm_arm: SimulatedArm, host: Host) -> None:
    _home(host, redarm_arm, [1, 2])
    host.ask(pc.set_param(2, Param.ACT_CONFIG, int(pc.ActConfig.SYNC_MOTION)))
    assert host.param(2, Param.ACT_CONFIG) == int(pc.ActConfig.SYNC_MOTION)
    t0 = time.monotonic()
    redarm_arm.power_cycle(2, off_s=0.3)
    assert time.monotonic() - t0 >= 0.3
    st = redarm_arm.status()
    assert not st.modules[2].homed and st.modules[1].homed  # only the cycled module lost it
    assert st.silenced == frozenset()  # on again: it speaks
    assert not host.state(2) & ActState.HOME_OK  # as the vendor library reads it
    assert host.param(2, Param.ACT_CONFIG) == 0  # factory settings


def test_each_module_says_when_it_halted_however_late_the_test_looks(redarm_arm: SimulatedArm,
                                                                       host: Host) -> None:
    # Module 2 by a HALT, module 1 by its watchdog (armed, then never refreshed); looked at 0.3 s later.
    before = redarm_arm.status()
    assert host.ask(pc.halt(2)) is not None
    assert host.ask(pc.set_param(1, Param.ACT_CONFIG, int(pc.ActConfig.WATCHDOG_ENABLE))) is not None
    after = redarm_arm.status()
    time.sleep(0.3)
    st = redarm_arm.wait_modules(ActState.HALTED | ActState.COMM_ERROR, [1], timeout=5.0)
    slack = 1e-3  # the frames' stamps are converted from wall time
    assert before.uptime_s - slack <= st.modules[2].halted_at_s <= after.uptime_s + slack
    armed_at = st.modules[1].halted_at_s - WATCHDOG_S  # its watchdog ran out WATCHDOG_S after
    assert before.uptime_s - slack <= armed_at <= after.uptime_s + slack
    assert st.uptime_s - st.modules[2].halted_at_s >= 0.3  # not when the status was read
    assert st.modules[3].halted_at_s is None
    assert host.ask(pc.reset(2)) is not None
    assert redarm_arm.status().modules[2].halted_at_s is None


def test_module_error_and_beyond_soft(redarm_arm: SimulatedArm, host: Host) -> None:
    _home(host, redarm_arm, [4, 5])
    host.drain()
    redarm_arm.module_error(4)
    frames = host.drain(0.2)  # the module's state frame, as a module announces an error
    assert any(f.arbitration_id == pc.IdBase.STATE + 4 for f in frames), frames
    assert host.state(4) & ActState.ERROR
    host.ask(pc.fstep(4, 0.2, 200))  # refused until RESET
    time.sleep(0.3)
    assert abs(redarm_arm.q[3]) < 1e-4
    host.ask(pc.reset(4))
    assert not host.state(4) & ActState.ERROR
    redarm_arm.beyond_soft(5)
    want = ActState.ERROR | ActState.BEYOND_SOFT
    assert host.state(5) & want == want
    assert redarm_arm.status().modules[5].has(want)
    with pytest.raises(SimControlError, match="no module with id 9"):
        redarm_arm.inject(9)


def test_simulator_killed_and_restarted(redarm_arm: SimulatedArm, host: Host) -> None:
    _home(host, redarm_arm, [4])
    host.ask(pc.fstep(4, 0.5, 600))
    redarm_arm.wait_at([0, 0, 0, 0.5, 0, 0, 0], tol=1e-3, timeout=10.0)
    old_pid = redarm_arm.children["sim"].pid
    last = redarm_arm.kill_sim()
    assert last is not None and last.q[3] == pytest.approx(0.5, abs=1e-3)
    assert host.ask(pc.get_param(4, Param.DEF_VERSION), timeout=0.2) is None  # gone
    redarm_arm.restart_sim(kill=False)
    assert redarm_arm.children["sim"].pid != old_pid
    st = redarm_arm.status()
    assert st.q[3] == pytest.approx(0.5, abs=1e-3)  # powered on where it stood
    assert not st.modules[4].homed
    assert host.ask(pc.get_param(4, Param.DEF_VERSION)) is not None


def test_bus_server_restarted(redarm_arm: SimulatedArm) -> None:
    redarm_arm.restart_bus_server(down_s=0.3)
    st = redarm_arm.wait_for(lambda s: s.counters["bus_reopened"] >= 1, 20.0, what="simulator reconnected")
    assert st.counters["bus_lost"] >= 1
    with redarm_arm.bus() as bus:  # a fresh client on the same channel is answered again
        h = Host.__new__(Host)
        h.bus = bus
        assert wait_until(lambda: h.ask(pc.get_param(1, Param.DEF_VERSION)), 10.0, what="module 1 answers")


def test_waits_say_what_they_saw(redarm_arm: SimulatedArm) -> None:
    with pytest.raises(WaitTimeoutError) as err:
        redarm_arm.wait_at([1.0] * ARM.n, timeout=0.2)
    msg = str(err.value)
    assert "arm at [1.0" in msg and "last seen: q=[0.0000" in msg and "module 7:" in msg
    with pytest.raises(WaitTimeoutError, match=r"flag: not reached within 0.05 s; last seen: 'off'"):
        wait_until(lambda: False, 0.05, what="flag", seen=lambda: "off")


def test_plugin_and_api_import_no_ros_or_pybullet() -> None:
    code = ("import sys, redarm_ros.testing.pytest_plugin as p; heavy = {'rclpy', 'pybullet', 'can'} & "
            "set(sys.modules); assert not heavy, heavy; import redarm_ros.testing; "
            "heavy = {'rclpy', 'pybullet'} & set(sys.modules); assert not heavy, heavy")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_a_bus_of_your_own_replaces_the_bus_server() -> None:
    cfg = SimArmConfig(bus={"interface": "socketcan", "channel": "vcan0"}, driver=True,
                       driver_params={"max_missed_replies": 3}).stack_config()
    assert (cfg.can_interface, cfg.can_channel, cfg.sim_control) == ("socketcan", "vcan0", True)
    assert cfg.extra_args["can_driver"] == ["-p", "duplicate_check_s:=0.0", "-p", "max_missed_replies:=3"]
    with pytest.raises(ValueError, match="interface and channel only"):
        SimArmConfig(bus={"interface": "socketcan", "bitrate": 500000}).stack_config()


def test_socketcan_vcan_where_the_kernel_has_it(redarm_arm_factory) -> None:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError) as exc:
        pytest.skip(f"no SocketCAN in this kernel: {exc}")
    if not Path("/sys/class/net/vcan0").exists():
        pytest.skip("no vcan0 (sudo ip link add vcan0 type vcan && sudo ip link set vcan0 up)")
    arm = redarm_arm_factory(bus={"interface": "socketcan", "channel": "vcan0"})
    assert "canbus" not in arm.children
    h = Host(arm.can_kwargs)
    try:
        assert h.ask(pc.get_param(1, Param.DEF_VERSION)) is not None
    finally:
        h.close()
    with pytest.raises(RuntimeError, match="no bus server"):
        arm.restart_bus_server()


@pytest.mark.redarm_arm(driver=True)
def test_ros_context_calls_the_driver_and_the_arm_shows_it(redarm_arm: SimulatedArm, redarm_ros) -> None:
    from std_srvs.srv import Trigger

    halt = redarm_ros.node.create_client(Trigger, "/can_driver/halt")
    answer = redarm_ros.call(halt, Trigger.Request(), timeout=30.0)
    assert answer.success, answer.message
    redarm_arm.wait_modules(ActState.HALTED, timeout=5.0)
    missing = redarm_ros.node.create_client(Trigger, "/no_such/service")
    with pytest.raises(WaitTimeoutError, match="service /no_such/service available"):
        redarm_ros.call(missing, Trigger.Request(), timeout=0.3)
