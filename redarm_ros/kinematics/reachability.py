"""Capability map of a swivel arm (Zacharias et al. 2007, "Capturing robot workspace structure"), exact.

For every voxel centre p of a grid around the shoulder and every tool orientation R of a fixed,
near-uniform set, the pose (R, p) is solved in closed form: its feasible swivel set (the swivels with
an in-limit solution, union over the 8 flip patterns, see :mod:`.feasible`) is computed exactly, not
sampled. Per voxel the map holds

* ``fraction``: the fraction of the orientations reachable within the joint limits (0..1), and
* ``width``: the mean measure (rad, 0..2 pi) of the feasible swivel set over the reachable
  orientations: how much room the elbow has there (0 where nothing is reachable).

Run ``python -m redarm_ros.kinematics.reachability --arm pa10`` (a 0.1 m grid and 32 orientations:
well under a minute); ``--step 0.05 --orientations 128`` for a finer map. Writes
``<out>/<arm>_reachability.npz`` (arrays ``x``, ``y``, ``z`` (m), ``fraction``, ``width`` (rad) indexed
[ix, iy, iz], ``orientations`` (K, 3, 3), ``step``, ``arm``) and ``<out>/<arm>_reachability.png``: the
vertical slice through the base axis (y = 0) of both maps. Units: m, rad.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.feasible import feasible_measure_batch
from redarm_ros.kinematics.loader import load_arm
from redarm_ros.kinematics.protocols import has_swivel
from redarm_ros.kinematics.swivel import SwivelArm
from redarm_ros.parallel import ENGINES, map_chunks

__all__ = [
    "CapabilityMap", "orientation_set", "feasible_measure_poses", "capability_map", "save_map", "main"
]

_log = logging.getLogger(__name__)


@dataclass
class CapabilityMap:
    """Voxel grid (centres ``x``, ``y``, ``z`` in m) with ``fraction`` and ``width`` (rad) per voxel."""

    arm: str
    step: float
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    fraction: np.ndarray
    width: np.ndarray
    orientations: np.ndarray


def orientation_set(k: int) -> np.ndarray:
    """k near-uniform rotations (k, 3, 3): a Fibonacci sphere of approach (tool z) directions, each with
    a roll about it from a golden-ratio sequence (deterministic, no random numbers)."""
    if k < 1:
        raise InvalidInputError(f"orientations must be >= 1, got {k}", field="orientations", value=k)
    i = np.arange(k) + 0.5
    zc = 1.0 - 2.0 * i / k
    rho = np.sqrt(np.maximum(0.0, 1.0 - zc * zc))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    a = np.stack([rho * np.cos(phi), rho * np.sin(phi), zc], axis=1)  # tool z
    # any unit vector orthogonal to a, then turned about a by the roll
    ref = np.where(np.abs(a[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(ref, a)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(a, u)
    roll = (i * 0.6180339887498949 % 1.0) * 2.0 * math.pi
    bx = np.cos(roll)[:, None] * u + np.sin(roll)[:, None] * v  # tool x
    by = np.cross(a, bx)
    return np.stack([bx, by, a], axis=2)


def feasible_measure_poses(arm: SwivelArm, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For (k, 4, 4) poses (base frame, m): the measure (rad, 0..2 pi) of each pose's feasible swivel
    set, union over the 8 flip patterns, and whether it has any in-limit solution (k,) bool.

    Exact (the closed-form interval ends of :mod:`.feasible`), batched; a pose out of reach has
    measure 0 and no solution. No input checks: the caller passes finite homogeneous poses.
    """
    Pn = [[T[:, i, j] for j in range(4)] for i in range(3)]
    Kc, t4, dsh, dwr, ok = arm._functions_np(Pn)  # noqa: SLF001
    width = np.zeros(len(T))
    anyok = np.zeros(len(T), bool)
    r = np.nonzero(ok)[0]
    if len(r):
        tab = arm._interval_tables  # noqa: SLF001 - the arm's limit tables (those of feasible_swivels)
        with np.errstate(invalid="ignore"):
            width[r], anyok[r] = feasible_measure_batch(Kc[r], t4[r], dsh[r], dwr[r], tab)
    return width, anyok


