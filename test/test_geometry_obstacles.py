"""Obstacle shapes, scenes and distances (redarm_ros.geometry.obstacles), checked against brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.obstacles import (
    TABLE,
    ArmCapsules,
    Box,
    Cylinder,
    Scene,
    Sphere,
    links_clearance,
    load_scene,
    obstacle_from_dict,
    obstacle_from_marker,
)


def sd_points(obstacle, pts: np.ndarray) -> np.ndarray:
    """Signed distance of many points, an independent numpy implementation of each shape."""
    c = np.asarray(obstacle.center)
    d = pts - c
    if isinstance(obstacle, Sphere):
        return np.linalg.norm(d, axis=1) - obstacle.radius
    if isinstance(obstacle, Cylinder):
        q = np.stack([np.hypot(d[:, 0], d[:, 1]) - obstacle.radius, np.abs(d[:, 2]) - obstacle.height / 2], 1)
    else:
        cy, sy = math.cos(obstacle.yaw), math.sin(obstacle.yaw)
        local = np.stack([cy * d[:, 0] + sy * d[:, 1], -sy * d[:, 0] + cy * d[:, 1], d[:, 2]], 1)
        q = np.abs(local) - np.asarray(obstacle.half)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def brute_segment(obstacle, a, b, samples: int = 20001) -> float:
    """Signed distance by sampling the segment densely and refining around the best sample."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    ts = np.linspace(0.0, 1.0, samples)
    vals = sd_points(obstacle, a + ts[:, None] * (b - a))
    k = int(np.argmin(vals))
    fine = np.linspace(ts[max(k - 1, 0)], ts[min(k + 1, samples - 1)], 4001)
    return float(sd_points(obstacle, a + fine[:, None] * (b - a)).min())


def brute_point_sd(obstacle, p, n: int = 60) -> float:
    """Signed distance of a point from a dense surface sampling (independent of the closed form)."""
    p = np.asarray(p, float)
    if isinstance(obstacle, Sphere):
        return float(np.linalg.norm(p - obstacle.center) - obstacle.radius)
    # Dense grid of points filling the solid; outside distance = min distance to the solid samples.
    if isinstance(obstacle, Box):
        h = np.asarray(obstacle.half)
        g = [np.linspace(-hi, hi, n) for hi in h]
        X, Y, Z = np.meshgrid(*g, indexing="ij")
        c, s = math.cos(obstacle.yaw), math.sin(obstacle.yaw)
        pts = np.stack([c * X - s * Y, s * X + c * Y, Z], -1).reshape(-1, 3) + obstacle.center
    else:
        r = np.linspace(0, obstacle.radius, n // 2)
        th = np.linspace(0, 2 * math.pi, 2 * n, endpoint=False)
        z = np.linspace(-obstacle.height / 2, obstacle.height / 2, n)
        R, TH, Z = np.meshgrid(r, th, z, indexing="ij")
        pts = np.stack([R * np.cos(TH), R * np.sin(TH), Z], -1).reshape(-1, 3) + obstacle.center
    return float(np.min(np.linalg.norm(pts - p, axis=1)))


SHAPES = [
    Sphere((0.4, 0.1, 0.3), 0.12),
    Cylinder((0.5, -0.2, 0.15), 0.08, 0.3),
    Box((0.45, 0.25, 0.1), (0.2, 0.1, 0.2), yaw=0.6),
    Box((0.0, 0.0, 0.0), (0.3, 0.2, 0.1)),
]


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: type(s).__name__)
def test_point_signed_distance_matches_sampled_solid(shape) -> None:
    rng = np.random.default_rng(1)
    c = np.asarray(shape.center)
    for _ in range(15):
        p = c + rng.uniform(-0.4, 0.4, 3)
        sd = shape.signed_distance(p)
        assert sd == pytest.approx(float(sd_points(shape, p[None, :])[0]), abs=1e-12)
        if sd > 0.01:  # outside: the sampled solid gives the distance up to the grid spacing
            assert abs(sd - brute_point_sd(shape, p)) < 0.012


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: type(s).__name__)
def test_segment_distance_matches_brute_force(shape) -> None:
    rng = np.random.default_rng(7)
    c = np.asarray(shape.center)
    worst = 0.0
    n_inside = 0
    for _ in range(150):
        a = c + rng.uniform(-0.5, 0.5, 3)
        b = c + rng.uniform(-0.5, 0.5, 3)
        d = shape.segment_distance(a, b)
        ref = brute_segment(shape, a, b)
        # The closed form is a true minimum: never above the sampled one, and close to it.
        assert d <= ref + 1e-9
        worst = max(worst, ref - d)
        n_inside += d < 0
    assert worst < 1e-6
    assert n_inside > 0  # the random segments did exercise the penetration branch


def test_segment_distance_special_cases() -> None:
    cyl = Cylinder((0, 0, 0), 0.1, 0.2)
    # Horizontal segment passing 0.05 above the top face.
    assert cyl.segment_distance((-1, 0, 0.15), (1, 0, 0.15)) == pytest.approx(0.05, abs=1e-12)
    # Diagonal above the rim: closest point is on the rim circle.
    a, b = (0.3, 0.0, 0.2), (0.0, 0.3, 0.2)
    assert cyl.segment_distance(a, b) == pytest.approx(brute_segment(cyl, a, b), abs=1e-9)
    # Degenerate segment (a point) and a vertical segment along the axis through the solid.
    assert cyl.segment_distance((0.5, 0, 0), (0.5, 0, 0)) == pytest.approx(0.4)
    assert cyl.segment_distance((0, 0, -1), (0, 0, 1)) == pytest.approx(-0.1)
    box = Box((0, 0, 0), (0.2, 0.2, 0.2))
    assert box.segment_distance((0.3, 0.3, 0.3), (0.3, 0.3, 0.3)) == pytest.approx(math.sqrt(3) * 0.2)
    assert box.segment_distance((-1, 0, 0), (1, 0, 0)) == pytest.approx(-0.1)
    sph = Sphere((0, 0, 0), 0.1)
    assert sph.segment_distance((-1, 0.3, 0), (1, 0.3, 0)) == pytest.approx(0.2)


