"""ik_service for an arm given by URDF: from a file, as parameter text and from the robot_description
topic; the closed form for the iiwa14-like arm, the numeric solver for the Franka-like chain, and the
response's ``solver`` naming which ran; bad URDF parameters refuse the start with the reason."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from redarm_interfaces.srv import SolveIK  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from test_node_ik_service import Caller, make_request  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.kinematics.model import pose_error  # noqa: E402
from redarm_ros.nodes.description import DESCRIPTION_QOS  # noqa: E402
from redarm_ros.nodes.ik_service import IKServiceNode  # noqa: E402
from redarm_ros.sim.urdf_arms import franka_like_urdf, iiwa14_urdf  # noqa: E402

R = SolveIK.Response


@pytest.fixture(scope="module")
def ctx(ros_env: Any) -> Iterator[Any]:
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros_env.domain_id)
    yield context
    rclpy.shutdown(context=context)


def _start(ctx: Any, name: str, **params: Any) -> tuple[IKServiceNode, Caller, SingleThreadedExecutor]:
    over = [Parameter("duplicate_check_s", value=0.0), Parameter("arms", value=["pa10"])]
    over += [Parameter(k, value=v) for k, v in params.items()]
    node = IKServiceNode(context=ctx, node_name=name, parameter_overrides=over)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    return node, Caller(ctx, executor, f"/{name}/solve_ik"), executor


def _stop(node: IKServiceNode, caller: Caller, executor: SingleThreadedExecutor) -> None:
    executor.shutdown()
    caller.node.destroy_node()
    node.destroy_node()


def _check_solves(arm: Any, caller: Caller, solver: str, arm_field: str = "", n: int = 6) -> None:
    rng = np.random.default_rng(31)
    for _ in range(n):
        q = rng.uniform(0.7 * arm.lower + 0.3 * arm.upper, 0.3 * arm.lower + 0.7 * arm.upper)
        T = arm.fk(q)
        resp = caller(make_request(T, arm_field, ignore_collisions=True, timeout=1.0))
        assert resp.status == R.SUCCESS, resp.message
        assert resp.solver.startswith(solver), resp.solver
        assert list(resp.solution.name) == arm.joint_names
        qs = np.array(resp.solution.position)
        assert np.all(qs >= arm.lower) and np.all(qs <= arm.upper)
        assert max(pose_error(arm.fk(qs), T)) <= 1e-5


def test_urdf_file_serves_the_closed_form_and_says_so(ctx: Any, tmp_path: Path) -> None:
    f = tmp_path / "iiwa.urdf"
    f.write_text(iiwa14_urdf(), encoding="utf-8")
    arm = load_arm(f, base_link="base_link", tip_link="tool0")
    node, caller, ex = _start(
        ctx, "ik_urdf_file", urdf=str(f), base_link="base_link", tip_link="tool0", base_frame="pa10_base"
    )
    try:
        caller.wait_ready()
        assert node.front.default_arm == "iiwa14_like"  # default_arm empty: the URDF arm
        _check_solves(arm, caller, "closed-form swivel IK")
        # the YAML arms are still served, and say their solver too
        pa10 = load_arm("pa10")
        req = make_request(pa10.fk(pa10.park), "pa10", timeout=1.0)
        req.target.header.frame_id = "pa10_base"  # the YAML arms' frame stays base_frame
        resp = caller(req)
        assert resp.status == R.SUCCESS and resp.solver == "closed-form swivel IK"
        # the URDF arm's targets are in its base link's frame
        req = make_request(arm.fk(np.full(7, 0.2)), "", ignore_collisions=True)
        req.target.header.frame_id = "base_link"
        assert caller(req).status == R.SUCCESS
        req.target.header.frame_id = "world"
        resp = caller(req)
        assert resp.status == R.INVALID_INPUT and "'base_link'" in resp.message
        # an unsolvable request still names the solver that refused it
        T = arm.fk(np.zeros(7))
        T[2, 3] += 1.0
        resp = caller(make_request(T, "", ignore_collisions=True))
        assert resp.status == R.OUT_OF_REACH and resp.solver == "closed-form swivel IK"
    finally:
        _stop(node, caller, ex)


def test_robot_description_text_of_a_non_spherical_arm_gets_the_numeric_solver(ctx: Any) -> None:
    arm = load_arm(franka_like_urdf(), base_link="base_link", tip_link="tool0")
    node, caller, ex = _start(
        ctx,
        "ik_urdf_text",
        robot_description=franka_like_urdf(),
        base_link="base_link",
        tip_link="tool0",
        urdf_arm_name="panda",
    )
    try:
        caller.wait_ready()
        _check_solves(arm, caller, "numeric IK (damped least squares): not closed form because", "panda")
        assert "elbow offset" in caller(make_request(arm.fk(arm.lower * 0.5), "panda")).solver
    finally:
        _stop(node, caller, ex)


def test_robot_description_topic(ctx: Any) -> None:
    pub_node = rclpy.create_node("urdf_publisher", context=ctx)
    pub = pub_node.create_publisher(String, "/test_robot_description", DESCRIPTION_QOS)
    node, caller, ex = _start(
        ctx,
        "ik_urdf_topic",
        robot_description_topic="/test_robot_description",
        base_link="base_link",
        tip_link="tool0",
    )
    ex.add_node(pub_node)
    try:
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:  # no description yet: no service
            ex.spin_once(timeout_sec=0.05)
        assert node.srv is None and not caller.client.service_is_ready()
        pub.publish(String(data=iiwa14_urdf(reframed=True)))
        caller.wait_ready()
        arm = load_arm(iiwa14_urdf(reframed=True), base_link="base_link", tip_link="tool0")
        _check_solves(arm, caller, "closed-form swivel IK")
    finally:
        _stop(node, caller, ex)
        pub_node.destroy_node()


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"urdf": "/no/such/file.urdf", "base_link": "a", "tip_link": "b"}, "cannot read URDF"),
        ({"robot_description": "x", "urdf": "y", "base_link": "a", "tip_link": "b"}, "one URDF source"),
        ({"robot_description": iiwa14_urdf()}, "needs the base_link and tip_link"),
        ({"robot_description": iiwa14_urdf(), "base_link": "base_link", "tip_link": "nope"}, "not a link"),
    ],
)
def test_bad_urdf_parameters_refuse_the_start(ctx: Any, params: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _start(ctx, "ik_urdf_bad", **params)


def _controller(ctx: Any, name: str, urdf: Path, base: str, tip: str) -> Any:
    from redarm_ros.nodes.controller import ControllerNode

    return ControllerNode(
        context=ctx,
        node_name=name,
        parameter_overrides=[
            Parameter("urdf", value=str(urdf)),
            Parameter("base_link", value=base),
            Parameter("tip_link", value=tip),
            Parameter("duplicate_check_s", value=0.0),
        ],
    )


def test_controller_node_takes_a_urdf_and_refuses_a_chain_it_cannot_run(ctx: Any, tmp_path: Path) -> None:
    from redarm_ros.sim.urdf import build_urdf

    for name, text, base, tip, joints in (
        ("pa10", build_urdf(load_arm("pa10")), "pa10_base_link", "pa10_tool", load_arm("pa10").joint_names),
        ("iiwa", iiwa14_urdf(), "base_link", "tool0", [f"iiwa_joint_{i}" for i in range(1, 8)]),
    ):
        f = tmp_path / f"{name}.urdf"
        f.write_text(text, encoding="utf-8")
        node = _controller(ctx, f"ctl_urdf_{name}", f, base, tip)
        try:
            assert node.arm.joint_names == joints
        finally:
            node.destroy_node()
    for name, text, match in (
        (
            "panda",
            franka_like_urdf(),
            "not a spherical-shoulder / elbow / spherical-wrist chain: axes 3 and 4",
        ),
        ("moved", iiwa14_urdf(reframed=True), "only through a base or tool transform"),
    ):
        f = tmp_path / f"{name}.urdf"
        f.write_text(text, encoding="utf-8")
        with pytest.raises(ValueError, match=match):
            _controller(ctx, f"ctl_urdf_{name}", f, "base_link", "tool0")
