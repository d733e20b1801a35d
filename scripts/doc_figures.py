"""Draw docs/media/swivel.png: the swivel angle of a 7-DOF arm, from the package's own kinematics.

For one tool pose the elbow can only lie on a circle around the shoulder-wrist axis; the swivel angle
says where on that circle. The figure shows the PA10 at three swivel angles of the same tool pose,
the circle, its axis and the angle.

    .venv/bin/python scripts/doc_figures.py [--out docs/media]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402

# A tool pose in front of the PA10, tool pointing down (rotation by pi about x).
TOOL_DOWN = np.diag([1.0, -1.0, -1.0])
TOOL_POSITION = np.array([0.55, -0.15, 0.35])
SWIVELS = (3.0, 2.2, -2.4)  # rad; the arm drawn at each (solid, dashed, dotted): all in the limits


def pose(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """4x4 transform from a rotation matrix and a position."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotation, position
    return T


def draw_swivel(out: Path) -> Path:
    """Write ``out/swivel.png`` and return its path."""
    arm = load_arm("pa10")
    T = pose(TOOL_DOWN, TOOL_POSITION)
    centre, normal, radius = arm.elbow_circle(T)
    fig = plt.figure(figsize=(8.0, 6.0), dpi=100)
    ax = fig.add_subplot(projection="3d")

    # The elbow circle: the elbow at every swivel angle, whole (grey) and where a solution is in the
    # joint limits (orange).
    def elbow(s: float, limits: bool = True) -> np.ndarray | None:
        sols = arm.ik(T, float(s), limits=limits)
        return arm.key_points(sols[0])[2] if len(sols) else None

    grid = np.linspace(-np.pi, np.pi, 361)
    whole = np.array([elbow(s, limits=False) for s in grid])
    ax.plot(*whole.T, color="0.6", lw=1, ls="--", label="elbow circle")
    inside = np.array([e if e is not None else np.full(3, np.nan) for e in (elbow(s) for s in grid)])
    ax.plot(*inside.T, color="tab:orange", lw=2.5, label="swivels with an in-limit solution")
    zero = elbow(0.0, limits=False)
    ax.scatter(*zero, color="0.3", s=15)
    ax.text(*zero, "  s = 0", color="0.3")

    styles = ("-", "--", ":")
    for s, style in zip(SWIVELS, styles, strict=True):
        sols = arm.ik(T, s)
        if not len(sols):
            continue
        P = arm.key_points(sols[0])  # base, shoulder, elbow, wrist, tool
        ax.plot(*P.T, style, color="tab:blue", lw=3 if style == "-" else 2, marker="o", ms=5,
                label=f"arm at swivel {s:+.1f} rad")
    P0 = arm.key_points(arm.ik(T, SWIVELS[0])[0])
    shoulder, elbow0, wrist = P0[1], P0[2], P0[3]

    # The shoulder-wrist axis (the circle's normal through its centre).
    ax.plot(*np.array([shoulder, wrist]).T, color="black", lw=1, ls="-.", label="shoulder-wrist axis")
    ax.scatter(*centre, color="black", s=12)
    # A change of swivel: from the first arm's elbow to the second's, drawn as an arc.
    e1 = elbow(SWIVELS[1])
    u0 = (elbow0 - centre) / np.linalg.norm(elbow0 - centre)
    u1 = (e1 - centre) / np.linalg.norm(e1 - centre)
    ang = np.arctan2(np.dot(np.cross(u0, u1), normal), np.dot(u0, u1))
    w = np.cross(normal, u0)
    arc = np.array([centre + 0.45 * radius * (np.cos(t) * u0 + np.sin(t) * w)
                    for t in np.linspace(0.0, ang, 30)])
    ax.plot(*arc.T, color="tab:red", lw=2)
    for e in (elbow0, e1):
        ax.plot(*np.array([centre, e]).T, color="tab:red", lw=0.8)
    mid = arc[len(arc) // 2]
    ax.text(*mid, "  swivel change", color="tab:red")
    ax.text(*shoulder, "  shoulder")
    ax.text(*wrist, "  wrist")
    ax.text(*TOOL_POSITION, "  tool")

    # Table top at z = 0.
    xx, yy = np.meshgrid(np.linspace(-0.2, 0.8, 2), np.linspace(-0.6, 0.4, 2))
    ax.plot_surface(xx, yy, np.zeros_like(xx), color="0.85", alpha=0.4)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_xlim(-0.2, 0.8)
    ax.set_ylim(-0.6, 0.4)
    ax.set_zlim(0.0, 1.0)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=18, azim=-60)
    ax.set_title("PA10, one tool pose: the elbow moves on a circle around the shoulder-wrist axis")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    path = out / "swivel.png"
    fig.savefig(path)
    plt.close(fig)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "docs" / "media")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(draw_swivel(args.out))


if __name__ == "__main__":
    main()
