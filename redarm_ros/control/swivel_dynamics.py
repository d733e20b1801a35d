"""Swivel-angle dynamics of the swivel paper, eq. (30)-(32), in angle and swivel-quaternion form.

    tau * ds/dt = l1 * h(s_des - s) + l_obs * F_obs + l_sing * F_sing + l_lim * F_lim       (31)

``h`` is an odd, non-decreasing saturation (``tanh`` by default, eq. 32), so ``s_des`` is a stable
fixed point (slope ``-l1 h'(0) / tau < 0``). Each force ``F`` is dimensionless: its *direction*
comes from probing the constraint at ``s + eps`` and ``s - eps`` (the paper's "small increments and
decrements of s", or the rotations ``r+/- u`` with ``r = cos(eps) + sin(eps) k`` in quaternion form),
its *amplitude* from how close the constraint is (for obstacles the inverse clearance, as the paper
says). A force is positive when increasing ``s`` relieves the constraint.

The swivel-quaternion form keeps ``u = ux i + uy j`` (unit, in the xy plane) as the state and uses
no trigonometric call in the loop: the angle error enters through ``2 tan(delta/2) = 2 sin/(1 + cos)``
(computed from the cross and dot products of ``u`` and ``u_des``; equal to ``delta`` to first order,
odd and strictly increasing on (-pi, pi)), the probe rotations use the constants ``cos(eps)``,
``sin(eps)``, and the Euler step ``u <- normalise(u + omega dt k x u)`` needs one square root.

Units: s, s_des, eps in rad; tau, dt in s; rates in rad/s; distances in m.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from redarm_ros.control.elbow import ElbowCircle
from redarm_ros.geometry.obstacles import ELBOW_LINKS, ArmCapsules, Scene, links_clearance
from redarm_ros.param_table import declared

Saturation = Callable[[float], float]
Vec3 = tuple[float, float, float]


def wrap_angle(x: float) -> float:
    """Wrap an angle (rad) into (-pi, pi]."""
    y = math.fmod(x + math.pi, 2.0 * math.pi)
    if y <= 0.0:
        y += 2.0 * math.pi
    return y - math.pi


@declared("swivel")
class SwivelParams:
    """Parameters of eq. (31) and of its forces: the time scale ``tau``, the weights ``l_i`` (``lam_*``),
    and how each force's direction (probe ``eps``) and amplitude are found."""


def smooth_sign(x: float, scale: float) -> float:
    """tanh(x / scale): a sign that is smooth within +/- scale of zero."""
    return math.tanh(x / scale)


def obstacle_amplitude(d: float, p: SwivelParams) -> float:
    """Inverse-distance amplitude of the obstacle force for clearance ``d`` (m), zero beyond influence."""
    if d >= p.obs_influence:
        return 0.0
    return p.obs_ref / max(abs(d), p.obs_min) - p.obs_ref / p.obs_influence if d > 0.0 else (
        p.obs_ref / p.obs_min - p.obs_ref / p.obs_influence)


def ramp_amplitude(x: float, threshold: float) -> float:
    """1 at x <= 0, falling linearly to 0 at x >= threshold (amplitude of singularity/limit forces)."""
    if x >= threshold:
        return 0.0
    if x <= 0.0:
        return 1.0
    return 1.0 - x / threshold


def probe_direction(f_plus: float, f_minus: float, eps: float, scale: float, bias: float = 0.0) -> float:
    """Smooth sign of the central difference ``(f_plus - f_minus) / (2 eps) + bias`` (scale: its unit)."""
    return smooth_sign((f_plus - f_minus) / (2.0 * eps) + bias, scale)


