"""ReachController: reaching, obstacle avoidance, continuity, limits, goal rejection, retargeting."""

from __future__ import annotations

import functools
import math
from types import SimpleNamespace

import numpy as np
import pytest
from support.control_scenes import elbow_obstacle_hold, pose

from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import (
    ControllerParams,
    GoalStatus,
    Phase,
)
from redarm_ros.control.simulate import evaluate, run_controller
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.obstacles import ArmCapsules, Cylinder, Scene, Sphere, load_scene, min_distance
from redarm_ros.kinematics import load_arm

DT = 0.01


@pytest.fixture(scope="module")
def arm():
    return load_arm("pa10")


@pytest.fixture(scope="module")
def q_start(arm):
    """Hand down at (0.3, 0.3, 0.15), elbow up: a start left of the table centre."""
    q, info = arm.ik_nearest(pose([0.3, 0.3, 0.15]), np.array([0.8, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    return q


def check_trajectory(arm, q: np.ndarray, from_rest: bool = True) -> None:
    """Joint limits hold, no step exceeds the joint velocity limits (so no branch flip) and no joint
    exceeds its acceleration limit (second difference of the commands, from rest at the start)."""
    assert np.all(q >= arm.lower - 1e-12) and np.all(q <= arm.upper + 1e-12)
    steps = np.abs(np.diff(q, axis=0)) / (np.asarray(arm.max_vel) * DT)
    assert steps.max() <= 1.0 + 1e-6
    qq = np.vstack([q[:1], q]) if from_rest else q
    acc = np.abs(np.diff(qq, n=2, axis=0)) / (np.asarray(arm.max_acc) * DT * DT)
    assert acc.max() <= 1.0 + 1e-6


def test_reaches_goal_on_empty_table_with_straight_path(arm, q_start) -> None:
    scene = load_scene("table_empty")
    ctl = make_controller(arm, scene)
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
    ctl = make_controller(arm, scene)
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
    assert near.any() and np.all(tr.tool[near, 2] > can.top)


def test_fixed_swivel_mode_keeps_the_elbow(arm, q_start) -> None:
    scene = load_scene("table_empty")
    ctl = make_controller(arm, scene, ControllerParams(swivel_mode="fixed"))
    ctl.reset(q_start)
    s0 = ctl.swivel
    T = pose([0.6, 0.0, 0.12])
    tr = run_controller(ctl, T, 6.0, DT)
    assert evaluate(arm, scene, tr.q, T, DT).reached  # it moved the hand to the goal ...
    assert np.allclose(tr.swivel, s0, atol=1e-12)  # ... with the elbow kept on its swivel


def test_swivel_dynamics_moves_elbow_away_from_an_obstacle(arm) -> None:
    """Hold the hand still; an obstacle placed at the elbow makes the swivel move and clear it."""
    run = elbow_obstacle_hold(arm)
    assert abs(run.last.swivel - run.swivel_before) > 0.1
    assert run.after > run.before + 0.03
    assert np.linalg.norm(arm.fk(run.last.q)[:3, 3] - arm.fk(run.q0)[:3, 3]) < 1e-3  # the hand stayed
    check_trajectory(arm, run.qs, from_rest=False)


def test_goal_rejections(arm, q_start) -> None:
    scene = load_scene("table_cylinder")
    ctl = make_controller(arm, scene)
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
    ctl = make_controller(arm, Scene())
    ctl.reset(q_start)
    # Straight down right next to the base: the wrist would be inside the elbow-limit shell.
    check = ctl.check_goal(pose([0.05, 0.0, 0.45]))
    assert check.status is GoalStatus.NO_SOLUTION_IN_LIMITS
    assert check.message


def test_retargets_smoothly_mid_motion(arm, q_start) -> None:
    scene = Scene((), 0.0)
    ctl = make_controller(arm, scene)
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
    ctl = make_controller(arm, Scene((), 0.0))
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
    check_trajectory(arm, np.array(qs), from_rest=False)


def test_obstacle_appearing_mid_reach_invalidating_the_goal(arm, q_start) -> None:
    ctl = make_controller(arm, Scene((), 0.0))
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
    ctl = make_controller(arm, Scene())
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
    with pytest.raises(ConfigError):  # neither a 7-DOF swivel arm nor the 6-DOF PowerCube arm
        make_controller(SimpleNamespace(n=5, name="five_joints", kind="chain"))
    ctl = make_controller(arm)
    with pytest.raises(InvalidInputError):
        ctl.reset([0.0] * 6)
    ctl.reset(np.zeros(7) + 0.2)
    with pytest.raises(InvalidInputError):
        ctl.step(-1.0)
    for bad in (math.inf, 7.0, "up"):  # the table's bound: +/- 2 pi
        with pytest.raises(InvalidInputError):
            ctl.set_preferred_swivel(bad)
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


def demo_pose(p, yaw: float = 0.0) -> np.ndarray:
    """The demo's goal convention: tool z down (rotation by pi about x), then yaw about base z."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = p
    return T


READY = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])  # the demo's ready pose
DEMO_BALL = Scene((Sphere((0.22, -0.20, 0.70), 0.07, "ball"),), 0.0)


def run_sequence(arm, scene: Scene, q0: np.ndarray, goals, per_goal: float = 15.0,
                 params: ControllerParams | None = None):
    """Reach ``goals`` one after the other (each until REACHED or ``per_goal`` s); returns the
    commanded joint trajectory, the final phase of each goal and the messages seen."""
    ctl = make_controller(arm, scene, params)
    ctl.reset(q0)
    qs = [ctl.q]
    phases = []
    messages = set()
    for T in goals:
        assert ctl.set_goal(T).accepted
        for _ in range(int(per_goal / DT)):
            r = ctl.step(DT)
            qs.append(r.q)
            if r.message:
                messages.add(r.message)
            if r.phase is Phase.REACHED:
                break
        phases.append(r.phase)
    return np.array(qs), phases, messages


@pytest.mark.parametrize("name", ["pa10", "powercube7"])
def test_singular_start_moves_in_joint_space_and_reaches(name: str) -> None:
    """From q = 0 (stretched straight up, where homing leaves the arm) a table goal is reached: a
    joint-space move to a goal configuration first (there is no elbow circle), then the normal loop;
    continuous, in limits, collision-free."""
    arm = load_arm(name)
    scene = Scene((), 0.0)
    T = demo_pose([0.5, 0.0, 0.3]) if name == "pa10" else demo_pose([0.4, 0.0, 0.25])
    qs, phases, messages = run_sequence(arm, scene, np.zeros(7), [T])
    assert phases == [Phase.REACHED]
    assert any("joint space" in m and "stretched" in m for m in messages)
    check_trajectory(arm, qs)
    m = evaluate(arm, scene, qs, T, DT)
    assert m.reached and m.collision_free


def test_singular_start_goal_behind_the_arm() -> None:
    """The unfold bends towards the goal (here behind the base's zero direction)."""
    arm = load_arm("pa10")
    T = demo_pose([-0.45, 0.2, 0.3])
    qs, phases, _ = run_sequence(arm, Scene((), 0.0), np.zeros(7), [T])
    assert phases == [Phase.REACHED]
    check_trajectory(arm, qs)


def test_demo_sequence_never_passes_through_the_ball(arm) -> None:
    """READY -> left -> front right past the ball (issue 5): the forearm once passed through the ball
    (clearance -0.065 m, as of a2d82c7); later the guard held the arm against the ball for good. Now
    no command has negative clearance, the guard stops the arm at the ball, and the re-planner takes
    it around in joint space (saying why) to the goal."""
    goals = [demo_pose([0.30, 0.45, 0.35], -0.4), demo_pose([0.50, -0.30, 0.25], 0.0)]
    qs, phases, messages = run_sequence(arm, DEMO_BALL, READY, goals)
    clear = [min_distance(arm, q, DEMO_BALL).distance for q in qs]
    assert min(clear) >= 0.0
    assert phases == [Phase.REACHED, Phase.REACHED]
    assert any(m.startswith("collision guard") and "ball" in m for m in messages)
    assert any(m.startswith("re-planning in joint space") for m in messages)
    check_trajectory(arm, qs)


SEQUENCE_SCENES = ["table_cylinder", "narrow_passage", "swivel_sphere", "demo_ball"]


@pytest.mark.parametrize("scene_name", SEQUENCE_SCENES)
def test_goal_sequences_are_collision_free(arm, scene_name: str) -> None:
    """Random (seeded) sequences of three accepted goals: no command ever has negative clearance,
    whatever the dynamics do (the guard holds instead), and every joint limit holds."""
    scene = DEMO_BALL if scene_name == "demo_ball" else load_scene(scene_name)
    rng = np.random.default_rng(SEQUENCE_SCENES.index(scene_name) + 11)
    probe = make_controller(arm, scene)
    goals = []
    while len(goals) < 3:
        p = [rng.uniform(0.3, 0.7), rng.uniform(-0.45, 0.45), rng.uniform(0.08, 0.4)]
        T = demo_pose(p, rng.uniform(-0.6, 0.6))
        if probe.check_goal(T).accepted and all(o.signed_distance(p) > 0.05 for o in scene.obstacles):
            goals.append(T)
    qs, phases, messages = run_sequence(arm, scene, READY, goals, per_goal=8.0)
    assert min_distance(arm, qs[0], scene).distance > 0.0
    clear = np.array([min_distance(arm, q, scene).distance for q in qs])
    assert clear.min() >= 0.0, (clear.min(), phases, messages)
    check_trajectory(arm, qs)
    assert phases.count(Phase.REACHED) >= 2


def _ball_ahead_of_the_forearm(arm, q_start, gap: float):
    """Reach from q_start for 0.8 s, then a ball ``gap`` m ahead of the forearm capsule, in the
    direction the forearm moves; returns (controller, commands so far, scene with the ball)."""
    ctl = make_controller(arm, Scene((), 0.0))
    ctl.reset(q_start)
    ctl.set_goal(pose([0.65, -0.15, 0.08]))
    qs = [ctl.q]
    for _ in range(80):
        qs.append(ctl.step(DT).q)
    kp0, kp1 = arm.key_points(qs[-2]), arm.key_points(qs[-1])
    mid = 0.5 * (np.asarray(kp1[2]) + np.asarray(kp1[3]))
    move = mid - 0.5 * (np.asarray(kp0[2]) + np.asarray(kp0[3]))
    ahead = mid + (ArmCapsules().radii[2] + 0.03 + gap) * move / np.linalg.norm(move)
    obstacles = Scene((Sphere(tuple(ahead), 0.03, "ball"),), 0.0)
    assert 0.0 < min_distance(arm, qs[-1], obstacles).distance < gap + 0.01
    assert ctl.set_scene(obstacles) is None  # the goal is still fine
    return ctl, qs, obstacles


def test_guard_brakes_in_time_for_an_obstacle_ahead(arm, q_start) -> None:
    """A ball appears 8 cm ahead of the moving forearm (the goal stays valid): the arm brakes
    within its acceleration limits and never touches it."""
    ctl, qs, obstacles = _ball_ahead_of_the_forearm(arm, q_start, 0.08)
    for _ in range(600):
        qs.append(ctl.step(DT).q)
    clear = [min_distance(arm, q, obstacles).distance for q in qs]
    assert min(clear) >= 0.0
    check_trajectory(arm, np.array(qs))


def test_guard_emergency_stop_rather_than_collide(arm, q_start) -> None:
    """A ball appears 1 cm ahead of the moving forearm: too close to brake within the acceleration
    limits, so the guard stops the arm (the one case where it exceeds them) and reports it."""
    ctl, qs, obstacles = _ball_ahead_of_the_forearm(arm, q_start, 0.01)
    n0 = len(qs)
    guarded = []  # steps the guard reported
    for _ in range(300):
        r = ctl.step(DT)
        qs.append(r.q)
        if r.message.startswith("collision guard"):
            guarded.append(len(qs) - 1)
    clear = [min_distance(arm, q, obstacles).distance for q in qs]
    assert min(clear) >= 0.0
    assert guarded, "the guard never reported"
    # ... and stopped the arm: a few braking steps, then a command equal to the last one
    first_still = next(k for k in range(n0, len(qs)) if np.array_equal(qs[k], qs[k - 1]))
    assert first_still - guarded[0] <= 10, (guarded[:5], first_still)


def _reach_and_watch(arm, scene_name: str, goals: list, watch_s: float = 2.0,
                     budget_s: float = 20.0) -> list:
    """Reach ``goals`` one after the other from the ready pose and watch each for ``watch_s`` after
    REACHED, as a user who acts on it: per goal, (the last step's result, the results of the steps after
    REACHED, the seconds to REACHED). Stops after the first goal not REACHED within ``budget_s`` (its
    watched results are empty)."""
    ctl = make_controller(arm, load_scene(scene_name))
    ctl.reset(np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0]), now=0.0)
    out = []
    for T in goals:
        assert ctl.set_goal(np.array(T)).accepted
        took_s = budget_s
        for k in range(round(budget_s / DT)):
            r = ctl.step(DT)
            if r.phase is Phase.REACHED:
                took_s = (k + 1) * DT
                break
        if r.phase is not Phase.REACHED:
            out.append((r, [], took_s))
            break
        out.append((r, [ctl.step(DT) for _ in range(round(watch_s / DT))], took_s))
    return out


def _all_reached(run: list, count: int, budget_s: float) -> list:
    """The first ``count`` goals of a :func:`_reach_and_watch` run, each REACHED within ``budget_s``:
    per goal, (the REACHED step's result, the results of the steps after it)."""
    assert len(run) >= count and run[count - 1][0].phase is Phase.REACHED, run[-1][0].message
    for r, _, took_s in run[:count]:
        assert took_s <= budget_s, (took_s, r.message)
    return [(r, after) for r, after, _ in run[:count]]


def _reached_then_watched(arm, scene_name: str, goals: list, watch_s: float = 2.0,
                          budget_s: float = 20.0) -> list:
    """:func:`_reach_and_watch` with every goal REACHED within ``budget_s`` (the way there is not what
    most tests below are about): per goal, (the REACHED step's result, the results of the steps after it)."""
    return _all_reached(_reach_and_watch(arm, scene_name, goals, watch_s, budget_s), len(goals), budget_s)


def _left_reached(after: list) -> str:
    """'' if every result stayed REACHED, else the first one that did not (phase and message)."""
    return next((f"{a.phase.value}: {a.message}" for a in after if a.phase is not Phase.REACHED), "")


# Goal sequences in the narrow passage (sequence_bench, seeds 2006 and 2018) that end with the elbow
# settling against a wide joint's limit: joint 5's lower limit after the 2nd goal of the first, joint 7's
# (-2 pi) after the 4th of the second. The swivel search used to throw the elbow back a whole search step
# at such a limit, and the limit probe saw the joint's in-limit copy 2 pi away instead of the limit, so
# the elbow ran into it at speed; either way it swung off and took the hand up to 15 mm (3 mm) off the
# goal after REACHED.
_PASSAGE_SEQUENCES = {
    "joint 5": (4, [
        [[0.5640511197310488, -0.48499485645873064, 0.6683010725254939, 0.11511199581192097],
         [0.18137067870120338, 0.8623390404923794, 0.47273254187769576, 0.2354064360373697],
         [-0.8055749569330064, -0.14543510047872832, 0.5743671476600375, 1.1274074116895068],
         [0.0, 0.0, 0.0, 1.0]],
        [[0.5238435676264591, -0.3247547146955691, -0.7874784390314333, -0.39412782899455023],
         [-0.06798170497002021, 0.9055839981541007, -0.4186837829157021, -0.538434888926958],
         [0.8490974057466861, 0.2728589334623901, 0.45230697317641955, 0.9353515720040166],
         [0.0, 0.0, 0.0, 1.0]],
    ]),
    "joint 7": (6, [
        [[0.10364301867238904, 0.7569117746654831, -0.6452462243618503, -0.25504772063963166],
         [-0.87415634539036, -0.24014439631998113, -0.42211533107656884, -0.18864773807049262],
         [-0.47445632938579746, 0.607795388505754, 0.6367699405726491, 0.6598373340186485],
         [0.0, 0.0, 0.0, 1.0]],
        [[0.08682316018266914, 0.014419210040899431, 0.9961193830247915, 0.12100942523064426],
         [-0.8382281632624706, -0.5392902575083043, 0.08086757366368826, 0.17383257898924404],
         [0.5383635251106075, -0.8419964991248025, -0.03473629646431736, 1.1448097118061544],
         [0.0, 0.0, 0.0, 1.0]],
        [[-0.576175714013667, 0.5769689391763028, -0.5789027464148125, 0.048202062438154746],
         [-0.7329153973404433, -0.6782115980995286, 0.05351680618818644, 0.8769705725898336],
         [-0.36174102189569435, 0.4551218204272955, 0.8136384710968401, 0.29965026142003276],
         [0.0, 0.0, 0.0, 1.0]],
        [[0.8532034449983519, 0.2262035302755729, -0.4699743017802273, -0.4956003192705507],
         [-0.3470103030980837, -0.4265232230876449, -0.8352615097744557, -0.359479015661325],
         [-0.3893940561779549, 0.875733922523157, -0.2854161277073961, 0.6518648206360305],
         [0.0, 0.0, 0.0, 1.0]],
    ]),
}


# Three goals of a sequence on the empty table (sequence_bench, seed 2019). After REACHED the elbow's
# creep towards its rest swivel kept the swivel below its settled rate, but a slow swivel can still turn
# a joint fast (near the shoulder singularity joints 1 and 3 turned at 44 % of their speed limit), and
# the phase went back to REACHING; in the sequence benchmark after 7 goals per scene of 200.
_CREEP_GOALS = [
    [[-0.7830739272324876, -0.1756272144165901, -0.5966157105247545, -0.42225144945093274],
     [0.0011484281505040883, 0.9588893421588662, -0.2837779248055068, 0.010185839966740513],
     [0.6219275726332381, -0.22290426431633345, -0.7506795477086894, 0.4322083746880148],
     [0.0, 0.0, 0.0, 1.0]],
    [[0.6229515347622966, -0.673114447845588, 0.39855780689735354, 0.30480427836788326],
     [-0.7423188670004128, -0.669386233911751, 0.029745075973442614, 0.519319504057946],
     [0.24676726896515755, -0.3143867203794899, -0.9166607360504246, 0.24631980728184727],
     [0.0, 0.0, 0.0, 1.0]],
    [[0.3453125693530285, 0.33494618153265154, -0.8766814044586014, -0.08245333051591115],
     [0.5418182140580607, 0.6915854275128083, 0.4776427738036656, 0.39013088960199327],
     [0.766284707117233, -0.6399380063167232, 0.05733319901797221, 0.5520091308884919],
     [0.0, 0.0, 0.0, 1.0]],
]


def test_after_reached_the_elbows_creep_keeps_every_joint_at_rest(arm) -> None:
    vmax = np.asarray(arm.max_vel)
    for reached, after in _reached_then_watched(arm, "table_empty", _CREEP_GOALS):
        assert _left_reached(after) == ""
        assert max(a.distance_to_goal for a in after) <= 1e-3
        Q = np.array([reached.q] + [a.q for a in after])
        assert float(np.max(np.abs(np.diff(Q, axis=0)) / (vmax * DT))) <= 0.1  # at rest: REACHED's 2 x 5 %


def test_the_elbow_keeps_one_rest_swivel_when_the_preferred_one_is_midway_between_two() -> None:
    """The third goal after the first two of the joint 5 case: the preferred swivel lies midway between the
    ends of a stretch where a joint is within the limit force's reach, so the rest swivels on either side
    are equally near. As the hand settled they took turns, and the elbow set off for the far one right
    after REACHED (the phase went back to REACHING). Now the first choice is kept, and the rest swivel
    is chosen (from twice the position tolerance on) before REACHED is judged."""
    for reached, after in _all_reached(_passage_joint5_run(), 3, budget_s=20.0):
        assert _left_reached(after) == ""
        assert {a.swivel_desired for a in after} == {reached.swivel_desired}  # one rest swivel


@pytest.mark.parametrize("case", sorted(_PASSAGE_SEQUENCES))
def test_the_hand_stays_at_the_goal_after_reached_with_the_elbow_near_a_wide_joints_limit(arm, case) -> None:
    joint, goals = _PASSAGE_SEQUENCES[case]
    run = (_all_reached(_passage_joint5_run(), len(goals), budget_s=20.0) if case == "joint 5"
           else _reached_then_watched(arm, "narrow_passage", goals))
    for _, after in run:
        assert _left_reached(after) == ""  # (the elbow may still creep: a self-motion)
        assert max(a.distance_to_goal for a in after) <= 1e-3
    r = after[-1]
    margin = min(r.q[joint] - arm.lower[joint], arm.upper[joint] - r.q[joint])
    if case == "joint 5":  # (the situation: the elbow settled against that joint's limit)
        assert margin < 0.05
    else:
        # joint 7's rest swivel was one that only its copy 2 pi away reaches: the elbow pressed against
        # the limit towards it. The rest swivels are now those reached along the elbow circle, on the
        # joints' own copies, and the elbow rests clear of the limit.
        assert margin > 0.25


@pytest.mark.parametrize("make", [
    lambda: ControllerParams(collision_margin=-0.01),
    lambda: ControllerParams(joint_brake_share=1.5),
    lambda: ControllerParams.from_dict({"unfold_pitch": [0.4, 0.0, 1.0]}),
], ids=["negative collision_margin", "joint_brake_share above 1", "unfold_pitch elbow under 0.2 rad"])
def test_new_parameters_are_validated(make) -> None:
    with pytest.raises(ConfigError):
        make()


def test_unfold_pitch_is_read_from_a_dict() -> None:
    assert ControllerParams.from_dict({"unfold_pitch": [0.3, 1.0, 0.8]}).unfold_pitch == (0.3, 1.0, 0.8)


# sequence_bench, table_empty, seed 2005: at the 4th goal the preferred swivel lies just below the start
# of the in-limit interval (around the circle). Taken on the interval's unwrapped axis, it was nearest
# to the far end, and the elbow swung ~3 rad across the interval with the hand already on the goal:
# not REACHED within the benchmark's 10 s (now at 5.9 s).
_WRAP_GAP_SEQUENCE = [
    [[0.37317122631629307, -0.3632186562723495, -0.8537068838807048, -0.543982792486226],
     [-0.7598646349863302, 0.40829665923762165, -0.5058651742831172, -0.08151867103309035],
     [0.5323053375147435, 0.8374759971432651, -0.12363244664006531, 0.5864362347362713],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.5424231474825172, -0.28524846909835644, 0.7901964565550792, 0.07323975185168448],
     [-0.006051889761369611, -0.9392408717087081, -0.3432054188706559, -0.7986607421273223],
     [0.8400836289950396, -0.1909447453817732, 0.507739697586878, 0.6295404312808455],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.3942343938605086, 0.8906135129180345, -0.2266865971010091, 0.22847600791114586],
     [0.39118839845775283, -0.06057594008838006, -0.9183148656068175, 0.2445605184436186],
     [-0.83159538214777, -0.4507084712873799, -0.32451655473996616, 0.5017695717934868],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.5206797369183741, 0.8526610270229289, 0.04314840157892774, -0.2861829306259964],
     [-0.6003762727917853, -0.32975262153050594, -0.7285681434583883, 0.22809766480846694],
     [-0.6069933629219157, -0.40525594577990187, 0.6836129575854898, 1.093795434707369],
     [0.0, 0.0, 0.0, 1.0]],
]


