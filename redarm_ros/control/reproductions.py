"""Reproductions of the two papers' examples, written as PNG plots plus a metrics table.

    python -m redarm_ros.control.reproductions --out repro_output            # full size
    python -m redarm_ros.control.reproductions --out /tmp/r --quick          # reduced size (tests)

Scenarios (PA10, 100 Hz, forward Euler):

* ``swivel1`` -- swivel paper, example 1: the tool circles three times in a horizontal plane at
  constant orientation near a spherical obstacle (``config/scenes/swivel_example1.yaml``, placed so that
  two of the ``s_des`` values would run into it); the swivel follows eq. (32) with a fixed ``s_des``
  for several values. Plots: s(t) (solid) and s_des (dashed), as the paper's fig. 7; the elbow path on
  the shoulder sphere S1 for ``s_des = -3pi/4`` with (red) and without (dashed blue) the obstacle.
* ``swivel2`` -- example 2: the same kind of motion (a higher circle, where 0.8 of the elbow circle is
  in the joint limits) with ``s_des`` rising linearly from 0.2 pi to 1.8 pi (0.8 of a turn) past a
  sphere (``swivel_example2.yaml``); integrated in the swivel-quaternion form (no trigonometry in the
  loop). Plots: s (red) and s_des (dashed blue) as the paper's fig. 9, plus s without the obstacle; the
  elbow on S1.
* ``narrow`` -- attractor paper, "cluttered environment": a target on the table surrounded by three
  obstacles (U shape, narrow passage); the hand passes over the front wall and dives behind it.
* ``moved_target`` -- the target is displaced mid-reach (paper fig. 7).
* ``appearing_obstacle`` -- an obstacle appears on the path mid-reach (paper fig. 8).

For each scenario: reached / final position error, minimum clearance arm-obstacles (> 0 means
collision-free; capsules from FK of the commanded joints), joint-limit margin, path length over
straight-line length, peak tool jerk. Matplotlib (Agg) is imported only here.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.control.elbow import ArmGeometry, elbow_circle
from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import ControllerParams
from redarm_ros.control.simulate import Trajectory, evaluate, peak_jerk, run_controller
from redarm_ros.control.swivel_dynamics import SwivelDynamics, SwivelParams, wrap_angle
from redarm_ros.geometry.obstacles import ArmCapsules, Cylinder, Scene, Sphere, links_clearance, load_scene
from redarm_ros.kinematics.protocols import ControlledSwivelArm

LOG = logging.getLogger(__name__)
DT = 0.01
DPI = 90  # small PNGs (tens of kB)


@dataclass
class ScenarioReport:
    """Scores of one reproduction run (units: m, rad, m/s^3); ``reached`` is None for tracking runs."""

    scenario: str
    variant: str
    reached: bool | None
    pos_err: float
    min_clearance: float
    limit_margin: float
    path_ratio: float
    peak_jerk: float
    note: str = ""


def _pose(p: Sequence[float], R: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def _down(yaw: float = 0.0) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


# Tool pointing forward (+x), horizontal: keeps the PA10 wrist above the shoulder for the circles.
_FORWARD = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


# ------------------------------------------------------------------------------------------------
# Swivel paper examples
# ------------------------------------------------------------------------------------------------


@dataclass
class SwivelRun:
    t: np.ndarray
    s: np.ndarray
    s_des: np.ndarray
    elbow: np.ndarray
    q: np.ndarray
    clearance: np.ndarray


def circle_path(t: float, period: float, center: Sequence[float], radius: float) -> np.ndarray:
    """Tool position (m) on the horizontal circle at time t (s)."""
    w = 2.0 * math.pi * t / period
    return np.array([center[0] + radius * math.cos(w), center[1] + radius * math.sin(w), center[2]])


def run_swivel_example(arm: ControlledSwivelArm, scene: Scene, s_des_fn: Any, laps: float = 3.0,
                       period: float = 4.0, center: Sequence[float] = (0.5, 0.0, 0.62), radius: float = 0.12,
                       quaternion_form: bool = False, params: SwivelParams | None = None,
                       capsules: ArmCapsules | None = None,
                       score_scene: Scene | None = None) -> SwivelRun:
    """Tool circling ``laps`` times at constant orientation; swivel from eq. (32); IK each step.

    ``s_des_fn(t)`` gives the desired swivel (rad). With ``quaternion_form`` the state is the swivel
    quaternion u and the loop uses no trigonometric call (probes r+/- u with constant cos/sin eps).
    The joint solution at each step is the in-limit one nearest the previous (no branch flip); NaN
    where there is none.
    ``score_scene``: scene the recorded clearance is measured against (default: ``scene``).
    """
    caps = capsules or ArmCapsules()
    geom = ArmGeometry.from_arm(arm)
    dyn = SwivelDynamics(params or SwivelParams(lam_des=0.5, lam_obs=0.5, lam_sing=0.0, lam_lim=0.0,
                                                max_rate=3.0, obs_influence=0.2))
    n = int(round(laps * period / DT))
    s = float(s_des_fn(0.0))
    u = (math.cos(s), math.sin(s))
    q_prev: np.ndarray | None = None
    ts, ss, sds, elbows, qs, clears = [], [], [], [], [], []
    for k in range(n + 1):
        t = k * DT
        T = _pose(circle_path(t, period, center, radius), _FORWARD)
        circle = elbow_circle(geom, T)
        sd = float(s_des_fn(t))
        if k > 0:
            if quaternion_form:
                ud = (math.cos(sd), math.sin(sd))  # the desired value is an input, not in the loop
                f = dyn.forces_u(circle, u, scene, caps)
                u = dyn.step_u(u, ud, DT, f)
                s = math.atan2(u[1], u[0])  # for plotting only
            else:
                f = dyn.forces(circle, s, scene, caps)
                s = dyn.step(s, sd, DT, f)
        sols = arm.ik_u(T, (u[0], u[1], 0.0)) if quaternion_form else arm.ik(T, s)
        if sols.shape[0]:
            if q_prev is None:  # start on the branch farthest from the joint limits
                margins = np.min(np.minimum(sols - arm.lower, arm.upper - sols), axis=1)
                q = sols[int(np.argmax(margins))]
            else:
                q = sols[int(np.argmin(np.max(np.abs(sols - q_prev), axis=1)))]
            q_prev = q
        # a step without an in-limit solution is NaN (not the last one again): the report counts them
        qs.append(q if sols.shape[0] else np.full(arm.n, np.nan))
        ts.append(t)
        ss.append(s)
        sds.append(sd)
        elbows.append(circle.elbow(s))
        clears.append(links_clearance(circle.key_points(s), score_scene or scene, caps).distance)
    return SwivelRun(np.array(ts), np.array(ss), np.array(sds), np.array(elbows), np.array(qs),
                     np.array(clears))


def _swivel_report(arm: ControlledSwivelArm, name: str, variant: str, run: SwivelRun) -> ScenarioReport:
    q = run.q
    valid = np.all(np.isfinite(q), axis=1)
    qv = q[valid]
    margin = float(np.min(np.minimum(qv - arm.lower, arm.upper - qv))) if valid.any() else -math.inf
    note = "" if valid.all() else f"{int((~valid).sum())} steps without an in-limit IK solution"
    if not note:
        dev = np.abs([wrap_angle(a - b) for a, b in zip(run.s, run.s_des, strict=True)])
        note = f"max abs(s - s_des) {dev.max():.2f} rad"
    return ScenarioReport(name, variant, None, float("nan"), float(np.min(run.clearance)), margin,
                          float("nan"), peak_jerk(run.elbow, DT), note + "; jerk of the elbow")


#: Tool circle of example 2 (centre, m): higher than example 1's, so that the ramp can cover 0.8 of
#: a turn inside the joint limits (at example 1's circle only the upper half of the elbow circle is).
EXAMPLE2_CENTER = (0.45, 0.0, 0.8)
#: The ramp of example 2: s_des from EXAMPLE2_RAMP[0] to EXAMPLE2_RAMP[1] (rad) over the run.
EXAMPLE2_RAMP = (0.2 * math.pi, 1.8 * math.pi)
#: The fixed s_des of example 1's elbow plot (one of the two that meet the sphere).
EXAMPLE1_ELBOW_S = -3 * math.pi / 4


def swivel_scene(example: int = 1) -> Scene:
    """The spherical obstacle of swivel example 1 or 2 (config/scenes/swivel_example<N>.yaml)."""
    return load_scene(f"swivel_example{int(example)}")


def example2_ramp(total: float) -> Any:
    """s_des(t) of example 2 for a run of ``total`` s (rad, wrapped)."""
    s0, s1 = EXAMPLE2_RAMP

    def ramp(t: float) -> float:
        return wrap_angle(s0 + (s1 - s0) * min(max(t / total, 0.0), 1.0))

    return ramp


def reproduce_swivel(arm: ControlledSwivelArm, out: Path, quick: bool, example: int) -> list[ScenarioReport]:
    """Swivel paper example 1 (fixed s_des) or 2 (ramp s_des, quaternion form)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = swivel_scene(example)
    empty = Scene()
    laps = 1.0 if quick else 3.0
    reports = []
    if example == 1:
        # The upper half of the elbow circle (s in [pi/2, 3pi/2]): with the PA10 shoulder limit of
        # +/-91 deg the lower half has no in-limit solution for these tool poses.
        # (s = pi, the elbow straight up, needs theta1 or theta3 at +/-180 deg: outside the limits.)
        values = [-3 * math.pi / 4, -0.9 * math.pi, 3 * math.pi / 4] if quick else [
            -math.pi / 2, -3 * math.pi / 4, -0.9 * math.pi, 3 * math.pi / 4, math.pi / 2]
        runs = {}
        for v in values:
            runs[v] = (run_swivel_example(arm, scene, lambda t, v=v: v, laps),
                       run_swivel_example(arm, empty, lambda t, v=v: v, laps, score_scene=scene))
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for i, v in enumerate(values):
            with_o, without = runs[v]
            c = f"C{i}"
            ax.plot(with_o.t, with_o.s, color=c, label=f"s, s_des = {v:+.2f}")
            ax.plot(with_o.t, with_o.s_des, color=c, ls="--", lw=0.8)
        ax.plot([], [], color="0.3", ls="--", lw=0.8, label="s_des (dashed)")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("swivel s [rad]")
        ax.set_title("Example 1: s(t) with the obstacle (solid) for fixed s_des (dashed)")
        ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        fig.savefig(out / "swivel_example1_s.png", dpi=DPI)
        plt.close(fig)
        with_o, without = runs[EXAMPLE1_ELBOW_S]
        _elbow_sphere_plot(arm, scene, with_o, without, out / "swivel_example1_elbow.png",
                           "Example 1: elbow on S1, s_des = -3pi/4")
        for v in values:
            reports.append(_swivel_report(arm, "swivel1", f"s_des={v:+.2f} obstacle", runs[v][0]))
            reports.append(_swivel_report(arm, "swivel1", f"s_des={v:+.2f} ignoring it", runs[v][1]))
    else:
        # Always the full three laps: the ramp's rate, not the run's length, decides what happens.
        laps = 3.0
        period = 4.0
        ramp = example2_ramp(laps * period)
        with_o = run_swivel_example(arm, scene, ramp, laps, center=EXAMPLE2_CENTER, quaternion_form=True)
        without = run_swivel_example(arm, empty, ramp, laps, center=EXAMPLE2_CENTER, quaternion_form=True,
                                     score_scene=scene)
        fig, ax = plt.subplots(figsize=(8, 4.5))
        ax.plot(with_o.t, _unwrap_from(with_o.s, EXAMPLE2_RAMP[0]), "r", label="s with obstacle")
        ax.plot(with_o.t, _unwrap_from(with_o.s_des, EXAMPLE2_RAMP[0]), "b--", lw=1.0,
                label="s_des (linear ramp)")
        ax.plot(without.t, _unwrap_from(without.s, EXAMPLE2_RAMP[0]), color="0.5", ls=":", lw=0.8,
                label="s without obstacle")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("swivel s [rad] (unwrapped)")
        ax.set_title("Example 2: linearly increasing s_des (0.8 turn), swivel-quaternion form")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "swivel_example2_s.png", dpi=DPI)
        plt.close(fig)
        _elbow_sphere_plot(arm, scene, with_o, without, out / "swivel_example2_elbow.png",
                           "Example 2: elbow on S1, ramp s_des")
        reports.append(_swivel_report(arm, "swivel2", "ramp obstacle", with_o))
        reports.append(_swivel_report(arm, "swivel2", "ramp ignoring it", without))
    return reports


