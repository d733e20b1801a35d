"""URDF builder: pybullet's tool link pose equals arm.fk(q) for every arm model; rpy conversion; inertias."""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.model import Joint
from redarm_ros.sim.plant import connect, quiet_stdio
from redarm_ros.sim.urdf import (
    build_urdf,
    joint_efforts,
    link_bodies,
    link_names,
    matrix_to_rpy,
    rpy_to_matrix,
    write_urdf,
)

with quiet_stdio():
    import pybullet as pb

ARMS = ["pa10", "pa10_7c", "powercube6", "powercube7"]
# pybullet hands link states back through float32 (measured: ~3e-7 worst on a 7-joint chain)
TOL = 1e-6


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _tf(R: np.ndarray, p: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


class _TwistedArm:
    """A model double with arbitrary rotations in every joint origin (stresses the rpy conversion)."""

    def __init__(self, rng: np.random.Generator, n: int = 6) -> None:
        self.name = "twisted"
        self.n = n
        self.chain = []
        for i in range(n):
            R = _rot(rng.normal(size=3), rng.uniform(-math.pi, math.pi))
            if i == 2:  # an exact gimbal-lock origin (pitch = +90 deg)
                R = rpy_to_matrix(0.3, math.pi / 2, -0.2)
            axis = rng.normal(size=3)
            self.chain.append(
                Joint(
                    f"tw_{i}",
                    _tf(R, tuple(rng.uniform(-0.2, 0.3, 3))),
                    axis / np.linalg.norm(axis),
                    -3.0,
                    3.0,
                    1.0,
                    2.0,
                )
            )
        self.tool = _tf(_rot([1, 1, 0], 0.4), (0.0, 0.02, 0.1))
        self.lower = np.full(n, -3.0)
        self.upper = np.full(n, 3.0)

    def fk(self, q: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        for j, qi in zip(self.chain, q, strict=True):
            T = T @ j.origin @ _tf(_rot(j.axis, qi), (0, 0, 0))
        return T @ self.tool


@pytest.fixture
def client():
    cid = connect()
    yield cid
    pb.disconnect(physicsClientId=cid)


def _load(arm, cid: int, tmp_path) -> int:
    path = write_urdf(arm, str(tmp_path / f"{arm.name}.urdf"))
    return pb.loadURDF(path, useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=cid)


def _max_tool_error(arm, cid: int, body: int, rng: np.random.Generator, count: int) -> float:
    worst = 0.0
    for _ in range(count):
        q = rng.uniform(arm.lower, arm.upper)
        for i in range(arm.n):
            pb.resetJointState(body, i, float(q[i]), physicsClientId=cid)
        s = pb.getLinkState(body, arm.n, computeForwardKinematics=True, physicsClientId=cid)
        R = np.asarray(pb.getMatrixFromQuaternion(s[5])).reshape(3, 3)
        T = arm.fk(q)
        worst = max(
            worst, float(np.abs(np.asarray(s[4]) - T[:3, 3]).max()), float(np.abs(R - T[:3, :3]).max())
        )
    return worst


@pytest.mark.parametrize("name", ARMS)
def test_tool_link_matches_fk(name, client, tmp_path):
    arm = load_arm(name)
    body = _load(arm, client, tmp_path)
    assert pb.getNumJoints(body, physicsClientId=client) == arm.n + 1
    for i, jn in enumerate(arm.joint_names):
        info = pb.getJointInfo(body, i, physicsClientId=client)
        assert info[1].decode() == jn
        assert info[2] == pb.JOINT_REVOLUTE
        assert info[8] == pytest.approx(arm.lower[i]) and info[9] == pytest.approx(arm.upper[i])
        assert info[11] == pytest.approx(arm.max_vel[i])
    assert pb.getJointInfo(body, arm.n, physicsClientId=client)[12].decode() == link_names(arm)[-1]
    assert _max_tool_error(arm, client, body, np.random.default_rng(7), 200) < TOL


def test_twisted_origins_match_fk(client, tmp_path):
    rng = np.random.default_rng(3)
    arm = _TwistedArm(rng)
    body = _load(arm, client, tmp_path)
    assert _max_tool_error(arm, client, body, rng, 100) < TOL


def test_rpy_round_trip_including_gimbal_lock():
    rng = np.random.default_rng(11)
    cases = [rpy_to_matrix(*rng.uniform(-math.pi, math.pi, 3)) for _ in range(200)]
    cases += [rpy_to_matrix(0.4, s * math.pi / 2, 1.1) for s in (1, -1)] + [np.eye(3), np.diag([1.0, -1, -1])]
    for R in cases:
        assert np.abs(rpy_to_matrix(*matrix_to_rpy(R)) - R).max() < 1e-12


@pytest.mark.parametrize("name", ARMS)
def test_urdf_is_well_formed_with_positive_inertias(name):
    arm = load_arm(name)
    root = ET.fromstring(build_urdf(arm))
    assert [link.get("name") for link in root.findall("link")] == link_names(arm)
    for link in root.findall("link"):
        assert float(link.find("inertial/mass").get("value")) > 0
        assert link.find("visual") is not None and link.find("collision") is not None
    for body in link_bodies(arm):
        eig = np.linalg.eigvalsh(body.inertia)
        assert eig.min() > 0
        # triangle inequality of principal moments: a physical rigid body
        assert eig[0] + eig[1] >= eig[2] * (1 - 1e-12)
    efforts = joint_efforts(arm)
    assert np.all(efforts >= 20.0)
    assert efforts[1] >= efforts[-1]  # the shoulder carries more than the wrist


def test_bad_model_is_refused():
    arm = _TwistedArm(np.random.default_rng(0), n=3)
    arm.chain[1] = dataclasses.replace(arm.chain[1], axis=np.array([0.0, 0.0, 2.0]))
    with pytest.raises(InvalidInputError, match="unit"):
        build_urdf(arm)
    arm = _TwistedArm(np.random.default_rng(0), n=3)
    arm.tool = np.full((4, 4), np.nan)
    with pytest.raises(InvalidInputError, match="tool"):
        build_urdf(arm)


def test_urdf_arm_keeps_its_meshes_where_the_files_exist(tmp_path):
    from redarm_ros.sim.plant import PybulletPlant
    from redarm_ros.sim.urdf_arms import iiwa14_urdf

    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "upper_arm.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    text = iiwa14_urdf().replace(  # link_2 (after joint 2) with a mesh, link_3 with a missing one
        '<link name="link_2"/>',
        '<link name="link_2"><visual><origin xyz="0 0 0.1"/><geometry><mesh filename="meshes/upper_arm.obj"/>'
        '</geometry><material name="m"><color rgba="1 0.5 0 1"/></material></visual></link>',
    ).replace(
        '<link name="link_3"/>',
        '<link name="link_3"><visual><geometry><mesh filename="package://no_such_pkg/x.stl"/></geometry>'
        "</visual></link>",
    )
    (tmp_path / "arm.urdf").write_text(text)
    arm = load_arm(tmp_path / "arm.urdf", base_link="base_link", tip_link="tool0")
    plant = PybulletPlant.create(arm)
    try:
        rows = plant.pb.getVisualShapeData(plant.body, physicsClientId=plant.cid)
    finally:
        plant.close()
    by_link: dict[int, list] = {}
    for row in rows:
        by_link.setdefault(row[1], []).append(row)
    # pybullet link 1 is the child of joint 2: the URDF's mesh replaces the generated shapes
    assert [(r[2], r[4].decode()) for r in by_link[1]] == [
        (pb.GEOM_MESH, str((tmp_path / "meshes" / "upper_arm.obj").resolve()))
    ]
    assert by_link[1][0][7][:3] == pytest.approx((1.0, 0.5, 0.0))
    # the missing mesh (and the links without visuals) keep the generated sphere and cylinder
    for link in (0, 2, 3):
        assert {r[2] for r in by_link[link]} == {pb.GEOM_SPHERE, pb.GEOM_CYLINDER}, link
