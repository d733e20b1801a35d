"""The CAN cycle in a process of its own (redarm_ros.can.driver_process): the parent's handle against
a real child process, over a loopback bus server with emulated modules served from this process."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import pytest
from support.waits import HANG_BUDGET_S

from redarm_ros.can.bus import open_bus
from redarm_ros.can.bus_server import LoopbackBusServer
from redarm_ros.can.driver_loop import LoopConfig, LoopState
from redarm_ros.can.driver_process import DriverProcess, DriverSpec, SampleThrottle
from redarm_ros.can.module_emulator import EmulatedArm, EmulatorRunner
from redarm_ros.errors import InvalidInputError

N = 3
LOWER, UPPER = [-2.0, -1.5, -2.0], [2.0, 1.5, 2.0]
VMAX, AMAX = [1.0, 1.0, 2.0], [5.0, 5.0, 10.0]


def wait_for(pred: Callable[[], Any], timeout: float = 20.0) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(0.02)
    return pred()


@pytest.fixture
def rig() -> Iterator[dict[str, Any]]:
    server = LoopbackBusServer().start()
    dev = open_bus(**server.client_config())
    arm = EmulatedArm.kinematic(LOWER, UPPER, VMAX, AMAX, q0=[0.3, -0.2, 0.1], watchdog_timeout_s=0.5)
    runner = EmulatorRunner(dev, arm, tick_s=0.002).start()
    logs: list[tuple[int, str]] = []
    samples: list[Any] = []
    # Generous timeouts: the emulated modules share this test process (and its GIL) with pytest.
    spec = DriverSpec(
        module_ids=(1, 2, 3), lower=tuple(LOWER), upper=tuple(UPPER), max_vel=tuple(VMAX),
        max_acc=tuple(AMAX),
        can_kwargs=server.client_config(), loop=LoopConfig(rate_hz=100.0, poll_hz=20.0),
        reply_timeout_s=0.1, max_missed=10, watchdog=True, realtime_priority=0,
    )
    sink: list[Callable[[Any], None]] = [samples.append]  # a test may swap in its own
    proc = DriverProcess(spec, on_sample=lambda s: sink[0](s), log=lambda lvl, msg: logs.append((lvl, msg)))
    try:
        yield {"proc": proc, "arm": arm, "logs": logs, "samples": samples, "sink": sink}
    finally:
        proc.stop()
        runner.stop()
        dev.shutdown()
        server.stop()


def test_cycle_process_inits_follows_and_stops(rig: dict[str, Any]) -> None:
    proc: DriverProcess = rig["proc"]
    assert proc.pid is None  # nothing runs before start()
    proc.start()
    assert wait_for(lambda: proc.state is LoopState.IDLE), proc.accepting_commands()
    assert proc.pid != os.getpid() and proc.alive
    ok, msg = proc.request("init", timeout=30.0)
    assert ok, msg
    assert proc.state is LoopState.RUNNING and proc.accepting_commands() == (True, "")
    goal = np.array([0.4, -0.3, 0.5])
    proc.commands.set_trajectory([0, 1, 2], [0.5, 1.0], np.array([goal / 2, goal]), start=time.monotonic())
    arm = rig["arm"]
    assert wait_for(lambda: np.allclose(arm.positions(), goal, atol=2e-3))
    # Samples of every cycle reach the parent; the status comes across whole.
    assert wait_for(lambda: len(rig["samples"]) > 20)
    assert rig["samples"][-1].target is not None and rig["samples"][-1].positions.shape == (N,)
    snap = proc.snapshot()
    assert snap.state is LoopState.RUNNING and snap.cycles > 10 and len(snap.module_stats) == N
    assert "normal scheduling" in snap.priority  # realtime_priority 0 in this test
    # A bad command is refused here, before it reaches the child.
    with pytest.raises(InvalidInputError):
        proc.commands.set_trajectory([0], [1.0], np.array([[np.nan]]), start=time.monotonic())
    pid = proc.pid
    proc.stop()
    assert proc.state is LoopState.STOPPED and not proc.alive
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_a_reader_that_falls_behind_hands_on_the_newest_sample(rig: dict[str, Any]) -> None:
    # A starved node: every sample takes it 0.1 s to publish while the cycle makes one per 0.01 s.
    # Handing on each in turn would make them ever older (the backlog of the socket); the newest
    # queued is handed on instead, so a sample is never older than about one publishing delay.
    ages: list[float] = []

    def slow(s: Any) -> None:
        ages.append(time.time() - s.stamp)
        time.sleep(0.1)

    rig["sink"][0] = slow
    proc: DriverProcess = rig["proc"].start()
    assert wait_for(lambda: proc.state is LoopState.IDLE)
    ok, msg = proc.request("init", timeout=30.0)
    assert ok, msg
    assert wait_for(lambda: len(ages) >= 30, 30.0)
    assert proc.samples_skipped > 100
    assert max(ages[10:]) < 0.35, [round(a, 3) for a in ages]


def test_a_killed_cycle_process_is_reported_and_the_watchdog_halts_the_arm(rig: dict[str, Any]) -> None:
    proc: DriverProcess = rig["proc"].start()
    assert wait_for(lambda: proc.state is LoopState.IDLE)
    ok, msg = proc.request("init", timeout=30.0)
    assert ok, msg
    os.kill(proc.pid, signal.SIGKILL)
    assert wait_for(lambda: proc.state is LoopState.STOPPED)
    assert any(lvl == logging.ERROR and "ended unexpectedly" in m for lvl, m in rig["logs"])
    ok, msg = proc.request("recover")
    assert not ok
    arm = rig["arm"]
    assert wait_for(lambda: all(int(arm[i].state()) & 0x20 for i in (1, 2, 3)), timeout=5.0)  # COMM_ERROR


def test_a_sigterm_to_the_process_group_leaves_the_stop_to_the_parent(rig: dict[str, Any]) -> None:
    """systemd (and a supervisor stopping a process group) sends SIGTERM to the node and its cycle
    process alike: the cycle process lets the node stop it, so the node's clean stop is not taken for a
    crash ("cycle process ended unexpectedly (exit code -15)", "driver process unreachable")."""
    proc: DriverProcess = rig["proc"].start()
    assert wait_for(lambda: proc.state is LoopState.IDLE)
    os.kill(proc.pid, signal.SIGTERM)
    time.sleep(0.5)
    assert proc.alive and proc.state is LoopState.IDLE
    proc.stop()
    assert proc.state is LoopState.STOPPED and not proc.alive
    errors = [m for lvl, m in rig["logs"] if lvl >= logging.ERROR]
    assert not errors, errors


def test_samples_are_handed_on_at_their_rate_on_average() -> None:
    """100 Hz from a 250 Hz cycle: 8 and 12 ms apart in turn, 100 per second; after a gap (a stalled
    cycle) the next sample goes at once and the schedule restarts from it."""
    th = SampleThrottle(100.0, 250.0)
    stamps = [1000.0 + 0.004 * k for k in range(500)]  # 2 s of cycles
    kept = [t for t in stamps if th.due(t)]
    assert len(kept) == 200
    gaps = {round(g * 1e3) for g in np.diff(kept)}
    assert gaps <= {8, 12}
    assert th.due(kept[-1] + 0.5)  # after a 0.5 s gap: at once
    assert not th.due(kept[-1] + 0.504) and th.due(kept[-1] + 0.512)


def test_a_still_arm_is_handed_on_at_the_heartbeat_rate_and_motion_at_the_full_rate_at_once() -> None:
    """100 Hz from 250 Hz with a 10 Hz heartbeat: a still arm (same target, positions within the
    epsilon) is handed on 10 times a second; the first cycle that moved, or a new target, goes on at
    the full rate's schedule; polls (no target) are never slowed."""
    th = SampleThrottle(100.0, 250.0, still_rate_hz=10.0)
    q, target = np.zeros(7), np.full(7, 0.1)
    stamps = [1000.0 + 0.004 * k for k in range(500)]  # 2 s of cycles
    kept = [t for t in stamps if th.due(t, q + 1e-6 * ((t * 250) % 2), target)]
    assert 20 <= len(kept) <= 21
    assert {round(g * 1e3) for g in np.diff(kept)} <= {100, 104}
    t = stamps[-1] + 0.004
    assert th.due(t, q + 1e-3, target)  # moved: at once (the full rate's period had passed)
    assert not th.due(t + 0.004, q + 2e-3, target)  # moving: the full rate's schedule
    assert th.due(t + 0.012, q + 3e-3, target)
    assert th.due(t + 0.024, q + 3e-3, target + 0.01)  # a new target, the arm not moved yet
    assert not th.due(t + 0.036, q + 3e-3, target + 0.01)  # still again
    assert th.due(t + 0.048, q + 3e-3, None) and th.due(t + 0.060, q + 3e-3, None)  # polls
    full = SampleThrottle(100.0, 250.0)  # without a heartbeat rate: never slowed
    assert sum(full.due(t, q, target) for t in stamps) == 200


