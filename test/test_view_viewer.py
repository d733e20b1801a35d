"""The browser view without a browser: the viser scene follows joint states and markers, the gizmo
hands out goals, the status panel says what it is given, and the ROS node wires topics to it.
(The page itself, in a real Chromium, is test/test_view_browser.py.)"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from support.waits import spin_until as spin_executor_until

from redarm_ros.kinematics import load_arm
from redarm_ros.view.urdf_model import model_for_arm
from redarm_ros.view.viewer import (
    ADD,
    CYLINDER,
    DELETE,
    DELETEALL,
    LINE_STRIP,
    SPHERE,
    ArmViewer,
    MarkerSpec,
    RateMeter,
    Status,
    scene_markers,
)

viser = pytest.importorskip("viser")

ARM = load_arm("pa10")
Q = np.array([0.3, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0])


@pytest.fixture
def server() -> Iterator[Any]:
    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        yield srv
    finally:
        srv.stop()


def _wxyz_to_R(wxyz: Any) -> np.ndarray:
    from redarm_ros.kinematics.quaternion import quat_to_matrix

    return quat_to_matrix(np.asarray(wxyz, dtype=float))


def test_binds_loopback_on_the_port_it_reports(server: Any) -> None:
    import socket

    port = server.get_port()
    assert port > 0
    with socket.create_connection(("127.0.0.1", port), timeout=5):
        pass


def test_arm_frames_follow_the_joint_states(server: Any) -> None:
    goals: list[tuple[np.ndarray, np.ndarray]] = []
    v = ArmViewer(server, model_for_arm("pa10"), on_goal=lambda p, q: goals.append((p, q)))
    v.set_joints(ARM.joint_names, Q)
    tool = v._link_frames["tool"]
    T = ARM.fk(Q)
    np.testing.assert_allclose(tool.position, T[:3, 3], atol=1e-9)
    np.testing.assert_allclose(_wxyz_to_R(tool.wxyz), T[:3, :3], atol=1e-9)
    # The gizmo starts on the tool; sending it hands out exactly that pose.
    v.send_goal()
    p, q_xyzw = goals[-1]
    np.testing.assert_allclose(p, T[:3, 3], atol=1e-9)
    np.testing.assert_allclose(_wxyz_to_R([q_xyzw[3], *q_xyzw[:3]]), T[:3, :3], atol=1e-9)
    # A second joint state moves the arm but not the gizmo (the user may have dragged it).
    q2 = Q + 0.2
    v.set_joints(ARM.joint_names, q2)
    np.testing.assert_allclose(tool.position, ARM.fk(q2)[:3, 3], atol=1e-9)
    np.testing.assert_allclose(v.gizmo.position, T[:3, 3], atol=1e-9)
    v.set_joints(["unknown_joint", ARM.joint_names[0]], [5.0, math.nan])  # ignored, nothing raised
    np.testing.assert_allclose(tool.position, ARM.fk(q2)[:3, 3], atol=1e-9)


def test_gizmo_streams_at_most_the_rate_and_always_sends_the_release(server: Any) -> None:
    sent: list[Any] = []
    v = ArmViewer(server, model_for_arm("pa10"), on_goal=lambda p, q: sent.append(p), goal_stream_hz=5.0)

    class Event:
        def __init__(self, phase: str) -> None:
            self.phase = phase

    for _ in range(10):  # a burst of drag updates within one stream period
        v._on_gizmo(Event("update"))
    assert len(sent) == 1
    v._on_gizmo(Event("end"))
    assert len(sent) == 2
    v.stream_box.value = False
    v._on_gizmo(Event("end"))
    assert len(sent) == 2  # streaming off: only "Send goal" publishes
    assert v.reach_button.disabled  # no on_reach given: the Reach button does nothing


def test_markers_add_modify_delete_and_groups(server: Any) -> None:
    v = ArmViewer(server, model_for_arm("pa10"))
    T = np.eye(4)
    T[:3, 3] = (0.2, -0.2, 0.7)
    ball = MarkerSpec("obstacles", 0, SPHERE, ADD, T, np.array([0.14] * 3), (0.5, 0.5, 0.5, 0.7))
    circle = MarkerSpec("elbow_circle", 0, LINE_STRIP, ADD, np.eye(4), np.array([0.008, 0, 0]),
                        (0.2, 0.6, 1.0, 0.8), np.array([[0.1, 0, 0.5], [0, 0.1, 0.5], [-0.1, 0, 0.5]]))
    v.set_markers("controller", [ball, circle])
    v.set_markers("obstacles", [MarkerSpec("obstacles", 0, CYLINDER, ADD, T, np.array([0.1, 0.1, 0.3]))])
    assert v.marker_keys() == [("controller", "elbow_circle", 0), ("controller", "obstacles", 0),
                               ("obstacles", "obstacles", 0)]
    node = v._markers[("controller", "obstacles", 0)][0]
    T2 = T.copy()
    T2[:3, 3] = (0.3, 0.0, 0.6)
    v.set_markers("controller", [MarkerSpec("obstacles", 0, SPHERE, ADD, T2, np.array([0.14] * 3),
                                            (0.5, 0.5, 0.5, 0.7))])
    assert v._markers[("controller", "obstacles", 0)][0] is node  # moved, not redrawn
    np.testing.assert_allclose(node.position, (0.3, 0.0, 0.6))
    v.set_markers("controller", [MarkerSpec("elbow_circle", 0, LINE_STRIP, DELETE)])
    assert v.marker_keys("controller") == [("controller", "obstacles", 0)]
    v.set_markers("controller", [MarkerSpec("", 0, SPHERE, DELETEALL)])
    assert v.marker_keys() == [("obstacles", "obstacles", 0)]


def test_scene_markers_draw_table_and_obstacles() -> None:
    scene = {"table_height": 0.0, "obstacles": [
        {"type": "sphere", "center": [0.2, -0.2, 0.7], "radius": 0.07},
        {"type": "cylinder", "center": [0.4, 0.3, 0.2], "radius": 0.05, "height": 0.4},
        {"type": "box", "center": [0.5, 0.0, 0.1], "size": [0.1, 0.2, 0.2], "yaw": math.pi / 2}]}
    ms = scene_markers(scene)
    assert [(m.ns, m.type) for m in ms] == [("table", 1), ("obstacles", SPHERE), ("obstacles", CYLINDER),
                                            ("obstacles", 1)]
    np.testing.assert_allclose(ms[1].scale, [0.14] * 3)
    np.testing.assert_allclose(ms[3].pose[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_status_panel_text_and_rates() -> None:
    s = Status(phase="reaching", swivel=math.radians(30), swivel_desired=math.radians(45), clearance=math.inf,
               distance_to_goal=0.0123, driver_state="running", driver_message="running: 7 modules",
               rates_hz={"/joint_states": 249.6})
    text = s.markdown()
    for needle in ("| phase | reaching |", "30.0 deg (desired 45.0 deg)", "| clearance | inf |",
                   "0.0123 m", "| driver | running: 7 modules |", "| rate /joint_states | 249.6 Hz |"):
        assert needle in text, (needle, text)
    assert "| swivel | - (desired -) |" in Status().markdown()
    r = RateMeter(window_s=2.0)
    for i in range(21):
        r.tick(10.0 + 0.01 * i)
    assert r.rate(10.2) == pytest.approx(100.0)
    assert r.rate(13.0) == 0.0  # everything older than the window is forgotten


def test_command_line_shorthands_become_parameters() -> None:
    from redarm_ros.nodes.view import ros_argv

    assert ros_argv([]) == []
    assert ros_argv(["--port", "0", "--arm", "powercube7"]) == ["--ros-args", "-p", "port:=0", "-p",
                                                                 "arm:=powercube7"]
    assert ros_argv(["--port", "9", "--ros-args", "-p", "goal_stream_hz:=5.0"]) == [
        "--ros-args", "-p", "goal_stream_hz:=5.0", "-p", "port:=9"]


def test_view_node_wires_topics_to_the_viewer(rclpy_context: Any) -> None:
    rclpy = pytest.importorskip("rclpy")
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from redarm_interfaces.msg import ControllerState
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import Marker, MarkerArray

    from redarm_ros.nodes.view import ViewNode

    node = ViewNode(context=rclpy_context, parameter_overrides=[Parameter("port", value=0)])
    peer = rclpy.create_node("view_test_peer", context=rclpy_context)
    goals: list[PoseStamped] = []
    peer.create_subscription(PoseStamped, "/goal_pose", goals.append, 10)
    js = peer.create_publisher(JointState, "/joint_states", 10)
    st = peer.create_publisher(ControllerState, "/controller/state", 10)
    mk = peer.create_publisher(MarkerArray, "/obstacles", 10)
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)

    def spin_until(pred: Any, timeout: float = 15.0) -> bool:
        return spin_executor_until(ex, pred, timeout)

    try:
        assert node.url.startswith("http://127.0.0.1:") and not node.url.endswith(":0/")
        tool = node.viewer._link_frames["tool"]

        def publish_all() -> None:
            js.publish(JointState(name=list(ARM.joint_names), position=[float(v) for v in Q]))
            st.publish(ControllerState(phase=ControllerState.REACHING, swivel=0.5, clearance=0.12))
            m = Marker(ns="obstacles", id=3, type=Marker.SPHERE, action=Marker.ADD)
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = m.scale.z = 0.1
            mk.publish(MarkerArray(markers=[m]))

        def all_seen() -> bool:
            publish_all()
            drawn = bool(np.allclose(tool.position, ARM.fk(Q)[:3, 3], atol=1e-9))
            return drawn and node.status.phase == "reaching" \
                and ("obstacles", "obstacles", 3) in node.viewer.marker_keys()

        assert spin_until(all_seen), (tool.position, node.status, node.viewer.marker_keys())
        node._refresh_status()
        assert "| phase | reaching |" in node.viewer._status_md.content
        assert spin_until(lambda: node.goal_pub.get_subscription_count() > 0)
        node.viewer.send_goal()
        assert spin_until(lambda: bool(goals))
        g = goals[-1]
        assert g.header.frame_id == "base_link"
        p = g.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], ARM.fk(Q)[:3, 3], atol=1e-9)
    finally:
        ex.shutdown(timeout_sec=1.0)
        node.close()
        node.destroy_node()
        peer.destroy_node()


def test_view_reach_button_sends_a_reach_goal_and_shows_the_outcome(rclpy_context: Any) -> None:
    rclpy = pytest.importorskip("rclpy")
    from rclpy.action import ActionServer
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from redarm_interfaces.action import Reach

    from redarm_ros.nodes.view import ViewNode

    node = ViewNode(context=rclpy_context, parameter_overrides=[Parameter("port", value=0)])
    peer = rclpy.create_node("controller", context=rclpy_context)  # a stand-in ~/reach server
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(peer)
    goals: list[Any] = []

    def execute(handle: Any) -> Any:
        goals.append(handle.request)
        handle.publish_feedback(Reach.Feedback(phase="reaching", distance_to_goal=0.2))
        handle.succeed()
        return Reach.Result(status=Reach.Result.SUCCESS, message="reached", position_error=2e-4)

    def spin_until(pred: Any, timeout: float = 15.0) -> bool:
        return spin_executor_until(ex, pred, timeout)

    try:
        assert not node.viewer.reach_button.disabled
        node.viewer._reach()  # what the button's click does
        assert spin_until(lambda: node.status.reach == "no action server /controller/reach")
        server = ActionServer(peer, Reach, "~/reach", execute)
        assert spin_until(node.reach_client.server_is_ready)
        node.viewer._reach()
        assert spin_until(lambda: node.status.reach.startswith("SUCCESS")), node.status.reach
        assert node.status.reach == "SUCCESS: reached (0.20 mm)"
        assert len(goals) == 1 and goals[0].target.header.frame_id == "base_link"
        p, q = node.viewer.gizmo_pose()
        pos, o = goals[0].target.pose.position, goals[0].target.pose.orientation
        np.testing.assert_allclose([pos.x, pos.y, pos.z], p, atol=1e-9)
        np.testing.assert_allclose([o.x, o.y, o.z, o.w], q, atol=1e-9)
        node._refresh_status()
        assert "| Reach action | SUCCESS: reached (0.20 mm) |" in node.viewer._status_md.content
        server.destroy()
    finally:
        ex.shutdown(timeout_sec=1.0)
        node.close()
        node.destroy_node()
        peer.destroy_node()
