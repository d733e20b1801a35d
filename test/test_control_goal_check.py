"""Goal check module: verdicts on new goals, the cheap per-sample check of stream goals, the swivel
capability check of arms, the parameter groups."""

from __future__ import annotations

import math

import numpy as np
import pytest

from redarm_ros.control.elbow import ArmGeometry
from redarm_ros.control.goal_check import check_goal, stream_feasibility
from redarm_ros.control.params import ControllerParams, ReplanParams, ServoParams, StreamParams
from redarm_ros.control.reach_controller import has_swivel
from redarm_ros.control.types import GoalStatus
from redarm_ros.errors import ConfigError
from redarm_ros.geometry.obstacles import ArmCapsules, Cylinder, Scene
from redarm_ros.kinematics import load_arm

ARM = load_arm("pa10")
GEOM = ArmGeometry.from_arm(ARM)
CAPS = ArmCapsules()
CAN = Scene((Cylinder((0.5, 0.0, 0.1), 0.05, 0.2, "can"),), 0.0)


def down(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = p
    return T


def test_check_goal_verdicts() -> None:
    assert check_goal(ARM, GEOM, down((0.6, 0.2, 0.2)), CAN, CAPS, 72).status is GoalStatus.ACCEPTED
    far = check_goal(ARM, GEOM, down((1.6, 0.0, 0.3)), CAN, CAPS, 72)
    assert far.status is GoalStatus.OUT_OF_REACH and "reach" in far.message
    inside = check_goal(ARM, GEOM, down((0.5, 0.0, 0.1)), CAN, CAPS, 72)
    assert inside.status is GoalStatus.IN_COLLISION and "can" in inside.message
    table = check_goal(ARM, GEOM, down((0.6, 0.2, 0.02)), CAN, CAPS, 72)
    assert table.status is GoalStatus.IN_COLLISION and "table" in table.message
    bad = down((0.6, 0.2, 0.2))
    bad[0, 0] = math.nan
    assert check_goal(ARM, GEOM, bad, CAN, CAPS, 72).status is GoalStatus.INVALID_INPUT


def test_stream_feasibility_says_why_without_rejecting() -> None:
    assert stream_feasibility(GEOM, down((0.6, 0.2, 0.2)), CAN, CAPS) == ""
    assert "out of reach" in stream_feasibility(GEOM, down((1.6, 0.0, 0.3)), CAN, CAPS)
    assert "inside obstacle" in stream_feasibility(GEOM, down((0.5, 0.0, 0.1)), CAN, CAPS)
    assert "the table" in stream_feasibility(GEOM, down((0.6, 0.2, 0.02)), CAN, CAPS)


def test_swivel_capability_is_asked_of_the_model_not_its_attributes() -> None:
    assert has_swivel(ARM) and has_swivel(load_arm("powercube7"))
    six = load_arm("powercube6")
    assert not has_swivel(six)


def test_parameter_groups_from_yaml_and_validation() -> None:
    p = ControllerParams.from_dict({"stream": {"gap": 0.3, "lead": 0.02}, "servo": {"gain": 20.0},
                                    "replan": {"vias": 50, "enabled": False}})
    assert p.stream == StreamParams(gap=0.3, lead=0.02)
    assert p.servo.gain == 20.0 and p.replan == ReplanParams(vias=50, enabled=False)
    with pytest.raises(ConfigError, match="unknown stream"):
        ControllerParams.from_dict({"stream": {"gapp": 0.3}})
    with pytest.raises(ConfigError):
        ControllerParams.from_dict({"servo": {"acc": -1.0}})
    with pytest.raises(ConfigError):
        ControllerParams.from_dict({"replan": {"vias": 0}})
    with pytest.raises(ValueError):
        ServoParams(yield_time=0.0)
    with pytest.raises(ValueError):
        ReplanParams(enabled="yes")  # type: ignore[arg-type]
