"""Robot description files: generated at build time, installed as share/redarm_ros/urdf/<arm>.urdf,
equal to the model's FK, and the frames RViz (config/redarm.rviz) and the controller expect.

* Every bundled arm's URDF (as the build step and the description node make it) has the documented
  frames (base_link, link_1..link_n, tool; the model's joint names) and its root -> tool transform,
  read with a URDF reader of the tests' own (test/urdf_chain.py), equals ``arm.fk`` everywhere.
* ``pip install .`` of a copy of the source tree into a temporary prefix installs exactly one URDF per
  config/arms/*.yaml; the build ran with pybullet, rclpy and python-can made unimportable, so the
  generator needs none of them. The installed files equal what the description node publishes, and
  both our reader and pybullet put their tool link where ``arm.fk`` puts the tool.
  (colcon's install is checked the same way in test_install_colcon.py.)
* config/redarm.rviz shows the arm from /robot_description (transient local), the controller's
  markers and the goal, in the frame the URDF and the controller share.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import urdf_chain
import yaml

from redarm_ros.kinematics import load_arm
from redarm_ros.sim.urdf import build_urdf

REPO = Path(__file__).resolve().parents[1]
ARMS = sorted(p.stem for p in (REPO / "config" / "arms").glob("*.yaml"))
# pybullet hands link states back through float32.
PB_TOL = 1e-6


def _description(arm: str) -> str:
    """What the description node publishes (and the build installs) for a bundled arm."""
    return build_urdf(load_arm(arm), prefix="")


@pytest.mark.parametrize("arm", ARMS)
def test_description_matches_fk(arm: str) -> None:
    urdf_chain.check_matches_fk(_description(arm), arm)


def test_reader_sees_a_wrong_origin() -> None:
    """The check can fail: one joint origin moved by 1 mm is caught."""
    arm = load_arm("pa10")
    root = ET.fromstring(_description("pa10"))
    origin = root.find(f"joint[@name='{arm.joint_names[3]}']/origin")
    xyz = [float(v) for v in origin.get("xyz").split()]
    xyz[2] += 1e-3
    origin.set("xyz", " ".join(repr(v) for v in xyz))
    with pytest.raises(AssertionError, match="differs from arm.fk"):
        urdf_chain.check_matches_fk(ET.tostring(root, encoding="unicode"), "pa10", count=5)


@pytest.mark.parametrize("arm", ARMS)
def test_frames_are_the_documented_ones(arm: str) -> None:
    model = load_arm(arm)
    root = ET.fromstring(_description(arm))
    links = [e.get("name") for e in root.findall("link")]
    assert links == ["base_link", *(f"link_{i}" for i in range(1, model.n + 1)), "tool"]
    assert urdf_chain.root_link(_description(arm)) == "base_link"
    joints = {j.get("name"): j.get("type") for j in root.findall("joint")}
    assert joints == {**dict.fromkeys(model.joint_names, "revolute"), "tool_joint": "fixed"}
    assert root.get("name") == model.name


@pytest.mark.parametrize("arm", ARMS)
def test_link_frames_are_the_models_joint_frames(arm: str) -> None:
    """docs/nodes.md: link_i is joint i's frame, ``arm.fk_frames(q)[i-1]``; tool is ``arm.fk(q)``."""
    model = load_arm(arm)
    urdf = _description(arm)
    rng = np.random.default_rng(5)
    qs = [rng.uniform(model.lower, model.upper) for _ in range(20)]
    for i in range(1, model.n + 1):
        joints = urdf_chain.chain(urdf, f"link_{i}")
        for q in qs:
            frames = model.fk_frames(q)
            assert np.abs(urdf_chain.fk(joints, q[:i]) - frames[i - 1]).max() < urdf_chain.FK_TOL


# -- pip install . ---------------------------------------------------------------------------------
_BLOCKED = ("pybullet", "rclpy", "can")


def _copy_source(dst: Path) -> None:
    """The repository's files (tracked and untracked, not ignored) copied to ``dst``."""
    try:
        listing = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
            capture_output=True, check=True, timeout=60,
        ).stdout.decode().split("\0")
    except (OSError, subprocess.CalledProcessError):
        listing = []
    if listing and listing != [""]:
        for rel in filter(None, listing):
            src = REPO / rel
            if src.is_file():
                (dst / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dst / rel)
        return
    shutil.copytree(REPO, dst, dirs_exist_ok=True, ignore=shutil.ignore_patterns(
        ".venv", ".build", "build", "install", "log", ".git", "__pycache__", "*.egg-info", "demo_output"))


