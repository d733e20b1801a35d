"""Collision guard (command checks, braking path, joint segments) and the broad phase."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.guard import CollisionGuard, levers
from redarm_ros.control.make import make_controller
from redarm_ros.geometry.broadphase import LEFT_OUT, SceneIndex, bounding_sphere, segment_point_distances
from redarm_ros.geometry.obstacles import ArmCapsules, Box, Cylinder, Scene, Sphere, min_distance
from redarm_ros.kinematics import load_arm

ARM = load_arm("pa10")
CAPS = ArmCapsules()
Q_A = np.array([0.8, 0.7, 0.0, 1.4, 0.0, 1.0, 0.0])
Q_B = np.array([-0.8, 0.7, 0.0, 1.4, 0.0, 1.0, 0.0])


def guard() -> CollisionGuard:
    return CollisionGuard(ARM, CAPS, 0.0, 0.005)


def ball_on_the_way() -> Scene:
    """A ball where the arm's forearm passes midway between Q_A and Q_B (joint 1 turning)."""
    kp = ARM.key_points(0.5 * (Q_A + Q_B))
    c = 0.5 * (kp[2] + kp[3])
    return Scene((Sphere(tuple(c), 0.05, "ball"),), 0.0)


def test_levers_bound_the_motion_of_every_point() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.uniform(ARM.lower, ARM.upper) * 0.8
        lev = levers(np.asarray(ARM.key_points(q)), 0.0)
        for j in range(7):
            dq = np.zeros(7)
            dq[j] = 1e-4
            moved = np.max(np.linalg.norm(ARM.key_points(q + dq) - ARM.key_points(q), axis=1))
            assert moved <= lev[j] * 1e-4 * (1 + 1e-6) + 1e-12


def test_segment_through_an_obstacle_is_refused_a_clear_one_passes() -> None:
    g = guard()
    blocked = ball_on_the_way()
    assert min(min_distance(ARM, Q_A + t * (Q_B - Q_A), blocked).distance for t in np.linspace(0, 1, 50)) < 0
    assert g.segment_clearance(Q_A, Q_B, blocked, 0.02) is None
    clear = Scene((Sphere((-0.5, -0.5, 0.2), 0.05, "far"),), 0.0)
    worst = g.segment_clearance(Q_A, Q_B, clear, 0.02)
    assert worst is not None and worst >= 0.02
    # what it proves holds on a dense check too
    assert (
        min(min_distance(ARM, Q_A + t * (Q_B - Q_A), clear).distance for t in np.linspace(0, 1, 200)) >= 0.02
    )


def test_segment_march_is_resumable_one_evaluation_per_step() -> None:
    g = guard()
    clear = Scene((Sphere((-0.5, -0.5, 0.2), 0.05, "far"),), 0.0)
    march = g.segment_march(Q_A, Q_B, clear, 0.02)
    n0 = g.evaluations
    steps = 0
    while True:
        try:
            next(march)
            steps += 1
        except StopIteration as stop:
            assert stop.value is not None
            break
    assert steps == g.evaluations - n0 and steps > 1


