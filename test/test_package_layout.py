"""The package card agrees with the code: package.xml, setup.py entry points, setup.cfg, launch file.

* package.xml is a format-3 ament_python manifest whose dependencies cover every ROS package and
  third-party module that ``redarm_ros/`` (exec) and ``test/`` (test) import, and every ROS package it
  names is importable here.
* setup.py's console scripts point at importable callables (skipped, with the module named, while
  a module is not written yet), and the venv's editable install is current with them.
* launch/redarm_sim.launch.py (when it exists) names only executables this package installs, and
  its imports are covered by package.xml like the package's own.
"""

from __future__ import annotations

import ast
import configparser
import importlib
import importlib.metadata
import importlib.util
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
from support.setup_py import console_scripts

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "redarm_ros"

# ros2 run names and their modules (README; test_install_colcon starts them from an install).
ROS_NODES = {
    "ik_service": "redarm_ros.nodes.ik_service:main",
    "controller": "redarm_ros.nodes.controller:main",
    "can_driver": "redarm_ros.nodes.can_driver:main",
    "sim": "redarm_ros.sim.hardware:main",
    "view": "redarm_ros.nodes.view:main",
}

# Third-party import name -> rosdep keys that satisfy it (any one of them).
ROSDEP_KEYS: dict[str, tuple[str, ...]] = {
    "numpy": ("python3-numpy",),
    "scipy": ("python3-scipy",),
    "yaml": ("python3-yaml",),
    "can": ("python3-can",),
    "pybullet": ("python3-pybullet", "python3-pybullet-pip"),
    "pybullet_data": ("python3-pybullet", "python3-pybullet-pip"),
    "matplotlib": ("python3-matplotlib",),
    "pytest": ("python3-pytest",),
    "hypothesis": ("python3-hypothesis",),
    "xdist": ("python3-pytest-xdist",),
    "ikpy": ("python3-ikpy-pip",),
    "imageio": ("python3-imageio",),
    "PIL": ("python3-pil",),
}
# ROS packages a real install needs that no registry here has (ros2 launch); not importable here.
REAL_INSTALL_ONLY = {"launch", "launch_ros"}
# Imports with no rosdep key at all; they are pip-only and documented in docs/setup.md.
PIP_ONLY = {
    "can_remote": "python-can-remote: the loopback test bus only; no Debian package or rosdep key",
    "viser": "viser: the browser view (redarm-view); pip only",
    "mcap": "mcap: MCAP recordings (redarm-record); pip only",
    "mcap_ros2": "mcap-ros2-support: ROS 2 schemas for MCAP recordings; pip only",
    "websocket": "websocket-client: the browser test's DevTools client; pip only",
    "distributed": "dask distributed: redarm-placement's optional cluster engine (extra 'cluster'); pip only",
}


def _manifest() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


def _deps(root: ET.Element, *tags: str) -> set[str]:
    return {(e.text or "").strip() for tag in tags for e in root.findall(tag)}


def _ament_packages() -> set[str]:
    """ROS packages known to the underlay (the venv's ament index) plus this repo's interfaces."""
    index = Path(sys.prefix) / "share" / "ament_index" / "resource_index" / "packages"
    known = {p.name for p in index.iterdir()} if index.is_dir() else set()
    return known | {"redarm_interfaces"}


