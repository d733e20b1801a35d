"""The IK step of the reference for the 6-DOF PowerCube arm (joint 3 locked): no swivel, the analytic IK
(:mod:`redarm_ros.kinematics.powercube6`) at every step, on the branch of the current configuration.

The arm has one solution per *branch* of a reachable pose (:func:`branch`): the base azimuth points
at the tool (``front``) or away from it, reaching over the base axis (``back``); the elbow bends one
way or the other (the sign of the elbow pitch ``q[3]``). :meth:`IKStepper6.advance` keeps the branch
of the previous reference (a branch is left only where the two meet: elbow straight, or the tool over
the base axis) and takes the solution nearest to it in time at the joint velocity limits, so a motion
never flips its elbow or turns its base half round.

With joint 3 locked the tool's approach axis (tool x) must lie in the arm's vertical plane: a
proposed orientation is first projected onto the reachable ones at the proposed position
(:meth:`IKStepper6.project`: the smallest rotation that brings the approach into that plane). The
goal itself is reachable (the goal check says so), so the projection vanishes at the goal and the
orientation dynamics converge there as for the 7-DOF arms.

The cascade when a step does not fit: no solution on the branch at the projected orientation (a
joint limit, typically the wrist pitch while the hand rises or dips with a fixed approach) tilts the
approach in the arm's plane, then rolls the tool about it, by the smallest multiple of
``search_step`` up to ``search_count`` of them that has one (the 6-DOF arm's counterpart of the 7-DOF
swivel search: the orientation yields on the way, the orientation attractor brings it back, and the
goal itself is reachable); a joint faster than its velocity limit shortens the whole step; no solution
at all (out of the workspace) halves it, up to eight times; then a
:class:`~redarm_ros.control.ik_step.DeadEnd`. The ``circle`` of an :class:`~redarm_ros.control.ik_step.IKStep`
is a degenerate elbow circle of radius 0 through the configuration's own key points
(:func:`fixed_circle`), so that everything that reads the arm's key points from the reference's
circle (obstacle sliding, the broad phase, the display) sees the actual arm. Units: m, rad, s;
quaternions (w, x, y, z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.ik_step import DEAD_END, DeadEnd, IKStep, StepperBase, blend, pose_matrix
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.kinematics.protocols import ControlledArm6
from redarm_ros.kinematics.quaternion import (
    matrix_from_quat,
    quat_angle,
    quat_between_vectors,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
)

__all__ = ["Branch", "IKStepper6", "Route6", "branch", "check_route6", "fixed_circle", "is_6dof"]

#: Below this elbow pitch (rad) or radial tool distance (m) the two branches meet: either may follow.
BRANCH_TOL = 1e-3


def is_6dof(arm: object) -> bool:
    """Is ``arm`` the 6-DOF PowerCube arm (analytic IK with joint 3 locked, no swivel)?"""
    return getattr(arm, "kind", "") == "powercube6" and getattr(arm, "n", None) == 6


@dataclass(frozen=True)
class Branch:
    """The IK branch of a configuration: ``elbow``, the sign of the elbow pitch ``q[3]`` (0: straight,
    where the two elbow branches meet), and ``front`` (+1: the base azimuth points at the tool, -1:
    away from it, reaching over the base axis; 0: the tool is over the axis)."""

    front: int
    elbow: int

    def admits(self, other: Branch) -> bool:
        """May a motion go from this branch to ``other`` without an elbow flip? Only the elbow is a
        branch of the motion: the tool may pass over the base axis with continuous joints (``front``
        changes sign), while turning the base half round is a jump that the step's continuity rule
        (``flip_ratio``) refuses anyway."""
        return self.elbow == 0 or other.elbow == 0 or self.elbow == other.elbow

    @property
    def elbow_up(self) -> bool | None:
        """Is the elbow above the shoulder-wrist line? (None where that is undefined.) With the tool in
        front a negative elbow pitch bends the forearm down from a raised elbow; reaching over the
        base axis the plane is mirrored."""
        if self.elbow == 0 or self.front == 0:
            return None
        return self.elbow * self.front < 0

    def describe(self) -> str:
        """'front, elbow up'-style text."""
        f = {1: "front", -1: "back (reaching over the base axis)", 0: "tool over the base axis"}[self.front]
        up = self.elbow_up
        if self.elbow == 0:
            e = "elbow straight"
        elif up is None:
            e = f"elbow pitch {'+' if self.elbow > 0 else '-'}"
        else:
            e = "elbow up" if up else "elbow down"
        return f"{f}, {e}"


def _radial(arm: ControlledArm6, q: np.ndarray) -> float:
    """Signed horizontal distance (m) of the tool from the base axis along the arm's plane (eq. 2 with
    joint 3 locked)."""
    L1, L23, L4, L56 = arm.link_lengths
    a2, a4 = float(q[1]), float(q[1] + q[3])
    return L1 + L23 * math.cos(a2) + L4 * math.cos(a4) + L56 * math.cos(a4 + float(q[4]))


def branch(arm: ControlledArm6, q: Any) -> Branch:
    """The :class:`Branch` of configuration ``q`` (rad) of the 6-DOF arm."""
    qa = np.asarray(q, float)
    r = _radial(arm, qa)
    front = 0 if abs(r) < BRANCH_TOL else (1 if r > 0.0 else -1)
    e = float(qa[3])
    elbow = 0 if abs(e) < BRANCH_TOL else (1 if e > 0.0 else -1)
    return Branch(front, elbow)


def fixed_circle(kp: Any) -> ElbowCircle:
    """A degenerate elbow circle (radius 0) through key points ``kp`` (5, 3) base, shoulder, elbow,
    wrist, tool (m): its key points at any swivel are ``kp``."""
    p = [tuple(float(c) for c in v) for v in np.asarray(kp, float)]
    return ElbowCircle(p[2], (0.0, 0.0, 1.0), 0.0, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), p[0], p[1], p[3], p[4])


class IKStepper6(StepperBase):
    """The IK step of the 6-DOF arm (see the module docstring). ``flip_ratio``: a joint step above
    ``flip_ratio * max_vel * dt`` is a branch change, never taken; ``search_step`` (rad) and
    ``search_count``: the orientation search where the projected orientation has no solution."""

    def __init__(self, arm: ControlledArm6, flip_ratio: float, search_step: float = 0.03,
                 search_count: int = 10) -> None:
        super().__init__(arm, flip_ratio, search_step, search_count)
        self.min_vel = float(np.min(np.asarray(arm.max_vel, float)))
        self.wide: list[int] = []  # no joint of the PowerCube arm turns more than a full turn

    # -- geometry ---------------------------------------------------------------------------------
    def azimuth(self, pos: Vec3, q_prev: np.ndarray) -> float:
        """Base azimuth (rad) of the arm plane through ``pos`` on the branch of ``q_prev``: the one of
        atan2(y, x) and atan2(y, x) + pi nearest to ``q_prev[0]``."""
        if math.hypot(pos[0], pos[1]) < 1e-9:
            return float(q_prev[0])
        a = math.atan2(pos[1], pos[0])
        b = math.remainder(a + math.pi, 2.0 * math.pi)
        da = abs(math.remainder(a - float(q_prev[0]), 2.0 * math.pi))
        db = abs(math.remainder(b - float(q_prev[0]), 2.0 * math.pi))
        return a if da <= db else b

    def project(self, pos: Vec3, rot: Quat, q_prev: np.ndarray) -> Quat | None:
        """The reachable orientation nearest ``rot`` at position ``pos``: ``rot`` turned by the
        smallest rotation that brings the approach (tool x) into the vertical plane through ``pos``;
        None if the approach is perpendicular to that plane (no nearest one)."""
        phi = self.azimuth(pos, q_prev)
        nx, ny = -math.sin(phi), math.cos(phi)  # normal of the arm plane
        R = matrix_from_quat(rot)
        ax, ay, az = R[0][0], R[1][0], R[2][0]
        off = ax * nx + ay * ny
        if abs(off) < 1e-12:
            return rot
        px, py, pz = ax - off * nx, ay - off * ny, az
        n = math.sqrt(px * px + py * py + pz * pz)
        if n < 1e-6:
            return None
        turn = quat_between_vectors((ax, ay, az), (px / n, py / n, pz / n))
        return quat_normalize(quat_mul(turn, rot))

    # -- selection --------------------------------------------------------------------------------
    def select(self, sols: np.ndarray, q_ref: np.ndarray, dt: float) -> tuple[np.ndarray, float] | None:
        """The solution on the branch of ``q_ref`` nearest to it in time at the velocity limits, and its
        ratio to the limit over ``dt``; None if no solution is on that branch."""
        if sols.shape[0] == 0:
            return None
        b0 = branch(self.arm, q_ref)
        keep = [i for i in range(sols.shape[0]) if b0.admits(branch(self.arm, sols[i]))]
        if not keep:
            return None
        s = sols[keep]
        ratios = np.max(np.abs(s - q_ref) * self.inv_vel, axis=1) / dt
        i = int(np.argmin(ratios))
        return s[i].copy(), float(ratios[i])

    def solve(self, T: np.ndarray, s: float, q_ref: np.ndarray, dt: float) -> tuple[np.ndarray, float] | None:
        """:meth:`select` over the IK solutions of ``T`` (``s`` is ignored: no swivel)."""
        return self.select(np.asarray(self.arm.ik(T), float).reshape(-1, self.arm.n), q_ref, dt)

    def search(self, pos: Vec3, rot: Quat, q_prev: np.ndarray, dt: float
               ) -> tuple[Quat, tuple[np.ndarray, float]] | None:
        """The nearest orientation to ``rot`` (in the arm's plane at ``pos``) with a continuous solution:
        the approach tilted in the plane, then the tool rolled about the approach, by +-k steps
        (k = 1 .. ``search_count``, smallest first) of ``search_step``, or of half what the slowest
        joint turns in ``dt`` if that is less (so that a found step can be within the velocity limits);
        None if none has one."""
        step = min(self.search_step, 0.5 * dt * self.min_vel)
        phi = self.azimuth(pos, q_prev)
        normal = (-math.sin(phi), math.cos(phi), 0.0)
        R = matrix_from_quat(rot)
        approach = (R[0][0], R[1][0], R[2][0])
        T = pose_matrix(pos, rot)
        for axis in (normal, approach):
            for k in range(1, self.search_count + 1):
                for sign in (1.0, -1.0):
                    a = sign * k * step
                    turn = quat_from_rotvec((a * axis[0], a * axis[1], a * axis[2]))
                    r = quat_normalize(quat_mul(turn, rot))
                    T[:3, :3] = matrix_from_quat(r)
                    pick = self.solve(T, 0.0, q_prev, dt)
                    if pick is not None and pick[1] <= self.flip_ratio:
                        return r, pick
        return None

    def circle(self, q: np.ndarray) -> ElbowCircle:
        """:func:`fixed_circle` of configuration ``q``."""
        return fixed_circle(self.arm.key_points(q))

    # -- the cascade ------------------------------------------------------------------------------
    def advance(self, pos0: Vec3, rot0: Quat, s0: float, q_prev: np.ndarray, new_pos: Vec3, new_rot: Quat,
                dt: float, swivel: Any = None, pose_swivel: bool = False) -> IKStep | DeadEnd:
        """The reference step from (``pos0``, ``rot0``, joints ``q_prev``) towards the proposed pose
        (``s0``, ``swivel`` and ``pose_swivel`` are accepted for the 7-DOF signature and ignored)."""
        scale = 1.0
        for _attempt in range(8):
            rot = self.project(new_pos, new_rot, q_prev)
            pick = None
            if rot is not None:
                pick = self.solve(pose_matrix(new_pos, rot), 0.0, q_prev, dt)
                if pick is None or pick[1] > self.flip_ratio:
                    # A joint limit at this orientation: let the orientation yield (tilt, roll).
                    found = self.search(new_pos, rot, q_prev, dt)
                    if found is not None:
                        rot, pick = found
            if pick is None or pick[1] > self.flip_ratio:
                # No solution on this branch here (workspace, joint limit, or only by a flip): shorter.
                new_pos, new_rot = blend(pos0, rot0, new_pos, new_rot, 0.5)
                scale *= 0.5
                continue
            q_new, ratio = pick
            if ratio > 1.0 + 1e-9:  # too fast for a joint: shorten the whole step
                frac = 0.98 / ratio
                new_pos, new_rot = blend(pos0, rot0, new_pos, new_rot, frac)
                scale *= frac
                continue
            assert rot is not None
            return IKStep(q_new, new_pos, rot, 0.0, 0.0, self.circle(q_new), scale)
        return DeadEnd(DEAD_END, scale)


@dataclass(frozen=True)
class Route6:
    """Outcome of :func:`check_route6`: ``dead_end`` ('' if the straight route is continuous on the
    start's branch), the least time (s) it needs at the hand, orientation and joint velocity limits
    (inf at a dead end) and the configuration it ends in."""

    dead_end: str
    time: float
    q_end: np.ndarray | None


def check_route6(stepper: IKStepper6, T0: np.ndarray, q0: np.ndarray, T_goal: np.ndarray, steps: int,
                 v_max: float, w_max: float) -> Route6:
    """March the straight Cartesian route from ``T0`` (joints ``q0``) to ``T_goal`` through the
    branch-keeping IK step: a goal that the start's branch cannot reach continuously (e.g. only with the
    other elbow) is a dead end, to be reached by a joint-space move instead."""
    p0 = (float(T0[0, 3]), float(T0[1, 3]), float(T0[2, 3]))
    pg = (float(T_goal[0, 3]), float(T_goal[1, 3]), float(T_goal[2, 3]))
    r0, rg = quat_from_matrix(T0[:3, :3]), quat_from_matrix(T_goal[:3, :3])
    duration = max(math.dist(p0, pg) / v_max, quat_angle(r0, rg) / w_max, 0.05)
    dt = duration / steps
    q = q0
    total = 0.0
    for k in range(1, steps + 1):
        pos, rot = blend(p0, r0, pg, rg, k / steps)
        rp = stepper.project(pos, rot, q)
        pick = None if rp is None else stepper.solve(pose_matrix(pos, rp), 0.0, q, dt)
        if pick is None or pick[1] > stepper.flip_ratio:
            b = branch(stepper.arm, q).describe()
            return Route6(f"the straight route has no continuous in-limit solution on the current branch "
                          f"({b}) at {100 * k // steps} %", math.inf, None)
        total += max(dt, float(np.max(np.abs(pick[0] - q) * stepper.inv_vel)))
        q = pick[0]
    return Route6("", total, q)
