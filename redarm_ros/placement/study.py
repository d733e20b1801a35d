"""The placement study: every base pose of the grid scored for the task set, and the ranking.

``place(problem)`` splits the grid into chunks of ``CHUNK`` base poses (a fixed size, so results do not
depend on the engine or the worker count), evaluates them on the chosen engine
(:mod:`redarm_ros.parallel`) and assembles a :class:`PlacementResult`.

Ranking: only **valid** base poses take part: footprint clear, every task reachable in the limits with
a collision-free solution. They are ordered by robustness (the narrowest feasible swivel set over the
tasks, rad, larger first; arms without a swivel skip this key), then by the worst joint-limit margin
(rad, larger first), then by grid index; scores are compared to 1e-9 rad, so float noise in equal
scores never reorders them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np

from redarm_ros.parallel import map_chunks
from redarm_ros.placement.evaluate import ChunkResult, evaluate_rows
from redarm_ros.placement.problem import PlacementProblem

__all__ = ["CHUNK", "PlacementResult", "place"]

CHUNK = 64  # base poses per unit of work
RANK_DECIMALS = 9  # scores equal to 1e-9 rad tie, and the grid index decides


@dataclass(frozen=True)
class PlacementResult:
    """Per base pose (N = grid size) and task (m) scores; see :class:`~.evaluate.ChunkResult`."""

    problem: PlacementProblem
    poses: np.ndarray  # (N, 3) x, y (m), yaw (rad)
    possible: np.ndarray  # (N, m)
    reach: np.ndarray  # (N, m)
    width: np.ndarray  # (N, m) rad
    footprint_ok: np.ndarray  # (N,)
    checked: np.ndarray  # (N,)
    free: np.ndarray  # (N, m)
    margin: np.ndarray  # (N, m) rad

    @property
    def valid(self) -> np.ndarray:
        """(N,) footprint clear and every task reachable, in the limits and collision-free."""
        return self.checked & self.free.all(axis=1)

    @property
    def fraction(self) -> np.ndarray:
        """(N,) share of the tasks reachable in the limits (collisions not counted)."""
        return self.reach.mean(axis=1)

    @property
    def robustness(self) -> np.ndarray:
        """(N,) narrowest feasible swivel set over the tasks (rad); NaN where not valid or no swivel."""
        with np.errstate(invalid="ignore"):
            w = np.where(self.reach.all(axis=1), self.width.min(axis=1), np.nan)
        return np.where(self.valid, w, np.nan)

    @property
    def worst_margin(self) -> np.ndarray:
        """(N,) smallest joint-limit margin over the tasks' chosen solutions (rad); NaN where not valid."""
        m = np.where(self.valid[:, None], self.margin, np.inf).min(axis=1)
        return np.where(self.valid, m, np.nan)

    @property
    def pruned_share(self) -> float:
        """Share of the base poses that inverse reachability ruled out (some task impossible there)."""
        return float(1.0 - self.possible.all(axis=1).mean())

    def ranking(self) -> np.ndarray:
        """Indices of the valid base poses, best first (module doc)."""
        idx = np.nonzero(self.valid)[0]
        # rounded to RANK_DECIMALS, so float noise between equal scores never reorders them
        rob = np.round(np.nan_to_num(self.robustness[idx], nan=0.0), RANK_DECIMALS)
        mar = np.round(self.worst_margin[idx], RANK_DECIMALS)
        order = np.lexsort((idx, -mar, -rob))  # lexsort: last key is the primary one
        return idx[order]

    def index_of(self, x: float, y: float, yaw: float, tol: float = 1e-6) -> int | None:
        """Grid index of the base pose (x, y in m, yaw in rad, any turn), None if it is not on the grid."""
        d_yaw = np.angle(np.exp(1j * (self.poses[:, 2] - yaw)))
        hit = np.nonzero((np.abs(self.poses[:, 0] - x) <= tol) & (np.abs(self.poses[:, 1] - y) <= tol)
                         & (np.abs(d_yaw) <= tol))[0]
        return int(hit[0]) if len(hit) else None

    def summary(self, top: int = 5) -> dict[str, Any]:
        """Plain-data digest (YAML/JSON-ready): arm, counts and the ``top`` best placements (m, deg, rad)."""
        best = []
        for i in self.ranking()[:top]:
            x, y, w = (float(v) for v in self.poses[i])
            rob = float(self.robustness[i])
            best.append({"x": round(x, 6), "y": round(y, 6), "yaw_deg": round(math.degrees(w), 6),
                         "robustness_rad": None if math.isnan(rob) else round(rob, 6),
                         "worst_margin_rad": round(float(self.worst_margin[i]), 6)})
        return {"arm": self.problem.arm, "base_height": float(self.problem.base_height),
                "base_poses": int(len(self.poses)), "tasks": int(len(self.problem.tasks)),
                "valid": int(self.valid.sum()), "best": best}


# Units of work: module-level functions, so worker processes can import them by name.
def _evaluate_pruned(problem: PlacementProblem, rows: np.ndarray) -> ChunkResult:
    return evaluate_rows(problem, rows, prune=True)


def _evaluate_all(problem: PlacementProblem, rows: np.ndarray) -> ChunkResult:
    return evaluate_rows(problem, rows, prune=False)


def place(problem: PlacementProblem, *, engine: str = "local", workers: int | None = 1,
          address: str | None = None, prune: bool = True, progress: TextIO | None = None,
          chunk: int = CHUNK) -> PlacementResult:
    """Score every base pose of ``problem.grid`` for the task set (module doc).

    ``engine``/``workers``/``address``: see :func:`redarm_ros.parallel.map_chunks`; ``prune=False``
    checks every pair exactly (no inverse reachability); ``progress``: a stream for the progress bar
    (None: quiet).
    """
    N = problem.grid.size
    chunks = [np.arange(a, min(a + chunk, N)) for a in range(0, N, chunk)]
    fn = _evaluate_pruned if prune else _evaluate_all
    parts: list[ChunkResult] = map_chunks(fn, chunks, args=(problem,), engine=engine, workers=workers,
                                          address=address, progress=progress, label="placement")

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])

    return PlacementResult(problem, problem.grid.poses(), cat("possible"), cat("reach"), cat("width"),
                           cat("footprint_ok"), cat("checked"), cat("free"), cat("margin"))
