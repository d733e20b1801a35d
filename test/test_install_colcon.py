"""Issue 4: the package installs the ament way, so `ros2 run redarm_ros <node>` works on a real install.

One `colcon build` of both packages (the repo root `redarm_ros`, ament_python, and
`interfaces/redarm_interfaces`, ament_cmake) into a temporary workspace, with the venv's colcon and
the ROS wheels as the underlay (what scripts/setup_env.sh prepares). Then:

* every node executable is in ``lib/redarm_ros/`` and the ament index marks both packages;
* each node is resolved through ``ament_index_python`` exactly as ``ros2 run`` does
  (``get_package_prefix`` + ``lib/<package>/<executable>``) and started with ``--help`` in the
  environment ``source install/setup.bash`` would give; it must either exit 0 or still be running
  after a few seconds (a node may ignore ``--help`` and spin; it may fail later for lack of a bus),
  and it must not die with a traceback. It is then stopped: SIGINT, wait, SIGINT, SIGKILL.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from redarm_ros.procs import ManagedProcess, ros_child_env

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
PYVER = f"python{sys.version_info.major}.{sys.version_info.minor}"

# ros2 run names -> module holding main (setup.py console_scripts; test_package_layout checks they agree).
NODES = {
    "ik_service": "redarm_ros.nodes.ik_service",
    "controller": "redarm_ros.nodes.controller",
    "can_driver": "redarm_ros.nodes.can_driver",
    "sim": "redarm_ros.sim.hardware",
    "view": "redarm_ros.nodes.view",
}
TOOLS = ["redarm-sim", "redarm-canbus", "redarm-bringup", "redarm-demo", "redarm-view", "redarm-record"]
START_GRACE_S = 6.0

pytestmark = pytest.mark.slow


@dataclass(frozen=True)
class Workspace:
    """A built colcon workspace: ``root``, ``install`` (isolated layout) and the build ``log``."""

    root: Path
    install: Path
    log: str

    def prefix(self, package: str) -> Path:
        return self.install / package


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Workspace]:
    colcon = shutil.which("colcon", path=str(VENV_BIN))
    if colcon is None:
        pytest.fail(f"colcon is not installed in {VENV_BIN}; run `make setup` (scripts/setup_env.sh)",
                    pytrace=False)
    root = tmp_path_factory.mktemp("colcon_ws")
    env = dict(os.environ)
    # The venv is the underlay, as /opt/ros/jazzy is on an apt install.
    env.update(
        CMAKE_PREFIX_PATH=sys.prefix,
        AMENT_PREFIX_PATH=sys.prefix,
        PATH=f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}",
        COLCON_HOME=str(root / "colcon_home"),
        PYTHONNOUSERSITE="1",
    )
    cmd = [
        colcon, "--log-base", str(root / "log"), "build",
        # The interfaces package sits inside the redarm_ros package; colcon does not look inside a
        # package, so both are named (docs/setup.md gives the same command for a real workspace).
        "--base-paths", str(REPO), str(REPO / "interfaces"),
        "--build-base", str(root / "build"), "--install-base", str(root / "install"),
        "--event-handlers", "console_direct-", "console_cohesion+",
        "--cmake-args", "-DBUILD_TESTING=OFF", f"-DPython3_EXECUTABLE={VENV_BIN / 'python3'}",
    ]
    proc = subprocess.run(cmd, cwd=root, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=600)
    if proc.returncode != 0:
        pytest.fail(f"colcon build failed ({proc.returncode}):\n{proc.stdout[-6000:]}", pytrace=False)
    yield Workspace(root=root, install=root / "install", log=proc.stdout)
    shutil.rmtree(root, ignore_errors=True)


def test_build_finished_both_packages(workspace: Workspace) -> None:
    assert re.search(r"Summary: 2 packages finished", workspace.log), workspace.log[-2000:]


@pytest.mark.parametrize("exe", [*NODES, *TOOLS])
def test_executable_installed_in_lib(workspace: Workspace, exe: str) -> None:
    path = workspace.prefix("redarm_ros") / "lib" / "redarm_ros" / exe
    assert path.is_file(), f"{path} missing; lib/redarm_ros has {sorted(os.listdir(path.parent))}"
    assert os.access(path, os.X_OK)
    # Not in bin/: ros2 run looks only in lib/<package> (setup.cfg redirects the scripts there).
    assert not (workspace.prefix("redarm_ros") / "bin" / exe).exists()


def test_ament_index_markers(workspace: Workspace) -> None:
    for package in ("redarm_ros", "redarm_interfaces"):
        marker = workspace.prefix(package) / "share" / "ament_index" / "resource_index" / "packages" / package
        assert marker.is_file(), marker
        assert (workspace.prefix(package) / "share" / package / "package.xml").is_file()


def test_data_files_installed(workspace: Workspace) -> None:
    share = workspace.prefix("redarm_ros") / "share" / "redarm_ros"
    for pattern in ("config/*.yaml", "config/arms/*.yaml", "config/scenes/*.yaml", "launch/*.launch.py"):
        in_repo = {p.name for p in REPO.glob(pattern)}
        installed = {p.name for p in share.glob(pattern)}
        assert in_repo == installed, f"{pattern}: repo has {sorted(in_repo)}, install has {sorted(installed)}"


def test_interfaces_importable_from_install(workspace: Workspace) -> None:
    """The freshly built interfaces load from the workspace install, not from the venv copy."""
    site = workspace.prefix("redarm_interfaces") / "lib" / PYVER / "site-packages"
    env = _sourced_env(workspace)
    code = ("import redarm_interfaces.srv as s; from redarm_interfaces.srv import SolveIK; "
            "SolveIK.Request(); print(s.__file__)")
    out = subprocess.run([sys.executable, "-c", code], env=env, stdin=subprocess.DEVNULL,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()).is_relative_to(site), out.stdout


def _sourced_env(workspace: Workspace) -> dict[str, str]:
    """What `source install/setup.bash` adds on top of the venv underlay, plus the DDS rules."""
    prefixes = [workspace.prefix("redarm_ros"), workspace.prefix("redarm_interfaces")]
    env = ros_child_env(int(os.environ.get("ROS_DOMAIN_ID", "0")) or 1,
                        log_dir=os.environ.get("ROS_LOG_DIR"))
    env["AMENT_PREFIX_PATH"] = os.pathsep.join([*map(str, prefixes), sys.prefix])
    env["PYTHONPATH"] = os.pathsep.join(str(p / "lib" / PYVER / "site-packages") for p in prefixes)
    env["LD_LIBRARY_PATH"] = os.pathsep.join(
        [str(workspace.prefix("redarm_interfaces") / "lib"), env.get("LD_LIBRARY_PATH", "")])
    return env


def _resolve_like_ros2_run(package: str, executable: str, env: dict[str, str]) -> Path:
    """ros2 run: get_package_prefix(package) / lib / package / executable, which must be executable."""
    from ament_index_python.packages import get_package_prefix

    saved = os.environ.get("AMENT_PREFIX_PATH")
    os.environ["AMENT_PREFIX_PATH"] = env["AMENT_PREFIX_PATH"]
    try:
        prefix = Path(get_package_prefix(package))
    finally:
        if saved is None:
            os.environ.pop("AMENT_PREFIX_PATH", None)
        else:
            os.environ["AMENT_PREFIX_PATH"] = saved
    path = prefix / "lib" / package / executable
    assert path.is_file() and os.access(path, os.X_OK), f"ros2 run would not find {path}"
    return path


@dataclass(frozen=True)
class StartResult:
    """How a started executable behaved: exited within the grace period (with ``returncode``) or not."""

    exited: bool
    returncode: int
    output: str


@pytest.fixture(scope="module")
def started(workspace: Workspace) -> dict[str, StartResult]:
    """Start every node whose module exists, all at once (one grace period), then stop them all."""
    env = _sourced_env(workspace)
    children: dict[str, ManagedProcess] = {}
    results: dict[str, StartResult] = {}
    try:
        for exe, module in NODES.items():
            if importlib.util.find_spec(module) is None:
                continue
            path = _resolve_like_ros2_run("redarm_ros", exe, env)
            children[exe] = ManagedProcess.start(exe, [str(path), "--help"], env=env, cwd=workspace.root,
                                                 sink=lambda line: None)
        deadline = time.monotonic() + START_GRACE_S
        while any(c.is_running() for c in children.values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        exited = {exe: not c.is_running() for exe, c in children.items()}
    finally:
        # SIGINT, wait, SIGINT, SIGKILL; a no-op for children that already exited.
        codes = {exe: c.stop() for exe, c in children.items()}
    for exe, c in children.items():
        results[exe] = StartResult(exited[exe], codes[exe], "\n".join(c.output()))
    return results


@pytest.mark.parametrize("exe", list(NODES))
def test_ros2_run_resolves_and_starts(
    workspace: Workspace, started: dict[str, StartResult], exe: str
) -> None:
    path = _resolve_like_ros2_run("redarm_ros", exe, _sourced_env(workspace))
    assert path.parent.parent.parent == workspace.prefix("redarm_ros")
    module = NODES[exe]
    if exe not in started:
        pytest.skip(f"{module} not written yet: resolution checked, start check pending")
    result = started[exe]
    tail = result.output[-4000:]
    if result.exited:
        assert result.returncode == 0, f"{exe} --help exited with {result.returncode}:\n{tail}"
    assert "Traceback" not in result.output, f"{exe} raised:\n{tail}"
    for bad in ("ModuleNotFoundError", "ImportError", "DistributionNotFound", "No module named"):
        assert bad not in result.output, f"{exe}: {bad}:\n{tail}"
