"""Base placement for a task set: pruning, agreement with the exact check, throughput, scaling, a plan.

The task sets are the bundled ``config/placement/table_pa10.yaml`` (8 table-top grasps, PA10 on a mobile
base, 20172 base poses at 0.1 m x 30 deg) and ``table_powercube6.yaml`` (4 top-down grasps, the 6-DOF
PowerCube arm on its base, 7688 base poses at 0.1 m x 45 deg). Per task set:

* **Pruning and agreement**: the share of base poses (and of base-task pairs) that inverse reachability
  rules out, and the full study with and without it compared array by array: pruning must change
  nothing, i.e. no base pose it rules out is reachable and the ranking is the same.
* **Throughput per core against a per-candidate ``ik_nearest`` loop** (the way one would check a grid
  without this module): the same base-task pairs, the loop on a seeded random sample of them,
  interleaved block by block with our exact stage in one process. Ours is timed twice: the exact stage
  alone (every pair, no pruning, no collisions: the like-for-like comparison) and the whole study as
  users run it (pruning, collisions, ranking).
* **Workers**: the whole study on a grid twice as fine, with 1 and 2 local worker processes, and on a
  2-worker Dask cluster on 127.0.0.1; the speed-up and whether the results are identical.
* **Cost model**: the time per base pose and per (base pose, task) pair, fitted from runs with 1 and all
  tasks, and the plan: a 2 cm x 5 deg study of a 3 m x 3 m floor for 100 task poses on 1, 8 and 64
  machines of 2 cores, simulated by list scheduling of the measured chunk times plus the measured
  per-chunk engine overhead (docs/placement.md explains the model and its limits).
* **Capability map through the same engine**: the PA10 map (0.1 m, 32 orientations) with 1 and 2
  workers, and the extrapolated time of a 2 cm, 200-orientation map.

Not a test: it asserts nothing. It prints the tables and writes benchmarks/results/placement_bench.md.

    .venv/bin/python benchmarks/placement_bench.py                   # the full run (several minutes)
    .venv/bin/python benchmarks/placement_bench.py --quick --no-write   # smoke run
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_common import doc_header, finish_sections, load_line  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.kinematics.reachability import capability_map  # noqa: E402
from redarm_ros.placement import PlacementProblem, load_problem, place  # noqa: E402
from redarm_ros.placement.evaluate import evaluate_rows  # noqa: E402
from redarm_ros.placement.problem import BaseGrid, base_transforms  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results" / "placement_bench.md"
TASK_SETS = ("table_pa10", "table_powercube6")
FIELDS = ("possible", "reach", "width", "footprint_ok", "checked", "free", "margin")


def _same(a, b, fields=FIELDS[1:]) -> bool:
    return all(getattr(a, f).tobytes() == getattr(b, f).tobytes() for f in fields)


def _coarse(problem: PlacementProblem, factor: int) -> PlacementProblem:
    g = problem.grid
    return dataclasses.replace(problem, grid=BaseGrid(g.x[::factor], g.y[::factor], g.yaw[::factor]))


def _timed(fn, *a, **kw):
    t0 = time.perf_counter()
    out = fn(*a, **kw)
    return out, time.perf_counter() - t0


def _throughput(problem: PlacementProblem, n_loop: int, rng: np.random.Generator) -> list[str]:
    """Exact stage (every pair, no pruning, no collisions) against an ik_nearest loop, interleaved."""
    arm = load_arm(problem.arm)
    bare = dataclasses.replace(problem, scene=None, check_collisions=False, footprint_radius=0.0)
    N, m = problem.grid.size, len(problem.tasks)
    poses = problem.grid.poses()
    blocks = np.array_split(np.arange(N), 8)
    pick = rng.choice(N * m, size=min(n_loop, N * m), replace=False)
    loop_blocks = np.array_split(pick, 8)
    seed = (arm.lower + arm.upper) / 2
    t_ours = t_loop = 0.0
    n_loop_ok = 0
    for rows, sample in zip(blocks, loop_blocks, strict=True):
        _, dt = _timed(evaluate_rows, bare, rows, prune=False)
        t_ours += dt
        t0 = time.perf_counter()
        for k in sample:
            i, j = divmod(int(k), m)
            B = base_transforms(poses[i:i + 1], problem.base_height)[0]
            q, _ = arm.ik_nearest(np.linalg.inv(B) @ problem.tasks[j], seed)
            n_loop_ok += q is not None
        t_loop += time.perf_counter() - t0
    _, t_full = _timed(place, problem)
    ours = N * m / t_ours
    loop = len(pick) / t_loop
    full = N * m / t_full
    return [
        "| method | pairs | time (s) | pairs/s (one core) | vs ik_nearest loop |",
        "|---|---:|---:|---:|---:|",
        f"| ik_nearest per pair (a seeded sample, {n_loop_ok} reachable) | {len(pick)} | {t_loop:.2f} | "
        f"{loop:,.0f} | 1.0 |",
        f"| exact stage, every pair (no pruning, no collisions) | {N * m} | {t_ours:.2f} | {ours:,.0f} | "
        f"{ours / loop:.1f} |",
        f"| whole study (pruning, collisions, ranking) | {N * m} | {t_full:.2f} | {full:,.0f} | "
        f"{full / loop:.1f} |",
    ]


def _simulate(n_chunks: int, chunk_s: np.ndarray, overhead_s: float, machines: int, cores: int,
              rng: np.random.Generator) -> float:
    """Makespan (s) of n_chunks chunks, durations drawn from the measured ``chunk_s``, on machines x cores
    workers by greedy list scheduling; the scheduler hands out one chunk per ``overhead_s`` (serial)."""
    dur = rng.choice(chunk_s, size=n_chunks)
    free = [0.0] * (machines * cores)
    heapq.heapify(free)
    release = 0.0
    end = 0.0
    for d in dur:
        w = heapq.heappop(free)
        release += overhead_s
        start = max(w, release)
        heapq.heappush(free, start + d)
        end = max(end, start + d)
    return end


def _finer(problem: PlacementProblem, factor: int) -> PlacementProblem:
    """The same study on a grid ``factor`` times finer in x and y (more work for the scaling rows)."""
    g = problem.grid
    step = (g.x[1] - g.x[0]) / factor
    x = g.x[0] + step * np.arange((len(g.x) - 1) * factor + 1)
    y = g.y[0] + step * np.arange((len(g.y) - 1) * factor + 1)
    return dataclasses.replace(problem, grid=BaseGrid(x, y, g.yaw))


def _scaling(problem: PlacementProblem, name: str, rng: np.random.Generator,
             fine: int) -> dict[str, list[str]]:
    big = _finer(problem, fine)
    r1, t1 = _timed(place, big, workers=1)
    r2, t2 = _timed(place, big, workers=2)
    rows = [
        f"The grid {fine} times finer in x and y ({big.grid.size} base poses), the whole study:",
        "",
        "| engine | workers | time (s) | speed-up | identical to 1 worker |",
        "|---|---:|---:|---:|---|",
        f"| local | 1 | {t1:.2f} | 1.00 | - |",
        f"| local (worker processes) | 2 | {t2:.2f} | {t1 / t2:.2f} | {_same(r1, r2)} |",
    ]
    overhead = 0.002  # s per chunk, replaced by the measured Dask figure when Dask is installed
    try:
        import distributed  # noqa: PLC0415

        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                      dashboard_address=None, protocol="tcp") as cl:
            place(problem, engine="dask", address=cl.scheduler_address)  # warm the workers
            rd, td = _timed(place, big, engine="dask", address=cl.scheduler_address)
            with distributed.Client(cl) as client:  # the scheduler's cost of one unit of work
                client.gather(client.map(abs, range(-50, 0)))
                t0 = time.perf_counter()
                client.gather(client.map(abs, range(-1000, 0)))
                overhead = (time.perf_counter() - t0) / 1000
        rows.append(f"| dask LocalCluster on 127.0.0.1 | 2 | {td:.2f} | {t1 / td:.2f} | {_same(r1, rd)} |")
    except ImportError:
        rows.append("| dask | - | not installed | - | - |")
    # cost model: t = N (a + b m) from runs with one task and all tasks (pruning and collisions on)
    m = len(problem.tasks)
    one = dataclasses.replace(problem, tasks=problem.tasks[:1], task_names=problem.task_names[:1])
    _, t_one = _timed(place, one)
    _, t1 = _timed(place, problem)
    N = problem.grid.size
    b = max((t1 - t_one) / (N * (m - 1)), 0.0)
    a = max(t_one / N - b, 0.0)
    chunk_times = []
    rows_all = np.arange(N)
    for c0 in range(0, N, 64):
        _, dt = _timed(evaluate_rows, problem, rows_all[c0:c0 + 64])
        chunk_times.append(dt)
    ct = np.array(chunk_times)
    cost = [
        f"Per base pose {a * 1e6:.1f} us + per (base pose, task) pair {b * 1e6:.1f} us (one core, pruning "
        f"and collisions on; fitted from 1 and {m} tasks). Chunks of 64 base poses: median "
        f"{np.median(ct) * 1e3:.1f} ms, p95 {np.percentile(ct, 95) * 1e3:.1f} ms, "
        f"max {ct.max() * 1e3:.1f} ms. Dask's cost per unit of work (1000 trivial tasks on the local "
        f"cluster): {overhead * 1e3:.2f} ms.",
        "",
    ]
    # the plan: 2 cm x 5 deg over 3 m x 3 m, 100 tasks; chunk times scaled by the task count and size
    n_base = 151 * 151 * 72
    tasks = 100
    per_pose = ct / 64 * (a + b * tasks) / (a + b * m)  # s per base pose, as measured chunk by chunk
    plan = [
        f"Plan: 2 cm x 5 deg over 3 m x 3 m ({n_base:,} base poses) x {tasks} task poses, this task set's "
        f"geometry ({name}): one core would need {n_base * (a + b * tasks) / 60:.0f} min.",
        "",
        "| machines (2 cores each) | base poses per chunk | chunks | makespan (simulated) | efficiency |",
        "|---:|---:|---:|---:|---:|",
    ]
    serial = n_base * float(np.mean(per_pose))
    for machines, chunk_base in ((1, 64), (8, 256), (64, 1024)):
        n_chunks = math.ceil(n_base / chunk_base)
        mk = _simulate(n_chunks, per_pose * chunk_base, overhead, machines, 2, rng)
        plan.append(f"| {machines} | {chunk_base} | {n_chunks:,} | {mk / 60:.1f} min | "
                    f"{serial / (mk * machines * 2):.2f} |")
    return {"workers": rows, "cost": cost + plan}


def _capability(quick: bool) -> list[str]:
    arm = load_arm("pa10")
    step, k = (0.2, 8) if quick else (0.1, 32)
    m1, t1 = _timed(capability_map, arm, step, k, workers=1)
    m2, t2 = _timed(capability_map, arm, step, k, workers=2)
    same = m1.fraction.tobytes() == m2.fraction.tobytes() and m1.width.tobytes() == m2.width.tobytes()
    n_vox = m1.fraction.size
    fine = (step / 0.02) ** 3 * (200 / k)
    return [
        "| map | voxels | workers | time (s) | speed-up | identical |",
        "|---|---:|---:|---:|---:|---|",
        f"| pa10, {step} m, {k} orientations | {n_vox} | 1 | {t1:.2f} | 1.00 | - |",
        f"| pa10, {step} m, {k} orientations | {n_vox} | 2 | {t2:.2f} | {t1 / t2:.2f} | {same} |",
        "",
        f"A 2 cm, 200-orientation map is {fine:,.0f} times this work: about {t1 * fine / 60:.0f} min on one "
        f"core, {t1 * fine / 60 / 128 * 1.05:.1f} min on 64 machines of 2 cores (the chunks are uniform).",
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse grids, small samples (smoke run)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not write the results file")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    load0, t0 = os.getloadavg(), time.time()
    rng = np.random.default_rng(args.seed)
    sections: dict[str, list[str]] = {}
    for name in TASK_SETS:
        problem = load_problem(REPO / "config" / "placement" / f"{name}.yaml")
        if args.quick:
            problem = _coarse(problem, 3)
        pruned, tp = _timed(place, problem)
        full, tf = _timed(place, problem, prune=False)
        pair_share = 1.0 - pruned.possible.mean()
        sections[f"## {name}: pruning and agreement"] = [
            "",
            f"{problem.grid.size} base poses x {len(problem.tasks)} tasks ({problem.arm}). Inverse "
            f"reachability rules out **{100 * pruned.pruned_share:.1f} %** of the base poses "
            f"({100 * pair_share:.1f} % of the pairs). With and without it every array is identical: "
            f"**{_same(pruned, full)}**; rankings equal: "
            f"**{np.array_equal(pruned.ranking(), full.ranking())}** ({len(pruned.ranking())} valid "
            f"placements). Time with pruning {tp:.2f} s, without {tf:.2f} s.",
            "",
        ]
        n_loop = 300 if args.quick else 3000
        sections[f"## {name}: throughput per core"] = ["", *_throughput(problem, n_loop, rng), ""]
        sc = _scaling(problem, name, rng, 1 if args.quick else 2)
        sections[f"## {name}: workers"] = ["", *sc["workers"], ""]
        sections[f"## {name}: cost model and plan"] = ["", *sc["cost"], ""]
    sections["## Capability map through the engine"] = ["", *_capability(args.quick), ""]
    header = doc_header("# Placement benchmark", __doc__)
    footer = (load_line(load0, t0) + "\n\nWhat this does not cover: collision checks are decided on a 10 deg "
              "swivel grid (a collision-free solution only between grid swivels is not seen); the plan's "
              "simulation assumes the measured chunk times and a serial scheduler overhead, not network "
              "transfer of results (about 60 KB per chunk of 64 base poses x 100 tasks).")
    finish_sections(RESULTS, header, sections, footer, args.no_write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
