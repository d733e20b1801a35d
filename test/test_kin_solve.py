"""The IK front end (kinematics/solve.py) without ROS: request in, one answer with a status out."""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import pytest
from support.benches import load_bench
from support.waits import HANG_BUDGET_S

from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.self_collision import self_collision, self_collision_batch
from redarm_ros.kinematics import IKStatus, load_arm
from redarm_ros.kinematics.solve import IKFrontEnd, nearest_collision_free

# The collision benchmark's pose set, drawn here on a small scale.
MIXED = load_bench("bench_common").mixed_collision_poses

ARMS = {name: load_arm(name) for name in ("pa10", "powercube6", "powercube7")}
FRONT = IKFrontEnd(ARMS, "pa10", base_move_timeout_s=HANG_BUDGET_S)
PA10 = ARMS["pa10"]
TWO_PI = 2.0 * math.pi


def _solve(T: np.ndarray, arm: str = "pa10", **kw: Any) -> Any:
    opts = {"swivel": None, "seed": [], "all_solutions": False, "timeout_s": HANG_BUDGET_S}
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
                # ... and no feasible swivel is nearer s than it (to the message's 4 decimals)
                gaps = [min((a0 - s) % TWO_PI, (s - b0) % TWO_PI) for iv in ivs for a0, b0 in iv.tolist()]
                named = min((a - s) % TWO_PI, (s - b) % TWO_PI)
                assert named <= min(gaps) + 2e-4, (named, min(gaps))
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
    front = IKFrontEnd({"powercube7": arm}, "powercube7", base_move_timeout_s=HANG_BUDGET_S)

    def broken(*a: Any, **k: Any) -> Any:
        raise ZeroDivisionError("a solver bug")

    monkeypatch.setattr(arm, "ik_nearest", broken)
    ans = front.solve(arm.fk(np.zeros(7)), "", swivel=None, seed=[], all_solutions=False,
                      timeout_s=HANG_BUDGET_S)
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


# ---------------------------------------------------------------------------------------------
# Collision filter and base-move suggestion
# ---------------------------------------------------------------------------------------------
def _wide_pa10() -> Any:
    """A PA10 with +-180 deg joints and a table 0.1 m up: the elbow can dip into it at some swivels, so
    one pose has colliding and collision-free solutions along its self-motion."""
    arm = load_arm("pa10", lower=[-math.pi] * 7, upper=[math.pi] * 7)
    arm.config["self_collision"] = {
        "pairs": [["base", "forearm"], ["base", "hand"], ["upper_arm", "hand"]],
        "ground_z": 0.1,
    }
    return arm


