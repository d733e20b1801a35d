"""The simulator's physics in a process of its own: replies never wait for it, commands reach it, the
state comes back, and it ends with the simulator.

In-process tests run a HardwareSim on python-can's virtual bus over a PhysicsProcess; the last test
runs ``redarm-sim`` itself. Waits are generous deadlines, never speed assertions.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from support.sim_thread import sim_running
from support.stalling_plant import stalling_plant

from redarm_ros.can import protocol as pc
from redarm_ros.can.protocol import ActState, Param
from redarm_ros.kinematics import load_arm
from redarm_ros.procs import python_module_cmd
from redarm_ros.sim.hardware import EXIT_PHYSICS_LOST, READY_LINE, HardwareSim
from redarm_ros.sim.physics_process import PhysicsProcess, build_plant

STALL_S = 1.0  # every physics step holds the interpreter lock this long


@pytest.fixture
def arm():
    return load_arm("pa10")


def _serve(physics: PhysicsProcess) -> Iterator[tuple[HardwareSim, can.BusABC]]:
    channel = f"redarm-physics-test-{uuid.uuid4().hex}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    host = can.Bus(interface="virtual", channel=channel)
    sim = HardwareSim(physics, sim_bus)
    with sim_running(sim, [host.shutdown, sim_bus.shutdown, physics.close]):
        yield sim, host
    assert not physics.alive()


def _ask(host: can.BusABC, msg: can.Message, timeout: float = 2.0) -> tuple[object, float]:
    mid = msg.arbitration_id & 0x1F
    t0 = time.monotonic()
    host.send(msg)
    while (left := t0 + timeout - time.monotonic()) > 0:
        r = host.recv(left)
        if r is not None and r.arbitration_id == pc.IdBase.CMD_ACK + mid:
            return pc.decode(r), time.monotonic() - t0
    raise AssertionError(f"no reply of module {mid} within {timeout} s")


def test_replies_do_not_wait_for_a_stalled_physics(arm):
    # Every physics step holds the interpreter lock for a second (a preempted physics thread): in the
    # simulator's own process that would hold up every reply for as long; in its own process, none.
    physics = PhysicsProcess(arm, functools.partial(stalling_plant, arm, STALL_S))
    for sim, host in _serve(physics):
        time.sleep(STALL_S)  # the physics is inside a stall now
        waits = []
        for k in range(30):
            reply, waited = _ask(host, pc.get_param(k % sim.n + 1, Param.ACT_FPOS))
            assert reply.value == pytest.approx(0.0, abs=1e-4)
            waits.append(waited)
            time.sleep(0.05)
        # 1.5 s of requests: one that waited for the lock would have waited up to STALL_S
        assert max(waits) < STALL_S / 2, waits
        assert sim.counters.replies_tx >= 30


def test_commands_reach_the_physics_and_its_state_comes_back(arm, tmp_path: Path):
    physics = PhysicsProcess(arm, functools.partial(build_plant, arm, time_step=1e-3))
    for sim, host in _serve(physics):
        _home(host, 2)
        _ask(host, pc.fstep(2, 0.3, 1000))
        # in motion from the moment it took the command, before the physics applied it
        assert ActState.MOTION in ActState(_ask(host, pc.get_param(2, Param.ACT_STATE))[0].value)
        deadline = time.monotonic() + 10
        while abs(physics.q[1] - 0.3) > 1e-4 or physics.joint(1).in_motion():
            assert time.monotonic() < deadline, physics.q
            time.sleep(0.05)
        assert _ask(host, pc.get_param(2, Param.ACT_FPOS))[0].value == pytest.approx(0.3, abs=1e-4)
        st = sim.status()
        assert np.allclose(st["tool"]["position"], arm.fk(np.asarray(st["q"]))[:3, 3], atol=1e-5)
        assert st["steps"] > 0 and st["sim_time_s"] > 0
        png = tmp_path / "now.png"
        physics.snapshot_png(png, 64, 48)
        assert png.stat().st_size > 0


def test_the_status_of_a_moving_arm_is_one_snapshot(arm):
    # Joints and tool pose read one by one come from different steps of a moving arm (the status said
    # tool != fk(q) by 4e-5 m once); the status takes them from one write of the process.
    physics = PhysicsProcess(arm, functools.partial(build_plant, arm, time_step=1e-3))
    for sim, host in _serve(physics):
        _home(host, 2)
        _ask(host, pc.fstep(2, 1.0, 3000))
        worst, reads = 0.0, 0
        deadline = time.monotonic() + 10
        while reads == 0 or physics.joint(1).in_motion():
            assert time.monotonic() < deadline, reads
            st = sim.status()
            if abs(st["dq"][1]) > 0.05:  # (judged while the joint moves)
                tool = np.asarray(st["tool"]["position"])
                worst = max(worst, float(np.max(np.abs(tool - arm.fk(np.asarray(st["q"]))[:3, 3]))))
                reads += 1
        assert reads >= 100, reads
        assert worst <= 1e-5, worst  # (as at rest: pybullet against fk)


def _home(host: can.BusABC, mid: int) -> None:
    _ask(host, pc.home(mid))  # moves need HOME_OK
    deadline = time.monotonic() + 10
    while ActState.HOME_OK not in ActState(_ask(host, pc.get_param(mid, Param.ACT_STATE))[0].value):
        assert time.monotonic() < deadline
        time.sleep(0.05)


def test_replies_keep_coming_while_the_physics_process_is_stopped(arm):
    # A stopped physics takes no commands: thousands of them (more than a pipe holds) must not hold up
    # a reply; once it runs again it takes the newest.
    physics = PhysicsProcess(arm, functools.partial(build_plant, arm, time_step=1e-3))
    for _sim, host in _serve(physics):
        _home(host, 2)
        os.kill(physics.pid, signal.SIGSTOP)
        try:
            for k in range(3000):
                reply, _ = _ask(host, pc.fstep(2, 0.2 * (k + 1) / 3000, 4))
                assert isinstance(reply, pc.SetMoveExtAck)
        finally:
            os.kill(physics.pid, signal.SIGCONT)
        deadline = time.monotonic() + 10
        while abs(physics.q[1] - 0.2) > 1e-3:
            assert time.monotonic() < deadline, physics.q
            time.sleep(0.05)


def _start_sim(procs, server, *extra: str):
    cmd = python_module_cmd("redarm_ros.sim.hardware", "--arm", "pa10", "--realtime-priority", "0",
                            *server.cli_args(), *extra)
    return procs.start("sim", cmd, ready=READY_LINE, ready_timeout=30.0)


def _physics_pid(sim) -> int:
    """The simulator's physics process: its child whose main thread is named so."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[-1].split()[1])
            comm = (entry / "comm").read_text().strip()
        except (OSError, ValueError, IndexError):
            continue
        if ppid == sim.pid and comm == "sim-physics":
            found.append(int(entry.name))
    assert len(found) == 1, found
    return found[0]


