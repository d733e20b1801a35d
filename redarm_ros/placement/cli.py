"""``redarm-placement``: where the arm's base should stand so that every task pose is reachable.

``redarm-placement TASKS.yaml --out DIR`` scores every base pose of the task file's grid
(:mod:`.problem` has the file format), prints the best placements and writes into DIR:

* ``placements.npz``: the grid (``x``, ``y``, ``yaw``), ``base_height`` (m), per base pose ``valid``,
  ``fraction``,
  ``robustness`` (rad), ``worst_margin`` (rad), ``footprint_ok``, per (base pose, task) ``reach``,
  ``width`` (rad), ``margin`` (rad), and ``ranking`` (indices into the flattened grid, best first);
* ``ranking.csv``: the valid placements, best first;
* ``heatmap_yaw<deg>.png``: per yaw, the share of reachable tasks and the robustness over (x, y), with
  the tasks' positions and the scene's obstacles from above.

``--engine dask --address tcp://host:port`` runs the same work on a Dask cluster (optional extra).
Exit codes: 0 a valid placement exists, 1 none does, 2 bad input.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.parallel import ENGINES
from redarm_ros.placement.problem import load_problem
from redarm_ros.placement.study import PlacementResult, place

__all__ = ["main", "write_outputs"]

_log = logging.getLogger("redarm-placement")


def write_outputs(res: PlacementResult, out: Path, *, plots: bool = True) -> list[Path]:
    """Write placements.npz, ranking.csv and (``plots``) one heat map PNG per yaw into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    g = res.problem.grid
    rank = res.ranking()
    npz = out / "placements.npz"
    np.savez_compressed(
        npz, x=g.x, y=g.y, yaw=g.yaw, shape=np.array(g.shape), arm=res.problem.arm,
        base_height=np.float64(res.problem.base_height),
        task_names=np.array(res.problem.task_names), tasks=res.problem.tasks,
        valid=res.valid, fraction=res.fraction, robustness=res.robustness, worst_margin=res.worst_margin,
        footprint_ok=res.footprint_ok, reach=res.reach, width=res.width, margin=res.margin, ranking=rank,
    )
    csv = out / "ranking.csv"
    with csv.open("w") as f:
        f.write("rank,x_m,y_m,yaw_deg,robustness_rad,worst_margin_rad\n")
        for k, i in enumerate(rank, 1):
            x, y, w = res.poses[i]
            f.write(f"{k},{x:.4f},{y:.4f},{math.degrees(w):.2f},{res.robustness[i]:.6f},"
                    f"{res.worst_margin[i]:.6f}\n")
    paths = [npz, csv]
    if plots:
        paths += _heatmaps(res, out)
    return paths


def _heatmaps(res: PlacementResult, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from redarm_ros.geometry.obstacles import Box, Cylinder, Scene, Sphere

    g = res.problem.grid
    nx, ny, nw = g.shape
    frac = res.fraction.reshape(nx, ny, nw)
    rob = np.nan_to_num(res.robustness, nan=0.0).reshape(nx, ny, nw)
    valid = res.valid.reshape(nx, ny, nw)
    step_x = g.x[1] - g.x[0] if nx > 1 else 0.1
    step_y = g.y[1] - g.y[0] if ny > 1 else 0.1
    ext = (g.x[0] - step_x / 2, g.x[-1] + step_x / 2, g.y[0] - step_y / 2, g.y[-1] + step_y / 2)
    scene = Scene.from_dict(res.problem.scene) if res.problem.scene else None
    paths = []
    for k, yaw in enumerate(g.yaw):
        fig, axs = plt.subplots(1, 2, figsize=(11, 4.8), constrained_layout=True)
        panels = ((axs[0], frac[:, :, k], "share of tasks reachable", 1.0, "fraction"),
                  (axs[1], rob[:, :, k], "robustness: narrowest swivel set (valid only)", 2 * math.pi, "rad"))
        for ax, data, title, vmax, unit in panels:
            im = ax.imshow(data.T, origin="lower", extent=ext, vmin=0.0, vmax=vmax, cmap="viridis")
            ax.contour(g.x, g.y, valid[:, :, k].T.astype(float), levels=[0.5], colors="w", linewidths=1)
            ax.plot(res.problem.tasks[:, 0, 3], res.problem.tasks[:, 1, 3], "r+", ms=8, label="tasks")
            for o in scene.obstacles if scene else ():
                c = o.center
                if isinstance(o, Box):
                    ax.add_patch(matplotlib.patches.Rectangle(
                        (c[0] - o.size[0] / 2, c[1] - o.size[1] / 2), o.size[0], o.size[1],
                        angle=math.degrees(o.yaw), rotation_point="center", fill=False, ec="orange"))
                elif isinstance(o, Cylinder | Sphere):
                    ax.add_patch(matplotlib.patches.Circle(c[:2], o.radius, fill=False, ec="orange"))
            ax.set_title(f"{res.problem.arm}, yaw {math.degrees(yaw):.0f} deg: {title}", fontsize=9)
            ax.set_xlabel("base x (m)")
            ax.set_ylabel("base y (m)")
            fig.colorbar(im, ax=ax, label=unit)
        p = out / f"heatmap_yaw{math.degrees(yaw):03.0f}.png"
        fig.savefig(p, dpi=90)
        plt.close(fig)
        paths.append(p)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    """Command line (module doc)."""
    ap = argparse.ArgumentParser(prog="redarm-placement", description=__doc__.splitlines()[0])
    ap.add_argument("tasks", type=Path, help="task file (YAML: arm, grid, tasks, optional scene)")
    ap.add_argument("--out", type=Path, default=Path("placement_output"), help="output directory")
    ap.add_argument("--engine", choices=ENGINES, default="local", help="where the work runs (default local)")
    ap.add_argument("--workers", type=int, default=None,
                    help="local worker processes (default: all cores; 1 = in this process)")
    ap.add_argument("--address", default=None, help="Dask scheduler address, tcp://host:port")
    ap.add_argument("--top", type=int, default=10, help="placements to print (default 10)")
    ap.add_argument("--no-prune", action="store_true", help="check every pair exactly (no inverse map)")
    ap.add_argument("--no-plots", action="store_true", help="skip the heat map PNGs")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        problem = load_problem(args.tasks)
        t0 = time.perf_counter()
        res = place(problem, engine=args.engine, workers=args.workers, address=args.address,
                    prune=not args.no_prune, progress=sys.stderr if sys.stderr.isatty() else None)
    except InvalidInputError as exc:
        _log.error("redarm-placement: %s", exc)
        return 2
    dt = time.perf_counter() - t0
    paths = write_outputs(res, args.out, plots=not args.no_plots)
    rank = res.ranking()
    _log.info("%s: %d base poses x %d tasks in %.2f s (%s); inverse reachability ruled out %.1f %%; "
              "%d valid placements", problem.arm, problem.grid.size, len(problem.tasks), dt, args.engine,
              100 * res.pruned_share, len(rank))
    for k, i in enumerate(rank[: args.top], 1):
        x, y, w = res.poses[i]
        rob = "" if math.isnan(res.robustness[i]) else f"robustness {res.robustness[i]:.3f} rad, "
        _log.info("  %2d. x %+.3f m, y %+.3f m, yaw %6.1f deg: %smargin %.3f rad",
                  k, x, y, math.degrees(w), rob, res.worst_margin[i])
    _log.info("wrote %s", ", ".join(str(p) for p in paths))
    return 0 if len(rank) else 1


if __name__ == "__main__":
    sys.exit(main())
