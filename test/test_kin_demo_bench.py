"""Smoke run of the IK benchmark (tiny sizes, no speed assertions)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import qmul, qy, qz

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "ik_bench.py"


@pytest.mark.slow
def test_benchmark_smoke(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    spec = importlib.util.spec_from_file_location("ik_bench", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "ik_bench", bench)  # dataclasses look their module up there
    spec.loader.exec_module(bench)
    out_md = tmp_path / "ik_bench.md"
    args = [
        "--n",
        "12",
        "--hard-n",
        "3",
        "--dense-n",
        "3",
        "--peer-n",
        "2",
        "--arms",
        "pa10",
        "--out",
        str(out_md),
    ]
    assert bench.main(args) == 0
    text = out_md.read_text()
    for solver in (
        "ik(T, s)",
        "ik_nearest",
        "ik_batch",
        "ik_nearest_batch",
        "DLS",
        "Flow sequential",
        "ikpy",
    ):
        assert solver in text
    for pose_set in ("uniform", "narrow", "theta4 at limit", "theta4 = 0"):
        assert f"| {pose_set} |" in text
    assert "load average" in text and "Targets" in text and "| pa10 |" in capsys.readouterr().out
    # the ikpy chain built from our model has our forward kinematics
    arm = load_arm("pa10")
    chain = bench.ikpy_chain(arm)
    q = np.array([0.3, -0.4, 0.5, 1.0, -0.2, 0.7, 0.1])
    assert np.allclose(chain.forward_kinematics([0.0, *q, 0.0]), arm.fk(q), atol=1e-12)


def test_fk_pq_quaternion_order() -> None:
    arm = load_arm("pa10")
    q = np.array([0.3, -0.4, 0.5, 1.0, -0.2, 0.7, 0.1])
    p, quat = arm.fk_pq(q)
    ref = np.array([1.0, 0.0, 0.0, 0.0])
    for i, t in enumerate(q):
        ref = qmul(ref, qz(t) if i % 2 == 0 else qy(t))
    ref = ref if ref[0] >= 0 else -ref
    assert np.allclose(quat, ref, atol=1e-12) and np.allclose(p, arm.fk(q)[:3, 3])


def test_nearest_miss_benchmark_smoke(monkeypatch: pytest.MonkeyPatch) -> None:
    """benchmarks/nearest_miss_bench.py on a few poses of one arm: every set and seed kind is solved both
    ways and compared (no miss on these 20 fixed-seed poses), and the table sums them."""
    path = BENCH.with_name("nearest_miss_bench.py")
    spec = importlib.util.spec_from_file_location("nearest_miss_bench", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "nearest_miss_bench", mod)
    monkeypatch.setattr(sys, "path", list(sys.path))  # (the bench puts benchmarks/ on the path)
    spec.loader.exec_module(mod)
    rows = mod.run_arm(("powercube7", 20, 5))
    assert [(r["set"], r["seed"]) for r in rows] == [(k, s) for k in mod.KINDS for s in ("mid", "random")]
    assert all(15 <= r["poses"] <= 20 and r["misses"] == 0 and r["t_def"] > 0.0 for r in rows)
    assert f"| all | | | {sum(r['poses'] for r in rows)} | 0 |" in mod.table(rows)
