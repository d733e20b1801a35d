"""The controller for the 6-DOF PowerCube arm (ReachController6), the self-collision guard of every arm,
and the base-move suggestion in the controller's rejections. In-process, fixed seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.guard import GROUND_PLANE, CollisionGuard, is_self
from redarm_ros.control.ik_step import IKStep, pose_matrix
from redarm_ros.control.ik_step6 import IKStepper6, branch, fixed_circle
from redarm_ros.control.make import make_controller
from redarm_ros.control.reach6 import ReachController6
from redarm_ros.control.reach_controller import GoalStatus, Phase, ReachController
from redarm_ros.errors import ConfigError
from redarm_ros.geometry.obstacles import ArmCapsules, Scene
from redarm_ros.geometry.self_collision import self_collision
from redarm_ros.kinematics import load_arm

DT = 0.01
ARM = load_arm("powercube6")
READY = np.array([0.0, 1.0, 0.0, -1.7, -0.9, 0.0])  # front, elbow up (the demo's ready pose)


def run(ctl: ReachController, max_steps: int = 3000) -> tuple[list, list[np.ndarray]]:
    """Step until REACHED/BLOCKED/REJECTED; returns the results and the commanded joints."""
    out, qs = [], [ctl.q]
    for _ in range(max_steps):
        r = ctl.step(DT)
        out.append(r)
        qs.append(r.q)
        if r.phase in (Phase.REACHED, Phase.BLOCKED, Phase.REJECTED):
            break
    return out, qs


def test_make_controller_picks_the_class_and_each_class_refuses_the_other_arm() -> None:
    ctl = make_controller(ARM)
    assert type(ctl) is ReachController6
    pa10 = load_arm("pa10")
    assert type(make_controller(pa10)) is ReachController
    # no class is swapped for another behind the caller's back: a wrong arm is a clear error
    with pytest.raises(ConfigError, match="make_controller"):
        ReachController(ARM)
    with pytest.raises(ConfigError, match="make_controller"):
        ReachController6(pa10)


def test_seeded_goals_reached_without_branch_flips_within_limits() -> None:
    rng = np.random.default_rng(6)
    ctl = make_controller(ARM)
    ctl.reset(READY)
    reached = 0
    tried = 0
    while tried < 5:
        # goals on the current branch, near the current configuration, clear of the ground
        qg = np.clip(ctl.q + rng.uniform(-0.5, 0.5, 6), ARM.lower, ARM.upper)
        qg[2] = 0.0
        if branch(ARM, qg).elbow != branch(ARM, ctl.q).elbow or self_collision(ARM, qg).min_distance < 0.02:
            continue
        check = ctl.set_goal(ARM.fk(qg))
        if not check.accepted:
            continue
        tried += 1
        b0 = branch(ARM, ctl.q)
        res, qs = run(ctl)
        Q = np.array(qs)
        assert all(b0.admits(branch(ARM, q)) for q in Q), "elbow flip within a motion"
        assert np.all(Q >= ARM.lower - 1e-12) and np.all(Q <= ARM.upper + 1e-12)
        qd = np.diff(Q, axis=0) / DT
        assert np.all(np.abs(qd) <= ARM.max_vel * (1 + 1e-6) + 1e-9)
        qdd = np.diff(qd, axis=0) / DT
        assert np.all(np.abs(qdd) <= ARM.max_acc * (1 + 1e-6) + 1e-6)
        assert res[-1].phase is Phase.REACHED, res[-1].message
        assert res[-1].distance_to_goal <= 1e-3 and res[-1].orientation_error <= 0.01
        assert all(r.clearance >= 0.0 for r in res)
        reached += 1
    assert reached == 5


def test_goal_only_on_the_other_elbow_is_reached_by_a_joint_space_elbow_change() -> None:
    from redarm_ros.demo import POWERCUBE6_GOALS

    goal = next(g for g in POWERCUBE6_GOALS if g.name == "elbow_down")
    T = goal.matrix()
    sols = ARM.ik(T)
    assert len(sols) >= 1 and all(branch(ARM, q).elbow != branch(ARM, READY).elbow for q in sols)
    ctl = make_controller(ARM)
    ctl.reset(READY)
    assert ctl.set_goal(T).accepted
    res, qs = run(ctl)
    assert res[-1].phase is Phase.REACHED, res[-1].message
    assert any("joint space" in r.message and "elbow" in r.message for r in res)
    assert branch(ARM, res[-1].q).elbow == branch(ARM, sols[0]).elbow
    Q = np.array(qs)
    assert np.all(np.abs(np.diff(Q, axis=0)) / DT <= ARM.max_vel * (1 + 1e-6) + 1e-9)


def test_ik_step6_projects_the_orientation_into_the_arm_plane() -> None:
    st = IKStepper6(ARM, 10.0)
    T = ARM.fk(READY)
    from redarm_ros.kinematics.quaternion import quat_angle, quat_from_matrix, quat_from_rotvec, quat_mul

    rot = quat_mul(quat_from_rotvec((0.0, 0.0, 0.05)), quat_from_matrix(T[:3, :3]))  # approach off-plane
    pos = (float(T[0, 3]), float(T[1, 3]) + 0.002, float(T[2, 3]))
    assert len(ARM.ik(pose_matrix(pos, rot))) == 0  # not reachable as asked
    out = st.advance(pos, quat_from_matrix(T[:3, :3]), 0.0, READY, pos, rot, DT)
    assert isinstance(out, IKStep), out
    Tq = ARM.fk(out.q)
    assert np.allclose(Tq[:3, 3], pos, atol=1e-9)
    assert np.allclose(Tq[:3, :3], pose_matrix(pos, out.rot)[:3, :3], atol=1e-9)
    # the approach (tool x) lies in the vertical plane through the tool, the nearest such orientation
    normal = np.array([-pos[1], pos[0], 0.0]) / math.hypot(pos[0], pos[1])
    assert abs(float(Tq[:3, 0] @ normal)) < 1e-9
    assert quat_angle(out.rot, rot) < 0.06
    # the circle is the configuration's own key points
    assert np.allclose(np.array(fixed_circle(ARM.key_points(out.q)).key_points(1.3)), ARM.key_points(out.q))


def test_guard_refuses_a_self_colliding_command_for_every_arm() -> None:
    for name, q_free, q_bad in (
        ("powercube6", [0.0, 1.5708, 0.0, -1.5708, -1.5708, 0.0], [0.0, 1.5708, 0.0, -1.5708, -2.0, 0.0]),
        ("pa10", [0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0], np.radians([0, 91, 0, 137, 0, 0, 0])),
    ):
        arm = load_arm(name)
        guard = CollisionGuard(arm, ArmCapsules(), 0.0, 0.005)
        q_free, q_bad = np.array(q_free), np.clip(np.array(q_bad), arm.lower, arm.upper)
        assert self_collision(arm, q_bad).colliding, name
        c_free = guard.clearance(q_free, Scene())
        assert c_free.distance > 0.0, name
        clear, bad = guard.check(q_bad, np.zeros(arm.n), c_free.distance, DT, Scene())
        assert bad is not None and bad.distance < 0.0, name
        assert is_self(bad.obstacle) or bad.obstacle == GROUND_PLANE, name
        # the scene-only clearance (self_check=False) does not see it
        assert guard.clearance(q_bad, Scene(), self_check=False).distance > bad.distance


def test_controller_stops_a_motion_into_the_arm_itself() -> None:
    # From the park posture (upper arm up, forearm forward, gripper down) a twist pulls the gripper back
    # towards the upper arm: the guard stops it before the capsules touch.
    ctl = make_controller(ARM)
    q0 = ARM.park
    ctl.reset(q0)
    kp = ARM.key_points(q0)
    towards = kp[1] - kp[4]
    towards[2] = 0.0
    towards /= np.linalg.norm(towards)
    worst = math.inf
    messages = set()
    for _ in range(400):
        ctl.set_twist(0.1 * towards, (0.0, 0.0, 0.0))
        r = ctl.step(DT)
        worst = min(worst, self_collision(ARM, r.q).min_distance)
        if r.message:
            messages.add(r.message)
    assert worst >= 0.0
    assert any("self-collision" in m or "ground plane" in m or "no joint solution" in m for m in messages)
    # the gripper did move towards the upper arm before it was stopped
    assert np.dot(ARM.key_points(ctl.q)[4] - kp[4], towards) > 0.01


@pytest.mark.parametrize("name, position", [("powercube6", (1.2, 0.0, 0.1)), ("pa10", (1.6, 0.0, 0.4))])
def test_rejection_message_carries_the_base_move(name: str, position: tuple[float, float, float]) -> None:
    from redarm_ros.demo import Goal

    arm = load_arm(name)
    ctl = make_controller(arm)
    ctl.reset(READY if name == "powercube6" else np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0]))
    T = Goal("far", position, approach="x" if name == "powercube6" else "z").matrix()
    check = ctl.set_goal(T)
    assert check.status is GoalStatus.OUT_OF_REACH
    assert "move the base by dx =" in check.message, check.message
    r = ctl.step(DT)
    assert r.phase is Phase.REJECTED and "move the base by" in r.message
    # moving the base by the suggestion makes the goal solvable
    bp = ctl._hints.placement(T)
    assert bp.valid
    q, _ = arm.ik_nearest(bp.apply(T), bp.q)
    assert q is not None and np.allclose(arm.fk(q), bp.apply(T), atol=1e-6)
    # the same goal again: no second search (bounded: once per rejected goal)
    searches = ctl._hints.searches
    ctl.set_goal(T)
    assert ctl._hints.searches == searches


def test_obstacle_avoided_through_the_heading_alone() -> None:
    # A ball in the way of the gripper's straight route (its capsule would pass through it): the heading
    # dynamics steer around it, no joint-space move, clearance positive all the way.
    from redarm_ros.demo import Goal
    from redarm_ros.geometry.obstacles import Sphere, links_clearance

    ball = Sphere((0.42, 0.18, 0.0), 0.05, "ball")
    scene = Scene((ball,), None)
    T = Goal("left", (0.25, 0.40, 0.10), 0.5, approach="x").matrix()
    T0 = ARM.fk(READY)
    straight = min(
        links_clearance([np.zeros(3), np.zeros(3), np.zeros(3),
                         (1 - t) * (T0[:3, 3] - 0.26 * T0[:3, 0]) + t * (T[:3, 3] - 0.26 * T[:3, 0]),
                         (1 - t) * T0[:3, 3] + t * T[:3, 3]], scene, ArmCapsules(), (3,)).distance
        for t in np.linspace(0.0, 1.0, 101))
    assert straight < 0.0  # the hand moved straight would hit the ball
    ctl = make_controller(ARM, scene)
    ctl.reset(READY)
    assert ctl.set_goal(T).accepted
    b0 = branch(ARM, READY)
    res, qs = run(ctl)
    assert res[-1].phase is Phase.REACHED, res[-1].message
    assert min(r.clearance for r in res) > 0.0
    assert not any("joint space" in r.message for r in res)
    assert all(b0.admits(branch(ARM, q)) for q in qs)


def test_goal_stream_tracked_by_the_servo() -> None:
    # A stream in the arm's plane (reachable orientations all along) is followed within a few mm.
    ctl = make_controller(ARM)
    ctl.reset(READY)
    T0 = ARM.fk(READY)
    t, errs, qs = 0.0, [], []
    for k in range(300):
        t += DT
        T = T0.copy()
        T[0, 3] += 0.08 * math.sin(0.8 * t)
        T[2, 3] += 0.05 * (1.0 - math.cos(0.8 * t))
        if k % 2 == 0:
            ctl.goal_message(T, stamp=t, now=t)
        r = ctl.step(DT, now=t)
        errs.append(r.distance_to_goal)
        qs.append(r.q)
    assert r.phase is Phase.TRACKING
    assert max(errs[100:]) < 3e-3
    b0 = branch(ARM, READY)
    assert all(b0.admits(branch(ARM, q)) for q in qs)
