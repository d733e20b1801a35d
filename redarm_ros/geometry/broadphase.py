"""Broad phase: cull obstacles by bounding spheres before the exact (scalar) distance computations.

Two levels, both conservative (an obstacle is dropped only if it provably cannot matter):

1. :meth:`SceneIndex.reach_scene` (once per scene): obstacles whose bounding sphere does not come
   within ``margin`` of the sphere the arm can sweep (around the shoulder, radius = the farthest key
   point plus the thickest capsule) can never touch the arm, and the hand can never need to pass
   above them. They are left out entirely.
2. :meth:`SceneIndex.local` (every control step, vectorised): of the remaining ones, only those whose
   bounding sphere comes within ``radius`` of one of the arm's capsule axes (at one or more joint
   configurations, e.g. the command and the reference) take part in that step's distances; the caller
   chooses ``radius`` to cover the range of every force plus the travel of the step and of a braking
   path. The heading dynamics looks farther ahead: :meth:`SceneIndex.ahead` keeps the obstacles within
   the distance to the target.

Obstacles keep their identity: :class:`LocalScene` maps its indices back to the full scene's, so
messages and ``StepResult.clearance_obstacle`` name the right one. Units: m.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from redarm_ros.geometry.obstacles import Box, Cylinder, Obstacle, Scene, Sphere

#: ``Clearance.obstacle`` of a clearance that is only a lower bound from obstacles left out.
LEFT_OUT = -2
#: Subsets kept per scene index (a step chooses among few: those near the arm now and soon).
SUBSET_CACHE = 16


def bounding_sphere(o: Obstacle) -> tuple[tuple[float, float, float], float]:
    """Centre (m) and radius (m) of a sphere that contains the shape."""
    if isinstance(o, Sphere):
        return o.center, o.radius
    if isinstance(o, Cylinder):
        return o.center, math.hypot(o.radius, 0.5 * o.height)
    assert isinstance(o, Box)
    h = o.half
    return o.center, math.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2])


def segments_point_distances(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distances (m), shape (S, N), from points ``p`` (N, 3) to each segment ``a[i]``-``b[i]``
    (``a``, ``b``: (S, 3)); a segment of zero length is its point."""
    ab = b - a
    ap = p[None, :, :] - a[:, None, :]
    den = np.einsum("ij,ij->i", ab, ab)
    t = np.einsum("snk,sk->sn", ap, ab) / np.where(den > 0.0, den, 1.0)[:, None]
    np.clip(t, 0.0, 1.0, out=t)
    d = ap - t[:, :, None] * ab[:, None, :]
    return np.sqrt(np.einsum("snk,snk->sn", d, d))


def segment_point_distances(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distances (m) from points ``p`` (N, 3) to the segment ``a``-``b`` (3-vectors)."""
    return segments_point_distances(np.asarray(a, float)[None], np.asarray(b, float)[None],
                                    np.asarray(p, float))[0]


@dataclass(frozen=True)
class LocalScene:
    """A subset of a scene: ``scene`` (same table) and ``index`` (its obstacles' indices in the full
    scene). ``floor`` (m) is a lower bound of the clearance of every obstacle left out (inf if none)."""

    scene: Scene
    index: tuple[int, ...]
    floor: float = math.inf

    def global_index(self, i: int) -> int:
        """Index in the full scene of local obstacle ``i`` (-1, the table, stays -1)."""
        return self.index[i] if 0 <= i < len(self.index) else i


class SceneIndex:
    """Bounding spheres of a scene's obstacles, for culling.

    ``centre`` (m, base frame) and ``reach`` (m): the sphere the arm can sweep (see the module
    docstring); ``margin`` (m) is added to it.
    """

    def __init__(self, scene: Scene, centre: Sequence[float], reach: float, margin: float) -> None:
        self.scene = scene
        n = len(scene.obstacles)
        self._c = np.zeros((n, 3))
        self._r = np.zeros(n)
        for i, o in enumerate(scene.obstacles):
            c, r = bounding_sphere(o)
            self._c[i] = c
            self._r[i] = r
        gap = np.linalg.norm(self._c - np.asarray(centre, float), axis=1) - self._r - reach if n \
            else np.zeros(0)
        keep = np.flatnonzero(gap <= margin)
        self._keep = keep
        self._reach = LocalScene(
            Scene(tuple(scene.obstacles[i] for i in keep), scene.table_height, scene.name),
            tuple(int(i) for i in keep),
            float(np.min(gap[gap > margin])) if np.any(gap > margin) else math.inf)
        self._kc = self._c[keep]
        self._kr = self._r[keep]
        # The last subsets built, by selection: from one step to the next the selection rarely
        # changes, and building a Scene costs more than the distances that chose it.
        self._subsets: dict[bytes, LocalScene] = {}

    @property
    def reach_scene(self) -> LocalScene:
        """The obstacles that can touch the arm at all (level 1)."""
        return self._reach

    @property
    def culled(self) -> int:
        """Number of obstacles left out for good (beyond the reach sphere plus the margin)."""
        return len(self.scene.obstacles) - len(self._keep)

    def _subset(self, sel: np.ndarray, gaps: np.ndarray) -> LocalScene:
        rs = self._reach
        rest = gaps[~sel]
        floor = min(rs.floor, float(np.min(rest))) if rest.size else rs.floor
        if rest.size == 0:
            return LocalScene(rs.scene, rs.index, floor)
        key = np.packbits(sel).tobytes()
        hit = self._subsets.get(key)
        if hit is None:
            idx = np.flatnonzero(sel)
            obs = rs.scene.obstacles
            hit = LocalScene(Scene(tuple(obs[i] for i in idx), rs.scene.table_height, rs.scene.name),
                             tuple(rs.index[i] for i in idx))
            if len(self._subsets) >= SUBSET_CACHE:
                self._subsets.pop(next(iter(self._subsets)))  # the oldest
            self._subsets[key] = hit
        return LocalScene(hit.scene, hit.index, floor)

    def local(self, key_point_sets: Sequence[np.ndarray], radii: Sequence[float],
              radius: float) -> LocalScene:
        """The obstacles whose bounding sphere comes within ``radius`` (m) of one of the capsules
        (``radii`` per link) of the arm at any of the given key-point sets ((5, 3) arrays, m)."""
        if self._kc.shape[0] == 0:
            return self._reach
        # Every link of every key-point set at once: segments a-b (S, 3), obstacle centres p (N, 3).
        kps = np.asarray(key_point_sets, float).reshape(-1, 5, 3)
        dist = segments_point_distances(kps[:, :4].reshape(-1, 3), kps[:, 1:].reshape(-1, 3), self._kc)
        dist -= np.tile(np.asarray(radii, float)[:4], len(kps))[:, None]
        gap = dist.min(axis=0) - self._kr
        return self._subset(gap <= radius, gap)

    def ahead(self, hand: Sequence[float], radius: float) -> LocalScene:
        """The obstacles whose bounding sphere comes within ``radius`` (m) of the hand point in the
        horizontal plane (the heading dynamics judges obstacles by their footprint)."""
        if self._kc.shape[0] == 0:
            return self._reach
        gap = np.linalg.norm(self._kc[:, :2] - np.asarray(hand, float)[:2], axis=1) - self._kr
        return self._subset(gap <= radius, gap)
