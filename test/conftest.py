"""Shared pytest fixtures: DDS isolation, child processes, the loopback CAN bus server.

* ``ros_env`` (session, autouse): a random ROS_DOMAIN_ID in 1..200 (or
  ``REDARM_TEST_DOMAIN_ID``), SHM-only Fast DDS and a temp ROS_LOG_DIR, set in
  ``os.environ`` so in-process rclpy obeys the network rule too.
* ``rclpy_context``: an initialised rclpy Context of its own, shut down after
  the test (tests running rclpy in the pytest process must not share one).
* ``procs``: a :class:`redarm_ros.procs.ProcessGroup` whose children inherit
  the rules; at teardown every child is stopped (SIGINT, SIGINT, SIGKILL) and
  the test fails if a child died unannounced or left descendants behind.
* ``canbus_server``: a ``redarm-canbus`` server subprocess on 127.0.0.1 and the
  python-can keyword arguments to reach it.
* ``no_open_buses``: fails a test that leaves a python-can bus open (and closes it); the CAN test
  modules use it for every test (``pytestmark = pytest.mark.usefixtures("no_open_buses")``).
* an autouse check that no child process of pytest outlives the test.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from support.can_buses import OpenBusTracker

from redarm_ros.procs import ManagedProcess, ProcessGroup, python_module_cmd, random_domain_id

REPO_ROOT = Path(__file__).resolve().parents[1]
_DDS_KEYS = ("FASTDDS_BUILTIN_TRANSPORTS", "ROS_DOMAIN_ID", "ROS_LOG_DIR", "ROS_AUTOMATIC_DISCOVERY_RANGE")


@dataclass(frozen=True)
class RosEnv:
    """The session's ROS isolation: ``domain_id`` and ``log_dir`` (also set in ``os.environ``)."""

    domain_id: int
    log_dir: Path


@pytest.fixture(scope="session", autouse=True)
def ros_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RosEnv]:
    """Random ROS_DOMAIN_ID (1..200) and SHM-only transport for the whole session, in os.environ."""
    domain = int(os.environ.get("REDARM_TEST_DOMAIN_ID") or random_domain_id())
    log_dir = tmp_path_factory.mktemp("ros_log")
    saved = {k: os.environ.get(k) for k in _DDS_KEYS}
    os.environ.update(
        FASTDDS_BUILTIN_TRANSPORTS="SHM",
        ROS_DOMAIN_ID=str(domain),
        ROS_LOG_DIR=str(log_dir),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
    )
    try:
        yield RosEnv(domain, log_dir)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.fixture
def rclpy_context(ros_env: RosEnv) -> Iterator[Any]:
    """A fresh, initialised ``rclpy.Context`` on the session's domain; shut down at teardown."""
    rclpy = pytest.importorskip("rclpy")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_env.domain_id)
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


def _stderr_sink(line: str) -> None:
    # Look sys.stderr up on every line: pytest swaps it per test phase, so output lands in the
    # report section of the test that was running.
    try:
        sys.stderr.write(line + "\n")
    except (ValueError, OSError):
        pass


