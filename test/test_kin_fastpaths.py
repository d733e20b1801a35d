"""Fast paths of the closed-form IK against the general computations they replace (same values, bit for bit).

Each reference below is the previous general code, kept here: the fast path must give exactly its values on
random poses and swivels and on hand-made edge values (angles at +-pi, 0 and the limits).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import SwivelArm, load_arm
from redarm_ros.kinematics.feasible import ALT_SIGN
from redarm_ros.kinematics.swivel import _PATTERN_GET

SWIVEL_ARMS = ["pa10", "pa10_7c", "powercube7"]
ARMS = {name: load_arm(name) for name in SWIVEL_ARMS}
PI, TWO_PI = math.pi, 2.0 * math.pi


def _expand_reference(arm: SwivelArm, base: tuple[float, ...]) -> list[tuple[float, ...]]:
    """The previous general loop of ``_expand`` (all_copies=False): every alternative wrapped by round."""
    t1, t2, t3, t4, t5, t6, t7 = base
    alts = ((t1, t1 + PI), (t2, -t2), (t3, t3 + PI), (t4, -t4), (t5, t5 + PI), (t6, -t6), (t7, t7 + PI))
    vals: list[float | None] = []
    for (a, b), (lot, upt, lo, up), wide in zip(alts, arm._lims, arm._wide, strict=True):  # noqa: SLF001
        for x in (a, b):
            v = x - TWO_PI * round(x / TWO_PI)
            if lot <= v <= upt:
                vals.append(lo if v < lo else (up if v > up else v))
            else:
                vals.append(arm._fit0(len(vals) >> 1, x) if wide else None)  # noqa: SLF001
    return [row for row in (get(vals) for get in _PATTERN_GET) if None not in row]


def _bits(rows: list) -> list[list[int]]:
    return [[int(np.float64(v).view(np.int64)) for v in r] for r in rows]


def _edge_bases(arm: SwivelArm, rng: np.random.Generator, n: int) -> list[tuple[float, ...]]:
    """Base solutions as ik makes them (pivots in [-pi, pi], hinges in [0, pi]) with edge values mixed in."""
    piv = [-PI, PI, 0.0, -0.0, math.nextafter(PI, 0.0), math.nextafter(-PI, 0.0), PI / 2, -PI / 2]
    hin = [0.0, PI, math.nextafter(PI, 0.0), 5e-324, PI / 2]
    piv += [float(v) for v in np.concatenate([arm.lower, arm.upper]) if -PI <= v <= PI]
    piv += [float(v - PI) for v in np.concatenate([arm.lower, arm.upper]) if 0.0 <= v - PI <= PI]
    hin += [abs(float(v)) for v in np.concatenate([arm.lower, arm.upper]) if abs(v) <= PI]
    out = []
    for _ in range(n):
        b = [
            float(rng.choice(piv)) if rng.random() < 0.3 else float(rng.uniform(-PI, PI))
            if j % 2 == 0
            else (float(rng.choice(hin)) if rng.random() < 0.3 else float(rng.uniform(0.0, PI)))
            for j in range(7)
        ]
        out.append(tuple(b))
    return out


@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_expand_equals_general_loop(name: str) -> None:
    arm = ARMS[name]
    rng = np.random.default_rng(11)
    Q = rng.uniform(arm.lower, arm.upper, (300, 7))
    bases = []
    for T, s in zip(arm.fk_batch(Q), rng.uniform(-4.0, 4.0, 300), strict=True):
        b = arm._base_solution(arm.check_pose(T), math.cos(s), math.sin(s))  # noqa: SLF001
        assert isinstance(b, tuple)
        bases.append(b)
    bases += _edge_bases(arm, rng, 3000)
    n_rows = 0
    for b in bases:
        got, ref = arm._expand(b), _expand_reference(arm, b)  # noqa: SLF001
        assert _bits(got) == _bits(ref), b
        n_rows += len(ref)
    assert n_rows > len(bases)  # (the sets are not trivially empty)


@pytest.mark.parametrize("name", SWIVEL_ARMS)
def test_ik_numpy_swivel_same_as_float(name: str) -> None:
    arm = ARMS[name]
    rng = np.random.default_rng(12)
    for q, s in zip(rng.uniform(arm.lower, arm.upper, (50, 7)), rng.uniform(-10.0, 10.0, 50), strict=True):
        T = arm.fk(q)
        a, b = arm.ik(T, np.float64(s)), arm.ik(T, float(s))
        assert a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))
    T = arm.fk(q)
    for bad in (np.float64("nan"), np.float64("inf"), np.float64(2e6), float("nan")):
        with pytest.raises(InvalidInputError):
            arm.ik(T, bad)
    with pytest.raises(InvalidInputError):
        arm.ik(T, True)  # noqa: FBT003 - bools are refused


def test_feasible_module_constants_unchanged() -> None:
    # (the fast paths rely on these: base alternatives even, flipped odd)
    assert ALT_SIGN.tolist() == [[1.0, 1.0 if j % 2 == 0 else -1.0] for j in range(7)]


def test_check_pose_rotation_range_each_entry() -> None:
    # the written-out range test of check_pose: each rotation entry alone NaN, inf or beyond 2 is refused,
    # as by the former all() over the nine entries
    T = ARMS["pa10"].fk(np.zeros(7))
    assert ARMS["pa10"].check_pose(T) == T.tolist()
    for i in range(3):
        for j in range(3):
            for bad in (math.nan, math.inf, -math.inf, 2.5, -2.5):
                Tb = T.copy()
                Tb[i, j] = bad
                with pytest.raises(InvalidInputError):
                    SwivelArm.check_pose(Tb)
