"""launch/redarm_sim.launch.py. launch/launch_ros are not installable here, so the file is read with
``ast``: every executable it names is a console script of the package (or one of the optional ROS
tools it may start), every config file it reads exists, every launch argument it uses is declared, and
DDS is kept on SHM. It is also *run* against minimal stand-ins for launch/launch_ros (recording the
actions it creates) over a temporary ament prefix, to check which description publisher it picks:
robot_state_publisher with the installed URDF when that package is present, else the description
node, and rviz2 with config/redarm.rviz on request."""

from __future__ import annotations

import ast
import configparser
import importlib.util
import os
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support.setup_py import console_scripts

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / "launch" / "redarm_sim.launch.py"
# Optional ROS tools the launch file may start (package, executable); not installable here.
EXTERNAL = {("robot_state_publisher", "robot_state_publisher"), ("rviz2", "rviz2")}


def _tree() -> ast.Module:
    return ast.parse(LAUNCH.read_text(encoding="utf-8"), filename=str(LAUNCH))


def _module_constants(tree: ast.Module) -> dict[str, object]:
    out: dict[str, object] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            try:
                out[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    return out


def _value(node: ast.AST, consts: dict[str, object]) -> object:
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name) and node.id in consts:
        return consts[node.id]
    return None


def _calls(tree: ast.Module, name: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and ((isinstance(n.func, ast.Name) and n.func.id == name)
                 or (isinstance(n.func, ast.Attribute) and n.func.attr == name))]


def _kw(call: ast.Call, key: str) -> ast.AST | None:
    return next((k.value for k in call.keywords if k.arg == key), None)


def test_launch_file_is_python_and_generates_a_description() -> None:
    tree = _tree()
    compile(tree, str(LAUNCH), "exec")
    assert any(isinstance(n, ast.FunctionDef) and n.name == "generate_launch_description" for n in tree.body)


def test_every_executable_is_a_console_script_of_the_package() -> None:
    tree = _tree()
    consts = _module_constants(tree)
    scripts = console_scripts()
    named: list[str] = []
    for call in _calls(tree, "Node") + _calls(tree, "ExecutableInPackage"):
        exe = _kw(call, "executable")
        pkg = _kw(call, "package")
        assert exe is not None and pkg is not None, ast.unparse(call)
        exe_v, pkg_v = _value(exe, consts), _value(pkg, consts)
        assert isinstance(exe_v, str), f"executable must be a literal: {ast.unparse(call)}"
        if (pkg_v, exe_v) in EXTERNAL:
            continue
        assert pkg_v == "redarm_ros", ast.unparse(call)
        named.append(exe_v)
    assert set(named) >= {"can_driver", "ik_service", "controller", "sim", "redarm-canbus", "description"}
    missing = sorted(set(named) - set(scripts))
    assert not missing, f"launch file names executables that setup.py does not install: {missing}"
    # Each named script's module exists in the source tree (the import target of the entry point).
    for exe in set(named):
        module = scripts[exe].split(":")[0]
        path = ROOT / (module.replace(".", "/") + ".py")
        assert path.is_file(), f"{exe}: module {module} missing"


def test_scripts_land_where_ros2_run_looks() -> None:
    """ament_python: console scripts go to lib/<package> (setup.cfg) and the launch file is installed."""
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    assert cfg.get("install", "install_scripts", fallback="").endswith("lib/redarm_ros")
    assert "launch/*.launch.py" in (ROOT / "setup.py").read_text(encoding="utf-8")


def test_config_files_it_reads_exist() -> None:
    text = LAUNCH.read_text(encoding="utf-8")
    tree = _tree()
    names = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
             and n.value.endswith(".yaml")}
    assert names >= {"sim.yaml", "can_driver.yaml", "ik_service.yaml", "controller.yaml",
                     "description.yaml"}, names
    rviz = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
            and n.value.endswith(".rviz") and " " not in n.value}
    assert rviz == {"redarm.rviz"}, rviz
    for name in names | rviz:
        assert (ROOT / "config" / name).is_file(), f"config/{name} missing (read by the launch file)"
    assert "get_package_share_directory" in text


