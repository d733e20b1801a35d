"""Tests of redarm_ros.procs: environment rules, readiness, staged stop, supervision."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from redarm_ros.procs import (
    ChildDiedError,
    ManagedProcess,
    ProcessGroup,
    ReadinessTimeoutError,
    poll_until,
    ros_child_env,
    thread_states,
)

FAST = (1.0, 1.0, 2.0)


def py(code: str) -> list[str]:
    return [sys.executable, "-c", textwrap.dedent(code)]


def test_env_enforces_dds_rules(tmp_path: Path) -> None:
    env = ros_child_env(
        17,
        log_dir=tmp_path,
        base={"PATH": "/bin", "PYTHONPATH": "/old"},
        extra={"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "ROS_DOMAIN_ID": "0", "X": "1"},
        pythonpath=["/repo"],
    )
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "SHM"
    assert env["ROS_DOMAIN_ID"] == "17"
    assert env["ROS_LOG_DIR"] == str(tmp_path)
    assert env["PYTHONUNBUFFERED"] == "1"
    assert env["PYTHONPATH"] == os.pathsep.join(["/repo", "/old"])
    assert env["X"] == "1"
    with pytest.raises(ValueError):
        ros_child_env(999)


def test_env_single_threaded_blas_unless_set(tmp_path: Path) -> None:
    # Idle OpenBLAS threads cost each numpy child ~0.1 s of CPU at start; a caller's choice wins.
    assert ros_child_env(17, log_dir=tmp_path, base={})["OPENBLAS_NUM_THREADS"] == "1"
    env = ros_child_env(17, log_dir=tmp_path, base={"OPENBLAS_NUM_THREADS": "4"})
    assert env["OPENBLAS_NUM_THREADS"] == "4"


def test_group_children_see_the_rules() -> None:
    code = """
        import os
        print("ENV", os.environ["FASTDDS_BUILTIN_TRANSPORTS"], os.environ["ROS_DOMAIN_ID"],
              os.path.isdir(os.environ["ROS_LOG_DIR"]), flush=True)
    """
    with ProcessGroup(domain_id=33, stop_timeouts=FAST, sink=lambda _l: None) as group:
        child = group.start("envcheck", py(code), extra_env={"ROS_DOMAIN_ID": "0"})
        child.expect_exit()
        m = child.wait_for_line(r"ENV (\S+) (\S+) (\S+)", 10)
        assert m.groups() == ("SHM", "33", "True")


def test_wait_for_line_consumes_in_order_and_prefixes() -> None:
    seen: list[str] = []
    child = ManagedProcess(
        "talker",
        py("""
            import time
            for i in range(3):
                print(f"tick {i}", flush=True)
            time.sleep(30)
        """),
        sink=seen.append,
    )
    try:
        assert child.wait_for_line(r"tick (\d)", 10).group(1) == "0"
        assert child.wait_for_line(r"tick (\d)", 10).group(1) == "1"
        assert child.wait_for_line(r"tick (\d)", 10, from_start=True).group(1) == "0"
        with pytest.raises(ReadinessTimeoutError):
            child.wait_for_line(r"never", 0.3)
        child.wait_for_line(r"tick 2", 10)
        child.wait_for_line(r"tick 0", 10, from_start=True)  # the cursor back after the first line
        child.skip_output()  # ... and past every line read so far
        with pytest.raises(ReadinessTimeoutError):
            child.wait_for_line(r"tick", 0.3)
    finally:
        child.stop(FAST)
    assert "[talker] tick 2" in seen


def test_wait_for_line_reports_early_exit() -> None:
    child = ManagedProcess("quitter", py("print('bye'); raise SystemExit(4)"), sink=lambda _l: None)
    try:
        with pytest.raises(ChildDiedError) as err:
            child.wait_for_line("ready", 10)
        assert err.value.returncode == 4
        assert "bye" in err.value.tail
    finally:
        child.stop(FAST)


def test_second_sigint_stops_a_child_that_ignores_the_first() -> None:
    code = """
        import signal, sys, time
        hits = []
        def handler(sig, frame):
            hits.append(sig)
            print("SIGINT", len(hits), flush=True)
            if len(hits) == 2:
                sys.exit(0)
        signal.signal(signal.SIGINT, handler)
        print("ready", flush=True)
        while True:
            time.sleep(0.05)
    """
    child = ManagedProcess("stubborn", py(code), sink=lambda _l: None)
    child.wait_for_line("ready", 10)
    rc = child.stop((0.5, 5.0, 2.0))
    assert rc == 0
    assert child.wait_for_line("SIGINT 2", 1, from_start=True)


def test_sigkill_when_sigint_is_ignored_and_descendants_go_too(tmp_path: Path) -> None:
    pidfile = tmp_path / "grandchild.pid"
    code = f"""
        import signal, subprocess, sys, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        deaf = "import signal,time; signal.signal(signal.SIGINT, signal.SIG_IGN); time.sleep(60)"
        g = subprocess.Popen([sys.executable, "-c", deaf])
        open({str(pidfile)!r}, "w").write(str(g.pid))
        print("ready", flush=True)
        time.sleep(60)
    """
    child = ManagedProcess("deaf", py(code), sink=lambda _l: None)
    child.wait_for_line("ready", 10)
    grandchild = int(pidfile.read_text())
    rc = child.stop((0.3, 0.3, 3.0))
    assert rc == -signal.SIGKILL
    assert not child.group_alive()
    state = Path(f"/proc/{grandchild}/stat")
    # Gone, or a zombie waiting for init to reap it.
    assert not state.exists() or state.read_text().rsplit(")", 1)[-1].split()[0] == "Z"


def test_a_child_reaped_late_after_sigkill_still_gets_its_exit_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a saturated machine the killed child was not reaped within the last wait: the stop raised and
    the bring-up skipped that child's "stopped" line. It waits longer now (a killed process ends)."""
    code = """
        import signal, time
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print("ready", flush=True)
        time.sleep(60)
    """
    child = ManagedProcess("slow_to_reap", py(code), sink=lambda _l: None)
    child.wait_for_line("ready", 10)
    real_wait = child.popen.wait
    ran_out = []

    def wait(timeout: float | None = None) -> int:
        if timeout == 1.0 and not ran_out:  # the wait after SIGKILL runs out once
            ran_out.append(timeout)
            time.sleep(0.2)
            raise subprocess.TimeoutExpired(child.cmd, timeout)
        return real_wait(timeout)

    monkeypatch.setattr(child.popen, "wait", wait)
    assert child.stop((0.2, 0.3, 1.0)) == -signal.SIGKILL
    assert ran_out


