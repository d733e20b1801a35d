"""Attractor dynamics of Iossifidis & Schoener: heading direction, hand orientation, redundancy angle.

Everything here is a first-order dynamical system ``dx/dt = f(x)`` integrated by forward Euler at the
controller rate; the planning variable sits in (or relaxes fast towards) an attractor.

Sign convention (checked by the tests): the paper prints the target terms as
``lambda * sin(x - x_tar)`` (eq. 20-22); with ``lambda > 0`` that has slope ``+lambda`` at ``x_tar``,
i.e. a *repeller*. The target terms here are ``-lambda * sin(x - x_tar)`` (slope ``-lambda < 0``: a
stable attractor). Obstacle force-lets ``+lambda * sin(x - x_i) * ...`` (eq. 18, 23, 24) are repellers
as printed (slope ``+lambda`` at ``x_i``).

Heading (eq. 17-19): the end effector moves along ``e(phi, theta) = (cos theta cos phi,
cos theta sin phi, sin theta)`` with azimuth ``phi`` and elevation ``theta`` (rad, theta above the
horizontal plane). Obstacles repel the azimuth with a limited angular range (eq. 18-19) and push the
elevation *up* to pass above them (one-sided; the elevation part of the paper's ref. [4] is not in our
copy, so this is our formulation: see :meth:`HeadingDynamics.rates`). The speed along the heading comes
from :class:`SpeedProfile` and stops at the target.

Units: angles rad, rates rad/s, lengths m, speeds m/s, times s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.geometry.obstacles import Obstacle
from redarm_ros.param_table import declared

Vec3 = tuple[float, float, float]


# ----------------------------------------------------------------------------------------------
# Elementary terms
# ----------------------------------------------------------------------------------------------


def target_attractor(x: float, x_tar: float, lam: float) -> float:
    """Stable attractor at ``x_tar``: ``-lam * sin(x - x_tar)`` (sign-corrected eq. 20-22), rad/s."""
    return -lam * math.sin(x - x_tar)


def paper_target_term(x: float, x_tar: float, lam: float) -> float:
    """The target term exactly as printed, ``lam * sin(x - x_tar)``: a repeller for ``lam > 0``.

    Kept only to document (and test) the sign error; the controller never uses it.
    """
    return lam * math.sin(x - x_tar)


def range_function(dx: float, delta: float, beta: float, margin: float) -> float:
    """Eq. (19): ``0.5 * (tanh(beta * (cos(dx) - cos(2 delta + margin))) + 1)``, in [0, 1].

    ``dx`` = heading minus obstacle direction (rad), ``delta`` = half angle under which the obstacle is
    seen (rad), ``margin`` = safety margin (rad), ``beta`` = sharpness.
    """
    return 0.5 * (math.tanh(beta * (math.cos(dx) - math.cos(min(2.0 * delta + margin, math.pi)))) + 1.0)


def forcelet(x: float, x_i: float, lam: float, sigma: float) -> float:
    """Repulsive force-let ``lam * sin(x - x_i) * exp(-(x - x_i)^2 / (2 sigma^2))`` (eq. 18, 23, 24).

    The difference is wrapped into (-pi, pi]; ``sigma`` (rad) is the angular range.
    """
    dx = wrap_angle(x - x_i)
    return lam * math.sin(dx) * math.exp(-dx * dx / (2.0 * sigma * sigma))


def obstacle_heading_term(phi: float, phi_i: float, d_i: float, delta_phi: float, lam: float, sigma: float,
                          d0: float, beta: float, margin: float) -> float:
    """Eq. (18): azimuth repeller of one obstacle seen under ``phi_i`` at distance ``d_i`` (m)."""
    dx = wrap_angle(phi - phi_i)
    return (forcelet(phi, phi_i, lam, sigma) * math.exp(-max(d_i, 0.0) / d0)
            * range_function(dx, delta_phi, beta, margin))


def direction(phi: float, theta: float) -> Vec3:
    """Unit vector of azimuth ``phi`` and elevation ``theta`` (rad)."""
    ct = math.cos(theta)
    return (ct * math.cos(phi), ct * math.sin(phi), math.sin(theta))


def heading_angles(v: Sequence[float], phi_default: float = 0.0) -> tuple[float, float]:
    """Azimuth and elevation (rad) of vector ``v``; ``phi_default`` where the azimuth is undefined."""
    h = math.hypot(v[0], v[1])
    phi = math.atan2(v[1], v[0]) if h > 1e-12 else phi_default
    return phi, math.atan2(v[2], h)


# ----------------------------------------------------------------------------------------------
# Heading-direction dynamics (eq. 17-19)
# ----------------------------------------------------------------------------------------------


@declared("heading")
class HeadingParams:
    """Parameters of the heading dynamics (rates in 1/s, lengths in m, angles in rad).

    The azimuth is attracted to the target's direction and repelled by obstacles (eq. 18, with the
    range function of eq. 19); the elevation is attracted to the target's and pushed up over obstacles
    (our formulation, see :meth:`HeadingDynamics.rates`). An obstacle ahead that the hand is not yet
    above also slows the hand (the speed dynamics of the dynamic approach to navigation).
    """


@dataclass(frozen=True)
class HeadingRates:  # a record of floats: alike in shape only to other records (mcap TopicSummary)
    """d(phi)/dt and d(theta)/dt (rad/s) plus the target direction and per-term parts for plots."""

    dphi: float
    dtheta: float
    phi_tar: float
    theta_tar: float
    obstacle_phi: float = 0.0
    obstacle_theta: float = 0.0
    speed_factor: float = 1.0
    applied: tuple[float, float] = (0.0, 0.0)


class HeadingDynamics:
    """Azimuth/elevation dynamics of the end-effector heading with a target and obstacle repellers."""

    def __init__(self, params: HeadingParams | None = None) -> None:
        self.params = params or HeadingParams()

    def rates(self, phi: float, theta: float, ee: Sequence[float], target: Sequence[float],
              obstacles: Sequence[Obstacle] = ()) -> HeadingRates:
        """Rates of the heading angles at end-effector position ``ee`` (m) toward ``target`` (m).

        Azimuth: ``-lam_tar sin(phi - phi_tar) + sum_i f_obs,i(phi)`` with eq. (17)-(19), where
        ``phi_i`` is the direction of the obstacle's vertical axis, ``d_i`` its signed distance from
        the end effector and ``delta_phi_i`` the half angle of its footprint; the term is faded out once
        the end effector is above the obstacle top plus ``clear_margin`` (it can pass above) and for
        obstacles beyond the target.

        Elevation: ``-(1 - b) lam_tar sin(theta - theta_tar) + sum_i g_i``, where ``g_i`` pulls the
        elevation up, and only up, towards the clearance elevation ``theta_c,i`` that passes
        ``clear_margin`` above the obstacle's top edge (near edge when below the top, far edge when
        above), weighted by the azimuth range function (only obstacles ahead count) and
        ``exp(-d_i / d0_up)``: ``g_i = lam_up * w_i * max(0, sin(theta_c,i - theta))``. ``b`` in [0, 1]
        measures how much an obstacle ahead, not yet cleared, blocks the way; it suspends a downward
        target pull (competitive dynamics) so that the elevation does settle at ``theta_c``.
        """
        p = self.params
        dx, dy, dz = target[0] - ee[0], target[1] - ee[1], target[2] - ee[2]
        phi_tar, theta_tar = heading_angles((dx, dy, dz), phi)
        dxy_tar = math.hypot(dx, dy)
        # (Straight above/below the target heading_angles returns phi_tar = phi: no azimuth drive.)
        dphi = target_attractor(phi, phi_tar, p.lam_tar)
        dtheta = target_attractor(theta, theta_tar, p.lam_tar)
        f_phi = 0.0
        f_theta = 0.0
        speed_factor = 1.0
        blocked = 0.0
        for o in obstacles:
            fp = o.footprint(ee[0], ee[1])
            near = fp.near
            # Obstacles whose near edge lies beyond the target do not constrain the path.
            gate = _logistic((dxy_tar - near) / p.target_gate) if p.target_gate > 0 else 1.0
            if gate < 1e-6:
                continue
            phi_i = fp.direction  # eq. (17), for the middle of the footprint as seen from the hand
            d_i = o.signed_distance(ee)
            delta = fp.half_angle
            dphi_i = wrap_angle(phi - phi_i)
            rng = range_function(dphi_i, delta, p.beta, p.range_margin)
            # Height still needed to pass above the top with the margin (m).
            h_need = o.top + p.clear_margin - ee[2]
            above = _logistic(h_need / 0.02)  # ~1 while below the clearance height
            f_phi += gate * above * obstacle_heading_term(phi, phi_i, d_i, delta, p.lam_obs, p.sigma, p.d0,
                                                          p.beta, p.range_margin)
            # Reach the clearance height a little before the near edge (the hand has a size).
            # Soft floor on the horizontal distance keeps theta_c continuous over the footprint.
            near_c = max(near - p.edge_margin, p.edge_soft)
            far = max(min(fp.far, dxy_tar), near_c)
            theta_c = max(math.atan2(h_need, near_c), math.atan2(h_need, far))
            if theta_c > theta:
                w = gate * rng * math.exp(-max(d_i, 0.0) / p.d0_up)
                f_theta += p.lam_up * w * math.sin(min(theta_c, 0.5 * math.pi) - theta)
                # Blocking the way and not yet cleared: slow down while the elevation rises.
                block = gate * rng * above * min(1.0, math.sin(min(theta_c, 0.5 * math.pi) - theta) / 0.3)
                slow = p.slow_min + (1.0 - p.slow_min) * min(1.0, max(d_i, 0.0) / p.slow_distance)
                speed_factor = min(speed_factor, 1.0 - block * (1.0 - slow))
                blocked = max(blocked, gate * rng * above * math.exp(-max(d_i, 0.0) / p.d0_up))
        # Competition: an obstacle that blocks the way suspends the target's pull on the elevation
        # (only when that pull is downward), so the elevation settles at the clearance elevation.
        if dtheta < 0.0:
            dtheta *= 1.0 - blocked
        return HeadingRates(dphi + f_phi, dtheta + f_theta, phi_tar, theta_tar, f_phi, f_theta, speed_factor)

    def step(self, phi: float, theta: float, dt: float, ee: Sequence[float], target: Sequence[float],
             obstacles: Sequence[Obstacle] = (), prev_rates: tuple[float, float] | None = None
             ) -> tuple[float, float, HeadingRates]:
        """One Euler step of ``dt`` s; the elevation stays in [-pi/2, pi/2].

        The applied rates are clamped to ``max_turn_rate``; with ``prev_rates`` (the rates applied in
        the previous step) their change is also limited to ``max_turn_acc * dt``, which bounds the
        lateral jerk of the hand when the target or the scene changes abruptly. The returned
        :class:`HeadingRates` carries the applied rates in ``applied``.
        """
        r = self.rates(phi, theta, ee, target, obstacles)
        p = self.params
        m = p.max_turn_rate
        dphi = max(-m, min(m, r.dphi))
        dtheta = max(-m, min(m, r.dtheta))
        if prev_rates is not None:
            da = p.max_turn_acc * dt
            dphi = max(prev_rates[0] - da, min(prev_rates[0] + da, dphi))
            dtheta = max(prev_rates[1] - da, min(prev_rates[1] + da, dtheta))
        phi_n = wrap_angle(phi + dt * dphi)
        theta_n = max(-0.5 * math.pi, min(0.5 * math.pi, theta + dt * dtheta))
        if theta_n in (-0.5 * math.pi, 0.5 * math.pi):
            dtheta = 0.0
        return phi_n, theta_n, replace(r, applied=(dphi, dtheta))


def _logistic(x: float) -> float:
    if x > 40.0:
        return 1.0
    if x < -40.0:
        return 0.0
    return 1.0 / (1.0 + math.exp(-x))


# ----------------------------------------------------------------------------------------------
# Hand orientation (eq. 20-21) and redundancy angle (eq. 22-24)
# ----------------------------------------------------------------------------------------------


def path_tangent(r_now: Sequence[float], r_prev: Sequence[float]) -> Vec3 | None:
    """Unit tangent ``(r(t_n) - r(t_{n-1})) / |...|`` of the end-effector path, None if not moving."""
    d = (r_now[0] - r_prev[0], r_now[1] - r_prev[1], r_now[2] - r_prev[2])
    n = math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    if n < 1e-12:
        return None
    return (d[0] / n, d[1] / n, d[2] / n)


def orientation_rates(phi_h: float, theta_h: float, phi_t: float, theta_t: float,
                      lam: float) -> tuple[float, float]:
    """Eq. (20)-(21), sign-corrected: hand azimuth/elevation relax to the path tangent's angles."""
    return target_attractor(phi_h, phi_t, lam), target_attractor(theta_h, theta_t, lam)


