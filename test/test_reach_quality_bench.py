"""benchmarks/reach_quality_bench.py and benchmarks/route_oracle.py: the oracle's verdicts on hand-built
routes, the speed-profile scores on synthetic profiles, and a one-move smoke run of the benchmark.

No timing is asserted; the smoke run checks the output's structure and what holds by construction.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from support.benches import load_bench

from redarm_ros.kinematics import load_arm

oracle = load_bench("route_oracle")
bench = load_bench("reach_quality_bench")
pose_down = load_bench("bench_common").pose_down
PA10 = load_arm("pa10")
READY = np.array([0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])


def _start(p: tuple[float, float, float]) -> np.ndarray:
    q, _ = PA10.ik_nearest(pose_down(p), READY)
    assert q is not None
    return np.asarray(q)


def test_oracle_finds_a_short_straight_route_and_its_chain_is_continuous() -> None:
    q0 = _start((0.5, -0.1, 0.3))
    T1 = pose_down((0.55, 0.15, 0.25), 0.4)
    v = oracle.straight_route(PA10, q0, T1)
    assert v.exists and v.reached_u == 1.0
    path = v.path
    assert path is not None and path.shape == (oracle.ROUTE_SAMPLES + 1, 7)
    assert np.array_equal(path[0], q0)
    assert float(np.max(np.abs(np.diff(path, axis=0)))) <= oracle.MAX_JUMP
    assert np.all(path >= PA10.lower - 1e-9) and np.all(path <= PA10.upper + 1e-9)
    # every node is on the route's pose and on the start's flip pattern
    poses = oracle.route_poses(PA10.fk(q0), T1)
    for k in range(1, len(path)):
        assert np.allclose(PA10.fk(path[k]), poses[k], atol=1e-7)
        assert np.array_equal(path[k, [1, 3, 5]] < 0.0, q0[[1, 3, 5]] < 0.0)
    assert oracle.straight_route(PA10, q0, T1, margin=oracle.SINGULAR_MARGIN).exists


def test_oracle_refuses_a_line_through_the_shoulder() -> None:
    # The hand crosses over the base: at mid-route the wrist is 0.17 m from the shoulder, which needs
    # the elbow folded beyond its 137 deg limit: no in-limit solution there, whatever the swivel.
    q0 = _start((0.5, 0.0, 0.4))
    T1 = pose_down((-0.5, 0.0, 0.4))
    assert len(PA10.ik(T1, 0.0, limits=False)) > 0  # the goal itself is reachable
    v = oracle.straight_route(PA10, q0, T1)
    assert not v.exists and v.path is None
    assert v.reached_u < 0.5
    assert min(v.nodes) == 0


def test_oracle_margin_and_jump_bound_only_remove_routes() -> None:
    rng = np.random.default_rng(7)
    found = {"plain": 0, "margin": 0}
    for _ in range(6):
        q0 = rng.uniform(0.7 * PA10.lower, 0.7 * PA10.upper)
        T1 = PA10.fk(rng.uniform(0.7 * PA10.lower, 0.7 * PA10.upper))
        plain = oracle.straight_route(PA10, q0, T1)
        margin = oracle.straight_route(PA10, q0, T1, margin=oracle.SINGULAR_MARGIN)
        tight = oracle.straight_route(PA10, q0, T1, max_jump=0.05)
        assert margin.reached_u <= plain.reached_u and tight.reached_u <= plain.reached_u
        found["plain"] += plain.exists
        found["margin"] += margin.exists
    assert found["plain"] >= found["margin"]


def test_oracle_six_dof_arm() -> None:
    # joint 3 of the 6-DOF arm is locked: the tool can only approach in the arm's vertical plane, so a
    # move in that plane with the same orientation has a route, and a turn out of it has none.
    arm = load_arm("powercube6")
    q0 = np.array([0.0, 0.4, 0.0, -1.2, -0.8, 0.0])
    T0 = arm.fk(q0)
    T1 = T0.copy()
    T1[:3, 3] += (0.05, 0.0, 0.05)
    v = oracle.straight_route(arm, q0, T1)
    assert v.exists and v.path is not None
    assert float(np.max(np.abs(np.diff(v.path, axis=0)))) <= oracle.MAX_JUMP
    T2 = arm.fk(q0 + np.array([0.6, 0.0, 0.0, 0.0, 0.0, 0.0]))
    T2[:3, :3] = T0[:3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert not oracle.straight_route(arm, q0, T2).exists


def _min_jerk_speed(n: int, length: float = 0.3) -> np.ndarray:
    tau = (np.arange(n) + 0.5) / n
    return length / (n * bench.DT) * 30.0 * tau**2 * (1.0 - tau) ** 2


def test_speed_peaks_and_min_jerk_deviation() -> None:
    v = _min_jerk_speed(150)
    assert bench.speed_peaks(v) == 1
    assert bench.min_jerk_deviation(v) < 0.01
    # ripple below the hysteresis (10 % of the peak) is one peak still
    ripple = v * (1.0 + 0.04 * np.sin(np.linspace(0.0, 40.0, len(v))))
    assert bench.speed_peaks(ripple) == 1
    # a stop mid-move and a second movement: two peaks, far from the minimum-jerk profile
    double = np.concatenate([_min_jerk_speed(80), _min_jerk_speed(80)])
    assert bench.speed_peaks(double) == 2
    assert bench.min_jerk_deviation(double) > 0.2
    # a constant-speed move (a trapezoid) is single-peaked but not minimum-jerk
    trap = np.minimum(np.minimum(np.arange(150), np.arange(150)[::-1]) / 20.0, 1.0) * 0.3
    assert bench.speed_peaks(trap) == 1
    assert bench.min_jerk_deviation(trap) > 0.1


def test_baselines_by_construction() -> None:
    q0 = _start((0.5, -0.1, 0.3))
    T1 = pose_down((0.55, 0.15, 0.25), 0.4)
    caps = bench.ControllerParams().capsules
    scene = bench.Scene()
    line = bench.cartesian_line(PA10, q0, T1, 0.4)
    joint = bench.joint_move(PA10, q0, T1, 0.4)
    for tr in (line, joint):
        assert tr.reached and np.array_equal(tr.q[0], q0)
        assert PA10.pose_error(tr.q[-1], T1)[0] < 1e-6
        sc = bench.score(PA10, scene, tr, T1, caps)
        assert not sc["limit_violation"] and not sc["collision"]
        assert sc["peaks"] == 1 and sc["mj_dev"] < 0.05
        assert sc["peak_speed"] <= 0.4 * 1.01
    assert bench.score(PA10, scene, line, T1, caps)["path_ratio"] < 1.001
    # a line through the shoulder fails where it leaves the limits
    bad = bench.cartesian_line(PA10, _start((0.5, 0.0, 0.4)), pose_down((-0.5, 0.0, 0.4)), 0.4)
    assert not bad.reached and ("no solution" in bad.reason or "jump" in bad.reason)


@pytest.mark.slow
def test_smoke_run_writes_every_move_and_the_summary(tmp_path: Path, capsys) -> None:
    out = tmp_path / "moves.json"
    assert bench.main(["--moves", "1", "--arms", "pa10", "--cases", "free45,table_cylinder", "--no-write",
                       "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert bench.SUMMARY_HEADER.splitlines()[0] in text
    for case in ("free45", "table_cylinder"):
        for method in bench.METHODS:
            assert f"| pa10 | {case} | {method} | 1 |" in text
    assert "Load average (1/5/15 min) before:" in text and "ReachController at commit" in text
    data = json.loads(out.read_text())
    assert set(data) == {"controller", "targets", "moves"}
    moves = data["moves"]
    assert len(moves) == 2 * len(bench.METHODS)
    for m in moves:
        assert set(m) >= {"arm", "case", "method", "reached", "replanned", "path_ratio", "peaks", "mj_dev",
                          "time_s", "limit_violation", "collision", "oracle", "oracle_margin", "straight"}
        if m["reached"]:
            assert m["path_ratio"] >= 1.0 - 1e-6 and m["peaks"] >= 1 and math.isfinite(m["time_s"])
        if m["oracle_margin"]:
            assert m["oracle"]
        if m["method"] != "controller":
            assert not m["replanned"]
    # the oracle's verdict is per move, the same for every method
    for case in ("free45", "table_cylinder"):
        assert len({m["oracle"] for m in moves if m["case"] == case}) == 1


def test_smoke_run_on_the_urdf_arm(capsys) -> None:
    # the iiwa14-like arm from its URDF (redarm_ros/sim/urdf_arms.py), from the model's ready posture
    assert bench.main(["--moves", "1", "--arms", "iiwa14", "--cases", "free45", "--no-write"]) == 0
    text = capsys.readouterr().out
    for method in bench.METHODS:
        assert f"| iiwa14_like | free45 | {method} | 1 |" in text
