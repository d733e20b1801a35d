"""kinematics/base_placement: moving the base by the suggestion makes the pose solvable (every arm), with
the elbow in the optimal region (phi4 = 0 for powercube6, elbow mid-range for the 7-DOF arms) at the
smallest displacement; the yaw, the hopeless cases, the hint sentence and the command line."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from support.benches import load_bench
from support.waits import HANG_BUDGET_S

from redarm_ros.geometry.self_collision import self_collision
from redarm_ros.kinematics import IKStatus, load_arm
from redarm_ros.kinematics.base_placement import (
    base_move_hint,
    main,
    planar_transform,
    suggest_base_move,
    wrist_point,
)
from redarm_ros.kinematics.model import transform_from_xyz_rpy
from redarm_ros.kinematics.solve import IKFrontEnd

# The collision benchmark's unsolvable poses, drawn here on a small scale.
SHIFTED = load_bench("bench_common").shifted_poses

ARMS = ["pa10", "pa10_7c", "powercube6", "powercube7"]
LOADED = {n: load_arm(n) for n in ARMS}
FRONT = IKFrontEnd(LOADED, "pa10", suggest_base_move=False)


def _solve(T: np.ndarray, arm: str) -> object:
    return FRONT.solve(T, arm, swivel=None, seed=[], all_solutions=False, timeout_s=HANG_BUDGET_S)


def _unsolvable_poses(name: str, count: int, seed: int) -> list[np.ndarray]:
    """Poses of collision-free postures shifted sideways by 0.4-1.2 m until the arm cannot solve them."""
    poses = SHIFTED(LOADED[name], np.random.default_rng(seed))
    return list(itertools.islice((T for T in poses if _solve(T, name).status is not IKStatus.SUCCESS), count))


@pytest.mark.parametrize("name", ARMS)
def test_moving_the_base_by_the_suggestion_makes_the_pose_solvable(name: str) -> None:
    arm = LOADED[name]
    optimal = 0
    for T in _unsolvable_poses(name, 12, seed=5):
        bp = suggest_base_move(arm, T, timeout_s=HANG_BUDGET_S)
        assert bp.valid, bp.message
        T2 = bp.apply(T)
        assert np.allclose(planar_transform(bp.x, bp.y, bp.yaw) @ T2, T, atol=1e-12)
        assert np.allclose(bp.transform() @ T2, T, atol=1e-12)
        assert T2[2, 3] == pytest.approx(T[2, 3])  # a planar move keeps the height
        ans = _solve(T2, name)  # the service's own solve, collision filter on
        assert ans.status is IKStatus.SUCCESS, ans.message
        # the returned solution reaches the moved target, inside the limits, collision-free
        assert arm.pose_error(bp.q, T2)[0] < 1e-9 and arm.pose_error(bp.q, T2)[1] < 1e-9
        assert arm.within_limits(bp.q) and not self_collision(arm, bp.q).colliding
        # ... with the elbow at the placement's value
        assert abs(abs(bp.q[3]) - bp.elbow) < 1e-6
        optimal += bp.optimal
    assert optimal >= 6  # most of these land in the optimal region itself


@pytest.mark.parametrize("name", ["pa10", "pa10_7c", "powercube7"])
def test_seven_dof_suggestion_is_the_nearest_point_of_the_elbow_circle(name: str) -> None:
    """The base lies on the circle of shoulder positions at the placement's elbow value; the smallest
    displacement is the circle's point nearest the current base, | |W_xy| - h |."""
    arm = LOADED[name]
    L1, L2, L3, L4 = arm.link_lengths
    mid = 0.5 * float(arm.upper[3])
    at_nearest = 0
    for T in _unsolvable_poses(name, 10, seed=6):
        bp = suggest_base_move(arm, T, timeout_s=HANG_BUDGET_S)
        assert bp.valid, bp.message
        if bp.optimal:
            assert bp.elbow == pytest.approx(mid)
        W = wrist_point(arm, T)
        d = math.sqrt(L2 * L2 + L3 * L3 + 2 * L2 * L3 * math.cos(bp.elbow))
        h = math.sqrt(d * d - (W[2] - L1) ** 2)
        nearest = abs(math.hypot(W[0], W[1]) - h)
        assert bp.distance >= nearest - 1e-9
        at_nearest += abs(bp.distance - nearest) < 1e-9
    assert at_nearest >= 8


def test_powercube6_out_of_reach_straight_ahead() -> None:
    """1.2 m ahead, approach along +x: the base moves forward until phi4 = 0 reaches it, by the closed
    form x = W_x - (L1 + sqrt((L23 + L4)^2 - W_z^2))."""
    arm = LOADED["powercube6"]
    L1, L23, L4, L56 = arm.link_lengths
    T = np.eye(4)
    T[:3, 3] = (1.2, 0.0, 0.1)
    assert _solve(T, "powercube6").status is IKStatus.OUT_OF_REACH
    bp = suggest_base_move(arm, T, timeout_s=HANG_BUDGET_S)
    wx = 1.2 - L56
    assert bp.valid and bp.optimal and bp.yaw == 0.0
    assert bp.x == pytest.approx(wx - (L1 + math.sqrt((L23 + L4) ** 2 - 0.1**2)), abs=1e-12)
    assert bp.y == pytest.approx(0.0, abs=1e-12)
    # the optimal region: phi4 = 0 (acos at the stretched 2R's reach boundary: ~sqrt(eps) round-off)
    assert bp.q[3] == pytest.approx(0.0, abs=1e-6)
    assert _solve(bp.apply(T), "powercube6").status is IKStatus.SUCCESS


