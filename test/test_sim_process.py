"""The redarm-sim process over the loopback CAN bus: modules answer, move, refuse, and faults behave.

Every test starts a ``redarm-canbus`` server and a ``redarm-sim`` process as subprocesses (the ``procs``
fixture stops them: SIGINT, wait, SIGINT, SIGKILL) and talks to the modules with the project's codec.
Waits are generous deadlines, never speed assertions.
"""

from __future__ import annotations

import json
import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from PIL import Image
from support.pc_host import Host

from redarm_ros.can import protocol as pc
from redarm_ros.can.protocol import ActState, Param
from redarm_ros.kinematics import load_arm
from redarm_ros.procs import python_module_cmd
from redarm_ros.sim.hardware import EXIT_BAD_ARGS, EXIT_NO_BUS, READY_LINE

pytestmark = pytest.mark.hil



def _start_sim(procs, server, tmp_path: Path, *extra: str, name: str = "sim"):
    cmd = python_module_cmd(
        "redarm_ros.sim.hardware",
        "--arm", "pa10",
        *server.cli_args(),
        "--status-file", str(tmp_path / "status.json"),
        "--status-rate", "50",
        *extra,
    )  # fmt: skip
    return procs.start(name, cmd, ready=READY_LINE, ready_timeout=30.0)


def _status(tmp_path: Path) -> dict[str, Any]:
    return json.loads((tmp_path / "status.json").read_text())


