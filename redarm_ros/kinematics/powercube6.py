"""Analytic IK of the 6-DOF PowerCube arm (Duguleana, mobile-base paper), joint 3 locked at 0.

Model (see config/arms/powercube6.yaml): standard DH ``a = L1, L23, L4, L56``, ``alpha1 = 90 deg``;
joints base yaw phi1 = q[0], shoulder pitch phi2 = q[1], upper-arm roll q[2] (locked, 0), elbow pitch
phi4 = q[3], wrist pitch phi5 = q[4], wrist roll q[5]. With q[2] = 0 the tool position is eq. (2)-(4):

    s = L1 + L23 cos phi2 + L4 cos(phi2 + phi4) + L56 cos(phi2 + phi4 + phi5)
    x = cos phi1 * s,  y = sin phi1 * s,  z = L23 sin phi2 + L4 sin(phi2 + phi4) + L56 sin(phi2 + phi4 + phi5)

and the tool orientation is ``Rz(phi1) Rx(90 deg) Rz(psi) Rx(q[5])`` with the approach angle
``psi = phi2 + phi4 + phi5``: the tool x axis (approach) is ``cos psi e_r + sin psi k`` in the arm's
vertical plane (``e_r = (cos phi1, sin phi1, 0)``), the tool z axis is the wrist pitch axis rotated by
the wrist roll. With joint 3 locked the arm has 5 DOF: a full pose is reachable only if the approach
lies in the arm's vertical plane.

IK as in the paper: base azimuth phi1 (two values, atan2(y, x) and + pi), then the planar 3-link problem
in that plane; the redundancy of the planar problem is removed by a fixed approach angle psi (from the
pose's orientation, or given), a fixed phi5 (L4 and L56 folded into one rigid link), or a fixed phi4
(default 0: the paper's "optimal region", L23 and L4 folded into one link).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.model import LIMIT_TOL, Arm, check_scalar, pose_error
from redarm_ros.kinematics.result import IKInfo, IKStatus

__all__ = ["PowerCube6Arm"]

PI = math.pi
TWO_PI = 2.0 * math.pi
ORIENT_TOL = 1e-9  # |approach . plane normal| above this: orientation not reachable with joint 3 locked
REACH_TOL = 1e-9  # m


def _wrap(x: float) -> float:
    return math.atan2(math.sin(x), math.cos(x)) if (x > PI or x <= -PI) else x


def _two_link(u: float, w: float, a: float, b: float) -> list[tuple[float, float]] | float:
    """Planar 2R IK: angles (t1, t2) with a (cos t1, sin t1) + b (cos(t1+t2), sin(t1+t2)) = (u, w).

    Returns up to 2 solutions (t2 >= 0 first), or the reach violation in m (> 0) if (u, w) is out of reach.
    """
    r2 = u * u + w * w
    r = math.sqrt(r2)
    if r > a + b + REACH_TOL:
        return r - (a + b)
    if r < abs(a - b) - REACH_TOL:
        return abs(a - b) - r
    c2 = (r2 - a * a - b * b) / (2.0 * a * b)
    c2 = max(-1.0, min(1.0, c2))
    out = []
    for t2 in (math.acos(c2), -math.acos(c2)):
        t1 = math.atan2(w, u) - math.atan2(b * math.sin(t2), a + b * math.cos(t2))
        out.append((_wrap(t1), t2))
    if abs(out[0][1]) < 1e-15:
        out = out[:1]
    return out


class PowerCube6Arm(Arm):
    """The 6-DOF PowerCube arm with the analytic IK of its 5-DOF (joint 3 locked) sub-chain."""

    kind = "powercube6"

    def _setup_model(self) -> None:
        self.link_lengths = tuple(float(v) for v in self.config["link_lengths"])

    # ------------------------------------------------------------------ helpers
    def _fits(self, q: list[float]) -> list[float] | None:
        out = []
        for j, x in enumerate(q):
            lo, up = self._lower_l[j], self._upper_l[j]
            best = None
            for k in (0, -1, 1, -2, 2):
                v = x + k * TWO_PI
                if lo - LIMIT_TOL <= v <= up + LIMIT_TOL and (best is None or abs(v) < abs(best)):
                    best = min(max(v, lo), up)
            if best is None:
                return None
            out.append(best)
        return out

    def _azimuths(self, px: float, py: float, ax: float, ay: float) -> list[tuple[float, float]]:
        """(phi1, signed radial distance of the target) candidates."""
        rxy = math.hypot(px, py)
        if rxy > 1e-12:
            p1 = math.atan2(py, px)
            return [(p1, rxy), (_wrap(p1 + PI), -rxy)]
        # target on the base axis: the approach (if not vertical) fixes the plane, else phi1 = 0
        if math.hypot(ax, ay) > 1e-9:
            p1 = math.atan2(ay, ax)
            return [(p1, 0.0), (_wrap(p1 + PI), 0.0)]
        return [(0.0, 0.0), (PI, 0.0)]

    # ------------------------------------------------------------------ IK
    def ik(self, T: np.ndarray, swivel: float | None = None) -> np.ndarray:
        """Every in-limit solution (k, 6), k <= 4, reaching pose T exactly with joint 3 at 0.

        ``swivel`` is accepted for a uniform call signature and ignored (a 6-DOF arm has no
        self-motion). Returns (0, 6) if the position is out of reach or the orientation is not
        reachable with joint 3 locked (approach outside the arm plane).
        Raises :class:`InvalidInputError` for a malformed T.
        """
        Tl = self.check_pose(T)
        sols, _ = self._ik_pose(Tl)
        return np.array(sols) if sols else np.empty((0, 6))

    def _ik_pose(self, Tl: list[list[float]]) -> tuple[list[list[float]], str]:
        L1, L23, L4, L56 = self.link_lengths
        r0, r1, r2 = Tl[0], Tl[1], Tl[2]
        px, py, pz = r0[3], r1[3], r2[3]
        ax, ay, az = r0[0], r1[0], r2[0]  # approach = tool x
        yx, yy, yz = r0[1], r1[1], r2[1]
        sols: list[list[float]] = []
        reason = ""
        for phi1, rad in self._azimuths(px, py, ax, ay):
            c1, s1 = math.cos(phi1), math.sin(phi1)
            if abs(-s1 * ax + c1 * ay) > ORIENT_TOL:
                reason = "orientation not reachable with joint 3 locked (approach not in the arm plane)"
                continue
            a_r = c1 * ax + s1 * ay
            psi = math.atan2(az, a_r)
            u = rad - L1 - L56 * math.cos(psi)
            w = pz - L56 * math.sin(psi)
            planar = _two_link(u, w, L23, L4)
            if not isinstance(planar, list):
                reason = reason or f"position out of reach by {planar:.6g} m"
                continue
            cp, sp = math.cos(psi), math.sin(psi)
            # wrist roll: Rx(q6) = B^T R with B = Rz(phi1) Rx(90) Rz(psi); y_B and z_B in the base frame
            ybx, yby, ybz = -sp * c1, -sp * s1, cp
            zbx, zby, zbz = s1, -c1, 0.0
            q6 = math.atan2(yx * zbx + yy * zby + yz * zbz, yx * ybx + yy * yby + yz * ybz)
            for phi2, phi4 in planar:
                phi5 = _wrap(psi - phi2 - phi4)
                q = self._fits([phi1, phi2, 0.0, phi4, phi5, q6])
                if q is None:
                    reason = reason or "solutions exist but none within the joint limits"
                    continue
                sols.append(q)
        return sols, reason

    def ik_position(
        self,
        p: Sequence[float],
        *,
        psi: float | None = None,
        phi5: float | None = None,
        phi4: float | None = None,
        roll: float = 0.0,
    ) -> np.ndarray:
        """Position-only analytic IK (k, 6), the paper's scheme: phi1 from atan2, then 3 links in a plane.

        Give at most one of ``psi`` (approach angle phi2 + phi4 + phi5 in the arm plane, rad), ``phi5``
        (fixed wrist pitch, rad; L4 and L56 folded into one link) or ``phi4`` (fixed elbow, rad; default
        0, the paper's optimal region). ``roll`` is the wrist roll q[5]. Joint 3 is 0. In-limit solutions
        only; (0, 6) if none.
        """
        pa = np.asarray(p, dtype=float)
        if pa.shape != (3,) or not np.all(np.isfinite(pa)):
            raise InvalidInputError("p must be 3 finite numbers (m)", field="p", value=p)
        given = [v is not None for v in (psi, phi5, phi4)]
        if sum(given) > 1:
            raise InvalidInputError("give at most one of psi, phi5, phi4", field="psi")
        for nm, v in (("psi", psi), ("phi5", phi5), ("phi4", phi4), ("roll", roll)):
            if v is not None and not math.isfinite(float(v)):
                raise InvalidInputError(f"{nm} must be finite", field=nm, value=v)
        if not any(given):
            phi4 = 0.0
        L1, L23, L4, L56 = self.link_lengths
        px, py, pz = pa.tolist()
        sols: list[list[float]] = []
        for p1, rad in self._azimuths(px, py, 1.0, 0.0):
            u0, w0 = rad - L1, pz
            cand: list[tuple[float, float, float]] = []
            if psi is not None:
                planar = _two_link(u0 - L56 * math.cos(psi), w0 - L56 * math.sin(psi), L23, L4)
                if isinstance(planar, list):
                    cand = [(a, b, psi - a - b) for a, b in planar]
            elif phi5 is not None:
                le = math.sqrt(L4 * L4 + L56 * L56 + 2 * L4 * L56 * math.cos(phi5))
                gam = math.atan2(L56 * math.sin(phi5), L4 + L56 * math.cos(phi5))
                planar = _two_link(u0, w0, L23, le)
                if isinstance(planar, list):
                    cand = [(a, b - gam, phi5) for a, b in planar]
            else:
                assert phi4 is not None
                la = math.sqrt(L23 * L23 + L4 * L4 + 2 * L23 * L4 * math.cos(phi4))
                dl = math.atan2(L4 * math.sin(phi4), L23 + L4 * math.cos(phi4))
                planar = _two_link(u0, w0, la, L56)
                if isinstance(planar, list):
                    cand = [(a - dl, phi4, b - phi4 + dl) for a, b in planar]
            for a, b, c in cand:
                q = self._fits([p1, _wrap(a), 0.0, _wrap(b), _wrap(c), _wrap(float(roll))])
                if q is not None:
                    sols.append(q)
        return np.array(sols) if sols else np.empty((0, 6))

    def ik_batch(self, Ts: np.ndarray, swivels: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """(m, 4, 4) poses -> (Q (m, 4, 6), valid (m, 4)); NaN where not valid. ``swivels`` is ignored."""
        Ts = np.asarray(Ts, dtype=float)
        if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
            raise InvalidInputError(f"Ts must have shape (m, 4, 4), got {Ts.shape}", field="Ts")
        Q = np.full((Ts.shape[0], 4, 6), np.nan)
        valid = np.zeros((Ts.shape[0], 4), dtype=bool)
        for i, T in enumerate(Ts):
            sols, _ = self._ik_pose(self.check_pose(T))
            for k, q in enumerate(sols[:4]):
                Q[i, k] = q
                valid[i, k] = True
        return Q, valid

    def ik_nearest(
        self,
        T: np.ndarray,
        q_seed: Sequence[float],
        *,
        weights: Sequence[float] | None = None,
        position_only: bool = False,
        samples: int = 72,
        timeout_s: float | None = None,
    ) -> tuple[np.ndarray | None, IKInfo]:
        """The analytic solution of T nearest to the seed (weighted squared joint distance).

        ``position_only=True`` ignores the orientation of T: the approach angle psi is scanned over
        ``samples`` values (and the seed's own), the wrist roll kept at the seed's. ``timeout_s`` (s, None =
        no limit) stops that scan early (status TIMEOUT with the best answer so far, if any); the full-pose
        solve is closed form and bounded. Failure reasons: INVALID_INPUT, OUT_OF_REACH (position, or
        orientation not reachable with joint 3 locked), NO_SOLUTION_IN_LIMITS, TIMEOUT.
        """
        t0 = time.perf_counter()
        timed_out = False
        try:
            Tl = self.check_pose(T)
            seed = self.check_q(q_seed, "q_seed")
            w = np.ones(6) if weights is None else np.asarray(weights, dtype=float)
            if w.shape != (6,) or not np.all(np.isfinite(w)) or np.any(w < 0):
                raise InvalidInputError("weights must be 6 finite non-negative numbers", field="weights")
            samples = int(check_scalar(samples, "samples", 1e6))
            if samples < 1:
                raise InvalidInputError(
                    f"samples must be >= 1, got {samples}", field="samples", value=samples
                )
            if timeout_s is not None and not check_scalar(timeout_s, "timeout_s") >= 0.0:
                raise InvalidInputError(
                    "timeout_s must be >= 0 s or None", field="timeout_s", value=timeout_s
                )
        except InvalidInputError as exc:
            return None, IKInfo(IKStatus.INVALID_INPUT, str(exc))
        if position_only:
            p = [Tl[0][3], Tl[1][3], Tl[2][3]]
            psi0 = seed[1] + seed[3] + seed[4]
            rows = []
            for k in range(samples):
                if timeout_s is not None and time.perf_counter() - t0 > timeout_s:
                    timed_out = True
                    break
                rows.append(self.ik_position(p, psi=psi0 + k * TWO_PI / samples, roll=float(seed[5])))
            sols = np.concatenate(rows) if rows else np.empty((0, 6))
            reason = "position out of reach or no solution within the joint limits"
        else:
            sl, reason = self._ik_pose(Tl)
            sols = np.array(sl) if sl else np.empty((0, 6))
        if len(sols) == 0:
            if timed_out:
                return None, IKInfo(IKStatus.TIMEOUT, f"timeout_s {timeout_s:g} s ran out before a solution")
            status = IKStatus.NO_SOLUTION_IN_LIMITS if "limits" in reason else IKStatus.OUT_OF_REACH
            return None, IKInfo(status, reason or "no solution", candidates=0)
        cost = ((sols - seed) ** 2 * w).sum(axis=1)
        q = sols[int(np.argmin(cost))]
        Tq = self.fk(q)
        Td = np.asarray(T, dtype=float)
        pe, re = pose_error(Tq, Td)
        if timed_out:
            msg = f"timeout_s {timeout_s:g} s ran out: best of the {len(sols)} candidates scanned"
            return q.copy(), IKInfo(IKStatus.TIMEOUT, msg, pos_err=pe, rot_err=re, candidates=len(sols))
        return q.copy(), IKInfo(IKStatus.SUCCESS, "ok", pos_err=pe, rot_err=re, candidates=len(sols))
