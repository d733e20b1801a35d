"""realtime.request_slice: a normal thread asks for a shorter time slice (Linux 6.12+), keeps its policy
and nice level, and the threads on the reply path (bus server relay, simulator bus thread, driver
cycle) take the slice they are told to. Set on threads started for the test (never the runner's)."""

from __future__ import annotations

import os
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
from support.sim_thread import sim_running
from support.waits import wait_until

from redarm_ros.can import realtime
from redarm_ros.procs import ManagedProcess, python_module_cmd

SLICE_MS = 0.3  # not the kernel's default (0.7 ms times 1 + log2 of the CPUs) nor the package's


def _in_thread(fn: Callable[[], Any]) -> Any:
    """``fn()`` in a fresh thread (its scheduling ends with it); its result."""
    out: list[Any] = []
    t = threading.Thread(target=lambda: out.append(fn()))
    t.start()
    t.join(10)
    return out[0]


def _kernel_takes_slices() -> str:
    got = _in_thread(lambda: realtime.request_slice(SLICE_MS, who="probe"))
    return "" if got.applied else got.message


pytestmark = pytest.mark.skipif(bool(_kernel_takes_slices()), reason=_kernel_takes_slices() or "-")


def _proc_slice_ns(pid: int, comm: str | None) -> int | None:
    """``se.slice`` (ns) of the thread of ``pid`` named ``comm`` (None: its main thread) (/proc), None
    when there is none."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            if (task.name != str(pid)) if comm is None else ((task / "comm").read_text().strip() != comm):
                continue
            for line in (task / "sched").read_text().splitlines():
                if line.startswith("se.slice"):
                    return int(float(line.split(":")[1]))
        except OSError:
            continue
    return None


def test_slice_is_set_and_read_back_on_a_thread() -> None:
    def ask() -> tuple[realtime.Slice, float, int | None]:
        got = realtime.request_slice(SLICE_MS, who="probe")
        realtime.name_thread("slice-probe")
        return got, realtime.thread_slice_ms(), _proc_slice_ns(os.getpid(), "slice-probe")

    got, read_back, proc_ns = _in_thread(ask)
    assert got.applied and not got.refused and got.ms == pytest.approx(SLICE_MS), got
    assert read_back == pytest.approx(SLICE_MS)
    assert proc_ns == int(SLICE_MS * 1e6)
    assert "0.3 ms" in got.message


def test_policy_and_nice_level_are_kept() -> None:
    """A thread at nice 5 (lowering one's own priority needs no privilege) stays at nice 5."""
    def ask() -> tuple[realtime.Slice, int, int]:
        os.setpriority(os.PRIO_PROCESS, 0, 5)  # this thread only (Linux nice is per thread)
        got = realtime.request_slice(SLICE_MS, who="probe")
        return got, os.getpriority(os.PRIO_PROCESS, 0), os.sched_getscheduler(0)

    got, nice, policy = _in_thread(ask)
    assert got.applied, got
    assert nice == 5 and policy == os.SCHED_OTHER


def test_zero_asks_for_nothing_and_a_later_thread_inherits_a_slice() -> None:
    def ask() -> tuple[float, realtime.Slice, float, float]:
        default = realtime.thread_slice_ms()
        nothing = realtime.request_slice(0.0, who="probe")
        realtime.request_slice(SLICE_MS, who="probe")
        return default, nothing, realtime.thread_slice_ms(), _in_thread(realtime.thread_slice_ms)

    default, nothing, after, child = _in_thread(ask)
    assert not nothing.applied and not nothing.refused and nothing.ms == default
    assert "none requested" in nothing.message
    assert after == child == pytest.approx(SLICE_MS)


def test_out_of_range_is_clamped_and_said() -> None:
    got = _in_thread(lambda: realtime.request_slice(0.01, who="probe"))
    assert got.refused and not got.applied and got.ms == pytest.approx(0.1), got  # the kernel's minimum


@pytest.mark.parametrize("slice_ms", [SLICE_MS, 0.0])
def test_bus_server_relay_thread_takes_its_slice(slice_ms: float) -> None:
    cmd = python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", "0",
                            "--realtime-priority", "0", "--slice-ms", f"{slice_ms:g}")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")) if p)}
    child = ManagedProcess.start("canbus", cmd, env=env, sink=lambda _line: None)
    try:
        child.wait_for_line(r"REDARM_CANBUS_PORT=\d+", 30)
        # (the relay names itself, then asks for its slice)
        assert wait_until(lambda: _proc_slice_ns(child.pid, "canbus-relay") == int(slice_ms * 1e6)
                          or not slice_ms and _proc_slice_ns(child.pid, "canbus-relay") is not None)
        relay = _proc_slice_ns(child.pid, "canbus-relay")
        main = _proc_slice_ns(child.pid, None)
    finally:
        assert child.stop() == 0
    if slice_ms:
        assert relay == int(slice_ms * 1e6)
        assert main != relay  # the relay only: the main thread keeps the kernel's default
    else:
        assert relay == main  # the kernel's default


