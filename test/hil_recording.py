"""Keep an MCAP recording of every failing hardware-in-the-loop run (pytest plugin, via conftest.py).

Every test marked ``hil`` that talks ROS (it uses the ``rclpy_context`` fixture) gets a recorder
node in its own rclpy context, recording every topic of the test's ROS domain (``/joint_states``,
``/joint_command``, ``/diagnostics``, ``/rosout``, ...) plus ``/tf`` computed from the joint states,
into ``<tmp_path>/run.mcap``. When the test fails, the recording is closed at once and copied to the
failure output directory, ``$REDARM_TEST_FAILURE_DIR`` or ``.build/test_failures/``, as
``<test name>/recording.mcap``; the failure report says where (section "HIL recording"). Open it in
Foxglove or play it with ``ros2 bag play``. A passing run's recording is left to pytest's temporary
directory clean-up.
"""

from __future__ import annotations

import os
import re
import shutil
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
FAILURE_DIR_ENV = "REDARM_TEST_FAILURE_DIR"
RECORDING_KEY = pytest.StashKey["HilRecording"]()


def failure_dir() -> Path:
    """Where recordings of failing runs are kept."""
    env = os.environ.get(FAILURE_DIR_ENV, "").strip()
    return Path(env) if env else REPO_ROOT / ".build" / "test_failures"


def run_dir_name(nodeid: str) -> str:
    """A file-system-safe directory name for a test id."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", nodeid.split("/")[-1]).strip("_")[:150]


@dataclass
class HilRecording:
    """A recorder node spinning in its own thread, writing ``path``."""

    path: Path
    writer: Any
    node: Any
    executor: Any
    thread: threading.Thread
    stop_event: threading.Event
    closed: bool = False

    @classmethod
    def start(cls, ctx: Any, path: Path) -> HilRecording:
        from rclpy.executors import SingleThreadedExecutor

        from redarm_ros.nodes.record import RecorderNode
        from redarm_ros.record.mcap_io import Ros2McapWriter

        writer = Ros2McapWriter(path)
        node = RecorderNode(writer, None, tf_from_joint_states=True, context=ctx, node_name="hil_recorder")
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        stop = threading.Event()

        def spin() -> None:
            while not stop.is_set():
                executor.spin_once(timeout_sec=0.05)

        thread = threading.Thread(target=spin, name="hil_recorder", daemon=True)
        thread.start()
        return cls(path, writer, node, executor, thread, stop)

    def close(self) -> None:
        """Stop spinning, destroy the node, finish the file (idempotent)."""
        if self.closed:
            return
        self.closed = True
        self.stop_event.set()
        self.thread.join(10.0)  # spin_once returns within 50 ms plus a callback
        if self.thread.is_alive():  # destroying a node that a thread still spins segfaults rclpy
            raise RuntimeError("hil recorder spin thread did not stop within 10 s")
        self.executor.remove_node(self.node)  # nothing may still dispatch to the node we destroy
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.writer.close()

    def keep(self, nodeid: str) -> Path:
        """Close and copy the recording into the failure output directory; returns the copy."""
        self.close()
        dest = failure_dir() / run_dir_name(nodeid) / "recording.mcap"
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(self.path, dest)
        return dest


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """On a failing call of a recorded test: keep its recording and name it in the report."""
    outcome = yield
    rep = outcome.get_result()
    rec = item.stash.get(RECORDING_KEY, None)
    if rec is None or rep.when != "call" or not rep.failed:
        return
    try:
        dest = rec.keep(item.nodeid)
        counts = ", ".join(f"{t} {n}" for t, n in sorted(rec.writer.counts.items()))
        rep.sections.append(("HIL recording", f"kept {dest} ({counts})"))
    except Exception as exc:  # noqa: BLE001 - the test's own failure matters more than its recording
        rep.sections.append(("HIL recording", f"could not keep the recording: {exc!r}"))


@pytest.fixture(autouse=True)
def _hil_recording(request: pytest.FixtureRequest) -> Iterator[None]:
    """Record HIL tests that use ROS (marked ``hil``, using ``rclpy_context``)."""
    if request.node.get_closest_marker("hil") is None or "rclpy_context" not in request.fixturenames:
        yield
        return
    ctx = request.getfixturevalue("rclpy_context")
    tmp = request.getfixturevalue("tmp_path")
    rec = HilRecording.start(ctx, tmp / "run.mcap")
    request.node.stash[RECORDING_KEY] = rec
    try:
        yield
    finally:
        rec.close()
        del request.node.stash[RECORDING_KEY]