def _mixed_poses(
    arm: Any, model: Any, count: int, seed: int
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(T, a colliding solution of T, all collision-free solutions on a 0.1 deg sweep) for mixed poses."""
    poses = MIXED(arm, model, np.random.default_rng(seed))
    return [(T, rows[np.nonzero(res.colliding)[0][0]], rows[res.free])
            for T, rows, res in itertools.islice(poses, count)]


def test_nearest_collision_free_on_the_swivel_circle_matches_a_dense_sweep() -> None:
    """The seed is a colliding solution of the pose: the answer is collision-free and no farther from the
    seed than the best collision-free solution of a 0.1 deg sweep over all swivels and flip patterns."""
    arm = _wide_pa10()
    front = IKFrontEnd({"wide": arm}, "wide", base_move_timeout_s=HANG_BUDGET_S)
    model = front.models["wide"]
    for T, q_coll, free_rows in _mixed_poses(arm, model, 4, seed=3):
        ans = front.solve(T, "wide", swivel=None, seed=list(q_coll), all_solutions=True,
                          timeout_s=HANG_BUDGET_S)
        assert ans.status is IKStatus.SUCCESS, ans.message
        assert not self_collision(arm, ans.q, model=model).colliding and ans.clearance >= 0.0
        assert ans.position_error < 1e-9 and ans.orientation_error < 1e-9
        sweep = ((arm.nearest_copies(free_rows, q_coll) - q_coll) ** 2).sum(axis=1).min()
        assert ((ans.q - q_coll) ** 2).sum() <= sweep + 1e-9
        assert len(ans.solutions) >= 1
        assert not self_collision_batch(arm, ans.solutions, model=model).colliding.any()
        # with the filter off the colliding seed itself is the answer
        off = front.solve(T, "wide", swivel=None, seed=list(q_coll), all_solutions=False,
                          timeout_s=HANG_BUDGET_S, check_collisions=False)
        assert off.status is IKStatus.SUCCESS and np.max(np.abs(off.q - q_coll)) < 1e-6
        assert math.isnan(off.clearance)


def test_swivel_given_where_every_solution_collides() -> None:
    arm = _wide_pa10()
    front = IKFrontEnd({"wide": arm}, "wide", base_move_timeout_s=HANG_BUDGET_S)
    T, q_coll, _ = _mixed_poses(arm, front.models["wide"], 1, seed=4)[0]
    s = arm.swivel(q_coll)
    ans = front.solve(T, "wide", swivel=s, seed=[], all_solutions=False, timeout_s=HANG_BUDGET_S)
    assert ans.status is IKStatus.ALL_SOLUTIONS_COLLIDE and ans.q is None
    assert "at swivel" in ans.message and "nearest collision-free solution is at swivel" in ans.message
    assert ans.base_offset is None  # other swivels are free: no base move is suggested
    found = nearest_collision_free(arm, T, (arm.lower + arm.upper) / 2.0, front.models["wide"])
    assert found is not None and f"at swivel {found.swivel:.4f} rad" in ans.message
    assert not self_collision(arm, found.q, model=front.models["wide"]).colliding
    off = front.solve(
        T, "wide", swivel=s, seed=[], all_solutions=False, timeout_s=HANG_BUDGET_S, check_collisions=False
    )
    assert off.status is IKStatus.SUCCESS


def test_powercube6_nearest_collision_free_among_its_analytic_solutions() -> None:
    arm = ARMS["powercube6"]
    model = FRONT.models["powercube6"]
    rng = np.random.default_rng(9)
    done = 0
    while done < 5:
        T = arm.fk(rng.uniform(arm.lower, arm.upper))
        sols = arm.ik(T)
        res = self_collision_batch(arm, sols, model=model)
        if not (res.free.any() and res.colliding.any()):
            continue
        seed = sols[np.nonzero(res.colliding)[0][0]]
        ans = _solve(T, "powercube6", seed=list(seed))
        assert ans.status is IKStatus.SUCCESS, ans.message
        free = sols[res.free]
        best = free[np.argmin(((free - seed) ** 2).sum(axis=1))]
        assert np.max(np.abs(ans.q - best)) < 1e-12
        done += 1


@pytest.mark.parametrize("name", ["pa10", "powercube6", "powercube7"])
def test_all_solutions_collide_and_the_flag_that_allows_it(name: str) -> None:
    """A posture with its wrist and tool under the ground plane: every solution collides."""
    arm = ARMS[name]
    q = np.radians([0, 90, 0, 90, 0, 0, 0] if arm.n == 7 else [0, -20, 0, -40, -30, 0])
    T = arm.fk(q)
    ans = _solve(T, name)
    assert ans.status is IKStatus.ALL_SOLUTIONS_COLLIDE and ans.q is None
    assert "ground" in ans.message
    assert ans.base_offset is not None and not ans.base_offset.valid  # no planar move lifts the hand
    assert "below the ground plane" in ans.message
    assert _solve(T, name, check_collisions=False).status is IKStatus.SUCCESS
    ans = _solve(T, name, swivel=arm.swivel(q)) if arm.n == 7 else None
    if ans is not None:
        assert ans.status is IKStatus.ALL_SOLUTIONS_COLLIDE and "every swivel" in ans.message


def test_answers_carry_the_clearance() -> None:
    q = np.array([0.3, 0.6, -0.4, 1.2, 0.5, -0.7, 0.9])
    ans = _solve(PA10.fk(q), seed=list(q))
    assert ans.status is IKStatus.SUCCESS
    assert ans.clearance == pytest.approx(self_collision(PA10, ans.q).min_distance) and ans.clearance > 0


@pytest.mark.parametrize("name", ["pa10", "powercube6", "powercube7"])
def test_out_of_reach_answer_carries_a_base_move_that_solves_it(name: str) -> None:
    arm = ARMS[name]
    T = arm.fk(arm.park).copy()
    T[0, 3] += 1.5  # 1.5 m further ahead
    ans = _solve(T, name)
    assert ans.status in (IKStatus.OUT_OF_REACH, IKStatus.NO_SOLUTION_IN_LIMITS)
    bp = ans.base_offset
    assert bp is not None and bp.valid, ans.message
    assert "moving the base by" in ans.message
    moved = _solve(bp.apply(T), name)
    assert moved.status is IKStatus.SUCCESS, moved.message
    quiet = IKFrontEnd(ARMS, "pa10", suggest_base_move=False)
    ans = quiet.solve(T, name, swivel=None, seed=[], all_solutions=False, timeout_s=HANG_BUDGET_S)
    assert ans.base_offset is None and "moving the base" not in ans.message


def test_swivel_without_in_limit_solution_suggests_no_base_move() -> None:
    """Another swivel solves the pose: the answer points there, not at the base."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        T = PA10.fk(rng.uniform(0.8 * PA10.lower, 0.8 * PA10.upper))
        for s in np.linspace(-3.0, 3.0, 25):
            if len(PA10.ik(T, float(s))) == 0 and any(len(iv) for iv in PA10.feasible_swivels(T)):
                ans = _solve(T, swivel=float(s))
                assert ans.status is IKStatus.NO_SOLUTION_IN_LIMITS and ans.base_offset is None
                return
    pytest.fail("no pose with an infeasible swivel found")


def test_exhaustive_nearest_option_is_passed_to_the_swivel_arms_only() -> None:
    """powercube7, theta6 near 0 at the optimum: the default search stops 2.3e-3 rad^2 short of it, the
    exhaustive one reaches it; the front end's option switches between them (powercube6 has no such
    option and is still answered)."""
    T = np.array(
        [[0.910600131619277, -0.3564056507987097, -0.20924247268110677, -0.20795363860573426],
         [-0.10857586461709254, -0.6948028463106141, 0.7109573027835918, -0.032633788826563724],
         [-0.3987714657765853, -0.6246791311044555, -0.6713846149897807, -0.034022094736451285],
         [0.0, 0.0, 0.0, 1.0]]
    )
    arm = ARMS["powercube7"]
    seed = (arm.lower + arm.upper) / 2
    opts = {"swivel": None, "seed": seed.tolist(), "all_solutions": False, "timeout_s": HANG_BUDGET_S,
            "check_collisions": False}
    exhaustive = IKFrontEnd(ARMS, "pa10", exhaustive_nearest=True, base_move_timeout_s=HANG_BUDGET_S)
    q_fast, _ = arm.ik_nearest(T, seed)
    q_ex, _ = arm.ik_nearest(T, seed, exhaustive=True)
    a_fast = FRONT.solve(T, "powercube7", **opts)
    a_ex = exhaustive.solve(T, "powercube7", **opts)
    assert a_fast.status is IKStatus.SUCCESS and a_ex.status is IKStatus.SUCCESS
    np.testing.assert_allclose(a_fast.q, q_fast, atol=1e-12)
    np.testing.assert_allclose(a_ex.q, q_ex, atol=1e-12)
    assert float(np.sum((q_ex - seed) ** 2)) <= float(np.sum((q_fast - seed) ** 2))
    pc6 = ARMS["powercube6"]
    ans = exhaustive.solve(pc6.fk(pc6.park), "powercube6", **{**opts, "seed": []})
    assert ans.status is IKStatus.SUCCESS, ans.message
