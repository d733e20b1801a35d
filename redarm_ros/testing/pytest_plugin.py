"""pytest plugin ``redarm`` (entry point ``pytest11``): fixtures for tests against the simulated arm.

Loaded by pytest whenever redarm_ros is installed; it costs nothing until a test asks for one of
its fixtures (no rclpy, pybullet or python-can import before that, no autouse fixture). Every
fixture name starts with ``redarm_``:

* ``redarm_dds`` (session): SHM-only DDS on a ROS domain of the session's own (random in 1..200,
  or ``$REDARM_TEST_DOMAIN_ID``; one per pytest-xdist worker), set in ``os.environ`` for in-process rclpy too
  (:class:`~redarm_ros.testing.sandbox.RosSandbox`: ``domain_id``, ``log_dir``).
* ``redarm_arm``: a started :class:`~redarm_ros.testing.SimulatedArm`, configured by the test's
  ``@pytest.mark.redarm_arm(...)`` (keywords of :class:`~redarm_ros.testing.SimArmConfig`);
  stopped after the test, which fails if one of its processes died unannounced.
* ``redarm_arm_factory``: ``redarm_arm_factory(**config)`` starts more arms (or one configured in
  the test body); all stopped after the test.
* ``redarm_ros``: a :class:`~redarm_ros.testing.ros.RosTestContext` (own rclpy context on the
  session's domain, a node, an executor on a thread); ``redarm_rclpy_context``: only the context.
* ``redarm_procs``: a :class:`~redarm_ros.procs.ProcessGroup` for children of the test's own; the
  test fails if one died unannounced or left processes behind.
* ``redarm_canbus``: a loopback CAN bus server (:class:`~redarm_ros.testing.CanBusServer`).
* ``redarm_no_open_buses``, ``redarm_no_leftover_children``: fail a test that leaves a python-can
  bus open or a child process running (use them with ``pytest.mark.usefixtures`` or autouse
  wrappers in your conftest).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from redarm_ros.procs import ProcessGroup
    from redarm_ros.testing import CanBusServer, SimulatedArm
    from redarm_ros.testing.ros import RosTestContext
    from redarm_ros.testing.sandbox import RosSandbox

MARKER = "redarm_arm"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", f"{MARKER}(**config): configure the redarm_arm fixture (SimArmConfig keywords)")


def _stderr_sink(line: str) -> None:
    # Look sys.stderr up on every line: pytest swaps it per test phase, so output lands in the
    # report section of the test that was running.
    try:
        sys.stderr.write(line + "\n")
    except (ValueError, OSError):
        pass


def _child_report(dead: list[Any], leaked: list[Any]) -> str:
    problems = [f"{c.name} (pid {c.pid}) died unexpectedly with code {c.returncode}:\n  "
                + "\n  ".join(c.tail(15)) for c in dead]
    problems += [f"{c.name} (pid {c.pid}) left processes in its group" for c in leaked]
    return "child process trouble:\n" + "\n".join(problems)


@pytest.fixture(scope="session")
def redarm_dds(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
               ) -> Iterator[RosSandbox]:
    """SHM-only DDS and a ROS domain of the session's own, in ``os.environ`` for the session (under
    pytest-xdist: one domain per worker)."""
    from redarm_ros.testing.sandbox import dds_sandbox, worker_domain_id

    domain_id = None
    worker = getattr(request.config, "workerinput", None)  # set in a pytest-xdist worker only
    if worker is not None:
        domain_id = worker_domain_id(int(worker["workerid"].removeprefix("gw")), int(worker["workercount"]),
                                     str(worker["testrunuid"]))
    with dds_sandbox(tmp_path_factory.mktemp("ros_log"), domain_id) as sandbox:
        yield sandbox


@pytest.fixture
def redarm_procs(redarm_dds: RosSandbox) -> Iterator[ProcessGroup]:
    """A ProcessGroup for this test; fails the test if a child died unannounced or leaked."""
    import signal

    from redarm_ros.procs import ProcessGroup

    group = ProcessGroup(domain_id=redarm_dds.domain_id, log_dir=redarm_dds.log_dir, sink=_stderr_sink)
    yield group
    dead = group.unexpected_deaths()
    group.stop_all()
    leaked = group.leaked()
    for child in leaked:
        try:
            os.killpg(child.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if dead or leaked:
        pytest.fail(_child_report(dead, leaked), pytrace=False)


@pytest.fixture
def redarm_canbus(redarm_procs: ProcessGroup) -> CanBusServer:
    """A loopback CAN bus server on 127.0.0.1 (ephemeral port), stopped after the test."""
    from redarm_ros.testing import start_canbus_server

    return start_canbus_server(redarm_procs)


@pytest.fixture
def redarm_arm_factory(redarm_dds: RosSandbox) -> Iterator[Callable[..., SimulatedArm]]:
    """``factory(**config)``: a started SimulatedArm (SimArmConfig keywords); all stopped after the
    test, which fails if one of their processes died unannounced."""
    from redarm_ros.testing import SimulatedArm

    arms: list[SimulatedArm] = []

    def factory(**config: Any) -> SimulatedArm:
        arm = SimulatedArm(domain_id=redarm_dds.domain_id, sink=_stderr_sink, **config)
        arm.start()
        arms.append(arm)
        return arm

    yield factory
    dead = [c for arm in arms for c in arm.stack.group.unexpected_deaths()]
    for arm in reversed(arms):
        arm.close()
    if dead:
        pytest.fail(_child_report(dead, []), pytrace=False)


@pytest.fixture
def redarm_arm(request: pytest.FixtureRequest,
               redarm_arm_factory: Callable[..., SimulatedArm]) -> SimulatedArm:
    """The simulated arm, started as ``@pytest.mark.redarm_arm(...)`` says (default: bus and simulator)."""
    marker = request.node.get_closest_marker(MARKER)
    return redarm_arm_factory(**(marker.kwargs if marker else {}))


@pytest.fixture
def redarm_rclpy_context(redarm_dds: RosSandbox) -> Iterator[Any]:
    """A fresh, initialised ``rclpy.Context`` on the session's domain; shut down after the test."""
    rclpy = pytest.importorskip("rclpy")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=redarm_dds.domain_id)
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


@pytest.fixture
def redarm_ros(redarm_dds: RosSandbox) -> Iterator[RosTestContext]:
    """A ROS context for the test: own rclpy context, a node, an executor spinning on a thread."""
    pytest.importorskip("rclpy")
    from redarm_ros.testing.ros import RosTestContext

    with RosTestContext(redarm_dds.domain_id) as ros:
        yield ros


@pytest.fixture
def redarm_no_open_buses() -> Iterator[None]:
    """Fail the test if it leaves a python-can bus open (and close it)."""
    from redarm_ros.testing.leaks import OpenBusTracker

    with OpenBusTracker() as tracker:
        yield
    leaked = tracker.close_leaked()
    if leaked:
        pytest.fail(f"test left CAN buses open: {leaked}", pytrace=False)


@pytest.fixture
def redarm_no_leftover_children() -> Iterator[None]:
    """Fail the test if it leaves a child process of pytest running (and end that child)."""
    from redarm_ros.testing.leaks import leftover_children, live_children

    before = set(live_children(os.getpid()))
    yield
    left = leftover_children(before)
    if left:
        pytest.fail("test left child processes running (now killed): "
                    + "; ".join(f"{p}: {c}" for p, c in left.items()), pytrace=False)
