"""Closed-form swivel IK (PA10, PA10-7C, PowerCube 7): round trips, swivel, properties, singular cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.kinematics import IKStatus, SwivelArm, load_arm
from redarm_ros.kinematics.quaternion import qrotate, shortest_rotation

SWIVEL_ARMS = ["pa10", "pa10_7c", "powercube7"]
ARMS = {name: load_arm(name) for name in SWIVEL_ARMS}
PROP = settings(
    max_examples=60, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


def _rand_q(arm: SwivelArm, n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(arm.lower, arm.upper, size=(n, arm.n))


def _contains(sols: np.ndarray, q: np.ndarray, atol: float = 1e-7) -> bool:
    return bool(len(sols)) and bool(np.any(np.all(np.abs(sols - q) < atol, axis=1)))


def _wrapdiff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + math.pi) % (2 * math.pi) - math.pi)


@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_round_trip_returns_q(name: str) -> None:
    arm = ARMS[name]
    for q in _rand_q(arm, 300, 10):
        T = arm.fk(q)
        s = arm.swivel(q)
        assert -math.pi < s <= math.pi
        assert _contains(arm.ik(T, s, all_copies=True), q)
        # default: each solution once, at the copy nearest 0 -> q modulo 2 pi
        sols = arm.ik(T, s)
        assert 1 <= len(sols) <= 8
        assert np.any(np.all(_wrapdiff(sols, q) < 1e-7, axis=1))
        # the swivel-quaternion form gives the same set
        u = arm.swivel_u(q)
        assert np.isclose(u[0], math.cos(s)) and np.isclose(u[1], math.sin(s)) and u[2] == 0.0
        assert np.allclose(arm.ik_u(T, u), sols, atol=1e-12)


@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_swivel_inverts_the_elbow_construction(name: str) -> None:
    """pE = C + rho qA u qA* (eq. 15) with u = Qz(s) i Qz(s)* for s = swivel(q) (eq. 13, 16)."""
    arm = ARMS[name]
    for q in _rand_q(arm, 100, 11):
        T = arm.fk(q)
        C, n, rho = arm.elbow_circle(T)
        pS, pE, pW = arm.key_points(q)[1:4]
        assert np.allclose(n, (pW - pS) / np.linalg.norm(pW - pS), atol=1e-12)
        s = arm.swivel(q)
        u = np.array([math.cos(s), math.sin(s), 0.0])
        qa = shortest_rotation(n)
        assert np.allclose(C + rho * qrotate(qa, u), pE, atol=1e-9)
        # every solution at s puts the elbow there and reports the same swivel
        sols = arm.ik(T, s)
        assert len(sols) >= 1  # q itself is one
        for sol in sols:
            assert np.allclose(arm.key_points(sol)[2], pE, atol=1e-9)
            assert abs(math.remainder(arm.swivel(sol) - s, 2 * math.pi)) < 1e-7


def test_eight_flips_with_open_limits() -> None:
    arm = load_arm("pa10", lower=[-2 * math.pi] * 7, upper=[2 * math.pi] * 7)
    wide = load_arm("pa10", lower=[-math.pi] * 7, upper=[math.pi] * 7)
    for q in _rand_q(wide, 30, 12):
        T = wide.fk(q)
        sols = wide.ik(T, wide.swivel(q))
        assert len(sols) == 8
        signs = {tuple(np.sign(s[[1, 3, 5]]).astype(int)) for s in sols}
        assert len(signs) == 8  # all three sign flips
        # rows follow the flip pattern (f2, f4, f6) in binary order
        base = sols[0]
        for k, sol in enumerate(sols):
            f2, f4, f6 = (k >> 2) & 1, (k >> 1) & 1, k & 1
            assert np.isclose(sol[1], -base[1] if f2 else base[1])
            assert np.isclose(sol[3], -base[3] if f4 else base[3])
            assert np.isclose(sol[5], -base[5] if f6 else base[5])
            assert _wrapdiff(np.array([sol[2]]), np.array([base[2] + math.pi * (f2 ^ f4)]))[0] < 1e-9
    # with +-2pi ranges every angle has two in-limit copies: all_copies lists them all
    q = np.array([0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0])
    assert len(arm.ik(arm.fk(q), arm.swivel(q), all_copies=True)) == 8 * 2**7


def test_wide_joints_copy_nearest_zero_and_all_copies() -> None:
    arm = ARMS["pa10"]  # joint 5 +-255 deg, joint 7 +-360 deg
    q = np.array([0.1, 0.4, -0.3, 1.0, math.radians(200), 0.5, math.radians(300)])
    T = arm.fk(q)
    s = arm.swivel(q)
    sols = arm.ik(T, s)
    assert np.all(np.abs(sols[:, [0, 1, 2, 3, 5]]) <= math.pi)
    assert np.all(np.abs(sols[:, 4]) <= math.pi) and np.all(np.abs(sols[:, 6]) <= math.pi)
    assert not _contains(sols, q)
    allc = arm.ik(T, s, all_copies=True)
    assert _contains(allc, q) and len(allc) > len(sols)
    assert np.all(allc >= arm.lower) and np.all(allc <= arm.upper)
    # ik_nearest picks the copy next to the seed
    qn, info = arm.ik_nearest(T, q + 0.01)
    assert info.status is IKStatus.SUCCESS
    assert np.allclose(qn, q, atol=0.05)


@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_limits_false_gives_all_eight_branches_beyond_the_limits_too(name: str) -> None:
    """``ik(T, s, limits=False)``: the 8 branches whatever the limits, each exact, in (-pi, pi], and
    the in-limit solutions among them; a posture 1 mrad beyond a limit is one of them (it is not in
    ``ik(T, s)``)."""
    arm = ARMS[name]
    for q in _rand_q(arm, 50, 13):
        T, s = arm.fk(q), arm.swivel(q)
        allb = arm.ik(T, s, limits=False)
        assert allb.shape == (8, 7)
        assert np.all(np.abs(allb) <= math.pi)
        for sol in allb:
            assert np.max(np.abs(arm.fk(sol) - T)) < 1e-9
        assert np.any(np.all(_wrapdiff(allb, q) < 1e-7, axis=1))
        for sol in arm.ik(T, s):
            assert np.any(np.all(_wrapdiff(allb, sol) < 1e-7, axis=1))
    q = _rand_q(arm, 1, 14)[0]
    q[0] = arm.upper[0] + 1e-3  # (joint 1's range is under 2 pi on every arm here)
    T, s = arm.fk(q), arm.swivel(q)
    assert not np.any(np.all(_wrapdiff(arm.ik(T, s), q) < 1e-7, axis=1))
    assert np.any(np.all(_wrapdiff(arm.ik(T, s, limits=False), q) < 1e-7, axis=1))
    with pytest.raises(InvalidInputError, match="limits must be True or False"):
        arm.ik(T, s, limits="no")  # type: ignore[arg-type]
    assert arm.ik(T, s, limits=False).shape == (8, 7)
    far = T.copy()
    far[:3, 3] = [5.0, 0.0, 0.0]  # out of reach
    assert arm.ik(far, 0.0, limits=False).shape == (0, 7)


def _fk_ok(arm: SwivelArm, sols: np.ndarray, T: np.ndarray) -> None:
    assert np.all(np.isfinite(sols))
    for sol in sols:
        assert np.max(np.abs(arm.fk(sol) - T)) < 1e-9
        assert np.all(sol >= arm.lower) and np.all(sol <= arm.upper)


@PROP
@given(
    name=st.sampled_from(SWIVEL_ARMS),
    fr=st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7),
    s=st.floats(-math.pi, math.pi),
)
def test_property_every_solution_is_exact_and_in_limits(name: str, fr: list[float], s: float) -> None:
    arm = ARMS[name]
    q = arm.lower + np.array(fr) * (arm.upper - arm.lower)
    T = arm.fk(q)
    sols = arm.ik(T, s)
    assert sols.shape[1] == 7 and len(sols) <= 8
    _fk_ok(arm, sols, T)
    _fk_ok(arm, arm.ik(T, s, all_copies=True), T)
    # away from singular configurations (where theta1/theta3, theta3/theta5 or theta5/theta7 couple)
    # the configuration itself is among the solutions at its own swivel
    if min(abs(math.sin(q[1])), abs(math.sin(q[3])), abs(math.sin(q[5]))) > 1e-3:
        assert _contains(arm.ik(T, arm.swivel(q), all_copies=True), q, atol=1e-6)


@PROP
@given(fr=st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7), s=st.floats(-math.pi, math.pi))
def test_property_batch_equals_scalar(fr: list[float], s: float) -> None:
    arm = ARMS["pa10"]
    q = arm.lower + np.array(fr) * (arm.upper - arm.lower)
    T = arm.fk(q)
    Q, valid = arm.ik_batch(T[None], np.array([s]))
    assert Q.shape == (1, 8, 7) and valid.shape == (1, 8)
    assert np.allclose(Q[0][valid[0]], arm.ik(T, s), atol=1e-9)
    assert np.all(np.isnan(Q[0][~valid[0]]))


def test_batch_many_poses() -> None:
    arm = ARMS["powercube7"]
    Qs = _rand_q(arm, 500, 13)
    Ts = arm.fk_batch(Qs)
    sw = np.array([arm.swivel(q) for q in Qs])
    Q, valid = arm.ik_batch(Ts, sw)
    assert Q.shape == (500, 8, 7)
    for i in range(0, 500, 25):
        assert np.allclose(Q[i][valid[i]], arm.ik(Ts[i], sw[i]), atol=1e-9)
        assert np.any(np.all(_wrapdiff(Q[i][valid[i]], Qs[i]) < 1e-7, axis=1))
    # chunks of any size give the same answers (the PA10's joints 5 and 7 have several copies)
    pa10 = ARMS["pa10"]
    Qp = _rand_q(pa10, 300, 14)
    Qp[::3, 4] = pa10.upper[4]
    Qp[1::3, 6] = pa10.lower[6]
    Tp = pa10.fk_batch(Qp)
    sp = np.array([pa10.swivel(q) for q in Qp])
    Q1, v1 = pa10.ik_batch(Tp, sp)
    Q2, v2 = pa10.ik_batch(Tp, sp, chunk=7)
    assert np.array_equal(v1, v2) and np.array_equal(Q1, Q2, equal_nan=True)
    for i in range(0, 300, 30):
        assert np.allclose(Q1[i][v1[i]], pa10.ik(Tp[i], sp[i]), atol=1e-9)
    far = Ts[:3].copy()
    far[:, :3, 3] = [5.0, 0.0, 0.0]
    _, v2 = arm.ik_batch(far, 0.0)
    assert not v2.any()
    with pytest.raises(InvalidInputError):
        arm.ik_batch(Ts[:, :3], sw)


# ---------------------------------------------------------------------- singular cases
OPEN = dict(lower=[-math.pi] * 7, upper=[math.pi] * 7)


def _pose(p: list[float], R: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    if R is not None:
        T[:3, :3] = R
    return T


@pytest.mark.parametrize("s", [0.0, 0.5, -2.0, math.pi])
def test_zero_pose_stretched_and_aligned(s: float) -> None:
    """q = 0: elbow stretched, elbow on the base axis and wrist aligned, all at once."""
    arm = ARMS["pa10"]
    T = arm.fk(np.zeros(7))
    sols = arm.ik(T, s)
    assert len(sols) >= 1
    _fk_ok(arm, sols, T)
    for sol in sols:  # the swivel still picks the arm plane consistently
        assert abs(math.remainder(arm.swivel(sol) - s, 2 * math.pi)) < 1e-9
    C, n, rho = arm.elbow_circle(T)
    assert rho == pytest.approx(0.0, abs=1e-12) and np.allclose(n, [0, 0, 1])
    assert np.allclose(C, arm.fk_frames(np.zeros(7))[3, :3, 3])  # the circle shrinks to the elbow
    assert np.isfinite(arm.swivel(np.zeros(7)))


def test_stretched_elbow_in_general_direction() -> None:
    arm = ARMS["powercube7"]
    q = np.array([0.7, 0.8, -0.4, 0.0, 0.3, 1.1, -0.2])
    T = arm.fk(q)
    for s in np.linspace(-3, 3, 7):
        sols = arm.ik(T, s)
        assert len(sols) >= 1
        _fk_ok(arm, sols, T)
    assert _contains(arm.ik(T, arm.swivel(q)), q)


def test_folded_elbow() -> None:
    arm = load_arm("pa10", **OPEN)
    q = np.array([0.3, 0.9, 0.2, math.pi, 0.4, 0.5, 0.6])
    T = arm.fk(q)
    for s in (0.0, 1.0, -2.5):
        sols = arm.ik(T, s)
        assert len(sols) >= 1
        _fk_ok(arm, sols, T)


def test_wrist_straight_below_and_above_the_shoulder() -> None:
    arm = load_arm("pa10", **OPEN)
    L1, L2, L3, L4 = arm.link_lengths
    down = np.diag([1.0, -1.0, -1.0])
    for T in (_pose([0, 0, L1 - 0.6 - L4], down), _pose([0, 0, L1 + 0.6 + L4])):
        C, n, rho = arm.elbow_circle(T)
        assert np.all(np.isfinite(C)) and rho > 0
        assert np.allclose(np.abs(n), [0, 0, 1])  # the shoulder-wrist line is the base axis
        for s in (0.0, 0.7, -2.0):
            sols = arm.ik(T, s)
            assert len(sols) >= 1
            _fk_ok(arm, sols, T)
            for sol in sols:
                assert abs(math.remainder(arm.swivel(sol) - s, 2 * math.pi)) < 1e-7


def test_wrist_at_the_shoulder_when_l2_equals_l3() -> None:
    arm = load_arm("pa10", link_lengths=[0.3, 0.4, 0.4, 0.1], **OPEN)
    T = _pose([0.0, 0.0, 0.3 - 0.1], np.diag([1.0, -1.0, -1.0]))
    sols = arm.ik(T, 0.3)
    assert len(sols) >= 1
    _fk_ok(arm, sols, T)


def test_out_of_reach() -> None:
    arm = ARMS["pa10"]
    T = _pose([2.0, 0.0, 0.3])
    assert arm.ik(T, 0.0).shape == (0, 7)
    with pytest.raises(UnreachableError) as err:
        arm.elbow_circle(T)
    assert err.value.distance is not None and err.value.distance > 0.5
    q, info = arm.ik_nearest(T, np.zeros(7))
    assert q is None and info.status is IKStatus.OUT_OF_REACH and "reach" in info.message
    near = _pose([0.0, 0.0, 0.315 + 0.01 + 0.08])  # wrist 1 cm from the shoulder: inside |L2 - L3|
    assert arm.ik(near, 0.0).shape == (0, 7)


def test_bad_swivel_and_u() -> None:
    arm = ARMS["pa10"]
    T = arm.fk(np.full(7, 0.3))
    for bad in (float("nan"), float("inf"), "x"):
        with pytest.raises(InvalidInputError):
            arm.ik(T, bad)  # type: ignore[arg-type]
    for u in ([1.0, 0.0, 0.5], [2.0, 0.0, 0.0], [1.0, 0.0], [np.nan, 0, 0]):
        with pytest.raises(InvalidInputError):
            arm.ik_u(T, u)


# ---------------------------------------------------------------------- ik_nearest
@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_nearest_from_mid_range_seed(name: str) -> None:
    arm = ARMS[name]
    seed = (arm.lower + arm.upper) / 2
    for q in _rand_q(arm, 60, 14):
        T = arm.fk(q)
        qn, info = arm.ik_nearest(T, seed)
        assert info.status is IKStatus.SUCCESS, info.message
        assert info.pos_err < 1e-9 and info.rot_err < 1e-9
        assert np.max(np.abs(arm.fk(qn) - T)) < 1e-9
        assert arm.within_limits(qn)
        assert (
            info.swivel is not None and abs(math.remainder(arm.swivel(qn) - info.swivel, 2 * math.pi)) < 1e-6
        )


@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_nearest_no_flip_next_to_a_solution(name: str) -> None:
    arm = ARMS[name]
    rng = np.random.default_rng(15)
    for q in _rand_q(arm, 150, 16):
        seed = q + rng.normal(0.0, 0.01, 7)
        qn, info = arm.ik_nearest(arm.fk(q), seed)
        assert info.ok
        assert np.max(np.abs(qn - q)) < 0.05  # same branch, same copy, next to q
        d_found = np.sum((qn - seed) ** 2)
        assert d_found <= np.sum((q - seed) ** 2) + 1e-6  # at least as near as the known solution


@pytest.mark.slow
def test_nearest_is_close_to_brute_force_optimum() -> None:
    arm = ARMS["pa10"]
    rng = np.random.default_rng(17)
    for q in _rand_q(arm, 15, 18):
        T = arm.fk(q)
        seed = rng.uniform(arm.lower, arm.upper) * 0.5
        qn, info = arm.ik_nearest(T, seed)
        best = np.inf
        for s in np.linspace(-math.pi, math.pi, 2000, endpoint=False):
            for sol in arm.ik(T, s, all_copies=True):
                best = min(best, float(np.sum((sol - seed) ** 2)))
        assert np.sum((qn - seed) ** 2) <= best + 1e-3


def test_nearest_deterministic_weights_and_failures() -> None:
    arm = ARMS["pa10"]
    q = np.array([0.3, 0.6, -0.4, 1.2, 0.5, -0.7, 0.9])
    T = arm.fk(q)
    a, _ = arm.ik_nearest(T, np.zeros(7))
    b, _ = arm.ik_nearest(T, np.zeros(7))
    assert np.array_equal(a, b)
    w = np.array([100.0, 1, 1, 1, 1, 1, 1])
    c, _ = arm.ik_nearest(T, np.zeros(7), weights=w)
    assert abs(c[0]) <= abs(a[0]) + 1e-9
    # reachable pose, but not with these narrow limits
    narrow = load_arm("pa10", lower=[-0.1] * 7, upper=[0.1] * 7)
    qq, info = narrow.ik_nearest(T, np.zeros(7))
    assert qq is None and info.status is IKStatus.NO_SOLUTION_IN_LIMITS
    for bad_T, bad_seed in ((T * np.nan, np.zeros(7)), (T, np.zeros(6)), (T[:3], np.zeros(7))):
        qq, info = arm.ik_nearest(bad_T, bad_seed)
        assert qq is None and info.status is IKStatus.INVALID_INPUT and info.message
    qq, info = arm.ik_nearest(T, np.zeros(7), weights=[1, 2])
    assert info.status is IKStatus.INVALID_INPUT
