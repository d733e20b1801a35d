"""CPU per control step of the controller core on the stack CPU benchmark's goals, and a hash of its output.

What runs: the core of the ``controller`` node (``make_controller``, PA10, the demo's scene, 100 Hz steps,
the node's stream lead of 0.06 s) in this process, no ROS: first ``stack_cpu_bench.py``'s stream case
(a goal on a 5 cm circle about the demo's ready pose, one turn in 4 s, a sample every other step, 20 s),
then the demo's goals one after the other until each is reached or rejected. The corridor plans are
waited for (``ReachController.wait_for_plans``), so a run is deterministic.

Printed per repetition: CPU seconds per stream step (of it, the goal messages') and of the demo part, and
a hash of every command and reported field; then the stream's CPU per step as the sum over its 100-step
chunks of each chunk's least CPU over the repetitions (what a busy machine inflates least). Two code
versions give the same commands if and only if their hashes agree; compare their CPU figures side by
side (the same load at the same moments)::

    .venv/bin/python benchmarks/controller_step_bench.py [--reps 3] [--profile tottime]

``--profile SORT`` prints a cProfile of one stream (CPU time). Not covered: the node's messages and
executor, the other processes of the stack.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import math
import os
import pstats
import sys
import time
from pathlib import Path

import numpy as np

from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import ControllerParams, ReachController
from redarm_ros.demo import DEMO_SCENE, GOALS, READY_Q
from redarm_ros.geometry.obstacles import Scene
from redarm_ros.kinematics import load_arm

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common, also when loaded by path
import bench_common  # noqa: E402
from stack_cpu_bench import CIRCLE_PERIOD_S, CIRCLE_RADIUS_M  # noqa: E402

DT = 0.01
STREAM_S = 20.0
CHUNK = 100


def run(prof: cProfile.Profile | None = None,
        demo: bool = True) -> tuple[float, float, float, list[float], str]:
    """One replay: (stream CPU s per step, of it the goal messages', demo CPU s, cumulative stream CPU s
    per chunk, hash)."""
    ReachController.wait_for_plans = True
    arm = load_arm("pa10")
    ctl = make_controller(arm, Scene.from_dict(DEMO_SCENE), ControllerParams.from_dict(
        {"dt": DT, "stream": {"lead": 0.06}}))
    ctl.reset(np.asarray(READY_Q), 0.0)
    T_ready = arm.fk(np.asarray(READY_Q))
    center = T_ready[:3, 3] - np.array([CIRCLE_RADIUS_M, 0.0, 0.0])
    h = hashlib.sha256()
    cpu = goal_cpu = 0.0
    chunks: list[float] = []
    steps = int(STREAM_S / DT)

    def record(res: object) -> None:
        h.update(res.q.tobytes())  # type: ignore[attr-defined]
        h.update(repr((res, ctl.goal_kind, ctl.goal)).encode())

    if prof is not None:
        prof.enable()
    for k in range(steps):
        t = k * DT
        c0 = time.process_time()
        if k % 2 == 0:
            a = 2 * math.pi * t / CIRCLE_PERIOD_S
            T = T_ready.copy()
            T[:3, 3] = center + CIRCLE_RADIUS_M * np.array([math.cos(a), math.sin(a), 0.0])
            h.update(repr(ctl.goal_message(T, t, t + 0.0003)).encode())
        c1 = time.process_time()
        res = ctl.step(DT, t + 0.0005)
        cpu += time.process_time() - c0
        goal_cpu += c1 - c0
        record(res)
        if k % CHUNK == CHUNK - 1:
            chunks.append(cpu)
    if prof is not None:
        prof.disable()
    demo_cpu = 0.0
    t = steps * DT
    for g in GOALS if demo else ():
        h.update(repr(ctl.goal_message(g.matrix(), 0.0, t)).encode())
        for k in range(1500):
            t += DT
            c0 = time.process_time()
            res = ctl.step(DT, t)
            demo_cpu += time.process_time() - c0
            record(res)
            if res.phase.name in ("REACHED", "REJECTED") and k > 5:
                break
    return cpu / steps, goal_cpu / steps, demo_cpu, chunks, h.hexdigest()[:16]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3, help="repetitions (fresh controllers)")
    ap.add_argument("--profile", metavar="SORT", help="cProfile one stream, sorted by SORT (e.g. tottime)")
    args = ap.parse_args(argv)
    t_start, load0 = time.time(), os.getloadavg()
    if args.profile:
        prof = cProfile.Profile(time.process_time)
        run(prof, demo=False)
        pstats.Stats(prof).sort_stats(args.profile).print_stats(40)
        return 0
    per_chunk = []
    for i in range(args.reps):
        per, goal, demo, chunks, digest = run()
        per_chunk.append(np.diff([0.0, *chunks]))
        print(f"run {i + 1}: stream {per * 1e6:.0f} us per step (goal messages {goal * 1e6:.0f} us of it), "
              f"demo {demo:.2f} s CPU, hash {digest}", flush=True)
    least = np.min(np.array(per_chunk), axis=0)
    per_step = least.sum() / (CHUNK * len(least))
    print(f"stream, least CPU per {CHUNK}-step chunk summed: {per_step * 1e6:.0f} us per step")
    print(bench_common.load_line(load0, t_start))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
