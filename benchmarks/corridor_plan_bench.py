"""Corridor-plan benchmark: the wall time of a point goal's corridor plan (what the controller's worker
thread runs while the arm holds: ``SwivelRedundancy.corridor_job``, i.e. the nearest goal configuration,
:func:`redarm_ros.control.corridor_route.plan_route` and the swivel corridors it asks for).

The plans are those of reach_quality_bench's free45 case: the same seeded goals, one after another from
where the controller ended the move before (the controller with the corridor on runs the moves; the
oracle and the baselines are left out, they draw no random numbers). ``--save`` keeps every plan's
inputs and result (npz), ``--load`` times the plans of such a file instead of running the controller, and
``--compare`` checks the results against a saved file: the same found / not found on every plan, the
schedule's joints within ``--tol`` rad at the saved samples, the durations within 5 %.

    .venv/bin/python benchmarks/corridor_plan_bench.py --arms pa10,powercube7 --moves 80 --save /tmp/plans.npz
    .venv/bin/python benchmarks/corridor_plan_bench.py --load /tmp/plans.npz --compare /tmp/plans.npz
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.redundancy import SwivelRedundancy
from redarm_ros.geometry.obstacles import Scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_common  # noqa: E402
import reach_quality_bench as rq  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "corridor_plan_bench.md"
NOT_COVERED = """What this does not cover: the plans run in this process's main thread, one at a time (the
controller's worker thread shares the interpreter with the control loop); timings are wall clock on a
shared machine."""


def capture(arm_name: str, moves: int, seed: int, params: ControllerParams) -> list[dict[str, Any]]:
    """The corridor plans the controller asks for on reach_quality_bench's free45 goals: per plan the
    reference (joints, pose) and the goal."""
    arm = rq._load(arm_name)
    jobs: list[dict[str, Any]] = []
    orig = SwivelRedundancy.corridor_job

    def spy(self: SwivelRedundancy, st: Any, p: ControllerParams, T: np.ndarray, scene: Scene) -> Any:
        jobs.append({"q0": st.ref.q.copy(), "pos": np.array(st.ref.pos), "rot": np.array(st.ref.rot),
                     "T1": np.array(T, float)})
        return orig(self, st, p, T, scene)

    SwivelRedundancy.corridor_job = spy  # type: ignore[method-assign]
    try:
        rng = np.random.default_rng(seed)
        scene = Scene()
        ctl = make_controller(arm, scene, params)
        ctl.reset(rq._start(arm), now=0.0)
        probe = make_controller(arm, scene, params)
        for _ in range(moves):
            q0 = ctl.q
            assert q0 is not None
            T = rq.free_goal(arm, probe, rng, arm.fk(q0), math.radians(45.0))
            rq.run_controller(ctl, T)
    finally:
        SwivelRedundancy.corridor_job = orig  # type: ignore[method-assign]
    return jobs


def run_plan(red: SwivelRedundancy, params: ControllerParams, job: dict[str, Any]
             ) -> tuple[Any, str, float, float]:
    """One plan, as the controller's worker thread runs it: (route or None, why, wall time s, this
    thread's CPU time s)."""
    ref = SimpleNamespace(q=job["q0"].copy(), pos=tuple(job["pos"]), rot=tuple(job["rot"]))
    fn = red.corridor_job(SimpleNamespace(ref=ref), params, job["T1"], Scene())  # (free45: no obstacles)
    t0, c0 = time.perf_counter(), time.thread_time()
    route, why = fn()
    return route, why, time.perf_counter() - t0, time.thread_time() - c0


def result_record(route: Any, why: str) -> dict[str, Any]:
    if route is None:
        return {"found": False, "why": why}
    c = route.corridor
    return {"found": True, "why": "", "u": c.u, "q": c.q, "swivel": c.swivel, "duration": route.duration}


def compare(new: list[dict[str, Any]], old: list[dict[str, Any]], tol: float) -> list[str]:
    """What differs between two runs' results (see the module docstring)."""
    out = []
    for i, (a, b) in enumerate(zip(new, old, strict=True)):
        if a["found"] != b["found"]:
            out.append(f"plan {i}: found {a['found']} ({a['why']}), was {b['found']} ({b['why']})")
            continue
        if not a["found"]:
            continue
        # the new schedule's joints at the old samples (linear between the new samples)
        Qa = np.stack([np.interp(b["u"], a["u"], a["q"][:, j]) for j in range(a["q"].shape[1])], axis=1)
        dq = float(np.max(np.abs(Qa - b["q"])))
        dT = abs(a["duration"] - b["duration"]) / b["duration"]
        if dq > tol or dT > 0.05:
            out.append(f"plan {i}: joints {dq:.3g} rad apart, duration {a['duration']:.3f} s, was "
                       f"{b['duration']:.3f} s")
    return out