@pytest.fixture(scope="module")
def pip_prefix(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``pip install .`` (no build isolation: the venv's setuptools, numpy, PyYAML) into a temp prefix."""
    root = tmp_path_factory.mktemp("pip_install")
    src, prefix, block = root / "src", root / "prefix", root / "block"
    src.mkdir()
    _copy_source(src)
    block.mkdir()
    for mod in _BLOCKED:  # importing any of these during the build fails it
        (block / f"{mod}.py").write_text(f"raise ImportError('{mod} imported while building')\n")
    env = dict(os.environ, PYTHONPATH=str(block), PIP_NO_INPUT="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    # --ignore-installed: never touch the venv's own (editable) redarm_ros.
    cmd = [sys.executable, "-m", "pip", "install", "--no-build-isolation", "--no-deps", "--no-index",
           "--ignore-installed", "--no-compile", "--prefix", str(prefix), str(src)]
    proc = subprocess.run(cmd, env=env, cwd=root, stdin=subprocess.DEVNULL, capture_output=True,
                          text=True, timeout=300)
    if proc.returncode != 0:
        pytest.fail(f"pip install failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}",
                    pytrace=False)
    yield prefix
    shutil.rmtree(root, ignore_errors=True)


pip_install = pytest.mark.slow


@pip_install
def test_pip_install_installs_one_urdf_per_arm(pip_prefix: Path) -> None:
    urdf_dir = pip_prefix / "share" / "redarm_ros" / "urdf"
    assert sorted(p.name for p in urdf_dir.glob("*")) == [f"{a}.urdf" for a in ARMS]
    # The rest of the share directory is still there (data files were extended, not replaced).
    share = pip_prefix / "share" / "redarm_ros"
    for name in ("package.xml", "config/redarm.rviz", "config/description.yaml",
                 "launch/redarm_sim.launch.py"):
        assert (share / name).is_file(), name


@pip_install
@pytest.mark.parametrize("arm", ARMS)
def test_pip_installed_urdf_is_the_published_one_and_matches_fk(pip_prefix: Path, arm: str) -> None:
    text = (pip_prefix / "share" / "redarm_ros" / "urdf" / f"{arm}.urdf").read_text(encoding="utf-8")
    assert text == _description(arm)
    urdf_chain.check_matches_fk(text, arm)


@pip_install
@pytest.mark.parametrize("arm", ARMS)
def test_pip_installed_urdf_in_pybullet_matches_fk(pip_prefix: Path, arm: str) -> None:
    from redarm_ros.sim.plant import connect, quiet_stdio

    with quiet_stdio():
        import pybullet as pb
    model = load_arm(arm)
    path = pip_prefix / "share" / "redarm_ros" / "urdf" / f"{arm}.urdf"
    cid = connect()
    try:
        body = pb.loadURDF(str(path), useFixedBase=True, physicsClientId=cid)
        tool = next(i for i in range(pb.getNumJoints(body, physicsClientId=cid))
                    if pb.getJointInfo(body, i, physicsClientId=cid)[12].decode() == "tool")
        rng = np.random.default_rng(11)
        for _ in range(50):
            q = rng.uniform(model.lower, model.upper)
            for i in range(model.n):
                pb.resetJointState(body, i, float(q[i]), physicsClientId=cid)
            s = pb.getLinkState(body, tool, computeForwardKinematics=True, physicsClientId=cid)
            R = np.asarray(pb.getMatrixFromQuaternion(s[5])).reshape(3, 3)
            T = model.fk(q)
            assert np.abs(np.asarray(s[4]) - T[:3, 3]).max() < PB_TOL
            assert np.abs(R - T[:3, :3]).max() < PB_TOL
    finally:
        pb.disconnect(physicsClientId=cid)


def test_build_requirements_name_the_generator_dependencies() -> None:
    """``pip install .`` with build isolation gets what setup.py's generator imports."""
    import tomllib

    req = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["build-system"]["requires"]
    names = {r.split(">")[0].split("=")[0].split("<")[0].strip().lower() for r in req}
    assert {"setuptools", "numpy", "pyyaml"} <= names, names
    manifest = ET.parse(REPO / "package.xml").getroot()
    build_deps = {(e.text or "").strip() for e in manifest.findall("build_depend")}
    assert {"python3-numpy", "python3-yaml"} <= build_deps, "rosdep must install them before colcon build"


# -- RViz --------------------------------------------------------------------------------------------
def _rviz() -> dict:
    return yaml.safe_load((REPO / "config" / "redarm.rviz").read_text(encoding="utf-8"))


def _display(cfg: dict, cls: str) -> dict:
    displays = cfg["Visualization Manager"]["Displays"]
    found = [d for d in displays if d["Class"] == f"rviz_default_plugins/{cls}"]
    assert len(found) == 1, f"config/redarm.rviz: {len(found)} {cls} displays"
    assert found[0]["Enabled"] is True
    return found[0]


def test_rviz_shows_arm_markers_and_goal_in_the_shared_frame() -> None:
    cfg = _rviz()
    controller = yaml.safe_load((REPO / "config" / "controller.yaml").read_text(encoding="utf-8"))
    base_frame = controller["/**"]["ros__parameters"].get("base_frame", "base_link")
    fixed = cfg["Visualization Manager"]["Global Options"]["Fixed Frame"]
    assert fixed == base_frame == urdf_chain.root_link(_description("pa10"))
    robot = _display(cfg, "RobotModel")
    assert robot["Description Source"] == "Topic"
    assert robot["Description Topic"]["Value"] == "/robot_description"
    # A volatile reader never gets a transient-local writer's earlier sample: RViz started after the
    # description node would show no arm.
    assert robot["Description Topic"]["Durability Policy"] == "Transient Local"
    markers = _display(cfg, "MarkerArray")
    assert markers["Topic"]["Value"] == "/controller/markers"
    goal = _display(cfg, "Pose")
    assert goal["Topic"]["Value"] == "/goal_pose"
    _display(cfg, "TF")


def test_rviz_topics_are_the_nodes_topics() -> None:
    """The names RViz subscribes to are the ones the nodes publish (node name controller, ~/markers)."""
    controller_src = (REPO / "redarm_ros" / "nodes" / "controller.py").read_text(encoding="utf-8")
    assert '"~/markers"' in controller_src and 'NODE_NAME = "controller"' in controller_src
    assert '"goal_pose"' in controller_src or "'goal_pose'" in controller_src
    from redarm_ros.nodes.description import TOPIC

    assert TOPIC == "robot_description"