def _unwrap_from(s: np.ndarray, start: float) -> np.ndarray:
    """``s`` (rad) unwrapped, shifted by whole turns so that it starts near ``start``."""
    u = np.unwrap(s)
    return u + 2.0 * math.pi * round((start - u[0]) / (2.0 * math.pi))


def _elbow_sphere_plot(arm: ControlledSwivelArm, scene: Scene, with_o: SwivelRun, without: SwivelRun,
                       path: Path, title: str) -> None:
    import matplotlib.pyplot as plt

    geom = ArmGeometry.from_arm(arm)
    ps = np.asarray(geom.shoulder)
    fig = plt.figure(figsize=(6.5, 6))
    ax = fig.add_subplot(111, projection="3d")
    u, v = np.mgrid[0:2 * np.pi:40j, 0:np.pi:20j]
    r = geom.upper
    ax.plot_wireframe(ps[0] + r * np.cos(u) * np.sin(v), ps[1] + r * np.sin(u) * np.sin(v),
                      ps[2] + r * np.cos(v), color="0.85", lw=0.4)
    ax.plot(*with_o.elbow.T, "r", lw=1.5, label="elbow, with obstacle")
    ax.plot(*without.elbow.T, "b--", lw=1.0, label="elbow, without obstacle")
    for o in scene.obstacles:
        if isinstance(o, Sphere):
            c = np.asarray(o.center)
            rr = o.radius
            ax.plot_surface(c[0] + rr * np.cos(u) * np.sin(v), c[1] + rr * np.sin(u) * np.sin(v),
                            c[2] + rr * np.cos(v), color="red", alpha=0.35, lw=0)
    ax.scatter(*ps, color="k", s=20)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------