@dataclass(frozen=True)
class Forcelet:
    """A repulsive force-let on the redundancy circle: centre ``kappa`` (rad), range ``sigma`` (rad),
    strength ``lam`` (1/s) and optional distance ``d`` (m) scaled by ``d0`` (eq. 23: ``exp(-d/d0)``)."""

    kappa: float
    sigma: float
    lam: float
    d: float | None = None
    d0: float = 0.1

    def __call__(self, alpha: float) -> float:
        """Contribution (rad/s) at redundancy angle ``alpha``."""
        f = forcelet(alpha, self.kappa, self.lam, self.sigma)
        if self.d is not None:
            f *= math.exp(-max(self.d, 0.0) / self.d0)
        return f


def redundancy_rate(alpha: float, alpha_tar: float, lam_tar: float, obstacles: Sequence[Forcelet] = (),
                    limits: Sequence[Forcelet] = ()) -> float:
    """Eq. (22)-(24): ``d alpha/dt = h_tar + sum h_obs,i + sum h_Jlim,i`` (rad/s), target term stable."""
    rate = target_attractor(alpha, alpha_tar, lam_tar)
    for f in obstacles:
        rate += f(alpha)
    for f in limits:
        rate += f(alpha)
    return rate


def sector_forcelet(blocked: Sequence[bool], angles: Sequence[float], lam: float, d: float | None = None,
                    d0: float = 0.1) -> Forcelet | None:
    """Force-let for the largest contiguous blocked sector of a sampled redundancy circle.

    ``blocked[k]`` says whether angle ``angles[k]`` (uniform, increasing, covering 2 pi) is disallowed;
    the force-let is centred on the sector (kappa) with ``sigma = 2 * delta`` where delta is its half
    width (section II-B). None if nothing is blocked; if everything is, the centre is undefined: None.
    """
    n = len(blocked)
    if n == 0 or not any(blocked) or all(blocked):
        return None
    step = 2.0 * math.pi / n
    best = (0, 0)
    k = 0
    # Start at a free sample so that sectors do not wrap past the start.
    start = next(i for i in range(n) if not blocked[i])
    while k < n:
        i = (start + k) % n
        if blocked[i]:
            length = 0
            while k < n and blocked[(start + k) % n]:
                length += 1
                k += 1
            if length > best[1]:
                best = (i, length)
        else:
            k += 1
    first, length = best
    kappa = wrap_angle(angles[first] + 0.5 * (length - 1) * step)
    delta = 0.5 * length * step
    return Forcelet(kappa, 2.0 * delta, lam, d, d0)


