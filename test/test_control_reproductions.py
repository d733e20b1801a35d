"""Paper reproductions at reduced size: PNGs are written and the scenarios behave as in the papers."""

from __future__ import annotations

import json
import math

import pytest

from redarm_ros.control.obstacles import Scene
from redarm_ros.control.reproductions import main, run_swivel_example, swivel_scene
from redarm_ros.control.swivel_dynamics import SwivelParams
from redarm_ros.kinematics import load_arm

pytest.importorskip("matplotlib")


def test_swivel_obstacle_force_is_what_keeps_the_elbow_clear() -> None:
    arm = load_arm("pa10")
    scene = swivel_scene()
    avoid = run_swivel_example(arm, scene, lambda t: -math.pi / 2, laps=1.0)
    blind = run_swivel_example(arm, scene, lambda t: -math.pi / 2, laps=1.0,
                               params=SwivelParams(lam_des=0.5, lam_obs=0.0, lam_sing=0.0, lam_lim=0.0))
    assert blind.clearance.min() < 0.0  # the fixed s_des would drive the elbow into the ball
    assert avoid.clearance.min() > 0.0
    assert abs(avoid.s - avoid.s_des).max() > 0.1  # ... because s left s_des
    # the angle form and the swivel-quaternion form give the same motion
    quat = run_swivel_example(arm, scene, lambda t: -math.pi / 2, laps=0.5, quaternion_form=True)
    angle = run_swivel_example(arm, scene, lambda t: -math.pi / 2, laps=0.5)
    assert abs(quat.s - angle.s).max() < 0.02
    free = run_swivel_example(arm, Scene(), lambda t: -math.pi / 2, laps=0.5)
    assert abs(free.s + math.pi / 2).max() < 1e-9


def test_reproductions_write_pngs_and_report(tmp_path) -> None:
    assert main(["--out", str(tmp_path), "--quick"]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == sorted([
        "swivel_example1_s.png", "swivel_example1_elbow.png", "swivel_example2_s.png",
        "swivel_example2_elbow.png", "attractor_narrow_passage.png", "attractor_moved_target.png",
        "attractor_appearing_obstacle.png"])
    for name in pngs:
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    reports = json.loads((tmp_path / "reproductions.json").read_text())
    assert "| scenario |" in (tmp_path / "reproductions.md").read_text()
    by = {(r["scenario"], r["variant"]): r for r in reports}
    for key in [k for k in by if k[0] in ("narrow", "moved_target", "appearing_obstacle")]:
        r = by[key]
        assert r["reached"] and r["pos_err"] < 1e-3, key
        assert r["min_clearance"] > 0.0, key
        assert r["limit_margin"] >= 0.0, key
    assert by[("swivel1", "s_des=-1.57 obstacle")]["min_clearance"] > 0.0
    assert by[("swivel1", "s_des=-1.57 ignoring it")]["min_clearance"] < 0.0
    assert by[("swivel2", "ramp obstacle")]["min_clearance"] > 0.0