def test_launch_arguments_are_declared() -> None:
    tree = _tree()
    declared = {ast.literal_eval(c.args[0]) for c in _calls(tree, "DeclareLaunchArgument")}
    used: set[str] = set()
    # LaunchConfiguration("x") directly, and arg("x") (the helper inside _stack).
    for c in _calls(tree, "LaunchConfiguration") + _calls(tree, "arg"):
        if c.args and isinstance(c.args[0], ast.Constant):
            used.add(c.args[0].value)
    assert used, "no launch arguments used?"
    assert used <= declared, f"undeclared launch arguments: {sorted(used - declared)}"


def test_dds_kept_on_shared_memory() -> None:
    tree = _tree()
    sets = [c for c in _calls(tree, "SetEnvironmentVariable")
            if [ast.literal_eval(a) for a in c.args[:2]] == ["FASTDDS_BUILTIN_TRANSPORTS", "SHM"]]
    assert sets, "the launch file must set FASTDDS_BUILTIN_TRANSPORTS=SHM"
    # The bus server binds loopback only.
    text = LAUNCH.read_text(encoding="utf-8")
    assert '"--host", "127.0.0.1"' in text


# -- the launch file run against stand-ins for launch / launch_ros -------------------------------------
class _Action:
    """Records how an action was constructed."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration:
    def __init__(self, name: str) -> None:
        self.name = name

    def perform(self, context: dict[str, str]) -> str:
        return context[self.name]


def _stub_modules() -> dict[str, types.ModuleType]:
    mods = {name: types.ModuleType(name) for name in (
        "launch", "launch.actions", "launch.conditions", "launch.substitutions", "launch_ros",
        "launch_ros.actions", "launch_ros.substitutions")}
    mods["launch"].LaunchDescription = lambda actions: list(actions)
    for name in ("DeclareLaunchArgument", "ExecuteProcess", "OpaqueFunction", "SetEnvironmentVariable"):
        setattr(mods["launch.actions"], name, type(name, (_Action,), {}))
    mods["launch.conditions"].IfCondition = type("IfCondition", (_Action,), {})
    mods["launch.substitutions"].LaunchConfiguration = _LaunchConfiguration
    mods["launch_ros.actions"].Node = type("Node", (_Action,), {})
    mods["launch_ros.substitutions"].ExecutableInPackage = type("ExecutableInPackage", (_Action,), {})
    return mods


@pytest.fixture
def prefix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An ament prefix holding redarm_ros (config/ from the source tree, urdf/ as the build makes it)
    and nothing else; the launch module's imports resolve to the stand-ins."""
    from redarm_ros.kinematics import load_arm
    from redarm_ros.sim.urdf import write_urdf

    share = tmp_path / "share" / "redarm_ros"
    (share / "urdf").mkdir(parents=True)
    (share / "config").symlink_to(ROOT / "config")
    for model in sorted((ROOT / "config" / "arms").glob("*.yaml")):
        write_urdf(load_arm(str(model)), str(share / "urdf" / f"{model.stem}.urdf"), prefix="")
    index = tmp_path / "share" / "ament_index" / "resource_index" / "packages"
    index.mkdir(parents=True)
    (index / "redarm_ros").touch()
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    for name, mod in _stub_modules().items():
        monkeypatch.setitem(sys.modules, name, mod)
    yield tmp_path


def _add_package(prefix: Path, package: str) -> None:
    (prefix / "share" / "ament_index" / "resource_index" / "packages" / package).touch()
    (prefix / "share" / package).mkdir(parents=True, exist_ok=True)


