"""Arm models: YAML loading, overrides, FK against the papers' equations, Jacobian, input validation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.kinematics import Arm, has_analytic_ik, has_swivel, load_arm
from redarm_ros.kinematics.protocols import CorridorArm
from redarm_ros.kinematics.quaternion import qmul, quat_to_matrix, qy, qz, rotation_error

ARMS = ["pa10", "pa10_7c", "powercube7", "powercube6"]


def _rand_q(arm: Arm, n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(arm.lower, arm.upper, size=(n, arm.n))


def test_load_all_arms_and_contract_attributes() -> None:
    for name in ARMS:
        arm = load_arm(name)
        assert arm.name == name
        assert arm.n == len(arm.joint_names) == len(arm.chain) == arm.lower.shape[0]
        assert np.all(arm.lower <= arm.upper)
        assert np.all(arm.max_vel > 0) and np.all(arm.max_acc > 0)
        for j in arm.chain:
            assert j.origin.shape == (4, 4) and np.isclose(np.linalg.norm(j.axis), 1.0)
        assert arm.tool.shape == (4, 4)
        q = _rand_q(arm, 1, 0)[0]
        assert arm.fk(q).shape == (4, 4)
        assert arm.fk_frames(q).shape == (arm.n + 1, 4, 4)
        assert np.allclose(arm.fk_frames(q)[-1], arm.fk(q), atol=1e-12)
        assert arm.key_points(q).shape == (5, 3)
        assert arm.jacobian(q).shape == (6, arm.n)


def test_pa10_paper_values() -> None:
    arm = load_arm("pa10")
    assert arm.n == 7
    assert arm.link_lengths == (0.315, 0.45, 0.50, 0.08)
    assert np.allclose(np.degrees(arm.upper), [177, 91, 174, 137, 255, 165, 360])
    assert np.allclose(arm.lower, -arm.upper)
    assert arm.joint_names[0] == "pa10_joint_1"
    assert load_arm("pa10_7c").link_lengths == (0.317, 0.45, 0.48, 0.07)
    T0 = arm.fk(np.zeros(7))  # zero pose: straight up +z
    assert np.allclose(T0[:3, :3], np.eye(3))
    assert np.allclose(T0[:3, 3], [0, 0, 0.315 + 0.45 + 0.50 + 0.08])


def _paper_fk(L: tuple[float, ...], t: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Swivel paper eq. 6-9 with quaternions: q = Qz Qy Qz Qy Qz Qy Qz; positions from q2, q4, q6."""
    qs = []
    q = np.array([1.0, 0, 0, 0])
    for i, ti in enumerate(t):
        q = qmul(q, qz(ti) if i % 2 == 0 else qy(ti))
        qs.append(q)
    k = np.array([0.0, 0.0, 1.0])
    pS = L[0] * k
    pE = pS + L[1] * quat_to_matrix(qs[1]) @ k
    pW = pE + L[2] * quat_to_matrix(qs[3]) @ k
    p = pW + L[3] * quat_to_matrix(qs[5]) @ k
    return p, qs[6], [pS, pE, pW, p]


@pytest.mark.parametrize("name", ["pa10", "pa10_7c", "powercube7"])
def test_swivel_arm_fk_equals_paper_quaternion_fk(name: str) -> None:
    arm = load_arm(name)
    for q in _rand_q(arm, 40, 1):
        p, quat, pts = _paper_fk(arm.link_lengths, q)
        T = arm.fk(q)
        assert np.allclose(T[:3, 3], p, atol=1e-12)
        assert np.allclose(T[:3, :3], quat_to_matrix(quat), atol=1e-12)
        kp = arm.key_points(q)
        assert np.allclose(kp[0], 0.0)
        assert np.allclose(kp[1:], np.array(pts), atol=1e-12)


@pytest.mark.parametrize("name", ["pa10", "powercube7", "powercube6"])
def test_key_points_are_the_origins_of_the_fk_frames(name: str) -> None:
    arm = load_arm(name)
    for q in _rand_q(arm, 50, 6):
        F = arm.fk_frames(q)
        want = np.vstack([np.zeros(3), *(F[i, :3, 3] for i in arm.key_joints), F[arm.n, :3, 3]])
        np.testing.assert_allclose(arm.key_points(q), want, rtol=0, atol=1e-14)


