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
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from redarm_ros.kinematics.swivel import SwivelArm

__all__ = [
    "LimitTables",
    "SwivelFunctions",
    "swivel_functions",
    "feasible_intervals",
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
            k = np.clip(np.rint((r - V[wj]) * INV_2PI), 0.0, kmax)
            V[wj] += TWO_PI * k
        return np.clip(V, self.lo3, self.up3), feas


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
    x4 = (c4 * x3x - s4 * zx, c4 * x3y - s4 * zy, c4 * x3z - s4 * zz)
    dx4, cx4 = c4 * dx3 - s4 * dz3, tuple(c4 * cx[i] - s4 * cz[i] for i in range(3))
    z4 = (s4 * x3x + c4 * zx, s4 * x3y + c4 * zy, s4 * x3z + c4 * zz)
    dz4, cz4 = s4 * dx3 + c4 * dz3, tuple(s4 * cx[i] + c4 * cz[i] for i in range(3))
    y3 = (y3x, y3y, y3z)
    r0, r1, r2 = Tl[0], Tl[1], Tl[2]
    tb = (r0[0], r1[0], r2[0])  # tool x
    ty = (r0[1], r1[1], r2[1])  # tool y
    ta = (r0[2], r1[2], r2[2])  # tool z (approach)

    def coef(
        v: tuple[float, ...], dv: float, cv: tuple[float, ...], t: tuple[float, ...], sg: float = 1.0
    ) -> list[float]:
        k0 = dv * (mx * t[0] + my * t[1] + mz * t[2])
        vt = v[0] * t[0] + v[1] * t[1] + v[2] * t[2]
        return [sg * k0, sg * (vt - k0), sg * (cv[0] * t[0] + cv[1] * t[1] + cv[2] * t[2])]

    X1 = [dz3 * mx, zx - dz3 * mx, cz[0]]
    Y1 = [dz3 * my, zy - dz3 * my, cz[1]]
    Z2 = [dz3 * mz, zz - dz3 * mz, cz[2]]
    X5, Y5, Z6 = coef(x4, dx4, cx4, ta), coef(y3, dy3, cy, ta), coef(z4, dz4, cz4, ta)
    # theta2 (theta6) 0 or pi on the whole circle: bound |(X, Y)| over the circle
    deg_sh = sum(math.hypot(X1[i], Y1[i]) for i in range(3)) <= DEGEN_SIN
    deg_wr = sum(math.hypot(X5[i], Y5[i]) for i in range(3)) <= DEGEN_SIN
    if deg_sh:  # R3 = Rz(theta3) Ry(0 or pi): theta3 = atan2(x3y, +-x3x), as ik
        sg = 1.0 if Z2[0] >= 0.0 else -1.0
        X3 = [sg * dx3 * mx, sg * (x3x - dx3 * mx), sg * cx[0]]
        Y3 = [dx3 * my, x3y - dx3 * my, cx[1]]
    else:  # theta3 = atan2(R3[2,1], -R3[2,0])
        X3 = [-dx3 * mz, -(x3z - dx3 * mz), -cx[2]]
        Y3 = [dy3 * mz, y3z - dy3 * mz, cy[2]]
    if deg_wr:
        X7 = coef(x4, dx4, cx4, tb, 1.0 if Z6[0] >= 0.0 else -1.0)
        Y7 = coef(y3, dy3, cy, tb)
    else:  # theta7 = atan2(W[2,1], -W[2,0])
        X7, Y7 = coef(z4, dz4, cz4, tb, -1.0), coef(z4, dz4, cz4, ty)
    Kl = [X1, X3, X5, X7, Y1, Y3, Y5, Y7, Z2, Z6]
    return SwivelFunctions(np.array(Kl), Kl, t4, deg_sh, deg_wr)


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
    d = np.arccos(np.clip(r, -1.0, 1.0))
    return phi + d, phi - d


def _alternatives(th: np.ndarray) -> np.ndarray:
    """(7, M) base-pattern angles -> (7, 2, M): per joint the base and the flipped alternative."""
    return th[:, None, :] * ALT_SIGN[:, :, None] + ALT_SHIFT[:, :, None]


def _critical(fn: SwivelFunctions, tab: LimitTables) -> np.ndarray:
    Ec, _ = fn.equations(tab)
    rp, rm = roots(Ec)
    allr = np.concatenate([rp, rm, fn.extremes()])
    return np.unique(wrap(allr[allr == allr]))


def feasible_intervals(fn: SwivelFunctions, tab: LimitTables) -> list[np.ndarray]:
    """Per flip pattern (8, order of ``ik``) the feasible swivels as closed intervals, (k, 2) arrays.

    Each row is [start, end] (rad) with start in [-pi, pi) and start <= end <= start + 2*pi (an interval
    may run past pi); the whole circle is [-pi, pi]. Ends are closed-form roots; an isolated feasible
    swivel (a joint touching a limit) is a zero-width row. Rows are sorted by start.
    """
    crit = _critical(fn, tab)
    n = len(crit)
    mids = (crit + np.append(crit[1:], crit[0] + TWO_PI)) / 2.0 if n else np.array([0.0])
    pts = np.concatenate([mids, crit])
    _, feas = tab.fit(_alternatives(fn.angles(pts)), None)
    ok = (_SEL @ np.where(feas, 0.0, 1.0).reshape(14, -1)) < 0.5  # (8, P): every joint feasible
    nm = len(mids)
    out: list[np.ndarray] = []
    crit_l = crit.tolist()
    for b in range(8):
        arc_ok = ok[b, :nm]
        if n == 0 or arc_ok.all():
            out.append(np.array([[-PI, PI]]) if arc_ok.all() else np.empty((0, 2)))
            continue
        pt_ok = ok[b, nm:]
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
        out.append(np.array(rows) if rows else np.empty((0, 2)))
    return out


@dataclass
class NearestResult:
    """Outcome of :func:`nearest`: the best (swivel rad, flip pattern, cost rad^2) and the work done.

    ``ranked``: every refined candidate as (cost, swivel, pattern), best first (the runners-up serve as
    fall-backs when round-off at a singular or end swivel makes the scalar solve disagree).
    """

    swivel: float | None
    branch: int
    cost: float
    candidates: int
    refined: int
    evaluations: int
    timed_out: bool
    ranked: list[tuple[float, float, int]]


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
    fn: SwivelFunctions, tab: LimitTables, s_seed: float | None, seed: list[float] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Sorted sample swivels of the nearest search and which of them are critical.

    Critical: the closed-form roots (limits, stationary points, and for a joint with several in-limit
    copies where it is opposite the ``seed``, where the nearest copy switches) and the hinge extremes.
    Plain: the uniform grid, the equal-angle roots of the pivot joints, the seed's own swivel and the
    mid point between every two neighbouring critical swivels, so that every arc between two
    neighbouring samples has a plain end (which decides the open arc's feasibility: no critical swivel
    inside).
    """
    Ec, Ed = fn.equations(tab, seed)
    nc = len(Ec)
    rp, rm = roots(np.concatenate([Ec, Ed]))
    crit = np.concatenate([rp[:nc], rm[:nc], fn.extremes()])
    # (np.remainder: slow per element but one call; these arrays are small)
    crit = np.sort(np.remainder(crit[crit == crit] + PI, TWO_PI) - PI)
    mids = (crit + np.append(crit[1:], crit[:1] + TWO_PI)) * 0.5
    plain = np.concatenate([rp[nc:], rm[nc:], _GRID_S, mids, [s_seed or 0.0]])
    S = np.concatenate([crit, np.remainder(plain[plain == plain] + PI, TWO_PI) - PI])
    flag = np.zeros(len(S), bool)
    flag[: len(crit)] = True
    order = np.argsort(S)
    S, flag = S[order], flag[order]
    close = np.diff(S) <= MERGE_TOL
    if close.any():  # one sample per cluster, critical if any member is
        keep = np.concatenate([[True], ~close])
        grp = np.cumsum(keep) - 1
        crit_any = np.zeros(int(grp[-1]) + 1, bool)
        np.logical_or.at(crit_any, grp, flag)
        rep = np.nonzero(keep)[0]
        ci = np.nonzero(flag & ~keep)[0]
        rep[grp[ci]] = ci  # the critical member (an exact root) represents the cluster
        S, flag = S[rep], crit_any
    return S, flag


def nearest(
    fn: SwivelFunctions,
    tab: LimitTables,
    seed: np.ndarray,
    w: np.ndarray,
    s_seed: float | None = None,
    deadline: float | None = None,
) -> NearestResult:
    """The swivel and flip pattern of the in-limit solution nearest the seed (weighted squared distance).

    Global over every pattern, 2*pi copy and feasible interval (ends included), see the module docstring.
    ``s_seed``: the seed's own swivel, sampled too. ``deadline``: a ``time.perf_counter()`` value after
    which no further candidate is refined (``timed_out`` set; the best one so far is returned).
    """
    seed_l = seed.tolist()
    S, flag = _sample_swivels(fn, tab, s_seed, seed_l)
    M = len(S)
    # per joint alternative: X = angle - (lower - tol), its copy in [0, 2 pi), feasible if below the range
    X = fn.angles(S)[:, None, :] * tab.sign3 + tab.shift_lot
    Xm = X - TWO_PI * np.floor(X * INV_2PI)
    feas = Xm <= tab.width3
    E = Xm + (tab.lot3 - seed[:, None, None])  # lowest in-limit copy minus the seed
    if len(tab.wide):  # more copies fit: the one nearest the seed
        wj = tab.wide
        Ew = E[wj]
        kmax = np.maximum(np.floor((tab.width3[wj] - Xm[wj]) * INV_2PI), 0.0)
        E[wj] = Ew + TWO_PI * np.clip(np.rint(Ew * -INV_2PI), 0.0, kmax)
    cost = _SEL @ np.where(feas, E * E * w[:, None, None], BIG).reshape(14, M)  # (8, M)
    # neighbours on the circle: pad one sample at each end
    cp = np.concatenate([cost[:, -1:], cost, cost[:, :1]], axis=1)
    c0 = cp[:, 1:-1]
    bs, idx = np.nonzero((c0 < 0.5 * BIG) & (c0 <= cp[:, :-2]) & (c0 <= cp[:, 2:]))
    if len(bs) == 0:
        return NearestResult(None, -1, math.inf, 8 * M, 0, 0, False, [])
    Sx = np.concatenate([[S[-1] - TWO_PI], S, [S[0] + TWO_PI]])
    # parabola through the three samples: its vertex starts the refinement, its depth below the sample
    # (times DEPTH_MARGIN) bounds how much lower the basin may be; candidates are refined in bound order
    # (one whose bound is above the best sample can never win: the best sample's basin comes first)
    sm, s0, sp = Sx[idx], Sx[idx + 1], Sx[idx + 2]
    fm, f0, fp = cp[bs, idx], cp[bs, idx + 1], cp[bs, idx + 2]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        d1 = (fp - f0) / (sp - s0)
        curv = 2.0 * (d1 - (f0 - fm) / (s0 - sm)) / (sp - sm)
        inner = (fm < 0.5 * BIG) & (fp < 0.5 * BIG) & (curv > 0.0)
        xv = np.where(inner, 0.5 * (s0 + sp) - d1 / curv, s0)
        lb = np.where(inner, f0 - DEPTH_MARGIN * 0.5 * curv * (xv - s0) ** 2, f0)
    fbest = float(f0.min())
    keep = np.nonzero(lb <= fbest + 1e-12 * (1.0 + fbest))[0]
    cands = sorted(
        zip(lb[keep].tolist(), bs[keep].tolist(), idx[keep].tolist(), xv[keep].tolist(), strict=True)
    )
    Sx = Sx.tolist()
    w_l = w.tolist()
    lo, up = tab.lo_l, tab.up_l
    lot = (tab.lower - LIMIT_TOL).tolist()
    best_f, best_s, best_b = math.inf, None, -1
    ranked: list[tuple[float, float, int]] = []
    refined = nev = 0
    timed_out = False
    for lb, b, i, xv in cands:
        if lb > best_f + 1e-12 * (1.0 + best_f):
            break
        if deadline is not None and refined > 0 and time.perf_counter() > deadline:
            timed_out = True
            break
        alt = _ALT_L[b]
        s0, f0 = Sx[i + 1], float(cost[b, i])
        Vi = [min(max(float(E[j, alt[j], i]) + seed_l[j], lo[j]), up[j]) for j in range(7)]
        # bracket: the arc to a neighbour belongs to this candidate if its copies Vi are in the limits
        # at the arc's plain end (an arc has no critical swivel inside)
        brk = []
        for nb, snb in (((i - 1) % M, Sx[i]), ((i + 1) % M, Sx[i + 2])):
            ok = True
            if not (flag[nb] and not flag[i]):
                for j in range(7):
                    av = float(X[j, alt[j], nb]) + lot[j]
                    v = av + TWO_PI * round((Vi[j] - av) * INV_2PI)
                    if v < lo[j] - LIMIT_TOL or v > up[j] + LIMIT_TOL:
                        ok = False
                        break
            brk.append(snb if ok else s0)
        a, c = brk
        sx, fx = s0, f0
        if a < c:
            x0 = xv if a < xv < c else s0
            sr, fr, ne = _refine(fn, b, x0, Vi, a, c, seed_l, w_l, tab)
            nev += ne
            if fr < fx:
                sx, fx = sr, fr
        refined += 1
        ranked.append((fx, sx - TWO_PI * math.floor((sx + PI) * INV_2PI), b))
        if fx < best_f:
            best_f, best_s, best_b = fx, sx, b
    ranked.sort()
    sw = None if best_s is None else (best_s - TWO_PI * math.floor((best_s + PI) * INV_2PI))
    return NearestResult(sw, best_b, best_f, 8 * M, refined, nev, timed_out, ranked)


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


def nearest_batch(
    K: np.ndarray,
    t4: np.ndarray,
    deg_sh: np.ndarray,
    deg_wr: np.ndarray,
    tab: LimitTables,
    seeds: np.ndarray,
    w: np.ndarray,
    s_seeds: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`nearest` for m poses at once (all reachable): returns (swivel (m,) rad or NaN, pattern (m,)
    or -1, cost (m,) rad^2 or inf). K (m, 10, 3), t4 / deg_sh / deg_wr (m,), seeds (m, 7), s_seeds (m,)."""
    m = K.shape[0]
    crit, mids, dirs = _critical_np(K, deg_sh, deg_wr, tab, seeds, directions=True)
    plain = np.concatenate([dirs, np.broadcast_to(_GRID_S, (m, GRID)), mids, s_seeds[:, None]], axis=1)
    S = np.concatenate([crit, wrap(plain)], axis=1)
    flag = np.zeros(S.shape, bool)
    flag[:, : crit.shape[1]] = crit == crit
    M = S.shape[1]
    # an empty slot (no root) gets a filler swivel off every grid, so every row has M distinct samples
    nan = S != S
    if nan.any():
        filler = np.broadcast_to((np.arange(M) + 0.5 + 0.1234567) * (TWO_PI / M) - PI, S.shape)
        S = np.where(nan, filler, S)
    order = np.argsort(S, axis=1)
    S = np.take_along_axis(S, order, axis=1)
    flag = np.take_along_axis(flag, order, axis=1)
    # ---- costs of the 8 patterns at every sample
    th = _angles_np(K, t4, deg_sh, deg_wr, S)  # (m, 7, M)
    Xa = th[:, :, None, :] * tab.sign3 + tab.shift_lot  # (m, 7, 2, M)
    Xm = Xa - TWO_PI * np.floor(Xa * INV_2PI)
    feas = Xm <= tab.width3
    E = Xm + (tab.lot3 - seeds[:, :, None, None])
    if len(tab.wide):
        wj = tab.wide
        Ew = E[:, wj]
        kmax = np.maximum(np.floor((tab.width3[wj] - Xm[:, wj]) * INV_2PI), 0.0)
        E[:, wj] = Ew + TWO_PI * np.clip(np.rint(Ew * -INV_2PI), 0.0, kmax)
    Cj = E * E * w[:, None, None]
    np.copyto(Cj, BIG, where=~feas)
    cost = np.matmul(_SEL, Cj.reshape(m, 14, M))  # (m, 8, M)
    # ---- candidates: sample-wise local minima per pattern; neighbours skip twins (gap <= MERGE_TOL)
    cp = np.concatenate([cost[:, :, -1:], cost, cost[:, :, :1]], axis=2)
    cm, cb, ci = np.nonzero((cost < 0.5 * BIG) & (cost <= cp[:, :, :-2]) & (cost <= cp[:, :, 2:]))
    best_s = np.full(m, np.nan)
    best_b = np.full(m, -1)
    best_f = np.full(m, np.inf)
    if len(cm) == 0:
        return best_s, best_b, best_f
    gap = np.diff(np.concatenate([S, S[:, :1] + TWO_PI], axis=1), axis=1)  # gap[i] = S[i+1] - S[i]
    il = (ci - 1) % M
    il = np.where(gap[cm, il] > MERGE_TOL, il, (ci - 2) % M)
    ir = (ci + 1) % M
    ir = np.where(gap[cm, ci] > MERGE_TOL, ir, (ci + 2) % M)
    s0 = S[cm, ci]
    sl = S[cm, il] - np.where(il > ci, TWO_PI, 0.0)
    sr = S[cm, ir] + np.where(ir < ci, TWO_PI, 0.0)
    f0, fl, fr = cost[cm, cb, ci], cost[cm, cb, il], cost[cm, cb, ir]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        d1 = (fr - f0) / (sr - s0)
        curv = 2.0 * (d1 - (f0 - fl) / (s0 - sl)) / (sr - sl)
        inner = (fl < 0.5 * BIG) & (fr < 0.5 * BIG) & (curv > 0.0)
        xv = np.where(inner, 0.5 * (s0 + sr) - d1 / curv, s0)
        lb = np.where(inner, f0 - DEPTH_MARGIN * 0.5 * curv * (xv - s0) ** 2, f0)
    # refine the candidates whose bound is below the pose's best sample, at most BATCH_CANDIDATES each
    starts = np.flatnonzero(np.concatenate([[True], cm[1:] != cm[:-1]]))  # cm is sorted (C order)
    fmin = np.repeat(np.minimum.reduceat(f0, starts), np.diff(np.append(starts, len(cm))))
    sel = lb <= fmin + 1e-12 * (1.0 + fmin)
    order = np.lexsort((lb, cm))
    sel_o = sel[order]
    rank = np.zeros(len(order), int)
    if len(order):
        first = np.concatenate([[True], cm[order][1:] != cm[order][:-1]])
        idx = np.arange(len(order))
        rank = idx - np.maximum.accumulate(np.where(first, idx, 0))
    take = order[sel_o & (rank < BATCH_CANDIDATES)]
    cm, cb, ci, il, ir, s0, sl, sr, f0, xv = (v[take] for v in (cm, cb, ci, il, ir, s0, sl, sr, f0, xv))
    n = len(cm)
    altb = ALT_INDEX[cb]  # (n, 7)
    jj = np.arange(7)[None, :]
    Vc = np.clip(E[cm[:, None], jj, altb, ci[:, None]] + seeds[cm], tab.lower, tab.upper)  # (n, 7)
    lot = tab.lower - LIMIT_TOL

    def arc_ok(nb: np.ndarray) -> np.ndarray:
        av = Xa[cm[:, None], jj, altb, nb[:, None]] + lot
        v = av + TWO_PI * np.rint((Vc - av) * INV_2PI)
        inside = ((v >= tab.lower - LIMIT_TOL) & (v <= tab.upper + LIMIT_TOL)).all(axis=1)
        return inside | (flag[cm, nb] & ~flag[cm, ci])

    a = np.where(arc_ok(il), sl, s0)
    c = np.where(arc_ok(ir), sr, s0)
    x = np.where((a < xv) & (xv < c), xv, s0)
    sgn = ALT_SIGN[jj, altb]
    shf = ALT_SHIFT[jj, altb]
    Kc, t4c, dsc, dwc, sdc = K[cm], t4[cm], deg_sh[cm], deg_wr[cm], seeds[cm]
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
    # per pose the best candidate (ties: the first in bound order); take keeps each pose's run together
    starts = np.flatnonzero(np.concatenate([[True], cm[1:] != cm[:-1]]))
    gmin = np.minimum.reduceat(bf, starts)
    best_f[cm[starts]] = gmin
    win = bf <= np.repeat(gmin, np.diff(np.append(starts, len(cm))))
    wi = np.nonzero(win)[0][::-1]  # reverse so that the first winner of each pose is written last
    best_s[cm[wi]] = wrap(bx[wi])
    best_b[cm[wi]] = cb[wi]
    return best_s, best_b, best_f
