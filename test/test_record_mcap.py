"""MCAP recordings: ros2msg schema text, CDR bytes, the writer's file read back with the mcap reader
(topics, counts, schemas, monotonic timestamps), the in-process recorder node and the
``redarm-record`` process over DDS."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from redarm_ros.errors import InvalidInputError
from redarm_ros.record.mcap_io import QosOffer, Ros2McapWriter, read_messages, summarize
from redarm_ros.record.schema import SEPARATOR, TF_MESSAGE_TYPE, field_types, ros2msg_definition
from redarm_ros.record.tf import tf_message
from redarm_ros.view.urdf_model import model_for_arm

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import TransformStamped  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from support.waits import spin_until  # noqa: E402

ARM_JOINTS = [f"pa10_joint_{i}" for i in range(1, 8)]


def test_field_types_skip_primitives_constants_and_bounds() -> None:
    text = ("# comment\nuint8 KIND=3\nstring<=10 name\nint32[] data\nHeader header\n"
            "geometry_msgs/Pose[4] poses  # fixed array\nPoint p\nbuiltin_interfaces/msg/Time t\n")
    assert field_types(text, "geometry_msgs") == [
        "std_msgs/msg/Header", "geometry_msgs/msg/Pose", "geometry_msgs/msg/Point",
        "builtin_interfaces/msg/Time"]


def test_definition_is_complete_with_rosbag2_delimiters() -> None:
    text = ros2msg_definition("sensor_msgs/msg/JointState")
    assert text.startswith("# This is a message that holds data")
    blocks = text.split(SEPARATOR + "\n")
    names = [b.splitlines()[0] for b in blocks[1:]]
    assert names == ["MSG: std_msgs/msg/Header", "MSG: builtin_interfaces/msg/Time"]
    tf = ros2msg_definition(TF_MESSAGE_TYPE)  # tf2_msgs itself is not installed here
    assert tf.splitlines()[0] == "geometry_msgs/TransformStamped[] transforms"
    assert "MSG: geometry_msgs/msg/Quaternion" in tf
    with pytest.raises(InvalidInputError, match="no definition"):
        ros2msg_definition("no_such_pkg/msg/Thing")


def test_dynamic_cdr_of_a_transform_equals_rclpy_serialization() -> None:
    """The /tf messages are encoded from the schema text; their bytes must be what ROS would send."""
    model = model_for_arm("pa10")
    q = np.array([0.3, -0.5, 0.2, 1.0, -0.4, 0.7, 0.1])
    tf = tf_message(model, dict(zip(ARM_JOINTS, q, strict=True)), 1_700_000_000_123_456_789, "base_link")
    # the model's root is base_link itself (the installed URDF's frames): no extra base transform
    assert [t["child_frame_id"] for t in tf["transforms"]][:2] == ["link_1", "link_2"]
    assert tf["transforms"][0]["header"]["frame_id"] == "base_link"
    from mcap_ros2._dynamic import serialize_dynamic

    d = tf["transforms"][3]
    enc = serialize_dynamic("geometry_msgs/msg/TransformStamped",
                            ros2msg_definition("geometry_msgs/msg/TransformStamped"))
    msg = TransformStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000, 123_456_789
    msg.header.frame_id, msg.child_frame_id = d["header"]["frame_id"], d["child_frame_id"]
    for k in "xyz":
        setattr(msg.transform.translation, k, d["transform"]["translation"][k])
    for k in "xyzw":
        setattr(msg.transform.rotation, k, d["transform"]["rotation"][k])
    ours, ros = enc["geometry_msgs/msg/TransformStamped"](d), serialize_message(msg)
    # Equal but for CDR's alignment padding, which rclpy leaves uninitialised (frame names of 6 + 1
    # bytes, "link_3", end unaligned): the same length, and ROS reads our bytes back as the message.
    assert len(ours) == len(ros)
    assert deserialize_message(ours, TransformStamped) == msg


def _joint_state(i: int) -> JointState:
    m = JointState()
    m.header.stamp.sec, m.header.stamp.nanosec = 1000 + i, 0
    m.name = ARM_JOINTS
    m.position = [0.01 * i] * 7
    return m


def test_writer_file_reads_back_with_topics_counts_schemas_and_order(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    model = model_for_arm("pa10")
    with Ros2McapWriter(path) as w:
        w.add_topic("/joint_states", "sensor_msgs/msg/JointState", offers=[QosOffer(depth=10)],
                    type_hash="RIHS01_" + "ab" * 32)
        w.add_topic("/tf", TF_MESSAGE_TYPE, offers=[QosOffer(depth=100)])
        t = 1_000_000_000
        for i in range(50):
            msg, ti = _joint_state(i), t + i * 4_000_000
            w.write("/joint_states", serialize_message(msg), ti)
            w.write_dict("/tf", tf_message(model, dict(zip(msg.name, msg.position, strict=True)), ti), ti)
        w.write("/joint_states", serialize_message(_joint_state(50)), t)  # an early clock is clamped
        with pytest.raises(InvalidInputError):
            w.add_topic("/tf", "sensor_msgs/msg/JointState")
    profile, topics = summarize(path)
    assert profile == "ros2"
    assert set(topics) == {"/joint_states", "/tf", "*"}
    js, tf = topics["/joint_states"], topics["/tf"]
    assert (js.count, tf.count, topics["*"].count) == (51, 50, 101)
    assert (js.schema_name, js.schema_encoding, js.message_encoding) == (
        "sensor_msgs/msg/JointState", "ros2msg", "cdr")
    assert (tf.schema_name, tf.schema_encoding, tf.message_encoding) == (TF_MESSAGE_TYPE, "ros2msg", "cdr")
    assert js.monotonic and tf.monotonic and topics["*"].monotonic
    assert js.metadata["topic_type_hash"] == "RIHS01_" + "ab" * 32
    qos = yaml.safe_load(js.metadata["offered_qos_profiles"])
    assert qos == [{"history": 1, "depth": 10, "reliability": 1, "durability": 2,
                    "deadline": {"sec": 9223372036, "nsec": 854775807},
                    "lifespan": {"sec": 9223372036, "nsec": 854775807}, "liveliness": 1,
                    "liveliness_lease_duration": {"sec": 9223372036, "nsec": 854775807},
                    "avoid_ros_namespace_conventions": False}]
    msgs = read_messages(path, ["/joint_states"])
    assert [round(m.position[0], 6) for _, _, m in msgs[:3]] == [0.0, 0.01, 0.02]
    last_tf = read_messages(path, ["/tf"])[-1][2]
    tool = [tr for tr in last_tf.transforms if tr.child_frame_id == "tool"][0]
    assert tool.header.frame_id == "link_7" and math.isclose(tool.transform.translation.z, 0.08)



def test_recorder_node_records_what_is_published(rclpy_context: Any, tmp_path: Path) -> None:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String

    from redarm_ros.nodes.record import RecorderNode

    pub_node = rclpy.create_node("rec_test_pub", context=rclpy_context)
    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    desc = pub_node.create_publisher(String, "/robot_description", latched)
    js = pub_node.create_publisher(JointState, "/joint_states", 50)
    desc.publish(String(data=model_for_arm("pa10").text))  # before the recorder exists: latched
    path = tmp_path / "rec.mcap"
    writer = Ros2McapWriter(path)
    rec = RecorderNode(writer, ["/joint_states", "/robot_description", "/goal_pose"],
                       tf_from_joint_states=True, tf_rate_hz=0.0, context=rclpy_context,
                       discovery_period_s=0.05)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(rec)
    ex.add_node(pub_node)
    try:
        assert spin_until(ex, lambda: set(rec.topics) >= {"/joint_states", "/robot_description"}, 20.0), \
            rec.topics
        assert spin_until(ex, lambda: writer.counts.get("/robot_description", 0) == 1, 10.0)
        # The subscription is matched once discovery has seen it both ways; then nothing is lost.
        assert spin_until(ex, lambda: js.get_subscription_count() > 0, 10.0)
        for i in range(40):
            js.publish(_joint_state(i))
            ex.spin_once(timeout_sec=0.005)
        assert spin_until(ex, lambda: writer.counts.get("/joint_states", 0) >= 40, 10.0), writer.counts
    finally:
        ex.shutdown(timeout_sec=1.0)
        rec.destroy_node()
        pub_node.destroy_node()
        writer.close()
    _, topics = summarize(path)
    assert topics["/joint_states"].count == 40
    assert topics["/tf"].count == 40  # tf_rate_hz 0: one /tf per joint state
    assert topics["/robot_description"].count == 1
    assert "/goal_pose" not in topics  # asked for, never published
    assert topics["*"].monotonic
    qos = yaml.safe_load(topics["/robot_description"].metadata["offered_qos_profiles"])
    assert qos[0]["durability"] == 1  # transient local, as offered
    first = read_messages(path, ["/joint_states"])[0][2]
    assert list(first.name) == ARM_JOINTS and first.header.stamp.sec == 1000


def test_redarm_record_process_writes_a_complete_file(procs: Any, rclpy_context: Any, tmp_path: Path) -> None:
    """The console tool over DDS: started, fed, stopped with SIGINT while messages keep arriving; the
    file is whole (no torn record) and has its summary."""
    from rclpy.executors import SingleThreadedExecutor

    from redarm_ros.procs import python_module_cmd

    path = tmp_path / "cli.mcap"
    cmd = python_module_cmd("redarm_ros.nodes.record", "-o", str(path), "/joint_states",
                            "--tf-from-joint-states")
    rec = procs.start("record", cmd, ready=r"record ready", ready_timeout=30)
    node = rclpy.create_node("rec_cli_pub", context=rclpy_context)
    js = node.create_publisher(JointState, "/joint_states", 50)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    try:
        i = 0
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not any("recording /tf" in ln for ln in rec.output()):
            js.publish(_joint_state(i))
            i += 1
            ex.spin_once(timeout_sec=0.02)
        for _ in range(30):
            js.publish(_joint_state(i))
            i += 1
            ex.spin_once(timeout_sec=0.02)
        # Stop it in the middle of a dense stream and keep publishing until it has exited.
        rec.expect_exit()
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            js.publish(_joint_state(i))
            i += 1
            time.sleep(0.0002)
        rec.send_signal(2)
        end = time.monotonic() + 30
        while rec.popen.poll() is None and time.monotonic() < end:
            js.publish(_joint_state(i))
            i += 1
            time.sleep(0.0002)
    finally:
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
    m = rec.wait_for_line(r"recorded (\d+) messages on (\d+) topics", 20)
    assert rec.popen.wait(timeout=20) == 0
    _, topics = summarize(path)
    assert int(m.group(1)) == topics["*"].count and int(m.group(2)) == 2
    assert topics["/joint_states"].count >= 30 and topics["/tf"].count >= 1
    assert topics["*"].monotonic
    from mcap.reader import make_reader

    with open(path, "rb") as fh:  # the summary section was written (make_reader would do without it)
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == topics["*"].count
    first = read_messages(path, ["/joint_states"])[0][2]  # and the records decode
    assert list(first.name) == list(_joint_state(0).name)