def test_driver_cycle_thread_takes_its_slice() -> None:
    from support.loop_rig import AMAX, LOWER, Q0, UPPER, VMAX, loop_rig

    from redarm_ros.can.driver_loop import LoopConfig
    from redarm_ros.can.module_emulator import EmulatedArm

    arm = EmulatedArm.kinematic(LOWER, UPPER, VMAX, AMAX, q0=Q0)
    logs: list[str] = []
    cfg = LoopConfig(rate_hz=100.0, poll_hz=20.0, slice_ms=SLICE_MS)
    with loop_rig(arm, cfg, log=lambda _lvl, msg: logs.append(msg)) as rig:
        rig["loop"].start()
        assert wait_until(lambda: _proc_slice_ns(os.getpid(), "can-cycle") == int(SLICE_MS * 1e6))
        assert wait_until(lambda: any("time slice 0.3 ms" in m for m in logs)), logs
        assert "time slice 0.3 ms" in rig["loop"].snapshot().priority


def test_sim_bus_thread_takes_its_slice() -> None:
    from redarm_ros.kinematics import load_arm
    from redarm_ros.sim.hardware import HardwareSim
    from redarm_ros.sim.plant import PybulletPlant

    sim_bus = can.Bus(interface="virtual", channel=f"redarm-sim-test-{uuid.uuid4().hex}")
    plant = PybulletPlant.create(load_arm("pa10"))
    sim = HardwareSim(plant, sim_bus, slice_ms=SLICE_MS)
    ready = threading.Event()
    with sim_running(sim, [sim_bus.shutdown, plant.close], on_ready=ready.set):
        assert ready.wait(20)
        assert wait_until(lambda: _proc_slice_ns(os.getpid(), "sim-bus") == int(SLICE_MS * 1e6))


def test_driver_cycle_process_takes_its_slice() -> None:
    from redarm_ros.can.bus_server import LoopbackBusServer
    from redarm_ros.can.driver_loop import LoopConfig
    from redarm_ros.can.driver_process import DriverProcess, DriverSpec

    with LoopbackBusServer() as server:  # no modules: the cycle scans for them, which is enough here
        spec = DriverSpec(module_ids=(1,), lower=(-1.0,), upper=(1.0,), max_vel=(1.0,), max_acc=(5.0,),
                          can_kwargs=server.client_config(),
                          loop=LoopConfig(rate_hz=100.0, slice_ms=SLICE_MS))
        proc = DriverProcess(spec, on_sample=lambda _s: None, log=lambda _lvl, _msg: None).start()
        try:
            assert wait_until(lambda: _proc_slice_ns(proc.pid, "can-cycle") == int(SLICE_MS * 1e6), 20)
            assert _proc_slice_ns(proc.pid, None) != int(SLICE_MS * 1e6)  # the cycle thread only
        finally:
            proc.stop()
