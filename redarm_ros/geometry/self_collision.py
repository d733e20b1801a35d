"""Self-collision and ground check of an arm posture, with the capsule model of the arm.

The arm is modelled by :class:`~redarm_ros.geometry.obstacles.ArmCapsules`: one capsule per link
between consecutive key points base - shoulder - elbow - wrist - tool, i.e. the links ``base`` (0),
``upper_arm`` (1), ``forearm`` (2), ``hand`` (3), with the radii of :class:`ArmCapsules`. For the
6-DOF PowerCube arm these are the paper's links L1, L23, L4 and L56 (Duguleana, mobile-base paper).

Two checks, both signed distances in m (negative = penetration depth):

* **link pairs**: the capsule distance ``|closest points of the two axes| - r_a - r_b`` of the pairs that
  can touch within the joint limits. Adjacent links share a key point and never count. Which of the
  non-adjacent pairs (base-forearm, base-hand, upper_arm-hand) can touch is a property of the arm: the
  arm YAML lists them under ``self_collision: pairs`` (the PowerCube paper's L1-L56 and L23-L56 for
  powercube6; derived by sampling for the 7-DOF arms, see docs/kinematics.md and :func:`pair_minima`);
  an arm without that entry checks every non-adjacent pair.
* **ground**: a horizontal plane ``z = ground_z`` (base frame) that no capsule of the ground links
  (``ArmCapsules.table_links``: every link but the base, which stands on it) may go below:
  ``min(z_a, z_b) - r - ground_z``. The arm YAML's ``self_collision: ground_z`` gives the plane
  (the table the 7-DOF arms stand on; the mobile robot's deck for powercube6), None = no plane.

:func:`self_collision` checks one posture (scalar maths, about 20 us), :func:`self_collision_batch`
many at once (numpy, for the IK filter). Both take the joint angles in rad; no ROS, numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.arm import ChainArm
from redarm_ros.geometry.obstacles import LINK_NAMES, ArmCapsules

__all__ = [
    "GROUND",
    "NON_ADJACENT_PAIRS",
    "CollisionModel",
    "SelfCollision",
    "SelfCollisionBatch",
    "collision_model",
    "self_collision",
    "self_collision_batch",
    "key_points_batch",
    "segment_distance",
    "segment_distance_batch",
    "pair_minima",
]

#: Name used for the ground plane in :attr:`SelfCollision.pair`.
GROUND = "ground"
#: Every pair of capsules that do not share a key point (indices into LINK_NAMES).
NON_ADJACENT_PAIRS: tuple[tuple[int, int], ...] = ((0, 2), (0, 3), (1, 3))

ArmGround = float | None | Literal["arm"]


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CollisionModel:
    """What is checked for one arm.

    ``pairs``: link index pairs (into ``LINK_NAMES``) checked against each other; ``ground_z``: z (m,
    base frame) of the ground plane, or None for none; ``capsules``: the radii (m) and the links checked
    against the ground (``capsules.table_links``).
    """

    pairs: tuple[tuple[int, int], ...]
    ground_z: float | None
    capsules: ArmCapsules

    @property
    def ground_links(self) -> tuple[int, ...]:
        """Links checked against the ground plane (none if there is no plane)."""
        return tuple(self.capsules.table_links) if self.ground_z is not None else ()


def _link_index(v: Any, where: str) -> int:
    if isinstance(v, str) and v in LINK_NAMES:
        return LINK_NAMES.index(v)
    if isinstance(v, int) and not isinstance(v, bool) and 0 <= v < len(LINK_NAMES):
        return v
    raise ConfigError(
        f"{where}: link {v!r} is not one of {', '.join(LINK_NAMES)} (or an index 0..3)",
        field="self_collision.pairs",
        value=v,
    )


def parse_pairs(raw: Any, where: str = "self_collision.pairs") -> tuple[tuple[int, int], ...]:
    """Link pairs from YAML (``[[base, hand], [upper_arm, hand]]``, names or indices), sorted, unique.

    Raises :class:`ConfigError` for an unknown link, a pair that is not two links, or adjacent links
    (they share a key point: their capsules always touch).
    """
    if not isinstance(raw, (list, tuple)):
        raise ConfigError(f"{where} must be a list of link pairs, got {raw!r}", field=where, value=raw)
    out: set[tuple[int, int]] = set()
    for item in raw:
        if not isinstance(item, (list, tuple)) or len(item) != 2:
            raise ConfigError(f"{where}: {item!r} is not a pair of links", field=where, value=item)
        a, b = sorted((_link_index(item[0], where), _link_index(item[1], where)))
        if b - a < 2:
            raise ConfigError(
                f"{where}: {LINK_NAMES[a]} and {LINK_NAMES[b]} are adjacent (they share a key point)",
                field=where,
                value=item,
            )
        out.add((a, b))
    return tuple(sorted(out))


def collision_model(
    arm: ChainArm, capsules: ArmCapsules | None = None, ground_z: ArmGround = "arm"
) -> CollisionModel:
    """The collision model of ``arm``: its YAML ``self_collision`` entry with the radii of ``capsules``.

    ``capsules`` (default: :class:`ArmCapsules` at the table's defaults); ``ground_z``: "arm" = the arm's
    configured plane (``self_collision: ground_z``, none if absent), a number (m) = that plane, None = no
    ground check. Raises :class:`ConfigError` for a malformed ``self_collision`` entry.
    """
    cfg = getattr(arm, "config", {}).get("self_collision") or {}
    if not isinstance(cfg, dict):
        raise ConfigError(f"arm {arm.name!r}: self_collision must be a mapping", field="self_collision")
    unknown = set(cfg) - {"pairs", "ground_z"}
    if unknown:
        raise ConfigError(
            f"arm {arm.name!r}: unknown self_collision field(s) {sorted(unknown)} (pairs, ground_z)",
            field="self_collision",
        )
    pairs = parse_pairs(cfg["pairs"]) if "pairs" in cfg else NON_ADJACENT_PAIRS
    if isinstance(ground_z, str):
        if ground_z != "arm":
            raise InvalidInputError(f"ground_z must be a number, None or 'arm', got {ground_z!r}",
                                    field="ground_z", value=ground_z)
        gz = cfg.get("ground_z")
    else:
        gz = ground_z
    if gz is not None:
        try:
            gz = float(gz)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"ground_z must be a number (m), got {gz!r}", field="ground_z",
                                    value=gz) from exc
        if not math.isfinite(gz):
            raise InvalidInputError(f"ground_z must be finite, got {gz!r}", field="ground_z", value=gz)
    return CollisionModel(pairs, gz, capsules or ArmCapsules())


# ----------------------------------------------------------------------------------------------
# Distances
# ----------------------------------------------------------------------------------------------
def segment_distance(
    a0: Sequence[float], a1: Sequence[float], b0: Sequence[float], b1: Sequence[float]
) -> float:
    """Distance (m) between the segments a0-a1 and b0-b1 (exact; scalar maths).

    Minimises |a0 + s d1 - b0 - t d2| over s, t in [0, 1]: the unconstrained s (or s = 0 for parallel
    segments) clamped, the t of that s clamped, then the s of that t clamped again; for two segments this
    reaches the constrained minimum because the squared distance is convex in (s, t).
    """
    d1x, d1y, d1z = a1[0] - a0[0], a1[1] - a0[1], a1[2] - a0[2]
    d2x, d2y, d2z = b1[0] - b0[0], b1[1] - b0[1], b1[2] - b0[2]
    rx, ry, rz = a0[0] - b0[0], a0[1] - b0[1], a0[2] - b0[2]
    aa = d1x * d1x + d1y * d1y + d1z * d1z
    ee = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    if aa <= 1e-24 and ee <= 1e-24:
        s = t = 0.0
    elif aa <= 1e-24:
        s, t = 0.0, min(max(f / ee, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if ee <= 1e-24:
            t, s = 0.0, min(max(-c / aa, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            den = aa * ee - b * b
            s = min(max((b * f - c * ee) / den, 0.0), 1.0) if den > 1e-12 * aa * ee else 0.0
            t = (b * s + f) / ee
            if t < 0.0:
                t, s = 0.0, min(max(-c / aa, 0.0), 1.0)
            elif t > 1.0:
                t, s = 1.0, min(max((b - c) / aa, 0.0), 1.0)
    dx = rx + s * d1x - t * d2x
    dy = ry + s * d1y - t * d2y
    dz = rz + s * d1z - t * d2z
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def segment_distance_batch(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Distances (m) between m pairs of segments: arrays (m, 3) -> (m,); the algorithm of
    :func:`segment_distance`, vectorised."""
    d1 = a1 - a0
    d2 = b1 - b0
    r = a0 - b0
    aa = np.einsum("ij,ij->i", d1, d1)
    ee = np.einsum("ij,ij->i", d2, d2)
    b = np.einsum("ij,ij->i", d1, d2)
    c = np.einsum("ij,ij->i", d1, r)
    f = np.einsum("ij,ij->i", d2, r)
    tiny = 1e-24
    a_ok = aa > tiny
    e_ok = ee > tiny
    aa_s = np.where(a_ok, aa, 1.0)
    ee_s = np.where(e_ok, ee, 1.0)
    den = aa * ee - b * b
    general = a_ok & e_ok
    s = np.where(general & (den > 1e-12 * aa * ee), np.clip((b * f - c * ee) / np.where(den > 0, den, 1.0),
                                                            0.0, 1.0), 0.0)
    t = np.where(e_ok, (b * s + f) / ee_s, 0.0)
    lo = general & (t < 0.0)
    hi = general & (t > 1.0)
    s = np.where(lo, np.clip(-c / aa_s, 0.0, 1.0), s)
    s = np.where(hi, np.clip((b - c) / aa_s, 0.0, 1.0), s)
    t = np.clip(t, 0.0, 1.0)
    # degenerate segments (points)
    only_b = ~a_ok & e_ok
    s = np.where(only_b, 0.0, s)
    t = np.where(only_b, np.clip(f / ee_s, 0.0, 1.0), t)
    only_a = a_ok & ~e_ok
    s = np.where(only_a, np.clip(-c / aa_s, 0.0, 1.0), s)
    t = np.where(only_a, 0.0, t)
    none = ~a_ok & ~e_ok
    s = np.where(none, 0.0, s)
    t = np.where(none, 0.0, t)
    d = r + s[:, None] * d1 - t[:, None] * d2
    return np.sqrt(np.einsum("ij,ij->i", d, d))


# ----------------------------------------------------------------------------------------------
# One posture
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SelfCollision:
    """Result of :func:`self_collision` (distances in m, signed: negative = penetration depth).

    ``min_distance``: the smaller of ``self_distance`` and ``ground_distance`` (inf if nothing was
    checked); ``pair``: the closest pair as names, e.g. ``("upper_arm", "hand")`` or
    ``("forearm", "ground")`` (empty if nothing was checked); ``self_distance`` and ``self_pair`` (link
    indices) of the closest checked link pair; ``ground_distance`` and ``ground_link`` of the lowest
    ground link (-1 / inf without a plane).
    """

    min_distance: float
    pair: tuple[str, ...]
    self_distance: float
    self_pair: tuple[int, int] | None
    ground_distance: float
    ground_link: int

    @property
    def colliding(self) -> bool:
        """True if two checked links or a link and the ground overlap (``min_distance < 0``)."""
        return self.min_distance < 0.0

    def describe(self) -> str:
        """One line for messages, e.g. ``upper_arm-hand capsules overlap by 0.012 m``."""
        if not self.pair:
            return "nothing to check"
        if self.min_distance >= 0.0:
            return f"{'-'.join(self.pair)} clearance {self.min_distance:.3f} m"
        if self.pair[1] == GROUND:
            return f"{self.pair[0]} is {-self.min_distance:.3f} m below the ground plane"
        return f"{self.pair[0]}-{self.pair[1]} capsules overlap by {-self.min_distance:.3f} m"


def _key_points(arm: ChainArm, q: Any) -> list[list[float]]:
    """The 5 key points (base, shoulder, elbow, wrist, tool) as lists (m), from the scalar FK path."""
    p, origins, _ = arm.fk_axes(q)
    k1, k2, k3 = arm.key_joints
    return [[0.0, 0.0, 0.0], origins[k1].tolist(), origins[k2].tolist(), origins[k3].tolist(), p.tolist()]


def self_collision(
    arm: ChainArm,
    q: Sequence[float],
    capsules: ArmCapsules | None = None,
    ground_z: ArmGround = "arm",
    *,
    model: CollisionModel | None = None,
) -> SelfCollision:
    """Self-collision and ground clearance of ``arm`` at joint angles ``q`` (rad, (n,)).

    ``capsules``: radii (m; default :class:`ArmCapsules`); ``ground_z``: "arm" (the arm's configured plane),
    a z in m (base frame), or None (no ground); ``model`` (from :func:`collision_model`) overrides both
    and saves re-reading the configuration in a loop. Raises :class:`InvalidInputError` for a malformed q.
    """
    m = model or collision_model(arm, capsules, ground_z)
    pts = _key_points(arm, q)
    radii = m.capsules.radii
    best_self, best_pair = math.inf, None
    for i, j in m.pairs:
        d = segment_distance(pts[i], pts[i + 1], pts[j], pts[j + 1]) - radii[i] - radii[j]
        if d < best_self:
            best_self, best_pair = d, (i, j)
    best_ground, ground_link = math.inf, -1
    if m.ground_z is not None:
        for i in m.ground_links:
            d = min(pts[i][2], pts[i + 1][2]) - radii[i] - m.ground_z
            if d < best_ground:
                best_ground, ground_link = d, i
    if best_pair is None and ground_link < 0:
        return SelfCollision(math.inf, (), math.inf, None, math.inf, -1)
    if best_ground < best_self:
        pair: tuple[str, ...] = (LINK_NAMES[ground_link], GROUND)
    else:
        assert best_pair is not None
        pair = (LINK_NAMES[best_pair[0]], LINK_NAMES[best_pair[1]])
    return SelfCollision(min(best_self, best_ground), pair, best_self, best_pair, best_ground, ground_link)


# ----------------------------------------------------------------------------------------------
# Many postures
# ----------------------------------------------------------------------------------------------
def _rot_batch(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(m, 3, 3) rotations by ``angles`` (rad) about the unit ``axis`` (Rodrigues)."""
    x, y, z = (float(v) for v in axis)
    c, s = np.cos(angles), np.sin(angles)
    C = 1.0 - c
    R = np.empty(angles.shape + (3, 3))
    R[:, 0, 0] = c + x * x * C
    R[:, 0, 1] = x * y * C - z * s
    R[:, 0, 2] = x * z * C + y * s
    R[:, 1, 0] = y * x * C + z * s
    R[:, 1, 1] = c + y * y * C
    R[:, 1, 2] = y * z * C - x * s
    R[:, 2, 0] = z * x * C - y * s
    R[:, 2, 1] = z * y * C + x * s
    R[:, 2, 2] = c + z * z * C
    return R


def key_points_batch(arm: ChainArm, Q: Any) -> np.ndarray:
    """(m, 5, 3) key points (m) base, shoulder, elbow, wrist, tool for joint vectors Q (m, n) in rad.

    The chain of ``arm.chain`` (joint origins and axes) evaluated for all rows at once; equal to
    ``arm.key_points(q)`` row by row. Raises :class:`InvalidInputError` for a wrong shape or NaN/inf.
    """
    Qa = np.asarray(Q, dtype=float)
    if Qa.ndim != 2 or Qa.shape[1] != arm.n:
        raise InvalidInputError(f"Q must have shape (m, {arm.n}), got {Qa.shape}", field="Q")
    if not np.all(np.isfinite(Qa)):
        raise InvalidInputError("Q contains NaN or inf", field="Q")
    m = Qa.shape[0]
    R = np.broadcast_to(np.eye(3), (m, 3, 3))
    p = np.zeros((m, 3))
    origins = np.empty((m, arm.n, 3))
    for i, j in enumerate(arm.chain):
        Ro, po = j.origin[:3, :3], j.origin[:3, 3]
        if np.any(po):
            p = p + R @ po
        if not np.array_equal(Ro, np.eye(3)):
            R = R @ Ro
        origins[:, i] = p
        R = R @ _rot_batch(j.axis, Qa[:, i])
    tool = p + R @ arm.tool[:3, 3]
    out = np.zeros((m, 5, 3))
    out[:, 1:4] = origins[:, list(arm.key_joints)]
    out[:, 4] = tool
    return out


@dataclass(frozen=True)
class SelfCollisionBatch:
    """Result of :func:`self_collision_batch` for m postures (arrays of shape (m,), m).

    ``min_distance``, ``self_distance``, ``ground_distance`` as in :class:`SelfCollision` (inf where
    nothing was checked); ``closest``: index into ``checks`` of the closest check per row (-1 if none);
    ``checks``: the checks in column order, link pairs ``(i, j)`` then ``(i, -1)`` for link i against
    the ground.
    """

    min_distance: np.ndarray
    self_distance: np.ndarray
    ground_distance: np.ndarray
    closest: np.ndarray
    checks: tuple[tuple[int, int], ...]

    @property
    def colliding(self) -> np.ndarray:
        """(m,) bool: ``min_distance < 0``."""
        return self.min_distance < 0.0

    @property
    def free(self) -> np.ndarray:
        """(m,) bool: no overlap (``min_distance >= 0``)."""
        return self.min_distance >= 0.0


def self_collision_batch(
    arm: ChainArm,
    Q: Any,
    capsules: ArmCapsules | None = None,
    ground_z: ArmGround = "arm",
    *,
    model: CollisionModel | None = None,
) -> SelfCollisionBatch:
    """:func:`self_collision` for many postures Q (m, n) rad at once (numpy; arguments as there)."""
    md = model or collision_model(arm, capsules, ground_z)
    P = key_points_batch(arm, Q)
    m = P.shape[0]
    radii = md.capsules.radii
    cols: list[np.ndarray] = []
    checks: list[tuple[int, int]] = []
    for i, j in md.pairs:
        d = segment_distance_batch(P[:, i], P[:, i + 1], P[:, j], P[:, j + 1]) - radii[i] - radii[j]
        cols.append(d)
        checks.append((i, j))
    n_self = len(cols)
    if md.ground_z is not None:
        for i in md.ground_links:
            cols.append(np.minimum(P[:, i, 2], P[:, i + 1, 2]) - radii[i] - md.ground_z)
            checks.append((i, -1))
    if not cols:
        inf = np.full(m, math.inf)
        return SelfCollisionBatch(inf, inf.copy(), inf.copy(), np.full(m, -1), ())
    D = np.stack(cols, axis=1)
    closest = np.argmin(D, axis=1)
    mind = D[np.arange(m), closest]
    selfd = D[:, :n_self].min(axis=1) if n_self else np.full(m, math.inf)
    groundd = D[:, n_self:].min(axis=1) if len(cols) > n_self else np.full(m, math.inf)
    return SelfCollisionBatch(mind, selfd, groundd, closest, tuple(checks))


# ----------------------------------------------------------------------------------------------
# Which pairs can touch (the derivation behind the YAML lists)
# ----------------------------------------------------------------------------------------------
def pair_minima(
    arm: ChainArm,
    capsules: ArmCapsules | None = None,
    pairs: Iterable[tuple[int, int]] = NON_ADJACENT_PAIRS,
    *,
    samples: int = 200_000,
    refine: int = 40,
    rng_seed: int = 0,
) -> dict[tuple[int, int], tuple[float, np.ndarray]]:
    """Smallest capsule distance (m) of each link pair over the joint limits, and a posture reaching it.

    Uniform samples inside the limits (``samples``, in chunks), then ``refine`` rounds of a shrinking
    random local search from the best 16 samples of each pair (clipped to the limits). A pair whose
    minimum stays positive cannot touch within the limits; the search finds an upper bound of the true
    minimum, so a positive result is the claim to check (the docs give the margins). Fixed seed.
    """
    caps = capsules or ArmCapsules()
    rng = np.random.default_rng(rng_seed)
    lo, up = np.asarray(arm.lower, float), np.asarray(arm.upper, float)
    prs = [tuple(p) for p in pairs]
    radii = caps.radii

    def dist(Qs: np.ndarray, pr: tuple[int, int]) -> np.ndarray:
        P = key_points_batch(arm, Qs)
        i, j = pr
        return segment_distance_batch(P[:, i], P[:, i + 1], P[:, j], P[:, j + 1]) - radii[i] - radii[j]

    best: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    chunk = 20_000
    done = 0
    while done < samples:
        k = min(chunk, samples - done)
        Qs = rng.uniform(lo, up, (k, arm.n))
        for pr in prs:
            d = dist(Qs, pr)
            if pr in best:
                d = np.concatenate([best[pr][0], d])
                Qs_all = np.concatenate([best[pr][1], Qs])
            else:
                Qs_all = Qs
            idx = np.argsort(d)[:16]
            best[pr] = (d[idx], Qs_all[idx])
        done += k
    out: dict[tuple[int, int], tuple[float, np.ndarray]] = {}
    span = up - lo
    for pr in prs:
        d, Qb = best[pr]
        step = 0.1 * span
        for _ in range(refine):
            cand = np.clip(Qb[:, None, :] + rng.normal(size=(len(Qb), 32, arm.n)) * step, lo, up)
            cand = cand.reshape(-1, arm.n)
            dc = dist(cand, pr).reshape(len(Qb), 32)
            k = np.argmin(dc, axis=1)
            better = dc[np.arange(len(Qb)), k] < d
            Qb = np.where(better[:, None], cand.reshape(len(Qb), 32, arm.n)[np.arange(len(Qb)), k], Qb)
            d = np.where(better, dc[np.arange(len(Qb)), k], d)
            step = step * 0.85
        i = int(np.argmin(d))
        out[pr] = (float(d[i]), Qb[i].copy())
    return out
