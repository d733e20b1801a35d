"""Keep an MCAP recording of every failing hardware-in-the-loop run (pytest plugin, via conftest.py).

Every test marked ``hil`` that talks ROS (it uses the ``rclpy_context`` or ``redarm_ros`` fixture) gets a
recorder process (``redarm-record --all``) recording every topic of the test's ROS domain (``/joint_states``,
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
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from redarm_ros.procs import ManagedProcess, ProcessGroup, python_module_cmd

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
    """``redarm-record`` in a child process of its own, writing ``path``.

    A separate process, not a node in the test's process: destroying an in-process recorder node
    at teardown crashed rclpy (a segfault in ``destroy_node``) in about one full suite run in four.
    It is not waited for: the test starts at once, the recorder joins the domain within a second or
    two (a failing run's first moments may be missing from its recording)."""

    path: Path
    group: ProcessGroup
    child: ManagedProcess
    closed: bool = False
    exit_code: int | None = None

    @classmethod
    def start(cls, domain_id: int, log_dir: Path, path: Path) -> HilRecording:
        group = ProcessGroup(domain_id=domain_id, log_dir=log_dir, pythonpath=[REPO_ROOT],
                             sink=lambda line: None)
        cmd = python_module_cmd("redarm_ros.nodes.record", "--all", "--tf-from-joint-states",
                                "-o", str(path), "--ros-args", "--log-level", "warn")
        child = group.start("hil_recorder", cmd)
        return cls(path, group, child)

    def close(self) -> None:
        """Stop the recorder (SIGINT: it closes the file), idempotent."""
        if self.closed:
            return
        self.closed = True
        self.exit_code = self.group.stop(self.child)

    def summary(self) -> str:
        """The recorder's last lines (its message counts)."""
        return " | ".join(self.child.tail(3))

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
        rep.sections.append(("HIL recording", f"kept {dest} (recorder: {rec.summary()})"))
    except Exception as exc:  # noqa: BLE001 - the test's own failure matters more than its recording
        rep.sections.append(("HIL recording", f"could not keep the recording: {exc!r}"))


@pytest.fixture(autouse=True)
def _hil_recording(request: pytest.FixtureRequest) -> Iterator[None]:
    """Record HIL tests that use ROS (marked ``hil``, using ``rclpy_context`` or ``redarm_ros``)."""
    uses_ros = {"rclpy_context", "redarm_ros", "redarm_rclpy_context"} & set(request.fixturenames)
    if request.node.get_closest_marker("hil") is None or not uses_ros:
        yield
        return
    env = request.getfixturevalue("ros_env")
    tmp = request.getfixturevalue("tmp_path")
    rec = HilRecording.start(env.domain_id, env.log_dir, tmp / "run.mcap")
    request.node.stash[RECORDING_KEY] = rec
    try:
        yield
    finally:
        rec.close()
        del request.node.stash[RECORDING_KEY]
