"""The URDF reader of the view and the recorder: its forward kinematics agrees with the arm models,
visuals and colours are read, and malformed URDF gets a typed error."""

from __future__ import annotations

import numpy as np
import pytest

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics import load_arm
from redarm_ros.sim.urdf import build_urdf, link_names
from redarm_ros.view.urdf_model import UrdfModel, axis_angle, model_for_arm, rpy_matrix


@pytest.mark.parametrize("name", ["pa10", "powercube7", "powercube6"])
def test_fk_of_generated_urdf_matches_the_arm_model(name: str) -> None:
    arm = load_arm(name)
    model = UrdfModel.from_string(build_urdf(arm))
    assert model.movable_joint_names == list(arm.joint_names)
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.uniform(arm.lower, arm.upper)
        poses = model.link_transforms(dict(zip(arm.joint_names, q, strict=True)))
        np.testing.assert_allclose(poses[link_names(arm)[-1]], arm.fk(q), atol=1e-12)


def test_visuals_and_colours_of_the_generated_urdf() -> None:
    model = model_for_arm("pa10")
    assert model.root == "base_link"
    kinds = {v.kind for vs in model.visuals.values() for v in vs}
    assert kinds == {"sphere", "cylinder"}
    tool = model.visuals["tool"][0]
    assert tool.kind == "sphere" and tool.rgba == pytest.approx((0.95, 0.75, 0.1, 1.0))
    housing = model.visuals["link_2"][0]
    assert housing.rgba == pytest.approx((0.85, 0.15, 0.12, 1.0))  # top-level named material


def test_missing_joint_values_are_zero_and_prismatic_moves_along_its_axis() -> None:
    text = """<robot name="r">
      <link name="a"/><link name="b"><visual><geometry><box size="1 2 3"/></geometry>
        <material name="x"><color rgba="0 1 0 1"/></material></visual></link><link name="c"/>
      <joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>
        <origin xyz="0 0 1" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/></joint>
      <joint name="fixed" type="fixed"><parent link="b"/><child link="c"/><origin xyz="0.5 0 0"/></joint>
    </robot>"""
    m = UrdfModel.from_string(text)
    assert m.movable_joint_names == ["slide"]
    np.testing.assert_allclose(m.link_transforms({})["c"][:3, 3], [0.0, 0.5, 1.0], atol=1e-12)
    np.testing.assert_allclose(m.link_transforms({"slide": 0.2})["b"][:3, 3], [0.0, 0.2, 1.0], atol=1e-12)
    assert m.visuals["b"][0].kind == "box" and m.visuals["b"][0].size == (1.0, 2.0, 3.0)
    assert m.visuals["b"][0].rgba == (0.0, 1.0, 0.0, 1.0)


def test_rpy_matches_the_urdf_convention() -> None:
    R = rpy_matrix(0.1, -0.4, 2.0)
    expected = axis_angle((0, 0, 1), 2.0) @ axis_angle((0, 1, 0), -0.4) @ axis_angle((1, 0, 0), 0.1)
    np.testing.assert_allclose(R, expected, atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("text, what", [
    ("not xml <", "valid XML"),
    ("<robots/>", "<robot>"),
    ('<robot name="r"><link name="a"/><link name="b"/></robot>', "one root link"),
    ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute"><parent link="a"/>'
     '<child link="b"/><axis xyz="0 0 0"/></joint></robot>', "zero axis"),
    ('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="fixed"><parent link="a"/>'
     '<child link="b"/><origin xyz="1 nan"/></joint></robot>', "origin xyz"),
])
def test_malformed_urdf_is_refused_with_a_reason(text: str, what: str) -> None:
    with pytest.raises(InvalidInputError, match=what.replace("<", r"\<").replace(">", r"\>")):
        UrdfModel.from_string(text)


@pytest.mark.parametrize("name", ["pa10", "powercube6"])
def test_fallback_model_uses_the_installed_urdfs_frame_names(name: str) -> None:
    """The view and the recorder draw / record this model until /robot_description arrives: its frames
    must be the installed URDF's (setup.py: prefix ""), or /tf from the recorder names frames nobody else
    uses and the goal's base_link is not the drawn base."""
    installed = UrdfModel.from_string(build_urdf(load_arm(name), prefix=""))
    model = model_for_arm(name)
    assert model.root == installed.root == "base_link"
    assert set(model.visuals) | {model.root} >= {"base_link", "link_1", "tool"}
    assert [j.child for j in model.joints] == [j.child for j in installed.joints]
