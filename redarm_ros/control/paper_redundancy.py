"""The attractor paper's own redundancy dynamics and path-tangent hand orientation (``swivel_mode:
attractor_paper``).

Iossifidis & Schoener resolve the redundancy of the arm with a dynamics of the redundancy angle
``alpha`` (our swivel ``s``; the paper's redundancy circle is our elbow circle), eq. (22)-(24):

    d alpha/dt = h_tar(alpha) + sum_i h_obs,i(alpha) + sum_i h_Jlim,i(alpha)
    h_tar      = -lam_tar sin(alpha - alpha_tar)                                      (22, sign-corrected)
    h_obs,i    = lam_obs sin(alpha - kappa_i) exp(-(alpha - kappa_i)^2 / 2 sigma_i^2) exp(-d / d0)  (23)
    h_Jlim,i   = lam_lim sin(alpha - kappa_i) exp(-(alpha - kappa_i)^2 / 2 sigma_i^2)                (24)

Constraints enter as *sectors* of the redundancy circle that are disallowed: each force-let repels
from the centre ``kappa_i`` of one sector with range ``sigma_i = 2 delta_i`` (``delta_i`` its half
width, section II-B). The paper computes them from a cylinder model of the obstacles and from the
wrist's joint limit; here the circle is sampled (``samples`` swivels on a fixed grid):

* an **obstacle sector** is a run of swivels at which the upper arm or forearm capsule comes closer
  than ``obs_distance`` to an obstacle or the table (the paper: "an obstacle that reaches up to the
  elbow"); ``d`` in eq. (23) is the clearance of those links at the current swivel;
* a **wrist-limit sector** is a run of swivels at which the joint solution on the current branch
  brings a wrist joint (the last three) within ``wrist_margin`` of its limit, or has no in-limit
  solution at all (the paper: "the most important joint angle limitation concerns the wrist").

The target term is the preferred swivel (``alpha_tar``: the controller's ``s_des``). As printed, eq.
(22) has the sign of a repeller (see :mod:`redarm_ros.control.attractor`); it is used sign-corrected.
The rate is clamped to the swivel dynamics' ``max_rate``; the controller's acceleration limit on the
swivel rate and its IK step apply as in the default mode.

The hand orientation of the same paper, eq. (20)-(21): the hand's azimuth and elevation relax to the
angles of the end-effector path's tangent ``s_T = (r(t_n) - r(t_{n-1})) / |...|`` (moving attractors,
rate ``lam_hand``, sign-corrected), so the hand trails the collision-free path of the end effector.
Our goals carry a full orientation, so near the goal the tool axis blends back to the goal's (see
:class:`TangentHand`).

Units: rad, rad/s, m, s; quaternions (w, x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from redarm_ros.control.attractor import direction, forcelet, heading_angles, target_attractor
from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.control.types import Quat, Vec3
from redarm_ros.geometry.obstacles import ELBOW_LINKS, ArmCapsules, Scene, links_clearance
from redarm_ros.kinematics.quaternion import (
    quat_between_vectors,
    quat_mul,
    quat_normalize,
    quat_rotate,
    slerp_vectors,
)
from redarm_ros.param_table import declared

__all__ = ["PaperSwivel", "PaperSwivelParams", "PaperSwivelStep", "Sector", "TangentHand", "sectors"]

MODE = "attractor_paper"  # the ControllerParams.swivel_mode that selects this module


@declared("paper_swivel")
class PaperSwivelParams:
    """Parameters of eq. (20)-(24) as used here (rates 1/s, lengths m, angles rad): the force-lets of the
    redundancy angle, the sampled sectors they come from, and the hand's path-tangent attractors."""


@dataclass(frozen=True)
class Sector:
    """A disallowed sector of the redundancy circle: centre ``kappa`` and half width ``delta`` (rad)."""

    kappa: float
    delta: float


def sectors(blocked: Sequence[bool], angles: Sequence[float]) -> list[Sector]:
    """Every contiguous run of ``blocked`` samples at ``angles`` (uniform steps covering 2 pi, any start)
    as a :class:`Sector` (runs wrap around the end). Empty if nothing or everything is blocked (a fully
    blocked circle has no centre to repel from)."""
    n = len(blocked)
    if n == 0 or not any(blocked) or all(blocked):
        return []
    step = 2.0 * math.pi / n
    start = next(i for i in range(n) if not blocked[i])  # runs never straddle the start then
    out = []
    k = 0
    while k < n:
        i = (start + k) % n
        if not blocked[i]:
            k += 1
            continue
        length = 0
        while k < n and blocked[(start + k) % n]:
            length += 1
            k += 1
        out.append(Sector(wrap_angle(angles[i] + 0.5 * (length - 1) * step), 0.5 * length * step))
    return out


@dataclass(frozen=True)
class PaperSwivelStep:
    """One step of eq. (22)-(24): the new swivel ``s`` (rad), the ``rate`` (rad/s) and its parts, the
    clearance (m) of the swivel-dependent links at the old swivel, and the sectors found."""

    s: float
    rate: float
    target: float
    obstacle: float
    limits: float
    clearance: float
    obstacle_sectors: tuple[Sector, ...]
    limit_sectors: tuple[Sector, ...]


