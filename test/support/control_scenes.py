"""Scenarios the in-process controller tests share (no ROS)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from redarm_ros.control.make import make_controller
from redarm_ros.control.reach_controller import ControllerParams, ReachController, StepResult
from redarm_ros.geometry.obstacles import Cylinder, Scene, min_distance
from support.benches import load_bench

DT = 0.01


# Tool at p pointing down, rotated by yaw about the vertical: the goal pose the benches use too.
pose = load_bench("bench_common").pose_down


@dataclass
class ElbowRun:
    ctl: ReachController
    q0: np.ndarray  # the held posture
    last: StepResult  # the last step, after the obstacle appeared
    qs: np.ndarray  # commanded joints from the obstacle on
    swivel_before: float
    before: float  # clearance to the obstacle when it appeared (m)
    after: float  # clearance at the end (m)


def elbow_obstacle_hold(arm, params: ControllerParams | None = None) -> ElbowRun:
    """Hold the hand still at a fixed pose, settle 2 s, then put a cylinder at the elbow and run 3 s."""
    q0, info = arm.ik_nearest(pose([0.55, 0.0, 0.2]), np.array([0.0, 0.6, 0.0, 1.6, 0.0, 1.0, 0.0]))
    assert info.ok
    ctl = make_controller(arm, Scene((), 0.0), params)
    ctl.reset(q0)
    ctl.set_goal(arm.fk(q0))
    for _ in range(200):  # settle at the preferred swivel
        r = ctl.step(DT)
    elbow = arm.key_points(r.q)[2]
    ball = Cylinder((elbow[0] + 0.02, elbow[1] + 0.13, elbow[2]), 0.05, 0.1)
    before = min_distance(arm, r.q, Scene((ball,), 0.0)).distance
    ctl.set_scene(Scene((ball,), 0.0))
    s_before = r.swivel
    qs = [r.q]
    for _ in range(300):
        r = ctl.step(DT)
        qs.append(r.q)
    after = min_distance(arm, r.q, Scene((ball,), 0.0)).distance
    return ElbowRun(ctl, q0, r, np.array(qs), s_before, before, after)
