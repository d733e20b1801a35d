"""Swivel dynamics (eq. 30-32), the elbow circle and the clearance gradient w.r.t. the swivel angle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.elbow import (
    ArmGeometry,
    clearance_at_swivel,
    clearance_at_u,
    elbow_circle,
    swivel_gradient,
)
from redarm_ros.control.swivel_dynamics import (
    SwivelDynamics,
    SwivelForces,
    SwivelParams,
    singularity_measure,
    wrap_angle,
)
from redarm_ros.errors import InvalidInputError, UnreachableError
from redarm_ros.geometry.obstacles import ArmCapsules, Scene, Sphere
from redarm_ros.kinematics import load_arm


@pytest.fixture(scope="module")
def arm():
    return load_arm("pa10")


@pytest.fixture(scope="module")
def geom(arm):
    return ArmGeometry.from_arm(arm)


def _tool_pose(p, down: bool = True) -> np.ndarray:
    T = np.eye(4)
    if down:
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = p
    return T


def test_elbow_circle_matches_ik_key_points(arm, geom) -> None:
    rng = np.random.default_rng(3)
    n = 0
    for _ in range(100):
        q = rng.uniform(arm.lower, arm.upper)
        T = arm.fk(q)
        circle = elbow_circle(geom, T)
        s = arm.swivel(q)
        assert np.allclose(circle.key_points(s), arm.key_points(q), atol=1e-9)
        ux, uy = math.cos(s), math.sin(s)
        assert np.allclose(circle.key_points_u(ux, uy), arm.key_points(q), atol=1e-9)
        assert abs(wrap_angle(circle.swivel(arm.key_points(q)[2]) - s)) < 1e-9
        n += 1
    assert n == 100


def test_elbow_circle_rejects_unreachable(geom) -> None:
    with pytest.raises(UnreachableError) as e:
        elbow_circle(geom, _tool_pose([2.0, 0.0, 0.3]))
    assert e.value.distance > 0
    with pytest.raises(InvalidInputError):
        elbow_circle(geom, np.full((4, 4), np.nan))
    T = _tool_pose([0.55, 0.1, 0.2])
    for bad in ((3, 2, math.inf), (0, 1, math.nan), (3, 3, -math.inf)):  # any entry, the last row too
        T_bad = T.copy()
        T_bad[bad[0], bad[1]] = bad[2]
        with pytest.raises(InvalidInputError):
            elbow_circle(geom, T_bad)
    with pytest.raises(InvalidInputError):
        elbow_circle(geom, T[:3])


def test_elbow_height_slope_matches_finite_difference(geom) -> None:
    circle = elbow_circle(geom, _tool_pose([0.55, 0.1, 0.2]))
    for s in np.linspace(-3.0, 3.0, 13):
        h = 1e-6
        fd = (circle.elbow(s + h)[2] - circle.elbow(s - h)[2]) / (2 * h)
        assert circle.elbow_height_slope(s) == pytest.approx(fd, abs=1e-8)


@pytest.mark.parametrize("s0", [-3.0, -1.5, -0.2, 0.4, 2.0, 3.1])
def test_attractor_is_stable_in_both_forms(s0: float) -> None:
    dyn = SwivelDynamics(SwivelParams(tau=0.2, max_rate=10.0))
    s_des = 0.7
    # slope of ds/dt at the fixed point is negative: stable
    h = 1e-6
    slope = (dyn.rate(s_des + h, s_des) - dyn.rate(s_des - h, s_des)) / (2 * h)
    assert slope < 0
    assert dyn.rate(s_des, s_des) == 0.0
    s = s0
    u = (math.cos(s0), math.sin(s0))
    ud = (math.cos(s_des), math.sin(s_des))
    for _ in range(3000):
        s = dyn.step(s, s_des, 0.01)
        u = dyn.step_u(u, ud, 0.01)
    assert abs(wrap_angle(s - s_des)) < 1e-6
    assert abs(math.atan2(u[1], u[0]) - s_des) < 1e-6
    assert math.hypot(*u) == pytest.approx(1.0, abs=1e-12)


def test_h_is_odd_and_quaternion_form_agrees_to_first_order() -> None:
    dyn = SwivelDynamics()
    for x in np.linspace(-3, 3, 25):
        assert dyn.h(-x) == pytest.approx(-dyn.h(x))
    s_des = 0.3
    for ds in (-1e-3, 2e-3, 0.01):
        s = s_des - ds
        u, ud = (math.cos(s), math.sin(s)), (math.cos(s_des), math.sin(s_des))
        assert dyn.rate_u(u, ud) == pytest.approx(dyn.rate(s, s_des), rel=1e-4)
    # Antipodal swivel: a definite direction, no division by zero.
    assert abs(dyn.attractor_u((1.0, 0.0), (-1.0, 0.0))) == pytest.approx(dyn.h(1e12))


def test_probe_rotations_are_plus_minus_eps() -> None:
    p = SwivelParams(eps=0.05)
    dyn = SwivelDynamics(p)
    s = 1.1
    up, um = dyn.probes_u((math.cos(s), math.sin(s)))
    assert math.atan2(up[1], up[0]) == pytest.approx(s + 0.05)
    assert math.atan2(um[1], um[0]) == pytest.approx(s - 0.05)


def test_params_validation() -> None:
    with pytest.raises(InvalidInputError):
        SwivelParams(tau=0.0)
    with pytest.raises(InvalidInputError):
        SwivelParams(lam_obs=-1.0)


def _upper_arm_sphere_gradient(circle, s, sphere, r_link):
    """Analytic d(clearance)/ds of the upper-arm capsule against a sphere (envelope theorem)."""
    ps = np.asarray(circle.shoulder)
    pe = np.asarray(circle.elbow(s))
    c = np.asarray(sphere.center)
    b = pe - ps
    t = float(np.clip(np.dot(c - ps, b) / np.dot(b, b), 0.0, 1.0))
    p = ps + t * b
    n = (p - c) / np.linalg.norm(p - c)
    dpe = circle.rho * (-math.sin(s) * np.asarray(circle.a) + math.cos(s) * np.asarray(circle.b))
    return float(np.dot(n, t * dpe)), float(np.linalg.norm(p - c) - sphere.radius - r_link)


def test_swivel_gradient_matches_analytic_and_fine_differences(geom) -> None:
    rng = np.random.default_rng(11)
    caps = ArmCapsules(radii=(0.0, 0.06, 0.0, 0.0), obstacle_links=(1,), table_links=())
    checked = 0
    for _ in range(60):
        p = np.array([rng.uniform(0.3, 0.7), rng.uniform(-0.4, 0.4), rng.uniform(0.05, 0.5)])
        try:
            circle = elbow_circle(geom, _tool_pose(p))
        except UnreachableError:
            continue
        s = rng.uniform(-math.pi, math.pi)
        # A sphere beside the upper arm, so that the upper arm is the closest link.
        mid = 0.5 * (np.asarray(circle.shoulder) + np.asarray(circle.elbow(s)))
        off = rng.normal(size=3)
        off /= np.linalg.norm(off)
        sphere = Sphere(mid + 0.2 * off, 0.05)
        scene = Scene((sphere,))
        d, g = swivel_gradient(circle, s, scene, caps, eps=1e-5)
        g_an, d_an = _upper_arm_sphere_gradient(circle, s, sphere, 0.06)
        assert d == pytest.approx(d_an, abs=1e-12)
        assert g == pytest.approx(g_an, abs=1e-5)
        h = 1e-7
        fd = (clearance_at_swivel(circle, s + h, scene, caps, (1,)).distance
              - clearance_at_swivel(circle, s - h, scene, caps, (1,)).distance) / (2 * h)
        assert g == pytest.approx(fd, abs=1e-5)
        # Quaternion form gives the same clearance.
        du = clearance_at_u(circle, math.cos(s), math.sin(s), scene, caps, (1,)).distance
        assert du == pytest.approx(d)
        checked += 1
    assert checked > 40


def test_obstacle_force_moves_the_elbow_away_and_clearance_grows(geom) -> None:
    circle = elbow_circle(geom, _tool_pose([0.6, 0.0, 0.25]))
    s0 = 2.5
    elbow = np.asarray(circle.elbow(s0))
    # Obstacle just outside the elbow capsule, off to one side along the circle.
    side = np.asarray(circle.elbow(s0 + 0.4)) - elbow
    sphere = Sphere(elbow + 0.5 * side + np.asarray(circle.normal) * 0.0, 0.06)
    scene = Scene((sphere,))
    caps = ArmCapsules()
    dyn = SwivelDynamics(SwivelParams(lam_des=0.0, lam_obs=1.0))
    f = dyn.forces(circle, s0, scene, caps)
    assert f.clearance < 0.1
    assert f.obstacle < 0.0  # the obstacle sits at larger s: push towards smaller s
    s = s0
    for _ in range(100):
        s = dyn.step(s, s, 0.01, dyn.forces(circle, s, scene, caps))
    assert clearance_at_swivel(circle, s, scene, caps, (1, 2)).distance > f.clearance + 0.03


def test_singularity_force_points_away_from_singularity(geom) -> None:
    # Wrist at shoulder height, sqrt(L3^2 - L2^2) in front of it: the top of the elbow circle is
    # nearly above the shoulder, where theta2 ~ 0 (shoulder singularity).
    d = math.sqrt(geom.fore ** 2 - geom.upper ** 2) + 0.03
    circle = elbow_circle(geom, _tool_pose([d, 0.0, geom.shoulder[2] + 0.08], down=False))
    ss = np.linspace(-math.pi, math.pi, 721)
    sig = [singularity_measure(circle.key_points(s)) for s in ss]
    s_sing = ss[int(np.argmin(sig))]
    dyn = SwivelDynamics(SwivelParams(lam_des=0.0, lam_sing=1.0, lam_obs=0.0))
    for ds in (-0.15, 0.15):
        f = dyn.forces(circle, s_sing + ds, None, ArmCapsules())
        assert f.singularity != 0.0
        assert math.copysign(1.0, f.singularity) == math.copysign(1.0, ds)


def test_limit_force_from_probed_margins(geom) -> None:
    from redarm_ros.control.swivel_dynamics import probe_direction, ramp_amplitude

    assert ramp_amplitude(0.1, 0.3) == pytest.approx(2 / 3)
    assert ramp_amplitude(0.5, 0.3) == 0.0
    assert probe_direction(0.12, 0.08, 0.02, 0.05) > 0.5
    dyn = SwivelDynamics(SwivelParams(lam_des=0.0, lam_obs=0.0, lam_sing=0.0, lam_lim=1.0, lim_threshold=0.3))
    assert dyn.rate(0.0, 0.0, SwivelForces()) == 0.0
    circle = elbow_circle(geom, _tool_pose([0.5, 0.0, 0.4]))
    s = 0.7
    # inside the threshold, the margin growing towards +s: the force and the swivel rate point to +s
    f = dyn.forces(circle, s, None, ArmCapsules(), limit_margins=(0.1, 0.12, 0.08))
    assert f.limits == pytest.approx((2 / 3) * probe_direction(0.12, 0.08, dyn.params.eps, 0.05))
    assert f.limits > 0.0 and dyn.rate(s, s, f) > 0.0
    # ... towards -s: negative
    f = dyn.forces(circle, s, None, ArmCapsules(), limit_margins=(0.1, 0.08, 0.12))
    assert f.limits < 0.0 and dyn.rate(s, s, f) < 0.0
    # margins beyond the threshold, or none probed: no limit force
    assert dyn.forces(circle, s, None, ArmCapsules(), limit_margins=(0.3, 0.35, 0.25)).limits == 0.0
    assert dyn.forces(circle, s, None, ArmCapsules()).limits == 0.0


def test_ik_step_selection_is_numpys_row_by_row() -> None:
    """IKStepper.select over plain floats gives numpy's answer bit for bit: each wide joint on its in-limit
    2 pi copy nearest the reference (np.rint's half-to-even at the ties), the ratio as np.max / dt, the first
    row of least ratio as np.argmin; seeded random rows around and across the +-pi seams."""
    from redarm_ros.control.make import make_controller
    from redarm_ros.control.reach_controller import ControllerParams

    arm = load_arm("pa10")
    stp = make_controller(arm, None, ControllerParams()).redundancy.stepper
    lower, upper, inv_vel = stp.lower, stp.upper, stp.inv_vel

    def numpy_select(sols: np.ndarray, q_ref: np.ndarray, dt: float) -> tuple[np.ndarray, float]:
        cont = sols.copy()
        for j in stp.wide:
            cont[:, j] -= 2.0 * math.pi * np.round((sols[:, j] - q_ref[j]) / (2.0 * math.pi))
        ok = (cont >= lower) & (cont <= upper)
        picked = np.where(ok, cont, sols)
        ratios = np.max(np.abs(picked - q_ref) * inv_vel, axis=1) / dt
        i = int(np.argmin(ratios))
        return picked[i], float(ratios[i])

    rng = np.random.default_rng(11)
    for k in range(3000):
        q_ref = rng.uniform(lower, upper)
        rows = rng.uniform(-math.pi, math.pi, size=(int(rng.integers(1, 9)), 7))
        if k % 3 == 0:  # copies 2 pi away, ties at half a turn, a repeated row (argmin's first)
            turns = rng.integers(-3, 4, size=(len(rows), len(stp.wide)))
            rows[:, stp.wide] = q_ref[stp.wide] + math.pi * turns
            rows = np.vstack([rows, rows[:1]])
        dt = float(rng.choice([0.01, 1.0, 0.004]))
        got = stp.select(rows, q_ref, dt)
        want = numpy_select(rows, q_ref, dt)
        assert got is not None
        assert got[0].tobytes() == want[0].tobytes() and got[1] == want[1]
    assert stp.select(np.empty((0, 7)), q_ref, 0.01) is None