def _voxel_chunk(arm: SwivelArm, Rs: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(fraction, summed width) of the voxel centres P (k, 3) (base frame, m) over the orientations Rs:
    one unit of work (module-level, so worker processes import it by name)."""
    K = len(Rs)
    T = np.zeros((len(P), K, 4, 4))
    T[:, :, :3, :3] = Rs[None]
    T[:, :, :3, 3] = P[:, None, :]
    T[:, :, 3, 3] = 1.0
    width, anyok = feasible_measure_poses(arm, T.reshape(-1, 4, 4))
    return anyok.reshape(len(P), K).mean(axis=1), width.reshape(len(P), K).sum(axis=1)


def capability_map(
    arm: SwivelArm, step: float = 0.1, orientations: int = 32, chunk: int = 4096, *,
    engine: str = "local", workers: int | None = 1, address: str | None = None,
    progress: TextIO | None = None,
) -> CapabilityMap:
    """The capability map of ``arm`` on a grid of ``step`` m around the shoulder (see the module doc).

    ``chunk`` poses (voxels x orientations) make one unit of work; ``engine``, ``workers``, ``address``
    choose where the units run (:func:`redarm_ros.parallel.map_chunks`: in this process by default, in
    local worker processes, or on a Dask cluster); the map is the same bit for bit on every engine.
    """
    if not has_swivel(arm):
        raise InvalidInputError(
            f"arm {arm.name!r} has no swivel parameterisation", field="arm", value=arm.name
        )
    if not (0.005 <= step <= 1.0):
        raise InvalidInputError(f"step must lie in [0.005, 1] m, got {step}", field="step", value=step)
    L1, L2, L3, L4 = arm.link_lengths
    reach = L2 + L3 + L4
    n = int(math.ceil(reach / step))
    ax = (np.arange(-n, n + 1)) * step
    x, y, z = ax, ax, ax + L1
    Rs = orientation_set(orientations)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel() - L1], axis=1)
    inside = np.linalg.norm(P, axis=1) <= reach + 1e-9  # the tool cannot leave this sphere
    frac = np.zeros(P.shape[0])
    wsum = np.zeros(P.shape[0])
    pts = np.nonzero(inside)[0]
    per = max(1, chunk // len(Rs))
    parts = [pts[k0 : k0 + per] for k0 in range(0, len(pts), per)]
    done = map_chunks(_voxel_chunk, [P[idx] + (0.0, 0.0, L1) for idx in parts], args=(arm, Rs),
                      engine=engine, workers=workers, address=address, progress=progress, label="voxels")
    for idx, (f, w) in zip(parts, done, strict=True):
        frac[idx], wsum[idx] = f, w
    cnt = frac * len(Rs)
    mean_w = np.where(cnt > 0, wsum / np.maximum(cnt, 1), 0.0)
    shape = (len(x), len(y), len(z))
    return CapabilityMap(arm.name, step, x, y, z, frac.reshape(shape), mean_w.reshape(shape), Rs)


def save_map(cmap: CapabilityMap, out_dir: Path) -> tuple[Path, Path]:
    """Write ``<arm>_reachability.npz`` and the y = 0 slice ``<arm>_reachability.png`` into out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    npz = out_dir / f"{cmap.arm}_reachability.npz"
    np.savez_compressed(
        npz,
        x=cmap.x,
        y=cmap.y,
        z=cmap.z,
        fraction=cmap.fraction,
        width=cmap.width,
        orientations=cmap.orientations,
        step=cmap.step,
        arm=cmap.arm,
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    iy = int(np.argmin(np.abs(cmap.y)))
    ext = (
        cmap.x[0] - cmap.step / 2,
        cmap.x[-1] + cmap.step / 2,
        cmap.z[0] - cmap.step / 2,
        cmap.z[-1] + cmap.step / 2,
    )
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.8), constrained_layout=True)
    for axp, data, title, vmax, unit in (
        (axs[0], cmap.fraction[:, iy, :], "reachable orientations", 1.0, "fraction"),
        (axs[1], cmap.width[:, iy, :], "mean feasible swivel width", 2 * math.pi, "rad"),
    ):
        im = axp.imshow(data.T, origin="lower", extent=ext, vmin=0.0, vmax=vmax, cmap="viridis")
        axp.set_title(f"{cmap.arm}: {title} (y = {cmap.y[iy]:.2f} m)")
        axp.set_xlabel("x (m)")
        axp.set_ylabel("z (m)")
        fig.colorbar(im, ax=axp, label=unit)
    png = out_dir / f"{cmap.arm}_reachability.png"
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return npz, png


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: compute and write the capability map of one arm."""
    ap = argparse.ArgumentParser(
        prog="python -m redarm_ros.kinematics.reachability", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--arm", default="pa10", help="arm name (config/arms/<name>.yaml) or YAML path")
    ap.add_argument("--step", type=float, default=0.1, help="voxel size in m (default 0.1)")
    ap.add_argument("--orientations", type=int, default=32, help="tool orientations per voxel (default 32)")
    ap.add_argument("--out", type=Path, default=Path("reachability_output"), help="output directory")
    ap.add_argument("--engine", choices=ENGINES, default="local", help="where the work runs (default local)")
    ap.add_argument("--workers", type=int, default=1, help="local worker processes (default 1: this process)")
    ap.add_argument("--address", default=None, help="Dask scheduler address, tcp://host:port")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        arm = load_arm(args.arm)
        t0 = time.perf_counter()
        cmap = capability_map(arm, args.step, args.orientations, engine=args.engine, workers=args.workers,
                              address=args.address, progress=sys.stderr if sys.stderr.isatty() else None)
    except InvalidInputError as exc:
        _log.error("reachability: %s", exc)
        return 2
    npz, png = save_map(cmap, args.out)
    n_vox = int(np.count_nonzero(cmap.fraction > 0))
    _log.info(
        "%s: %d voxels of %.3g m, %d orientations, %d voxels reachable, best fraction %.2f, "
        "in %.1f s: %s, %s",
        cmap.arm,
        cmap.fraction.size,
        cmap.step,
        len(cmap.orientations),
        n_vox,
        float(cmap.fraction.max()),
        time.perf_counter() - t0,
        npz,
        png,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