def test_powercube6_approach_outside_the_arm_plane_is_fixed_by_a_sideways_move() -> None:
    """With joint 3 locked the approach must lie in the arm's vertical plane: a reachable position with a
    sideways approach is OUT_OF_REACH; the base moves onto the vertical plane through the approach."""
    arm = LOADED["powercube6"]
    T = transform_from_xyz_rpy((0.5, 0.0, 0.2), (0.0, 0.0, 0.6))  # approach turned 0.6 rad off radial
    ans = _solve(T, "powercube6")
    assert ans.status is IKStatus.OUT_OF_REACH and "arm plane" in ans.message
    bp = suggest_base_move(arm, T, timeout_s=HANG_BUDGET_S)
    assert bp.valid and bp.optimal
    a = T[:3, 0]
    W = wrist_point(arm, T)
    # the moved base lies on the vertical plane through the approach axis
    cross = (W[0] - bp.x) * a[1] - (W[1] - bp.y) * a[0]
    assert abs(cross) < 1e-9
    assert _solve(bp.apply(T), "powercube6").status is IKStatus.SUCCESS


def test_yaw_is_suggested_only_when_no_translation_works_nearby() -> None:
    """A target right behind the powercube6 (joint 1 reaches +-170 deg): the nearest placement needs the
    base turned; without yaw the suggestion is a larger move or none."""
    arm = LOADED["powercube6"]
    T = transform_from_xyz_rpy((-0.9, 0.0, 0.1), (0.0, 0.0, math.pi))  # approach pointing away, along -x
    with_yaw = suggest_base_move(arm, T, timeout_s=HANG_BUDGET_S)
    assert with_yaw.valid and abs(with_yaw.yaw) > 0.1
    assert _solve(with_yaw.apply(T), "powercube6").status is IKStatus.SUCCESS
    no_yaw = suggest_base_move(arm, T, allow_yaw=False, timeout_s=HANG_BUDGET_S)
    assert no_yaw.yaw == 0.0
    assert (not no_yaw.valid) or no_yaw.distance > with_yaw.distance
    if no_yaw.valid:
        assert _solve(no_yaw.apply(T), "powercube6").status is IKStatus.SUCCESS


@pytest.mark.parametrize("name", ARMS)
def test_hopeless_poses_are_invalid_with_a_reason(name: str) -> None:
    arm = LOADED[name]
    high = np.eye(4)
    high[:3, 3] = (0.3, 0.2, 3.0)  # far above anything the arm can reach from any base position
    bp = suggest_base_move(arm, high, timeout_s=HANG_BUDGET_S)
    assert not bp.valid and "above the shoulder" in bp.message
    assert bp.describe().startswith("no base move found")
    low = np.eye(4)
    low[:3, 3] = (0.6, 0.0, -0.5)  # below the ground plane: a planar move keeps every height
    bp = suggest_base_move(arm, low, timeout_s=HANG_BUDGET_S)
    assert not bp.valid and "below the ground plane" in bp.message


def test_timeout_gives_an_invalid_answer_saying_so() -> None:
    arm = LOADED["pa10"]
    T = _unsolvable_poses("pa10", 1, seed=8)[0]
    bp = suggest_base_move(arm, T, timeout_s=0.0)
    assert not bp.valid and "time budget" in bp.message


def test_collision_check_can_be_switched_off() -> None:
    """Below the ground plane but otherwise reachable from elsewhere: only the check refuses it."""
    arm = LOADED["pa10"]
    T = transform_from_xyz_rpy((1.4, 0.0, -0.02), (0.0, math.pi, 0.0))  # tool pointing down, into the table
    refused = suggest_base_move(arm, T, timeout_s=HANG_BUDGET_S)
    assert not refused.valid and "below the ground plane" in refused.message
    bp = suggest_base_move(arm, T, check_collisions=False, timeout_s=HANG_BUDGET_S)
    assert bp.valid and arm.pose_error(bp.q, bp.apply(T))[0] < 1e-9


def test_hint_sentence() -> None:
    arm = LOADED["powercube6"]
    T = np.eye(4)
    T[:3, 3] = (1.2, 0.0, 0.1)
    hint = base_move_hint(arm, T)
    assert hint.startswith("moving the base by x = ") and "phi4 = 0.0 deg (the optimal region)" in hint
    assert "base first" in hint
    bad = np.eye(4)
    bad[0, 0] = 2.0
    assert base_move_hint(arm, bad).startswith("no base move computed")


def test_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--arm", "powercube6", "1.2", "0.0", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "base move: x = 0.2793 m, y = 0.0000 m" in out and "phi4 = 0.00 deg (optimal region)" in out
    assert main(["--arm", "pa10", "1.5", "0.3", "0.4", "--quat", "1", "0", "0", "0"]) == 0
    assert "|theta4|" in capsys.readouterr().out
    assert main(["--arm", "powercube6", "0.2", "0.2", "3.0"]) == 1
    assert "no base move found" in capsys.readouterr().out
    assert main(["--arm", "powercube6", "0.2", "0.2", "0.3", "--quat", "0", "0", "0", "0"]) == 2