def test_the_cycle_thread_writes_its_samples_itself_and_never_waits() -> None:
    # No sender thread runs here: a sample still reaches the parent at once, written by the thread
    # that made it (one wake-up of a helper thread per sample saved). A parent that stopped reading
    # (the socket full) loses samples, counted, and the write returns at once.
    import socket

    from redarm_ros.can.driver_loop import CycleSample
    from redarm_ros.can.driver_process import _Child

    ours, theirs = socket.socketpair()
    parent, child_conn = Connection(ours.detach()), Connection(theirs.detach())
    spec = DriverSpec(module_ids=(1, 2, 3), lower=tuple(LOWER), upper=tuple(UPPER), max_vel=tuple(VMAX),
                      max_acc=tuple(AMAX))
    child = _Child(child_conn, spec)
    try:
        q = np.array([0.1, 0.2, 0.3])
        child.on_sample(CycleSample(12.5, q, 2 * q, None))
        assert parent.poll(2.0)
        kind, stamp, pos, vel, target = parent.recv()
        assert (kind, stamp, target) == ("sample", 12.5, None)
        assert pos.tolist() == q.tolist() and vel.tolist() == (2 * q).tolist()
        child._direct.setblocking(False)
        with pytest.raises(BlockingIOError):  # fill the socket: the parent reads nothing
            while True:
                child._direct.send(b"\0" * 4096)
        child._direct.setblocking(True)
        full = CycleSample(13.0, q, q, q)
        writer = threading.Thread(target=lambda: [child.on_sample(full) for _ in range(5)])
        writer.start()
        writer.join(HANG_BUDGET_S)  # (a write that waited would hang here)
        assert not writer.is_alive() and child.samples_dropped == 5
    finally:
        child._direct.close()
        child_conn.close()
        parent.close()


