"""The nodes' standard main(): at shutdown it waits for callbacks still running in executor threads
before the node is destroyed (destroying it under a publishing callback crashes inside rcl)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402

from redarm_ros.nodes._common import _drain_callbacks  # noqa: E402


@pytest.fixture
def ctx() -> Iterator[Context]:
    context = Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


def _spin_with_busy_timer(ctx: Context, release: threading.Event) -> tuple[Node, MultiThreadedExecutor,
                                                                            threading.Thread, dict]:
    """A node whose timer callback runs until ``release`` is set, spun by a multi-threaded executor;
    returns once that callback is running."""
    node = Node("runner_probe", context=ctx)
    marks: dict[str, float] = {}

    def busy() -> None:
        if "started" in marks:
            return
        marks["started"] = time.monotonic()
        release.wait(10.0)
        marks["finished"] = time.monotonic()

    node.create_timer(0.01, busy)
    executor = MultiThreadedExecutor(context=ctx)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    end = time.monotonic() + 10.0
    while "started" not in marks and time.monotonic() < end:
        time.sleep(0.01)
    assert "started" in marks
    return node, executor, spinner, marks


def test_shutdown_waits_for_a_running_callback(ctx: Context) -> None:
    release = threading.Event()
    node, executor, spinner, marks = _spin_with_busy_timer(ctx, release)
    threading.Timer(0.5, release.set).start()  # the callback ends 0.5 s from now
    assert _drain_callbacks(executor, 5.0)
    assert "finished" in marks  # it returned only after the callback had ended
    spinner.join(5.0)
    assert not spinner.is_alive()
    node.destroy_node()


def test_shutdown_gives_up_on_a_callback_that_does_not_end(ctx: Context) -> None:
    release = threading.Event()
    node, executor, spinner, marks = _spin_with_busy_timer(ctx, release)
    t0 = time.monotonic()
    assert not _drain_callbacks(executor, 0.3)  # still running: the caller must not destroy the node
    assert time.monotonic() - t0 < 2.0 and "finished" not in marks
    release.set()
    spinner.join(5.0)
    end = time.monotonic() + 5.0
    while "finished" not in marks and time.monotonic() < end:
        time.sleep(0.01)
    assert "finished" in marks
    node.destroy_node()


# A node whose first timer tick raises the bare RuntimeError rclpy's bindings raise when a take races the
# shutdown of the context; with SHUT_DOWN set the tick shuts the context down first, as Ctrl-C does.
_RACING_NODE = """
import sys
import rclpy
from rclpy.node import Node
from redarm_ros.nodes._common import run_node

class Racing(Node):
    def __init__(self):
        super().__init__("runner_race_probe")
        self.create_timer(0.05, self.tick)

    def tick(self):
        if sys.argv[1] == "shut_down":
            rclpy.shutdown()
        raise RuntimeError("Unable to convert call argument '0' to Python object")

raise SystemExit(run_node(Racing, []))
"""


@pytest.mark.parametrize(("mode", "stops_cleanly"), [("shut_down", True), ("running", False)])
def test_a_take_racing_shutdown_stops_cleanly_and_other_errors_still_raise(
        ros_env: object, mode: str, stops_cleanly: bool) -> None:
    proc = subprocess.run([sys.executable, "-c", _RACING_NODE, mode], capture_output=True, text=True,
                          timeout=60)
    if stops_cleanly:
        assert proc.returncode == 0, proc.stderr
        assert "Traceback" not in proc.stderr
    else:  # the context is still up: a real error, not swallowed
        assert proc.returncode != 0
        assert "Unable to convert call argument" in proc.stderr


_NICE_NODE = """
import json, os
import rclpy
from rclpy.node import Node
from redarm_ros.nodes._common import run_node

class Niced(Node):
    def __init__(self):
        super().__init__("runner_nice_probe")
        self.declare_parameter("nice", -3)
        self.create_timer(0.05, self.tick)

    def tick(self):
        tids = os.listdir("/proc/self/task")
        print(json.dumps(sorted({os.getpriority(os.PRIO_PROCESS, int(t)) for t in tids})), flush=True)
        rclpy.shutdown()

raise SystemExit(run_node(Niced, []))
"""


@pytest.mark.skipif(not hasattr(os, "getpriority") or os.geteuid() != 0, reason="needs root to lower nice")
def test_run_node_applies_the_nodes_nice_parameter_to_every_thread(ros_env: object) -> None:
    proc = subprocess.run([sys.executable, "-c", _NICE_NODE], capture_output=True, text=True, timeout=60,
                          preexec_fn=lambda: os.setpriority(os.PRIO_PROCESS, 0, 0))
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [-3]
    assert "running at nice -3" in proc.stderr


_RT_NODE = """
import json, os
import rclpy
from rclpy.node import Node
from redarm_ros.nodes._common import run_node

class RealTime(Node):
    PROCESS_REALTIME = True

    def __init__(self):
        super().__init__("runner_rt_probe")
        self.declare_parameter("nice", -3)
        self.declare_parameter("realtime_priority", 6)
        self.create_timer(0.05, self.tick)

    def tick(self):
        tids = [int(t) for t in os.listdir("/proc/self/task")]
        print("RUNNING", json.dumps(sorted({(os.sched_getscheduler(t), os.sched_getparam(t).sched_priority)
                                            for t in tids})), flush=True)
        rclpy.shutdown()