def test_links_clearance_reports_closest_link_and_table() -> None:
    pts = [(0, 0, 0), (0, 0, 0.3), (0.3, 0, 0.5), (0.6, 0, 0.2), (0.65, 0, 0.12)]
    caps = ArmCapsules(radii=(0.05, 0.05, 0.05, 0.02))
    scene = Scene((Sphere((0.3, 0.0, 0.7), 0.1),), table_height=0.0)
    c = links_clearance(pts, scene, caps)
    # Upper arm and forearm both end at the elbow (0.3, 0, 0.5): 0.2 - 0.1 - 0.05 = 0.05.
    assert c.distance == pytest.approx(0.05)
    assert c.link in (1, 2) and c.obstacle == 0
    low = Scene((), table_height=0.11)
    c = links_clearance(pts, low, caps)
    assert c.obstacle == TABLE and c.link == 3
    assert c.distance == pytest.approx(0.12 - 0.11 - 0.02)
    # The base link is not checked against the table by default.
    c = links_clearance(pts, Scene((), table_height=0.2), caps)
    assert c.link in (2, 3) and c.distance < 0
    assert links_clearance(pts, Scene(), caps).distance == math.inf


def test_scene_from_dict_round_trip_and_errors(tmp_path) -> None:
    d = {"name": "t", "table_height": 0.0, "obstacles": [
        {"type": "sphere", "center": [0.5, 0, 0.2], "radius": 0.05},
        {"type": "cylinder", "center": [0.4, 0.2, 0.1], "radius": 0.04, "height": 0.2, "name": "can"},
        {"type": "box", "center": [0.4, -0.2, 0.05], "size": [0.1, 0.1, 0.1], "yaw": 0.3}]}
    scene = Scene.from_dict(d)
    assert len(scene) == 3 and scene.obstacles[1].name == "can"
    assert Scene.from_dict(scene.to_dict()) == scene
    with pytest.raises(ConfigError, match="radius"):
        obstacle_from_dict({"type": "sphere", "center": [0, 0, 0]})
    with pytest.raises(ConfigError, match="type"):
        obstacle_from_dict({"type": "cone", "center": [0, 0, 0]})
    with pytest.raises(ConfigError):
        obstacle_from_dict({"type": "sphere", "center": [0, 0], "radius": 1})
    with pytest.raises(ConfigError, match="radius"):
        obstacle_from_dict({"type": "sphere", "center": [0, 0, 0], "radius": -1})
    with pytest.raises(ConfigError, match="unknown"):
        Scene.from_dict({"obstacle": []})
    with pytest.raises(InvalidInputError):
        Sphere((0, 0, math.nan), 1.0)
    bad = tmp_path / "bad.yaml"
    bad.write_text("obstacles: [ {type: sphere\n")
    with pytest.raises(ConfigError, match="YAML"):
        Scene.from_yaml(bad)
    with pytest.raises(ConfigError, match="bundled scenes"):
        load_scene("no_such_scene")


def test_bundled_scenes_load() -> None:
    from redarm_ros.geometry.obstacles import scenes_dir

    files = sorted(scenes_dir().glob("*.yaml"))
    assert files, "config/scenes/*.yaml missing"
    for f in files:
        scene = load_scene(f.stem)
        assert scene.name
        for o in scene.obstacles:
            if scene.table_height is not None:  # table-top scenes: obstacles rest on or above the table
                assert o.center[2] - (o.top - o.center[2]) >= scene.table_height - 1e-9


def test_obstacle_from_marker_fields() -> None:
    yaw = 0.4
    q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))  # ROS order x, y, z, w
    box = obstacle_from_marker(1, (0.5, 0.1, 0.1), q, (0.2, 0.1, 0.2), "crate")
    assert isinstance(box, Box) and box.yaw == pytest.approx(yaw) and box.size == (0.2, 0.1, 0.2)
    ball = obstacle_from_marker("sphere", (0.5, 0.0, 0.3), (0, 0, 0, 0), (0.1, 0.1, 0.1))
    assert isinstance(ball, Sphere) and ball.radius == pytest.approx(0.05)
    can = obstacle_from_marker(3, (0.4, 0.0, 0.1), (0, 0, 0, 1), (0.08, 0.08, 0.2))
    assert isinstance(can, Cylinder) and can.radius == pytest.approx(0.04) and can.height == 0.2
    tilted = (math.sin(0.3), 0.0, 0.0, math.cos(0.3))
    with pytest.raises(InvalidInputError, match="tilted"):
        obstacle_from_marker(3, (0.4, 0.0, 0.1), tilted, (0.08, 0.08, 0.2))
    with pytest.raises(InvalidInputError, match="marker type"):
        obstacle_from_marker(4, (0, 0, 0), (0, 0, 0, 1), (1, 1, 1))
    with pytest.raises(InvalidInputError):
        obstacle_from_marker(2, (0, 0, 0), (0, 0, 0, 1), (0, 0, 0))


def test_free_space_means_no_obstacle_and_no_table():
    assert Scene().free_space
    assert not Scene(table_height=0.0).free_space
    assert not Scene((Sphere((0.5, 0.0, 0.5), 0.1),)).free_space