def test_the_rest_swivel_is_the_nearest_around_the_circle_not_on_the_unwrapped_interval(arm) -> None:
    # every goal within the benchmark's 10 s; before, the elbow was still swinging then at the last
    _reached_then_watched(arm, "table_empty", _WRAP_GAP_SEQUENCE, budget_s=10.0)


# table_cylinder, sequence 16, goals 0-1 of the sequence benchmark (seed 2000): at goal 1 joint 1 stands
# 0.5 mrad inside its upper limit with the elbow 0.3 rad from its rest swivel
_LIMIT_PROBE_SEQUENCE = [
    [[0.2556108013018554, 0.9432342905096803, 0.21206647887991043, -0.17311358333171464],
     [0.6197993653932599, 0.008464770705426228, -0.7847146578948406, 0.2745277098954575],
     [-0.741964867710012, 0.33202021152876315, -0.582452327852211, 0.7754452088701662],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.008621255137771275, 0.6942401158606942, -0.7196918336966035, 0.628334832532274],
     [-0.43988346366029857, 0.6437080133960096, 0.6262128487087929, 0.08479547811843358],
     [0.8980134811672197, 0.32197927731376264, 0.2998351757590143, 0.7833841811570178],
     [0.0, 0.0, 0.0, 1.0]],
]