@pytest.fixture
def procs(ros_env: RosEnv) -> Iterator[ProcessGroup]:
    """A ProcessGroup for this test; fails the test if a child died unannounced or leaked."""
    group = ProcessGroup(
        domain_id=ros_env.domain_id,
        log_dir=ros_env.log_dir,
        pythonpath=[REPO_ROOT],
        sink=_stderr_sink,
    )
    yield group
    dead = group.unexpected_deaths()
    group.stop_all()
    leaked = group.leaked()
    for child in leaked:
        try:
            os.killpg(child.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    problems = [f"{c.name} (pid {c.pid}) died unexpectedly with code {c.returncode}:\n  "
                + "\n  ".join(c.tail(15)) for c in dead]
    problems += [f"{c.name} (pid {c.pid}) left processes in its group" for c in leaked]
    if problems:
        pytest.fail("child process trouble:\n" + "\n".join(problems), pytrace=False)


@dataclass
class CanBusServer:
    """A running loopback bus server: ``port``, python-can ``kwargs`` for ``can.Bus(**kwargs)``."""

    port: int
    kwargs: dict[str, Any]
    process: ManagedProcess
    env: dict[str, str] = field(default_factory=dict)

    @property
    def channel(self) -> str:
        """The python-can channel string (``ws://127.0.0.1:<port>/``)."""
        return str(self.kwargs["channel"])

    def cli_args(self) -> list[str]:
        """``--can-interface remote --can-channel ws://...`` for redarm processes taking CAN flags."""
        return ["--can-interface", str(self.kwargs["interface"]), "--can-channel", self.channel]


def start_canbus_server(group: ProcessGroup, name: str = "canbus", port: int = 0) -> CanBusServer:
    """Start ``redarm-canbus`` (``python -m redarm_ros.can.bus_server``) in ``group``; wait for its port.

    ``port`` 0 picks an ephemeral one; pass a previous server's port to restart "the same bus".
    """
    pytest.importorskip("redarm_ros.can.bus_server", reason="redarm_ros.can.bus_server not written yet")
    proc = group.start(
        name,
        python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", str(port)),
        ready=r"REDARM_CANBUS_PORT=(\d+)",
        ready_timeout=20.0,
    )
    from redarm_ros.can.bus_server import client_config, client_env

    port = int(proc.ready_match.group(1))  # type: ignore[attr-defined]
    return CanBusServer(port=port, kwargs=client_config(port), process=proc, env=client_env(port))


@pytest.fixture
def canbus_server(procs: ProcessGroup) -> CanBusServer:
    """A ``redarm-canbus`` server subprocess on 127.0.0.1 (ephemeral port), stopped at teardown."""
    return start_canbus_server(procs)


def _live_children(pid: int) -> dict[int, str]:
    """Live (non-zombie) direct children of ``pid``: pid -> command line."""
    out: dict[int, str] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat", encoding="ascii", errors="replace") as f:
                fields = f.read().rsplit(")", 1)[-1].split()
            if int(fields[1]) != pid or fields[0] in ("Z", "X"):
                continue
            with open(f"/proc/{entry.name}/cmdline", "rb") as f:
                cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, IndexError, ValueError):
            continue
        out[int(entry.name)] = cmd
    return out


# Long-lived helpers that libraries start once per interpreter on purpose.
_BENIGN = ("multiprocessing.resource_tracker", "multiprocessing.forkserver")


@pytest.fixture(autouse=True)
def _no_leftover_children() -> Iterator[None]:
    """Fail a test that leaves a child process of pytest running (and end that child)."""
    me = os.getpid()
    before = set(_live_children(me))
    yield
    deadline = time.monotonic() + 3.0
    while True:
        left = {p: c for p, c in _live_children(me).items()
                if p not in before and not any(b in c for b in _BENIGN)}
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    if left:
        for p in left:
            try:
                os.kill(p, signal.SIGKILL)
                os.waitpid(p, 0)
            except (ProcessLookupError, ChildProcessError):
                pass
        pytest.fail("test left child processes running (now killed): "
                    + "; ".join(f"{p}: {c}" for p, c in left.items()), pytrace=False)


# An MCAP recording of every failing HIL run that talks ROS, kept in .build/test_failures/ (see there).
# (A copy of this file elsewhere, as test_conftest_fixtures makes, goes without.)
if (Path(__file__).parent / "hil_recording.py").is_file():
    from hil_recording import _hil_recording, pytest_runtest_makereport  # noqa: F401


@pytest.fixture
def no_open_buses() -> Iterator[None]:
    """Fail the test if it leaves a CAN bus open (and close it)."""
    with OpenBusTracker() as tracker:
        yield
    leaked = tracker.close_leaked()
    if leaked:
        pytest.fail(f"test left CAN buses open: {leaked}", pytrace=False)
