"""``redarm-demo --placement``: the demo's goals as a placement task set, studied in this process before
the run (no ROS here: the stack is replaced by one that does not start)."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from redarm_ros import demo as demo_mod
from redarm_ros.demo import DEMOS, PLACEMENT_GRID, Goal, build_parser, demo_placement, demo_placement_problem

SMALL_GRID = {"x": [-0.2, 0.2], "y": [-0.2, 0.2], "step": 0.2, "yaw_deg": [0, 90]}


def test_task_set_is_the_goals_the_demo_expects_to_reach() -> None:
    d = DEMOS["pa10"]
    p = demo_placement_problem(d)
    reachable = [g for g in d.goals if g.reachable]
    assert p.task_names == tuple(g.name for g in reachable) and "out_of_reach" not in p.task_names
    for T, g in zip(p.tasks, reachable, strict=True):
        np.testing.assert_allclose(T, g.matrix(), atol=1e-12)
    assert p.arm == "pa10" and p.base_height == 0.0
    assert [o["name"] for o in p.scene["obstacles"]] == ["ball"] and p.scene["table_height"] == 0.0
    # +-1 m at 0.1 m, yaw every 45 deg, around the current base
    assert p.grid.shape == (21, 21, 8) and PLACEMENT_GRID["yaw_step_deg"] == 45.0
    np.testing.assert_allclose(p.grid.yaw, np.radians(np.arange(0, 360, 45)))


@pytest.mark.parametrize("arm", ["pa10", "powercube6"])
def test_placement_says_best_and_that_the_current_base_serves_the_demo(tmp_path: Path, arm: str) -> None:
    lines: list[str] = []
    res = demo_placement(DEMOS[arm], tmp_path / "placement", lines.append, grid=SMALL_GRID, workers=1)
    here = res.index_of(0.0, 0.0, 0.0)
    assert here is not None and res.valid[here]  # the demo reaches these goals from where it stands
    b = res.poses[res.ranking()[0]]
    assert len(lines) == 1
    assert f"best x {b[0]:+.2f} m, y {b[1]:+.2f} m, yaw {math.degrees(b[2]):.0f} deg" in lines[0]
    assert "the current base (0, 0, 0) is valid" in lines[0]
    out = tmp_path / "placement"
    assert (out / "placements.npz").is_file() and (out / "ranking.csv").is_file()
    pngs = sorted(p.name for p in out.glob("heatmap_yaw*.png"))
    assert pngs == ["heatmap_yaw000.png", "heatmap_yaw090.png"]


def test_current_base_off_the_grid_or_not_valid_is_said(tmp_path: Path) -> None:
    lines: list[str] = []
    demo_placement(DEMOS["pa10"], tmp_path, lines.append, plots=False, workers=1,
                   grid={"x": [0.5, 0.5], "y": [0.0, 0.0], "yaw_deg": [0]})
    assert "is not on the grid" in lines[0]
    # A goal 1.5 m ahead: out of reach from (0, 0, 0), in reach with the base 1 m closer.
    far = dataclasses.replace(DEMOS["pa10"], goals=(Goal("far", (1.5, 0.0, 0.3)),))
    lines.clear()
    res = demo_placement(far, tmp_path, lines.append, plots=False, workers=1,
                         grid={"x": [0.0, 1.0], "y": [0.0, 0.0], "step": 1.0, "yaw_deg": [0]})
    assert res.index_of(0.0, 0.0, 2 * math.pi) == res.index_of(0.0, 0.0, 0.0)  # a whole turn is the same
    assert list(res.valid) == [False, True]
    assert "best x +1.00 m, y +0.00 m, yaw 0 deg" in lines[0]
    assert "the current base (0, 0, 0) is NOT valid" in lines[0]


class _NoStack:
    """Stands in for the ROS stack: refuses to start, so the demo stops right after its preparations."""

    def __init__(self, *a: Any, **kw: Any) -> None:
        pass

    def start(self) -> None:
        raise RuntimeError("no stack in this test")

    def close(self) -> None:
        pass


@pytest.mark.parametrize("flag", [False, True])
def test_option_is_off_by_default_and_runs_before_the_stack(tmp_path: Path, monkeypatch: Any,
                                                            flag: bool) -> None:
    calls: list[Path] = []
    monkeypatch.setattr(demo_mod, "Stack", _NoStack)
    monkeypatch.setattr(demo_mod, "demo_placement", lambda d, out, say: calls.append(out))
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    argv = ["--output", str(tmp_path)] + (["--placement"] if flag else [])
    args: argparse.Namespace = build_parser().parse_args(argv)
    assert args.placement is flag
    out: list[str] = []

    class Sink:
        def write(self, s: str) -> None:
            out.append(s)

        def flush(self) -> None:
            pass

    assert demo_mod.Demo(args, Sink()).run() == 2  # type: ignore[arg-type]
    assert calls == ([tmp_path.resolve() / "placement"] if flag else [])