def _imports(folder: Path) -> dict[str, set[str]]:
    """Top-level modules imported anywhere under ``folder`` (also inside functions) -> files."""
    found: dict[str, set[str]] = {}
    for path in sorted(folder.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(str(path.relative_to(REPO)))
    return found


def _third_party(imports: dict[str, set[str]]) -> dict[str, set[str]]:
    local = {PACKAGE, "conftest", "__future__", "support"} | {p.stem for p in (REPO / "test").glob("*.py")}
    return {m: f for m, f in imports.items() if m not in sys.stdlib_module_names and m not in local}


def test_manifest_is_format3_ament_python() -> None:
    root = _manifest()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == PACKAGE
    assert root.findtext("export/build_type") == "ament_python"
    assert root.findtext("license") and root.find("maintainer") is not None
    setup_src = (REPO / "setup.py").read_text(encoding="utf-8")
    assert f'version="{root.findtext("version")}"' in setup_src, "package.xml and setup.py versions differ"


def _check_covered(folder: str, allowed: set[str]) -> list[str]:
    ament = _ament_packages() | REAL_INSTALL_ONLY
    problems = []
    for module, files in sorted(_third_party(_imports(REPO / folder)).items()):
        where = ", ".join(sorted(files)[:3])
        if module in ament:
            if module not in allowed:
                problems.append(f"ROS package {module} (imported in {where}) is not in package.xml")
        elif module in ROSDEP_KEYS:
            if not set(ROSDEP_KEYS[module]) & allowed:
                problems.append(f"{module} (imported in {where}) needs one of {ROSDEP_KEYS[module]}")
        elif module not in PIP_ONLY:
            problems.append(f"{module} (imported in {where}) is unknown: add it to package.xml and to "
                            "ROSDEP_KEYS/PIP_ONLY in this test")
    return problems


@pytest.mark.slow
def test_manifest_covers_runtime_imports() -> None:
    root = _manifest()
    allowed = _deps(root, "depend", "exec_depend")
    problems = _check_covered(PACKAGE, allowed) + _check_covered("launch", allowed)
    assert not problems, "\n".join(problems)


@pytest.mark.slow
def test_manifest_covers_test_imports() -> None:
    root = _manifest()
    allowed = _deps(root, "depend", "exec_depend", "test_depend")
    problems = _check_covered("test", allowed)
    assert not problems, "\n".join(problems)


def test_manifest_ros_dependencies_exist() -> None:
    """Every ROS package named in package.xml is importable here (a typo would break rosdep too)."""
    ament = _ament_packages()
    root = _manifest()
    declared = _deps(root, "depend", "exec_depend", "test_depend")
    ros_deps = {d for d in declared if not d.startswith("python3-")}
    missing = [d for d in sorted(ros_deps - REAL_INSTALL_ONLY)
               if d not in ament or importlib.util.find_spec(d) is None]
    assert not missing, f"package.xml names ROS packages that are not installed: {missing}"


def test_ros_nodes_declared() -> None:
    scripts = console_scripts()
    assert {name: scripts.get(name) for name in ROS_NODES} == ROS_NODES


@pytest.mark.parametrize("name", sorted(console_scripts()))
def test_entry_point_importable(name: str) -> None:
    module_name, _, func = console_scripts()[name].partition(":")
    if importlib.util.find_spec(module_name) is None:
        pytest.skip(f"{module_name} (entry point {name}) not written yet")
    module = importlib.import_module(module_name)
    assert callable(getattr(module, func, None)), f"{module_name} has no callable {func}()"


def test_venv_install_is_current() -> None:
    """`pip install -e .` (scripts/setup_env.sh) put every console script in the venv's bin/."""
    try:
        dist = importlib.metadata.distribution(PACKAGE)
    except importlib.metadata.PackageNotFoundError:
        pytest.fail("redarm_ros is not installed in this interpreter; run `make setup`", pytrace=False)
    installed = {ep.name: ep.value for ep in dist.entry_points if ep.group == "console_scripts"}
    assert installed == console_scripts(), "stale editable install: run `make setup`"
    bindir = Path(sys.executable).parent
    missing = [n for n in installed if not (bindir / n).is_file()]
    assert not missing, f"missing from {bindir}: {missing}"


def test_setup_cfg_puts_scripts_in_lib() -> None:
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    assert cfg.get("develop", "script_dir") == f"$base/lib/{PACKAGE}"
    assert cfg.get("install", "install_scripts") == f"$base/lib/{PACKAGE}"
    assert (REPO / "resource" / PACKAGE).is_file(), "ament index marker source resource/redarm_ros missing"


# --- launch file -------------------------------------------------------------------------------------
# launch and launch_ros are not installable here, so the launch file is read, not run: every call with
# an ``executable=`` keyword (Node, ExecutableInPackage, ...) and every ``redarm-*`` string in a command.
def _module_constants(tree: ast.Module) -> dict[str, Any]:
    consts: dict[str, Any] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    consts[target.id] = node.value.value
    return consts


def _value(node: ast.expr | None, consts: dict[str, Any]) -> Any:
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name):
        return consts.get(node.id, f"<{node.id}>")
    return "<expression>"


