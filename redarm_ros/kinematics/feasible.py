"""Closed-form joint functions along the self-motion circle: the feasible swivel set and the nearest solution.

For a fixed tool pose the arm's self-motion is a rotation of the shoulder frame about the shoulder-wrist
axis ``m = qA k qA*`` (the swivel construction ``pE = C + rho qA u(s) qA*`` with ``u(s) = Qz(s) i Qz(s)*``
turns the elbow by s about m). So every entry of the shoulder frame ``R3(s) = Rot(m, s) R3(0)`` and of the
wrist matrix ``W(s) = R4(s)^T R_tool`` is affine in (cos s, sin s):

    r(s) = k0 + k1 cos s + k2 sin s

and the joint angles of the base flip pattern (Shimizu et al. 2008, "Analytical inverse kinematic
computation for 7-DOF redundant manipulators with joint limits", IEEE T-RO 24(5), in our PA10 convention
``Qz Qy Qz Qy Qz Qy Qz``) are

    theta1 = atan2(R3[1,2], R3[0,2])         theta2 = atan2(hypot(R3[0,2], R3[1,2]), R3[2,2])
    theta3 = atan2(R3[2,1], -R3[2,0])        theta4 = constant along the circle
    theta5 = atan2(W[1,2], W[0,2])           theta6 = atan2(hypot(W[0,2], W[1,2]), W[2,2])
    theta7 = atan2(W[2,1], -W[2,0])

i.e. atan2 of two affine functions for the pivot joints and acos of one for the hinge joints. The other
seven flip patterns are affine maps of these (``theta -> -theta`` or ``theta + pi``).

**Where a joint meets a limit** is then a closed-form root: a pivot joint equals L (mod pi) where
``-sin L X(s) + cos L Y(s) = 0``; a hinge joint equals +-L where ``Z(s) = cos L``; both are
``e0 + e1 cos s + e2 sin s = 0``, solved with one acos. Added to those roots (the "critical swivels"):
where a pivot joint is stationary (``X Y' - Y X' = 0``, also affine in cos/sin: the joint touches a limit
without crossing it) and where a hinge joint is extreme (where the pivot joints next to it may jump by pi:
theta2 or theta6 passing 0 or pi). Between two consecutive critical swivels no joint of any flip pattern
crosses a limit, so one evaluation inside each arc decides it: the feasible set of each flip pattern is an
exact union of closed intervals whose ends are these roots.

Singular cases handled explicitly:

* theta4 = 0 or pi (stretched / folded elbow): the shoulder frame still turns about m (x3 is taken from
  the swivel, as in ``ik``); theta4 is constant, decided by its limit once per pose (with the same
  1e-10 rad tolerance as ``ik``, so an exact-limit theta4 is feasible).
* theta2 (or theta6) identically 0 or pi along the whole circle (wrist on the base axis with the elbow
  stretched / folded; wrist aligned with the tool axis): theta1 (theta5) is 0 by the convention of ``ik``
  and theta3 (theta7) takes the whole rotation: ``atan2(R3[1,0], +-R3[0,0])``, again affine.
* theta2 (theta6) passing 0 or pi at an isolated swivel: theta1/theta3 (theta5/theta7) turn by up to pi
  within a window whose width shrinks with the closest approach; the extreme of the hinge function is a
  critical swivel, and the nearest search samples the pivot joints at equal steps of their *angle* (the
  swivels where atan2(Y, X) = k pi / m are closed-form roots too), so a narrow window is never stepped over.
* a joint function constant and exactly at a limit: no roots, decided by evaluation with the tolerance.

:func:`nearest` minimises the weighted squared distance to a seed over every flip pattern, every in-limit
2*pi copy (per joint the copy nearest the seed; the cost is separable) and every feasible interval,
interval ends included: dense closed-form samples (uniform, equal-angle, critical swivels and the arcs'
mid points), the sample-wise local minima of each pattern, and a safeguarded Newton refinement with
analytic first and second derivatives inside each candidate's feasible bracket.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from itertools import chain
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from redarm_ros.kinematics.swivel import SwivelArm

__all__ = [
    "LimitTables",
    "SwivelFunctions",
    "swivel_functions",
    "feasible_intervals",
    "pattern_intervals",
    "nearest",
    "NearestResult",
    "roots",
    "ALT_SIGN",
    "ALT_SHIFT",
    "ALT_INDEX",
]

PI = math.pi
TWO_PI = 2.0 * math.pi
INV_2PI = 1.0 / TWO_PI
LIMIT_TOL = 1e-10  # rad, as ik: an angle this close outside a limit counts as on it (and is clipped)
SEARCH_ROOT_TOL = LIMIT_TOL - 1e-13  # rad beyond a limit at the critical swivels of the nearest search
INTERVAL_ROOT_TOL = 0.5 * LIMIT_TOL  # rad beyond a limit at the ends of feasible_swivels' intervals
DEGEN_SIN = 1e-12  # as ik: |sin theta2| (|sin theta6|) below this uses the theta1 = 0 (theta5 = 0) convention
TANGENT_TOL = 1e-9  # |e0| / hypot(e1, e2) up to 1 + this still gives a (touching) root
MERGE_TOL = 1e-12  # rad; samples of the nearest search closer than this are one sample
GRID = 16  # uniform swivel samples of the nearest search
DIRECTIONS = 8  # equal-angle samples per pivot joint: atan2(Y, X) = k pi / DIRECTIONS
BIG = 1e30  # cost of an out-of-limit alternative (finite, so pattern sums stay one matrix product)
DEPTH_MARGIN = 3.0  # a candidate basin may lie this many times its parabolic depth below its sample
UNEVEN = 4.0  # neighbouring gaps this uneven: a basin may also lie the wide gap's rise below its sample
ARC_GAIN = 1e-10  # rad^2 (relative to 1 + cost): an arc is refined if its bound is this far below the best
ARC_ROUNDS = 3  # halvings of the arcs whose bound is below the best before they are refined

# flip pattern b -> (f2, f4, f6) = bits of b (f2 most significant); per joint which alternative
ALT_INDEX = np.array(
    [
        [f2, f2, f2 ^ f4, f4, f4 ^ f6, f6, f6]
        for f2, f4, f6 in (((b >> 2) & 1, (b >> 1) & 1, b & 1) for b in range(8))
    ]
)
# alternative 1 of a joint as an affine map of the base angle: theta -> sign * theta + shift
ALT_SIGN = np.array([[1.0, 1.0 if j % 2 == 0 else -1.0] for j in range(7)])
ALT_SHIFT = np.array([[0.0, PI if j % 2 == 0 else 0.0] for j in range(7)])
_ALT_L = ALT_INDEX.tolist()
_SIGN_L = [[float(ALT_SIGN[j, a]) for j, a in enumerate(row)] for row in ALT_INDEX.tolist()]
_SHIFT_L = [[float(ALT_SHIFT[j, a]) for j, a in enumerate(row)] for row in ALT_INDEX.tolist()]
# pattern b's cost is the sum of its joints' alternatives: SEL (8, 14) @ per-alternative costs (14, M)
_SEL = np.zeros((8, 14))
for _b in range(8):
    for _j in range(7):
        _SEL[_b, 2 * _j + ALT_INDEX[_b, _j]] = 1.0
_GRID_S = np.arange(GRID) * (TWO_PI / GRID) - PI
# the scalar nearest search works on the six joints that vary along the circle, pivots first (theta4 is
# constant on the circle and is handled per pose): row k of its (6, 2, M) arrays is joint _J6[k]
_J6 = (0, 2, 4, 6, 1, 5)
_J6A = np.array(_J6)
_SEL6 = np.zeros((8, 12))
for _b in range(8):
    for _k, _j in enumerate(_J6):
        _SEL6[_b, 2 * _k + ALT_INDEX[_b, _j]] = 1.0
_PM = np.array([[1.0], [-1.0]])  # the two roots of a row: phi + d and phi - d
# a pattern's cost slope from its joints' rates: 2 w e theta' per alternative. Pivot joints keep their
# rate when flipped (theta + pi); a hinge's rate is -Z'/rho, and its flipped alternative (-theta) has +Z'/rho
_SLOPE_SIGN = np.array([[2.0, 2.0]] * 4 + [[-2.0, 2.0]] * 2)[:, :, None]
_SEL6_SLOPE = _SEL6 * _SLOPE_SIGN.reshape(1, 12)

# rows of the coefficient table K (const, cos s, sin s): pivot X rows, pivot Y rows, hinge Z rows
# 0..3: X1, X3, X5, X7   4..7: Y1, Y3, Y5, Y7   8, 9: Z2, Z6
_PIVOT_JOINTS = (0, 2, 4, 6)


def wrap(s: np.ndarray) -> np.ndarray:
    """Swivels (rad) wrapped into [-pi, pi)."""
    x = s + PI
    return x - TWO_PI * np.floor(x * INV_2PI) - PI


class LimitTables:
    """Per-arm constants of the feasible-set computations: limits (rad) in the shapes they are used in.

    ``root_tol`` (rad): the limit-crossing roots are where a joint is this far beyond its limit. ``ik``
    accepts an angle up to LIMIT_TOL beyond a limit (and clips it), and near a joint's stationary point
    that widens the feasible swivels by ~sqrt(2 LIMIT_TOL / theta'') (about 1e-5 rad). The nearest search
    uses almost all of it (SEARCH_ROOT_TOL: its optimum may sit there, and a solve that round-off pushes
    past the tolerance falls back to a swivel beside it); the public intervals keep half of it as a
    margin (INTERVAL_ROOT_TOL), so that ``ik`` at an interval end accepts the joint even where its
    computation is ill-conditioned (theta2 or theta6 near 0).
    """

    #: tables by their limits (:meth:`shared`); a few per arm and margin set, never changed once built
    _shared: dict[tuple[bytes, bytes, float], LimitTables] = {}

    @classmethod
    def shared(cls, lower: np.ndarray, upper: np.ndarray, root_tol: float = SEARCH_ROOT_TOL) -> LimitTables:
        """The tables of these limits, built once (2 ms each; a swivel corridor asks for them on every
        plan, with the same few limits every time). Built from copies: the caller's arrays stay theirs."""
        lo = np.asarray(lower, dtype=float)
        up = np.asarray(upper, dtype=float)
        key = (lo.tobytes(), up.tobytes(), float(root_tol))
        tab = cls._shared.get(key)
        if tab is None:
            if len(cls._shared) >= 256:  # (a bound, not expected to be reached)
                cls._shared.clear()
            tab = cls._shared[key] = cls(lo.copy(), up.copy(), root_tol)
        return tab

    def __init__(self, lower: np.ndarray, upper: np.ndarray, root_tol: float = SEARCH_ROOT_TOL) -> None:
        self.lower = np.asarray(lower, dtype=float)
        self.upper = np.asarray(upper, dtype=float)
        self.lo_l = self.lower.tolist()
        self.up_l = self.upper.tolist()
        self.lo3 = self.lower[:, None, None]
        self.up3 = self.upper[:, None, None]
        self.lot3 = self.lo3 - LIMIT_TOL
        self.upt3 = self.up3 + LIMIT_TOL
        # joints where more than one 2*pi copy of an angle can fit (PA10 joints 5 and 7)
        self.wide = np.nonzero(self.upper - self.lower >= TWO_PI - 2 * LIMIT_TOL)[0]
        self.wide_l = self.wide.tolist()
        piv = list(_PIVOT_JOINTS)
        lim = np.stack([self.lower[piv] - root_tol, self.upper[piv] + root_tol], axis=1)  # (4, 2)
        self.piv_s = np.sin(lim)[:, :, None]
        self.piv_c = np.cos(lim)[:, :, None]
        hin = np.stack([self.lower[[1, 5]] - root_tol, self.upper[[1, 5]] + root_tol], axis=1)  # (2, 2)
        self.hinge_cos = np.cos(hin)
        # linear equation rows as one matrix product with K: E = Lmat @ K + Coff. Rows: per pivot joint
        # its two limits (8), per hinge joint its two limits (4), then per pivot joint the DIRECTIONS
        # equal-angle rows. cos L * Y - sin L * X = 0 (pivot), Z - cos L = 0 (hinge)
        nlin = 12 + 4 * DIRECTIONS
        L = np.zeros((nlin, 10))
        C = np.zeros((nlin, 3))
        for p in range(4):
            for k in range(2):
                L[2 * p + k, p] = -float(self.piv_s[p, k, 0])
                L[2 * p + k, 4 + p] = float(self.piv_c[p, k, 0])
            for k in range(DIRECTIONS):
                r = 12 + p * DIRECTIONS + k
                L[r, p] = -math.sin(k * PI / DIRECTIONS)
                L[r, 4 + p] = math.cos(k * PI / DIRECTIONS)
        for h in range(2):
            for k in range(2):
                L[8 + 2 * h + k, 8 + h] = 1.0
                C[8 + 2 * h + k, 0] = -float(self.hinge_cos[h, k])
        # drop repeated rows (a +-2*pi limit pair is one equation; a limit at k pi / DIRECTIONS is also an
        # equal-angle row): every root then appears once
        keep = []
        seen: list[tuple[float, ...]] = []
        for r in range(nlin):
            key = tuple(np.round(np.concatenate([L[r], C[r]]), 12).tolist())
            neg = tuple(np.round(-np.concatenate([L[r], C[r]]), 12).tolist())
            if key not in seen and neg not in seen:
                seen.append(key)
                keep.append(r)
        keep_a = np.array(keep)
        self.Lc, self.Cc = L[keep_a[keep_a < 12]], C[keep_a[keep_a < 12]]
        self.Ld = L[keep_a[keep_a >= 12]]
        # which pivot joint (0..3) each kept row belongs to, -1 for hinge rows (degenerate masking)
        owner = np.array(
            [r // 2 if r < 8 else (-1 if r < 12 else (r - 12) // DIRECTIONS) for r in range(nlin)]
        )
        self.owner_c = owner[keep_a[keep_a < 12]]
        self.owner_d = owner[keep_a[keep_a >= 12]]
        self.shift_lot = ALT_SHIFT[:, :, None] - self.lot3  # A - (lower - tol) = th * sign + this
        self.width3 = self.upt3 - self.lot3  # range plus both tolerances
        self.sign3 = ALT_SIGN[:, :, None].copy()
        # the same per alternative as (14, 1) columns, row 2 j + a = alternative a of joint j (ik_batch)
        self.sign14 = ALT_SIGN.reshape(14, 1)
        self.shift_lot14 = self.shift_lot.reshape(14, 1)
        self.width14 = np.repeat(self.width3[:, 0, 0], 2)[:, None]
        self.lot14 = np.repeat(self.lot3[:, 0, 0], 2)[:, None]
        self.upt14 = np.repeat(self.upt3[:, 0, 0], 2)[:, None]
        self.lo14 = np.repeat(self.lower, 2)[:, None]
        self.up14 = np.repeat(self.upper, 2)[:, None]
        # ---- the scalar nearest search (_sample_swivels, _alternative_costs): the joints of _J6 as rows
        j6 = list(_J6)
        self.width6 = self.width3[j6].copy()
        self.lot6v = self.lower[j6] - LIMIT_TOL
        self.lot6_l = self.lot6v.tolist()
        # (alternative - (lower - tol)) mod 2 pi = atan2 of the alternative's (x, y) pair turned by
        # -(lower - tol - shift + pi), plus pi. Pairs: pivot joint p (X_p, Y_p) (flip: shift pi); hinge
        # joint (Z, +-rho). ROT (24, 12) maps [X1 X3 X5 X7 Y1 Y3 Y5 Y7 Z2 Z6 rho2 rho6] to the turned
        # x (rows 0..11) and y (rows 12..23) of the 12 alternatives, in the row order of _SEL6
        rot = np.zeros((24, 12))
        for k, j in enumerate(j6):
            for a in (0, 1):
                r = 2 * k + a
                if j % 2 == 0:  # pivot j // 2: (X, Y) at row (j // 2, 4 + j // 2) of the coefficients
                    ix, iy, sy = j // 2, 4 + j // 2, 1.0
                    dl = self.lower[j] - LIMIT_TOL - (PI if a else 0.0) + PI
                else:  # hinge: (Z, rho) with rho -> -rho for the flipped alternative
                    ix, iy, sy = 8 + j // 4, 10 + j // 4, (-1.0 if a else 1.0)
                    dl = self.lower[j] - LIMIT_TOL + PI
                cd, sd = math.cos(dl), math.sin(dl)
                rot[r, ix], rot[r, iy] = cd, sd * sy
                rot[12 + r, ix], rot[12 + r, iy] = -sd, cd * sy
        self.rot = rot
        # the same as gathers and scalings, for the batch (no matrix product: BLAS threads on a busy
        # machine made that 20x slower): x' = rc * V[rx] + rs * V[ry], y' = rc2 * V[ry] - rs2 * V[rx]
        self.rx = np.array([j // 2 if j % 2 == 0 else 8 + j // 4 for j in j6 for _ in (0, 1)])
        self.ry = np.array([4 + j // 2 if j % 2 == 0 else 10 + j // 4 for j in j6 for _ in (0, 1)])
        self.rc = rot[np.arange(12), self.rx][:, None, None]
        self.rs = rot[np.arange(12), self.ry][:, None, None]
        self.rc2 = rot[12 + np.arange(12), self.ry][:, None, None]
        self.rs2 = -rot[12 + np.arange(12), self.rx][:, None, None]
        # the batch turns and atan2s only the 6 base alternatives (even rows) and derives the flipped ones:
        # a pivot's flipped X is X + pi (mod 2 pi); a hinge's -theta gives (c - X) mod 2 pi with
        # c = -2 (lower - tol), kept in [2 pi, 4 pi) so that the difference is positive
        self.rx0, self.ry0 = self.rx[0::2].copy(), self.ry[0::2].copy()
        self.rc0, self.rs0 = self.rc[0::2].copy(), self.rs[0::2].copy()
        self.rc20, self.rs20 = self.rc2[0::2].copy(), self.rs2[0::2].copy()
        self.hinge_flip = np.array(
            [(-2.0 * (self.lower[j] - LIMIT_TOL)) % TWO_PI + TWO_PI for j in j6[4:]]
        )[:, None, None]
        # theta1 (theta5) fixed at 0 by convention: its alternatives' values, (shift - (lower - tol)) mod 2 pi
        self.fixed6 = {
            j: [(sh - lot) % TWO_PI for sh in (0.0, PI)]
            for j, lot in ((0, self.lot6_l[0]), (4, self.lot6_l[2]))
        }
        wide6 = [k for k, j in enumerate(j6) if j in self.wide_l]
        # a slice where the wide rows are contiguous (PA10: joints 5 and 7), so updates act in place
        self.wide6: slice | np.ndarray | None = None
        if wide6:
            contiguous = wide6 == list(range(wide6[0], wide6[-1] + 1))
            self.wide6 = slice(wide6[0], wide6[-1] + 1) if contiguous else np.array(wide6)
            self.width6w = self.width6[self.wide6]
        # its equations, as columns (e0, e1, e2) of a (3, R) table: 4 stationary rows and one anti-seed
        # row per wide joint (computed per pose), the limit rows, then the equal-angle rows (those two from
        # one product GT with the coefficients and a constant row). The first ones up to the equal-angle
        # rows give critical swivels. Equal-angle rows that repeat a critical swivel on every pose go last
        # (theta3 = 0 and theta5 = 0 mod pi where theta2 / theta6 is extreme; theta3 = pi / 2 where theta1
        # is stationary and theta5 = pi / 2 where theta7 is), so that they can be left out per pose.
        n_py = 4 + len(self.wide_l)
        dir_owner = self.owner_d.tolist()
        dir_k = [int(r - 12) % DIRECTIONS for r in keep_a[keep_a >= 12].tolist()]
        repeat = {(1, 0): 0, (1, DIRECTIONS // 2): 0, (2, 0): 1, (2, DIRECTIONS // 2): 1}  # -> hinge
        order = [i for i in range(len(dir_k)) if (dir_owner[i], dir_k[i]) not in repeat]
        for h in (0, 1):
            order += [i for i in range(len(dir_k)) if repeat.get((dir_owner[i], dir_k[i])) == h]
        G = np.concatenate([self.Lc, self.Ld[order]])
        const = np.concatenate([self.Cc[:, 0], np.zeros(len(order))])
        self.GT = np.ascontiguousarray(np.concatenate([G, const[:, None]], axis=1).T)  # (11, R - n_py)
        self.n_py = n_py
        self.n_crit_rows = n_py + len(self.Lc)
        R = n_py + len(G)
        col = {i: self.n_crit_rows + j for j, i in enumerate(order)}  # Ld row -> column
        self.dir_col = {(dir_owner[i], dir_k[i]): col[i] for i in range(len(dir_k))}
        # per hinge (0: theta2, 1: theta6) the column range repeating its extremes and the stationary
        # points next to it
        self.repeat_cols = []
        for h in (0, 1):
            cols = [col[i] for i in range(len(dir_k)) if repeat.get((dir_owner[i], dir_k[i])) == h]
            self.repeat_cols.append((min(cols), max(cols) + 1) if cols else (0, 0))
        anti_owner = [j // 2 if j % 2 == 0 else -1 for j in self.wide_l]
        owner_all = np.array(
            [0, 1, 2, 3] + anti_owner + self.owner_c.tolist() + [dir_owner[i] for i in order]
        )
        assert len(owner_all) == R
        # samples per pose of the batched search (padded): roots of every row, extremes, mid points, grid,
        # the seed's swivel, and the two neighbours around the circle
        self.batch_samples = 2 * (2 * self.n_crit_rows + 4) + 2 * (R - self.n_crit_rows) + GRID + 1 + 2
        # columns to drop when theta1 (theta5) is 0 by convention on the whole circle
        self.dead_cols = {p: np.nonzero(owner_all == p)[0] for p in (0, 2)}

    def fit(self, A: np.ndarray, ref: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Alternatives A (7, 2, M) at their in-limit 2*pi copy nearest ``ref`` (7,) (None: nearest 0).

        Returns (V clipped into the limits, feasible (bool)); within LIMIT_TOL of a limit is feasible.
        """
        X = A - self.lot3
        V = X - TWO_PI * np.floor(X * INV_2PI) + self.lot3  # lowest copy >= lower - tol
        room = self.upt3 - V
        feas = room >= 0.0
        if len(self.wide):
            wj = self.wide
            kmax = np.maximum(np.floor(room[wj] * INV_2PI), 0.0)
            r = 0.0 if ref is None else ref[wj][:, None, None]
            k = np.rint((r - V[wj]) * INV_2PI).clip(0.0, kmax)  # (ndarray methods: np.clip's, no wrapper)
            V[wj] += TWO_PI * k
        return np.minimum(np.maximum(V, self.lo3), self.up3), feas  # np.clip's picks, without its wrappers


@dataclass
class SwivelFunctions:
    """The joint angles of one pose as closed-form functions of the swivel s (rad), base flip pattern.

    ``K`` (10, 3): coefficients (const, cos s, sin s) of X1, X3, X5, X7, Y1, Y3, Y5, Y7, Z2, Z6 (see the
    module docstring: pivot joint j = atan2(Yj, Xj), hinge joints atan2(hypot(X, Y), Z) with the X, Y of
    joint 1 (5)); ``t4`` the constant elbow angle (rad, >= 0); ``deg_shoulder`` / ``deg_wrist``: theta2
    (theta6) is 0 or pi on the whole circle, so theta1 (theta5) is 0 by convention.
    """

    K: np.ndarray
    Kl: list[list[float]]
    t4: float
    deg_shoulder: bool
    deg_wrist: bool
    Ka: np.ndarray | None = None  # (11, 3): K and the constant row (1, 0, 0), for one-product equations
    KV: np.ndarray | None = None  # (20, 3): the rates' coefficients (d/ds of each row), then K

    def __post_init__(self) -> None:
        # (swivel_functions passes both; built here for functions made from K alone)
        if self.Ka is None:
            self.Ka = np.vstack([self.K, [1.0, 0.0, 0.0]])
        if self.KV is None:
            K = np.asarray(self.K, dtype=float)
            self.KV = np.vstack([np.stack([np.zeros(10), K[:, 2], -K[:, 1]], axis=1), K])

    def angles(self, s: np.ndarray) -> np.ndarray:
        """(7, M) base-pattern joint angles (rad) at the swivels s (M,); pivot joints in (-pi, pi]."""
        CS = np.empty((3, s.shape[0]))
        CS[0] = 1.0
        np.cos(s, out=CS[1])
        np.sin(s, out=CS[2])
        P = self.K @ CS
        th = np.empty((7, s.shape[0]))
        th[0::2] = np.arctan2(P[4:8], P[0:4])
        XY = P[0:7:2]  # X1, X5, Y1, Y5 (rows 0, 2, 4, 6)
        XY = XY * XY
        th[1::4] = np.arctan2(np.sqrt(XY[0:2] + XY[2:4]), P[8:10])
        th[3] = self.t4
        if self.deg_shoulder:
            th[0] = 0.0
        if self.deg_wrist:
            th[4] = 0.0
        return th

    def equations(self, tab: LimitTables, seed: list[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Rows (e0, e1, e2) of e0 + e1 cos s + e2 sin s = 0: (critical rows, equal-angle rows).

        Critical: per pivot joint where it is stationary (X Y' - Y X' = 0) and where it equals each of
        its limits (mod pi, which covers the flipped pattern too); per hinge joint where it equals
        +-each limit. Equal-angle rows (sampling only): pivot joint = k pi / DIRECTIONS.
        """
        Kl = self.Kl
        stat = []
        for p in range(4):
            x0, x1, x2 = Kl[p]
            y0, y1, y2 = Kl[p + 4]
            stat.append([x1 * y2 - x2 * y1, x0 * y2 - y0 * x2, y0 * x1 - x0 * y1])
        if seed is not None:  # joints with several in-limit copies switch copy opposite the seed
            for j in tab.wide_l:
                L = seed[j] + PI
                sl, cl = math.sin(L), math.cos(L)
                if j % 2 == 0:
                    p = j // 2
                    x0, x1, x2 = Kl[p]
                    y0, y1, y2 = Kl[p + 4]
                    stat.append([cl * y0 - sl * x0, cl * y1 - sl * x1, cl * y2 - sl * x2])
                else:
                    z0, z1, z2 = Kl[8 + j // 4]
                    stat.append([z0 - cl, z1, z2])
        Ec = np.concatenate([np.array(stat), tab.Lc @ self.K + tab.Cc])
        Ed = tab.Ld @ self.K
        if self.deg_shoulder or self.deg_wrist:  # theta1 (theta5) is constant 0: no rows for it
            dead = ([0] if self.deg_shoulder else []) + ([2] if self.deg_wrist else [])
            extra = [j // 2 if j % 2 == 0 else -1 for j in tab.wide_l] if seed is not None else []
            owners = np.concatenate([np.arange(4), np.array(extra, dtype=int), tab.owner_c])
            keep_c = ~np.isin(owners, dead)
            Ec, Ed = Ec[keep_c], Ed[~np.isin(tab.owner_d, dead)]
        return Ec, Ed

    def extremes(self) -> list[float]:
        """Swivels where theta2 and theta6 are extreme (nearest 0 or pi): the singular candidates."""
        out = []
        for _, z1, z2 in self.Kl[8:10]:
            if z1 * z1 + z2 * z2 > 1e-30:
                se = math.atan2(z2, z1)
                out += [se, se + PI]
        return out


def swivel_functions(arm: SwivelArm, Tl: list[list[float]], circ: tuple[float, ...]) -> SwivelFunctions:
    """Build the closed-form joint functions of pose Tl (nested lists) with elbow circle ``circ``.

    A vector v turning with the arm is Rot(m, s) v0 = (m.v0) m + cos s (v0 - (m.v0) m) + sin s (m x v0),
    so its component along a fixed t is (m.v0)(m.t) + cos s (v0.t - (m.v0)(m.t)) + sin s (m x v0).t.
    """
    zx, zy, zz, x3x, x3y, x3z, y3x, y3y, y3z, t4, c4, s4 = arm._frame3(circ, 1.0, 0.0)  # noqa: SLF001
    a0x, a0y, a0z = arm._rot_qa(circ, 1.0, 0.0)  # noqa: SLF001
    a1x, a1y, a1z = arm._rot_qa(circ, 0.0, 1.0)  # noqa: SLF001
    mx, my, mz = a0y * a1z - a0z * a1y, a0z * a1x - a0x * a1z, a0x * a1y - a0y * a1x  # qA k qA*
    # m . v and m x v of the shoulder frame's axes (those of frame 4 follow linearly)
    dz3 = mx * zx + my * zy + mz * zz
    cz = (my * zz - mz * zy, mz * zx - mx * zz, mx * zy - my * zx)
    dx3 = mx * x3x + my * x3y + mz * x3z
    cx = (my * x3z - mz * x3y, mz * x3x - mx * x3z, mx * x3y - my * x3x)
    dy3 = mx * y3x + my * y3y + mz * y3z
    cy = (my * y3z - mz * y3y, mz * y3x - mx * y3z, mx * y3y - my * y3x)
    # frame 4 = frame 3 turned by theta4 about y3: x4 = c4 x3 - s4 z3, z4 = s4 x3 + c4 z3 (and their m . v,
    # m x v alike). Written out in scalars: this runs once per ik_nearest call (about 6 us)
    x4x, x4y, x4z = c4 * x3x - s4 * zx, c4 * x3y - s4 * zy, c4 * x3z - s4 * zz
    z4x, z4y, z4z = s4 * x3x + c4 * zx, s4 * x3y + c4 * zy, s4 * x3z + c4 * zz
    dx4, dz4 = c4 * dx3 - s4 * dz3, s4 * dx3 + c4 * dz3
    cx4x, cx4y, cx4z = c4 * cx[0] - s4 * cz[0], c4 * cx[1] - s4 * cz[1], c4 * cx[2] - s4 * cz[2]
    cz4x, cz4y, cz4z = s4 * cx[0] + c4 * cz[0], s4 * cx[1] + c4 * cz[1], s4 * cx[2] + c4 * cz[2]
    r0, r1, r2 = Tl[0], Tl[1], Tl[2]
    bx, by, bz = r0[0], r1[0], r2[0]  # tool x
    yx, yy, yz = r0[1], r1[1], r2[1]  # tool y
    ax, ay, az = r0[2], r1[2], r2[2]  # tool z (approach)
    ma, mb, my_ = mx * ax + my * ay + mz * az, mx * bx + my * by + mz * bz, mx * yx + my * yy + mz * yz
    # component along a tool axis t of a turning v: [(m.v)(m.t), v.t - (m.v)(m.t), (m x v).t]
    k0 = dx4 * ma
    X5 = [k0, x4x * ax + x4y * ay + x4z * az - k0, cx4x * ax + cx4y * ay + cx4z * az]
    k0 = dy3 * ma
    Y5 = [k0, y3x * ax + y3y * ay + y3z * az - k0, cy[0] * ax + cy[1] * ay + cy[2] * az]
    k0 = dz4 * ma
    Z6 = [k0, z4x * ax + z4y * ay + z4z * az - k0, cz4x * ax + cz4y * ay + cz4z * az]
    X1 = [dz3 * mx, zx - dz3 * mx, cz[0]]
    Y1 = [dz3 * my, zy - dz3 * my, cz[1]]
    Z2 = [dz3 * mz, zz - dz3 * mz, cz[2]]
    # theta2 (theta6) 0 or pi on the whole circle: bound |(X, Y)| over the circle
    hyp = math.hypot
    deg_sh = hyp(X1[0], Y1[0]) + hyp(X1[1], Y1[1]) + hyp(X1[2], Y1[2]) <= DEGEN_SIN
    deg_wr = hyp(X5[0], Y5[0]) + hyp(X5[1], Y5[1]) + hyp(X5[2], Y5[2]) <= DEGEN_SIN
    if deg_sh:  # R3 = Rz(theta3) Ry(0 or pi): theta3 = atan2(x3y, +-x3x), as ik
        sg = 1.0 if Z2[0] >= 0.0 else -1.0
        X3 = [sg * dx3 * mx, sg * (x3x - dx3 * mx), sg * cx[0]]
        Y3 = [dx3 * my, x3y - dx3 * my, cx[1]]
    else:  # theta3 = atan2(R3[2,1], -R3[2,0])
        X3 = [-dx3 * mz, -(x3z - dx3 * mz), -cx[2]]
        Y3 = [dy3 * mz, y3z - dy3 * mz, cy[2]]
    if deg_wr:  # theta7 = atan2(W[1,0], +-W[0,0])
        sg = 1.0 if Z6[0] >= 0.0 else -1.0
        k0 = dx4 * mb
        X7 = [sg * k0, sg * (x4x * bx + x4y * by + x4z * bz - k0), sg * (cx4x * bx + cx4y * by + cx4z * bz)]
        k0 = dy3 * mb
        Y7 = [k0, y3x * bx + y3y * by + y3z * bz - k0, cy[0] * bx + cy[1] * by + cy[2] * bz]
    else:  # theta7 = atan2(W[2,1], -W[2,0])
        k0 = dz4 * mb
        X7 = [-k0, -(z4x * bx + z4y * by + z4z * bz - k0), -(cz4x * bx + cz4y * by + cz4z * bz)]
        k0 = dz4 * my_
        Y7 = [k0, z4x * yx + z4y * yy + z4z * yz - k0, cz4x * yx + cz4y * yy + cz4z * yz]
    Kl = [X1, X3, X5, X7, Y1, Y3, Y5, Y7, Z2, Z6]
    # rows: the rates' coefficients (0, k2, -k1) of the ten, the ten (k0, k1, k2), the constant row
    rows = (X1, X3, X5, X7, Y1, Y3, Y5, Y7, Z2, Z6)
    A = np.fromiter(
        chain(chain.from_iterable((0.0, r[2], -r[1]) for r in rows), *rows, (1.0, 0.0, 0.0)), float, 63
    ).reshape(21, 3)
    return SwivelFunctions(A[10:20], Kl, t4, deg_sh, deg_wr, A[10:], A[:20])


def roots(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roots of e0 + e1 cos s + e2 sin s = 0 for the rows of E (k, 3): (s_plus, s_minus), NaN where none.

    Two roots where |e0| <= hypot(e1, e2) (a touching root up to a relative TANGENT_TOL beyond); none
    where the cos/sin part vanishes (the function is constant along the circle).
    """
    e1, e2 = E[:, 1], E[:, 2]
    # a vanishing cos/sin part gives |r| ~ 1e300 (no root), without a division warning
    r = -E[:, 0] / np.maximum(np.sqrt(e1 * e1 + e2 * e2), 1e-300)
    r[np.abs(r) > 1.0 + TANGENT_TOL] = np.nan
    phi = np.arctan2(e2, e1)
    d = np.arccos(np.minimum(np.maximum(r, -1.0), 1.0))  # np.clip's picks (NaN stays), without its wrappers
    return phi + d, phi - d


def sorted_unique(x: np.ndarray) -> np.ndarray:
    """``np.unique`` of a 1-D float array without NaN, by its own sorting path (the same sort, then the
    first of every run of equal values: 0.0 or -0.0 as np.unique keeps it), without its Python set-up:
    less than half its cost on the few hundred values asked here."""
    a = np.sort(x)
    if len(a) < 2:
        return a
    keep = np.empty(len(a), dtype=bool)
    keep[0] = True
    np.not_equal(a[1:], a[:-1], out=keep[1:])
    return a[keep]


def _alternatives(th: np.ndarray) -> np.ndarray:
    """(7, M) base-pattern angles -> (7, 2, M): per joint the base and the flipped alternative."""
    return th[:, None, :] * ALT_SIGN[:, :, None] + ALT_SHIFT[:, :, None]


def _critical(fn: SwivelFunctions, tab: LimitTables) -> np.ndarray:
    Ec, _ = fn.equations(tab)
    rp, rm = roots(Ec)
    allr = np.concatenate([rp, rm, fn.extremes()])
    return sorted_unique(wrap(allr[allr == allr]))


def feasible_intervals(fn: SwivelFunctions, tab: LimitTables) -> list[np.ndarray]:
    """Per flip pattern (8, order of ``ik``) the feasible swivels as closed intervals, (k, 2) arrays.

    Each row is [start, end] (rad) with start in [-pi, pi) and start <= end <= start + 2*pi (an interval
    may run past pi); the whole circle is [-pi, pi]. Ends are closed-form roots; an isolated feasible
    swivel (a joint touching a limit) is a zero-width row. Rows are sorted by start.
    """
    crit, ok = _feasible_arcs(fn, tab)
    return [_pattern_rows(crit, ok[b]) for b in range(8)]


def pattern_intervals(fn: SwivelFunctions, tab: LimitTables, pattern: int) -> np.ndarray:
    """``feasible_intervals(fn, tab)[pattern]``, computed for that flip pattern only."""
    crit, ok = _feasible_arcs(fn, tab)
    return _pattern_rows(crit, ok[pattern])


def _feasible_arcs(fn: SwivelFunctions, tab: LimitTables) -> tuple[np.ndarray, np.ndarray]:
    """The critical swivels (sorted, n) and per pattern whether every joint is feasible (8, P): on the
    n arcs between them (their mid points) first, then at the n critical swivels."""
    crit = _critical(fn, tab)
    n = len(crit)
    mids = (crit + np.append(crit[1:], crit[0] + TWO_PI)) / 2.0 if n else np.array([0.0])
    pts = np.concatenate([mids, crit])
    _, feas = tab.fit(_alternatives(fn.angles(pts)), None)
    return crit, (_SEL @ np.where(feas, 0.0, 1.0).reshape(14, -1)) < 0.5


def _pattern_rows(crit: np.ndarray, ok_b: np.ndarray) -> np.ndarray:
    """One pattern's intervals (see :func:`feasible_intervals`) from :func:`_feasible_arcs`."""
    n = len(crit)
    nm = max(n, 1)
    arc_ok = ok_b[:nm]
    if n == 0 or arc_ok.all():
        return np.array([[-PI, PI]]) if arc_ok.all() else np.empty((0, 2))
    pt_ok = ok_b[nm:]
    crit_l = crit.tolist()
    rows: list[list[float]] = []
    start = int(np.argmin(arc_ok))  # an infeasible arc: every feasible run is contiguous after it
    cur: list[float] | None = None
    for t in range(n):
        i = (start + 1 + t) % n  # arc i runs from crit[i] to crit[i + 1]
        a = crit_l[i]
        if arc_ok[i]:
            end = crit_l[i + 1] if i + 1 < n else crit_l[0] + TWO_PI
            if cur is None:
                cur = [a, end]
            else:
                cur[1] = end if end >= cur[1] else end + TWO_PI
        else:
            if cur is not None:
                rows.append(cur)
                cur = None
            if pt_ok[i] and not arc_ok[i - 1]:  # isolated: infeasible arcs on both sides
                rows.append([a, a])
    if cur is not None:
        rows.append(cur)
    for r in rows:  # start in [-pi, pi)
        w = r[1] - r[0]
        r[0] = r[0] - TWO_PI if r[0] >= PI else r[0]
        r[1] = r[0] + w
    rows.sort()
    return np.array(rows) if rows else np.empty((0, 2))


# realise(swivel, pattern, predicted cost) -> (q, swivel, pattern, cost) of a solution as ``ik`` computes
# it there (or beside it), or None: see :func:`nearest`
Realise = Callable[[float, int, float], "tuple[Any, float, int, float] | None"]


@dataclass
class NearestResult:
    """Outcome of :func:`nearest`: the best (swivel rad, flip pattern, cost rad^2, q) and the work done.

    ``q``: the solution ``realise`` returned for the best candidate (None without ``realise``, or if no
    candidate could be realised: ``swivel`` is then the best predicted one, or None if there was no
    candidate at all, i.e. no in-limit solution).
    """

    swivel: float | None
    branch: int
    cost: float
    candidates: int
    refined: int
    evaluations: int
    timed_out: bool
    q: Any = None


def _fgh(
    fn: SwivelFunctions,
    s: float,
    b: int,
    Vref: list[float],
    seed: list[float],
    w: list[float],
    tab: LimitTables,
) -> tuple[float, float, float, list[float]]:
    """Cost of pattern b at s with the copies continued from Vref, and its first and second derivative
    d/ds; cost inf if one of these copies is outside its limits (beyond the tolerance)."""
    c, sn = math.cos(s), math.sin(s)
    K = fn.Kl
    th = [0.0] * 7
    g = [0.0] * 7
    h = [0.0] * 7
    for p in range(4):
        j = 2 * p
        if (p == 0 and fn.deg_shoulder) or (p == 2 and fn.deg_wrist):
            continue  # theta1 (theta5) = 0 by convention
        k0, k1, k2 = K[p]
        X, Xd, Xdd = k0 + k1 * c + k2 * sn, k2 * c - k1 * sn, -k1 * c - k2 * sn
        k0, k1, k2 = K[p + 4]
        Y, Yd, Ydd = k0 + k1 * c + k2 * sn, k2 * c - k1 * sn, -k1 * c - k2 * sn
        Q = X * X + Y * Y
        th[j] = math.atan2(Y, X)
        if Q > 0.0:
            N = X * Yd - Y * Xd
            g[j] = N / Q
            h[j] = ((X * Ydd - Y * Xdd) * Q - 2.0 * N * (X * Xd + Y * Yd)) / (Q * Q)
    for j, p, deg in ((1, 0, fn.deg_shoulder), (5, 2, fn.deg_wrist)):
        k0, k1, k2 = K[p]
        X = k0 + k1 * c + k2 * sn
        k0, k1, k2 = K[p + 4]
        Y = k0 + k1 * c + k2 * sn
        k0, k1, k2 = K[8 + p // 2]
        Z = k0 + k1 * c + k2 * sn
        rho = math.sqrt(X * X + Y * Y)
        th[j] = math.atan2(rho, Z)
        if rho > DEGEN_SIN and not deg:
            Zd, Zdd = k2 * c - k1 * sn, -k1 * c - k2 * sn
            g[j] = -Zd / rho
            h[j] = -(Zdd * rho * rho + Z * Zd * Zd) / (rho * rho * rho)
    th[3] = fn.t4
    sg = _SIGN_L[b]
    sh = _SHIFT_L[b]
    lo, up = tab.lo_l, tab.up_l
    f = d = dd = 0.0
    V = [0.0] * 7
    for j in range(7):
        a = th[j] * sg[j] + sh[j]
        v = a + TWO_PI * round((Vref[j] - a) * INV_2PI)
        if v < lo[j]:
            if v < lo[j] - LIMIT_TOL:
                return math.inf, 0.0, 0.0, Vref
            v = lo[j]
        elif v > up[j]:
            if v > up[j] + LIMIT_TOL:
                return math.inf, 0.0, 0.0, Vref
            v = up[j]
        V[j] = v
        e = v - seed[j]
        wj = w[j]
        gj = g[j] * sg[j]
        f += wj * e * e
        d += wj * e * gj
        dd += wj * (gj * gj + e * h[j] * sg[j])
    return f, 2.0 * d, 2.0 * dd, V


def _refine(
    fn: SwivelFunctions,
    b: int,
    x: float,
    V0: list[float],
    a: float,
    c: float,
    seed: list[float],
    w: list[float],
    tab: LimitTables,
    max_iter: int = 40,
) -> tuple[float, float, int]:
    """Safeguarded Newton on the cost of pattern b inside the bracket [a, c] (a <= x <= c), from x.

    No critical swivel lies inside the bracket, so the cost is smooth there; its minimum may be an end.
    Stops when the Newton model predicts a gain below 1e-14 (relative). Returns (s, cost, evaluations).
    """
    fx, g, h, V = _fgh(fn, x, b, V0, seed, w, tab)
    n = 1
    if not math.isfinite(fx):  # round-off right at a limit of this copy
        return x, math.inf, n
    best_f, best_x = fx, x
    tried = math.nan
    for _ in range(max_iter):
        if g > 0.0:
            c = x
        elif g < 0.0:
            a = x
        else:
            break
        if h > 0.0:
            if 0.5 * g * g / h <= 1e-14 * (1.0 + fx):
                break  # the model's remaining gain is below round-off of the cost
            xn = x - g / h
        else:
            xn = math.nan
        if not (a < xn < c):
            # the model's minimum is beyond the bracket: try the end it points to (a limit optimum
            # is reached in one step), then bisect
            end = c if g < 0.0 else a
            xn = end if end != tried else 0.5 * (a + c)
            tried = end
        if abs(xn - x) <= 4e-16 * (1.0 + abs(x)):
            break
        fxn, gn, hn, Vn = _fgh(fn, xn, b, V, seed, w, tab)
        n += 1
        if not math.isfinite(fxn):  # beyond a limit of this copy: the minimum is on this side of xn
            if xn > x:
                c = xn
            else:
                a = xn
            continue
        x, fx, g, h, V = xn, fxn, gn, hn, Vn
        if fx < best_f:
            best_f, best_x = fx, x
    return best_x, best_f, n


def _sample_swivels(
    fn: SwivelFunctions, tab: LimitTables, s_seed: float | None, seed: list[float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample swivels of the nearest search: (Sp, flag, gaps).

    Critical samples: the closed-form roots (limits, stationary points, and for a joint with several
    in-limit copies where it is opposite the ``seed``, where the nearest copy switches) and the hinge
    extremes. Plain: the uniform grid, the equal-angle roots of the pivot joints, the seed's own swivel
    and the mid point between every two neighbouring critical swivels, so that every arc between two
    neighbouring samples has a plain end (which decides the open arc's feasibility: no critical swivel
    inside). ``Sp`` (M + 2,): the M samples sorted in [-pi, pi), padded with S[M - 1] in front and S[0]
    behind (the neighbours around the circle); ``flag`` (M,) critical; ``gaps`` (M + 1,): gaps[i] =
    S[i] - S[i - 1] around the circle (gaps[0] = gaps[M] is the gap across pi).

    Runs once per ``ik_nearest`` with about 50 equations and 100 samples, so numpy's per-call overhead
    (about 1 us a call on the 2-core test machine) is its cost, not the arithmetic: all equations are
    solved by the same dozen calls on contiguous rows, and samples that would repeat a critical swivel on
    every pose are not made (merging near-equal samples used to cost 15 us a call).
    """
    Kl = fn.Kl
    n_py = tab.n_py
    ET = np.empty((3, n_py + tab.GT.shape[1]))  # columns (e0, e1, e2): e0 + e1 cos s + e2 sin s = 0
    a0, a1, a2 = [], [], []
    for p in range(4):  # where pivot joint p is stationary: X Y' - Y X' = 0, affine in cos / sin
        x0, x1, x2 = Kl[p]
        y0, y1, y2 = Kl[p + 4]
        a0.append(x1 * y2 - x2 * y1)
        a1.append(x0 * y2 - y0 * x2)
        a2.append(y0 * x1 - x0 * y1)
    # where theta2 and theta6 are extreme (nearest 0 or pi: the singular candidates), as pre-wrap values
    # (see the roots below: se + pi and se give se and its antipode). Away from 0 and pi (cos within 1e-6
    # of +-1) a hinge's extremes are where theta3 (theta5) = 0 mod pi, and the stationary points of
    # theta1 (theta7) where theta3 (theta5) = pi / 2: rows for those would only repeat critical swivels
    ext = [math.nan] * 4
    n_ext = 0
    regular = [False, False]
    for h, (z0, z1, z2) in enumerate(Kl[8:10]):
        zz = z1 * z1 + z2 * z2
        if zz > 1e-30:
            se = math.atan2(z2, z1)
            ext[2 * h : 2 * h + 2] = (se + PI, se)
            n_ext += 2
            regular[h] = abs(z0) + math.sqrt(zz) < 1.0 - 1e-6
    drop = []
    for q, j in enumerate(tab.wide_l):  # a joint with several in-limit copies switches copy opposite the seed
        L = seed[j] + PI
        sl, cl = math.sin(L), math.cos(L)
        if j % 2 == 0:
            p = j // 2
            (x0, x1, x2), (y0, y1, y2) = Kl[p], Kl[p + 4]
            a0.append(cl * y0 - sl * x0)
            a1.append(cl * y1 - sl * x1)
            a2.append(cl * y2 - sl * x2)
            k = L * (DIRECTIONS / PI)  # L = k pi / DIRECTIONS: an equal-angle row repeats this one
            if abs(k - round(k)) < 1e-12:
                k = round(k) % DIRECTIONS
                if p in (1, 2) and k in (0, DIRECTIONS // 2) and regular[p - 1]:
                    drop.append(4 + q)  # ... and it repeats a hinge extreme or a stationary point
                else:
                    drop.append(tab.dir_col.get((p, k), -1))
        else:
            z0, z1, z2 = Kl[8 + j // 4]
            a0.append(z0 - cl)
            a1.append(z1)
            a2.append(z2)
    ET[:, :n_py] = (a0, a1, a2)
    ET[:, n_py:] = np.dot(fn.Ka.T, tab.GT)
    for h in (0, 1):
        if regular[h]:
            r0, r1 = tab.repeat_cols[h]
            ET[0, r0:r1] = np.inf  # (a root of e0 = inf: none)
    if fn.deg_shoulder:  # theta1 (theta5) is 0 on the whole circle: no rows for it
        drop.extend(tab.dead_cols[0].tolist())
    if fn.deg_wrist:
        drop.extend(tab.dead_cols[2].tolist())
    if len(drop) <= 4:  # (one by one: a fancy assignment from a list costs a few us)
        for c in drop:
            if c >= 0:
                ET[0, c] = np.inf
    else:
        ET[0, [c for c in drop if c >= 0]] = np.inf
    # roots: with (e1, e2) = h (cos phi, sin phi) and r = e0 / h, s = phi + pi -+ acos(r), i.e. phi -+
    # acos(r) - pi (mod 2 pi); x - copysign(pi, x) wraps phi -+ acos(r) (in [-2 pi, 2 pi]) into [-pi, pi]
    e1 = ET[1]
    e2 = ET[2]
    r = ET[0] / np.maximum(np.hypot(e1, e2), 1e-300)  # a constant row: |r| ~ 1e300, no root
    bad = np.abs(r) > 1.0 + TANGENT_TOL  # no root (up to TANGENT_TOL beyond: a touching root)
    d = np.arccos(np.minimum(np.maximum(r, -1.0), 1.0))
    d[bad] = np.nan
    phi = np.arctan2(e2, e1)
    # Y: [critical roots +, critical roots -, extremes, equal-angle roots +, equal-angle roots -]
    nc = tab.n_crit_rows
    nr = len(r)
    Y = np.empty(2 * nr + 4)
    np.add(phi[:nc], d[:nc], out=Y[:nc])
    np.subtract(phi[:nc], d[:nc], out=Y[nc : 2 * nc])
    Y[2 * nc : 2 * nc + 4] = ext
    np.add(phi[nc:], d[nc:], out=Y[2 * nc + 4 : nr + nc + 4])
    np.subtract(phi[nc:], d[nc:], out=Y[nr + nc + 4 :])
    Y -= np.copysign(PI, Y)
    c = Y[: 2 * nc + 4].copy()
    c.sort()  # NaN (no root) last
    nbad_c = int(np.count_nonzero(bad[:nc]))
    n = 2 * (nc - nbad_c) + n_ext
    c = c[:n]
    mids = np.empty(n)
    if n:
        np.add(c[:-1], c[1:], out=mids[:-1])
        mids *= 0.5
        m = 0.5 * (float(c[-1]) + float(c[0])) + PI  # the arc across pi, wrapped
        mids[-1] = m - TWO_PI if m >= PI else m
    seed_s: tuple[float, ...] = ()
    if s_seed is not None:  # (on a grid point it would only repeat that sample)
        t = (s_seed + PI) * (GRID / TWO_PI)
        if abs(t - round(t)) * (TWO_PI / GRID) > MERGE_TOL:
            seed_s = (s_seed - TWO_PI if s_seed >= PI else s_seed,)
    S = np.concatenate((c, mids, Y[2 * nc + 4 :], _GRID_S, seed_s))
    M = len(S) - 2 * (int(np.count_nonzero(bad)) - nbad_c)
    order = S.argsort()[:M]  # NaN (no root) last
    Sp = np.empty(M + 2)
    np.take(S, order, out=Sp[1:-1], mode="clip")
    flag = order < n
    gaps = np.empty(M + 1)
    np.subtract(Sp[2:-1], Sp[1:-2], out=gaps[1:-1])
    # rare: the wrap gave pi, or near-equal samples
    if Sp[-2] >= PI or (M > 1 and np.minimum.reduce(gaps[1:-1]) <= MERGE_TOL):
        S = Sp[1:-1]
        S[S >= PI] -= TWO_PI
        order = S.argsort()
        S, flag = _merge_close(S[order], flag[order])
        M = len(S)
        Sp = np.empty(M + 2)
        Sp[1:-1] = S
        gaps = np.empty(M + 1)
        np.subtract(Sp[2:-1], Sp[1:-2], out=gaps[1:-1])
    Sp[0] = Sp[-2]
    Sp[-1] = Sp[1]
    gaps[0] = gaps[-1] = Sp[1] + TWO_PI - Sp[-2]
    return Sp, flag, gaps


def _merge_close(S: np.ndarray, flag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted samples with one sample per cluster of samples closer than MERGE_TOL, critical if any member
    is (the critical member, an exact root, represents the cluster). Rare: touching roots, coincidences."""
    keep = np.concatenate([[True], np.diff(S) > MERGE_TOL])
    grp = np.cumsum(keep) - 1
    crit_any = np.zeros(int(grp[-1]) + 1, bool)
    np.logical_or.at(crit_any, grp, flag)
    rep = np.nonzero(keep)[0]
    ci = np.nonzero(flag & ~keep)[0]
    rep[grp[ci]] = ci
    return S[rep], crit_any


def _theta4_copies(
    fn: SwivelFunctions, tab: LimitTables, seed: list[float]
) -> list[tuple[float, float] | None]:
    """theta4 (constant on the circle) per alternative (t4, -t4): (in-limit copy nearest the seed, that
    copy clipped into the limits), or None if no copy is within the limits (LIMIT_TOL)."""
    lo, up, r = tab.lo_l[3], tab.up_l[3], seed[3]
    out: list[tuple[float, float] | None] = []
    for a in (fn.t4, -fn.t4):
        v0 = lo - LIMIT_TOL + (a - lo + LIMIT_TOL) % TWO_PI  # lowest copy >= lower - tol
        kmax = math.floor((up + LIMIT_TOL - v0) / TWO_PI)
        if kmax < 0:
            out.append(None)
            continue
        v = v0 + TWO_PI * min(max(round((r - v0) / TWO_PI), 0), kmax)
        out.append((v, min(max(v, lo), up)))
    return out


def _alternative_costs(
    fn: SwivelFunctions,
    tab: LimitTables,
    Sp: np.ndarray,
    seed: np.ndarray,
    w: np.ndarray | None,
    c4: np.ndarray,
    slopes: bool = False,
) -> tuple[np.ndarray, ...]:
    """Costs (8, K) of the flip patterns at the K swivels Sp, and the per-alternative arrays behind them.

    Returns (cost, X, E): X (6, 2, K) per joint of _J6 and alternative the lowest copy >= lower - tol,
    minus (lower - tol) (feasible where X <= width6); E (6, 2, K) the in-limit copy nearest the seed,
    minus the seed. ``w``: weights (7,), None for all ones. ``c4`` (8, 1): theta4's share of each
    pattern's cost (BIG where out of limits). The eight patterns share their joints' alternatives, so the
    per-alternative work is done once (12 rows) and the patterns are one matrix product. ``slopes``: also
    return D (8, K), each pattern's d(cost)/ds (meaningful where the cost is below BIG; at a critical
    swivel one side's, and huge where theta2 or theta6 is exactly 0 at a sample).
    """
    K = Sp.shape[0]
    CS = np.empty((3, K))
    CS[0] = 1.0
    np.cos(Sp, out=CS[1])
    np.sin(Sp, out=CS[2])
    W = np.empty((22, K))
    np.dot(fn.KV, CS, out=W[:20])  # X1' .. Z6' (rows 0..9), then X1, X3, X5, X7, Y1, Y3, Y5, Y7, Z2, Z6
    V = W[10:]
    if slopes:
        R = np.hypot(V[0:4], V[4:8])  # |(X, Y)| of the pivot joints
        V[10:12] = R[0::2]  # rho2 = |(X1, Y1)|, rho6 = |(X5, Y5)|
    else:
        np.hypot(V[0:3:2], V[4:7:2], out=V[10:12])
    T = np.dot(tab.rot, V)
    X = np.arctan2(T[12:], T[:12])  # (the alternative - (lower - tol)) mod 2 pi, minus pi
    X += PI
    X = X.reshape(6, 2, K)
    if fn.deg_shoulder:  # theta1 = 0 by convention
        X[0] = np.array(tab.fixed6[0])[:, None]
    if fn.deg_wrist:
        X[2] = np.array(tab.fixed6[4])[:, None]
    E = X + (tab.lot6v - seed[_J6A])[:, None, None]
    if tab.wide6 is not None:  # more copies fit: the one nearest the seed
        rw = tab.wide6
        Ew = E[rw]
        k = np.rint(Ew * -INV_2PI)
        np.maximum(k, 0.0, out=k)
        np.minimum(k, np.floor((tab.width6w - X[rw]) * INV_2PI), out=k)
        k *= TWO_PI
        Ew += k
        if not isinstance(rw, slice):
            E[rw] = Ew
    C = E * E
    if w is not None:
        C *= w[_J6A][:, None, None]
    np.copyto(C, BIG, where=X > tab.width6)
    cost = np.dot(_SEL6, C.reshape(12, K))
    cost += c4
    if not slopes:
        return cost, X, E
    # the joints' rates: pivot (X Y' - Y X') / (X^2 + Y^2), hinge -Z' / rho (the minus in _SEL6_SLOPE). The
    # tiny terms keep an exactly singular sample finite: a huge rate, below BIG, no warning
    Vd = W[:10]
    Q = R * R
    Q += 1e-24
    G = np.empty((6, K))
    N = V[0:4] * Vd[4:8]
    N -= V[4:8] * Vd[0:4]
    np.divide(N, Q, out=G[:4])
    np.divide(Vd[8:10], R[0::2] + 1e-12, out=G[4:])
    if fn.deg_shoulder:  # theta1 and theta2 constant on the circle
        G[0] = G[4] = 0.0
    if fn.deg_wrist:
        G[2] = G[5] = 0.0
    Dl = E * G[:, None, :]
    if w is not None:
        Dl *= w[_J6A][:, None, None]
    return cost, X, E, np.dot(_SEL6_SLOPE, Dl.reshape(12, K))


def _tangent_drop(g: np.ndarray, hl: np.ndarray, hr: np.ndarray) -> np.ndarray:
    """How far the tangent at a sample (slope g) falls across the gap it points down into: g hl where the
    cost rises (the left gap hl), -g hr where it falls (the right gap hr)."""
    drop = np.maximum(g, 0.0) * hl
    drop -= np.minimum(g, 0.0) * hr
    return drop


def _candidates(
    gaps: np.ndarray, cost: np.ndarray, limit: float | None = None, slope: np.ndarray | None = None
) -> tuple[list[tuple[float, int, int, float]], float]:
    """Candidate basins: each pattern's sample-wise local minima, as (bound, pattern, sample, offset).

    ``cost`` (8, M + 2) padded as the samples of :func:`_sample_swivels`. A parabola through a candidate
    and its two neighbours gives the start of its refinement (the vertex, ``offset`` rad from the sample)
    and a bound on how much lower the basin may be (DEPTH_MARGIN times the vertex depth, or where the gaps
    are uneven the rise across the wide one, if more); only candidates
    whose bound is at most ``limit`` (default: the best sample) are returned, sorted by bound, with the
    limit used. ``slope`` (8, M + 2): the cost's d/ds at the samples; the bound then also allows the
    basin to lie as low as the tangent at the sample reaches across the gap it points down into (a
    lower bound wherever the cost is convex on that arc, which the parabola is not: near a hinge passing
    close to 0 the cost falls steeply beside a sample and the parabola through three samples is far too
    shallow). With d0, d1 the slopes left and
    right of the sample and hl, hr the gaps, the vertex lies -(d0 hr + d1 hl) / (2 (d1 - d0)) from the
    sample and (d0 hr + d1 hl)^2 / (4 (d1 - d0)(hl + hr)) deep.

    The table is worked on flattened (the rows one after another) so that every numpy call runs on
    contiguous 1-D data; positions next to a row boundary are padding and are skipped.
    """
    K = cost.shape[1]
    cf = cost.ravel()
    g = np.empty((8, K))
    g[:, :-1] = gaps
    g[:, -1] = 1.0  # between one row's end and the next row's start: unused
    gf = g.ravel()[:-1]  # gf[k]: the gap from flat position k to k + 1
    sl = (cf[1:] - cf[:-1]) / gf
    d0 = sl[:-1]  # at flat positions 1 .. L - 2
    d1 = sl[1:]
    fin = cf < 0.5 * BIG
    hl = gf[:-1]
    hr = gf[1:]
    num = d0 * hr
    num += d1 * hl
    curv = d1 - d0  # >= 0 at a local minimum; 0 only where flat (no vertex)
    # (cost <= 8 BIG and gaps > MERGE_TOL keep num^2 below 1e88: the floor 1e-200 cannot overflow, and
    # at a local minimum a denominator that small means d0 = d1 = 0, so num = 0 too)
    depth = num * num
    depth /= np.maximum(curv * (hl + hr), 1e-200)
    nb = fin[:-2] & fin[2:]
    depth *= nb  # a parabola only through feasible neighbours
    f0 = cf[1:-1]
    lb = f0 - (0.25 * DEPTH_MARGIN) * depth
    # uneven gaps (one more than UNEVEN times the other): the parabola says little about the wide side,
    # where the basin may lie below the sample by as much as the cost rises across that gap (found: a
    # steep descent beside a swivel where theta2 passes near 0, then flat); the bound allows that too
    rise = np.where(hl > UNEVEN * hr, cf[:-2], np.where(hr > UNEVEN * hl, cf[2:], f0))
    rise -= f0
    rise *= nb
    np.minimum(lb, f0 - rise, out=lb)
    if slope is not None:
        # the tangent across the gap the sample's slope points down into: f0 - |g| h (feasible samples)
        # (the slopes stay below 1e26 even at an exact singularity, so an infeasible sample stays above
        # BIG / 2; fmin: a NaN slope leaves the parabola's bound)
        np.fmin(lb, f0 - _tangent_drop(slope.ravel()[1:-1], hl, hr), out=lb)
    if limit is None:
        fbest = float(cf.min())
        if fbest >= 0.5 * BIG:
            return [], fbest
        limit = fbest + 1e-12 * (1.0 + fbest)
    # (lb <= limit < BIG / 2 also excludes an infeasible sample: its depth is 0 or it is no minimum)
    keep = (d0 <= 0.0) & (d1 >= 0.0) & (lb <= limit)
    out = []
    for k in np.flatnonzero(keep).tolist():
        b, t = divmod(k + 1, K)
        if 1 <= t < K - 1:
            dk = depth[k]
            out.append((float(lb[k]), b, t - 1, -0.5 * float(num[k]) / float(curv[k]) if dk > 0.0 else 0.0))
    out.sort()
    return out, limit


def _monotone_bound(e0: np.ndarray, e1: np.ndarray, w6: np.ndarray | None) -> np.ndarray:
    """Per joint, a lower bound of the cost of a joint that is monotone between two swivels where it is
    ``e0`` and ``e1`` away from the seed (rad, joints along axis 0): at least the smaller end's square
    (weighted), or nothing where the seed lies between the ends."""
    lo = np.minimum(e0 * e0, e1 * e1)
    np.copyto(lo, 0.0, where=e0 * e1 <= 0.0)
    if w6 is not None:
        lo *= w6.reshape((6,) + (1,) * (lo.ndim - 1))
    return lo


def _unrefined_arcs(
    fn: SwivelFunctions,
    tab: LimitTables,
    seed: np.ndarray,
    w: np.ndarray | None,
    c4: np.ndarray,
    Sp: np.ndarray,
    E: np.ndarray,
    cost: np.ndarray,
    flag: np.ndarray,
    gaps: np.ndarray,
    done: set[tuple[int, int]],
    limit: float,
    rounds: int = ARC_ROUNDS,
) -> list[tuple[float, int, int, float]]:
    """Arcs that may still hold a solution cheaper than ``limit``, as candidates (bound, pattern, left
    sample, offset from it): branch and bound on the arcs between neighbouring samples.

    The bound is rigorous: no joint of any pattern is stationary or crosses a limit inside an arc
    (each such swivel is a critical sample), so on an arc (and on any part of it) each joint lies
    between its end values (:func:`_monotone_bound`). Arcs that a refinement covered (a candidate
    (b, i) refined from sample i covers the arcs on both sides of it) are left out; the others whose
    bound is below ``limit`` are halved ``rounds`` times (all at once: one evaluation of the joint
    functions per round), keeping the halves whose bound still is, and a half whose middle costs
    less than ``limit`` is a candidate at once. Arguments: :func:`_alternative_costs`' arrays at the
    padded samples ``Sp`` and the rest as :func:`nearest` has them.
    """
    M = len(flag)
    w6 = None if w is None else w[_J6A]
    # arc t runs from sample t to sample t + 1 (mod M)
    lo = _monotone_bound(E[:, :, 1 : M + 1], E[:, :, 2 : M + 2], w6)
    lb = np.dot(_SEL6, lo.reshape(12, M))
    lb += c4
    # an arc is feasible for a pattern where its plain end is (an arc has no critical swivel inside)
    plain = np.where(flag, np.arange(2, M + 2), np.arange(1, M + 1))
    np.copyto(lb, math.inf, where=cost[:, plain] >= 0.5 * BIG)
    for b, i in done:  # a refinement from sample i covered arc i - 1 (from sample i - 1) and arc i
        lb[b, i] = lb[b, i - 1] = math.inf
    bs, ts = np.nonzero(lb < limit)
    if not len(bs):
        return []
    a6 = ALT_INDEX[bs][:, _J6A]  # (n, 6) each arc's alternative per joint
    rows = np.arange(6)
    ea = E[rows, a6, ts[:, None] + 1].T  # (6, n) at the arc's start and end
    ec = E[rows, a6, ts[:, None] + 2].T
    sa = Sp[ts + 1]
    sc = sa + gaps[ts + 1]
    out: list[tuple[float, int, int, float]] = []
    for _ in range(rounds):
        sm = 0.5 * (sa + sc)
        cm, _, Em = _alternative_costs(fn, tab, sm, seed, w, c4)
        n = len(sm)
        em = Em[rows, a6, np.arange(n)[:, None]].T
        fm = cm[bs, np.arange(n)]
        for k in np.nonzero(fm < limit)[0].tolist():  # a cheaper point: refine from it
            out.append((float(fm[k]), int(bs[k]), int(ts[k]), float(sm[k] - Sp[ts[k] + 1])))
        c4b = c4[bs, 0]
        lbl = _monotone_bound(ea, em, w6).sum(axis=0) + c4b
        lbr = _monotone_bound(em, ec, w6).sum(axis=0) + c4b
        go_l, go_r = (lbl < limit) & (fm >= limit), (lbr < limit) & (fm >= limit)
        if not (go_l.any() or go_r.any()):
            break
        bs = np.concatenate((bs[go_l], bs[go_r]))
        ts = np.concatenate((ts[go_l], ts[go_r]))
        a6 = np.concatenate((a6[go_l], a6[go_r]))
        ea, ec = np.concatenate((ea[:, go_l], em[:, go_r]), 1), np.concatenate((em[:, go_l], ec[:, go_r]), 1)
        sa, sc = np.concatenate((sa[go_l], sm[go_r])), np.concatenate((sm[go_l], sc[go_r]))
        bound = np.concatenate((lbl[go_l], lbr[go_r]))
    else:
        # still open after the last round: refine from each remaining part's middle
        for k in range(len(sa)):
            mid_k = 0.5 * (sa[k] + sc[k]) - Sp[ts[k] + 1]
            out.append((float(bound[k]), int(bs[k]), int(ts[k]), float(mid_k)))
    out.sort()
    return out


def nearest(
    fn: SwivelFunctions,
    tab: LimitTables,
    seed: np.ndarray,
    w: np.ndarray,
    s_seed: float | None = None,
    deadline: float | None = None,
    realise: Realise | None = None,
    exhaustive: bool = False,
) -> NearestResult:
    """The swivel and flip pattern of the in-limit solution nearest the seed (weighted squared distance).

    Global over every pattern, 2*pi copy and feasible interval (ends included), see the module docstring.
    ``s_seed``: the seed's own swivel, sampled too. ``deadline``: a ``time.perf_counter()`` value after
    which no further candidate is refined (``timed_out`` set; the best one so far is returned).

    ``realise``: turns a refined candidate that beats the best so far into a solution as ``ik`` computes
    it. The closed-form functions and ``ik`` agree to round-off except at a singular swivel (theta2 or
    theta6 at 0: ``ik`` takes theta1 = 0 there, the functions a limit from one side) and within the 1e-10
    rad limit tolerance; the realised cost, not the predicted one, then bounds the candidates still to
    refine, so a prediction that cannot be realised never prunes a basin that can.

    The candidate basins are the samples' local minima, each allowed a parabolic depth below its sample
    and the reach of its tangent across the gap it points down into (:func:`_candidates`). Both are
    estimates: where a hinge passes near 0 the pivot joints beside it turn fast between two samples,
    and a basin can lie deeper than either allows (measured: 2 poses in 480000, at most 1.9e-2 rad^2).
    ``exhaustive``: then also bound every arc between two samples rigorously (:func:`_unrefined_arcs`)
    and refine each arc that may still hold a nearer solution; 2-3 times the time.
    """
    seed_l = seed.tolist()
    w_l = w.tolist()
    Sp, flag, gaps = _sample_swivels(fn, tab, s_seed, seed_l)
    M = len(flag)
    t4c = _theta4_copies(fn, tab, seed_l)
    c4a = [BIG if v is None else w_l[3] * (v[0] - seed_l[3]) ** 2 for v in t4c]
    c4 = np.array([c4a[0], c4a[0], c4a[1], c4a[1]] * 2).reshape(8, 1)  # theta4 follows the f4 bit
    unit = w_l.count(1.0) == 7
    cost, X, E, D = _alternative_costs(fn, tab, Sp, seed, None if unit else w, c4, slopes=True)
    cands, limit = _candidates(gaps, cost, slope=D)
    lo, up = tab.lo_l, tab.up_l
    lot6 = tab.lot6_l

    def refine(b: int, i: int, dx: float) -> tuple[float, float, int]:
        """Candidate (pattern b, sample i) refined in its feasible bracket: (swivel, cost, evaluations)."""
        alt = _ALT_L[b]
        s0, f0 = float(Sp[i + 1]), float(cost[b, i + 1])
        ei = E[:, :, i + 1].tolist()
        Vi = [0.0] * 7
        for k, j in enumerate(_J6):
            Vi[j] = min(max(ei[k][alt[j]] + seed_l[j], lo[j]), up[j])
        Vi[3] = t4c[alt[3]][1]  # type: ignore[index]  (feasible: its cost is below BIG)
        # bracket: the arc to a neighbour belongs to this candidate if its copies Vi are in the limits
        # at the arc's plain end (an arc has no critical swivel inside); Sp is padded: sample i at i + 1
        a = s0 - float(gaps[i])
        c = s0 + float(gaps[i + 1])
        for col, nb in ((i, (i - 1) % M), (i + 2, (i + 1) % M)):
            if flag[nb] and not flag[i]:
                continue
            xn = X[:, :, col].tolist()
            for k, j in enumerate(_J6):
                av = xn[k][alt[j]] + lot6[k]
                v = av + TWO_PI * round((Vi[j] - av) * INV_2PI)
                if v < lo[j] - LIMIT_TOL or v > up[j] + LIMIT_TOL:
                    if col == i:
                        a = s0
                    else:
                        c = s0
                    break
        if a < c:
            xv = s0 + dx
            sr, fr, ne = _refine(fn, b, xv if a < xv < c else s0, Vi, a, c, seed_l, w_l, tab)
            if fr < f0:
                return sr, fr, ne
            return s0, f0, ne
        return s0, f0, 0

    best_f, best_s, best_b, best_q = math.inf, None, -1, None
    pred_s, pred_b, pred_f = None, -1, math.inf  # the best prediction, when nothing could be realised
    refined = nev = 0
    timed_out = False
    done: set[tuple[int, int]] = set()

    def take(b: int, i: int, dx: float) -> None:
        """Refine candidate (pattern b, sample i); keep it if it beats the best so far."""
        nonlocal best_f, best_s, best_b, best_q, pred_s, pred_b, pred_f, refined, nev
        sx, fx, ne = refine(b, i, dx)
        nev += ne
        refined += 1
        done.add((b, i))
        sx -= TWO_PI * math.floor((sx + PI) * INV_2PI)
        if fx < pred_f:
            pred_s, pred_b, pred_f = sx, b, fx
        if fx < best_f:
            if realise is None:
                best_f, best_s, best_b = fx, sx, b
            else:
                r = realise(sx, b, fx)
                if r is not None and r[3] < best_f:
                    best_q, best_s, best_b, best_f = r

    def run(cands: list[tuple[float, int, int, float]], slack: float, arcs: bool = False) -> bool:
        """Take the candidates, lowest bound first, while their bound is below the best so far (plus
        ``slack`` relative); ``arcs``: skip an arc a refinement has covered meanwhile. False if the
        deadline cut it short."""
        for lb, b, i, dx in cands:
            if lb > best_f + slack * (1.0 + best_f):
                break
            if arcs and ((b, i) in done or (b, (i + 1) % M) in done):
                continue
            if deadline is not None and refined > 0 and time.perf_counter() > deadline:
                return False
            take(b, i, dx)
        return True

    while cands:
        if not run(cands, 1e-12):
            timed_out = True
            break
        if best_f <= limit:
            break
        # the best realised cost is above the bound the candidates were cut at (a sample's prediction
        # that ik could not realise, at a singular swivel): the candidates below the realised cost too
        limit = best_f + 1e-12 * (1.0 + best_f) if best_f < math.inf else 0.5 * BIG
        cands = [cd for cd in _candidates(gaps, cost, limit, D)[0] if (cd[1], cd[2]) not in done]
    if exhaustive and not timed_out:
        # the parabolas' depth is an estimate: every arc whose rigorous bound is still below the best is
        # refined too
        arcs = _unrefined_arcs(fn, tab, seed, None if unit else w, c4, Sp, E, cost, flag, gaps, done,
                               best_f - ARC_GAIN * (1.0 + best_f))
        timed_out = not run(arcs, -ARC_GAIN, arcs=True)
    if best_s is None:
        return NearestResult(pred_s, pred_b, pred_f, 8 * M, refined, nev, timed_out)
    return NearestResult(best_s, best_b, best_f, 8 * M, refined, nev, timed_out, best_q)


# ---------------------------------------------------------------------------------------------------
# Batched nearest: the same search vectorised over poses (and over candidates in the refinement)
# ---------------------------------------------------------------------------------------------------
NEWTON_MAX = 40  # Newton / bisection steps of the batched refinement (each candidate stops when done)
BATCH_CANDIDATES = 64  # at most this many candidate basins refined per pose (lowest bounds first)


def _roots_np(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`roots` for E (..., 3): (s_plus, s_minus) of shape (...), NaN where there is none."""
    e1, e2 = E[..., 1], E[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = -E[..., 0] / np.sqrt(e1 * e1 + e2 * e2)
        r = np.where(np.abs(r) <= 1.0 + TANGENT_TOL, r, np.nan)
        phi = np.arctan2(e2, e1)
        d = np.arccos(np.clip(r, -1.0, 1.0))
    return phi + d, phi - d


def _angles_np(
    K: np.ndarray, t4: np.ndarray, deg_sh: np.ndarray, deg_wr: np.ndarray, S: np.ndarray
) -> np.ndarray:
    """(m, 7, M) base-pattern angles at the swivels S (m, M) of m poses with coefficients K (m, 10, 3)."""
    CS = np.empty((S.shape[0], 3, S.shape[1]))
    CS[:, 0] = 1.0
    np.cos(S, out=CS[:, 1])
    np.sin(S, out=CS[:, 2])
    P = np.matmul(K, CS)  # (m, 10, M)
    th = np.empty((S.shape[0], 7, S.shape[1]))
    th[:, 0::2] = np.arctan2(P[:, 4:8], P[:, 0:4])
    XY = P[:, 0:7:2]
    XY = XY * XY
    th[:, 1::4] = np.arctan2(np.sqrt(XY[:, 0:2] + XY[:, 2:4]), P[:, 8:10])
    th[:, 3] = t4[:, None]
    if deg_sh.any():
        th[deg_sh, 0] = 0.0
    if deg_wr.any():
        th[deg_wr, 4] = 0.0
    return th


def _fgh_np(
    x: np.ndarray,
    K: np.ndarray,
    t4: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    sg: np.ndarray,
    sh: np.ndarray,
    Vref: np.ndarray,
    seed: np.ndarray,
    w: np.ndarray,
    tab: LimitTables,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_fgh` for n candidates at once: x (n,), K (n, 10, 3), sg / sh / Vref / seed (n, 7)."""
    c, sn = np.cos(x)[:, None], np.sin(x)[:, None]
    k0, k1, k2 = K[:, :, 0], K[:, :, 1], K[:, :, 2]
    P = k0 + k1 * c + k2 * sn
    Pd = k2 * c - k1 * sn
    Pdd = k0 - P
    X, Y, Xd, Yd, Xdd, Ydd = P[:, 0:4], P[:, 4:8], Pd[:, 0:4], Pd[:, 4:8], Pdd[:, 0:4], Pdd[:, 4:8]
    th = np.empty((len(x), 7))
    g = np.zeros((len(x), 7))
    h = np.zeros((len(x), 7))
    Q = X * X + Y * Y
    N = X * Yd - Y * Xd
    with np.errstate(divide="ignore", invalid="ignore"):
        th[:, 0::2] = np.arctan2(Y, X)
        g[:, 0::2] = np.where(Q > 0.0, N / Q, 0.0)
        h[:, 0::2] = np.where(Q > 0.0, ((X * Ydd - Y * Xdd) * Q - 2.0 * N * (X * Xd + Y * Yd)) / (Q * Q), 0.0)
        rho = np.sqrt(Q[:, 0::2])  # joints 1 and 5: |(X, Y)|
        Z, Zd, Zdd = P[:, 8:10], Pd[:, 8:10], Pdd[:, 8:10]
        th[:, 1::4] = np.arctan2(rho, Z)
        live = rho > DEGEN_SIN
        g[:, 1::4] = np.where(live, -Zd / rho, 0.0)
        h[:, 1::4] = np.where(live, -(Zdd * rho * rho + Z * Zd * Zd) / (rho * rho * rho), 0.0)
    th[:, 3] = t4
    for dmask, jp, jh in ((deg_sh, 0, 1), (deg_wr, 4, 5)):
        if dmask.any():
            th[dmask, jp] = 0.0
            g[dmask, jp] = h[dmask, jp] = g[dmask, jh] = h[dmask, jh] = 0.0
    a = th * sg + sh
    V = a + TWO_PI * np.rint((Vref - a) * INV_2PI)
    out = ((V < tab.lower - LIMIT_TOL) | (V > tab.upper + LIMIT_TOL)).any(axis=1)
    V = np.clip(V, tab.lower, tab.upper)
    e = V - seed
    gs = g * sg
    f = (w * e * e).sum(axis=1)
    d = 2.0 * (w * e * gs).sum(axis=1)
    dd = 2.0 * (w * (gs * gs + e * h * sg)).sum(axis=1)
    f[out] = np.inf
    return f, d, dd, V


def _critical_np(
    K: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    tab: LimitTables,
    seeds: np.ndarray | None,
    directions: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Critical swivels of m poses, vectorised: (crit (m, C) sorted and de-duplicated, NaN-padded at the
    end; mids (m, C) the mid points of the arcs between neighbouring critical swivels (circular), NaN
    where none; equal-angle sampling roots (m, D) NaN where none, empty without ``directions``)."""
    m = K.shape[0]
    X, Y = K[:, 0:4], K[:, 4:8]
    stat = np.stack(
        [
            X[..., 1] * Y[..., 2] - X[..., 2] * Y[..., 1],
            X[..., 0] * Y[..., 2] - Y[..., 0] * X[..., 2],
            Y[..., 0] * X[..., 1] - X[..., 0] * Y[..., 1],
        ],
        axis=-1,
    )  # (m, 4, 3)
    anti = []  # joints with several in-limit copies switch copy opposite the seed
    anti_owner = []
    for j in tab.wide_l if seeds is not None else []:
        L = seeds[:, j] + PI
        sl, cl = np.sin(L)[:, None], np.cos(L)[:, None]
        if j % 2 == 0:
            anti.append(cl * K[:, 4 + j // 2] - sl * K[:, j // 2])
            anti_owner.append(j // 2)
        else:
            row = K[:, 8 + j // 4].copy()
            row[:, 0] -= cl[:, 0]
            anti.append(row)
            anti_owner.append(-1)
    parts = [stat] + ([np.stack(anti, axis=1)] if anti else [])
    Ec = np.concatenate(parts + [np.einsum("rk,mkc->mrc", tab.Lc, K) + tab.Cc], axis=1)
    owner_c = np.concatenate([np.arange(4), np.array(anti_owner, dtype=int), tab.owner_c])
    Ed = np.einsum("rk,mkc->mrc", tab.Ld, K) if directions else np.empty((m, 0, 3))
    for dmask, p in ((deg_sh, 0), (deg_wr, 2)):  # theta1 (theta5) constant 0: no rows for it
        if dmask.any():
            Ec[np.ix_(dmask, owner_c == p)] = np.nan
            if directions:
                Ed[np.ix_(dmask, tab.owner_d == p)] = np.nan
    rp, rm = _roots_np(np.concatenate([Ec, Ed], axis=1))
    nc = Ec.shape[1]
    z1, z2 = K[:, 8:10, 1], K[:, 8:10, 2]
    se = np.where(z1 * z1 + z2 * z2 > 1e-30, np.arctan2(z2, z1), np.nan)
    crit = np.sort(wrap(np.concatenate([rp[:, :nc], rm[:, :nc], se, se + PI], axis=1)), axis=1)
    dup = np.diff(crit, axis=1) <= MERGE_TOL
    if dup.any():
        crit[:, 1:][dup] = np.nan
        crit = np.sort(crit, axis=1)
    ncrit = (crit == crit).sum(axis=1)
    nxt = np.concatenate([crit[:, 1:], crit[:, :1]], axis=1)
    has = ncrit > 0
    last = np.maximum(ncrit - 1, 0)
    nxt[np.arange(m)[has], last[has]] = crit[has, 0] + TWO_PI
    mids = wrap(0.5 * (crit + nxt))
    return crit, mids, np.concatenate([rp[:, nc:], rm[:, nc:]], axis=1)


def feasible_measure_batch(
    K: np.ndarray, t4: np.ndarray, deg_sh: np.ndarray, deg_wr: np.ndarray, tab: LimitTables
) -> tuple[np.ndarray, np.ndarray]:
    """For m reachable poses: (measure of the feasible swivel set, union over the 8 patterns, rad (m,);
    any in-limit solution at all (m,) bool, which also counts isolated feasible swivels)."""
    m = K.shape[0]
    crit, mids, _ = _critical_np(K, deg_sh, deg_wr, tab, None, directions=False)
    ncrit = (crit == crit).sum(axis=1)
    none = ncrit == 0  # no critical swivel: the whole circle decides at one point
    mids = np.where(none[:, None] & (np.arange(crit.shape[1]) == 0), 0.0, mids)
    S = np.concatenate([mids, crit], axis=1)
    valid = S == S
    S = np.where(valid, S, 0.0)
    th = _angles_np(K, t4, deg_sh, deg_wr, S)
    Xa = th[:, :, None, :] * tab.sign3 + tab.shift_lot
    Xm = Xa - TWO_PI * np.floor(Xa * INV_2PI)
    bad = (Xm > tab.width3).reshape(m, 14, -1).astype(float)
    ok = (np.einsum("bk,mkn->mbn", _SEL, bad) < 0.5).any(axis=1) & valid  # (m, P): some pattern feasible
    C = crit.shape[1]
    nxt = np.concatenate([crit[:, 1:], crit[:, :1]], axis=1)
    last = np.maximum(ncrit - 1, 0)
    rows = np.nonzero(~none)[0]
    nxt[rows, last[rows]] = crit[rows, 0] + TWO_PI
    arc = np.where(crit == crit, nxt - crit, 0.0)
    width = np.where(ok[:, :C], arc, 0.0).sum(axis=1)
    width = np.where(none, np.where(ok[:, 0], TWO_PI, 0.0), width)
    return width, ok.any(axis=1)


def _theta4_batch(
    t4: np.ndarray, tab: LimitTables, seeds: np.ndarray, w3: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_theta4_copies` for n poses: (V4 (n, 2) clipped copies of (t4, -t4) nearest the seeds (NaN if
    out of limits), c4 (8, n, 1): theta4's share of each pattern's cost, BIG where out of limits)."""
    lo, up = tab.lo_l[3], tab.up_l[3]
    a = np.stack([t4, -t4], axis=1)
    v0 = (lo - LIMIT_TOL) + np.remainder(a - (lo - LIMIT_TOL), TWO_PI)
    kmax = np.floor((up + LIMIT_TOL - v0) * INV_2PI)
    k = np.minimum(np.maximum(np.rint((seeds[:, 3:4] - v0) * INV_2PI), 0.0), kmax)
    v = v0 + TWO_PI * k
    c = np.where(kmax >= 0.0, w3 * (v - seeds[:, 3:4]) ** 2, BIG)
    V4 = np.where(kmax >= 0.0, np.clip(v, lo, up), np.nan)
    return V4, c[:, _F4].T[:, :, None]


_F4 = np.array([(b >> 1) & 1 for b in range(8)])  # theta4's alternative in pattern b (the f4 bit)
_B_F2 = np.array([(b >> 2) & 1 for b in range(8)])
_B_F6 = np.array([b & 1 for b in range(8)])


def _sample_swivels_batch(
    Ka: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    tab: LimitTables,
    seeds: np.ndarray,
    s_seeds: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_sample_swivels` for n poses at once, the same samples: (Sp, flag, gaps, first, unused, odd).

    A pose's M samples sit right-aligned in its row of Sp (n, W = N + 2), N the most any pose can have:
    columns ``first - 1`` (S[M - 1], the neighbour across pi) to W - 1 (S[0] again), S[0] at ``first``;
    ``unused`` (n, W) marks the columns before. ``flag`` (n, W) critical, ``gaps`` (n, W - 1) from each
    column to the next (2 pi added across pi). ``odd``: poses to solve one by one (a root wrapped onto pi).
    """
    n = Ka.shape[0]
    X, Y = Ka[:, 0:4], Ka[:, 4:8]
    rows = [
        np.stack(
            [
                X[..., 1] * Y[..., 2] - X[..., 2] * Y[..., 1],
                X[..., 0] * Y[..., 2] - Y[..., 0] * X[..., 2],
                Y[..., 0] * X[..., 1] - X[..., 0] * Y[..., 1],
            ],
            axis=-1,
        )
    ]  # where each pivot joint is stationary
    for j in tab.wide_l:  # a joint with several in-limit copies switches copy opposite the seed
        L = seeds[:, j] + PI
        sl, cl = np.sin(L)[:, None], np.cos(L)[:, None]
        if j % 2 == 0:
            rows.append((cl * Ka[:, 4 + j // 2] - sl * Ka[:, j // 2])[:, None])
        else:
            r = Ka[:, 8 + j // 4].copy()
            r[:, 0] -= cl[:, 0]
            rows.append(r[:, None])
    rows.append(np.matmul(tab.GT.T, Ka))  # limit and equal-angle rows
    E = np.concatenate(rows, axis=1)  # (n, R, 3)
    # hinge extremes (pre-wrap: se + pi and se give se and its antipode), and the equal-angle rows that
    # would only repeat them (and the stationary points) where the hinge stays away from 0 and pi
    z0, z1, z2 = Ka[:, 8:10, 0], Ka[:, 8:10, 1], Ka[:, 8:10, 2]
    zz = z1 * z1 + z2 * z2
    has = zz > 1e-30
    se = np.where(has, np.arctan2(z2, z1), np.nan)
    regular = has & (np.abs(z0) + np.sqrt(zz) < 1.0 - 1e-6)
    for h in (0, 1):
        r0, r1 = tab.repeat_cols[h]
        E[regular[:, h], r0:r1, 0] = np.inf
    for q, j in enumerate(tab.wide_l):  # an anti-seed row on an equal-angle row: drop one of the two
        if j % 2:
            continue
        p = j // 2
        kk = (seeds[:, j] + PI) * (DIRECTIONS / PI)
        hit = np.abs(kk - np.rint(kk)) < 1e-12
        if hit.any():
            kr = np.rint(kk).astype(int) % DIRECTIONS
            for i in np.nonzero(hit)[0].tolist():
                k = int(kr[i])
                if p in (1, 2) and k in (0, DIRECTIONS // 2) and regular[i, p - 1]:
                    E[i, 4 + q, 0] = np.inf
                elif (p, k) in tab.dir_col:
                    E[i, tab.dir_col[(p, k)], 0] = np.inf
    for dmask, p in ((deg_sh, 0), (deg_wr, 2)):  # theta1 (theta5) 0 on the whole circle: no rows for it
        if dmask.any():
            E[np.ix_(dmask, tab.dead_cols[p], [0])] = np.inf
    e1, e2 = E[..., 1], E[..., 2]
    r = E[..., 0] / np.maximum(np.hypot(e1, e2), 1e-300)
    d = np.arccos(np.minimum(np.maximum(r, -1.0), 1.0))
    d[~(np.abs(r) <= 1.0 + TANGENT_TOL)] = np.nan
    phi = np.arctan2(e2, e1)
    nc, R = tab.n_crit_rows, E.shape[1]
    nd = R - nc
    C = 2 * nc + 4  # critical slots: roots +, roots -, extremes
    Sa = np.empty((n, 2 * C + 2 * nd + GRID + 1))
    np.add(phi[:, :nc], d[:, :nc], out=Sa[:, :nc])
    np.subtract(phi[:, :nc], d[:, :nc], out=Sa[:, nc : 2 * nc])
    Sa[:, 2 * nc : C : 2] = se + PI
    Sa[:, 2 * nc + 1 : C : 2] = se
    np.add(phi[:, nc:], d[:, nc:], out=Sa[:, 2 * C : 2 * C + nd])
    np.subtract(phi[:, nc:], d[:, nc:], out=Sa[:, 2 * C + nd : 2 * C + 2 * nd])
    Sa[:, :C] -= np.copysign(PI, Sa[:, :C])
    Sa[:, 2 * C : 2 * C + 2 * nd] -= np.copysign(PI, Sa[:, 2 * C : 2 * C + 2 * nd])
    c = Sa[:, :C]
    c.sort(axis=1)  # NaN last
    nv = C - np.isnan(c).sum(axis=1)
    mids = Sa[:, C : 2 * C]
    np.add(c[:, :-1], c[:, 1:], out=mids[:, :-1])
    mids *= 0.5
    mids[:, -1] = np.nan
    rows_i = np.nonzero(nv > 0)[0]
    last = nv[rows_i] - 1
    m = 0.5 * (c[rows_i, last] + c[rows_i, 0]) + PI  # the arc across pi, wrapped
    mids[rows_i, last] = np.where(m >= PI, m - TWO_PI, m)
    Sa[:, 2 * C + 2 * nd : -1] = _GRID_S
    t = (s_seeds + PI) * (GRID / TWO_PI)
    Sa[:, -1] = np.where(np.abs(t - np.rint(t)) * (TWO_PI / GRID) > MERGE_TOL, s_seeds, np.nan)
    Sa[:, -1] -= np.where(Sa[:, -1] >= PI, TWO_PI, 0.0)
    N = Sa.shape[1]
    crit = np.zeros(N, bool)
    crit[:C] = True
    # no root (NaN) last. The rows are runs of sorted samples (critical, mid points, grid): the stable sort
    # (a merge sort) takes half the time of the default quicksort there; ties are the same sample
    order = np.argsort(Sa, axis=1, kind="stable")
    S = np.take_along_axis(Sa, order, axis=1)
    flag = np.take_along_axis(crit, order.ravel()).reshape(n, N)
    # twins (closer than MERGE_TOL) are one sample, as in the scalar search: the critical member (an
    # exact root) stays; rare (touching roots, coincidences: a few poses in a thousand), so the pass is
    # simply repeated, on those poses' rows only (most chunks have one: sorting all rows again cost 5 %)
    tw = np.diff(S, axis=1) <= MERGE_TOL
    while tw.any():
        pi_, ji = np.nonzero(tw)
        drop = np.where(flag[pi_, ji + 1] & ~flag[pi_, ji], ji, ji + 1)
        Sa[pi_, order[pi_, drop]] = np.nan
        rr = np.unique(pi_)
        o2 = np.argsort(Sa[rr], axis=1, kind="stable")
        order[rr] = o2
        S[rr] = np.take_along_axis(Sa[rr], o2, axis=1)
        flag[rr] = crit[o2]
        tw = np.diff(S, axis=1) <= MERGE_TOL
    # every pose's M samples right-aligned in a row of N + 2, with its neighbours around the circle
    # (S[M - 1] in front, S[0] behind) as in the scalar search; the columns before them are unused
    M = N - np.isnan(S).sum(axis=1)
    # rows as wide as the most samples any pose of the chunk has, not as the most it could have (about
    # 130 instead of 155 columns on the test machine's poses: every later array operation is that much
    # shorter)
    N = max(int(M.max()), 1)
    W = N + 2
    first = (W - 1 - M)[:, None]  # column of S[0]
    src = (np.arange(W)[None, :] - first) % M[:, None]
    Sp = np.take_along_axis(S, src, axis=1)
    flag = np.take_along_axis(flag, src, axis=1)
    gaps = np.diff(Sp, axis=1)
    gaps[np.arange(n), first[:, 0] - 1] += TWO_PI  # S[M - 1] - 2 pi .. S[0]
    gaps[:, -1] += TWO_PI  # S[M - 1] .. S[0] + 2 pi
    unused = np.arange(W)[None, :] < first - 1
    gaps[unused[:, 1:]] = 1.0
    # solved one by one: a root wrapped onto pi (rare), and poses where a hinge passes within 1e-6 (in
    # cos) of 0 or pi, where the scalar search's solve tries the flip patterns that trade places at the
    # singular swivel (rare on uniform poses, every pose with theta2 or theta6 exactly 0)
    odd = (Sp[:, -2] >= PI) | (has & ~regular).any(axis=1)
    return Sp, flag, gaps, first[:, 0], unused, odd


class NearestWorkspace:
    """Arrays of the batched evaluation, allocated once per ``ik_nearest_batch`` call and reused by every
    chunk: a fresh temporary of a few hundred kB per operation cost a page fault per 4 kB page each time
    (glibc returns such blocks to the kernel when freed), which made the batch 2x slower on the 2-core
    test machine than the same arithmetic into reused arrays."""

    _ROWS = {"V": 12, "Vx": 12, "Vy": 12, "T1": 12, "T2": 12, "X": 12, "E": 12, "B": 12}
    _ROWS |= {"A": 2, "F": 2, "cost": 8, "t8": 8}

    def __init__(self, n: int, k: int) -> None:
        self.n, self.k = n, k
        self._buf = {
            name: np.empty(rows * n * k, bool if name == "B" else float) for name, rows in self._ROWS.items()
        }

    def view(self, name: str, n: int, k: int) -> np.ndarray:
        """Array ``name`` as (rows, n, k) for n poses of k samples (n, k at most the capacity): the head of
        its buffer, contiguous, so that every operation on it runs over one block."""
        rows = self._ROWS[name]
        return self._buf[name][: rows * n * k].reshape(rows, n, k)


def _alternative_costs_batch(
    K: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    tab: LimitTables,
    Sp: np.ndarray,
    seeds: np.ndarray,
    w: np.ndarray | None,
    c4: np.ndarray,
    unused: np.ndarray,
    ws: NearestWorkspace,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_alternative_costs` for n poses: cost (8, n, K), X and E (6, 2, n, K) at the swivels Sp (n, K),
    computed in the arrays of ``ws`` (valid until its next use).

    Alternative-major: the per-alternative constants are (12, 1, 1) columns and every operation runs over
    the trailing (n, K) block of all poses and samples; the turning of the (x, y) pairs is written out as
    gathers and scalings (a matrix product there went to BLAS threads, 20x slower on a busy machine).
    """
    n, Kn = Sp.shape
    V, Vx, Vy, T1, T2, X, E, B = (ws.view(a, n, Kn) for a in ("V", "Vx", "Vy", "T1", "T2", "X", "E", "B"))
    c = np.cos(Sp)
    s = np.sin(Sp)
    Kt = K.transpose(1, 2, 0)[:, :, :, None]  # (10, 3, n, 1)
    np.multiply(Kt[:, 1], c, out=V[:10])
    np.multiply(Kt[:, 2], s, out=T1[:10])
    V[:10] += T1[:10]
    V[:10] += Kt[:, 0]
    np.multiply(V[0:7:2], V[0:7:2], out=T1[:4])  # X1^2, X5^2, Y1^2, Y5^2
    np.add(T1[0:2], T1[2:4], out=V[10:12])
    np.sqrt(V[10:12], out=V[10:12])
    # the base alternative of each joint (even rows of X): its (x, y) pair turned, atan2 (the costliest
    # operation of the batch, so done for 6 rows, not 12)
    x6, y6, t6a, t6b = Vx[:6], Vy[:6], T1[:6], T2[:6]
    np.take(V, tab.rx0, axis=0, out=x6, mode="clip")
    np.take(V, tab.ry0, axis=0, out=y6, mode="clip")
    np.multiply(y6, tab.rs0, out=t6a)
    np.multiply(x6, tab.rs20, out=t6b)
    x6 *= tab.rc0
    x6 += t6a  # x of the turned pair
    y6 *= tab.rc20
    y6 -= t6b  # y
    Xb, Xf = X[0::2], X[1::2]
    np.arctan2(y6, x6, out=Xb)
    Xb += PI
    # the flipped alternatives from the base ones: pivot theta + pi, hinge -theta (see LimitTables)
    np.add(Xb[:4], PI, out=Xf[:4])
    np.subtract(tab.hinge_flip, Xb[4:], out=Xf[4:])
    # mod 2 pi of values in [0, 4 pi): one subtraction, exact there (Sterbenz), as fmod (3x slower)
    np.greater_equal(Xf, TWO_PI, out=B[:6])
    np.subtract(Xf, TWO_PI, out=Xf, where=B[:6])
    X4 = X.reshape(6, 2, n, Kn)
    if deg_sh.any():
        X4[0][:, deg_sh] = np.array(tab.fixed6[0])[:, None, None]
    if deg_wr.any():
        X4[2][:, deg_wr] = np.array(tab.fixed6[4])[:, None, None]
    E4 = E.reshape(X4.shape)
    np.add(X4, (tab.lot6v[:, None] - seeds[:, _J6A].T)[:, None, :, None], out=E4)
    if tab.wide6 is not None:
        rw = tab.wide6
        Ew = E4[rw]
        k = T1.reshape(X4.shape)[rw]
        np.multiply(Ew, -INV_2PI, out=k)
        np.rint(k, out=k)
        np.maximum(k, 0.0, out=k)
        kmax = T2.reshape(X4.shape)[rw]
        np.subtract(tab.width6w[..., None], X4[rw], out=kmax)
        kmax *= INV_2PI
        np.floor(kmax, out=kmax)
        np.minimum(k, kmax, out=k)
        k *= TWO_PI
        Ew += k
        if not isinstance(rw, slice):
            E4[rw] = Ew
    C = T2
    np.multiply(E, E, out=C)
    if w is not None:
        C *= np.repeat(w[_J6A], 2)[:, None, None]
    np.greater(X4, tab.width6[..., None], out=B.reshape(X4.shape))
    np.copyto(C, BIG, where=B)
    # the patterns (f2, f4, f6) as sums of their alternatives: theta1 and theta2 follow f2, theta3 f2 ^ f4,
    # theta5 f4 ^ f6, theta6 and theta7 f6 (rows 2 k + a of C: joint _J6[k], alternative a)
    A, F, cost, t8 = (ws.view(a, n, Kn) for a in ("A", "F", "cost", "t8"))
    np.add(C[0:2], C[8:10], out=A)
    np.add(C[6:8], C[10:12], out=F)
    np.take(A, _B_F2, axis=0, out=cost, mode="clip")
    np.take(C[2:4], _B_F2 ^ _F4, axis=0, out=t8, mode="clip")
    cost += t8
    np.take(C[4:6], _F4 ^ _B_F6, axis=0, out=t8, mode="clip")
    cost += t8
    np.take(F, _B_F6, axis=0, out=t8, mode="clip")
    cost += t8
    cost += c4
    np.copyto(cost, BIG, where=unused)
    return cost, X4, E4


def _slopes_batch(
    K: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    Sp: np.ndarray,
    E4: np.ndarray,
    w: np.ndarray | None,
    pose: np.ndarray,
    b: np.ndarray,
    t: np.ndarray,
) -> np.ndarray:
    """d(cost)/ds of pattern b at sample t of each pose (the slopes of :func:`_alternative_costs`, only at
    the given entries): K (m, 10, 3), Sp (m, K), E4 (6, 2, m, K) as :func:`_alternative_costs_batch`."""
    s = Sp[pose, t]
    L = len(pose)
    CS = np.empty((L, 3, 2))  # columns: (1, cos s, sin s) for the values, (0, -sin s, cos s) for the rates
    CS[:, 0, 0] = 1.0
    CS[:, 0, 1] = 0.0
    np.cos(s, out=CS[:, 1, 0])
    np.sin(s, out=CS[:, 2, 0])
    np.negative(CS[:, 2, 0], out=CS[:, 1, 1])
    CS[:, 2, 1] = CS[:, 1, 0]
    PP = np.matmul(K[pose], CS)  # (L, 10, 2): values, rates
    P, Pd = PP[:, :, 0], PP[:, :, 1]
    X, Y = P[:, 0:4], P[:, 4:8]
    Q = X * X + Y * Y
    G = np.empty((L, 6))
    G[:, :4] = (X * Pd[:, 4:8] - Y * Pd[:, 0:4]) / (Q + 1e-24)  # (the scalar search's guards)
    G[:, 4:] = Pd[:, 8:10] / (np.sqrt(Q[:, 0::2]) + 1e-12)  # -Z' / rho (joints 2 and 6), sign in _SLOPE_SIGN
    dsh, dwr = deg_sh[pose], deg_wr[pose]
    G[dsh, 0] = G[dsh, 4] = 0.0
    G[dwr, 2] = G[dwr, 5] = 0.0
    k6 = np.arange(6)[None, :]
    alt6 = ALT_INDEX[b][:, _J6A]
    D = E4[k6, alt6, pose[:, None], t[:, None]] * G * _SLOPE_SIGN[k6, alt6, 0]
    if w is not None:
        D *= w[_J6A]
    return D.sum(axis=1)


def _candidates_batch(
    gaps: np.ndarray, cost: np.ndarray, first: np.ndarray, slope_args: tuple | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_candidates` for n poses, cost (8, n, K): (pose, pattern, column, bound, vertex offset) of
    every candidate whose bound is at most its pose's best sample, sorted by pose and bound.

    The local minima are found on the whole table (flattened); the parabolas only at them (a few in a
    thousand entries), which keeps the full-size temporaries to two. ``slope_args``: the arguments of
    :func:`_slopes_batch` before (pose, b, t), for the tangent bound of :func:`_candidates` (computed at
    the local minima only).
    """
    _, n, Kn = cost.shape
    cf = cost.ravel()
    d = cf[1:] - cf[:-1]  # (the sign of a slope is the sign of the difference: gaps are positive)
    lmin = d[:-1] <= 0.0
    lmin &= d[1:] >= 0.0
    lmin &= cf[1:-1] < 0.5 * BIG
    k = np.flatnonzero(lmin) + 1
    b, rest = np.divmod(k, n * Kn)
    pose, t = np.divmod(rest, Kn)
    inside = (t >= first[pose]) & (t <= Kn - 2)  # a sample, not a neighbour copy or unused
    k, pose, b, t = k[inside], pose[inside], b[inside], t[inside]
    hl, hr = gaps[pose, t - 1], gaps[pose, t]
    fm, f0, fp = cf[k - 1], cf[k], cf[k + 1]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        d0, d1 = (f0 - fm) / hl, (fp - f0) / hr
        num = d0 * hr + d1 * hl
        curv = d1 - d0
        depth = num * num / np.maximum(curv * (hl + hr), 1e-200)
    nb = (fm < 0.5 * BIG) & (fp < 0.5 * BIG)
    depth = np.where(nb & np.isfinite(depth), depth, 0.0)
    lb = f0 - (0.25 * DEPTH_MARGIN) * depth
    # uneven gaps: the rise across the wide one too (see _candidates)
    rise = np.where(hl > UNEVEN * hr, fm, np.where(hr > UNEVEN * hl, fp, f0)) - f0
    lb = np.minimum(lb, f0 - np.where(nb, rise, 0.0))
    if slope_args is not None and len(k):
        lb = np.fmin(lb, f0 - _tangent_drop(_slopes_batch(*slope_args, pose, b, t), hl, hr))
    fbest = cost.min(axis=(0, 2))
    keep = lb <= (fbest + 1e-12 * (1.0 + fbest))[pose]
    pose, b, t, lb, depth, num, curv = (
        pose[keep],
        b[keep],
        t[keep],
        lb[keep],
        depth[keep],
        num[keep],
        curv[keep],
    )
    dx = np.where(depth > 0.0, -0.5 * num / np.where(depth > 0.0, curv, 1.0), 0.0)
    order = np.lexsort((lb, pose))
    return pose[order], b[order], t[order], lb[order], dx[order]


def nearest_batch(
    K: np.ndarray,
    t4: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    tab: LimitTables,
    seeds: np.ndarray,
    w: np.ndarray,
    s_seeds: np.ndarray,
    ws: NearestWorkspace | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`nearest` for m poses at once (all reachable): returns (swivel (m,) rad or NaN, pattern (m,)
    or -1, predicted cost (m,) rad^2 or inf, odd (m,): poses to solve one by one instead).

    K (m, 10, 3), t4 / deg_sh / deg_wr (m,), seeds (m, 7), s_seeds (m,); ``ws``: a workspace to reuse
    (see :class:`NearestWorkspace`). The same search as the scalar one, stage by stage on (pose, ...) arrays;
    the candidates of all poses are refined together.
    """
    m = K.shape[0]
    Ka = np.concatenate([K, np.broadcast_to([[[1.0, 0.0, 0.0]]], (m, 1, 3))], axis=1)
    Sp, flag, gaps, col0, unused, odd = _sample_swivels_batch(Ka, deg_sh, deg_wr, tab, seeds, s_seeds)
    V4, c4 = _theta4_batch(t4, tab, seeds, float(w[3]))
    unit = bool(np.all(w == 1.0))
    if ws is None or ws.k < Sp.shape[1] or ws.n < m:
        ws = NearestWorkspace(m, Sp.shape[1])
    cost, X, E = _alternative_costs_batch(
        K, deg_sh, deg_wr, tab, Sp, seeds, None if unit else w, c4, unused, ws
    )
    cm, cb, col, lb, dx = _candidates_batch(
        gaps, cost, col0, (K, deg_sh, deg_wr, Sp, E, None if unit else w)
    )
    best_s = np.full(m, np.nan)
    best_b = np.full(m, -1)
    best_f = np.full(m, np.inf)
    if len(cm) == 0:
        return best_s, best_b, best_f, odd
    # at most BATCH_CANDIDATES per pose, lowest bounds first (candidates are sorted by pose, then bound)
    first = np.concatenate([[True], cm[1:] != cm[:-1]])
    idx = np.arange(len(cm))
    rank = idx - np.maximum.accumulate(np.where(first, idx, 0))
    take = rank < BATCH_CANDIDATES
    cm, cb, col, dx = cm[take], cb[take], col[take], dx[take]
    n = len(cm)
    alt6 = ALT_INDEX[cb][:, _J6A]  # (n, 6) the alternative of each of the joints _J6
    k6 = np.arange(6)[None, :]
    Vc = np.empty((n, 7))
    Vc[:, _J6A] = np.clip(
        E[k6, alt6, cm[:, None], col[:, None]] + seeds[cm][:, _J6A], tab.lower[_J6A], tab.upper[_J6A]
    )
    Vc[:, 3] = V4[cm, ALT_INDEX[cb, 3]]
    s0 = Sp[cm, col]
    f0 = cost[cb, cm, col]
    lo6, up6 = tab.lower[_J6A], tab.upper[_J6A]
    lot6 = tab.lot6v

    def arc_ok(nb: np.ndarray) -> np.ndarray:
        # the arc to a neighbour (column nb) belongs to the candidate if its copies Vc are in the limits
        # at the arc's plain end (an arc has no critical swivel inside)
        av = X[k6, alt6, cm[:, None], nb[:, None]] + lot6
        v = av + TWO_PI * np.rint((Vc[:, _J6A] - av) * INV_2PI)
        inside = ((v >= lo6 - LIMIT_TOL) & (v <= up6 + LIMIT_TOL)).all(axis=1)
        return inside | (flag[cm, nb] & ~flag[cm, col])

    a = np.where(arc_ok(col - 1), s0 - gaps[cm, col - 1], s0)
    c = np.where(arc_ok(col + 1), s0 + gaps[cm, col], s0)
    xv = s0 + dx
    x = np.where((a < xv) & (xv < c), xv, s0)
    jj = np.arange(7)[None, :]
    altb = ALT_INDEX[cb]
    sgn = ALT_SIGN[jj, altb]
    shf = ALT_SHIFT[jj, altb]
    Kc, t4c, dsc, dwc, sdc = K[cm], t4[cm], deg_sh[cm], deg_wr[cm], seeds[cm]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        fx, g, hx, Vx = _fgh_np(x, Kc, t4c, dsc, dwc, sgn, shf, Vc, sdc, w, tab)
    bad = ~np.isfinite(fx)
    x[bad], fx[bad], g[bad], hx[bad], Vx[bad] = s0[bad], f0[bad], 0.0, 1.0, Vc[bad]
    bx, bf = x.copy(), fx.copy()
    active = a < c
    tried = np.full(n, np.nan)
    for _ in range(NEWTON_MAX):
        act = np.nonzero(active)[0]
        if len(act) == 0:
            break
        ga, ha, xa_, fa = g[act], hx[act], x[act], fx[act]
        c[act] = np.where(ga > 0.0, xa_, c[act])
        a[act] = np.where(ga < 0.0, xa_, a[act])
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = np.where(ha > 0.0, 0.5 * ga * ga / ha, np.inf)
            xn = np.where(ha > 0.0, xa_ - ga / ha, np.nan)
        done = (ga == 0.0) | (c[act] - a[act] <= 1e-13 * (1.0 + np.abs(xa_))) | (gain <= 1e-14 * (1.0 + fa))
        # beyond the bracket: try the end the model points to once (a limit optimum), then bisect
        end = np.where(ga < 0.0, c[act], a[act])
        out = ~((a[act] < xn) & (xn < c[act]))
        xn = np.where(out, np.where(end != tried[act], end, 0.5 * (a[act] + c[act])), xn)
        tried[act] = np.where(out, end, tried[act])
        done |= np.abs(xn - xa_) <= 4e-16 * (1.0 + np.abs(xa_))
        active[act[done]] = False
        act, xn = act[~done], xn[~done]
        if len(act) == 0:
            break
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            fn_, gn, hn, Vn = _fgh_np(
                xn, Kc[act], t4c[act], dsc[act], dwc[act], sgn[act], shf[act], Vx[act], sdc[act], w, tab
            )
        ok = np.isfinite(fn_)
        # beyond a limit of this copy: shrink the bracket to this side, keep the point
        side = xn > x[act]
        c[act[~ok & side]] = xn[~ok & side]
        a[act[~ok & ~side]] = xn[~ok & ~side]
        u = act[ok]
        x[u], fx[u], g[u], hx[u], Vx[u] = xn[ok], fn_[ok], gn[ok], hn[ok], Vn[ok]
        better = fx[u] < bf[u]
        bx[u[better]], bf[u[better]] = x[u[better]], fx[u[better]]
    keep0 = f0 <= bf
    bx = np.where(keep0, s0, bx)
    bf = np.where(keep0, f0, bf)
    # per pose the best candidate (ties: the first in bound order); cm is sorted, each pose's run together
    starts = np.flatnonzero(np.concatenate([[True], cm[1:] != cm[:-1]]))
    gmin = np.minimum.reduceat(bf, starts)
    best_f[cm[starts]] = gmin
    win = bf <= np.repeat(gmin, np.diff(np.append(starts, n)))
    wi = np.nonzero(win)[0][::-1]  # reverse so that the first winner of each pose is written last
    best_s[cm[wi]] = wrap(bx[wi])
    best_b[cm[wi]] = cb[wi]
    return best_s, best_b, best_f, odd