raise SystemExit(run_node(RealTime, []))
"""


def _rt_node_run() -> tuple[dict[str, list[list[int]]], str]:
    proc = subprocess.run([sys.executable, "-c", _RT_NODE], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    seen = {}
    for line in proc.stdout.splitlines():
        tag, _, rest = line.partition(" ")
        if tag == "RUNNING":
            seen[tag] = json.loads(rest)
    return seen, proc.stderr


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler") or os.geteuid() != 0,
                    reason="needs root for SCHED_FIFO")
def test_run_node_puts_every_thread_of_a_realtime_node_at_fifo(ros_env: object) -> None:
    """The controller's case: the middleware's threads exist before the node learns its priority."""
    seen, stderr = _rt_node_run()
    assert seen["RUNNING"] == [[os.SCHED_FIFO, 6]]
    assert "SCHED_FIFO priority 6" in stderr


# A node whose close() (the start of run_node's teardown) takes a while, as a real one does on a
# starved machine; it says when it spins, and when teardown starts and ends.
_SLOW_TEARDOWN_NODE = """
import time
from rclpy.node import Node
from redarm_ros.nodes._common import run_node

class SlowTeardown(Node):
    def __init__(self):
        super().__init__("runner_teardown_probe")
        self.timer = self.create_timer(0.05, self.ready)

    def ready(self):  # from a callback: the node is built and spinning
        self.timer.cancel()
        print("READY", flush=True)

    def close(self):
        print("CLOSING", flush=True)
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            time.sleep(0.01)
        print("CLOSED", flush=True)

code = run_node(SlowTeardown, [])
print("RETURNED", code, flush=True)
raise SystemExit(code)
"""


def _ctrl_c_during_teardown(times: int) -> tuple[int, str, str]:
    """Start the slow-teardown node, SIGINT it once it runs and again ``times - 1`` times while it
    tears down; returns (exit code, stdout, stderr)."""
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_TEARDOWN_NODE], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        lines = [proc.stdout.readline()]
        assert lines[0].strip() == "READY", lines
        proc.send_signal(signal.SIGINT)
        lines.append(proc.stdout.readline())
        assert lines[-1].strip() == "CLOSING", lines
        for _ in range(times - 1):
            time.sleep(0.2)
            proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, "".join(lines) + out, err


@pytest.mark.parametrize("times", [1, 3])
def test_ctrl_c_during_teardown_is_noted_and_the_teardown_finishes(ros_env: object, times: int) -> None:
    """A supervisor's staged stop sends SIGINT again after its grace period: raised inside the
    teardown, it would abandon it and end the process by the signal (exit code -2)."""
    code, out, err = _ctrl_c_during_teardown(times)
    assert code == 0, (out, err)
    assert out.split() == ["READY", "CLOSING", "CLOSED", "RETURNED", "0"], (out, err)
    assert "Traceback" not in err, err
    assert ("already stopping" in err) == (times > 1), err


# A node that logs through its own logger (to /rosout) while it tears down, as can_driver does when its
# cycle process reports that it stopped.
_LOGGING_TEARDOWN_NODE = """
import time
from rclpy.node import Node
from redarm_ros.nodes._common import run_node

class LoggingTeardown(Node):
    def __init__(self):
        super().__init__("runner_sigterm_probe")
        self.timer = self.create_timer(0.05, self.ready)

    def ready(self):
        self.timer.cancel()
        print("READY", flush=True)

    def close(self):
        print("CLOSING", flush=True)
        self.get_logger().info("closing: this line goes to /rosout too")
        time.sleep(0.3)
        print("CLOSED", flush=True)

code = run_node(LoggingTeardown, [])
print("RETURNED", code, flush=True)
raise SystemExit(code)
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_takes_the_same_clean_path_as_ctrl_c(ros_env: object, sig: int) -> None:
    """docker stop and systemd send SIGTERM: the node tears down as on Ctrl-C, its logs still reach
    /rosout, and it exits with code 0 (it used to end with "Failed to publish log message to rosout")."""
    proc = subprocess.Popen([sys.executable, "-c", _LOGGING_TEARDOWN_NODE], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "READY"
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, (out, err)
    assert out.split() == ["CLOSING", "CLOSED", "RETURNED", "0"], (out, err)
    assert "Traceback" not in err and "Failed to publish" not in err, err


# A node whose construction takes a while and, like a library's catch-all or a finaliser, swallows the
# KeyboardInterrupt that a Ctrl-C raises meanwhile.
_SWALLOWING_CONSTRUCTOR_NODE = """
import time
from rclpy.node import Node
from redarm_ros.nodes._common import run_node

class SlowStart(Node):
    def __init__(self):
        super().__init__("runner_slow_start_probe")
        print("BUILDING", flush=True)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            try:
                time.sleep(0.01)
            except BaseException:
                pass
        self.create_timer(0.05, lambda: print("SPINNING", flush=True))

code = run_node(SlowStart, [])
print("RETURNED", code, flush=True)
raise SystemExit(code)
"""


def test_a_ctrl_c_while_the_node_is_built_is_not_lost(ros_env: object) -> None:
    """A SIGINT in a node's first second, whose KeyboardInterrupt some code swallowed, still stops it
    (the controller once went on running after a bring-up's Ctrl-C in its first second)."""
    proc = subprocess.Popen([sys.executable, "-c", _SWALLOWING_CONSTRUCTOR_NODE], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "BUILDING"
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"still running 20 s after SIGINT: {out} {err}") from None
    assert proc.returncode == 0, (out, err)
    assert "SPINNING" not in out and out.split()[-2:] == ["RETURNED", "0"], (out, err)
