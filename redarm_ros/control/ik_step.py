"""One IK step of the reference: the closed-form solution at the new pose and swivel, and the
fallback cascade when it is not continuous with the previous one.

For a proposed tool pose and the swivel the dynamics asks for, :meth:`IKStepper.advance`

1. takes the in-limit solution nearest to the previous reference in *time at the joint velocity
   limits* (each wide joint at its 2 pi copy nearest the previous value): no branch flip;
2. if a joint would exceed its velocity limit, lets the elbow yield first (a shorter swivel change),
   then shortens the whole step (pose and swivel);
3. if no continuous solution exists at that swivel, searches nearby swivels for the nearest one
   that has one;
4. if still none, halves the Cartesian step, up to four times;
5. reports a dead end (:class:`DeadEnd`) otherwise: the caller holds and may re-plan.

Near an obstacle (clearance of the upper arm/forearm below ``elbow_priority_clearance``) the hand
yields to the elbow instead: the hand step is shortened so that the swivel keeps its rate.

No state is kept here: the caller passes the previous reference and gets the new one back, with the
factor by which the hand speed had to be scaled. Units: m, rad, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from redarm_ros.control.elbow import ArmGeometry, ElbowCircle, elbow_circle
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.errors import UnreachableError
from redarm_ros.kinematics.protocols import ControlledArm, ControlledSwivelArm
from redarm_ros.kinematics.quaternion import (
    matrix_from_quat,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    rotvec_between,
)

DEAD_END = "no joint solution continuous with the current configuration (joint limits or singularity)"
#: halvings of the swivel search's last step (0.03 rad by default: to about 1e-4 rad)
SEARCH_BISECTIONS = 8


@dataclass(frozen=True)
class IKStep:
    """A successful step: reference joints ``q`` (rad) at pose (``pos``, ``rot``) and swivel ``s``
    with its ``circle``; ``s_des`` the swivel attractor used; ``speed_scale`` the factor by which the
    hand speed had to be reduced (1 = not at all)."""

    q: np.ndarray
    pos: Vec3
    rot: Quat
    s: float
    s_des: float
    circle: ElbowCircle
    speed_scale: float


@dataclass(frozen=True)
class DeadEnd:
    """No continuous in-limit step exists from the previous reference: ``reason`` says why."""

    reason: str = DEAD_END
    speed_scale: float = 0.0


#: ``swivel(circle, T, s0) -> (s_new, s_des, elbow_priority)``: the swivel the dynamics asks for.
SwivelFn = Callable[[ElbowCircle, np.ndarray, float], tuple[float, float, bool]]


def pose_matrix(pos: Vec3, rot: Quat) -> np.ndarray:
    """4x4 of a position (m) and quaternion (w, x, y, z)."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(rot)
    T[:3, 3] = pos
    return T


def pose_of(T: np.ndarray) -> tuple[Vec3, Quat]:
    """Position (m) and quaternion (w, x, y, z) of a 4x4 pose: the inverse of :func:`pose_matrix`."""
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), quat_from_matrix(T[:3, :3])


def blend(pos0: Vec3, rot0: Quat, pos1: Vec3, rot1: Quat, t: float) -> tuple[Vec3, Quat]:
    """Pose a fraction ``t`` of the way from (pos0, rot0) to (pos1, rot1)."""
    pos = (pos0[0] + t * (pos1[0] - pos0[0]), pos0[1] + t * (pos1[1] - pos0[1]),
           pos0[2] + t * (pos1[2] - pos0[2]))
    w = rotvec_between(rot0, rot1)
    rot = quat_normalize(quat_mul(quat_from_rotvec((t * w[0], t * w[1], t * w[2])), rot0))
    return pos, rot


class StepperBase:
    """What both IK steppers (7-DOF swivel, 6-DOF) keep of the arm: ``flip_ratio``, the search
    ``search_step`` (rad) and ``search_count``, the joint limits and ``1 / max_vel``."""

    def __init__(self, arm: ControlledArm, flip_ratio: float, search_step: float, search_count: int) -> None:
        self.arm = arm
        self.flip_ratio = float(flip_ratio)
        self.search_step = float(search_step)
        self.search_count = int(search_count)
        self.lower = np.asarray(arm.lower, float)
        self.upper = np.asarray(arm.upper, float)
        self.inv_vel = 1.0 / np.asarray(arm.max_vel, float)
        # (the same as plain floats, for the selection's loop)
        self._lower_l, self._upper_l = self.lower.tolist(), self.upper.tolist()
        self._inv_vel_l = self.inv_vel.tolist()