def test_powercube6_fk_equals_eq_2_to_4() -> None:
    arm = load_arm("powercube6")
    L1, L23, L4, L56 = 0.13, 0.36, 0.18, 0.26
    assert arm.link_lengths == (L1, L23, L4, L56)
    rng = np.random.default_rng(2)
    for _ in range(50):
        q = rng.uniform(-math.pi, math.pi, 6)
        q[2] = 0.0
        f1, f2, f4, f5 = q[0], q[1], q[3], q[4]
        s = L1 + L23 * math.cos(f2) + L4 * math.cos(f2 + f4) + L56 * math.cos(f2 + f4 + f5)
        expected = [
            math.cos(f1) * s,
            math.sin(f1) * s,
            L23 * math.sin(f2) + L4 * math.sin(f2 + f4) + L56 * math.sin(f2 + f4 + f5),
        ]
        unlocked = load_arm("powercube6", lower=[-4] * 6, upper=[4] * 6)
        assert np.allclose(unlocked.fk(q)[:3, 3], expected, atol=1e-12)
        # wrist roll does not move the tool point
        q2 = q.copy()
        q2[5] += 1.0
        assert np.allclose(unlocked.fk(q2)[:3, 3], expected, atol=1e-12)
    assert np.allclose(arm.fk(np.zeros(6))[:3, 3], [L1 + L23 + L4 + L56, 0, 0])
    assert arm.lower[2] == arm.upper[2] == 0.0  # joint 3 locked


@pytest.mark.parametrize("name", ARMS)
def test_jacobian_matches_finite_differences(name: str) -> None:
    arm = load_arm(name)
    h = 1e-6
    for q in _rand_q(arm, 5, 3):
        J = arm.jacobian(q)
        T0 = arm.fk(q)
        for i in range(arm.n):
            dq = np.zeros(arm.n)
            dq[i] = h
            Tp, Tm = arm.fk(q + dq), arm.fk(q - dq)
            assert np.allclose(J[:3, i], (Tp[:3, 3] - Tm[:3, 3]) / (2 * h), atol=1e-7)
            w = (rotation_error(T0[:3, :3], Tp[:3, :3]) - rotation_error(T0[:3, :3], Tm[:3, :3])) / (2 * h)
            assert np.allclose(J[3:, i], w, atol=1e-7)


def test_fk_batch_matches_fk() -> None:
    arm = load_arm("powercube7")
    Q = _rand_q(arm, 20, 4)
    Tb = arm.fk_batch(Q)
    assert Tb.shape == (20, 4, 4)
    for q, T in zip(Q, Tb, strict=True):
        assert np.allclose(T, arm.fk(q), atol=1e-12)


def test_overrides() -> None:
    arm = load_arm("pa10", link_lengths=[0.3, 0.4, 0.4, 0.1])
    assert arm.link_lengths == (0.3, 0.4, 0.4, 0.1)
    assert np.isclose(arm.fk(np.zeros(7))[2, 3], 1.2)
    arm = load_arm("pa10", upper=[1.0] * 7, lower=[-1.0] * 7, max_vel=[0.5] * 7)
    assert np.allclose(arm.upper, 1.0) and np.allclose(arm.max_vel, 0.5)
    with pytest.raises(ConfigError):
        load_arm("pa10", link_lengths=[0.3, 0.4])
    with pytest.raises(ConfigError):
        load_arm("pa10", no_such_key=1)
    with pytest.raises(ConfigError):
        load_arm("pa10", lower=[0.5] * 7, upper=[0.0] * 7)


