"""The README's pictures, made from a demo recording: a short GIF and a plot of the tool path.

``python -m redarm_ros.record.media [demo_output/demo.mcap] [--out docs/media]`` writes

* ``demo.gif``: the run at a smaller size and frame rate than ``demo_output/demo.gif`` (the README
  wants it under 2 MB);
* ``tool_path.png``: the simulated tool's path (forward kinematics of the recorded ``/joint_states``)
  from above (x-y) and from the side (x-z), with each goal sent on ``/goal_pose`` marked and
  numbered, the obstacle and the table drawn; goals outside the plotted workspace are marked at the
  border with their distance.

Run it after ``make demo``. No ROS here (the recording is read with the mcap libraries).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.record.animate import (
    DEMO_CAMERA,
    SceneRenderer,
    Timeline,
    frames,
    goal_caption,
    load_timeline,
    write_gif,
)

_LOG = logging.getLogger("redarm_ros.record.media")
README_GIF_LIMIT = 2_000_000  # bytes


def plot_tool_path(tl: Timeline, arm: Any, scene: dict[str, Any], names: Sequence[str],
                   goal_positions: Sequence[Sequence[float]], out: str | Path,
                   limits: tuple[float, float, float, float, float, float] = (-0.2, 1.0, -0.6, 0.7, 0.0, 1.4)
                   ) -> Path:
    """Write the two-view tool path plot (PNG) to ``out``; ``limits`` are x0, x1, y0, y1, z0, z1 (m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    step = max(1, len(tl.t) // 4000)
    path = tl.tool_path(arm, step)
    sent = [g[1] for g in tl.goals]
    pos = np.asarray(goal_positions, dtype=float)
    x0, x1, y0, y1, z0, z1 = limits
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), dpi=100)
    views = ((axes[0], 0, 1, "x (m)", "y (m)", "from above"),
             (axes[1], 0, 2, "x (m)", "z (m)", "from the side"))
    for ax, i, j, xl, yl, title in views:
        lims = ((x0, x1), (y0, y1) if j == 1 else (z0, z1))
        ax.plot(path[:, i], path[:, j], color="tab:blue", lw=1.2, label="simulated tool")
        ax.plot(path[0, i], path[0, j], "o", color="tab:blue", ms=5)
        for o in scene.get("obstacles") or []:
            if o.get("type") == "sphere":
                c = o["center"]
                ax.add_patch(Circle((c[i], c[j]), o["radius"], color="tab:gray", alpha=0.5,
                                    label=f"obstacle ({o.get('name', 'ball')})"))
        if j == 2 and scene.get("table_height") is not None:
            ax.axhline(scene["table_height"], color="saddlebrown", lw=2, label="table top")
        for k, g in enumerate(sent):
            d = np.linalg.norm(pos - g, axis=1) if len(pos) else np.array([np.inf])
            label = str(int(np.argmin(d)) + 1) if d.min() < 1e-6 else "?"
            gx, gy = g[i], g[j]
            inside = lims[0][0] <= gx <= lims[0][1] and lims[1][0] <= gy <= lims[1][1]
            if inside:
                ax.plot(gx, gy, "*", color="tab:green", ms=12, mec="k", mew=0.5,
                        label="goal" if k == 0 else None)
                ax.annotate(label, (gx, gy), textcoords="offset points", xytext=(6, 6), fontsize=9)
            else:  # out of the plotted workspace (the out-of-reach goal): an arrow at the border
                cx = min(max(gx, lims[0][0]), lims[0][1])
                cy = min(max(gy, lims[1][0]), lims[1][1])
                ax.annotate(f"goal {label}\n({np.linalg.norm(g):.2f} m away)", (cx, cy), xytext=(-95, 30),
                            textcoords="offset points", fontsize=8, color="tab:red",
                            arrowprops={"arrowstyle": "->", "color": "tab:red"})
        ax.set_xlim(*lims[0])
        ax.set_ylim(*lims[1])
        ax.set_aspect("equal")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(title)
        ax.grid(True, alpha=0.3)
    axes[1].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"redarm demo: the simulated tool's path and the {len(sent)} goals sent")
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def make_media(mcap: str | Path, out_dir: str | Path, *, size: tuple[int, int] = (480, 360),
               fps: float = 6.0) -> dict[str, Any]:
    """Write ``demo.gif`` and ``tool_path.png`` into ``out_dir`` from the demo recording ``mcap``.

    The GIF is re-made at a lower frame rate (and then size) until it is under 2 MB.
    """
    from redarm_ros.demo import DEMO_SCENE, GOALS
    from redarm_ros.kinematics import load_arm

    arm = load_arm("pa10")
    tl = load_timeline(mcap, arm.joint_names)
    out = Path(out_dir)
    names = [g.name for g in GOALS]
    positions = [g.position for g in GOALS]
    plot = plot_tool_path(tl, arm, DEMO_SCENE, names, positions, out / "tool_path.png")
    gif = out / "demo.gif"
    while True:
        r = SceneRenderer(arm, DEMO_SCENE, size, camera=DEMO_CAMERA)
        try:
            n = write_gif(gif, frames(tl, r, fps=fps, caption=goal_caption(names, positions)), fps=fps,
                          palette_extra=[r.swatch()])
        finally:
            r.close()
        nbytes = gif.stat().st_size
        if nbytes < README_GIF_LIMIT or fps <= 2:
            break
        fps, size = fps * 0.75, (int(size[0] * 0.85), int(size[1] * 0.85))
    return {"gif": str(gif), "frames": n, "fps": fps, "size": list(size), "bytes": nbytes, "plot": str(plot)}


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point: ``python -m redarm_ros.record.media [MCAP] [--out DIR]``."""
    ap = argparse.ArgumentParser(prog="python -m redarm_ros.record.media",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("mcap", nargs="?", default="demo_output/demo.mcap", help="the demo's recording")
    ap.add_argument("--out", default="docs/media", help="output directory (default docs/media)")
    ap.add_argument("--size", default="480x360", help="GIF size WIDTHxHEIGHT (default 480x360)")
    ap.add_argument("--fps", type=float, default=6.0, help="GIF frame rate (default 6)")
    ns = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    w, h = (int(v) for v in ns.size.lower().split("x"))
    if not Path(ns.mcap).is_file():
        _LOG.error("%s not found: run `make demo` first", ns.mcap)
        return 1
    info = make_media(ns.mcap, ns.out, size=(w, h), fps=ns.fps)
    _LOG.info("wrote %s (%d frames, %.0f kB) and %s", info["gif"], info["frames"], info["bytes"] / 1e3,
              info["plot"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