# ----------------------------------------------------------------------------------------------
# Speed along the heading
# ----------------------------------------------------------------------------------------------


@declared("speed")
class SpeedParams:
    """Speed profile: ``v_des(d) = v_max * tanh(k * d / v_max)`` (m/s) for distance ``d`` (m) to the
    target, tracked by a critically damped second-order filter of natural frequency ``omega`` (rad/s),
    so the speed and acceleration are continuous; ``a_max`` (m/s^2) caps the acceleration and
    ``j_max`` (m/s^3) its rate of change (the jerk along the path).
    Near the target ``v ~ k d``: with the filter the distance obeys a linear third-order equation
    with characteristic polynomial ``x^3 + 2 omega x^2 + omega^2 x + omega^2 k``, whose roots are all
    real (no overshoot of the target) iff ``k <= 4 omega / 27``; the defaults keep that margin."""


class SpeedProfile:
    """Smooth speed along the heading that stops at the target (state: speed and acceleration)."""

    def __init__(self, params: SpeedParams | None = None) -> None:
        self.params = params or SpeedParams()

    def desired(self, d: float) -> float:
        """v_des (m/s) at distance ``d`` (m) from the target."""
        p = self.params
        return p.v_max * math.tanh(p.k * max(d, 0.0) / p.v_max)

    def step(self, v: float, a: float, d: float, dt: float,
             v_cap: float | None = None, a_limit: float | None = None) -> tuple[float, float]:
        """Advance speed ``v`` (m/s) and acceleration ``a`` (m/s^2) by ``dt`` (s); returns ``(v, a)``.

        ``v_cap`` optionally lowers the target speed (e.g. joint-velocity limits); ``a_limit`` (m/s^2)
        optionally lowers ``a_max`` for speeding up in this step (e.g. joint-acceleration limits).
        """
        p = self.params
        # a_limit bounds speeding up only: braking keeps a_max, so the stop at the target stays
        # smooth (a late stop would be worse for the joints than a brisk one).
        a_up = p.a_max if a_limit is None else max(min(p.a_max, a_limit), 1e-3)
        target = self.desired(d)
        if v_cap is not None:
            target = min(target, v_cap)
        # Semi-implicit Euler of v'' = w^2 (v_des - v) - 2 w v', sub-stepped so that w h <= 0.5.
        n = max(1, math.ceil(p.omega * dt / 0.5))
        h = dt / n
        da = p.j_max * h  # jerk limit, then acceleration limit
        v_new, a_new = v, a
        for _ in range(n):
            a_filter = a_new + h * (p.omega * p.omega * (target - v_new) - 2.0 * p.omega * a_new)
            if a_filter > 0.0:  # jerk-limited approach of the target speed from below (no overshoot):
                # ramping a down by j h per step gains a^2 / (2 j) + a h / 2 more speed.
                jh2 = 0.5 * da
                room = max(target - v_new, 0.0)
                a_filter = min(a_filter, -jh2 + math.sqrt(jh2 * jh2 + 2.0 * p.j_max * room))
            a_new = max(-p.a_max, min(a_up, max(a_new - da, min(a_new + da, a_filter))))
            v_new = max(0.0, v_new + h * a_new)
            if v_new > p.v_max:  # residual overshoot of at most j_max h^2
                v_new, a_new = p.v_max, min(a_new, 0.0)
        # Never overshoot the target speed downward into motion past the target: at d ~ 0 stop.
        if v_new > 0.0 and target == 0.0 and v_new * dt > d:
            v_new = d / dt if dt > 0 else 0.0
        return v_new, a_new
