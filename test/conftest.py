"""The suite's fixtures: the public ones of the ``redarm`` pytest plugin
(:mod:`redarm_ros.testing.pytest_plugin`) under the suite's names, plus what is the suite's own.

* ``ros_env`` (session, autouse): the plugin's ``redarm_dds`` for every test, so in-process rclpy
  obeys the network rule too (``domain_id``, ``log_dir``; ``REDARM_TEST_DOMAIN_ID`` pins the domain).
* ``rclpy_context``, ``procs``, ``canbus_server``, ``no_open_buses``: the plugin's
  ``redarm_rclpy_context``, ``redarm_procs``, ``redarm_canbus``, ``redarm_no_open_buses`` (the CAN
  test modules use the last for every test: ``pytestmark = pytest.mark.usefixtures("no_open_buses")``).
* under pytest-xdist ``--dist loadfile``: the files of hil tests in one unit (two with three workers or
  more; first, each on one worker, in order), every other file spread over the workers, the longest
  files first (``LONGEST_FILES``, then the files with a test marked slow).
* an autouse check that no child process of pytest outlives the test (``redarm_no_leftover_children``).
* an MCAP recording of every failing HIL run that talks ROS (``hil_recording.py``).
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from redarm_ros.procs import ProcessGroup
from redarm_ros.testing import CanBusServer
from redarm_ros.testing.sandbox import RosSandbox


def pytest_configure(config: pytest.Config) -> None:
    # The plugin is loaded by its entry point once redarm_ros is installed; from a tree that is not
    # installed, load it here (once: pytest refuses a plugin registered twice).
    if not config.pluginmanager.has_plugin("redarm"):
        import redarm_ros.testing.pytest_plugin as plugin

        config.pluginmanager.register(plugin, "redarm")


# Under pytest-xdist (`make test`: -n 3 --dist loadfile) the test files marked hil (the simulated arm's
# processes over the loopback bus) form serial units of work, started first and run in order, each by
# one worker: one unit with fewer than three workers, two with three or more (the demo and the stacks
# of its kind in the second), so at most two stacks share the cores and the stack chain is not the
# whole run's length. The stack tests spend much of their time waiting on real motion, which is why
# a third worker of pure computation fits beside them on two cores. Every other file is a unit of its
# own (its module fixtures start once), spread over the workers, longest first (LONGEST_FILES, then
# the files with a test marked slow), so that the run ends on short files on every worker instead of one
# finishing a long file alone. The two hil units take about as long as each other.
SERIAL_UNIT = "hil tests"
SECOND_SERIAL_UNIT = "hil tests (demo)"
SECOND_UNIT_FILES = frozenset({"test/test_e2e_demo.py", "test/test_examples.py", "test/test_e2e_stack6.py",
                               "test/test_two_hosts.py", "test/test_e2e_namespace.py",
                               "test/test_e2e_stream.py"})
# The files outside the hil units that took longest in a full run on two cores (one of them kept busy),
# longest first; a file missing here only starts later.
LONGEST_FILES = (
    "test/test_install_colcon.py", "test/test_control_reach.py", "test/test_node_reach_action.py",
    "test/test_control_replan.py", "test/test_kin_corridor.py", "test/test_node_controller.py",
    "test/test_control_tracking.py", "test/test_placement.py", "test/test_node_ik_service.py",
    "test/test_kin_feasible.py", "test/test_conftest_fixtures.py", "test/test_uml_socketcan.py",
    "test/test_control_stream_swivel.py", "test/test_control_reproductions.py",
    "test/test_view_browser.py",
)


@functools.cache
def marks_used(path: str) -> frozenset[str]:
    """The marks a test file's code uses (``pytest.mark.<name>``); a mark named in a string (a test file
    that writes test files) does not count."""
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"), filename=path)
    except (OSError, SyntaxError):
        return frozenset()
    return frozenset(node.attr for node in ast.walk(tree)
                     if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute)
                     and node.value.attr == "mark" and isinstance(node.value.value, ast.Name)
                     and node.value.value.id == "pytest")


def _unit_rank(root: Path, scope: str) -> tuple[int, int]:
    """Where a unit of work goes in the queue: the hil units, LONGEST_FILES in their order, the files
    with slow tests, then the rest."""
    if scope in (SERIAL_UNIT, SECOND_SERIAL_UNIT):
        return (0, 0)
    if scope in LONGEST_FILES:
        return (1, LONGEST_FILES.index(scope))
    return (2, 0) if "slow" in marks_used(str(root / scope)) else (3, 0)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    if config.getoption("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    root = config.rootpath
    two_units = int(config.getoption("numprocesses") or 0) >= 3

    class HilTestsInOneUnit(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            if "hil" not in marks_used(str(root / path)):
                return path
            return SECOND_SERIAL_UNIT if two_units and path in SECOND_UNIT_FILES else SERIAL_UNIT

        def _assign_work_unit(self, node: Any) -> None:
            # A stable sort: within a rank, xdist's order (most tests first) stays.
            for scope in sorted(self.workqueue, key=lambda scope: _unit_rank(root, scope)):
                self.workqueue.move_to_end(scope)
            super()._assign_work_unit(node)

    return HilTestsInOneUnit(config, log)


RosEnv = RosSandbox  # the suite's name for it


@pytest.fixture(scope="session", autouse=True)
def ros_env(redarm_dds: RosSandbox) -> RosSandbox:
    """Random ROS_DOMAIN_ID (1..200) and SHM-only transport for the whole session, in os.environ."""
    return redarm_dds


@pytest.fixture
def rclpy_context(redarm_rclpy_context: Any) -> Any:
    """A fresh, initialised ``rclpy.Context`` on the session's domain; shut down at teardown."""
    return redarm_rclpy_context


@pytest.fixture
def procs(redarm_procs: ProcessGroup) -> ProcessGroup:
    """A ProcessGroup for this test; fails the test if a child died unannounced or leaked."""
    return redarm_procs


@pytest.fixture
def canbus_server(redarm_canbus: CanBusServer) -> CanBusServer:
    """A ``redarm-canbus`` server subprocess on 127.0.0.1 (ephemeral port), stopped at teardown."""
    return redarm_canbus


@pytest.fixture
def no_open_buses(redarm_no_open_buses: None) -> None:
    """Fail the test if it leaves a CAN bus open (and close it)."""


@pytest.fixture(autouse=True)
def _no_leftover_children(redarm_no_leftover_children: None) -> Iterator[None]:
    """Fail a test that leaves a child process of pytest running (and end that child)."""
    yield


@pytest.fixture(autouse=True)
def _corridor_plans_waited(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process controllers wait for a point goal's corridor plan (``ReachController.wait_for_plans``)
    instead of holding for as many steps as the worker thread takes, so a test's steps do not depend on
    the machine's load; the node tests keep the node's hold."""
    if not request.path.name.startswith(("test_node_", "test_e2e_")):
        from redarm_ros.control.reach_controller import ReachController  # noqa: PLC0415

        monkeypatch.setattr(ReachController, "wait_for_plans", True)


# An MCAP recording of every failing HIL run that talks ROS, kept in .build/test_failures/ (see there).
# (A copy of this file elsewhere, as test_conftest_fixtures makes, goes without.)
if (Path(__file__).parent / "hil_recording.py").is_file():
    from hil_recording import _hil_recording, pytest_runtest_makereport  # noqa: F401
