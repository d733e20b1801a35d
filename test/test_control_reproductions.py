"""Paper reproductions at reduced size: PNGs are written and the scenarios behave as in the papers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from redarm_ros.control.reproductions import (
    EXAMPLE2_CENTER,
    example2_ramp,
    main,
    run_swivel_example,
    swivel_scene,
)
from redarm_ros.control.swivel_dynamics import SwivelParams
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics import load_arm

pytest.importorskip("matplotlib")


BLIND = SwivelParams(lam_des=0.5, lam_obs=0.0, lam_sing=0.0, lam_lim=0.0)


@pytest.mark.parametrize("s_des", [-3 * math.pi / 4, -0.9 * math.pi])
def test_example1_sphere_is_met_at_two_s_des_and_the_obstacle_force_keeps_the_elbow_clear(s_des) -> None:
    arm = load_arm("pa10")
    scene = swivel_scene(1)
    avoid = run_swivel_example(arm, scene, lambda t: s_des, laps=1.0)
    blind = run_swivel_example(arm, scene, lambda t: s_des, laps=1.0, params=BLIND)
    assert blind.clearance.min() < 0.0  # the fixed s_des would drive the elbow into the ball
    assert avoid.clearance.min() > 0.0
    assert abs(avoid.s - avoid.s_des).max() > 0.1  # ... because s left s_des
    assert np.all(np.isfinite(avoid.q))  # an in-limit IK solution at every step


def test_example1_other_s_des_never_meet_the_sphere_and_forms_agree() -> None:
    arm = load_arm("pa10")
    scene = swivel_scene(1)
    for s_des in (-math.pi / 2, 3 * math.pi / 4, math.pi / 2):
        run = run_swivel_example(arm, scene, lambda t, v=s_des: v, laps=1.0)
        assert abs(run.s - s_des).max() < 1e-9 and run.clearance.min() > 0.1
    # the angle form and the swivel-quaternion form give the same motion
    quat = run_swivel_example(arm, scene, lambda t: -3 * math.pi / 4, laps=0.5, quaternion_form=True)
    angle = run_swivel_example(arm, scene, lambda t: -3 * math.pi / 4, laps=0.5)
    assert abs(quat.s - angle.s).max() < 0.02
    free = run_swivel_example(arm, Scene(), lambda t: -math.pi / 2, laps=0.5)
    assert abs(free.s + math.pi / 2).max() < 1e-9


def test_example2_ramp_covers_more_than_half_a_turn_and_the_sphere_holds_s_back() -> None:
    arm = load_arm("pa10")
    total = 12.0
    ramp = example2_ramp(total)
    s_des = np.unwrap([ramp(t) for t in np.linspace(0.0, total, 200)])
    assert s_des[-1] - s_des[0] > 1.5 * math.pi  # 0.8 of a turn (the paper's figure: more than half)
    scene = swivel_scene(2)
    with_o = run_swivel_example(arm, scene, ramp, 3.0, center=EXAMPLE2_CENTER, quaternion_form=True)
    blind = run_swivel_example(arm, scene, ramp, 3.0, center=EXAMPLE2_CENTER, quaternion_form=True,
                               params=BLIND)
    assert blind.clearance.min() < 0.0 and with_o.clearance.min() > 0.0
    assert np.all(np.isfinite(with_o.q))
    lag = np.abs(np.unwrap(with_o.s) - np.unwrap(with_o.s_des))
    assert lag.max() > 0.5  # held back by the sphere (the figure's dip) ...
    assert lag[-1] < 0.3  # ... and back on the ramp at the end


def test_reproductions_write_pngs_and_report(tmp_path) -> None:
    assert main(["--out", str(tmp_path), "--quick"]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == sorted([
        "swivel_example1_s.png", "swivel_example1_elbow.png", "swivel_example2_s.png",
        "swivel_example2_elbow.png", "attractor_narrow_passage.png", "attractor_moved_target.png",
        "attractor_appearing_obstacle.png"])
    for name in pngs:
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and 10_000 < len(data) < 250_000
    reports = json.loads((tmp_path / "reproductions.json").read_text())
    assert "| scenario |" in (tmp_path / "reproductions.md").read_text()
    by = {(r["scenario"], r["variant"]): r for r in reports}
    attractor = ("narrow", "moved_target", "appearing_obstacle")
    assert set(attractor) <= {k[0] for k in by}  # every attractor scenario is in the report
    for key in [k for k in by if k[0] in attractor]:
        r = by[key]
        assert r["reached"] and r["pos_err"] < 1e-3, key
        assert r["min_clearance"] > 0.0, key
        assert r["limit_margin"] >= 0.0, key
    for v in ("-2.36", "-2.83"):  # example 1: the sphere is met at two s_des
        assert by[("swivel1", f"s_des={v} obstacle")]["min_clearance"] > 0.0
        assert by[("swivel1", f"s_des={v} ignoring it")]["min_clearance"] < 0.0
    assert by[("swivel2", "ramp obstacle")]["min_clearance"] > 0.0
