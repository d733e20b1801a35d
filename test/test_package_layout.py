"""The package card agrees with the code: package.xml, setup.py entry points, setup.cfg, launch file.

* package.xml is a format-3 ament_python manifest whose dependencies cover every ROS package and
  third-party module that ``redarm_ros/`` (exec) and ``test/`` (test) import, and every ROS package it
  names is importable here.
* setup.py's console scripts point at importable callables (skipped, with the module named, while
  a module is not written yet), and the venv's editable install is current with them.
* launch/redarm_sim.launch.py (when it exists) starts only executables this package installs.
"""

from __future__ import annotations

import ast
import configparser
import contextlib
import importlib
import importlib.abc
import importlib.machinery
import importlib.metadata
import importlib.util
import runpy
import sys
import types
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "redarm_ros"

# ros2 run names and their modules (DESIGN.md; test_install_colcon starts them from an install).
ROS_NODES = {
    "ik_service": "redarm_ros.nodes.ik_service:main",
    "controller": "redarm_ros.nodes.controller:main",
    "can_driver": "redarm_ros.nodes.can_driver:main",
    "sim": "redarm_ros.sim.hardware:main",
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
    "ikpy": ("python3-ikpy-pip",),
}
# Imports with no rosdep key at all; they are pip-only and documented in docs/setup.md.
PIP_ONLY = {
    "can_remote": "python-can-remote: the loopback test bus only; no Debian package or rosdep key",
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
    local = {PACKAGE, "conftest", "__future__"} | {p.stem for p in (REPO / "test").glob("*.py")}
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
    ament = _ament_packages()
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


def test_manifest_covers_runtime_imports() -> None:
    root = _manifest()
    allowed = _deps(root, "depend", "exec_depend")
    problems = _check_covered(PACKAGE, allowed)
    assert not problems, "\n".join(problems)


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
    missing = [d for d in sorted(ros_deps) if d not in ament or importlib.util.find_spec(d) is None]
    assert not missing, f"package.xml names ROS packages that are not installed: {missing}"


def _console_scripts() -> dict[str, str]:
    """setup.py's console_scripts, read from its source (name -> "module:function")."""
    tree = ast.parse((REPO / "setup.py").read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    entries = ast.literal_eval(value)
                    return {n.strip(): t.strip() for n, t in (e.split("=", 1) for e in entries)}
    raise AssertionError("setup.py has no console_scripts entry points")


def test_ros_nodes_declared() -> None:
    scripts = _console_scripts()
    assert {name: scripts.get(name) for name in ROS_NODES} == ROS_NODES


@pytest.mark.parametrize("name", sorted(_console_scripts()))
def test_entry_point_importable(name: str) -> None:
    module_name, _, func = _console_scripts()[name].partition(":")
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
    assert installed == _console_scripts(), "stale editable install: run `make setup`"
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
# launch and launch_ros are not installable here, so the launch file runs against stand-ins that
# record what it would start.
class _Recorder:
    calls: list[tuple[str, dict[str, Any]]] = []

    def __init__(self, kind: str) -> None:
        self.kind = kind

    def __call__(self, *args: Any, **kwargs: Any) -> _Recorder:
        _Recorder.calls.append((self.kind, {"args": args, **kwargs}))
        return _Recorder(f"{self.kind}()")

    def __getattr__(self, name: str) -> _Recorder:
        return _Recorder(f"{self.kind}.{name}")

    def __iter__(self) -> Iterator[Any]:
        return iter(())

    def __add__(self, other: Any) -> _Recorder:
        return self

    __radd__ = __add__


class _StubModule(types.ModuleType):
    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        return _Recorder(name)


class _StubFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    roots = ("launch", "launch_ros", "launch_xml", "launch_yaml")

    def find_spec(
        self, fullname: str, path: Any, target: Any = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname.split(".")[0] in self.roots:
            return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
        return None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        module = _StubModule(spec.name)
        module.__path__ = []  # a package, so submodule imports work
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        pass


@contextlib.contextmanager
def _stub_launch() -> Iterator[None]:
    finder = _StubFinder()
    saved = {k: v for k, v in sys.modules.items() if k.split(".")[0] in _StubFinder.roots}
    for k in saved:
        del sys.modules[k]
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
        for k in [k for k in sys.modules if k.split(".")[0] in _StubFinder.roots]:
            del sys.modules[k]
        sys.modules.update(saved)


def test_launch_file_names_installed_executables() -> None:
    path = REPO / "launch" / "redarm_sim.launch.py"
    if not path.is_file():
        pytest.skip("launch/redarm_sim.launch.py not written yet")
    _Recorder.calls = []
    with _stub_launch():
        namespace = runpy.run_path(str(path))
        assert callable(namespace.get("generate_launch_description")), "no generate_launch_description()"
        namespace["generate_launch_description"]()
    scripts = _console_scripts()
    nodes = [kw for kind, kw in _Recorder.calls if kind == "Node"]
    assert nodes, "the launch file starts no launch_ros Node"
    for kw in nodes:
        package, executable = kw.get("package"), kw.get("executable")
        if package == PACKAGE:
            assert executable in scripts, f"Node(executable={executable!r}) is not installed by setup.py"
        else:
            assert isinstance(package, str) and importlib.util.find_spec(package) is not None, \
                f"Node(package={package!r}) is not available here"
    for kind, kw in _Recorder.calls:
        if kind == "ExecuteProcess":
            cmd = kw.get("cmd") or (kw["args"][0] if kw["args"] else [])
            first = cmd[0] if cmd else None
            if isinstance(first, str) and first.startswith("redarm-"):
                assert first in scripts, f"ExecuteProcess runs {first!r}, which setup.py does not install"
