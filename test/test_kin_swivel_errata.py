"""The printed errata of the swivel paper (Moore & Oztop) that docs/kinematics.md lists, checked against
the closed-form IK on all 8 flip patterns: eq. 11 as printed, eq. 12 as printed and corrected, the
branch condition, and the angle of eq. 14's shortest rotation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import qmul, qrotate, shortest_rotation

# joint limits opened to +-pi so that ik returns all 8 flip patterns at every swivel
ARM = load_arm("pa10", lower=[-math.pi] * 7, upper=[math.pi] * 7)


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# R[i, j] below is the paper's R(i+1, j+1): the paper counts from 1
def eq11_printed(R: np.ndarray) -> tuple[float, float, float]:
    return (
        math.atan2(R[1, 2], R[0, 2]),
        math.atan2(math.hypot(R[0, 2], R[1, 2]), R[2, 2]),
        math.atan2(R[2, 1], -R[2, 0]),
    )


def eq12_printed(R: np.ndarray) -> tuple[float, float, float]:
    return (
        math.atan2(-R[1, 2], -R[0, 2]),
        math.atan2(-math.hypot(R[0, 2], R[1, 2]), R[2, 2]),
        math.atan2(-R[2, 1], -R[2, 0]),
    )


def eq12_corrected(R: np.ndarray) -> tuple[float, float, float]:
    a1, a2, _ = eq12_printed(R)
    return a1, a2, math.atan2(-R[2, 1], R[2, 0])


def _same(a: float, b: float) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) < 1e-9


def _branch_triples() -> list[tuple[str, int, tuple[float, float, float]]]:
    """(spherical joint, flip pattern, (first, middle, last) angle) of every solution of random poses."""
    rng = np.random.default_rng(0)
    out = []
    for _ in range(60):
        T = ARM.fk(rng.uniform(-2.5, 2.5, 7))
        sols = ARM.ik(T, float(rng.uniform(-math.pi, math.pi)))
        assert len(sols) == 8
        for b, q in enumerate(sols):
            out.append(("shoulder", b, (q[0], q[1], q[2])))
            out.append(("wrist", b, (q[4], q[5], q[6])))
    return out


TRIPLES = _branch_triples()


def test_every_pattern_has_both_signs_of_the_last_angle() -> None:
    """So a rule keyed on the sign of theta3 (theta7) is really tested on every pattern."""
    for joint in ("shoulder", "wrist"):
        for b in range(8):
            signs = {t[2] >= 0 for j, bb, t in TRIPLES if j == joint and bb == b}
            assert signs == {True, False}, (joint, b)


def test_eq11_gives_the_patterns_with_a_positive_middle_angle() -> None:
    """Eq. 11 reproduces theta1..3 (theta5..7) exactly where theta2 (theta6) > 0, whatever the sign of
    theta3: its condition "theta3 in [0, pi]" belongs to theta2."""
    for joint, b, t in TRIPLES:
        R = _rz(t[0]) @ _ry(t[1]) @ _rz(t[2])
        got = eq11_printed(R)
        assert all(_same(g, v) for g, v in zip(got, t, strict=True)) == (t[1] > 0), (joint, b)


def test_eq12_as_printed_gives_pi_minus_theta3() -> None:
    """Where theta2 < 0, printed eq. 12 has theta1 and theta2 right but returns pi - theta3 for theta3
    (right only at theta3 = +-pi/2); the corrected last line atan2(-R(3,2), R(3,1)) is exact."""
    n_neg = 0
    for _, _, t in TRIPLES:
        if t[1] >= 0:
            continue
        n_neg += 1
        R = _rz(t[0]) @ _ry(t[1]) @ _rz(t[2])
        p = eq12_printed(R)
        assert _same(p[0], t[0]) and _same(p[1], t[1])
        assert _same(p[2], math.pi - t[2]) and not _same(p[2], t[2])
        c = eq12_corrected(R)
        assert all(_same(g, v) for g, v in zip(c, t, strict=True))
    assert n_neg == len(TRIPLES) // 2  # half of the 8 patterns flip theta2 (and half theta6)


def test_flip_pattern_sets_the_sign_of_theta2_and_theta6() -> None:
    """The implementation's pattern bits (f2, f4, f6): f2 set <=> theta2 < 0, f6 set <=> theta6 < 0."""
    for joint, b, t in TRIPLES:
        bit = (b >> 2) & 1 if joint == "shoulder" else b & 1
        assert (t[1] < 0) == bool(bit)


@pytest.mark.parametrize("seed", range(5))
def test_eq14_rotation_angle_is_the_angle_between_k_and_n(seed: int) -> None:
    """qA (eq. 14) turns k onto n about k x n by acos(k . n), not by the swivel angle s."""
    n = np.random.default_rng(seed).normal(size=3)
    n /= np.linalg.norm(n)
    qa = shortest_rotation(n)
    assert np.allclose(qrotate(qa, [0.0, 0.0, 1.0]), n, atol=1e-12)
    angle = 2.0 * math.atan2(float(np.linalg.norm(qa[1:])), float(qa[0]))
    assert angle == pytest.approx(math.acos(n[2]), abs=1e-12)
    axis = qa[1:] / np.linalg.norm(qa[1:])
    k_x_n = np.cross([0.0, 0.0, 1.0], n)
    assert np.allclose(axis, k_x_n / np.linalg.norm(k_x_n), atol=1e-12)


def test_one_sided_product_turns_u_by_epsilon() -> None:
    """r+ u with r+ = cos(e) + sin(e) k turns a u in the xy plane by e (not 2e): r+ u and r- u are 2e
    apart, the same span as s +- e. The sandwich r u r* would turn by 2e."""
    e, s = 0.01, 0.7
    u = np.array([0.0, math.cos(s), math.sin(s), 0.0])
    rp = np.array([math.cos(e), 0.0, 0.0, math.sin(e)])
    v = qmul(rp, u)
    assert abs(v[0]) < 1e-15 and math.atan2(v[2], v[1]) == pytest.approx(s + e, abs=1e-12)
    w = qrotate(rp, u[1:])
    assert math.atan2(w[1], w[0]) == pytest.approx(s + 2 * e, abs=1e-12)