Records = dict[str, list[dict[str, Any]]]  # per arm, per plan


def _save(path: Path, plans: Records, results: Records) -> None:
    flat: dict[str, Any] = {}
    for arm_name, jobs in plans.items():
        for i, job in enumerate(jobs):
            for k, v in job.items():
                flat[f"{arm_name}/{i}/in/{k}"] = v
            for k, v in results[arm_name][i].items():
                flat[f"{arm_name}/{i}/out/{k}"] = np.asarray(v)
    flat["meta"] = np.array(json.dumps({a: len(j) for a, j in plans.items()}))
    np.savez_compressed(path, **flat)


def _load(path: Path) -> tuple[dict[str, list[dict[str, Any]]], dict[str, list[dict[str, Any]]]]:
    z = np.load(path)
    counts = json.loads(str(z["meta"]))
    plans: dict[str, list[dict[str, Any]]] = {}
    results: dict[str, list[dict[str, Any]]] = {}
    for arm_name, n in counts.items():
        plans[arm_name], results[arm_name] = [], []
        for i in range(n):
            pre = f"{arm_name}/{i}/"
            plans[arm_name].append({k[len(pre) + 3:]: z[k] for k in z.files if k.startswith(pre + "in/")})
            res = {k[len(pre) + 4:]: z[k] for k in z.files if k.startswith(pre + "out/")}
            res["found"], res["why"] = bool(res["found"]), str(res["why"])
            if res["found"]:
                res["duration"] = float(res["duration"])
            results[arm_name].append(res)
    return plans, results


def _stats(x: list[float]) -> str:
    a = np.asarray(x) * 1e3
    return f"{np.median(a):.0f} / {np.percentile(a, 90):.0f} / {a.max():.0f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arms", default="pa10,powercube7")
    ap.add_argument("--moves", type=int, default=80, help="free45 moves per arm (default 80)")
    ap.add_argument("--seed", type=int, default=3200, help="reach_quality_bench's free45 seed")
    ap.add_argument("--params", default="", help="controller parameters as JSON (the corridor is turned on)")
    ap.add_argument("--save", type=Path, default=None, help="keep the plans' inputs and results here (npz)")
    ap.add_argument("--load", type=Path, default=None, help="time the plans of this file")
    ap.add_argument("--compare", type=Path, default=None, help="check the results against this file")
    ap.add_argument("--tol", type=float, default=0.02, help="joints' tolerance of --compare (rad)")
    ap.add_argument("--note", default="", help="appended to the section title (e.g. the code's commit)")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 3 moves of the PA10")
    args = ap.parse_args(argv)
    if args.quick:
        args.arms, args.moves = "pa10", 3
    pdict = json.loads(args.params) if args.params else {}
    pdict.setdefault("replan", {})["corridor"] = True
    params = ControllerParams.from_dict(pdict)
    load0, t0 = os.getloadavg(), time.time()
    if args.load is not None:
        plans, _ = _load(args.load)
    else:
        plans = {a: capture(a, args.moves, args.seed, params) for a in args.arms.split(",") if a}
    results: dict[str, list[dict[str, Any]]] = {}
    rows = ["| arm | plans | found | plan wall time median / p90 / max ms | CPU time median / p90 / max ms |",
            "|---|---|---|---|---|"]
    for arm_name, jobs in plans.items():
        arm = rq._load(arm_name)
        red = make_controller(arm, Scene(), params).redundancy
        assert isinstance(red, SwivelRedundancy)
        results[arm_name], times, cpu = [], [], []
        for job in jobs:
            route, why, dt, dc = run_plan(red, params, job)
            results[arm_name].append(result_record(route, why))
            times.append(dt)
            cpu.append(dc)
        found = sum(r["found"] for r in results[arm_name])
        rows.append(f"| {arm_name} | {len(jobs)} | {found} | {_stats(times)} | {_stats(cpu)} |")
        print(rows[-1], flush=True)
    if args.save is not None:
        _save(args.save, plans, results)
    diffs: list[str] = []
    if args.compare is not None:
        _, old = _load(args.compare)
        for arm_name in results:
            diffs += [f"{arm_name} {d}" for d in compare(results[arm_name], old[arm_name], args.tol)]
        print("\n".join(diffs) if diffs else f"same results as {args.compare}", flush=True)
    title = (f"## {', '.join(plans)} free45 plans, seed {args.seed}"
             + (f"; parameters {args.params}" if args.params else "")
             + (f"; {args.note}" if args.note else ""))
    body = ["", *rows, "", bench_common.load_line(load0, t0), ""]
    header = bench_common.doc_header("# Corridor-plan benchmark (`benchmarks/corridor_plan_bench.py`)",
                                     __doc__)
    bench_common.finish_sections(RESULTS, header, {title: body}, NOT_COVERED, args.no_write)
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