def _run_launch(**overrides: str) -> list[_Action]:
    spec = importlib.util.spec_from_file_location("redarm_sim_launch_under_test", LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    context = {a.args[0]: a.kwargs.get("default_value", "") for a in description
               if type(a).__name__ == "DeclareLaunchArgument"}
    unknown = set(overrides) - set(context)
    assert not unknown, f"not launch arguments: {unknown}"
    context.update(overrides)
    stack = [a for a in description if type(a).__name__ == "OpaqueFunction"]
    assert len(stack) == 1
    return stack[0].kwargs["function"](context)


def _nodes(actions: list[_Action]) -> dict[tuple[str, str], _Action]:
    return {(a.kwargs["package"], a.kwargs["executable"]): a for a in actions if type(a).__name__ == "Node"}


def _params(node: _Action) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for p in node.kwargs.get("parameters", []):
        if isinstance(p, dict):
            out.update(p)
        else:
            assert os.path.isfile(p), f"parameter file {p} missing"
    return out


def test_without_robot_state_publisher_the_description_node_publishes(prefix: Path) -> None:
    nodes = _nodes(_run_launch(arm="powercube7"))
    assert ("redarm_ros", "description") in nodes
    assert _params(nodes[("redarm_ros", "description")])["arm"] == "powercube7"
    assert ("robot_state_publisher", "robot_state_publisher") not in nodes
    assert ("rviz2", "rviz2") not in nodes
    assert {e for _, e in nodes} >= {"can_driver", "ik_service", "controller"}


def test_robot_state_publisher_is_used_when_installed(prefix: Path) -> None:
    _add_package(prefix, "robot_state_publisher")
    nodes = _nodes(_run_launch(arm="pa10_7c"))
    rsp = nodes[("robot_state_publisher", "robot_state_publisher")]
    installed = (prefix / "share" / "redarm_ros" / "urdf" / "pa10_7c.urdf").read_text(encoding="utf-8")
    assert _params(rsp)["robot_description"] == installed
    # One publisher of /robot_description: robot_state_publisher's own.
    assert ("redarm_ros", "description") not in nodes
    nodes = _nodes(_run_launch(robot_state_publisher="false"))
    assert ("redarm_ros", "description") in nodes
    assert ("robot_state_publisher", "robot_state_publisher") not in nodes


def test_arm_given_as_a_path_gets_a_generated_description(prefix: Path, tmp_path: Path) -> None:
    from redarm_ros.kinematics import load_arm
    from redarm_ros.sim.urdf import build_urdf

    _add_package(prefix, "robot_state_publisher")
    model = tmp_path / "my_arm.yaml"
    pa10 = (ROOT / "config" / "arms" / "pa10.yaml").read_text(encoding="utf-8")
    model.write_text(pa10.replace("name: pa10", "name: my_arm"), encoding="utf-8")
    nodes = _nodes(_run_launch(arm=str(model), robot_state_publisher="true"))
    urdf = _params(nodes[("robot_state_publisher", "robot_state_publisher")])["robot_description"]
    assert urdf == build_urdf(load_arm(str(model)), prefix="")
    assert '<robot name="my_arm">' in urdf


def test_rviz_on_request_with_the_packages_config(prefix: Path) -> None:
    nodes = _nodes(_run_launch(rviz="true"))
    args = nodes[("rviz2", "rviz2")].kwargs["arguments"]
    assert args[0] == "-d" and Path(args[1]) == prefix / "share" / "redarm_ros" / "config" / "redarm.rviz"
    assert Path(args[1]).is_file()


@pytest.mark.parametrize(("overrides", "homes"), [
    ({}, True),                                            # the simulated arm: homed by itself
    ({"bus": "external"}, False),                          # a real arm waits for ~/init
    ({"bus": "external", "auto_init": "true"}, True),      # ... unless asked
    ({"bus": "loopback", "auto_init": "false"}, False),
])
def test_can_driver_homes_a_real_arm_only_when_asked(prefix: Path, overrides: dict[str, str],
                                                     homes: bool) -> None:
    driver = _nodes(_run_launch(**overrides))[("redarm_ros", "can_driver")]
    assert _params(driver)["auto_init"] is homes


def test_simulator_waits_for_the_bus_server_it_starts() -> None:
    """The launch file starts redarm-canbus and redarm-sim together: the simulator must wait for the
    server (redarm-sim --bus-wait, by default BUS_WAIT_S > 0), not try once and exit."""
    from redarm_ros.sim.hardware import BUS_WAIT_S, build_parser

    assert BUS_WAIT_S > 0
    assert build_parser().parse_args([]).bus_wait == BUS_WAIT_S
