"""The placement heat map on the floor under the arm, as geometry for the browser view (no ROS, no viser).

``redarm-placement`` writes ``placements.npz`` in a world frame whose floor is z = 0, with the arm's base
at ``Trans(x, y, base_height) Rz(yaw)`` (:func:`redarm_ros.placement.problem.base_transforms`). The view
draws the arm in its base frame, so :func:`placement_floor` draws the map as seen by the arm standing at
the **best** placement: every world point ``p`` is shown at ``B_best^-1 p``. The floor is then the plane
z = -base_height, the best placement's square lies right under the arm, and the tasks appear where the
arm would meet them.

Per (x, y) cell: the share of tasks reachable at the best yaw there (max over the yaws) as a coloured
square (viridis, as in the PNG heat maps; cells with no task reachable are left out), the boundary of
the cells where some yaw is a valid placement, the grid's extent, and the best placement as a cross with
a heading line along the arm's x axis. Units: m, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.placement.problem import base_transforms

__all__ = ["FLOOR_LIFT", "PlacementFloor", "floor_meshes", "load_placements", "placement_floor"]

REQUIRED = ("x", "y", "yaw", "shape", "base_height", "valid", "fraction", "ranking", "tasks")
FLOOR_LIFT = 0.002  # m: the map floats this far above the floor, so it never flickers with the ground grid
HEADING_M = 0.3  # m: length of the best placement's heading line


@dataclass(frozen=True)
class PlacementFloor:
    """What the view draws, in the view's frame (the arm's base frame at the best placement).

    ``corners`` (K, 4, 3) of the K drawn squares (counter-clockwise seen from above), ``fraction`` (K,)
    and ``colors`` (K, 3) uint8 RGB of each; ``outline`` (L, 2, 3) segments around the cells where some
    yaw is valid; ``extent`` (4, 2, 3) the grid's border; ``best_mark`` (4, 2, 3) cross and heading at
    the best placement; ``tasks`` (m, 3) task positions; ``best`` (x, y, yaw) world pose the arm stands at;
    ``best_valid`` False when no placement is valid (the arm then stands at the largest share).
    """

    corners: np.ndarray
    fraction: np.ndarray
    colors: np.ndarray
    outline: np.ndarray
    extent: np.ndarray
    best_mark: np.ndarray
    tasks: np.ndarray
    best: tuple[float, float, float]
    best_valid: bool
    n_valid: int
    n_poses: int
    arm: str
    base_height: float

    def markdown(self, source: str = "") -> str:
        """The panel text: what is drawn and where the arm stands."""
        x, y, w = self.best
        where = f"x {x:+.2f} m, y {y:+.2f} m, yaw {math.degrees(w):.0f} deg"
        head = (f"The arm stands at the **best placement** ({where}, base {self.base_height:.2f} m above "
                "the floor): the map is the task world seen from there." if self.best_valid else
                f"**No valid placement.** The arm stands at the largest share of reachable tasks ({where}).")
        src = f"`{Path(source).name}`, " if source else ""
        return (f"{src}{self.arm}: {self.n_valid} of {self.n_poses} base poses valid.\n\n{head}\n\n"
                "Floor squares: share of the tasks reachable with the base there (best yaw; yellow = all). "
                "Black outline: some yaw is valid there. Red cross and line: the best placement and its "
                "heading. Red dots: the tasks.")


def load_placements(path: str | Path) -> dict[str, Any]:
    """The arrays of a ``placements.npz`` written by ``redarm-placement``; :class:`InvalidInputError`
    naming the file if it cannot be read or lacks an array the view needs."""
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InvalidInputError(f"cannot read placements file {p}: {exc}", field="placement",
                                value=str(p)) from exc
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise InvalidInputError(f"{p} is not a redarm-placement result (missing {', '.join(missing)}; "
                                "re-run redarm-placement)", field="placement", value=str(p))
    nx, ny, nw = (int(v) for v in data["shape"])
    if (len(data["x"]), len(data["y"]), len(data["yaw"])) != (nx, ny, nw) or \
            data["fraction"].shape != (nx * ny * nw,) or data["valid"].shape != (nx * ny * nw,):
        raise InvalidInputError(f"{p}: grid arrays do not match shape {(nx, ny, nw)}", field="placement",
                                value=str(p))
    return data


def _step(axis: np.ndarray, other: np.ndarray) -> float:
    for a in (axis, other):
        if len(a) > 1:
            return float(a[1] - a[0])
    return 0.1  # a single base position: a 0.1 m square


def _to_view(points: np.ndarray, B_inv: np.ndarray) -> np.ndarray:
    return points @ B_inv[:3, :3].T + B_inv[:3, 3]


def placement_floor(data: dict[str, Any]) -> PlacementFloor:
    """The floor geometry of a placement result (``load_placements`` arrays; module doc)."""
    from matplotlib import colormaps

    gx, gy, gw = (np.asarray(data[k], dtype=float) for k in ("x", "y", "yaw"))
    nx, ny, nw = len(gx), len(gy), len(gw)
    h = float(data["base_height"])
    frac = np.asarray(data["fraction"], dtype=float).reshape(nx, ny, nw)
    valid = np.asarray(data["valid"], dtype=bool)
    ranking = np.asarray(data["ranking"], dtype=int)
    best_valid = len(ranking) > 0
    i_best = int(ranking[0]) if best_valid else int(np.argmax(data["fraction"]))
    ix, rest = divmod(i_best, ny * nw)
    iy, iw = divmod(rest, nw)
    best = (float(gx[ix]), float(gy[iy]), float(gw[iw]))
    B_inv = np.linalg.inv(base_transforms(np.array([best]), h)[0])
    z = FLOOR_LIFT  # world height of everything drawn on the floor

    dx, dy = _step(gx, gy), _step(gy, gx)
    best_frac = frac.max(axis=2)
    valid_xy = valid.reshape(nx, ny, nw).any(axis=2)
    IX, IY = np.nonzero(best_frac > 0.0)
    cx, cy = gx[IX], gy[IY]
    offs = np.array([[-dx, -dy], [dx, -dy], [dx, dy], [-dx, dy]]) / 2  # counter-clockwise from above
    world = np.zeros((len(IX), 4, 3))
    world[:, :, 0] = cx[:, None] + offs[:, 0]
    world[:, :, 1] = cy[:, None] + offs[:, 1]
    world[:, :, 2] = z
    shares = best_frac[IX, IY]
    colors = np.round(255 * colormaps["viridis"](shares)[:, :3]).astype(np.uint8)

    # Boundary of the valid cells: a side whose neighbour is outside the grid or not valid.
    pad = np.pad(valid_xy, 1)
    segs = []
    for (di, dj), (a, b) in (((-1, 0), (0, 3)), ((1, 0), (1, 2)), ((0, -1), (0, 1)), ((0, 1), (3, 2))):
        cells_i, cells_j = np.nonzero(valid_xy & ~pad[1 + di: 1 + di + nx, 1 + dj: 1 + dj + ny])
        for i, j in zip(cells_i, cells_j, strict=True):
            c = np.array([gx[i], gy[j]])
            segs.append([[*(c + offs[a]), z], [*(c + offs[b]), z]])
    outline = np.array(segs, dtype=float).reshape(-1, 2, 3)

    lo = np.array([gx[0] - dx / 2, gy[0] - dy / 2])
    hi = np.array([gx[-1] + dx / 2, gy[-1] + dy / 2])
    box = np.array([[lo[0], lo[1], z], [hi[0], lo[1], z], [hi[0], hi[1], z], [lo[0], hi[1], z]])
    extent = np.stack([box, np.roll(box, -1, axis=0)], axis=1)

    r = 0.5 * min(dx, dy)
    zv = z - h  # the floor in the view frame (the arm's base is at the origin)
    tip = [HEADING_M, 0, zv]
    best_mark = np.array([[[-r, 0, zv], [r, 0, zv]], [[0, -r, zv], [0, r, zv]],  # cross
                          [[0, 0, zv], tip], [tip, [HEADING_M - r / 2, r / 2, zv]]], dtype=float)  # heading
    tasks = np.asarray(data["tasks"], dtype=float).reshape(-1, 4, 4)[:, :3, 3]
    return PlacementFloor(
        corners=_to_view(world.reshape(-1, 3), B_inv).reshape(-1, 4, 3), fraction=shares, colors=colors,
        outline=_to_view(outline.reshape(-1, 3), B_inv).reshape(-1, 2, 3),
        extent=_to_view(extent.reshape(-1, 3), B_inv).reshape(-1, 2, 3), best_mark=best_mark,
        tasks=_to_view(tasks, B_inv), best=best, best_valid=best_valid, n_valid=int(valid.sum()),
        n_poses=int(valid.size), arm=str(data.get("arm", "")), base_height=h,
    )


def floor_meshes(floor: PlacementFloor) -> list[tuple[tuple[int, int, int], np.ndarray, np.ndarray]]:
    """The squares as one triangle mesh per colour: ``(rgb, vertices (4k, 3), faces (2k, 3))`` (a mesh
    has a single colour in the view; the shares take at most tasks + 1 values, so the meshes are few)."""
    out = []
    keys = [tuple(int(v) for v in c) for c in floor.colors]
    for rgb in sorted(set(keys)):
        sel = np.array([k == rgb for k in keys])
        verts = floor.corners[sel].reshape(-1, 3)
        base = 4 * np.arange(int(sel.sum()))[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.int32)
        out.append((rgb, verts, faces))
    return out