# Attractor paper scenarios
# ------------------------------------------------------------------------------------------------


def _start(arm: ControlledSwivelArm, p: Sequence[float], yaw: float = 0.0) -> np.ndarray:
    q, info = arm.ik_nearest(_pose(p, _down(yaw)), np.array([0.0, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    if q is None:
        raise RuntimeError(f"no start posture for {p}: {info.message}")
    return q


def _reach_report(arm: ControlledSwivelArm, name: str, variant: str, scene: Scene, tr: Trajectory,
                  T_goal: np.ndarray, note: str = "") -> ScenarioReport:
    m = evaluate(arm, scene, tr.q, T_goal, DT, tr.step_s, tr.reached_at)
    return ScenarioReport(name, variant, m.reached, m.pos_err, m.min_clearance, m.limit_margin,
                          m.path_ratio, m.peak_jerk, note)


def _reach_plot(arm: ControlledSwivelArm, scenes: list[tuple[float, Scene]], tr: Trajectory,
                goals: list[np.ndarray], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Polygon

    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    top, side, dist, sw = axes.ravel()
    for t0, scene in scenes:
        alpha = 0.35 if t0 == 0.0 else 0.2
        for o in scene.obstacles:
            c = o.center
            if isinstance(o, Sphere | Cylinder):
                top.add_patch(Circle(c[:2], o.footprint_radius, color="C3", alpha=alpha))
                fr, bottom = o.footprint_radius, o.top - 2 * (o.top - c[2])
                side.add_patch(Polygon([[c[0] - fr, bottom], [c[0] + fr, bottom], [c[0] + fr, o.top],
                                        [c[0] - fr, o.top]], color="C3", alpha=alpha))
            else:
                cy, sy = math.cos(o.yaw), math.sin(o.yaw)
                hx, hy, hz = o.half
                corners = [(c[0] + cy * x - sy * y, c[1] + sy * x + cy * y)
                           for x, y in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
                top.add_patch(Polygon(corners, color="C3", alpha=alpha))
                xs = [p[0] for p in corners]
                side.add_patch(Polygon([[min(xs), c[2] - hz], [max(xs), c[2] - hz], [max(xs), c[2] + hz],
                                        [min(xs), c[2] + hz]], color="C3", alpha=alpha))
    top.plot(tr.tool[:, 0], tr.tool[:, 1], "b", label="tool")
    top.plot(tr.elbow[:, 0], tr.elbow[:, 1], "g", lw=0.8, label="elbow")
    side.plot(tr.tool[:, 0], tr.tool[:, 2], "b", label="tool")
    side.plot(tr.elbow[:, 0], tr.elbow[:, 2], "g", lw=0.8, label="elbow")
    for i, g in enumerate(goals):
        top.plot(g[0, 3], g[1, 3], "k*", ms=10, label="target" if i == 0 else None)
        side.plot(g[0, 3], g[2, 3], "k*", ms=10)
    side.axhline(0.0, color="0.4", lw=0.8)
    top.set_aspect("equal")
    side.set_aspect("equal")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("top view")
    side.set_xlabel("x [m]")
    side.set_ylabel("z [m]")
    side.set_title("side view (table at z = 0)")
    top.legend(fontsize=8)
    goal_pos = np.array([g[:3, 3] for g in goals])
    # distance to the target active at each time
    d = np.linalg.norm(tr.tool - goal_pos[-1], axis=1)
    dist.plot(tr.t, d, "b", label="distance to (final) target [m]")
    dist.plot(tr.t, np.clip(tr.clearance, -0.1, 0.5), "C3", label="clearance [m]")
    dist.axhline(0.0, color="k", lw=0.6)
    dist.set_xlabel("t [s]")
    dist.legend(fontsize=8)
    sw.plot(tr.t, np.unwrap(tr.swivel), "g", label="swivel s (unwrapped)")
    sw.plot(tr.t, np.unwrap(tr.swivel_desired), "g:", label="preferred s_des")
    sw.set_xlabel("t [s]")
    sw.set_ylabel("[rad]")
    sw.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


NARROW_TARGET = (0.62, 0.0, 0.06)


def reproduce_attractor(arm: ControlledSwivelArm, out: Path, quick: bool) -> list[ScenarioReport]:
    """Narrow passage, moved target, appearing obstacle (attractor paper section IV-C)."""
    reports = []
    duration = 8.0
    params = ControllerParams()
    # 1. target surrounded by three obstacles
    scene = load_scene("narrow_passage")
    T = _pose(NARROW_TARGET, _down())
    ctl = make_controller(arm, scene, params)
    ctl.reset(_start(arm, (0.38, 0.15, 0.3)))
    tr = run_controller(ctl, T, duration, DT)
    _reach_plot(arm, [(0.0, scene)], tr, [T], out / "attractor_narrow_passage.png",
                "Target surrounded by three obstacles (narrow passage)")
    reports.append(_reach_report(arm, "narrow", "3 obstacles", scene, tr, T))
    # 2. target displaced mid-reach (A -> B)
    scene = load_scene("table_empty")
    TA = _pose((0.6, -0.25, 0.1), _down())
    TB = _pose((0.55, 0.25, 0.12), _down(0.6))
    ctl = make_controller(arm, scene, params)
    ctl.reset(_start(arm, (0.38, -0.15, 0.3)))
    tr = run_controller(ctl, TA, duration, DT, events=[(0.9, lambda c: c.set_goal(TB))])
    _reach_plot(arm, [(0.0, scene)], tr, [TA, TB], out / "attractor_moved_target.png",
                "Target displaced from A to B at t = 0.9 s")
    reports.append(_reach_report(arm, "moved_target", "A->B at 0.9 s", scene, tr, TB))
    # 3. obstacle appears on the path mid-reach
    empty = load_scene("table_empty")
    can = Cylinder((0.56, 0.0, 0.1), 0.05, 0.2, "appearing can")
    with_can = Scene((can,), 0.0, "appeared")
    T = _pose((0.68, -0.12, 0.08), _down())
    ctl = make_controller(arm, empty, params)
    ctl.reset(_start(arm, (0.36, 0.2, 0.2)))
    tr = run_controller(ctl, T, duration, DT, events=[(0.4, lambda c: c.set_scene(with_can))])
    _reach_plot(arm, [(0.4, with_can)], tr, [T], out / "attractor_appearing_obstacle.png",
                "An obstacle appears on the path at t = 0.4 s")
    reports.append(_reach_report(arm, "appearing_obstacle", "can at 0.4 s", with_can, tr, T,
                                 "clearance scored against the can for the whole run"))
    return reports


def format_reports(reports: list[ScenarioReport]) -> str:
    """Markdown table of the reports."""
    lines = ["| scenario | variant | reached | final pos err (m) | min clearance (m) | joint-limit margin "
             "(rad) | path / straight | peak jerk (m/s^3) | note |", "|---|---|---|---|---|---|---|---|---|"]
    def num(x: float, fmt: str) -> str:
        return "-" if not math.isfinite(x) else format(x, fmt)

    for r in reports:
        reached = "-" if r.reached is None else ("yes" if r.reached else "NO")
        lines.append(f"| {r.scenario} | {r.variant} | {reached} | {num(r.pos_err, '.2e')} | "
                     f"{num(r.min_clearance, '.3f')} | {num(r.limit_margin, '.3f')} | "
                     f"{num(r.path_ratio, '.3f')} | {num(r.peak_jerk, '.1f')} | {r.note} |")
    return "\n".join(lines)


def run_all(out: Path, quick: bool = False, only: Sequence[str] = ("swivel1", "swivel2", "attractor"),
            arm_name: str = "pa10") -> list[ScenarioReport]:
    """Run the selected reproductions, write PNGs, ``reproductions.md`` and ``reproductions.json``."""
    from redarm_ros.kinematics import load_arm

    out.mkdir(parents=True, exist_ok=True)
    arm = load_arm(arm_name)
    reports: list[ScenarioReport] = []
    if "swivel1" in only:
        reports += reproduce_swivel(arm, out, quick, 1)
    if "swivel2" in only:
        reports += reproduce_swivel(arm, out, quick, 2)
    if "attractor" in only:
        reports += reproduce_attractor(arm, out, quick)
    table = format_reports(reports)
    (out / "reproductions.md").write_text(f"# Reproductions ({'quick' if quick else 'full'})\n\n{table}\n")
    (out / "reproductions.json").write_text(json.dumps([asdict(r) for r in reports], indent=1))
    return reports


def main(argv: list[str] | None = None) -> int:
    """CLI entry point."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="repro_output", help="output directory for PNGs and tables")
    ap.add_argument("--quick", action="store_true", help="reduced size (fewer laps and s_des values)")
    ap.add_argument("--only", default="swivel1,swivel2,attractor", help="comma-separated subset")
    args = ap.parse_args(argv)
    reports = run_all(Path(args.out), args.quick, [s.strip() for s in args.only.split(",") if s.strip()])
    sys.stdout.write(format_reports(reports) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