def test_a_sample_written_by_the_cycle_thread_never_overtakes_a_queued_one() -> None:
    # A sample queued for the sender thread (the socket was busy) counts as waiting until it is
    # written, so the next sample queues behind it instead of being written first: the parent, which
    # hands on the newest it read, never goes back in time.
    import socket

    from redarm_ros.can.driver_loop import CycleSample
    from redarm_ros.can.driver_process import _Child

    ours, theirs = socket.socketpair()
    parent, child_conn = Connection(ours.detach()), Connection(theirs.detach())
    spec = DriverSpec(module_ids=(1,), lower=(-1.0,), upper=(1.0,), max_vel=(1.0,), max_acc=(1.0,))
    child = _Child(child_conn, spec)
    child.sender.start()
    q = np.zeros(1)
    try:
        with child._conn_lock:  # the socket busy (the sender thread writing something else)
            child.on_sample(CycleSample(1.0, q, q, None))
            assert wait_for(lambda: child.out.empty(), HANG_BUDGET_S)  # the sender holds it, waiting
            time.sleep(0.05)
            assert child._samples_waiting == 1
            child.on_sample(CycleSample(2.0, q, q, None))
        stamps = [parent.recv()[1] for _ in range(2)]
        assert stamps == [1.0, 2.0]
    finally:
        child.out.put(None)
        child.sender.join(HANG_BUDGET_S)
        child._direct.close()
        child_conn.close()
        parent.close()
