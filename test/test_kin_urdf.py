"""Arm models from URDF (kinematics.urdf_chain): the bundled arms against URDFs of themselves, an
iiwa14-like arm mapped onto the closed-form swivel model (plain and re-framed), a Franka-like chain on the
numeric solver with the reason, and malformed input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from support.waits import HANG_BUDGET_S

from redarm_ros.errors import ConfigError
from redarm_ros.kinematics import has_swivel, load_arm
from redarm_ros.kinematics.model import pose_error
from redarm_ros.kinematics.result import IKStatus
from redarm_ros.kinematics.urdf_chain import MappedSwivelArm, describe_solver, swivel_map
from redarm_ros.sim.urdf import build_urdf
from redarm_ros.sim.urdf_arms import IIWA_LIMITS_DEG, franka_like_urdf, iiwa14_urdf  # from published facts

STRICT = 1e-5  # m and rad: TRAC-IK's tolerance


def _urdf_arm(name: str):  # noqa: ANN202
    yaml_arm = load_arm(name)
    return yaml_arm, load_arm(build_urdf(yaml_arm), base_link=f"{name}_base_link", tip_link=f"{name}_tool")


@pytest.mark.parametrize("name", ["pa10", "pa10_7c", "powercube7"])
def test_bundled_swivel_arms_from_their_urdf_match_the_yaml_models(name: str) -> None:
    a, b = _urdf_arm(name)
    assert type(b).__name__ == "SwivelArm" and b.kind == "swivel7"
    assert b.joint_names == a.joint_names
    np.testing.assert_array_equal(b.lower, a.lower)
    np.testing.assert_array_equal(b.max_vel, a.max_vel)
    np.testing.assert_allclose(b.link_lengths, a.link_lengths, rtol=0, atol=1e-15)
    rng = np.random.default_rng(3)
    Q = rng.uniform(a.lower, a.upper, (300, 7))
    for q in Q:
        assert np.abs(a.fk(q) - b.fk(q)).max() <= 1e-12
    for q in Q[:60]:
        T = a.fk(q)
        s = a.swivel(q)
        assert abs(b.swivel(q) - s) <= 1e-12
        ra, rb = a.ik(T, s), b.ik(T, s)
        assert ra.shape == rb.shape and np.abs(ra - rb).max(initial=0.0) <= 1e-12
        seed = (a.lower + a.upper) / 2
        qa, _ = a.ik_nearest(T, seed)
        qb, _ = b.ik_nearest(T, seed)
        assert np.abs(qa - qb).max() <= 1e-12
    assert describe_solver(b) == "closed-form swivel IK"


def test_powercube6_from_its_urdf_is_numeric_with_the_reason_and_the_same_fk() -> None:
    a, b = _urdf_arm("powercube6")
    assert not has_swivel(b) and "6 joints" in b.config["closed_form_refused"]
    assert describe_solver(b).startswith("numeric IK")
    rng = np.random.default_rng(4)
    Q = rng.uniform(a.lower, a.upper, (200, 6))
    for q in Q:
        assert np.abs(a.fk(q) - b.fk(q)).max() <= 1e-12
    for q in Q[:10]:
        T = a.fk(q)
        qb, info = b.ik_nearest(T, q + 0.05, timeout_s=None)
        assert info.status is IKStatus.SUCCESS
        assert max(pose_error(b.fk(qb), T)) <= STRICT


@pytest.fixture(scope="module", params=[False, True], ids=["iiwa14", "iiwa14_reframed"])
def iiwa(request: pytest.FixtureRequest) -> MappedSwivelArm:
    arm = load_arm(iiwa14_urdf(reframed=request.param), base_link="base_link", tip_link="tool0")
    assert isinstance(arm, MappedSwivelArm)
    return arm


def test_iiwa_maps_onto_the_swivel_model_with_its_published_geometry(iiwa: MappedSwivelArm) -> None:
    assert has_swivel(iiwa) and describe_solver(iiwa) == "closed-form swivel IK"
    np.testing.assert_allclose(iiwa.link_lengths, (0.36, 0.42, 0.40, 0.126), atol=1e-12)
    assert iiwa.map.deviation <= 1e-12
    if iiwa.name == "iiwa14_like":  # the plain URDF: joint 4 turns about -y, the rest as the model
        np.testing.assert_array_equal(iiwa.map.sign, [1, 1, 1, -1, 1, 1, 1])
        np.testing.assert_allclose(iiwa.map.offset, 0.0, atol=1e-15)
        np.testing.assert_allclose(np.degrees(iiwa.upper), IIWA_LIMITS_DEG, atol=1e-12)
    else:
        assert np.abs(iiwa.map.offset).max() > 0.1  # the zero pose is bent
        assert np.abs(iiwa.map.base[:3, :3] - np.eye(3)).max() > 0.1  # the base is turned
    rng = np.random.default_rng(5)
    for q in rng.uniform(iiwa.lower, iiwa.upper, (100, 7)):
        Tc = iiwa.canonical.fk(iiwa._qc(q))  # noqa: SLF001 - the map itself
        assert np.abs(iiwa.map.base @ Tc @ iiwa.map.tool - iiwa.fk(q)).max() <= 1e-12


def _hard_postures(arm: MappedSwivelArm, rng: np.random.Generator) -> np.ndarray:
    """Postures with a joint exactly at a limit, and with the elbow (q4) near stretched."""
    out = []
    for j in range(7):
        for lim in (arm.lower[j], arm.upper[j]):
            q = rng.uniform(arm.lower, arm.upper)
            q[j] = lim
            out.append(q)
    for e in (1e-9, 1e-6, 1e-3, 0.0):
        q = rng.uniform(arm.lower, arm.upper)
        q[3] = e + arm.map.offset[3]  # canonical theta4 = +-e: the stretched elbow
        out.append(q)
    return np.array(out)


def _strict(arm: MappedSwivelArm, q: np.ndarray | None, T: np.ndarray) -> bool:
    if q is None:
        return False
    inside = bool(np.all(q >= arm.lower) and np.all(q <= arm.upper))  # limits exact
    pe, re = pose_error(arm.fk(q), T)
    return inside and pe <= STRICT and re <= STRICT


def test_iiwa_strict_success_on_uniform_and_hard_poses(iiwa: MappedSwivelArm) -> None:
    rng = np.random.default_rng(11)
    Q = np.vstack([rng.uniform(iiwa.lower, iiwa.upper, (300, 7)), _hard_postures(iiwa, rng)])
    seed = (iiwa.lower + iiwa.upper) / 2
    fails = []
    for k, q in enumerate(Q):
        T = iiwa.fk(q)
        qs, info = iiwa.ik_nearest(T, seed, timeout_s=None)
        if not (info.status is IKStatus.SUCCESS and _strict(iiwa, qs, T)):
            fails.append((k, info.status, info.message))
        else:  # the info's errors are this arm's, whether taken from the model or recomputed
            pe, re = pose_error(iiwa.fk(qs), T)
            assert abs(info.pos_err - pe) <= 1e-12 and abs(info.rot_err - re) <= 1e-12, k
        rows = iiwa.ik(T, iiwa.swivel(q))
        assert len(rows) >= 1, k
        assert min(float(np.abs(r - q).max()) for r in iiwa.nearest_copies(rows, q)) <= 1e-6, k
        for r in rows:
            assert _strict(iiwa, r, T), (k, r)
    assert not fails, fails[:5]


def test_iiwa_ik_nearest_is_the_exhaustive_optimum(iiwa: MappedSwivelArm) -> None:
    rng = np.random.default_rng(12)
    Q = np.vstack([rng.uniform(iiwa.lower, iiwa.upper, (25, 7)), _hard_postures(iiwa, rng)[::3]])
    for k, q in enumerate(Q):
        T = iiwa.fk(q)
        seed = rng.uniform(iiwa.lower, iiwa.upper)
        qa, ia = iiwa.ik_nearest(T, seed, timeout_s=None)
        qe, ie = iiwa.ik_nearest(T, seed, timeout_s=None, exhaustive=True)
        assert ia.status is IKStatus.SUCCESS and ie.status is IKStatus.SUCCESS, k
        ca, ce = float(np.sum((qa - seed) ** 2)), float(np.sum((qe - seed) ** 2))
        assert ca <= ce + 1e-9 * (1 + ce), (k, ca, ce)


def test_iiwa_batch_feasible_and_elbow_circle_in_its_own_frames(iiwa: MappedSwivelArm) -> None:
    rng = np.random.default_rng(13)
    Q = rng.uniform(iiwa.lower, iiwa.upper, (40, 7))
    Ts = np.array([iiwa.fk(q) for q in Q])
    S = np.array([iiwa.swivel(q) for q in Q])
    Qb, valid = iiwa.ik_batch(Ts, S)
    for i in range(len(Q)):
        single = iiwa.ik(Ts[i], S[i])
        assert valid[i].sum() == len(single)
        np.testing.assert_allclose(Qb[i][valid[i]], single, atol=1e-9)
        # the elbow circle holds the posture's elbow (key point 2) in the arm's own base frame
        C, n, rho = iiwa.elbow_circle(Ts[i])
        kp = iiwa.key_points(Q[i])
        assert abs(np.linalg.norm(kp[2] - C) - rho) <= 1e-9 and abs(float((kp[2] - C) @ n)) <= 1e-9
        ivs = iiwa.feasible_swivels(Ts[i])
        assert any(((S[i] - a) % (2 * math.pi)) <= b - a + 1e-9 for iv in ivs for a, b in iv)
    res = iiwa.ik_nearest_batch(Ts, (iiwa.lower + iiwa.upper) / 2)
    for i in range(len(Q)):
        assert _strict(iiwa, res.q[i], Ts[i])


def test_iiwa_key_points_are_its_joint_centres() -> None:
    arm = load_arm(iiwa14_urdf(), base_link="base_link", tip_link="tool0")
    kp = arm.key_points(np.zeros(7))
    np.testing.assert_allclose(
        kp, [[0, 0, 0], [0, 0, 0.36], [0, 0, 0.78], [0, 0, 1.18], [0, 0, 1.306]], atol=1e-12
    )


def test_franka_like_chain_gets_the_numeric_solver_and_the_reason() -> None:
    arm = load_arm(franka_like_urdf(), base_link="base_link", tip_link="tool0")
    assert not has_swivel(arm) and arm.kind == "chain"
    why = arm.config["closed_form_refused"]
    assert "axes 3 and 4 do not meet (elbow offset) by 0.0825 m" in why
    assert "wrist" in why and "\n" not in why
    line = describe_solver(arm)
    assert line.startswith("numeric IK") and "elbow offset" in line
    rng = np.random.default_rng(21)
    seed = (arm.lower + arm.upper) / 2
    ok = 0
    iterations = []
    Q = rng.uniform(arm.lower, arm.upper, (60, 7))
    for q in Q:
        T = arm.fk(q)
        qs, info = arm.ik_nearest(T, seed, timeout_s=None, max_iter=3000)
        ok += info.status is IKStatus.SUCCESS and _strict(arm, qs, T)
        iterations.append(info.iterations)
    assert ok == 60  # the rate at the 5 ms budget is the benchmark's (benchmarks/urdf_ik_bench.py)
    # the work, machine-independent: batched iterations (one FK + Jacobian of all starts each); the
    # 5 ms rate rests on the slowest poses needing few of them
    assert max(iterations) <= 12


def test_structure_tolerance_is_stated_and_applies() -> None:
    # an elbow offset of 1e-7 m is within the default 1e-6 tolerance; 1e-5 m is not
    base = load_arm(iiwa14_urdf(), base_link="base_link", tip_link="tool0")
    for gap, closed in ((1e-7, True), (1e-5, False)):
        head = (
            '<joint name="iiwa_joint_4" type="revolute">\n    <parent link="link_3"/><child link="link_4"/>'
        )
        text = iiwa14_urdf().replace(head + '<origin xyz="0 0 ', head + f'<origin xyz="{gap:.17g} 0 ')
        assert text != iiwa14_urdf()
        arm = load_arm(text, base_link="base_link", tip_link="tool0")
        assert has_swivel(arm) is closed, arm.config.get("closed_form_refused")
        if not closed:
            assert "elbow offset" in arm.config["closed_form_refused"]
            assert "tolerance 1e-06" in arm.config["closed_form_refused"]
    assert swivel_map(base, tol=1e-6) is not None


def test_urdf_from_a_file_with_acceleration_limits_beside_it(tmp_path: Path) -> None:
    f = tmp_path / "iiwa.urdf"
    f.write_text(iiwa14_urdf(), encoding="utf-8")
    arm = load_arm(f, base_link="base_link", tip_link="tool0")
    np.testing.assert_allclose(arm.max_acc, 2.0 * arm.max_vel)  # ACC_PER_VEL without a limits file
    (tmp_path / "iiwa.yaml").write_text(
        "joint_limits:\n  iiwa_joint_1: {has_acceleration_limits: true, max_acceleration: 3.5}\n",
        encoding="utf-8",
    )
    arm = load_arm(str(f), base_link="base_link", tip_link="tool0", arm_name="lbr")
    assert arm.name == "lbr" and arm.max_acc[0] == 3.5 and arm.max_acc[1] == 2.0 * arm.max_vel[1]
    assert arm.config["urdf"] == str(f)
    # a sub-chain: base_link -> link_4 is 4 revolute joints (numeric)
    sub = load_arm(f, base_link="base_link", tip_link="link_4")
    assert sub.n == 4 and "4 joints" in sub.config["closed_form_refused"]


def test_continuous_and_fixed_joints() -> None:
    text = iiwa14_urdf().replace(
        '<joint name="iiwa_joint_7" type="revolute">', '<joint name="iiwa_joint_7" type="continuous">'
    )
    arm = load_arm(text, base_link="base_link", tip_link="tool0")
    assert has_swivel(arm) and arm.upper[6] == 2 * math.pi and arm.lower[6] == -2 * math.pi
    # the mount (a fixed joint) folds into the base transform of the re-framed arm
    arm = load_arm(iiwa14_urdf(reframed=True), base_link="mount", tip_link="tool0")
    assert has_swivel(arm)


@pytest.mark.parametrize(
    ("text", "base", "tip", "what"),
    [
        ("<robot name='x'><joint", "a", "b", "well-formed"),
        ("<robt/>", "a", "b", "<robot>"),
        (iiwa14_urdf(), "base_link", "nope", "not a link"),
        (iiwa14_urdf(), "link_3", "link_1", "not below"),
        (iiwa14_urdf().replace('type="revolute"', 'type="prismatic"', 1), "base_link", "tool0", "prismatic"),
        (iiwa14_urdf().replace('velocity="', 'velocity="-', 1), "base_link", "tool0", "velocity"),
        ('<robot name="r" xmlns:xacro="x"><xacro:macro/></robot>', "a", "b", "xacro"),
    ],
)
def test_bad_urdf_input_is_a_clear_config_error(text: str, base: str, tip: str, what: str) -> None:
    with pytest.raises(ConfigError, match=what):
        load_arm(text, base_link=base, tip_link=tip)


def test_urdf_needs_both_links_and_a_readable_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="base_link and tip_link"):
        load_arm(iiwa14_urdf(), base_link="base_link")
    with pytest.raises(ConfigError, match="cannot read URDF"):
        load_arm(tmp_path / "missing.urdf", base_link="a", tip_link="b")
    with pytest.raises(ConfigError, match="unknown override"):
        load_arm(iiwa14_urdf(), base_link="base_link", tip_link="tool0", link_lengths=[1, 2, 3, 4])


def test_batched_fk_jacobian_matches_the_scalar_one() -> None:
    from redarm_ros.kinematics.numeric import fk_jacobian_batch

    for text in (franka_like_urdf(), iiwa14_urdf(reframed=True)):
        arm = load_arm(text, base_link="base_link", tip_link="tool0")
        Q = np.random.default_rng(8).uniform(arm.lower, arm.upper, (20, 7))
        R, p, J = fk_jacobian_batch(arm, Q)
        for i, q in enumerate(Q):
            R1, p1, J1 = arm.fk_jacobian(q)
            assert np.abs(R[i] - R1).max() <= 1e-12 and np.abs(p[i] - p1).max() <= 1e-12
            assert np.abs(J[i] - J1).max() <= 1e-12


def test_numeric_chain_answers_bad_input_and_unreachable_poses() -> None:
    arm = load_arm(franka_like_urdf(), base_link="base_link", tip_link="tool0")
    q, info = arm.ik_nearest(np.full((4, 4), np.nan), np.zeros(7))
    assert q is None and info.status is IKStatus.INVALID_INPUT
    T = np.eye(4)
    T[0, 3] = 3.0  # beyond the reach
    q, info = arm.ik_nearest(T, np.zeros(7), timeout_s=None, max_iter=50)
    assert q is None and info.status is IKStatus.TIMEOUT and "max_iter" in info.message


def test_ik_front_end_serves_urdf_arms_with_the_collision_filter() -> None:
    from redarm_ros.kinematics.solve import IKFrontEnd

    iiwa = load_arm(iiwa14_urdf(reframed=True), base_link="base_link", tip_link="tool0")
    panda = load_arm(franka_like_urdf(), base_link="base_link", tip_link="tool0")
    fe = IKFrontEnd({"iiwa": iiwa, "panda": panda}, "iiwa")
    rng = np.random.default_rng(17)
    for name, arm in (("iiwa", iiwa), ("panda", panda)):
        for _ in range(8):
            T = arm.fk(rng.uniform(arm.lower, arm.upper))
            ans = fe.solve(T, name, swivel=None, seed=[], all_solutions=True, timeout_s=HANG_BUDGET_S)
            assert ans.status in (IKStatus.SUCCESS, IKStatus.ALL_SOLUTIONS_COLLIDE), ans.message
            assert ans.solver == describe_solver(arm)
            if ans.status is IKStatus.SUCCESS:
                assert _strict(arm, ans.q, T) and ans.clearance >= 0.0
    T = iiwa.fk(np.full(7, 0.3))
    ans = fe.solve(T, "iiwa", swivel=0.2, seed=[], all_solutions=True, timeout_s=HANG_BUDGET_S)
    assert ans.status is IKStatus.SUCCESS and all(_strict(iiwa, r, T) for r in ans.solutions)
    T[2, 3] += 5.0
    ans = fe.solve(T, "iiwa", swivel=None, seed=[], all_solutions=False, timeout_s=HANG_BUDGET_S)
    assert ans.status is IKStatus.OUT_OF_REACH and "no base placement model" in ans.message


def test_controller_runs_urdf_arms_in_the_model_frames_and_refuses_other_chains_with_the_reason() -> None:
    from redarm_ros.control.make import make_controller
    from redarm_ros.control.reach_controller import JointMappedController
    from redarm_ros.control.types import Phase

    _, pa10 = _urdf_arm("pa10")
    ctl = make_controller(pa10)
    ctl.reset(np.array([0.0, -0.5, 0.0, 2.0, 0.0, 1.2, 0.0]))
    assert ctl.step(0.01).q.shape == (7,)
    # the iiwa: joint 4 turns about -y; the controller runs the model with joint values mapped
    iiwa = load_arm(iiwa14_urdf(), base_link="base_link", tip_link="tool0")
    ctl = make_controller(iiwa)
    assert isinstance(ctl, JointMappedController)
    q0 = np.radians([10.0, 30.0, 0.0, -60.0, 0.0, 60.0, 0.0])
    ctl.reset(q0)
    np.testing.assert_allclose(ctl.q, q0, atol=1e-12)
    goal_q = np.radians([40.0, 45.0, 10.0, -80.0, 20.0, 40.0, 30.0])
    goal = iiwa.fk(goal_q)
    check = ctl.set_goal(goal)
    assert check.accepted, check.message
    q = q0
    for _ in range(3000):
        r = ctl.step(0.01)
        assert np.all(r.q >= iiwa.lower) and np.all(r.q <= iiwa.upper)
        assert np.abs(r.q - q).max() <= iiwa.max_vel.max() * 0.01 + 1e-9  # rate-limited in its own joints
        q = r.q
        if r.phase is Phase.REACHED:
            break
    assert r.phase is Phase.REACHED, r.message
    assert max(pose_error(iiwa.fk(r.q), goal)) <= 2e-3
    reframed = load_arm(iiwa14_urdf(reframed=True), base_link="base_link", tip_link="tool0")
    with pytest.raises(ConfigError, match="base or tool transform") as e1:
        make_controller(reframed)
    panda = load_arm(franka_like_urdf(), base_link="base_link", tip_link="tool0")
    with pytest.raises(ConfigError, match="elbow offset") as e2:
        make_controller(panda)
    assert "\n" not in str(e1.value) + str(e2.value)


def test_controller_capsules_come_from_the_urdf_collision_geometry(tmp_path: Path) -> None:
    import dataclasses
    import struct

    from redarm_ros.control.make import make_controller
    from redarm_ros.control.params import ControllerParams
    from redarm_ros.geometry.obstacles import ArmCapsules, Scene

    tri = np.array([[0.11, 0.0, 0.1], [0.0, 0.05, 0.2], [0.0, 0.0, 0.3]], np.float32)  # binary STL
    stl = b"\0" * 80 + struct.pack("<I", 1) + np.zeros(3, np.float32).tobytes() + tri.tobytes() + b"\0\0"
    (tmp_path / "forearm.stl").write_bytes(stl)
    text = (
        iiwa14_urdf()
        .replace('<link name="link_2"/>', '<link name="link_2"><collision><origin xyz="0 0 0.21"/><geometry>'
                 '<cylinder radius="0.09" length="0.3"/></geometry></collision></link>')
        .replace('<link name="link_4"/>', '<link name="link_4"><collision><geometry>'
                 '<mesh filename="forearm.stl"/></geometry></collision></link>')
        .replace('<link name="link_6"/>', '<link name="link_6"><collision><geometry>'
                 '<mesh filename="hand.dae"/></geometry></collision></link>')
    )
    (tmp_path / "arm.urdf").write_text(text)
    arm = load_arm(tmp_path / "arm.urdf", base_link="base_link", tip_link="tool0")
    ctl = make_controller(arm, Scene())
    radii = ctl.inner.params.capsules.radii
    default = ArmCapsules().radii
    # upper arm: the cylinder on its axis; forearm: the mesh vertex 0.11 m off its axis; the base (no
    # geometry) and the hand (a mesh format not read) keep the defaults
    assert radii == pytest.approx((default[0], 0.09, 0.11, default[3]), abs=1e-7)
    mine = ArmCapsules(radii=(0.2, 0.2, 0.2, 0.2))  # capsules set by the user are kept
    ctl = make_controller(arm, Scene(), dataclasses.replace(ControllerParams(), capsules=mine))
    assert ctl.inner.params.capsules == mine
    plain = load_arm(iiwa14_urdf(), base_link="base_link", tip_link="tool0")  # URDF text, no geometry
    assert make_controller(plain, Scene()).inner.params.capsules == ArmCapsules()
