"""The IK front end (kinematics/solve.py) without ROS: request in, one answer with a status out."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import IKStatus, load_arm
from redarm_ros.kinematics.solve import IKFrontEnd

ARMS = {name: load_arm(name) for name in ("pa10", "powercube6", "powercube7")}
FRONT = IKFrontEnd(ARMS, "pa10")
PA10 = ARMS["pa10"]


def _solve(T: np.ndarray, arm: str = "pa10", **kw: Any) -> Any:
    opts = {"swivel": None, "seed": [], "all_solutions": False, "timeout_s": 0.05}
    opts.update(kw)
    return FRONT.solve(T, arm, **opts)


def test_default_arm_must_be_served() -> None:
    with pytest.raises(InvalidInputError, match="default_arm"):
        IKFrontEnd(ARMS, "no_such_arm")


def test_nearest_and_all_solutions() -> None:
    q = np.array([0.3, 0.6, -0.4, 1.2, 0.5, -0.7, 0.9])
    T = PA10.fk(q)
    ans = _solve(T, all_solutions=True, seed=list(q + 0.01))
    assert ans.status is IKStatus.SUCCESS and np.max(np.abs(ans.q - q)) < 0.05
    assert ans.position_error < 1e-9 and ans.orientation_error < 1e-9
    assert ans.joint_names == PA10.joint_names
    assert len(ans.solutions) >= 1
    for row in ans.solutions:  # every solution at the answer's swivel
        assert PA10.pose_error(row, T)[0] < 1e-9
        assert abs(math.remainder(PA10.swivel(row) - ans.swivel, 2 * math.pi)) < 1e-6


def test_at_swivel_calls_ik_once_and_picks_the_copy_nearest_the_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    """PA10 joint 7 (+-360 deg) has two in-limit copies: a seed near the other copy gets that one."""
    q = np.array([0.1, 0.4, -0.3, 1.0, math.radians(200), 0.5, math.radians(300)])
    T = PA10.fk(q)
    calls = []
    real = PA10.ik

    def spy(*a: Any, **k: Any) -> np.ndarray:
        calls.append((a, k))
        return real(*a, **k)

    monkeypatch.setattr(PA10, "ik", spy)
    ans = _solve(T, swivel=PA10.swivel(q), seed=list(q), all_solutions=True)
    assert len(calls) == 1
    assert ans.status is IKStatus.SUCCESS and np.max(np.abs(ans.q - q)) < 1e-7
    assert len(ans.solutions) >= 1 and np.all(np.abs(ans.solutions[:, 6]) <= math.pi)  # copies near 0 there


def test_at_swivel_without_solution_names_the_nearest_feasible_swivels() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        T = PA10.fk(rng.uniform(0.8 * PA10.lower, 0.8 * PA10.upper))
        ivs = [iv for iv in PA10.feasible_swivels(T) if len(iv)]
        for s in np.linspace(-3.0, 3.0, 25):
            if len(PA10.ik(T, float(s))) == 0 and ivs:
                ans = _solve(T, swivel=float(s))
                assert ans.status is IKStatus.NO_SOLUTION_IN_LIMITS and ans.q is None
                assert "nearest in-limit swivels" in ans.message
                a, b = (float(v) for v in ans.message.split("[")[1].split("]")[0].split(","))
                assert len(PA10.ik(T, 0.5 * (a + b))) >= 1  # the named interval has solutions
                return
    pytest.fail("no pose with an infeasible swivel found")


def test_statuses_for_bad_and_unreachable_requests() -> None:
    T = PA10.fk(np.full(7, 0.3))
    far = np.eye(4)
    far[:3, 3] = (3.0, 0.0, 0.5)
    assert _solve(far).status is IKStatus.OUT_OF_REACH
    assert _solve(far, swivel=0.3).status is IKStatus.OUT_OF_REACH
    assert _solve(T, arm="no_such_arm").status is IKStatus.INVALID_INPUT
    assert _solve(T, seed=[0.0] * 3).status is IKStatus.INVALID_INPUT
    assert _solve(T, seed=[math.nan] * 7).status is IKStatus.INVALID_INPUT
    assert _solve(T, swivel=math.nan).status is IKStatus.INVALID_INPUT
    ans = _solve(ARMS["powercube6"].fk(np.zeros(6)), arm="powercube6", swivel=0.2)
    assert ans.status is IKStatus.INVALID_INPUT and "swivel" in ans.message
    # a seed outside the limits is a preference, not an error
    assert _solve(T, seed=[10.0] * 7).status is IKStatus.SUCCESS


def test_internal_error_is_not_invalid_input(monkeypatch: pytest.MonkeyPatch) -> None:
    arm = load_arm("powercube7")
    front = IKFrontEnd({"powercube7": arm}, "powercube7")

    def broken(*a: Any, **k: Any) -> Any:
        raise ZeroDivisionError("a solver bug")

    monkeypatch.setattr(arm, "ik_nearest", broken)
    ans = front.solve(arm.fk(np.zeros(7)), "", swivel=None, seed=[], all_solutions=False, timeout_s=0.05)
    assert ans.status is IKStatus.INTERNAL_ERROR and "ZeroDivisionError" in ans.message


def test_timeout_is_passed_to_the_search_and_honoured() -> None:
    rng = np.random.default_rng(6)
    statuses = set()
    for _ in range(40):
        T = PA10.fk(rng.uniform(PA10.lower, PA10.upper))
        ans = _solve(T, seed=list(rng.uniform(PA10.lower, PA10.upper)), timeout_s=1e-9)
        statuses.add(ans.status)
        assert ans.q is not None and PA10.pose_error(ans.q, T)[0] < 1e-9
    assert IKStatus.TIMEOUT in statuses
    assert _solve(PA10.fk(np.zeros(7)), timeout_s=0.0).status is IKStatus.INVALID_INPUT