@pytest.mark.hil
def test_the_physics_process_ends_with_the_simulator(procs, canbus_server):
    sim = _start_sim(procs, canbus_server)
    physics = _physics_pid(sim)
    assert os.getsid(physics) == physics  # its own session (and CPU share)
    assert procs.stop(sim) == 0  # SIGINT: the simulator stops its physics, then exits
    assert not Path(f"/proc/{physics}").exists()


@pytest.mark.hil
def test_the_simulator_exits_when_its_physics_process_dies(procs, canbus_server):
    sim = _start_sim(procs, canbus_server)
    sim.expect_exit()
    os.kill(_physics_pid(sim), signal.SIGKILL)
    deadline = time.monotonic() + 10
    while sim.returncode is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert sim.returncode == EXIT_PHYSICS_LOST


class _MovingPlant:
    """A plant whose setpoints move every step (never at rest) and records the commands it gets."""

    def __init__(self) -> None:
        self.q_setpoint = np.zeros(2)
        self.dq = np.ones(2)
        self.steps: list[int] = []
        self.commands: list[tuple] = []

    def step(self, count: int) -> None:
        self.steps.append(count)
        self.q_setpoint = self.q_setpoint + count

    def joint(self, j: int):
        plant = self

        class _J:
            def command_position(self, *args) -> None:
                plant.commands.append((j, *args))

        return _J()


def test_a_streaming_host_sets_the_physics_wake_ups_to_its_step() -> None:
    # While it moves, the process wakes once per streamed step (a 250 Hz host's 4 ms: half the wake-ups
    # of 2 ms), never more than MAX_MOVING_WAKE_S apart nor less than MOVING_WAKE_S; a single move
    # (no duration) leaves the wake-ups as they are.
    from redarm_ros.sim.physics_process import MAX_MOVING_WAKE_S, MOVING_WAKE_S, RealTimeStepper, _apply

    plant = _MovingPlant()
    stepper = RealTimeStepper(plant, 1000.0)
    assert stepper.moving_batch == round(MOVING_WAKE_S * 1000) == 2
    for duration, batch in ((0.004, 4), (0.002, 2), (0.0005, 2), (0.010, round(MAX_MOVING_WAKE_S * 1000)),
                            (None, round(MAX_MOVING_WAKE_S * 1000)), (0.004, 4)):
        assert _apply(plant, (1, "position", 0, 0.3, None, None, duration), stepper)
        assert stepper.moving_batch == batch, duration
    assert len(plant.commands) == 6
    stepper.start()
    stepper.advance(stepper.t0 + 0.0041)  # the first wake-up steps what is due, then plans a host step
    assert plant.steps == [4] and stepper.batch == 4
    late = stepper.counters.overruns
    stepper.advance(stepper.t0 + 0.0081)  # four steps as planned: not late
    assert plant.steps == [4, 4] and stepper.counters.overruns == late


def test_the_physics_process_does_not_run_the_parents_main_module_again(tmp_path: Path) -> None:
    """spawn would import the parent's ``__main__`` in the child (as ``__mp_main__``): for the simulator
    that is python-can and the protocol, which the physics never uses. Nothing pickled names it here."""
    probe, seen = tmp_path / "probe_main.py", tmp_path / "imported_again"
    probe.write_text(
        "import functools, os, sys\n"
        "from redarm_ros.kinematics import load_arm\n"
        "from redarm_ros.sim.physics_process import PhysicsProcess, build_plant\n"
        "if __name__ != '__main__':\n"
        f"    open({str(seen)!r}, 'a').write(__name__ + '\\n')\n"
        "else:\n"
        "    arm = load_arm('pa10')\n"
        "    PhysicsProcess(arm, functools.partial(build_plant, arm, time_step=1e-3)).close()\n"
        "    print(sys.modules['__main__'].__file__, flush=True)\n",
        encoding="utf-8",
    )
    out = subprocess.run([sys.executable, str(probe)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() == str(probe)  # the main module got its file back
    assert not seen.exists(), seen.read_text()