class PaperSwivel:
    """Eq. (22)-(24) with sampled obstacle and wrist-limit sectors (see the module docstring).

    Args:
        params: :class:`PaperSwivelParams`.
        capsules: the controller's link radii.
        max_rate: clamp on |ds/dt| (rad/s).
        lower, upper: joint limits (rad) of the arm.
    """

    def __init__(self, params: PaperSwivelParams, capsules: ArmCapsules, max_rate: float,
                 lower: Sequence[float], upper: Sequence[float]) -> None:
        self.params = params
        self.capsules = capsules
        self.max_rate = float(max_rate)
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)
        n = params.samples
        self._angles = [wrap_angle(-math.pi + 2.0 * math.pi * k / n) for k in range(n)]
        self._steps = 0
        self._obs_sectors: list[Sector] = []
        self._lim_sectors: list[Sector] = []

    def step(self, circle: ElbowCircle, T: np.ndarray, s: float, s_des: float, q_ref: np.ndarray, dt: float,
             scene: Scene | None, stepper: Any) -> PaperSwivelStep:
        """One forward-Euler step of ``dt`` s from swivel ``s`` towards ``s_des`` for the tool pose
        ``T`` whose elbow circle is ``circle``; ``q_ref`` (the current joints) picks the branch and
        ``stepper`` (an :class:`~redarm_ros.control.ik_step.IKStepper`) solves the IK of the samples."""
        p = self.params
        refresh = self._steps % p.refresh_steps == 0
        self._steps += 1
        # A grid fixed on the circle (not moving with s): the sectors change only when the blocked set
        # does, so a swivel at rest next to a sector does not see its centre jitter.
        angles = self._angles
        # Obstacle sectors (only when an obstacle or the table is near enough to matter).
        clear = math.inf
        if scene is not None and (len(scene.obstacles) or scene.table_height is not None):
            caps = self.capsules
            clear = links_clearance(circle.key_points(s), scene, caps, ELBOW_LINKS).distance
            if refresh:
                self._obs_sectors = []
                if clear < p.obs_cutoff:
                    blocked = [links_clearance(circle.key_points(a), scene, caps, ELBOW_LINKS).distance
                               < p.obs_distance for a in angles]
                    self._obs_sectors = sectors(blocked, angles)
        elif refresh:
            self._obs_sectors = []
        if refresh:
            # Wrist-limit sectors: the branch nearest the current joints at each sampled swivel.
            lo, hi = self.lower[-3:], self.upper[-3:]
            blocked_lim = []
            for a in angles:
                pick = stepper.solve(T, a, q_ref, 1.0)
                if pick is None:
                    blocked_lim.append(True)
                    continue
                w = pick[0][-3:]
                blocked_lim.append(float(np.min(np.minimum(w - lo, hi - w))) < p.wrist_margin)
            self._lim_sectors = sectors(blocked_lim, angles)
        obs_sectors, lim_sectors = self._obs_sectors, self._lim_sectors
        h_tar = target_attractor(s, s_des, p.lam_tar)
        damp = math.exp(-max(clear, 0.0) / p.d0) if math.isfinite(clear) else 0.0
        h_obs = sum(forcelet(s, sec.kappa, p.lam_obs, 2.0 * sec.delta) for sec in obs_sectors) * damp
        h_lim = sum(forcelet(s, sec.kappa, p.lam_lim, 2.0 * sec.delta) for sec in lim_sectors)
        rate = max(-self.max_rate, min(self.max_rate, h_tar + h_obs + h_lim))
        return PaperSwivelStep(wrap_angle(s + dt * rate), rate, h_tar, h_obs, h_lim, clear,
                               tuple(obs_sectors), tuple(lim_sectors))


class TangentHand:
    """Eq. (20)-(21): the hand's azimuth and elevation follow the path tangent as moving attractors.

    The state (hand angles) starts from the tool axis when a new goal is first seen. The orientation
    target is the goal orientation turned so that its tool axis points along the hand angles, fully
    beyond ``2 hand_distance`` from the goal, blending back to the goal's own axis at ``hand_distance``.
    """

    def __init__(self, params: PaperSwivelParams) -> None:
        self.params = params
        self._goal: object | None = None
        self._phi = 0.0
        self._theta = 0.0

    def target(self, goal: object, goal_rot: Quat, rot: Quat, tangent: Vec3 | None, dist: float,
               dt: float) -> Quat:
        """Orientation target (w, x, y, z) for this step: ``goal`` identifies the goal (a new one
        restarts the hand angles from the current tool axis ``rot``), ``tangent`` is the unit tangent of
        the end-effector path (None when not moving), ``dist`` (m) the distance to the goal."""
        p = self.params
        if goal is not self._goal:
            self._goal = goal
            self._phi, self._theta = heading_angles(quat_rotate(rot, (0.0, 0.0, 1.0)))
        if tangent is not None:
            phi_t, theta_t = heading_angles(tangent, self._phi)
            self._phi = wrap_angle(self._phi + dt * target_attractor(self._phi, phi_t, p.lam_hand))
            self._theta += dt * target_attractor(self._theta, theta_t, p.lam_hand)
            self._theta = max(-0.5 * math.pi, min(0.5 * math.pi, self._theta))
        w = max(0.0, min(1.0, (dist - p.hand_distance) / p.hand_distance))
        if w <= 0.0:
            return goal_rot
        g = quat_rotate(goal_rot, (0.0, 0.0, 1.0))
        a = slerp_vectors(g, direction(self._phi, self._theta), w)
        return quat_normalize(quat_mul(quat_between_vectors(g, a), goal_rot))
