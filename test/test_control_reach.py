"""ReachController: reaching, obstacle avoidance, continuity, limits, goal rejection, retargeting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.obstacles import ArmCapsules, Cylinder, Scene, load_scene, min_distance
from redarm_ros.control.reach_controller import (
    ControllerParams,
    GoalStatus,
    Phase,
    ReachController,
)
from redarm_ros.control.simulate import evaluate, run_controller
from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.kinematics import load_arm

DT = 0.01


def pose(p, yaw: float = 0.0) -> np.ndarray:
    """Tool at p pointing down, rotated by yaw about the vertical."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = p
    return T


@pytest.fixture(scope="module")
def arm():
    return load_arm("pa10")


@pytest.fixture(scope="module")
def q_start(arm):
    """Hand down at (0.3, 0.3, 0.15), elbow up: a start left of the table centre."""
    q, info = arm.ik_nearest(pose([0.3, 0.3, 0.15]), np.array([0.8, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    return q


def check_trajectory(arm, q: np.ndarray) -> None:
    """Joint limits hold, and no step exceeds the joint velocity limits (so no branch flip)."""
    assert np.all(q >= arm.lower - 1e-12) and np.all(q <= arm.upper + 1e-12)
    steps = np.abs(np.diff(q, axis=0)) / (np.asarray(arm.max_vel) * DT)
    assert steps.max() <= 1.0 + 1e-6


def test_reaches_goal_on_empty_table_with_straight_path(arm, q_start) -> None:
    scene = load_scene("table_empty")
    ctl = ReachController(arm, scene)
    ctl.reset(q_start)
    assert ctl.phase is Phase.IDLE
    T = pose([0.65, -0.15, 0.08], 0.3)
    tr = run_controller(ctl, T, 8.0, DT)
    m = evaluate(arm, scene, tr.q, T, DT, tr.step_s, tr.reached_at)
    assert m.reached and tr.phase[-1] == "REACHED"
    assert m.pos_err < 1e-3 and m.ori_err < 0.01
    assert m.collision_free
    assert m.path_ratio < 1.02  # human-like straight path
    check_trajectory(arm, tr.q)
    # the commanded q really realises the commanded pose
    r = ctl.step(DT)
    assert np.allclose(arm.fk(r.q)[:3, 3], r.position, atol=1e-9)


def test_avoids_a_can_on_the_table(arm, q_start) -> None:
    scene = load_scene("table_cylinder")
    T = pose([0.65, -0.15, 0.08])
    # The straight line from the start to the goal runs through the can.
    p0 = arm.fk(q_start)[:3, 3]
    line = [p0 + t * (T[:3, 3] - p0) for t in np.linspace(0, 1, 200)]
    assert min(scene.obstacles[0].signed_distance(p) for p in line) < 0
    ctl = ReachController(arm, scene)
    ctl.reset(q_start)
    tr = run_controller(ctl, T, 8.0, DT)
    m = evaluate(arm, scene, tr.q, T, DT)
    assert m.reached
    assert m.min_clearance > 0.0  # recomputed from the joint trajectory, every step
    assert np.nanmin(tr.clearance) > 0.0  # and the controller's own report agrees
    check_trajectory(arm, tr.q)
    # it went above the can, not below or through it
    can = scene.obstacles[0]
    near = np.linalg.norm(tr.tool[:, :2] - np.asarray(can.center[:2]), axis=1) < can.radius
    assert np.all(tr.tool[near, 2] > can.top)


def test_fixed_swivel_mode_keeps_the_elbow(arm, q_start) -> None:
    ctl = ReachController(arm, load_scene("table_empty"), ControllerParams(swivel_mode="fixed"))
    ctl.reset(q_start)
    s0 = ctl.swivel
    tr = run_controller(ctl, pose([0.6, 0.0, 0.12]), 6.0, DT)
    assert np.allclose(tr.swivel, s0, atol=1e-12)


def test_swivel_dynamics_moves_elbow_away_from_an_obstacle(arm) -> None:
    """Hold the hand still; an obstacle placed at the elbow makes the swivel move and clear it."""
    q0, info = arm.ik_nearest(pose([0.55, 0.0, 0.2]), np.array([0.0, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    ctl = ReachController(arm, Scene((), 0.0))
    ctl.reset(q0)
    ctl.set_goal(arm.fk(q0))
    for _ in range(200):  # settle at the preferred swivel
        r = ctl.step(DT)
    elbow = arm.key_points(r.q)[2]
    ball = Cylinder((elbow[0] + 0.02, elbow[1] + 0.13, elbow[2]), 0.05, 0.1)
    before = min_distance(arm, r.q, Scene((ball,), 0.0)).distance
    ctl.set_scene(Scene((ball,), 0.0))
    s_before = r.swivel
    qs = [r.q]
    for _ in range(300):
        r = ctl.step(DT)
        qs.append(r.q)
    after = min_distance(arm, r.q, Scene((ball,), 0.0)).distance
    assert abs(r.swivel - s_before) > 0.1
    assert after > before + 0.03
    assert np.linalg.norm(arm.fk(r.q)[:3, 3] - arm.fk(q0)[:3, 3]) < 1e-3  # the hand stayed
    check_trajectory(arm, np.array(qs))


def test_goal_rejections(arm, q_start) -> None:
    scene = load_scene("table_cylinder")
    ctl = ReachController(arm, scene)
    assert ctl.set_goal(pose([0.6, 0.0, 0.1])).status is GoalStatus.NOT_READY
    with pytest.raises(InvalidInputError):
        ctl.step(DT)
    ctl.reset(q_start)
    far = ctl.set_goal(pose([1.5, 0.0, 0.3]))
    assert far.status is GoalStatus.OUT_OF_REACH and "reach" in far.message
    assert ctl.phase is Phase.REJECTED
    inside = ctl.set_goal(pose([0.5, 0.0, 0.1]))  # inside the can
    assert inside.status is GoalStatus.IN_COLLISION and "can" in inside.message
    below = ctl.set_goal(pose([0.6, 0.2, -0.05]))
    assert below.status is GoalStatus.IN_COLLISION and "table" in below.message
    bad = np.eye(4)
    bad[0, 0] = math.nan
    assert ctl.set_goal(bad).status is GoalStatus.INVALID_INPUT
    skew = pose([0.6, 0.2, 0.1])
    skew[:3, :3] *= 1.1
    assert ctl.set_goal(skew).status is GoalStatus.INVALID_INPUT
    # after rejections the arm holds still
    q_hold = ctl.q
    for _ in range(20):
        r = ctl.step(DT)
    assert r.phase is Phase.REJECTED and np.array_equal(r.q, q_hold) and r.message


def test_goal_outside_joint_limits_is_rejected(arm, q_start) -> None:
    ctl = ReachController(arm, Scene())
    ctl.reset(q_start)
    # Straight down right next to the base: the wrist would be inside the elbow-limit shell.
    check = ctl.check_goal(pose([0.05, 0.0, 0.45]))
    assert check.status in (GoalStatus.NO_SOLUTION_IN_LIMITS, GoalStatus.OUT_OF_REACH)
    assert check.message


def test_retargets_smoothly_mid_motion(arm, q_start) -> None:
    scene = Scene((), 0.0)
    ctl = ReachController(arm, scene)
    ctl.reset(q_start)
    T1, T2 = pose([0.65, -0.2, 0.1]), pose([0.5, 0.1, 0.25], 0.5)
    tr = run_controller(ctl, T1, 8.0, DT, events=[(0.8, lambda c: c.set_goal(T2))])
    m = evaluate(arm, scene, tr.q, T2, DT)
    assert m.reached
    check_trajectory(arm, tr.q)
    speed = np.linalg.norm(np.diff(tr.tool, axis=0), axis=1) / DT
    k = int(0.8 / DT)
    assert speed[k - 5] > 0.1  # it was moving when the goal changed
    # speed stays continuous across the switch (no stop, no jump)
    assert np.max(np.abs(np.diff(speed[k - 10:k + 10]))) < 0.05


def test_rejected_goal_mid_motion_stops_smoothly(arm, q_start) -> None:
    ctl = ReachController(arm, Scene((), 0.0))
    ctl.reset(q_start)
    ctl.set_goal(pose([0.65, -0.2, 0.1]))
    for _ in range(60):
        r = ctl.step(DT)
    assert r.speed > 0.1
    assert not ctl.set_goal(pose([2.0, 0.0, 0.1])).accepted
    speeds = []
    qs = [r.q]
    for _ in range(100):
        r = ctl.step(DT)
        speeds.append(r.speed)
        qs.append(r.q)
    assert speeds[-1] == 0.0 and r.phase is Phase.REJECTED
    assert np.max(np.abs(np.diff(speeds))) < 0.05
    check_trajectory(arm, np.array(qs))


def test_obstacle_appearing_mid_reach_invalidating_the_goal(arm, q_start) -> None:
    ctl = ReachController(arm, Scene((), 0.0))
    ctl.reset(q_start)
    ctl.set_goal(pose([0.65, -0.15, 0.08]))
    for _ in range(30):
        ctl.step(DT)
    check = ctl.set_scene(Scene((Cylinder((0.65, -0.15, 0.1), 0.05, 0.2, "box"),), 0.0))
    assert check is not None and check.status is GoalStatus.IN_COLLISION
    assert ctl.phase is Phase.REJECTED
    assert ctl.set_scene(Scene((), 0.0)) is None


def test_powercube7_reaches_too() -> None:
    arm = load_arm("powercube7")
    q0 = np.clip(np.array([0.3, 0.7, 0.0, 1.2, 0.0, 0.9, 0.0]), arm.lower, arm.upper)
    T0 = arm.fk(q0)
    T = T0.copy()
    T[:3, 3] += np.array([0.05, -0.12, -0.06])
    ctl = ReachController(arm, Scene())
    ctl.reset(q0)
    tr = run_controller(ctl, T, 6.0, DT)
    m = evaluate(arm, Scene(), tr.q, T, DT, capsules=ArmCapsules())
    assert m.reached and m.path_ratio < 1.05
    check_trajectory(arm, tr.q)


def test_params_and_arm_validation(arm) -> None:
    with pytest.raises(ConfigError):
        ControllerParams(swivel_reference="sideways")
    with pytest.raises(ConfigError):
        ControllerParams(dt=0.0)
    with pytest.raises(ConfigError):
        ReachController(load_arm("powercube6"))
    ctl = ReachController(arm)
    with pytest.raises(InvalidInputError):
        ctl.reset([0.0] * 6)
    ctl.reset(np.zeros(7) + 0.2)
    with pytest.raises(InvalidInputError):
        ctl.step(-1.0)
    with pytest.raises(InvalidInputError):
        ctl.set_preferred_swivel(math.inf)
    r = ctl.step(DT)  # no goal: holds
    assert r.phase is Phase.IDLE and math.isinf(r.distance_to_goal)


def test_params_from_dict() -> None:
    p = ControllerParams.from_dict({"preferred_swivel": 0.3, "speed": {"v_max": 0.25},
                                    "capsules": {"radii": [0.1, 0.07, 0.06, 0.04]}})
    assert p.preferred_swivel == 0.3 and p.speed.v_max == 0.25 and p.speed.k == ControllerParams().speed.k
    assert p.capsules.radii == (0.1, 0.07, 0.06, 0.04)
    assert ControllerParams.from_dict(None) == ControllerParams()
    with pytest.raises(ConfigError, match="unknown controller parameter"):
        ControllerParams.from_dict({"prefered_swivel": 0.3})
    with pytest.raises(ConfigError, match="unknown speed"):
        ControllerParams.from_dict({"speed": {"vmax": 1.0}})
    with pytest.raises(ConfigError):
        ControllerParams.from_dict({"speed": {"v_max": -1.0}})
