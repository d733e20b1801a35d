"""Base placement for a task set (redarm_ros.placement): exact against brute force, conservative inverse
reachability, engines that agree bit for bit, the task file and the command line."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from redarm_ros.errors import ConfigError
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, links_clearance
from redarm_ros.geometry.self_collision import collision_model, self_collision
from redarm_ros.kinematics import load_arm
from redarm_ros.placement import load_problem, place, problem_from_dict
from redarm_ros.placement.cli import main as placement_main
from redarm_ros.placement.evaluate import SWIVEL_STEP, evaluate_rows
from redarm_ros.placement.inverse import possible_pairs
from redarm_ros.placement.problem import base_transforms

TABLE = {"obstacles": [{"type": "box", "center": [0.0, 0.0, 0.35], "size": [0.8, 0.6, 0.7]}]}


def _pa10_problem(**kw):
    d = {
        "arm": "pa10",
        "base_height": 0.6,
        "grid": {"x": [-1.2, 1.2], "y": [-1.0, 1.0], "step": 0.2, "yaw_deg": [0, 120]},
        "footprint_radius": 0.2,
        "scene": TABLE,
        "tasks": [
            {"name": "a", "position": [-0.25, 0.1, 0.85], "rpy_deg": [180, 0, 0]},
            {"name": "b", "position": [0.25, 0.15, 0.85], "rpy_deg": [180, 0, 0]},
            {"name": "c", "position": [0.0, -0.2, 0.9], "rpy_deg": [150, 10, 40]},
        ],
    }
    d.update(kw)
    return problem_from_dict(d)


def _pc6_problem(**kw):
    # joint 3 locked: a vertical approach (tool x down) is reachable from any base position around it
    d = {
        "arm": "powercube6",
        "base_height": 0.3,
        "grid": {"x": [-0.9, 0.9], "y": [-0.9, 0.9], "step": 0.15, "yaw_deg": [0, 90]},
        "tasks": [
            {"position": [0.1, 0.0, 0.45], "rpy_deg": [0, 90, 0]},
            {"position": [-0.1, 0.15, 0.4], "rpy_deg": [0, 90, 30]},
        ],
    }
    d.update(kw)
    return problem_from_dict(d)


def _union_measure(ivs_per_pattern) -> float:
    """Measure (rad) of the union of swivel intervals on the circle."""
    iv = sorted((float(a), float(b)) for ivs in ivs_per_pattern for a, b in ivs)
    # merged on the unrolled line (intervals start in [-pi, pi))
    merged: list[list[float]] = []
    for a, b in iv:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    total = sum(b - a for a, b in merged)
    if merged and merged[-1][1] > math.pi:  # wraps past pi onto the first intervals
        over = merged[-1][1] - 2 * math.pi
        total -= sum(max(0.0, min(b, over) - a) for a, b in merged[:-1] if a < over)
    return min(total, 2 * math.pi)


def _brute_force(problem):
    """Every (base pose, task) pair by the scalar API: ik_nearest for reachability, feasible_swivels for
    the width, a scalar loop over the same swivel grid with the scalar collision checks for the margin."""
    arm = load_arm(problem.arm)
    poses = problem.grid.poses()
    B = base_transforms(poses, problem.base_height)
    m = len(problem.tasks)
    scene = Scene.from_dict(problem.scene) if problem.scene else None
    caps = ArmCapsules()
    md = collision_model(arm, caps)
    n = len(poses)
    reach = np.zeros((n, m), bool)
    width = np.full((n, m), np.nan)
    margin = np.full((n, m), np.nan)
    foot = np.ones(n, bool)
    S = -math.pi + SWIVEL_STEP * (np.arange(int(math.ceil(2 * math.pi / SWIVEL_STEP))) + 0.5)
    for i in range(n):
        if scene and problem.footprint_radius > 0:
            x, y = poses[i, :2]
            r, h = problem.footprint_radius, problem.base_height
            foot[i] = all(o.segment_distance((x, y, 0.0), (x, y, h)) >= r for o in scene.obstacles)
        Ts = [np.linalg.inv(B[i]) @ problem.tasks[j] for j in range(m)]
        for j, T in enumerate(Ts):
            q, _ = arm.ik_nearest(T, (arm.lower + arm.upper) / 2)
            reach[i, j] = q is not None
            if arm.has_swivel and reach[i, j]:
                width[i, j] = _union_measure(arm.feasible_swivels(T))
        if not (foot[i] and reach[i].all()):
            continue
        for j, T in enumerate(Ts):
            sols = [arm.ik(T)] if not arm.has_swivel else [arm.ik(T, float(s)) for s in S]
            Q = [q for rows in sols for q in rows]
            best = math.nan
            for q in Q:
                mg = float(np.minimum(q - arm.lower, arm.upper - q)[arm.upper > arm.lower].min())
                if not math.isnan(best) and mg <= best:
                    continue
                if self_collision(arm, q, model=md).min_distance < 0:
                    continue
                if scene is not None:
                    kp = arm.key_points(q) @ B[i, :3, :3].T + B[i, :3, 3]
                    if links_clearance(kp, scene, caps).distance < 0:
                        continue
                best = mg
            margin[i, j] = best
    valid = foot & reach.all(1) & ~np.isnan(margin).any(1)
    idx = np.nonzero(valid)[0]
    rob = np.min(np.where(valid[:, None], width, np.inf), axis=1) if arm.has_swivel else np.zeros(n)
    mar = np.min(np.where(valid[:, None], margin, np.inf), axis=1)
    ranking = sorted(idx, key=lambda k: (-round(float(rob[k]), 9), -round(float(mar[k]), 9), k))
    return reach, width, margin, foot, np.array(ranking, dtype=int)


@pytest.mark.parametrize("make", [_pa10_problem, _pc6_problem], ids=["pa10", "powercube6"])
def test_placement_equals_brute_force(make):
    problem = make()
    res = place(problem)
    reach, width, margin, foot, ranking = _brute_force(problem)
    assert np.array_equal(res.reach, reach)
    assert np.array_equal(res.footprint_ok, foot)
    if load_arm(problem.arm).has_swivel:
        np.testing.assert_allclose(res.width[reach], width[reach], atol=1e-6)
    assert res.valid.sum() > 3 and (~res.valid).sum() > 3  # the case decides something
    np.testing.assert_allclose(res.margin[res.valid], margin[res.valid], atol=1e-9)
    assert np.array_equal(res.ranking(), ranking)


@pytest.mark.parametrize("make", [_pa10_problem, _pc6_problem], ids=["pa10", "powercube6"])
def test_inverse_reachability_prunes_nothing_reachable(make):
    problem = make()
    pruned = evaluate_rows(problem, np.arange(problem.grid.size), prune=True)
    full = evaluate_rows(problem, np.arange(problem.grid.size), prune=False)
    for name in ("reach", "width", "footprint_ok", "checked", "free", "margin"):
        assert getattr(pruned, name).tobytes() == getattr(full, name).tobytes(), name
    assert not pruned.possible.all() and pruned.possible.any()


@pytest.mark.parametrize("arm_name", ["pa10", "powercube7", "powercube6"])
def test_inverse_map_is_conservative_on_random_pairs(arm_name):
    """Poses sampled near the shell's edges: every pair the map rules out has no solution."""
    arm = load_arm(arm_name)
    rng = np.random.default_rng(7)
    Q = rng.uniform(arm.lower, arm.upper, size=(300, arm.n))
    tasks = np.stack([arm.fk(q) for q in Q])
    poses = np.column_stack([rng.normal(0, 0.08, 300), rng.normal(0, 0.08, 300), rng.uniform(-3, 3, 300)])
    poss = possible_pairs(arm, tasks, poses, 0.0)
    diag = np.diagonal(poss)
    B = base_transforms(poses, 0.0)
    ruled_out = 0
    for k in range(300):
        q, _ = arm.ik_nearest(np.linalg.inv(B[k]) @ tasks[k], (arm.lower + arm.upper) / 2)
        if not diag[k]:
            ruled_out += 1
            assert q is None, f"pair {k} ruled out but reachable"
    assert ruled_out > 10  # the sample reaches the map's edges
    # the poses themselves, from the base that made them, are never ruled out
    assert possible_pairs(arm, tasks, np.zeros((1, 3)), 0.0).all()


