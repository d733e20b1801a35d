"""Attractor dynamics (Iossifidis & Schoener eq. 17-24): sign check, repellers, heading, speed profile."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.attractor import (
    Forcelet,
    HeadingDynamics,
    HeadingParams,
    SpeedParams,
    SpeedProfile,
    direction,
    forcelet,
    heading_angles,
    obstacle_heading_term,
    orientation_rates,
    paper_target_term,
    path_tangent,
    range_function,
    redundancy_rate,
    sector_forcelet,
    target_attractor,
)
from redarm_ros.control.swivel_dynamics import wrap_angle
from redarm_ros.errors import InvalidInputError
from redarm_ros.geometry.obstacles import Box, Cylinder, Sphere


def _integrate(f, x0: float, dt: float = 0.01, n: int = 2000) -> float:
    x = x0
    for _ in range(n):
        x = wrap_angle(x + dt * f(x))
    return x


def _slope(f, x: float, h: float = 1e-6) -> float:
    return (f(x + h) - f(x - h)) / (2 * h)


def test_printed_target_term_is_a_repeller_and_corrected_one_an_attractor() -> None:
    lam, x_tar = 4.0, 0.8
    # As printed (eq. 20-22): slope +lam at the target -> unstable.
    assert _slope(lambda x: paper_target_term(x, x_tar, lam), x_tar) == pytest.approx(lam)
    assert abs(wrap_angle(_integrate(lambda x: paper_target_term(x, x_tar, lam), x_tar + 0.01) - x_tar)) > 1.0
    # Corrected: slope -lam -> stable, from anywhere but the antipode.
    assert _slope(lambda x: target_attractor(x, x_tar, lam), x_tar) == pytest.approx(-lam)
    for x0 in np.linspace(-3.0, 3.0, 13):
        if abs(wrap_angle(x0 - x_tar)) > 3.1:
            continue
        assert abs(wrap_angle(_integrate(lambda x: target_attractor(x, x_tar, lam), x0) - x_tar)) < 1e-6


def test_orientation_and_redundancy_attractors_converge() -> None:
    ph, th = -1.0, 0.9
    for _ in range(2000):
        dph, dth = orientation_rates(ph, th, 0.4, -0.2, 3.0)
        ph, th = ph + 0.01 * dph, th + 0.01 * dth
    assert ph == pytest.approx(0.4, abs=1e-6) and th == pytest.approx(-0.2, abs=1e-6)
    a = _integrate(lambda x: redundancy_rate(x, 1.0, 3.0), -1.5)
    assert a == pytest.approx(1.0, abs=1e-6)


def test_forcelets_repel_with_limited_range() -> None:
    lam, sigma = 2.0, 0.4
    # positive slope at the centre (repeller), pushes away on both sides
    assert _slope(lambda x: forcelet(x, 0.5, lam, sigma), 0.5) == pytest.approx(lam)
    assert forcelet(0.6, 0.5, lam, sigma) > 0 and forcelet(0.4, 0.5, lam, sigma) < 0
    # far outside its range it vanishes
    assert abs(forcelet(0.5 + 4 * sigma, 0.5, lam, sigma)) < 1e-3 * lam
    # an obstacle force-let shifts the redundancy attractor away from the obstacle sector
    obs = Forcelet(kappa=0.6, sigma=0.5, lam=6.0, d=0.02, d0=0.1)
    a = _integrate(lambda x: redundancy_rate(x, 0.5, 2.0, obstacles=[obs]), 0.5 - 1e-3)
    assert a < 0.5 - 0.2
    lim = Forcelet(kappa=0.3, sigma=0.3, lam=6.0)
    a2 = _integrate(lambda x: redundancy_rate(x, 0.5, 2.0, limits=[lim]), 0.5)
    assert a2 > 0.5 + 0.1


def test_range_function_and_heading_repeller_eq_18_19() -> None:
    assert range_function(0.0, 0.2, 4.0, 0.2) > 0.5
    assert range_function(math.pi, 0.2, 4.0, 0.2) < 0.01
    assert 0.0 <= range_function(0.7, 0.2, 4.0, 0.2) <= 1.0
    args = dict(d_i=0.05, delta_phi=0.2, lam=5.0, sigma=0.6, d0=0.1, beta=4.0, margin=0.2)
    # heading slightly left of the obstacle -> pushed further left; right -> right
    assert obstacle_heading_term(0.1, 0.0, **args) > 0
    assert obstacle_heading_term(-0.1, 0.0, **args) < 0
    # obstacle behind the heading: no force (limited angular range)
    assert abs(obstacle_heading_term(math.pi - 0.1, 0.0, **args)) < 1e-3
    # far obstacle: much weaker
    far = dict(args, d_i=1.0)
    assert abs(obstacle_heading_term(0.1, 0.0, **far)) < 0.01 * abs(obstacle_heading_term(0.1, 0.0, **args))


def test_sector_forcelet_center_and_width() -> None:
    n = 36
    angles = [-math.pi + 2 * math.pi * k / n for k in range(n)]
    blocked = [abs(wrap_angle(a - 1.0)) < 0.35 for a in angles]
    f = sector_forcelet(blocked, angles, lam=3.0)
    assert f is not None
    assert f.kappa == pytest.approx(1.0, abs=2 * math.pi / n)
    assert f.sigma == pytest.approx(2 * 0.35, abs=2 * 2 * math.pi / n)
    assert sector_forcelet([False] * n, angles, 1.0) is None
    # a sector that wraps around +/-pi
    blocked = [abs(wrap_angle(a - math.pi)) < 0.3 for a in angles]
    f = sector_forcelet(blocked, angles, lam=3.0)
    assert abs(wrap_angle(f.kappa - math.pi)) < 2 * math.pi / n


def test_heading_helpers() -> None:
    for phi, th in [(0.3, 0.2), (-2.0, -1.0), (3.0, 0.0)]:
        assert heading_angles(direction(phi, th)) == pytest.approx((phi, th))
    assert heading_angles((0, 0, -1), phi_default=0.7) == pytest.approx((0.7, -math.pi / 2))
    assert path_tangent((1, 0, 0), (1, 0, 0)) is None
    assert path_tangent((1, 1, 0), (0, 1, 0)) == pytest.approx((1, 0, 0))


def test_heading_goes_straight_without_obstacles_and_up_over_one() -> None:
    dyn = HeadingDynamics()
    ee, target = (0.3, 0.3, 0.15), (0.65, -0.15, 0.08)
    phi_t, th_t = heading_angles(np.subtract(target, ee))
    r = dyn.rates(phi_t, th_t, ee, target, [])
    assert r.dphi == pytest.approx(0.0, abs=1e-12) and r.dtheta == pytest.approx(0.0, abs=1e-12)
    # a can standing on the straight line: the elevation is pushed up, never down
    can = Cylinder((0.47, 0.08, 0.1), 0.05, 0.2)
    r = dyn.rates(phi_t, th_t, ee, target, [can])
    assert r.obstacle_theta > 0.5
    # the same can beyond the target or behind the hand does not act
    beyond = Cylinder((0.8, -0.35, 0.1), 0.05, 0.2)
    behind = Cylinder((0.15, 0.5, 0.1), 0.05, 0.2)
    r = dyn.rates(phi_t, th_t, ee, target, [beyond, behind])
    assert abs(r.obstacle_theta) < 0.01 and abs(r.obstacle_phi) < 0.01  # smooth gates: tails only
    # once the hand is above the can's top plus the margin, nothing pushes
    high = (0.47, 0.08, 0.2 + HeadingParams().clear_margin + 0.05)
    r = dyn.rates(-1.0, -0.3, high, target, [can])
    assert r.obstacle_theta == pytest.approx(0.0, abs=1e-9)


def test_heading_integration_passes_above_obstacles() -> None:
    """Point-mass check of the heading dynamics: the path clears the top of each obstacle shape."""
    dyn = HeadingDynamics()
    speed = SpeedProfile()
    for obs in (Cylinder((0.47, 0.08, 0.1), 0.05, 0.2), Box((0.47, 0.08, 0.08), (0.1, 0.1, 0.16), 0.4),
                Sphere((0.47, 0.08, 0.07), 0.07)):
        ee = np.array([0.3, 0.3, 0.15])
        target = np.array([0.65, -0.15, 0.08])
        phi, th = heading_angles(target - ee)
        v = a = 0.0
        min_d = math.inf
        for _ in range(1500):
            phi, th, _ = dyn.step(phi, th, 0.01, ee, target, [obs])
            d = float(np.linalg.norm(target - ee))
            v, a = speed.step(v, a, d, 0.01)
            ee = ee + min(v * 0.01, d) * np.asarray(direction(phi, th))
            min_d = min(min_d, obs.signed_distance(ee))
        assert np.linalg.norm(target - ee) < 1e-3
        assert min_d > 0.05, type(obs).__name__


def test_speed_profile_stops_at_target_without_overshoot() -> None:
    p = SpeedParams()
    sp = SpeedProfile(p)
    assert p.k <= 4 * p.omega / 27  # real roots: no overshoot in the linear regime
    d, v, a = 0.6, 0.0, 0.0
    ds, accs = [], []
    for _ in range(800):
        v, a = sp.step(v, a, d, 0.01)
        assert 0.0 <= v <= p.v_max + 1e-12
        d -= v * 0.01
        ds.append(d)
        accs.append(a)
        assert d >= -1e-12
    assert d < 1e-4
    assert all(np.diff(ds) <= 1e-15)  # monotone approach
    jerks = np.abs(np.diff(accs)) / 0.01
    assert jerks.max() <= p.j_max + 1e-9
    assert np.max(np.abs(accs)) <= p.a_max + 1e-12
    with pytest.raises(InvalidInputError):
        SpeedParams(v_max=0.0)
    with pytest.raises(InvalidInputError):
        HeadingParams(lam_tar=-1.0)