# narrow_passage, sequence 6 (seed 2006): goals 2-4 after the two of the joint 5 case above; goal 4 ends
# a joint-space move with joint 3 0.14 rad from its limit, where the limit force and the attraction
# balance
_PASSAGE_JOINT5_ON = [
    [[0.9134055276191193, -0.1428682829330417, -0.3811548187372199, -0.25462830168332723],
     [0.0630711992542891, 0.9747471211060789, -0.21421968565012203, 0.12792053615425952],
     [0.4021347609191032, 0.171629553478344, 0.8993502823891033, 0.6540499721405489],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.6530960036449416, 0.7473087070550716, 0.12245532402751597, -0.4413802820079831],
     [0.5074200671093348, 0.5518892133230957, -0.6617727492971986, -0.04036767630038432],
     [-0.56213031008634, -0.3700648491511887, -0.739636073961339, 0.1422293305433152],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.9328576600173808, 0.010346892829979637, -0.36009655365701854, 0.21901464649874447],
     [-0.13599377127189766, -0.9357407592618995, 0.3254150052336413, -0.18250265444934674],
     [-0.333589988342192, 0.35253676867062944, 0.8743200480448378, 0.5994143154789846],
     [0.0, 0.0, 0.0, 1.0]],
]


@functools.cache
def _passage_joint5_run() -> list:
    """The joint 5 case's two goals and the three after them, reached (each within 20 s) and watched
    once for the three tests that look at its first 2, 3 and 5 goals. The controller is deterministic
    (a point goal's corridor plan is waited for), so the first goals of this run are the run of those
    goals alone; cached here, not in a module fixture, which would run before that is patched in."""
    return _reach_and_watch(load_arm("pa10"), "narrow_passage", [*_PASSAGE_SEQUENCES["joint 5"][1],
                                                                 *_PASSAGE_JOINT5_ON])