class IKStepper(StepperBase):
    """The IK step of one arm (see the module docstring). ``flip_ratio``: a joint step above
    ``flip_ratio * max_vel * dt`` is a branch change, never taken; ``search_step`` (rad) and
    ``search_count``: the swivel search around a swivel without a continuous solution."""

    def __init__(self, arm: ControlledSwivelArm, geom: ArmGeometry, flip_ratio: float, search_step: float,
                 search_count: int) -> None:
        super().__init__(arm, flip_ratio, search_step, search_count)
        self.geom = geom
        self.wide = [j for j in range(arm.n) if self.upper[j] - self.lower[j] > 2.0 * math.pi]

    # -- selection --------------------------------------------------------------------------------
    def select(self, sols: np.ndarray, q_ref: np.ndarray, dt: float) -> tuple[np.ndarray, float] | None:
        """Solution nearest to ``q_ref`` in time at the velocity limits, and its ratio to the limit
        over ``dt``; each wide joint at the in-limit 2 pi copy nearest ``q_ref``."""
        if sols.shape[0] == 0:
            return None
        # Plain floats over the (at most 8) rows: numpy's cost per call was most of the work (16 -> 6 us).
        # The same arithmetic: round() is np.rint's half-to-even; a max picks a value, whatever the order;
        # the first row of least ratio, as argmin (IK rows and the reference are finite).
        qr = q_ref.tolist()
        lower, upper, inv_vel = self._lower_l, self._upper_l, self._inv_vel_l
        best_row: list[float] = []
        best = math.inf
        for row in sols.tolist():
            for j in self.wide:  # the in-limit 2 pi copy nearest q_ref (else the row's own)
                x = row[j]
                c = x - 2.0 * math.pi * round((x - qr[j]) / (2.0 * math.pi))
                if lower[j] <= c <= upper[j]:
                    row[j] = c
            ratio = max([abs(x - r) * iv for x, r, iv in zip(row, qr, inv_vel, strict=True)]) / dt
            if not best_row or ratio < best:
                best, best_row = ratio, row
        return np.array(best_row), best

    def solve(self, T: np.ndarray, s: float, q_ref: np.ndarray, dt: float) -> tuple[np.ndarray, float] | None:
        """:meth:`select` over the IK solutions of ``T`` at swivel ``s``."""
        return self.select(self.arm.ik(T, s), q_ref, dt)

    def margin(self, q: np.ndarray) -> float:
        """Smallest distance (rad) of any joint to its limit."""
        return float(np.minimum(q - self.lower, self.upper - q).min())

    def limit_margins(self, T: np.ndarray, s: float, q_ref: np.ndarray, eps: float,
                      threshold: float) -> tuple[float, float, float] | None:
        """Joint-limit margins (rad) at s, s + eps, s - eps on the current branch, if near a limit."""
        m0 = self.margin(q_ref)
        if m0 >= threshold:
            return None
        out = [m0]
        for ds in (eps, -eps):
            out.append(self._continued_margin(T, s + ds, q_ref))
        return out[0], out[1], out[2]

    def follow(self, T: np.ndarray, s: float, q_ref: np.ndarray) -> np.ndarray | None:
        """The solution of pose T at swivel ``s`` on the branch continued from ``q_ref`` (the limits
        ignored, every joint on its 2 pi copy nearest ``q_ref``: beyond a limit where the branch passes
        it), or None if the pose has no solution."""
        sols = self.arm.ik(T, s, limits=False)
        if sols.shape[0] == 0:
            return None
        sols = sols - 2.0 * math.pi * np.round((sols - q_ref) / (2.0 * math.pi))
        return sols[int(np.argmin(np.max(np.abs(sols - q_ref), axis=1)))]

    def _continued_margin(self, T: np.ndarray, s: float, q_ref: np.ndarray) -> float:
        """Least limit margin (rad, negative beyond a limit) at swivel ``s`` of the branch continued from
        ``q_ref``: the solution nearest ``q_ref`` with the limits ignored, every joint on its 2 pi copy
        nearest ``q_ref``; -1 if the pose has no solution. Probed among the in-limit solutions only,
        a joint that passed its limit left that branch out, and the nearest in-limit solution (another
        branch, or a wide joint's copy 2 pi away) looked like open space: the limit force then pushed
        the elbow into the limit (a false rest, then a swing after REACHED) or let it run in at speed."""
        q = self.follow(T, s, q_ref)
        return -1.0 if q is None else self.margin(q)

    # -- the cascade ------------------------------------------------------------------------------
    def advance(self, pos0: Vec3, rot0: Quat, s0: float, q_prev: np.ndarray, new_pos: Vec3, new_rot: Quat,
                dt: float, swivel: SwivelFn, pose_swivel: bool = False) -> IKStep | DeadEnd:
        """The reference step from (``pos0``, ``rot0``, ``s0``, joints ``q_prev``) towards the proposed
        pose, with the swivel from ``swivel`` (see :data:`SwivelFn`). ``pose_swivel``: the swivel is a
        function of the pose (the servo's pose law): a shortened step asks ``swivel`` again at its own
        pose instead of shortening the swivel change in proportion, and the elbow does not yield alone
        (either would leave the elbow off the preferred swivel of the pose it reaches)."""
        scale = 1.0
        for _attempt in range(4):
            T = pose_matrix(new_pos, new_rot)
            try:
                circle = elbow_circle(self.geom, T)
            except UnreachableError:  # the step would leave the workspace: shorten it
                new_pos, new_rot = blend(pos0, rot0, new_pos, new_rot, 0.5)
                scale *= 0.5
                continue
            s_new, s_des, elbow_first = swivel(circle, T, s0)
            if elbow_first and s_new != s0:
                shortened = self._yield_hand(pos0, rot0, new_pos, new_rot, s_new, q_prev, dt)
                if shortened is not None:
                    new_pos, new_rot, T, circle, frac = shortened
                    scale *= frac
            pick = self.solve(T, s_new, q_prev, dt)
            if (pick is None or pick[1] > 1.0 + 1e-9) and s_new != s0 and not pose_swivel:
                # Too fast for a joint (or no solution there): the elbow yields first, the hand path
                # has priority.
                yielded = self._yield_swivel(T, s0, s_new, q_prev, dt, math.inf if pick is None else pick[1])
                if yielded is not None and (pick is None or yielded[2] < pick[1]):
                    s_new, pick = yielded[0], (yielded[1], yielded[2])
            if pick is None or pick[1] > self.flip_ratio:
                pick, s_new = self._search_swivel(T, s_new, q_prev, dt)
            if pick is None:
                # No continuous solution here: try a shorter Cartesian step before giving up.
                new_pos, new_rot = blend(pos0, rot0, new_pos, new_rot, 0.5)
                scale *= 0.5
                continue
            q_new, ratio = pick
            if ratio > 1.0 + 1e-9:
                # Too fast for a joint: shorten the whole step (pose and swivel).
                scaled = self._scale_step(pos0, rot0, s0, new_pos, new_rot, s_new, q_prev, dt, ratio,
                                          swivel if pose_swivel else None)
                if scaled is None:
                    new_pos, new_rot = blend(pos0, rot0, new_pos, new_rot, 0.5)
                    continue
                new_pos, new_rot, s_new, q_new, circle, frac = scaled
                scale *= frac
            return IKStep(q_new, new_pos, new_rot, s_new, s_des, circle, scale)
        return DeadEnd(DEAD_END, scale)

    def _yield_hand(self, pos0: Vec3, rot0: Quat, pos1: Vec3, rot1: Quat, s: float, q_prev: np.ndarray,
                    dt: float) -> tuple[Vec3, Quat, np.ndarray, ElbowCircle, float] | None:
        """Shorten the hand step (not the swivel change) until the joint velocities fit; None if the
        whole hand step fits already or no shortening helps."""
        frac = 1.0
        for _ in range(4):
            tried = self._solve_blend(pos0, rot0, pos1, rot1, frac, s, q_prev, dt)
            if tried is None or tried[4][1] > self.flip_ratio:
                return None
            pos, rot, T, circle, (_, r) = tried
            if r <= 1.0 + 1e-9:
                if frac >= 1.0:
                    return None
                return pos, rot, T, circle, frac
            frac = 0.0 if frac < 0.1 else frac * 0.9 / r
        return None

    def _solve_blend(self, pos0: Vec3, rot0: Quat, pos1: Vec3, rot1: Quat, frac: float, s: float,
                     q_prev: np.ndarray, dt: float
                     ) -> tuple[Vec3, Quat, np.ndarray, ElbowCircle, tuple[np.ndarray, float]] | None:
        """The pose ``frac`` of the way from (pos0, rot0) to (pos1, rot1), its 4x4, its elbow circle
        and the IK pick (q, ratio) at swivel ``s``; None if the pose is out of reach or unsolved."""
        pos, rot = blend(pos0, rot0, pos1, rot1, frac)
        T = pose_matrix(pos, rot)
        try:
            circle = elbow_circle(self.geom, T)
        except UnreachableError:
            return None
        pick = self.solve(T, s, q_prev, dt)
        return None if pick is None else (pos, rot, T, circle, pick)

    def _yield_swivel(self, T: np.ndarray, s0: float, s1: float, q_prev: np.ndarray, dt: float,
                      ratio: float) -> tuple[float, np.ndarray, float] | None:
        """Shorten only the swivel change so the joint velocities fit; None if the hand motion alone
        is already too fast (then the whole step is shortened)."""
        ds = wrap_angle(s1 - s0)
        fracs = (0.98 / ratio, 0.5 / ratio, 0.0) if math.isfinite(ratio) else (0.5, 0.1, 0.0)
        best: tuple[float, np.ndarray, float] | None = None
        for frac in fracs:
            s = wrap_angle(s0 + frac * ds)
            pick = self.solve(T, s, q_prev, dt)
            if pick is None or pick[1] > self.flip_ratio:
                continue
            if best is None or pick[1] < best[2]:
                best = (s, pick[0], pick[1])
            if pick[1] <= 1.0 + 1e-9:
                return best
        return best

    def _search_swivel(self, T: np.ndarray, s_new: float, q_prev: np.ndarray, dt: float
                       ) -> tuple[tuple[np.ndarray, float] | None, float]:
        """The swivel nearest ``s_new`` with a continuous solution: the first of s_new +- k
        ``search_step`` (k = 1 .. ``search_count``) that has one, then bisected towards the step before
        it (which had none) to :data:`SEARCH_BISECTIONS` halvings. A whole search step would be a jump
        of the elbow: at a joint limit, where the swivel is held and the hand drifts by a hair, the
        elbow was thrown back 0.03 rad in one step and swung off, taking the hand 15 mm off its goal."""
        for k in range(1, self.search_count + 1):
            for sign in (1.0, -1.0):
                s_try = wrap_angle(s_new + sign * k * self.search_step)
                pick = self.solve(T, s_try, q_prev, dt)
                if pick is not None and pick[1] <= self.flip_ratio:
                    s_bad = wrap_angle(s_new + sign * (k - 1) * self.search_step)
                    return self._bisect_edge(T, s_bad, s_try, pick, q_prev, dt)
        return None, s_new

    def _bisect_edge(self, T: np.ndarray, s_bad: float, s_ok: float, pick: tuple[np.ndarray, float],
                     q_prev: np.ndarray, dt: float) -> tuple[tuple[np.ndarray, float], float]:
        """Between swivel ``s_bad`` (no continuous solution) and ``s_ok`` (``pick``), the swivel with one
        nearest ``s_bad`` to :data:`SEARCH_BISECTIONS` halvings, and its pick."""
        for _ in range(SEARCH_BISECTIONS):
            s_mid = wrap_angle(s_bad + 0.5 * wrap_angle(s_ok - s_bad))
            mid = self.solve(T, s_mid, q_prev, dt)
            if mid is not None and mid[1] <= self.flip_ratio:
                s_ok, pick = s_mid, mid
            else:
                s_bad = s_mid
        return pick, s_ok

    def _scale_step(self, pos0: Vec3, rot0: Quat, s0: float, pos1: Vec3, rot1: Quat, s1: float,
                    q_prev: np.ndarray, dt: float, ratio: float, swivel: SwivelFn | None = None
                    ) -> tuple[Vec3, Quat, float, np.ndarray, ElbowCircle, float] | None:
        """The step shortened until no joint is too fast: pose and swivel change in proportion, or, with
        ``swivel``, the swivel it gives at the shortened pose."""
        frac = 1.0
        for _ in range(4):
            frac *= 0.98 / ratio  # shorten the (already shortened) step by the excess ratio
            s = wrap_angle(s0 + frac * wrap_angle(s1 - s0))
            if swivel is not None:
                pos, rot = blend(pos0, rot0, pos1, rot1, frac)
                T = pose_matrix(pos, rot)
                try:
                    s = swivel(elbow_circle(self.geom, T), T, s0)[0]
                except UnreachableError:
                    return None
            tried = self._solve_blend(pos0, rot0, pos1, rot1, frac, s, q_prev, dt)
            if tried is None:
                return None
            pos, rot, _, circle, (q, ratio) = tried
            if ratio <= 1.0 + 1e-9:
                return pos, rot, s, q, circle, frac
        return None