def _wait_status(tmp_path: Path, pred, timeout: float = 10.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        st = _status(tmp_path)
        if pred(st):
            return st
        if time.monotonic() > deadline:
            raise AssertionError(f"status condition not met within {timeout} s; last status: {st}")
        time.sleep(0.02)


@pytest.fixture
def host(canbus_server) -> Iterator[Host]:
    h = Host(canbus_server.kwargs)
    yield h
    h.close()


def test_modules_answer_home_move_refuse_and_survive_garbage(procs, canbus_server, host, tmp_path):
    snaps = tmp_path / "snaps"
    sim = _start_sim(
        procs, canbus_server, tmp_path, "--snapshot-dir", str(snaps), "--snapshot-size", "160x120"
    )
    arm = load_arm("pa10")

    # discovery as the vendor library does it: DEF_VERSION from 1..n, nothing from n+1
    for mid in range(1, arm.n + 1):
        r = host.ask(pc.get_param(mid, Param.DEF_VERSION))
        assert r is not None and isinstance(r[0], pc.GetParamReply) and r[0].value > 0, mid
    assert host.ask(pc.get_param(arm.n + 1, Param.DEF_VERSION), timeout=0.3) is None

    # HOME, then ACT_STATE shows HOME_OK
    assert host.ask(pc.home(2)) is not None
    deadline = time.monotonic() + 10
    while not host.state(2) & ActState.HOME_OK:
        assert time.monotonic() < deadline, "HOME_OK never set"
        time.sleep(0.05)

    # an FSTEP moves the joint in the simulation: the status file follows, tool pose == fk(q)
    r = host.ask(pc.fstep(2, 0.3, 500))
    assert r is not None and isinstance(r[0], pc.SetMoveExtAck)
    assert r[0].position == pytest.approx(0.0, abs=1e-4)  # position before the move
    st = _wait_status(
        tmp_path, lambda s: abs(s["q"][1] - 0.3) < 1e-4 and "MOTION" not in s["modules"][1]["flags"]
    )
    assert host.param(2, Param.ACT_FPOS) == pytest.approx(0.3, abs=1e-4)
    T = arm.fk(np.asarray(st["q"]))
    assert np.allclose(st["tool"]["position"], T[:3, 3], atol=1e-5)
    assert np.abs(np.asarray(st["q"])[[0, 2, 3, 4, 5, 6]]).max() < 1e-4  # the others held still

    # a target beyond the soft limit is refused: ERROR | BEYOND_SOFT, no motion until RESET
    host.ask(pc.fstep(1, float(arm.upper[0]) + 0.1, 500))
    assert host.state(1) & (ActState.ERROR | ActState.BEYOND_SOFT) == ActState.ERROR | ActState.BEYOND_SOFT
    host.ask(pc.fstep(1, 0.2, 200))
    time.sleep(0.4)
    assert abs(_status(tmp_path)["q"][0]) < 1e-4
    host.ask(pc.reset(1))
    assert not host.state(1) & ActState.ERROR
    host.ask(pc.fstep(1, 0.2, 200))
    _wait_status(tmp_path, lambda s: abs(s["q"][0] - 0.2) < 1e-4)

    # malformed frames are counted and survived
    garbage = [
        can.Message(arbitration_id=0x0C3, data=[0x0A], is_extended_id=False),  # GETPARAM without param
        can.Message(arbitration_id=0x0E3, data=[0x55], is_extended_id=False),  # unknown command
        can.Message(
            arbitration_id=0x0E3, data=[0x0B, 0x06, 0, 0, 0xC0, 0x7F, 10, 0], is_extended_id=False
        ),  # NaN
        can.Message(arbitration_id=0x0E3, data=[0x0B, 0x06, 1, 2], is_extended_id=False),  # short FSTEP
    ]
    for g in garbage:
        host.send(g)
    _wait_status(tmp_path, lambda s: s["counters"]["malformed"] >= len(garbage))
    assert host.param(3, Param.DEF_VERSION) is not None
    assert _status(tmp_path)["counters"]["handler_errors"] == 0

    # snapshots: start.png at start-up, one on SIGUSR2, final.png on a clean stop
    sim.send_signal(signal.SIGUSR2)
    _wait_status(tmp_path, lambda s: len(s["snapshots"]) >= 2)
    assert sim.stop() == 0
    final = _status(tmp_path)
    assert final["running"] is False
    names = sorted(p.name for p in snaps.iterdir())
    assert names == ["final.png", "snapshot_0001.png", "start.png"]
    img = np.asarray(Image.open(snaps / "final.png"))
    assert img.shape == (120, 160, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10


def test_drop_delay_and_silence(procs, canbus_server, host, tmp_path):
    control = tmp_path / "control.json"
    sim = _start_sim(
        procs, canbus_server, tmp_path,
        "--drop-replies", "0.5", "--seed", "7", "--delay-replies", "40",
        "--silence-module", "3", "--control-file", str(control),
    )  # fmt: skip
    # drops: about half of a burst of 60 requests go unanswered, every missing one is counted;
    # the replies that come are delayed by --delay-replies
    t0 = time.monotonic()
    for _ in range(60):
        host.send(pc.get_param(1, Param.ACT_FPOS))
    first = host.bus.recv(1.0)
    assert first is not None and time.monotonic() - t0 >= 0.035  # 40 ms minus clock granularity
    answered = 1 + len(host.drain(0.3))
    assert 15 <= answered <= 45
    st = _wait_status(tmp_path, lambda s: s["counters"]["dropped_replies"] == 60 - answered)
    assert st["faults"]["silenced"] == [3]

    # silence: module 3 ignores everything; SIGUSR1 toggles it back
    assert all(host.ask(pc.get_param(3, Param.DEF_VERSION), timeout=0.15) is None for _ in range(3))
    assert _status(tmp_path)["counters"]["silenced_rx"] >= 3
    sim.send_signal(signal.SIGUSR1)
    _wait_status(tmp_path, lambda s: s["faults"]["silenced"] == [])
    got = [host.ask(pc.get_param(3, Param.DEF_VERSION), timeout=0.3) for _ in range(8)]
    assert any(g is not None for g in got)

    # the control file changes faults at run time: no drops, no delay, module 5 silent
    control.write_text(json.dumps({"drop_replies": 0.0, "delay_replies_ms": 0, "silence": [5]}))
    _wait_status(tmp_path, lambda s: s["faults"]["silenced"] == [5] and s["faults"]["drop_replies"] == 0)
    host.drain()
    assert all(host.ask(pc.get_param(1, Param.ACT_FPOS)) is not None for _ in range(20))
    assert host.ask(pc.get_param(5, Param.ACT_FPOS), timeout=0.15) is None
    control.write_text("{not json")
    _wait_status(tmp_path, lambda s: s["counters"]["control_errors"] >= 1)
    assert sim.stop() == 0


def test_die_after_crashes_like_hardware_losing_power(procs, canbus_server, host, tmp_path):
    sim = _start_sim(procs, canbus_server, tmp_path, "--die-after", "0.8")
    sim.expect_exit()
    assert host.ask(pc.get_param(1, Param.DEF_VERSION)) is not None
    deadline = time.monotonic() + 20
    while sim.is_running():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert sim.returncode == -signal.SIGKILL
    assert _status(tmp_path)["running"] is True  # no clean-up happened
    assert host.ask(pc.get_param(1, Param.DEF_VERSION), timeout=0.2) is None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    ("args", "code"),
    [
        (["--drop-replies", "1.5", "--can-interface", "virtual"], EXIT_BAD_ARGS),
        (["--arm", "no_such_arm", "--can-interface", "virtual"], EXIT_BAD_ARGS),
        (["--initial-q", "0", "0", "--can-interface", "virtual"], EXIT_BAD_ARGS),
        (["--can-interface", "remote", "--can-channel", f"ws://127.0.0.1:{_free_port()}/",
          "--bus-wait", "0.5"], EXIT_NO_BUS),
        # A configuration that can never work is not waited for (the long --bus-wait would time the test out).
        (["--can-interface", "no_such_interface", "--bus-wait", "600"], EXIT_NO_BUS),
    ],
)
def test_bad_arguments_and_missing_bus_exit_with_a_code(procs, args, code):
    proc = procs.start("sim-bad", python_module_cmd("redarm_ros.sim.hardware", *args), exits=True)
    proc.popen.wait(timeout=30)
    assert proc.returncode == code


def test_sim_waits_for_a_bus_server_that_starts_after_it(procs, tmp_path):
    """As in the launch file, which starts redarm-canbus and redarm-sim together: the simulator retries
    the bus (saying so once) and comes up when the server does."""
    port = _free_port()

    class _Server:  # what _start_sim needs of the canbus fixture
        def cli_args(self) -> list[str]:
            return ["--can-interface", "remote", "--can-channel", f"ws://127.0.0.1:{port}/"]

    cmd = python_module_cmd("redarm_ros.sim.hardware", "--arm", "pa10", *_Server().cli_args(),
                            "--bus-wait", "60")
    sim = procs.start("sim-early", cmd)
    sim.wait_for_line(r"waiting up to 60 s for the CAN bus", timeout=30.0)
    server_cmd = python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", str(port))
    procs.start("canbus", server_cmd, ready=r"REDARM_CANBUS_PORT=", ready_timeout=20.0)
    sim.wait_for_line(READY_LINE, timeout=40.0, from_start=True)
    assert sim.popen.poll() is None


def test_sim_reconnects_when_the_bus_server_comes_back(procs, tmp_path):
    port = _free_port()
    server_cmd = python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", str(port))
    server = procs.start("canbus", server_cmd, ready=r"REDARM_CANBUS_PORT=", ready_timeout=20.0)

    class _Server:  # what _start_sim needs of the canbus fixture
        def cli_args(self) -> list[str]:
            return ["--can-interface", "remote", "--can-channel", f"ws://127.0.0.1:{port}/"]

    _start_sim(procs, _Server(), tmp_path)
    kwargs = {"interface": "remote", "channel": f"ws://127.0.0.1:{port}/"}
    host = Host(kwargs)
    try:
        assert host.ask(pc.get_param(1, Param.DEF_VERSION)) is not None
    finally:
        host.close()
    assert server.stop() == 0
    _wait_status(tmp_path, lambda s: s["counters"]["bus_lost"] >= 1)
    procs.start("canbus2", server_cmd, ready=r"REDARM_CANBUS_PORT=", ready_timeout=20.0)
    _wait_status(tmp_path, lambda s: s["counters"]["bus_reopened"] >= 1, timeout=20.0)
    host = Host(kwargs)
    try:
        assert host.ask(pc.get_param(1, Param.DEF_VERSION)) is not None
    finally:
        host.close()