def test_after_reached_the_elbow_stays_when_a_joint_stood_at_its_limit(arm) -> None:
    """The limit probe saw another branch beyond joint 1's limit (open space), pushed the elbow into
    the limit against its attraction, and the wanted rate there fell below REACHED's threshold: REACHED
    came with the elbow 0.3 rad from its rest swivel, then it swung 0.54 rad after REACHED."""
    reached, after = _reached_then_watched(arm, "table_cylinder", _LIMIT_PROBE_SEQUENCE, budget_s=10.0)[-1]
    assert _left_reached(after) == ""
    assert max(float(np.max(np.abs(a.q - reached.q))) for a in after) < 0.05
    assert abs(wrap_angle(reached.swivel - reached.swivel_desired)) < 0.05  # at its rest swivel already


def test_reached_does_not_flicker_when_the_wanted_swivel_rate_does(arm) -> None:
    """In a force balance near a joint limit the elbow's wanted rate flickers over REACHED's threshold
    for a step or two while the elbow stands: REACHED stays (it left for 0.07 s before)."""
    reached, after = _all_reached(_passage_joint5_run(), 5, budget_s=10.0)[-1]
    assert _left_reached(after) == ""
    assert max(float(np.max(np.abs(a.q - reached.q))) for a in after) < 0.05


