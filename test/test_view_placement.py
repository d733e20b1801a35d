"""The placement heat map in the browser view: the floor geometry (no browser, no ROS) seen from the arm
standing at the best placement, the npz it is read from, the viser drawing and the view node's option."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.placement import place, problem_from_dict
from redarm_ros.placement.cli import write_outputs
from redarm_ros.view.placement_floor import FLOOR_LIFT, floor_meshes, load_placements, placement_floor

H = 0.5  # base height (m)


def _data(**kw: Any) -> dict[str, Any]:
    """A hand-made 3 x 2 x 2 result: valid at (0.1, 0.1, 90 deg) (best) and (0.2, 0.1, 0 deg)."""
    x, y, yaw = np.array([0.0, 0.1, 0.2]), np.array([0.0, 0.1]), np.array([0.0, math.pi / 2])
    frac = np.zeros((3, 2, 2))
    frac[0, 0] = [0.0, 0.0]  # nothing reachable: not drawn
    frac[0, 1] = [0.5, 0.0]
    frac[1, 0] = [0.0, 0.5]
    frac[1, 1] = [0.5, 1.0]
    frac[2, 0] = [0.5, 0.5]
    frac[2, 1] = [1.0, 0.5]
    valid = np.zeros((3, 2, 2), dtype=bool)
    valid[1, 1, 1] = valid[2, 1, 0] = True
    i_best, i_other = np.ravel_multi_index((1, 1, 1), (3, 2, 2)), np.ravel_multi_index((2, 1, 0), (3, 2, 2))
    task = np.eye(4)
    task[:3, 3] = (0.6, 0.1, 1.0)
    d = {"x": x, "y": y, "yaw": yaw, "shape": np.array([3, 2, 2]), "base_height": np.float64(H),
         "valid": valid.ravel(), "fraction": frac.ravel(), "ranking": np.array([i_best, i_other]),
         "tasks": task[None], "arm": np.array("pa10")}
    d.update(kw)
    return d


def test_map_is_seen_from_the_arm_at_the_best_placement() -> None:
    f = placement_floor(_data())
    assert f.best == (0.1, 0.1, math.pi / 2) and f.best_valid and (f.n_valid, f.n_poses) == (2, 12)
    assert len(f.corners) == 5  # the cell with nothing reachable is left out
    z = FLOOR_LIFT - H  # the floor, base_height below the arm's base
    np.testing.assert_allclose(f.corners[..., 2], z, atol=1e-12)
    # Share per cell = max over the yaws; the best cell (1, 1) lies right under the arm.
    centres = {tuple(np.round(c.mean(axis=0), 9)): s for c, s in zip(f.corners, f.fraction, strict=True)}
    assert centres[(0.0, 0.0, round(z, 9))] == 1.0
    # The best base faces world +y (yaw 90 deg): world +x is on the arm's right (-y), world -y behind it.
    assert centres[(0.0, -0.1, round(z, 9))] == 1.0  # world (0.2, 0.1)
    assert centres[(-0.1, 0.0, round(z, 9))] == 0.5  # world (0.1, 0.0)
    assert centres[(0.0, 0.1, round(z, 9))] == 0.5  # world (0.0, 0.1)
    assert centres[(-0.1, -0.1, round(z, 9))] == 0.5  # world (0.2, 0.0)
    # Squares are 0.1 m across, counter-clockwise seen from above.
    for c in f.corners:
        e1, e2 = c[1] - c[0], c[2] - c[1]
        assert math.isclose(np.linalg.norm(e1), 0.1) and math.isclose(np.linalg.norm(e2), 0.1)
        assert np.cross(e1, e2)[2] > 0
    # Viridis, as in the PNG heat maps: all tasks reachable is yellow.
    assert tuple(f.colors[f.fraction == 1.0][0]) == (253, 231, 37)
    # The task at world (0.6, 0.1, 1.0) is 0.5 m along world x, i.e. to the arm's right, 0.5 m up.
    np.testing.assert_allclose(f.tasks, [[0.0, -0.5, 1.0 - H]], atol=1e-12)
    # The best mark sits at the arm's feet, its heading line along the arm's x.
    np.testing.assert_allclose(f.best_mark[2], [[0, 0, z], [0.3, 0, z]], atol=1e-12)


def test_outline_is_the_boundary_of_the_cells_valid_for_some_yaw() -> None:
    f = placement_floor(_data())
    # Two valid neighbours along x, (1, 1) and (2, 1): their shared side is not drawn, 6 sides are.
    assert f.outline.shape == (6, 2, 3)
    lengths = np.linalg.norm(f.outline[:, 1] - f.outline[:, 0], axis=1)
    np.testing.assert_allclose(lengths, 0.1)
    mids = np.round((f.outline[:, 0] + f.outline[:, 1])[:, :2] / 2, 9)
    assert not any(np.allclose(m, [0.0, -0.05]) for m in mids)  # the shared side (world x = 0.15)
    # The grid's border: a 0.3 m x 0.2 m rectangle.
    assert f.extent.shape == (4, 2, 3)
    assert math.isclose(float(np.linalg.norm(f.extent[:, 1] - f.extent[:, 0], axis=1).sum()), 1.0)


def test_no_valid_placement_stands_the_arm_at_the_largest_share() -> None:
    d = _data(valid=np.zeros(12, dtype=bool), ranking=np.zeros(0, dtype=int))
    f = placement_floor(d)
    assert not f.best_valid and f.n_valid == 0 and len(f.outline) == 0
    assert f.best == (0.1, 0.1, math.pi / 2)  # the first pose with share 1.0
    assert "No valid placement" in f.markdown()
    assert "best placement" in placement_floor(_data()).markdown("out/placements.npz")


def test_meshes_one_per_colour_cover_every_square() -> None:
    f = placement_floor(_data())
    meshes = floor_meshes(f)
    assert len(meshes) == 2  # shares 0.5 and 1.0
    assert sum(len(faces) for _, _, faces in meshes) == 2 * len(f.corners)
    for rgb, verts, faces in meshes:
        assert faces.max() == len(verts) - 1 and len(verts) == 2 * len(faces)
        sel = [tuple(c) == rgb for c in f.colors]
        np.testing.assert_allclose(verts, f.corners[sel].reshape(-1, 3))


def test_round_trip_through_redarm_placement_outputs(tmp_path: Path) -> None:
    problem = problem_from_dict({
        "arm": "pa10", "base_height": 0.3, "check_collisions": False,
        "grid": {"x": [-0.6, 0.6], "y": [-0.6, 0.6], "step": 0.3, "yaw_deg": [0, 90, 180, 270]},
        "tasks": [{"position": [0.3, 0.2, 0.7], "rpy_deg": [180, 0, 0]},
                  {"position": [0.2, -0.3, 0.6], "rpy_deg": [180, 0, 30]}]})
    res = place(problem, workers=1)
    write_outputs(res, tmp_path, plots=False)
    data = load_placements(tmp_path / "placements.npz")
    assert float(data["base_height"]) == 0.3
    f = placement_floor(data)
    best = res.ranking()[0]
    assert f.best == tuple(float(v) for v in res.poses[best]) and f.n_valid == int(res.valid.sum())
    # Mapped back to the world, each square's centre carries the best share over the yaws there.
    from redarm_ros.placement.problem import base_transforms

    B = base_transforms(np.array([f.best]), 0.3)[0]
    frac = res.fraction.reshape(problem.grid.shape).max(axis=2)
    for c, share in zip(f.corners, f.fraction, strict=True):
        w = B[:3, :3] @ c.mean(axis=0) + B[:3, 3]
        ix, iy = np.argmin(abs(problem.grid.x - w[0])), np.argmin(abs(problem.grid.y - w[1]))
        assert math.isclose(w[0], problem.grid.x[ix], abs_tol=1e-9)
        assert math.isclose(w[2], FLOOR_LIFT, abs_tol=1e-9)
        assert share == frac[ix, iy] > 0
    np.testing.assert_allclose(f.tasks, (problem.tasks[:, :3, 3] - B[:3, 3]) @ B[:3, :3], atol=1e-12)


def test_bad_placement_files_are_refused_with_the_file_named(tmp_path: Path) -> None:
    with pytest.raises(InvalidInputError, match="cannot read placements file"):
        load_placements(tmp_path / "missing.npz")
    old = tmp_path / "old.npz"
    np.savez(old, **{k: v for k, v in _data().items() if k != "base_height"})
    with pytest.raises(InvalidInputError, match=r"old\.npz .*missing base_height"):
        load_placements(old)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **_data(fraction=np.zeros(5)))
    with pytest.raises(InvalidInputError, match="do not match shape"):
        load_placements(bad)


# -- viser and the node ---------------------------------------------------------------------------------
def test_viewer_draws_the_map_and_explains_it(tmp_path: Path) -> None:
    viser = pytest.importorskip("viser")
    from redarm_ros.view.urdf_model import model_for_arm
    from redarm_ros.view.viewer import ArmViewer

    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        v = ArmViewer(srv, model_for_arm("pa10"))
        f = placement_floor(_data())
        v.set_placement(f, "run/placements.npz")
        np.testing.assert_allclose(srv.scene._handle_from_node_name["/ground"].position, (0.4, 0.0, -H))
        names = sorted(n.name for n in v._placement_nodes)
        assert names == ["/placement/best", "/placement/extent", "/placement/share_0", "/placement/share_1",
                         "/placement/tasks", "/placement/valid"]
        assert "`placements.npz`" in v._placement_md.content and "best placement" in v._placement_md.content
        v.set_placement(placement_floor(_data(valid=np.zeros(12, dtype=bool), ranking=np.zeros(0, int))))
        assert "/placement/valid" not in [n.name for n in v._placement_nodes]
        assert "No valid placement" in v._placement_md.content
    finally:
        srv.stop()


def test_view_node_placement_option(rclpy_context: Any, tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    pytest.importorskip("viser")
    from rclpy.parameter import Parameter

    from redarm_ros.nodes.view import ViewNode, ros_argv

    assert ros_argv(["--placement", "p.npz"]) == ["--ros-args", "-p", "placement:=p.npz"]
    path = tmp_path / "placements.npz"
    np.savez(path, **_data())
    node = ViewNode(context=rclpy_context, parameter_overrides=[Parameter("port", value=0),
                                                                Parameter("placement", value=str(path))])
    try:
        assert "best placement" in node.viewer._placement_md.content
        assert len(node.viewer._placement_nodes) == 6
    finally:
        node.close()
        node.destroy_node()
    with pytest.raises(ValueError, match="cannot read placements file"):
        ViewNode(context=rclpy_context, parameter_overrides=[
            Parameter("port", value=0), Parameter("placement", value=str(tmp_path / "none.npz"))])