@pytest.mark.slow
def test_engines_agree_bit_for_bit():
    problem = _pa10_problem()
    one = place(problem, workers=1)
    two = place(problem, workers=2, chunk=32)
    two_b = place(problem, workers=2)
    for name in ("possible", "reach", "width", "footprint_ok", "checked", "free", "margin"):
        assert getattr(one, name).tobytes() == getattr(two_b, name).tobytes(), name
        assert getattr(one, name).tobytes() == getattr(two, name).tobytes(), name


@pytest.mark.slow
def test_dask_engine_on_a_loopback_cluster_agrees_bit_for_bit():
    distributed = pytest.importorskip("distributed")
    problem = _pc6_problem()
    local = place(problem, workers=1)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None, protocol="tcp") as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        remote = place(problem, engine="dask", address=cluster.scheduler_address)
    for name in ("possible", "reach", "width", "footprint_ok", "checked", "free", "margin"):
        assert getattr(local, name).tobytes() == getattr(remote, name).tobytes(), name
    assert np.array_equal(local.ranking(), remote.ranking())


def test_task_file_errors_name_the_file(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("arm: pa10\ntasks:\n  - {position: [0.5, 0, 0.5], quaternion_xyzw: [0, 0, 0, 2]}\n")
    with pytest.raises(ConfigError, match="t.yaml.*unit quaternion"):
        load_problem(p)
    p.write_text("arm: pa10\ntask: []\n")
    with pytest.raises(ConfigError, match="unknown field"):
        load_problem(p)
    p.write_text("arm: [pa10\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_problem(p)
    with pytest.raises(ConfigError, match="step must be > 0"):
        problem_from_dict({"tasks": [{"position": [0.5, 0, 0.5]}],
                           "grid": {"x": [0, 1], "y": [0, 1], "step": 0}})


def test_command_line_writes_ranking_npz_and_heat_maps(tmp_path, capsys):
    import yaml

    problem = _pc6_problem()
    d = {"arm": "powercube6", "base_height": 0.3,
         "grid": {"x": [-0.9, 0.9], "y": [-0.9, 0.9], "step": 0.15, "yaw_deg": [0, 90]},
         "tasks": [{"position": [0.1, 0.0, 0.45], "rpy_deg": [0, 90, 0]},
                   {"position": [-0.1, 0.15, 0.4], "rpy_deg": [0, 90, 30]}]}
    f = tmp_path / "tasks.yaml"
    f.write_text(yaml.safe_dump(d))
    out = tmp_path / "out"
    assert placement_main([str(f), "--out", str(out), "--workers", "1"]) == 0
    data = np.load(out / "placements.npz")
    res = place(problem)
    assert np.array_equal(data["ranking"], res.ranking())
    assert data["valid"].shape == (problem.grid.size,)
    assert float(data["base_height"]) == 0.3  # the view needs it to put the map on the floor
    maps = sorted(p.name for p in out.glob("heatmap_yaw*.png"))
    assert maps == ["heatmap_yaw000.png", "heatmap_yaw090.png"]
    lines = (out / "ranking.csv").read_text().splitlines()
    assert len(lines) == 1 + res.valid.sum()
    # nothing reachable: exit 1; bad file: exit 2
    d["tasks"] = [{"position": [5.0, 5.0, 5.0]}]
    d["grid"] = {"x": [0, 0.2], "y": [0, 0.2], "step": 0.1, "yaw_deg": [0]}
    f.write_text(yaml.safe_dump(d))
    assert placement_main([str(f), "--out", str(out), "--workers", "1", "--no-plots"]) == 1
    f.write_text("tasks: 3\n")
    assert placement_main([str(f), "--out", str(out)]) == 2


def test_summary_and_index_of_a_base_pose():
    res = place(_pc6_problem())
    s = res.summary(top=3)
    assert (s["arm"], s["base_height"], s["tasks"]) == ("powercube6", 0.3, 2)
    assert s["base_poses"] == res.poses.shape[0]
    assert s["valid"] == int(res.valid.sum()) > 3 and len(s["best"]) == 3
    for b, i in zip(s["best"], res.ranking(), strict=False):
        x, y, w = res.poses[i]
        assert (b["x"], b["y"], b["yaw_deg"]) == (round(x, 6), round(y, 6), round(math.degrees(w), 6))
        assert b["worst_margin_rad"] == round(float(res.worst_margin[i]), 6)
        assert b["robustness_rad"] is None  # a 6-DOF arm has no swivel
        assert res.index_of(x, y, w + 2 * math.pi) == i and res.index_of(x, y, w - 2 * math.pi) == i
    assert res.index_of(0.05, 0.0, 0.0) is None and res.index_of(0.0, 0.0, math.radians(45)) is None
    assert res.index_of(0.0, 0.0, 0.0) is not None


def test_base_height_and_yaw_move_the_tasks_into_the_base_frame():
    problem = dataclasses.replace(_pc6_problem(), check_collisions=False)
    res = place(problem)
    arm = load_arm("powercube6")
    B = base_transforms(problem.grid.poses(), problem.base_height)
    i = int(res.ranking()[0])
    for T in problem.tasks:
        assert len(arm.ik(np.linalg.inv(B[i]) @ T)) > 0


def test_capability_map_is_the_same_on_worker_processes():
    from redarm_ros.kinematics.reachability import capability_map

    arm = load_arm("pa10")
    one = capability_map(arm, step=0.25, orientations=8, chunk=256)
    two = capability_map(arm, step=0.25, orientations=8, chunk=256, workers=2)
    assert one.fraction.tobytes() == two.fraction.tobytes()
    assert one.width.tobytes() == two.width.tobytes()
    assert one.fraction.max() > 0.5


@pytest.mark.slow
def test_placement_benchmark_smoke(monkeypatch, capsys):
    """benchmarks/placement_bench.py in quick mode on the powercube6 task set: every section is there and
    pruning changes nothing."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "placement_bench.py"
    monkeypatch.syspath_prepend(str(path.parent))
    spec = importlib.util.spec_from_file_location("placement_bench", path)
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "placement_bench", mod)
    spec.loader.exec_module(mod)
    monkeypatch.setattr(mod, "TASK_SETS", ("table_powercube6",))
    assert mod.main(["--quick", "--no-write"]) == 0
    out = capsys.readouterr().out
    for title in ("pruning and agreement", "throughput per core", "workers", "cost model and plan",
                  "Capability map through the engine"):
        assert title in out
    assert "every array is identical: **True**; rankings equal: **True**" in out
    assert "| 64 | 1024 |" in out