def test_group_stops_in_reverse_order(tmp_path: Path) -> None:
    order = tmp_path / "order.txt"
    code = """
        import signal, sys, time
        name = sys.argv[1]
        def handler(sig, frame):
            with open(sys.argv[2], "a") as f:
                f.write(name + "\\n")
            sys.exit(0)
        signal.signal(signal.SIGINT, handler)
        print("ready", flush=True)
        while True:
            time.sleep(0.05)
    """
    with ProcessGroup(domain_id=5, stop_timeouts=FAST, sink=lambda _l: None) as group:
        for name in ("a", "b", "c"):
            group.start(name, [*py(code), name, str(order)], ready="ready")
    assert order.read_text().split() == ["c", "b", "a"]
    assert not group.leaked()


def test_group_reports_unexpected_death_but_not_announced_exits() -> None:
    with pytest.raises(ChildDiedError) as err:
        with ProcessGroup(domain_id=5, stop_timeouts=FAST, sink=lambda _l: None) as group:
            crash = group.start("crasher", py("print('up', flush=True); raise SystemExit(3)"), ready="up")
            crash.popen.wait(10)
            with pytest.raises(ChildDiedError):
                group.check()
    assert err.value.name == "crasher"
    assert err.value.returncode == 3

    with ProcessGroup(domain_id=5, stop_timeouts=FAST, sink=lambda _l: None) as group:
        child = group.start("planned", py("print('up', flush=True); raise SystemExit(3)"))
        child.expect_exit()
        child.popen.wait(10)
        group.check()


def test_ready_timeout_stops_the_child() -> None:
    with ProcessGroup(domain_id=5, stop_timeouts=FAST, sink=lambda _l: None) as group:
        with pytest.raises(ReadinessTimeoutError):
            group.start("mute", py("import time; time.sleep(30)"), ready="never", ready_timeout=0.5)
        assert not group.children[0].is_running()


def _alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[-1].split()[0] not in ("Z", "X")
    except OSError:
        return False


@pytest.mark.parametrize("sched_fifo", [False, True])
def test_a_child_dies_with_its_killed_parent(sched_fifo: bool) -> None:
    """kill -9 of a supervisor (a crashed pytest or bring-up) takes its children along: no orphans,
    also for a child that made itself real-time (where the kernel permits it)."""
    child_code = "import os, time\n"
    if sched_fifo:
        child_code += (
            "try:\n    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))\n"
            "except OSError:\n    pass\n"
        )
    child_code += "print('up', flush=True)\ntime.sleep(60)\n"
    parent = ManagedProcess(
        "parent",
        py(f"""
            import sys, time
            from redarm_ros.procs import ManagedProcess
            c = ManagedProcess("child", [sys.executable, "-c", {child_code!r}], sink=lambda line: None)
            c.wait_for_line("up", 20.0)
            print("child", c.pid, flush=True)
            time.sleep(60)
        """),
        sink=lambda line: None,
    )
    try:
        child_pid = int(parent.wait_for_line(r"child (\d+)", 30.0).group(1))
        assert _alive(child_pid)
        real_time = os.sched_getscheduler(child_pid) == os.SCHED_FIFO
        os.kill(parent.pid, signal.SIGKILL)  # only the parent: the child is in its own session
        parent.popen.wait(10.0)
        deadline = time.monotonic() + 10.0
        while _alive(child_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child_pid)
    finally:
        parent.kill()
    if sched_fifo and not real_time:
        pytest.skip("the kernel refused SCHED_FIFO here: the child was not real-time")


def test_thread_states_names_the_threads_that_are_not_sleeping() -> None:
    """The line logged for a child that does not stop: a spinning thread shows up with its scheduling."""
    import subprocess

    spin = subprocess.Popen(py("while True: pass"))
    idle = subprocess.Popen(py("import time; time.sleep(60)"))
    try:
        assert poll_until(lambda: "R normal" in thread_states(spin.pid), 10.0)
        line = thread_states(spin.pid)
        assert line.startswith("threads: 1 R; not sleeping: ") and "cpu " in line
        assert poll_until(lambda: thread_states(idle.pid) == "threads: 1 S", 10.0), thread_states(idle.pid)
    finally:
        for p in (spin, idle):
            p.kill()
            p.wait()
    assert thread_states(spin.pid) == "no thread information"
