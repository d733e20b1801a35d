"""Reach benchmark: attractor/swivel controller vs fixed swivel vs straight line + DLS (in-process).

Random table-top scenes (seeded): the PA10 stands on a table (z = 0); a reachable start above the
table, a reachable target near the table surface (hand pointing down, random yaw), and 1-3 obstacles
(cylinders, boxes, spheres resting on the table) between start and target. Each scene is also run
with its obstacles removed, to measure how straight the paths are (human-like reaching).

Methods, all at 100 Hz with the same speed limit:
  attractor   ReachController defaults (heading + orientation + swivel dynamics)
  fixed       the same controller with the swivel frozen at its start value (redundancy unused)
  attractor_paper  the same controller with swivel_mode "attractor_paper": the attractor paper's own
              redundancy dynamics (eq. 22-24, sector force-lets, wrist-limit sectors) and its
              path-tangent hand orientation (eq. 20-21) in place of the swivel dynamics (not in the
              default --methods; --append adds its table as a section of the results file)
  dls         straight-line Cartesian interpolation (minimum-jerk timing), damped-least-squares IK
              with a null-space gradient that pushes the arm away from obstacles

Scores are computed from the joint trajectories (FK + capsules), not from the controllers' reports.
Success = tool within 1 mm / 0.01 rad of the goal within 8 s, and clearance > 0 at every step.

    .venv/bin/python benchmarks/reach_bench.py --scenes 200       # writes benchmarks/results/reach_bench.md
    .venv/bin/python benchmarks/reach_bench.py --quick --no-write     # smoke run: 6 scenes
    .venv/bin/python benchmarks/reach_bench.py --scenes 50 --methods attractor,attractor_paper --append
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import ControllerParams
from redarm_ros.control.simulate import ReachMetrics, evaluate, run_controller
from redarm_ros.geometry import obstacles as ob
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, links_clearance, min_distance
from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import quat_from_matrix, quat_from_rotvec, quat_mul, rotvec_between

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common, also when loaded by path
import bench_common  # noqa: E402

DT = 0.01
DURATION = 8.0
V_MAX = 0.4  # m/s, same cap for every method
RESULTS = Path(__file__).resolve().parent / "results" / "reach_bench.md"
QUICK_SCENES = 6
Q_HOME = np.array([0.0, 0.5, 0.0, 1.5, 0.0, 1.0, 0.0])


@dataclass
class Case:
    """One benchmark scene."""

    seed: int
    scene: Scene
    q_start: np.ndarray
    T_goal: np.ndarray


def _start_q(arm, T: np.ndarray, rng: np.random.Generator, scene: Scene,
             caps: ArmCapsules) -> np.ndarray | None:
    """A random start posture: an in-limit IK solution at a random swivel, clear of the table and of
    singular/limit configurations (so the fixed-swivel baseline keeps whatever elbow it was given)."""
    for _ in range(20):
        sols = arm.ik(T, rng.uniform(-math.pi, math.pi))
        ok = []
        for q in sols:
            if float(np.min(np.minimum(q - arm.lower, arm.upper - q))) < 0.15:
                continue
            if abs(math.sin(q[1])) < 0.15 or abs(math.sin(q[5])) < 0.15:
                continue
            if min_distance(arm, q, scene, caps).distance < 0.03:
                continue
            ok.append(q)
        if ok:
            return ok[int(np.argmin([np.max(np.abs(q - Q_HOME)) for q in ok]))]
    return None


def make_case(arm, seed: int, caps: ArmCapsules) -> Case:
    """Random reachable start/target with 1-3 obstacles between them (rejection sampling)."""
    rng = np.random.default_rng(seed)
    probe = make_controller(arm, Scene((), 0.0))
    for _ in range(500):
        ps = np.array([rng.uniform(0.25, 0.6), rng.uniform(-0.4, 0.4), rng.uniform(0.15, 0.4)])
        pg = np.array([rng.uniform(0.35, 0.75), rng.uniform(-0.45, 0.45), rng.uniform(0.06, 0.16)])
        dxy = np.linalg.norm((pg - ps)[:2])
        if dxy < 0.3 or np.linalg.norm(pg[:2]) < 0.3 or np.linalg.norm(ps[:2]) < 0.25:
            continue
        Ts = bench_common.pose_down(ps, rng.uniform(-0.6, 0.6))
        Tg = bench_common.pose_down(pg, rng.uniform(-0.6, 0.6))
        q0 = _start_q(arm, Ts, rng, Scene((), 0.0), caps)
        if q0 is None:
            continue
        if not probe.check_goal(Tg).accepted:
            continue
        n_obs = int(rng.integers(1, 4))
        obstacles = []
        u = (pg - ps)[:2] / dxy
        lateral = np.array([-u[1], u[0]])
        for _k in range(n_obs):
            f = rng.uniform(0.3, 0.7)
            c_xy = ps[:2] + f * (pg - ps)[:2] + lateral * rng.uniform(-0.06, 0.06)
            kind = rng.choice(["cylinder", "box", "sphere"])
            if kind == "cylinder":
                r, h = rng.uniform(0.03, 0.06), rng.uniform(0.08, 0.22)
                obstacles.append(ob.Cylinder((c_xy[0], c_xy[1], h / 2), r, h, f"cyl{_k}"))
            elif kind == "box":
                sx, sy, h = rng.uniform(0.05, 0.12), rng.uniform(0.05, 0.12), rng.uniform(0.08, 0.22)
                yaw = rng.uniform(-1.5, 1.5)
                obstacles.append(ob.Box((c_xy[0], c_xy[1], h / 2), (sx, sy, h), yaw, f"box{_k}"))
            else:
                r = rng.uniform(0.04, 0.07)
                obstacles.append(ob.Sphere((c_xy[0], c_xy[1], r), r, f"ball{_k}"))
        scene = Scene(tuple(obstacles), 0.0, f"bench{seed}")
        # Keep scenes where the start is free and the goal acceptable.
        if min_distance(arm, q0, scene, caps).distance < 0.02:
            continue
        ctl = make_controller(arm, scene)
        if not ctl.check_goal(Tg).accepted:
            continue
        # Targets right next to an obstacle are fine, but not under an overhang of the hand.
        if any(o.signed_distance(pg) < 0.03 for o in obstacles):
            continue
        return Case(seed, scene, q0, Tg)
    raise RuntimeError(f"no valid scene for seed {seed}")


# ------------------------------------------------------------------------------------------------
# Baseline: straight line + damped least squares + null-space obstacle gradient
# ------------------------------------------------------------------------------------------------


class StraightLineDLS:
    """Minimum-jerk straight line in Cartesian space, tracked by DLS IK with a null-space clearance term."""

    def __init__(self, arm, scene: Scene, caps: ArmCapsules, damping: float = 0.03, null_gain: float = 0.5,
                 influence: float = 0.12, tol: float = 1e-3, ori_tol: float = 0.01) -> None:
        self.arm = arm
        self.scene = scene
        self.caps = caps
        self.damping = damping
        self.null_gain = null_gain
        self.influence = influence
        self.tol = tol
        self.ori_tol = ori_tol

    def run(self, q0: np.ndarray, T_goal: np.ndarray, duration: float, dt: float):
        arm = self.arm
        q = q0.copy()
        T0 = arm.fk(q)
        p0, pg = T0[:3, 3].copy(), T_goal[:3, 3].copy()
        r0, rg = quat_from_matrix(T0[:3, :3]), quat_from_matrix(T_goal[:3, :3])
        w_total = rotvec_between(r0, rg)
        L = float(np.linalg.norm(pg - p0))
        ang = math.sqrt(sum(c * c for c in w_total))
        T_move = max(0.5, 1.875 * L / V_MAX, 1.875 * ang / 1.5)
        qs = [q.copy()]
        steps = []
        reached_at = None
        vmax = np.asarray(arm.max_vel) * dt
        for k in range(1, int(round(duration / dt)) + 1):
            t0 = time.perf_counter()
            tau = min(1.0, k * dt / T_move)
            sc = 10 * tau ** 3 - 15 * tau ** 4 + 6 * tau ** 5
            pd = p0 + sc * (pg - p0)
            rd = quat_mul(quat_from_rotvec(tuple(sc * c for c in w_total)), r0)
            T = arm.fk(q)
            e_p = pd - T[:3, 3]
            e_r = np.array(rotvec_between(quat_from_matrix(T[:3, :3]), rd))
            err = np.concatenate([e_p, e_r])
            J = arm.jacobian(q)
            JJt = J @ J.T + (self.damping ** 2) * np.eye(6)
            dq = J.T @ np.linalg.solve(JJt, err)
            # Null-space push away from the closest obstacle when inside the influence distance.
            kp = arm.key_points(q)
            c0 = links_clearance(kp, self.scene, self.caps).distance
            if c0 < self.influence:
                grad = np.zeros(arm.n)
                h = 1e-4
                for j in range(arm.n):
                    qh = q.copy()
                    qh[j] += h
                    grad[j] = (links_clearance(arm.key_points(qh), self.scene, self.caps).distance - c0) / h
                Jp = J.T @ np.linalg.solve(JJt, J)
                amp = self.null_gain * (1.0 / max(c0, 0.005) - 1.0 / self.influence) * dt
                dq = dq + (np.eye(arm.n) - Jp) @ grad * amp
            ratio = float(np.max(np.abs(dq) / vmax))
            if ratio > 1.0:
                dq = dq / ratio
            q = np.clip(q + dq, arm.lower, arm.upper)
            steps.append(time.perf_counter() - t0)
            qs.append(q.copy())
            Tq = arm.fk(q)
            perr = float(np.linalg.norm(Tq[:3, 3] - pg))
            oerr = math.acos(max(-1.0, min(1.0, (np.trace(Tq[:3, :3].T @ T_goal[:3, :3]) - 1) / 2)))
            if perr <= self.tol and oerr <= self.ori_tol:
                reached_at = k * dt
                break
        return np.array(qs), np.array(steps), reached_at


# ------------------------------------------------------------------------------------------------


def run_method(method: str, arm, case: Case, scene: Scene, caps: ArmCapsules) -> ReachMetrics:
    if method == "dls":
        q, steps, reached_at = StraightLineDLS(arm, scene, caps).run(case.q_start, case.T_goal, DURATION, DT)
        return evaluate(arm, scene, q, case.T_goal, DT, steps, reached_at, caps)
    params = ControllerParams(capsules=caps)
    if method in ("fixed", "attractor_paper"):
        params = params.with_(swivel_mode=method)
    ctl = make_controller(arm, scene, params)
    ctl.reset(case.q_start)
    traj = run_controller(ctl, case.T_goal, DURATION, DT)
    return evaluate(arm, scene, traj.q, case.T_goal, DT, traj.step_s, traj.reached_at, caps)


def _pct(x: list[bool]) -> str:
    return f"{100.0 * sum(x) / max(len(x), 1):.1f}"


def _med(x: list[float]) -> str:
    x = [v for v in x if math.isfinite(v)]
    return f"{np.median(x):.3f}" if x else "-"


def _p95(x: list[float]) -> str:
    x = [v for v in x if math.isfinite(v)]
    return f"{np.percentile(x, 95):.3f}" if x else "-"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=200, help="number of random scenes (default 200)")
    ap.add_argument("--seed", type=int, default=1000, help="seed of the first scene")
    ap.add_argument("--methods", default="attractor,fixed,dls")
    ap.add_argument("--quick", action="store_true",
                    help=f"smoke run: {QUICK_SCENES} scenes (overrides --scenes)")
    ap.add_argument("--no-write", action="store_true", help="do not write benchmarks/results/reach_bench.md")
    ap.add_argument("--append", action="store_true",
                    help="append the table as a new section of the results file (keep what is there)")
    ap.add_argument("--verbose", action="store_true", help="one line per scene and method")
    bench_common.add_plot_dir(ap)
    args = ap.parse_args(argv)
    if args.quick:
        args.scenes = QUICK_SCENES
    arm = load_arm("pa10")
    caps = ArmCapsules()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    res: dict[str, list[ReachMetrics]] = {m: [] for m in methods}
    free: dict[str, list[ReachMetrics]] = {m: [] for m in methods}
    t_start = time.time()
    load0 = os.getloadavg()
    n_obs = []
    for i in range(args.scenes):
        case = make_case(arm, args.seed + i, caps)
        n_obs.append(len(case.scene))
        empty = Scene((), case.scene.table_height, "empty")
        for m in methods:
            r = run_method(m, arm, case, case.scene, caps)
            res[m].append(r)
            free[m].append(run_method(m, arm, case, empty, caps))
            if args.verbose:
                print(f"scene {case.seed} {m:9s} success={r.success} reached={r.reached} "
                      f"clear={r.min_clearance:.3f} t={r.time_to_goal:.2f} ratio={r.path_ratio:.3f}",
                      flush=True)
    elapsed = time.time() - t_start

    lines = []
    last = args.seed + args.scenes - 1
    head = "##" if args.append else "#"
    lines.append(f"{head} Reach benchmark ({args.scenes} random table scenes, seeds {args.seed}..{last}; "
                 f"{', '.join(methods)})")
    lines.append("")
    lines.append(f"PA10 on a table, 1-3 obstacles between start and target ({np.mean(n_obs):.2f} on "
                 f"average), random start posture (random feasible swivel), 100 Hz, speed cap {V_MAX} m/s, "
                 "8 s limit. Success = within 1 mm / 0.01 rad and clearance > 0 at every step (capsules "
                 "from FK of the commanded joints). Path ratio = tool path length / start-goal distance. "
                 "Times in s, step times in us (wall clock, this machine).")
    lines.append("")
    lines.append("| method | success % | collision-free % | reached % | time to goal (median s) | "
                 "path ratio (median) | no-obstacle path ratio (median / p95) | no-obstacle reached % | "
                 "step median us | step p99 us |")
    lines.append("|---|---|---|---|---|---|---|---|---|---|")
    for m in methods:
        r, f = res[m], free[m]
        lines.append(
            f"| {m} | {_pct([x.success for x in r])} | {_pct([x.collision_free for x in r])} | "
            f"{_pct([x.reached for x in r])} | {_med([x.time_to_goal for x in r])} | "
            f"{_med([x.path_ratio for x in r if x.reached])} | "
            f"{_med([x.path_ratio for x in f if x.reached])} / "
            f"{_p95([x.path_ratio for x in f if x.reached])} | "
            f"{_pct([x.reached for x in f])} | "
            f"{np.median([x.step_median_us for x in r]):.0f} | {np.median([x.step_p99_us for x in r]):.0f} |")
    lines.append("")
    lines.append("Peak tool jerk (median over scenes, m/s^3): " + ", ".join(
        f"{m} {_med([x.peak_jerk for x in res[m]])}" for m in methods))
    lines.append("Smallest joint-limit margin (rad, min over scenes): " + ", ".join(
        f"{m} {min(x.limit_margin for x in res[m]):.3f}" for m in methods))
    lines.append("Largest joint speed / limit (max over scenes): " + ", ".join(
        f"{m} {max(x.max_vel_ratio for x in res[m]):.3f}" for m in methods))
    lines.append("Largest joint acceleration / limit (max over scenes): " + ", ".join(
        f"{m} {max(x.max_acc_ratio for x in res[m]):.3f}" for m in methods))
    lines.append("")
    cmd = "--quick" if args.quick else f"--scenes {args.scenes}"
    if args.methods != "attractor,fixed,dls":
        cmd += f" --methods {args.methods}"
    if args.append:
        cmd += " --append"
    load1 = os.getloadavg()
    lines.append(
        f"Run: `python benchmarks/reach_bench.py {cmd}` on {platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}, {elapsed:.0f} s wall; load average (1/5/15 min) before "
        f"{load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, after {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}."
    )
    lines.append("")
    lines.append(
        "What this does not cover: one goal per scene from a random start (goal sequences: sequence_bench; "
        "streams: track_bench); the start swivel is feasible and clear of limits and singularities "
        "(adversarial starts are in the sequence benchmark); the commanded joints are scored (the arm is "
        "taken to follow them exactly); step times are wall clock on a shared machine."
    )
    plot_dir = args.plot_dir or (None if args.no_write else RESULTS.parent)
    if plot_dir is not None:
        pngs = write_plots(res, free, plot_dir, f"reach_bench.py {cmd}: {args.scenes} scenes", load0)
        lines += ["", *bench_common.plots().markdown_links(pngs, RESULTS.parent)]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        if args.append and RESULTS.exists():
            RESULTS.write_text(RESULTS.read_text().rstrip("\n") + "\n\n" + text + "\n")
        else:
            RESULTS.write_text(text + "\n")
    return 0


def write_plots(res: dict[str, list[ReachMetrics]], free: dict[str, list[ReachMetrics]], out_dir: Path,
                run: str, load0: tuple[float, ...]) -> list[Path]:
    """reach_bench_success.png (success, collision-free, reached per method) and reach_bench_time.png
    (time to goal over the scenes; unreached scenes count as failures) into ``out_dir``."""
    plots = bench_common.plots()
    caption = plots.run_caption(run, load0)
    groups = ["success", "collision-free", "reached", "reached, obstacles removed"]
    rates = {
        m: [float(np.mean([x.success for x in r])), float(np.mean([x.collision_free for x in r])),
            float(np.mean([x.reached for x in r])), float(np.mean([x.reached for x in free[m]]))]
        for m, r in res.items()
    }
    n = len(next(iter(res.values())))
    return [
        plots.success_bars(out_dir / "reach_bench_success.png", groups, rates, counts=[n] * len(groups),
                           title="Reach benchmark: success per method (random table scenes)",
                           caption=caption),
        plots.time_distribution(out_dir / "reach_bench_time.png",
                                {m: [x.time_to_goal for x in r] for m, r in res.items()}, unit="s",
                                log_x=False, bins=30, caption=caption, missing="not reached",
                                title="Reach benchmark: time to goal (scenes with obstacles)"),
    ]


if __name__ == "__main__":
    sys.exit(main())
