"""description node: the URDF on /robot_description with transient-local durability, so a subscriber
that joins after the one publication still gets it, in process and over a ``redarm-bringup``."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from support.waits import spin_until  # noqa: E402

from redarm_ros.bringup import build_parser, config_from_args  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.nodes.description import (  # noqa: E402
    DESCRIPTION_QOS,
    DescriptionNode,
    robot_description,
    summarize,
)
from redarm_ros.procs import python_module_cmd  # noqa: E402
from redarm_ros.sim.urdf import build_urdf  # noqa: E402

LATE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _node(ctx: Any, **params: Any) -> DescriptionNode:
    overrides = [Parameter("duplicate_check_s", value=0.0)]
    overrides += [Parameter(k, value=v) for k, v in params.items()]
    return DescriptionNode(context=ctx, parameter_overrides=overrides)


def test_publisher_qos_is_robot_state_publishers() -> None:
    assert DESCRIPTION_QOS.durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert DESCRIPTION_QOS.reliability == ReliabilityPolicy.RELIABLE
    assert DESCRIPTION_QOS.depth == 1


def test_late_subscriber_gets_the_description(rclpy_context: Any) -> None:
    node = _node(rclpy_context, arm="powercube7")
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    listener = rclpy.create_node("late_listener", context=rclpy_context)
    ex.add_node(listener)
    try:
        spin_until(ex, lambda: False, 0.5)  # the one publication is long done
        got: list[str] = []
        listener.create_subscription(String, "/robot_description", lambda m: got.append(m.data), LATE_QOS)
        assert spin_until(ex, lambda: bool(got), 10.0), "late subscriber got nothing"
        assert got[0] == build_urdf(load_arm("powercube7"), prefix="")
        # A volatile subscriber does not get the earlier sample: the durability is what makes it work.
        volatile: list[str] = []
        listener.create_subscription(String, "/robot_description", lambda m: volatile.append(m.data),
                                     QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        spin_until(ex, lambda: bool(volatile), 1.0)
        assert volatile == []
    finally:
        ex.shutdown()
        listener.destroy_node()
        node.destroy_node()


def test_prefix_and_file_parameters(rclpy_context: Any, tmp_path: Path) -> None:
    node = _node(rclpy_context, arm="pa10", prefix="left_")
    try:
        s = node.summary
        assert (s.root, s.tips) == ("left_base_link", ["left_tool"])
        assert s.joints == list(load_arm("pa10").joint_names)
    finally:
        node.destroy_node()
    custom = tmp_path / "custom.urdf"
    custom.write_text('<robot name="x"><link name="a"/><link name="b"/>'
                      '<joint name="j" type="revolute"><parent link="a"/><child link="b"/></joint></robot>')
    node = _node(rclpy_context, urdf_file=str(custom))
    try:
        assert node.urdf == custom.read_text()
        assert (node.summary.name, node.summary.root, node.summary.joints) == ("x", "a", ["j"])
    finally:
        node.destroy_node()


def test_bad_inputs_are_refused_with_a_reason(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="cannot build a URDF for 'no_such_arm'"):
        robot_description("no_such_arm")
    with pytest.raises(ValueError, match="cannot read"):
        robot_description(urdf_file=str(tmp_path / "missing.urdf"))
    with pytest.raises(ValueError, match="not XML"):
        summarize("<robot>")
    with pytest.raises(ValueError, match="not <robot>"):
        summarize("<sdf/>")
    two_roots = '<robot name="x"><link name="a"/><link name="b"/></robot>'
    with pytest.raises(ValueError, match="exactly one root link"):
        summarize(two_roots)


def test_bringup_starts_it_by_default() -> None:
    assert config_from_args(build_parser().parse_args([])).description is True
    assert config_from_args(build_parser().parse_args(["--no-description"])).description is False


@pytest.mark.slow
def test_late_subscriber_gets_it_over_a_bringup(procs: Any, rclpy_context: Any) -> None:
    """redarm-bringup's stack publishes /robot_description; a subscriber started after the whole stack
    is up (a late RViz) receives the complete URDF."""
    bringup = procs.start(
        "bringup",
        python_module_cmd("redarm_ros.bringup", "--hardware", "none", "--no-controller",
                          "--log-level", "warn"),
    )
    up = bringup.wait_for_line(r"stack up: (.*); Ctrl-C to stop", timeout=90.0)
    assert "description (pid" in up.group(1), up.group(0)
    node = rclpy.create_node("late_rviz", context=rclpy_context)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    try:
        spin_until(ex, lambda: False, 1.0)  # join well after the publication
        got: list[str] = []
        node.create_subscription(String, "robot_description", lambda m: got.append(m.data), LATE_QOS)
        assert spin_until(ex, lambda: bool(got), 20.0), "no /robot_description for a late subscriber"
        assert got[0] == build_urdf(load_arm("pa10"), prefix="")
        # the publisher's node name arrives with the participant's discovery data, which may come
        # after the topic's endpoint data: wait for it rather than read it once
        names: list[str] = []

        def publisher_names_known() -> bool:
            names[:] = [p.node_name for p in node.get_publishers_info_by_topic("/robot_description")]
            return "_NODE_NAME_UNKNOWN_" not in names

        spin_until(ex, publisher_names_known, 20.0)
        assert names == ["description"]
    finally:
        ex.shutdown()
        node.destroy_node()
        bringup.expect_exit()
        bringup.send_signal(2)
        deadline = time.monotonic() + 30.0
        while bringup.returncode is None and time.monotonic() < deadline:
            time.sleep(0.05)
    assert bringup.returncode == 0