def test_a_segment_starting_in_contact_must_move_away() -> None:
    """From an arm touching a ball, a segment that backs away passes, one that presses in does not."""
    g = guard()
    kp = ARM.key_points(Q_A)
    side = np.cross(kp[3] - kp[2], [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    c = 0.5 * (kp[2] + kp[3]) + side * (CAPS.radii[2] + 0.04)  # touching the forearm capsule
    ball = Scene((Sphere(tuple(c), 0.04, "ball"),), None)
    assert abs(min_distance(ARM, Q_A, ball).distance) < 1e-6
    dq = np.array([0.3, 0, 0, 0, 0, 0, 0])
    away = Q_A - dq if min_distance(ARM, Q_A - 0.01 * dq, ball).distance > 0 else Q_A + dq
    into = 2 * Q_A - away
    assert g.segment_clearance(Q_A, away, ball, 0.02) is not None
    assert g.segment_clearance(Q_A, into, ball, 0.02) is None


def test_check_refuses_a_command_whose_braking_path_hits() -> None:
    g = guard()
    scene = ball_on_the_way()
    q = Q_A + 0.35 * (Q_B - Q_A)
    qd = 0.8 * (Q_B - Q_A) / np.linalg.norm(Q_B - Q_A)  # moving towards the ball fast
    c = min_distance(ARM, q, scene).distance
    assert c > 0.0
    _, bad = g.check(q, qd, c, 0.01, scene)
    assert bad is not None
    _, ok = g.check(q, np.zeros(7), c, 0.01, scene)
    assert ok is None


def test_sync_braking_keeps_the_joint_space_direction() -> None:
    g = guard()
    qd = np.array([1.0, 0.5, 0.0, -2.0, 0.0, 0.0, 3.0])
    q_b, v_b, _ = g.brake(Q_A, qd, math.inf, 0.01, Scene(), sync=True)
    assert np.all(np.abs(v_b - qd) <= ARM.max_acc * 0.01 + 1e-12)
    ratio = v_b[qd != 0] / qd[qd != 0]
    assert np.allclose(ratio, ratio[0]) and 0.0 <= ratio[0] < 1.0  # braked, along the same direction
    assert np.all(v_b[qd == 0] == 0.0)  # still joints stay still


# ------------------------------------------------------------------------------------------------
# broad phase
# ------------------------------------------------------------------------------------------------
def clutter(n: int, seed: int = 3) -> list:
    """Small boxes and balls 1.5-3 m from the shoulder (out of reach of the PA10)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        c = rng.uniform([-3, -3, 0], [3, 3, 2])
        if np.linalg.norm(c - [0, 0, 0.315]) < 1.5:
            continue
        out.append(
            Box(tuple(c), (0.1, 0.1, 0.1), 0.3, f"b{len(out)}")
            if len(out) % 2
            else Sphere(tuple(c), 0.05, f"s{len(out)}")
        )
    return out


def test_bounding_spheres_contain_the_shapes() -> None:
    shapes = [
        Sphere((0.1, 0.2, 0.3), 0.1),
        Cylinder((0.5, 0, 0.1), 0.05, 0.2),
        Box((0, 0, 0), (0.2, 0.1, 0.4), 0.7),
    ]
    rng = np.random.default_rng(2)
    for o in shapes:
        c, r = bounding_sphere(o)
        for _ in range(300):
            p = np.asarray(c) + rng.normal(size=3) * r
            if o.signed_distance(p) <= 0.0:
                assert np.linalg.norm(p - c) <= r + 1e-9


def test_segment_point_distances_match_the_scalar_kernel() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=3), rng.normal(size=3)
    pts = rng.normal(size=(50, 3))
    d = segment_point_distances(a, b, pts)
    for p, dv in zip(pts, d, strict=True):
        assert Sphere(tuple(p), 1e-9).segment_distance(a, b) + 1e-9 == pytest.approx(dv, abs=1e-9)


def test_reach_cull_keeps_only_what_the_arm_can_touch() -> None:
    near = Sphere((0.5, 0.0, 0.2), 0.05, "near")
    idx = SceneIndex(Scene((near, *clutter(200)), 0.0), (0.0, 0.0, 0.315), 1.1, 0.3)
    assert idx.reach_scene.index == (0,) and idx.culled == 200
    assert idx.reach_scene.floor > 0.0
    # a lower bound indeed
    far = Scene(tuple(clutter(200)), None)
    for q in (Q_A, Q_B):
        assert min_distance(ARM, q, far).distance >= idx.reach_scene.floor


def test_local_scene_keeps_the_obstacles_near_the_arm_with_their_global_index() -> None:
    q = np.array([0.0, 0.6, 0.0, 1.4, 0.0, 1.0, 0.0])
    kp = np.asarray(ARM.key_points(q))
    near = kp[3] + np.array([0.0, 0.15, 0.0])  # 0.15 m beside the wrist
    obs = [Sphere((-0.5, 0.4, 0.3), 0.05, "behind"), Sphere(tuple(near), 0.05, "near")]
    idx = SceneIndex(Scene(tuple(obs), 0.0), (0.0, 0.0, 0.315), 1.1, 0.3)
    local = idx.local([kp], CAPS.radii, 0.2)
    assert [o.name for o in local.scene.obstacles] == ["near"] and local.index == (1,)
    assert local.global_index(0) == 1 and local.global_index(-1) == -1
    assert local.floor <= min_distance(ARM, q, Scene((obs[0],), None)).distance + 1e-9


def test_local_scene_of_several_postures_is_the_per_link_minimum() -> None:
    """All links of all postures in one vectorised pass choose exactly what a link-by-link loop of the
    plain kernel chooses, with the same floor; a repeated selection reuses its scene."""
    rng = np.random.default_rng(3)
    obs = tuple(Sphere(tuple(c), float(r), f"s{i}") for i, (c, r) in
                enumerate(zip(rng.uniform([-0.9, -0.9, 0.0], [0.9, 0.9, 1.2], (120, 3)),
                              rng.uniform(0.02, 0.1, 120), strict=True)))
    idx = SceneIndex(Scene(obs, 0.0), (0.0, 0.0, 0.315), 1.1, 0.3)
    kept = [obs[i] for i in idx.reach_scene.index]
    centres = np.array([o.center for o in kept])
    radii = np.array([o.radius for o in kept])
    for _ in range(20):
        sets = [np.asarray(ARM.key_points(rng.uniform(ARM.lower, ARM.upper))) for _ in range(2)]
        gap = np.full(len(kept), np.inf)
        for kp in sets:
            for link in range(4):
                d = segment_point_distances(kp[link], kp[link + 1], centres) - radii - CAPS.radii[link]
                gap = np.minimum(gap, d)
        local = idx.local(sets, CAPS.radii, 0.15)
        want = tuple(idx.reach_scene.index[i] for i in np.flatnonzero(gap <= 0.15))
        assert local.index == want
        rest = gap[gap > 0.15]
        floor = min(idx.reach_scene.floor, float(rest.min())) if rest.size else idx.reach_scene.floor
        assert local.floor == pytest.approx(floor, abs=1e-12)
        again = idx.local(sets, CAPS.radii, 0.15)
        assert again.index == local.index and again.floor == local.floor
        if 0 < len(want) < len(kept):
            assert again.scene is local.scene  # the cached subset


def test_far_clutter_does_not_change_the_motion() -> None:
    """The same reach with and without 300 obstacles out of the arm's reach: identical commands; the
    reported clearance is a lower bound when an obstacle left out might be nearer."""
    T = ARM.fk(np.array([0.5, 0.8, -0.2, 1.2, 0.3, 0.8, 0.2]))
    base = Scene((Cylinder((0.5, 0.3, 0.1), 0.04, 0.2, "can"),), 0.0)
    runs = []
    for scene in (base, base.with_obstacles((*base.obstacles, *clutter(300)))):
        ctl = make_controller(ARM, scene)
        ctl.reset(np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0]))
        ctl.set_goal(T)
        runs.append([ctl.step(0.01) for _ in range(300)])
    for a, b in zip(*runs, strict=True):
        assert np.array_equal(a.q, b.q)
        assert b.clearance <= a.clearance + 1e-12
        assert b.clearance_obstacle in (a.clearance_obstacle, LEFT_OUT)