def test_launch_file_names_installed_executables() -> None:
    path = REPO / "launch" / "redarm_sim.launch.py"
    if not path.is_file():
        pytest.skip("launch/redarm_sim.launch.py not written yet")
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    consts = _module_constants(tree)
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in functions, "no generate_launch_description()"
    scripts = console_scripts()
    named: list[tuple[Any, Any]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            kw = {k.arg: k.value for k in node.keywords if k.arg}
            if "executable" in kw:
                named.append((_value(kw.get("package"), consts), _value(kw["executable"], consts)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and re.fullmatch(r"redarm-[a-z-]+", node.value):
            assert node.value in scripts, f"the launch file runs {node.value!r}; setup.py does not install it"
    assert named, "the launch file names no executable"
    # Optional ROS tools it starts when they are installed (not this package's executables).
    named = [pe for pe in named if pe not in {("robot_state_publisher", "robot_state_publisher"),
                                              ("rviz2", "rviz2")}]
    for package, executable in named:
        assert package == PACKAGE, f"executable {executable!r} of package {package!r}: not this package"
        assert executable in scripts, f"executable {executable!r} is not installed by setup.py"
    # The three ROS nodes that make up the simulated stack, at least.
    assert {"can_driver", "ik_service", "controller"} <= {e for _, e in named}


def test_runtime_package_ships_no_test_machinery() -> None:
    """The UML runner, its scenario and the CAN bus fakes live under test/support/, not in the package."""
    # setup.py installs every package under redarm_ros/ (find_packages): none may be test machinery
    packages = [str(d.parent.relative_to(REPO)) for d in (REPO / "redarm_ros").rglob("__init__.py")]
    assert "redarm_ros/can" in packages and not [p for p in packages if p.endswith("uml")], packages
    assert "uml" not in (REPO / "setup.py").read_text(encoding="utf-8")
    assert not (REPO / "redarm_ros" / "can" / "testing.py").exists()
    shipped = "\n".join(p.read_text(encoding="utf-8") for p in (REPO / "redarm_ros").rglob("*.py"))
    assert "support." not in shipped and "uml_scenario" not in shipped
    assert (REPO / "test" / "support" / "uml" / "runner.py").is_file()


def test_every_node_takes_the_same_constructor_keywords() -> None:
    """One construction signature: context, parameter_overrides, node_name, namespace (keyword-only)."""
    import importlib
    import inspect

    from rclpy.node import Node

    common = ["context", "parameter_overrides", "node_name", "namespace"]
    found = []
    for path in sorted((REPO / "redarm_ros" / "nodes").glob("[!_]*.py")):
        module = importlib.import_module(f"redarm_ros.nodes.{path.stem}")
        for cls in vars(module).values():
            if inspect.isclass(cls) and issubclass(cls, Node) and cls.__module__ == module.__name__:
                params = inspect.signature(cls.__init__).parameters
                kw_only = [n for n, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY]
                assert set(common) <= set(kw_only), f"{cls.__name__}: {list(params)}"
                found.append(cls.__name__)
    assert len(found) >= 6, found


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A ROS parameters mapping with its nested groups as dotted names (``can.channel``)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


@pytest.mark.parametrize("node", ["controller", "can_driver", "ik_service", "description"])
def test_config_file_lists_every_parameter_at_its_default(node: str) -> None:
    """config/<node>.yaml says "every value here is the node's default": each declared parameter is there
    with that default (a parameter without a default, e.g. can_driver's module_ids, may stay commented out),
    and nothing else is."""
    import yaml
    from rclpy.parameter import Parameter

    module = importlib.import_module(f"redarm_ros.nodes.{node}")
    doc = yaml.safe_load((REPO / "config" / f"{node}.yaml").read_text())
    (name, body), = doc.items()
    assert name == "/**", "the file must apply to the node in any namespace (__ns:=/left), not only /" + node
    listed = _flatten(body["ros__parameters"])
    specs = {s.name: s.default for s in module.PARAMS}
    assert set(listed) <= set(specs), sorted(set(listed) - set(specs))
    for pname, default in specs.items():
        if isinstance(default, Parameter.Type):  # declared without a default
            continue
        assert pname in listed, f"config/{node}.yaml lacks {pname} (default {default!r})"
        value = listed[pname]
        assert value == default and type(value) is type(default), (pname, value, default)


# --- layering of the cores ---------------------------------------------------------------------------
# Which parts of the package each low core may import (itself always). geometry/ sits below both the
# IK front end and the controller: an arm enters it as key points or as an object that gives them.
CORE_MAY_IMPORT: dict[str, set[str]] = {
    "yaml_safe": set(),
    "param_table": {"errors", "yaml_safe"},
    "motion": {"errors"},
    "geometry": {"errors", "param_table", "yaml_safe"},
    "kinematics": {"errors", "param_table", "geometry", "motion", "parallel", "yaml_safe"},
}


def _package_imports(path: Path) -> set[str]:
    """First parts below ``redarm_ros.`` of every import in ``path`` (also inside functions; not the
    annotation-only ``if TYPE_CHECKING:`` blocks)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] if node.module != PACKAGE else [f"{PACKAGE}.{a.name}" for a in node.names]
        found |= {n.split(".")[1] for n in names if n.startswith(f"{PACKAGE}.")}
    return found


@pytest.mark.parametrize("core", sorted(CORE_MAY_IMPORT))
def test_low_cores_import_only_what_lies_below_them(core: str) -> None:
    """kinematics/ and geometry/ import nothing of control/; geometry/ nothing of kinematics/ either."""
    folder = REPO / PACKAGE / core
    paths = sorted(folder.rglob("*.py")) if folder.is_dir() else [folder.with_suffix(".py")]
    assert paths and all(p.is_file() for p in paths), core
    wrong = {str(p.relative_to(REPO)): sorted(_package_imports(p) - CORE_MAY_IMPORT[core] - {core})
             for p in paths}
    wrong = {p: mods for p, mods in wrong.items() if mods}
    assert not wrong, f"{core} imports from above it: {wrong}"


@pytest.mark.parametrize("module, home", [("obstacles", "geometry.obstacles"),
                                          ("self_collision", "geometry.self_collision"),
                                          ("param_table", "param_table")])
def test_documented_old_paths_still_import(module: str, home: str) -> None:
    """redarm_ros.control.obstacles, .self_collision and .param_table, once documented, are the modules
    of their new homes."""
    old = importlib.import_module(f"{PACKAGE}.control.{module}")
    assert old is importlib.import_module(f"{PACKAGE}.{home}")
    # the package itself uses the new home only
    users = [str(p.relative_to(REPO)) for p in (REPO / PACKAGE).rglob("*.py")
             if f"{PACKAGE}.control.{module}" in p.read_text(encoding="utf-8")]
    assert users == [f"{PACKAGE}/control/{module}.py"], users