def test_unknown_arm_and_bad_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown arm"):
        load_arm("no_such_arm")
    with pytest.raises(ConfigError):
        load_arm(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nkind: swivel7\nlink_lengths: [1, 1, 1, 1]\njoints: [{name: a}]\n")
    with pytest.raises(ConfigError):
        load_arm(bad)
    bad.write_text("name: x\nkind: teleport\njoints: [{limits: [-1, 1], max_vel: 1, max_acc: 1, axis: z}]\n")
    with pytest.raises(ConfigError, match="unknown kind"):
        load_arm(bad)
    bad.write_text(": : :\n")
    with pytest.raises(ConfigError):
        load_arm(bad)
    assert issubclass(ConfigError, InvalidInputError)


def test_generic_chain_yaml_reproduces_pa10(tmp_path: Path) -> None:
    L = (0.315, 0.45, 0.50, 0.08)
    z = [0.0, L[0], 0.0, L[1], 0.0, L[2], 0.0]
    lines = [
        "name: pa10_chain",
        "kind: chain",
        "key_joints: [1, 3, 5]",
        "tool: {xyz: [0, 0, 0.08]}",
        "joints:",
    ]
    for i in range(7):
        ax = "z" if i % 2 == 0 else "[0, 1, 0]"
        lines.append(
            f"  - {{name: j{i}, axis: {ax}, origin: {{xyz: [0, 0, {z[i]}], rpy: [0, 0, 0]}}, "
            "limits: [-3, 3], max_vel: 1, max_acc: 1}"
        )
    path = tmp_path / "pa10_chain.yaml"
    path.write_text("\n".join(lines) + "\n")
    chain = load_arm(path)
    pa10 = load_arm("pa10")
    assert chain.kind == "chain" and not chain.has_swivel and not has_swivel(chain)
    for q in _rand_q(chain, 10, 5):
        assert np.allclose(chain.fk(q), pa10.fk(q), atol=1e-12)
        assert np.allclose(chain.key_points(q), pa10.key_points(q), atol=1e-12)
    # a generic chain has no closed form: the capability protocols say so (and it has no `ik`)
    assert not has_analytic_ik(chain) and not hasattr(chain, "ik")
    assert has_swivel(pa10) and has_analytic_ik(pa10) and pa10.has_swivel
    assert has_analytic_ik(load_arm("powercube6")) and not has_swivel(load_arm("powercube6"))
    # the routes' protocol (the swivel corridor and the limit check) holds for the swivel arms only
    assert all(isinstance(load_arm(a), CorridorArm) for a in ("pa10", "powercube7"))
    assert not isinstance(load_arm("powercube6"), CorridorArm) and not isinstance(chain, CorridorArm)


@pytest.mark.parametrize(
    "q",
    [np.zeros(6), np.full(7, np.nan), np.array([0, 0, 0, np.inf, 0, 0, 0]), "abc", np.zeros((7, 1))],
)
def test_bad_q_rejected(q: object) -> None:
    arm = load_arm("pa10")
    with pytest.raises(InvalidInputError):
        arm.fk(q)  # type: ignore[arg-type]


def test_bad_pose_rejected() -> None:
    arm = load_arm("pa10")
    T = arm.fk(np.full(7, 0.2))
    bad = [T[:3], T * np.nan, T + np.diag([0.1, 0, 0, 0]), np.diag([1.0, 1.0, -1.0, 1.0]), "x"]
    T2 = T.copy()
    T2[3, 0] = 0.5
    bad.append(T2)
    for B in bad:
        with pytest.raises(InvalidInputError):
            arm.check_pose(B)
        with pytest.raises(InvalidInputError):
            arm.ik(B, 0.0)  # type: ignore[arg-type]


def test_kinematics_modules_import_without_a_cycle() -> None:
    """Every import between kinematics modules (also inside functions; not the type-checking-only ones)
    points down one layering: no module needs one that needs it back."""
    import ast

    pkg = Path(__file__).resolve().parents[1] / "redarm_ros" / "kinematics"
    graph: dict[str, set[str]] = {}
    for path in pkg.glob("*.py"):
        tree = ast.parse(path.read_text())
        skip: set[int] = set()
        for node in ast.walk(tree):  # `if TYPE_CHECKING:` blocks are for annotations only
            if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
                skip.update(id(n) for b in node.body for n in ast.walk(b))
        deps = set()
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("redarm_ros.kinematics."):
                deps.add(node.module.rsplit(".", 1)[1])
            elif isinstance(node, ast.Import):
                deps.update(
                    a.name.rsplit(".", 1)[1]
                    for a in node.names
                    if a.name.startswith("redarm_ros.kinematics.")
                )
        graph[path.stem] = deps - {path.stem}
    state: dict[str, int] = {}

    def visit(mod: str, trail: list[str]) -> None:
        if state.get(mod) == 1:
            raise AssertionError(f"import cycle: {' -> '.join(trail + [mod])}")
        if state.get(mod) == 2:
            return
        state[mod] = 1
        for dep in graph.get(mod, ()):
            visit(dep, trail + [mod])
        state[mod] = 2

    for mod in graph:
        visit(mod, [])
    assert "swivel" not in graph["model"] and "loader" in graph["__init__"]
    assert not (graph["numeric"] & {"model", "swivel", "powercube6", "loader"})


@pytest.mark.parametrize("name", ["pa10", "powercube7", "powercube6"])
def test_fk_after_key_points_at_the_same_joints_takes_one_pass(
        name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    # The controller asks for the key points of each command and then its pose: one FK pass serves
    # both, bit for bit; other joints (a sign of zero too) get their own pass.
    arm = load_arm(name)
    rng = np.random.default_rng(11)
    q = rng.uniform(arm.lower, arm.upper)
    fresh = arm.fk(q)
    passes = []
    inner = arm._fk_lists
    monkeypatch.setattr(arm, "_fk_lists", lambda *a: passes.append(1) or inner(*a))
    arm.key_points(q)
    assert np.array_equal(arm.fk(q.copy()), fresh) and len(passes) == 1
    q2 = q.copy()
    q2[-1] += 1e-9
    assert np.array_equal(arm.fk(q2), load_arm(name).fk(q2)) and len(passes) == 2
    z = np.zeros(arm.n)
    arm.key_points(z)
    assert np.array_equal(arm.fk(-z), load_arm(name).fk(-z)) and len(passes) == 4
