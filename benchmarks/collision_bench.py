"""Self-collision check, the IK front end's collision filter and the base-move suggestion: time and quality.

What it measures, per bundled arm unless said otherwise (no ROS, one process):

* ``self_collision`` (one posture, scalar) and ``self_collision_batch`` (per row of 10,000);
* the IK front end's nearest solve on uniform collision-free poses with the filter on and off, seed
  mid-range (the filter's cost when the nearest solution is free: one scalar check);
* the fallback ``nearest_collision_free`` when the nearest solution collides. The bundled 7-DOF arms
  almost never get there (their shoulder-pitch limits keep the elbow high, and the 8 flip patterns share
  their links), so this uses a PA10 with +-180 deg joints and a table 0.1 m up, seeded with a colliding
  solution of poses whose self-motion has colliding and collision-free parts; the optimality column
  compares with the best collision-free solution of a 0.1 deg sweep over all swivels and patterns;
* ``suggest_base_move`` on poses the arm cannot solve (collision-free postures shifted sideways by
  0.4-1.2 m): time, how many got a valid suggestion, how many in the optimal region, and a check that
  the moved target is solved by the front end.

Not covered: the cross-process service round trip (ik_service_bench), obstacles other than the arm
itself and the ground, the controller.

    python benchmarks/collision_bench.py --quick      # smoke run
    python benchmarks/collision_bench.py              # full run, writes benchmarks/results/collision_bench.md
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common
import bench_common  # noqa: E402

from redarm_ros.geometry.self_collision import self_collision, self_collision_batch
from redarm_ros.kinematics import IKStatus, load_arm
from redarm_ros.kinematics.base_placement import suggest_base_move
from redarm_ros.kinematics.collision_ik import nearest_collision_free
from redarm_ros.kinematics.solve import IKFrontEnd

ARMS = ["pa10", "pa10_7c", "powercube6", "powercube7"]
OUT = Path(__file__).resolve().parent / "results" / "collision_bench.md"


def _load() -> str:
    return ", ".join(f"{v:.2f}" for v in os.getloadavg())


def _ms(ts: list[float]) -> tuple[float, float, float]:
    a = np.asarray(ts) * 1e3
    return float(np.median(a)), float(np.percentile(a, 95)), float(a.max())


def bench_checks(n_scalar: int, n_batch: int) -> list[str]:
    rows = ["| arm | self_collision, 1 posture (us) | self_collision_batch (us per row) |", "|---|---|---|"]
    for name in ARMS:
        arm = load_arm(name)
        Q = np.random.default_rng(0).uniform(arm.lower, arm.upper, (max(n_scalar, n_batch), arm.n))
        t = time.perf_counter()
        for q in Q[:n_scalar]:
            self_collision(arm, q)
        ts = (time.perf_counter() - t) / n_scalar * 1e6
        t = time.perf_counter()
        self_collision_batch(arm, Q[:n_batch])
        tb = (time.perf_counter() - t) / n_batch * 1e6
        rows.append(f"| {name} | {ts:.1f} | {tb:.2f} |")
    return rows


def bench_filter(n: int) -> list[str]:
    arms = {name: load_arm(name) for name in ARMS}
    front = IKFrontEnd(arms, "pa10")
    rows = [
        "| arm | poses | filter on: median / p95 ms | filter off: median / p95 ms | same answer |",
        "|---|---|---|---|---|",
    ]
    for name, arm in arms.items():
        rng = np.random.default_rng(1)
        Ts = []
        while len(Ts) < n:
            q = rng.uniform(arm.lower, arm.upper)
            if not self_collision(arm, q).colliding:
                Ts.append(arm.fk(q))
        on, off, same = [], [], 0
        for T in Ts:  # interleaved pose by pose
            t = time.perf_counter()
            a = front.solve(T, name, swivel=None, seed=[], all_solutions=False, timeout_s=0.05)
            on.append(time.perf_counter() - t)
            t = time.perf_counter()
            b = front.solve(T, name, swivel=None, seed=[], all_solutions=False, timeout_s=0.05,
                            check_collisions=False)
            off.append(time.perf_counter() - t)
            agree = a.q is not None and b.q is not None and bool(np.allclose(a.q, b.q))
            # a different answer only where the unfiltered nearest solution collides
            assert agree or (b.q is not None and self_collision(arm, b.q).colliding)
            same += agree
        m1, p1, _ = _ms(on)
        m2, p2, _ = _ms(off)
        rows.append(f"| {name} | {n} | {m1:.3f} / {p1:.3f} | {m2:.3f} / {p2:.3f} | {same} |")
    return rows


def bench_fallback(n: int) -> list[str]:
    arm = load_arm("pa10", lower=[-math.pi] * 7, upper=[math.pi] * 7)
    arm.config["self_collision"] = {
        "pairs": [["base", "forearm"], ["base", "hand"], ["upper_arm", "hand"]],
        "ground_z": 0.1,
    }
    front = IKFrontEnd({"wide": arm}, "wide")
    model = front.models["wide"]
    rng = np.random.default_rng(3)
    times, excess, found = [], [], 0
    for T, rows, res in bench_common.mixed_collision_poses(arm, model, rng):
        found += 1
        qc = rows[np.nonzero(res.colliding)[0][rng.integers(res.colliding.sum())]]
        t = time.perf_counter()
        f = nearest_collision_free(arm, T, qc, model)
        times.append(time.perf_counter() - t)
        assert f is not None and not self_collision(arm, f.q, model=model).colliding
        sweep = ((arm.nearest_copies(rows[res.free], qc) - qc) ** 2).sum(axis=1).min()
        excess.append(f.cost - sweep)
        if found == n:
            break
    med, p95, mx = _ms(times)
    return [
        "| poses | median ms | p95 ms | max ms | worse than the 0.1 deg sweep | largest excess (rad^2) |",
        "|---|---|---|---|---|---|",
        f"| {n} | {med:.1f} | {p95:.1f} | {mx:.1f} | {sum(e > 1e-9 for e in excess)} | {max(excess):.2e} |",
    ]


def bench_base(n: int) -> list[str]:
    arms = {name: load_arm(name) for name in ARMS}
    front = IKFrontEnd(arms, "pa10", suggest_base_move=False)
    rows = [
        "| arm | unsolvable poses | valid | optimal region | moved target solved | median ms | max ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, arm in arms.items():
        rng = np.random.default_rng(5)
        times, valid, optimal, solved, k = [], 0, 0, 0, 0
        for T in bench_common.shifted_poses(arm, rng):
            ans = front.solve(T, name, swivel=None, seed=[], all_solutions=False, timeout_s=0.05)
            if ans.status is IKStatus.SUCCESS:
                continue
            k += 1
            t = time.perf_counter()
            bp = suggest_base_move(arm, T, timeout_s=10.0)
            times.append(time.perf_counter() - t)
            if bp.valid:
                valid += 1
                optimal += bp.optimal
                ans = front.solve(
                    bp.apply(T), name, swivel=None, seed=[], all_solutions=False, timeout_s=0.05
                )
                solved += ans.status is IKStatus.SUCCESS
            if k == n:
                break
        med, _, mx = _ms(times)
        rows.append(f"| {name} | {n} | {valid} | {optimal} | {solved} | {med:.1f} | {mx:.1f} |")
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: small sets")
    ap.add_argument(
        "--no-write", action="store_true", help="do not write benchmarks/results/collision_bench.md"
    )
    args = ap.parse_args(argv)
    q = args.quick
    load0 = _load()
    t0 = time.perf_counter()
    parts = [
        ("Collision check", bench_checks(200 if q else 5000, 2000 if q else 10000)),
        ("IK front end, nearest solve, uniform collision-free poses (filter on vs off, interleaved)",
         bench_filter(30 if q else 500)),
        ("Fallback: nearest collision-free solution when the nearest one collides (wide-limit PA10)",
         bench_fallback(5 if q else 100)),
        ("Base-move suggestion", bench_base(5 if q else 40)),
    ]
    load1 = _load()
    lines = [
        "# Self-collision, collision filter, base-move suggestion",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
        f"load average before {load0}, after {load1}; {time.perf_counter() - t0:.0f} s in all. "
        "Run: `python benchmarks/collision_bench.py`.",
        "",
    ]
    for title, rows in parts:
        lines += [f"## {title}", "", *rows, ""]
    lines += [
        "`same answer`: the filtered answer equals the unfiltered one; they differ exactly where the "
        "unfiltered nearest solution collides (for powercube6 one of its other analytic solutions is "
        "then nearest and collision-free). Times are per call in one process, the filter's overhead being "
        "one scalar check when the nearest solution is collision-free.",
        "",
        "Not covered: the service round trip (see ik_service_bench.md), obstacles other than the arm itself "
        "and the ground plane, the controller.",
        "",
    ]
    text = "\n".join(lines)
    sys.stdout.write(text)
    if not args.no_write and not q:
        OUT.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
