"""swivel_mode "attractor_paper": the attractor paper's redundancy dynamics (eq. 22-24, sector
force-lets, wrist-limit sectors) and path-tangent hand orientation (eq. 20-21)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.control_scenes import elbow_obstacle_hold, pose

from redarm_ros.control.elbow import ArmGeometry, elbow_circle
from redarm_ros.control.make import make_controller
from redarm_ros.control.paper_redundancy import PaperSwivel, PaperSwivelParams, sectors
from redarm_ros.control.reach_controller import ControllerParams, Phase
from redarm_ros.control.simulate import evaluate, run_controller
from redarm_ros.errors import ConfigError, InvalidInputError
from redarm_ros.geometry.obstacles import ArmCapsules, load_scene
from redarm_ros.kinematics import load_arm

DT = 0.01
PAPER = ControllerParams(swivel_mode="attractor_paper")


@pytest.fixture(scope="module")
def arm():
    return load_arm("pa10")


def check_limits(arm, q: np.ndarray, from_rest: bool = True) -> None:
    """Position limits, |dq| <= max_vel dt and |d2q| <= max_acc dt^2 on every command."""
    assert np.all(q >= arm.lower - 1e-12) and np.all(q <= arm.upper + 1e-12)
    assert (np.abs(np.diff(q, axis=0)) / (np.asarray(arm.max_vel) * DT)).max() <= 1.0 + 1e-6
    qq = np.vstack([q[:1], q]) if from_rest else q
    assert (np.abs(np.diff(qq, n=2, axis=0)) / (np.asarray(arm.max_acc) * DT * DT)).max() <= 1.0 + 1e-6


def test_sectors_are_the_blocked_runs_with_their_centre_and_half_width() -> None:
    n = 12
    step = 2 * math.pi / n
    angles = [-math.pi + step * k for k in range(n)]
    blocked = [False] * n
    for k in (3, 4, 5):
        blocked[k] = True
    blocked[11] = blocked[0] = True  # a run that wraps around the end of the list
    got = sectors(blocked, angles)
    assert len(got) == 2
    mid = next(s for s in got if abs(s.kappa - angles[4]) < 1e-12)
    assert mid.delta == pytest.approx(1.5 * step)
    wrap = next(s for s in got if s is not mid)
    assert abs(math.remainder(wrap.kappa - (angles[11] + 0.5 * step), 2 * math.pi)) < 1e-12
    assert wrap.delta == pytest.approx(step)
    assert sectors([False] * n, angles) == [] and sectors([True] * n, angles) == []


class _Stepper:
    """IK stand-in: no in-limit solution for swivels in [0.4, 0.9] rad, a mid-range one elsewhere."""

    def solve(self, T, s, q_ref, dt):
        if 0.4 <= s <= 0.9:
            return None
        return np.zeros(7), 0.0


def test_a_wrist_limit_sector_repels_the_swivel_and_the_target_attracts_it(arm) -> None:
    geom = ArmGeometry.from_arm(arm)
    T = pose([0.55, 0.0, 0.3])
    circle = elbow_circle(geom, T)
    dyn = PaperSwivel(PaperSwivelParams(samples=36), ArmCapsules(), 1.0, arm.lower, arm.upper)
    near_below = dyn.step(circle, T, 0.3, 0.3, np.zeros(7), DT, None, _Stepper())
    assert len(near_below.limit_sectors) == 1
    sec = near_below.limit_sectors[0]
    assert 0.55 < sec.kappa < 0.75 and sec.delta > 0.2
    assert near_below.limits < 0.0 and near_below.s < 0.3  # pushed away, below the sector
    assert near_below.target == 0.0  # at the preferred swivel the target term is 0
    above = PaperSwivel(PaperSwivelParams(samples=36), ArmCapsules(), 1.0, arm.lower, arm.upper)
    r = above.step(circle, T, 1.0, 1.0, np.zeros(7), DT, None, _Stepper())
    assert r.limits > 0.0  # above the sector: pushed up
    free = PaperSwivel(PaperSwivelParams(samples=36), ArmCapsules(), 1.0, arm.lower, arm.upper)
    r = free.step(circle, T, -2.0, -1.5, np.zeros(7), DT, None, _Stepper())
    assert r.target > 0.0 and abs(r.limits) < 1e-3 * r.target  # far away: the attractor dominates


@pytest.mark.parametrize(("error", "make"), [
    (InvalidInputError, lambda: PaperSwivelParams(lam_obs=-1.0)),
    (InvalidInputError, lambda: PaperSwivelParams(samples=4)),
    (ConfigError, lambda: ControllerParams(swivel_mode="paper")),
], ids=["negative lam_obs", "too few samples", "unknown swivel_mode"])
def test_bad_parameters_are_refused(error, make) -> None:
    with pytest.raises(error):
        make()


def test_paper_parameters_are_read_from_a_dict() -> None:
    p = ControllerParams.from_dict({"swivel_mode": "attractor_paper", "paper_swivel": {"lam_obs": 5.0}})
    assert p.paper_swivel.lam_obs == 5.0


def test_attractor_paper_mode_reaches_goals_within_the_limits(arm) -> None:
    scene = load_scene("table_empty")
    q0, info = arm.ik_nearest(pose([0.3, 0.3, 0.15]), np.array([0.8, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    ctl = make_controller(arm, scene, PAPER)
    ctl.reset(q0)
    for k, T in enumerate((pose([0.65, -0.15, 0.08], 0.3), pose([0.45, 0.25, 0.2], -0.4))):  # no reset
        tr = run_controller(ctl, T, 8.0, DT)
        m = evaluate(arm, scene, tr.q, T, DT, tr.step_s, tr.reached_at)
        assert m.reached and tr.phase[-1] == "REACHED", tr.phase[-1]
        assert m.pos_err < 1e-3 and m.ori_err < 0.01 and m.collision_free
        # From rest at the start; the second goal starts while the elbow may still be settling.
        check_limits(arm, tr.q, from_rest=k == 0)


def test_attractor_paper_hand_trails_the_path_far_from_the_goal(arm) -> None:
    """Eq. 20-21: on a long horizontal move the tool axis (down at both ends) tilts towards the path."""
    scene = load_scene("table_empty")
    q0, info = arm.ik_nearest(pose([0.45, 0.35, 0.2]), np.array([0.8, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    T = pose([0.45, -0.35, 0.2])
    tilt = {}
    for name, params in (("paper", PAPER), ("default", ControllerParams())):
        ctl = make_controller(arm, scene, params)
        ctl.reset(q0)
        tr = run_controller(ctl, T, 8.0, DT)
        assert tr.phase[-1] == "REACHED", (name, tr.phase[-1])
        # Largest tilt of the tool axis away from straight down, and its sideways (-y) part.
        axes = np.array([arm.fk(q)[:3, 2] for q in tr.q[::5]])
        tilt[name] = float(np.max(-axes[:, 1]))
    assert tilt["default"] < 0.05  # the default keeps the goal orientation on the way
    assert tilt["paper"] > 0.3  # the paper's hand leans into the direction of motion (-y)


def test_attractor_paper_mode_avoids_obstacles_with_the_elbow(arm) -> None:
    """The hand holds still; an obstacle put at the elbow is avoided by the swivel (eq. 23)."""
    run = elbow_obstacle_hold(arm, PAPER)
    assert abs(run.last.swivel - run.swivel_before) > 0.1
    assert run.after > run.before + 0.03
    p0 = arm.fk(run.q0)[:3, 3]
    assert max(np.linalg.norm(arm.fk(q)[:3, 3] - p0) for q in run.qs) < 1e-3  # the hand stayed, throughout
    assert run.ctl.phase is not Phase.REJECTED
    check_limits(arm, run.qs, from_rest=False)


@pytest.mark.slow
def test_attractor_paper_mode_reaches_past_a_can_without_collision(arm) -> None:
    scene = load_scene("table_cylinder")
    q0, info = arm.ik_nearest(pose([0.3, 0.3, 0.15]), np.array([0.8, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    T = pose([0.65, -0.15, 0.08])
    ctl = make_controller(arm, scene, PAPER)
    ctl.reset(q0)
    # The hand trailing the path (eq. 20-21) turns the tool horizontal over the can; the attractor run
    # is overdue and the joint-space re-planner finishes it: more time than the default mode needs.
    tr = run_controller(ctl, T, 14.0, DT)
    m = evaluate(arm, scene, tr.q, T, DT)
    assert m.reached and m.min_clearance > 0.0
    check_limits(arm, tr.q)