# table_cylinder, sequence 19, goals 0-3 (seed 2000): at goal 3 joint 5 stands at its lower limit, and
# 2 mm from the goal its branch passes the limit by a hair
_WRIST_LIMIT_SEQUENCE = [
    [[-0.16381086092846953, -0.22708561364594715, 0.9599990239145648, 0.8791074598562094],
     [0.899909473609388, 0.3642728535158479, 0.2397253167679546, -0.22840321311783818],
     [-0.40413975447850725, 0.9031818268025908, 0.14468464529308783, 0.7389153250347537],
     [0.0, 0.0, 0.0, 1.0]],
    [[0.2365387331350946, 0.2034952173151353, 0.9500732204713017, -0.18960493350295066],
     [-0.6618915601847258, -0.6820915423408149, 0.31088694154524704, -0.5857664787026536],
     [0.711300914018163, -0.7023822494888337, -0.026649302428614297, 0.9477334725950091],
     [0.0, 0.0, 0.0, 1.0]],
    [[-0.8950093396536772, -0.4036023186181247, 0.18990379232327792, 0.05486142726872606],
     [-0.013578654672020823, -0.4008973382050047, -0.9160223492674403, -0.4902490155233198],
     [0.4458406689277985, -0.8224271959427265, 0.35332648542643563, 1.0668868504808877],
     [0.0, 0.0, 0.0, 1.0]],
    [[0.9010513416723238, -0.33207568127716197, -0.27898426761165906, -0.3690537739521921],
     [0.2960948048692288, 0.0009713112825307235, 0.9551580618326194, -0.33929646134660596],
     [-0.3169137835436611, -0.9432522454034769, 0.09920108538388325, 1.1023821699351197],
     [0.0, 0.0, 0.0, 1.0]],
]


def test_the_rest_swivel_is_one_the_elbow_reaches_on_its_own_branch(arm) -> None:
    """The rest swivel came from the interval of the nearest in-limit solution at the goal, a flipped
    wrist, and every swivel counted with a wide joint on any copy: the elbow pulled towards a swivel
    beyond joint 5's limit, stood there held by it, and the goal was not REACHED in 10 s. Now it is
    the branch the arm is on, followed along the circle from where the elbow is."""
    reached, after = _reached_then_watched(arm, "table_cylinder", _WRIST_LIMIT_SEQUENCE, budget_s=10.0)[-1]
    assert _left_reached(after) == ""
    assert abs(wrap_angle(reached.swivel - reached.swivel_desired)) < 0.05  # at its rest swivel