def singularity_measure(points: Sequence[Sequence[float]]) -> float:
    """How far the swivel-dependent joints are from a singularity, from the key points.

    min(|sin theta2|, |sin theta6|) for a z-y-z shoulder with a vertical first axis through the
    shoulder and a spherical wrist: |sin theta2| is the horizontal offset of the elbow from the
    shoulder axis over the upper-arm length; |sin theta6| the sine of the forearm-hand angle.
    ``points`` = base, shoulder, elbow, wrist, tool (m). Returns a value in [0, 1].
    """
    _, ps, pe, pw, pt = points
    ux, uy, uz = pe[0] - ps[0], pe[1] - ps[1], pe[2] - ps[2]
    lu = math.sqrt(ux * ux + uy * uy + uz * uz)
    s2 = math.hypot(ux, uy) / lu if lu > 0.0 else 0.0
    fx, fy, fz = pw[0] - pe[0], pw[1] - pe[1], pw[2] - pe[2]
    hx, hy, hz = pt[0] - pw[0], pt[1] - pw[1], pt[2] - pw[2]
    cx, cy, cz = fy * hz - fz * hy, fz * hx - fx * hz, fx * hy - fy * hx
    lf = math.sqrt(fx * fx + fy * fy + fz * fz)
    lh = math.sqrt(hx * hx + hy * hy + hz * hz)
    s6 = math.sqrt(cx * cx + cy * cy + cz * cz) / (lf * lh) if lf > 0.0 and lh > 0.0 else 1.0
    return min(s2, s6)


@dataclass(frozen=True)
class SwivelForces:
    """The dimensionless forces of eq. (31) at one instant, and what they were computed from.

    clearance: of the swivel-dependent links (m); gradient: its derivative w.r.t. s (m/rad);
    singularity: the measure of :func:`singularity_measure`.
    """

    obstacle: float = 0.0
    singularity: float = 0.0
    limits: float = 0.0
    clearance: float = math.inf
    gradient: float = 0.0
    singularity_value: float = 1.0


