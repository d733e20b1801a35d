"""Numeric IK for any model: damped least squares (6-D) and the thesis' Flow update (both variants)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from redarm_ros.kinematics import IKStatus, load_arm, pose_error
from redarm_ros.kinematics.numeric import fk_jacobian, solve_dls, solve_flow

ARMS = ["pa10", "powercube7", "powercube6"]


def _near_targets(name: str, n: int, seed: int, noise: float) -> list[tuple[np.ndarray, np.ndarray]]:
    arm = load_arm(name)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        q = rng.uniform(arm.lower, arm.upper) * 0.8
        out.append((q, np.clip(q + rng.normal(0, noise, arm.n), arm.lower, arm.upper)))
    return out


@pytest.mark.parametrize("name", ARMS)
def test_fk_jacobian_matches_model(name: str) -> None:
    arm = load_arm(name)
    for q, _ in _near_targets(name, 5, 0, 0.0):
        R, p, J = fk_jacobian(arm, q.tolist())
        T = arm.fk(q)
        assert np.allclose(R, T[:3, :3]) and np.allclose(p, T[:3, 3])
        assert np.allclose(J, arm.jacobian(q), atol=1e-12)


@pytest.mark.parametrize("name", ARMS)
def test_dls_converges_with_orientation_and_limits(name: str) -> None:
    arm = load_arm(name)
    for q, q0 in _near_targets(name, 10, 1, 0.2):
        T = arm.fk(q)
        qs, info = solve_dls(arm, T, q0, tol=1e-8, max_iter=500, timeout_s=None)
        assert info.status is IKStatus.SUCCESS, info.message
        assert info.pos_err < 1e-8 and info.rot_err < 1e-8
        assert arm.within_limits(qs)
        assert np.max(np.abs(arm.fk(qs)[:3, 3] - T[:3, 3])) < 1e-8


def test_dls_is_deterministic_and_reports_failure() -> None:
    arm = load_arm("pa10")
    T = arm.fk(np.array([0.3, 0.5, -0.2, 1.0, 0.2, 0.4, 0.1]))
    a = solve_dls(arm, T, np.zeros(7), timeout_s=None, max_iter=300)[0]
    b = solve_dls(arm, T, np.zeros(7), timeout_s=None, max_iter=300)[0]
    assert a is not None and np.array_equal(a, b)
    far = T.copy()
    far[:3, 3] = [3.0, 0, 0]
    q, info = solve_dls(arm, far, np.zeros(7), timeout_s=None, max_iter=60)
    assert q is None and info.status is IKStatus.TIMEOUT and info.pos_err > 1.0
    q, info = solve_dls(arm, T * np.nan, np.zeros(7))
    assert q is None and info.status is IKStatus.INVALID_INPUT


@pytest.mark.parametrize("variant", ["sequential", "batch"])
@pytest.mark.parametrize("name", ARMS)
def test_flow_reaches_positions(name: str, variant: str) -> None:
    arm = load_arm(name)
    # the batch (plain Jacobian-transpose) variant converges linearly and zigzags on ill-conditioned
    # poses: ask it for 0.1 mm, the sequential variant for 1 um
    tol = 1e-6 if variant == "sequential" else 1e-4
    for q, q0 in _near_targets(name, 6, 2, 0.15):
        p = arm.fk(q)[:3, 3]
        qs, info = solve_flow(arm, p, q0, variant=variant, tol=tol, max_iter=10000, timeout_s=None)
        assert info.status is IKStatus.SUCCESS, info.message
        assert np.linalg.norm(arm.fk(qs)[:3, 3] - p) < tol
        assert arm.within_limits(qs)


def test_flow_sequential_equals_refreshing_fk_after_each_joint() -> None:
    """One sequential sweep equals updating joint by joint with a full FK after every joint."""
    arm = load_arm("pa10")
    q0 = np.array([0.2, 0.4, -0.3, 0.9, 0.1, 0.5, 0.0])
    p = arm.fk(np.array([0.3, 0.5, -0.2, 1.1, 0.2, 0.4, 0.1]))[:3, 3]
    qr = q0.copy()
    for i in range(6, -1, -1):  # distal -> proximal, full FK before every joint
        F = arm.fk_frames(qr)
        z = F[i, :3, :3] @ arm.chain[i].axis
        o = F[i, :3, 3]
        pe = F[-1, :3, 3]
        qr[i] += 0.5 * (p - pe) @ np.cross(z, pe - o)
    assert not np.allclose(qr, q0)  # the sweep moved the joints
    e0 = float(np.linalg.norm(p - arm.fk(q0)[:3, 3]))
    e1 = float(np.linalg.norm(p - arm.fk(qr)[:3, 3]))
    assert e1 < e0
    # solve_flow returns q only on success: a tolerance between the errors before and after the
    # reference sweep ends it as SUCCESS right after its first (and only) sweep
    q1, info = solve_flow(
        arm, p, q0, max_iter=1, tol=0.5 * (e0 + e1), timeout_s=None, gain=0.5, clamp=False
    )
    assert info.status is IKStatus.SUCCESS and info.iterations == 1
    assert q1 is not None
    np.testing.assert_allclose(q1, qr, rtol=0, atol=1e-12)


def test_flow_unreachable_stalls_and_bad_input() -> None:
    arm = load_arm("powercube7")
    q, info = solve_flow(arm, [5.0, 0.0, 0.0], np.zeros(7), stall_iters=20, max_iter=5000, timeout_s=None)
    assert q is None and info.status is IKStatus.OUT_OF_REACH and "stalled" in info.message
    for kw in ({"variant": "random"}, {"gain": -1.0}):
        q, info = solve_flow(arm, [0.3, 0.0, 0.5], np.zeros(7), **kw)
        assert info.status is IKStatus.INVALID_INPUT
    q, info = solve_flow(arm, [0.3, np.inf, 0.5], np.zeros(7))
    assert info.status is IKStatus.INVALID_INPUT


def test_generic_chain_uses_numeric_nearest(tmp_path: Path) -> None:
    path = tmp_path / "planar3.yaml"
    path.write_text(
        "name: planar3\nkind: chain\ntool: {xyz: [0.3, 0, 0]}\njoints:\n"
        "  - {name: a, axis: z, limits: [-3, 3], max_vel: 1, max_acc: 1}\n"
        "  - {name: b, axis: z, origin: {xyz: [0.4, 0, 0]}, limits: [-3, 3], max_vel: 1, max_acc: 1}\n"
        "  - {name: c, axis: z, origin: {xyz: [0.35, 0, 0]}, limits: [-3, 3], max_vel: 1, max_acc: 1}\n"
        "  - {name: d, axis: x, origin: {xyz: [0.1, 0, 0]}, limits: [-3, 3], max_vel: 1, max_acc: 1}\n"
        "  - {name: e, axis: y, limits: [-3, 3], max_vel: 1, max_acc: 1}\n"
        "  - {name: f, axis: z, limits: [-3, 3], max_vel: 1, max_acc: 1}\n"
    )
    arm = load_arm(path)
    q = np.array([0.3, -0.5, 0.4, 0.2, -0.3, 0.1])
    qs, info = arm.ik_nearest(arm.fk(q), q + 0.1, timeout_s=None, max_iter=500)
    assert info.ok and info.pos_err < 1e-5 and info.rot_err < 1e-5
    assert qs is not None and arm.within_limits(qs)
    pe, re = pose_error(arm.fk(qs), arm.fk(q))  # the returned q, not only the report, solves it
    assert pe < 1e-5 and re < 1e-5
