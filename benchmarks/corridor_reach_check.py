"""Free-space point-to-point reaches with and without the swivel corridor route, in process.

ReachController at dt 0.01 s; seeded random reachable goals (tool turned by at most 45 deg, at least
5 cm away, above z = 0.15 m), one after another without resets, from the park posture. Per run: the
share of moves re-planned in joint space, the path ratio (tool path / straight distance: median, p90),
the share of moves straight (ratio <= 1.05, no joint-space move), the share with a single-peaked hand
speed (rising then falling within 3 % of the peak), the RMS distance from the minimum-jerk speed profile
of the same distance and duration over the peak speed (median), the share reached, the controller step
median and the load average.

    python benchmarks/corridor_reach_check.py pa10 80 1     # arm, moves, corridor on (1) / off (0)
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections import Counter

import numpy as np

from redarm_ros.control.make import make_controller
from redarm_ros.control.params import ControllerParams
from redarm_ros.control.reach_controller import Phase
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import quat_angle, quat_from_matrix

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # bench_common
import bench_common  # noqa: E402


def speed_shape(P: np.ndarray, dt: float) -> tuple[bool, float]:
    """(single-peaked, minimum-jerk deviation / peak) of the tool positions P (k, 3) sampled every dt."""
    v = np.linalg.norm(np.diff(P, axis=0), axis=1) / dt
    if len(v) < 3 or v.max() <= 0.0:
        return True, 0.0
    peak = float(v.max())
    i = int(np.argmax(v))
    tol = 0.03 * peak
    single = bool(np.all(np.diff(v[: i + 1]) >= -tol) and np.all(np.diff(v[i:]) <= tol))
    moving = np.nonzero(v > 0.01 * peak)[0]
    a, b = int(moving[0]), int(moving[-1]) + 1
    x = (np.arange(a, b) + 0.5 - a) / (b - a)
    dist = float(np.sum(v[a:b])) * dt
    v_mj = dist / ((b - a) * dt) * 30.0 * x**2 * (1.0 - x) ** 2
    return single, float(np.sqrt(np.mean((v[a:b] - v_mj) ** 2)) / peak)


def run(name: str, moves: int, corridor: bool, seed: int = 11) -> tuple[list[dict], list[float], list[float]]:
    arm = load_arm(name)
    p = ControllerParams()
    p = p.with_(replan=dataclasses.replace(p.replan, corridor=corridor))
    ctl = make_controller(arm, None, p)
    ctl.reset(np.array(arm.park, float))
    rng = np.random.default_rng(seed)
    lo, up = np.asarray(arm.lower), np.asarray(arm.upper)
    rows: list[dict] = []
    step_times: list[float] = []
    plan_times: list[float] = []
    for _ in range(moves):
        T0 = arm.fk(ctl.q)
        for _try in range(1000):
            Tg = arm.fk(rng.uniform(0.85 * lo, 0.85 * up))
            turn = quat_angle(quat_from_matrix(T0[:3, :3]), quat_from_matrix(Tg[:3, :3]))
            far = np.linalg.norm(Tg[:3, 3] - T0[:3, 3]) >= 0.05
            if turn <= math.radians(45) and Tg[2, 3] >= 0.15 and far and ctl.check_goal(Tg).accepted:
                break
        ctl.set_goal(Tg)
        plan_times.append(bench_common.wait_for_corridor_plan(ctl))
        replanned, why, reached = False, "", False
        pos = [np.asarray(arm.fk(ctl.q))[:3, 3]]
        steps = 0
        for steps in range(1, 3001):  # noqa: B007 (the count is the move's time)
            t0 = time.perf_counter()
            r = ctl.step(0.01)
            step_times.append(time.perf_counter() - t0)
            pos.append(np.asarray(r.position))
            if r.phase is Phase.REPLANNING and not replanned:
                replanned, why = True, ctl._st.plan_reason  # noqa: SLF001 (the reason ~/state shows)
            if r.phase is Phase.REACHED:
                reached = True
                break
        P = np.array(pos)
        d = float(np.linalg.norm(P[-1] - P[0]))
        ratio = float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1))) / d if d > 1e-3 else 1.0
        single, dev = speed_shape(P, 0.01)
        rows.append({"replanned": replanned, "ratio": ratio, "single": single, "dev": dev, "reached": reached,
                     "why": why, "time": steps * 0.01})
    return rows, step_times, [t for t in plan_times if t > 0.0]


def summary(rows: list[dict], step_times: list[float]) -> dict[str, float]:
    ratio = np.array([r["ratio"] for r in rows])
    return {
        "moves": len(rows),
        "replanned": float(np.mean([r["replanned"] for r in rows])),
        "straight": float(np.mean([r["ratio"] <= 1.05 and not r["replanned"] for r in rows])),
        "ratio_median": float(np.median(ratio)),
        "ratio_p90": float(np.percentile(ratio, 90)),
        "single_peaked": float(np.mean([r["single"] for r in rows])),
        "min_jerk_dev_median": float(np.median([r["dev"] for r in rows])),
        "reached": float(np.mean([r["reached"] for r in rows])),
        "move_time_median_s": float(np.median([r["time"] for r in rows])),
        "step_median_ms": float(np.median(step_times)) * 1e3,
    }


def main() -> None:
    name, moves, corridor = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "1"
    print("load average", os.getloadavg())
    rows, step_times, plan_times = run(name, moves, corridor)
    print(name, "corridor" if corridor else "without corridor",
          {k: round(v, 3) for k, v in summary(rows, step_times).items()})
    if plan_times:
        print(f"corridor plans (worker thread, not in the step): {len(plan_times)}, median "
              f"{np.median(plan_times):.2f} s, p90 {np.percentile(plan_times, 90):.2f} s")
    print(Counter(r["why"][:200] for r in rows if r["replanned"]).most_common(8))


if __name__ == "__main__":
    main()