class SwivelDynamics:
    """Eq. (31) with Euler integration, in angle form (``step``) and quaternion form (``step_u``).

    ``h`` is the odd, non-decreasing saturation (default ``math.tanh``).
    """

    def __init__(self, params: SwivelParams | None = None, h: Saturation = math.tanh) -> None:
        self.params = params or SwivelParams()
        self.h = h
        self._ce = math.cos(self.params.eps)
        self._se = math.sin(self.params.eps)

    # -- attractor -------------------------------------------------------------------------------
    def attractor(self, s: float, s_des: float) -> float:
        """h(s_des - s) with the difference wrapped into (-pi, pi] (short way around the circle)."""
        return self.h(wrap_angle(s_des - s))

    def attractor_u(self, u: Sequence[float], u_des: Sequence[float]) -> float:
        """Quaternion-form attractor: h(2 tan(delta / 2)), delta = angle from u to u_des, no trig."""
        sin_d = u[0] * u_des[1] - u[1] * u_des[0]
        cos_d = u[0] * u_des[0] + u[1] * u_des[1]
        den = 1.0 + cos_d
        if den < 1e-12:  # antipodal: any direction is downhill; break the tie consistently
            return self.h(1e12) if sin_d >= 0.0 else -self.h(1e12)
        return self.h(2.0 * sin_d / den)

    # -- rate and Euler step ---------------------------------------------------------------------
    def _total(self, attract: float, f: SwivelForces | None) -> float:
        p = self.params
        total = p.lam_des * attract
        if f is not None:
            total += p.lam_obs * f.obstacle + p.lam_sing * f.singularity + p.lam_lim * f.limits
        rate = total / p.tau
        return max(-p.max_rate, min(p.max_rate, rate))

    def rate(self, s: float, s_des: float, forces: SwivelForces | None = None) -> float:
        """ds/dt (rad/s) of eq. (31)."""
        return self._total(self.attractor(s, s_des), forces)

    def step(self, s: float, s_des: float, dt: float, forces: SwivelForces | None = None) -> float:
        """One forward-Euler step of ``dt`` seconds; returns the new swivel angle wrapped to (-pi, pi]."""
        return wrap_angle(s + dt * self.rate(s, s_des, forces))

    def rate_u(self, u: Sequence[float], u_des: Sequence[float], forces: SwivelForces | None = None) -> float:
        """Angular rate (rad/s) of the swivel quaternion, eq. (31) in quaternion form."""
        return self._total(self.attractor_u(u, u_des), forces)

    def step_u(self, u: Sequence[float], u_des: Sequence[float], dt: float,
               forces: SwivelForces | None = None) -> tuple[float, float]:
        """One Euler step of the swivel quaternion: ``u + omega dt (k x u)``, renormalised."""
        w = dt * self.rate_u(u, u_des, forces)
        x, y = u[0] - w * u[1], u[1] + w * u[0]
        n = math.sqrt(x * x + y * y)
        return x / n, y / n

    def probes_u(self, u: Sequence[float]) -> tuple[tuple[float, float], tuple[float, float]]:
        """``r+ u`` and ``r- u`` with ``r+/- = cos(eps) +/- sin(eps) k`` (constants, no trig here)."""
        c, s = self._ce, self._se
        return (c * u[0] - s * u[1], s * u[0] + c * u[1]), (c * u[0] + s * u[1], -s * u[0] + c * u[1])

    # -- forces from the elbow circle ------------------------------------------------------------
    def forces(self, circle: ElbowCircle, s: float, scene: Scene | None, capsules: ArmCapsules,
               limit_margins: tuple[float, float, float] | None = None) -> SwivelForces:
        """Obstacle and singularity forces at swivel ``s`` (rad) for the tool pose of ``circle``.

        ``limit_margins``: joint-limit margin (rad) at ``(s, s + eps, s - eps)`` if the caller probed
        the IK there; None means no joint-limit force.
        """
        ux, uy = math.cos(s), math.sin(s)
        return self.forces_u(circle, (ux, uy), scene, capsules, limit_margins)

    def forces_u(self, circle: ElbowCircle, u: Sequence[float], scene: Scene | None, capsules: ArmCapsules,
                 limit_margins: tuple[float, float, float] | None = None) -> SwivelForces:
        """As :meth:`forces` for the swivel quaternion ``u``; probes with ``r+/- u``."""
        p = self.params
        up, um = self.probes_u(u)
        pts0 = circle.key_points_u(u[0], u[1])
        ptsp = circle.key_points_u(*up)
        ptsm = circle.key_points_u(*um)
        # Elbow height slope along +s, used to resolve symmetric cases upward.
        dz = (ptsp[2][2] - ptsm[2][2]) / (2.0 * p.eps)
        # Tie-break only (|up_bias| < grad_scale), fading out at the top of the circle where dz ~ 0.
        up_bias = p.up_bias * smooth_sign(dz, 0.05)
        f_obs = 0.0
        d0 = math.inf
        grad = 0.0
        if scene is not None and (len(scene.obstacles) or scene.table_height is not None):
            d0 = links_clearance(pts0, scene, capsules, ELBOW_LINKS).distance
            amp = obstacle_amplitude(d0, p)
            if amp > 0.0:
                dp = links_clearance(ptsp, scene, capsules, ELBOW_LINKS).distance
                dm = links_clearance(ptsm, scene, capsules, ELBOW_LINKS).distance
                grad = (dp - dm) / (2.0 * p.eps)
                f_obs = amp * smooth_sign(grad + up_bias, p.grad_scale)
        sig0 = singularity_measure(pts0)
        f_sing = 0.0
        amp = ramp_amplitude(sig0, p.sing_threshold)
        if amp > 0.0:
            sp = singularity_measure(ptsp)
            sm = singularity_measure(ptsm)
            f_sing = amp * probe_direction(sp, sm, p.eps, 0.05)
        f_lim = 0.0
        if limit_margins is not None:
            m0, mp, mm = limit_margins
            amp = ramp_amplitude(m0, p.lim_threshold)
            if amp > 0.0:
                f_lim = amp * probe_direction(mp, mm, p.eps, 0.05)
        return SwivelForces(f_obs, f_sing, f_lim, d0, grad, sig0)
