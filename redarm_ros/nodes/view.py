"""``view`` (also ``redarm-view``): the arm in a web browser, live from ROS topics (viser).

A thin rclpy shell around :class:`redarm_ros.view.viewer.ArmViewer`, which serves the page with
``viser`` (its web client is bundled in the wheel, so no network is needed) on ``host:port``
(127.0.0.1:8080 by default; port 0 picks a free one). Prints ``view ready: http://HOST:PORT/``.

Topic names are relative, so a view started in the namespace of a stack (``--ros-args -r __ns:=/left``)
shows that stack (``/left/joint_states`` ...); ``/diagnostics`` is global by ROS convention.

* in  ``joint_states`` (sensor_msgs/JointState): poses the arm (redrawn at ``update_rate_hz``);
* in  ``controller/state`` (redarm_interfaces/ControllerState): phase, swivel, clearance, distance;
* in  ``controller/markers``, ``obstacles`` (visualization_msgs/MarkerArray): goal, heading arrow,
  elbow circle, table, obstacles;
* in  ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): the CAN driver's state and loop rate;
* in  ``robot_description`` (std_msgs/String, transient local), when someone publishes it: the URDF
  to draw; until then (or without it) the URDF generated from the ``arm`` model;
* out ``goal_pose`` (geometry_msgs/PoseStamped in ``base_frame``): the transform gizmo's pose, streamed
  while it is dragged (at most ``goal_stream_hz``) or sent with the "Send goal" button;
* action client of ``controller/reach`` (redarm_interfaces/action/Reach): the "Reach (action)" button
  sends the gizmo pose as a Reach goal; its feedback and result show in the status panel.

``placement`` (a ``placements.npz`` of ``redarm-placement``) draws its heat map on the floor, the arm
standing at the best placement (:mod:`redarm_ros.view.placement_floor`).

Command line: ``redarm-view [--host H] [--port P] [--arm NAME] [--scene NAME|PATH] [--placement NPZ]``
(shorthands for the parameters) or ``--ros-args -p port:=8081 ...``. See docs/view.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, QoSProfile
from redarm_interfaces.action import Reach
from redarm_interfaces.msg import ControllerState
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from visualization_msgs.msg import Marker, MarkerArray

from redarm_ros.errors import InvalidInputError, RedarmError
from redarm_ros.nodes._common import ParamNode, ParamSpec, in_range, positive, run_node
from redarm_ros.view.placement_floor import load_placements, placement_floor
from redarm_ros.view.urdf_model import UrdfModel, model_for_arm
from redarm_ros.view.viewer import ArmViewer, MarkerSpec, RateMeter, Status, scene_markers

NODE_NAME = "view"
REACH_ACTION = "controller/reach"
# Relative names: resolved in the node's namespace (see the module docstring).
JOINT_STATES, GOAL_POSE, ROBOT_DESCRIPTION = "joint_states", "goal_pose", "robot_description"
CONTROLLER_STATE, CONTROLLER_MARKERS, OBSTACLES = "controller/state", "controller/markers", "obstacles"
REACH_REJECTED = "Reach goal rejected"  # how the controller's state message starts for a rejected goal
DRIVER_LOOP_STATUS = "can_driver: loop"  # DiagnosticStatus name of the driver's loop (can_driver node)

PARAMS = [
    ParamSpec("host", "127.0.0.1", "Address the web server binds (127.0.0.1: this machine only).",
              read_only=True),
    ParamSpec("port", 8080, "TCP port of the web page (0 = any free port; a busy one is skipped).",
              in_range(0, 65535), read_only=True),
    ParamSpec("arm", "pa10", "Arm model whose generated URDF is drawn until /robot_description arrives.",
              read_only=True),
    ParamSpec("scene", "", "Scene (config/scenes name or YAML path) drawn as markers; for runs without "
              "a controller, whose markers already show its scene ('' = none).", read_only=True),
    ParamSpec("placement", "", "placements.npz of redarm-placement drawn on the floor, the arm standing at "
              "the best placement ('' = none).", read_only=True),
    ParamSpec("base_frame", "base_link", "frame_id of the goals published on /goal_pose.", read_only=True),
    ParamSpec("update_rate_hz", 30.0, "How often the drawn arm follows /joint_states (Hz).",
              in_range(1.0, 120.0), read_only=True),
    ParamSpec("goal_stream_hz", 20.0, "Largest rate of goals streamed while dragging the gizmo (Hz).",
              positive, read_only=True),
]


def marker_spec(m: Marker) -> MarkerSpec:
    """The viewer's copy of a visualization_msgs/Marker (quaternion x, y, z, w -> 4x4 pose)."""
    from redarm_ros.kinematics.quaternion import quat_to_matrix

    o = m.pose.orientation
    n = math.sqrt(o.w * o.w + o.x * o.x + o.y * o.y + o.z * o.z)
    T = np.eye(4)
    if n > 1e-9 and math.isfinite(n):
        T[:3, :3] = quat_to_matrix(np.array([o.w, o.x, o.y, o.z]) / n)
    T[:3, 3] = (m.pose.position.x, m.pose.position.y, m.pose.position.z)
    pts = np.array([[p.x, p.y, p.z] for p in m.points], dtype=float).reshape(-1, 3)
    return MarkerSpec(m.ns, int(m.id), int(m.type), int(m.action), T,
                      np.array([m.scale.x, m.scale.y, m.scale.z], dtype=float),
                      (m.color.r, m.color.g, m.color.b, m.color.a), pts)


class ViewNode(ParamNode, node_name=NODE_NAME, params=PARAMS):
    """``view``: ROS topics in, a viser page out (see the module docstring)."""

    def _setup(self, p: dict[str, Any]) -> None:
        import viser  # here, not at import time: `--help` and the package tests need no web server

        try:
            model = model_for_arm(p["arm"])
            scene = _load_scene(p["scene"]) if p["scene"] else None
            floor = placement_floor(load_placements(p["placement"])) if p["placement"] else None
        except (RedarmError, OSError) as exc:
            raise ValueError(f"view configuration: {exc}") from exc
        self.base_frame = p["base_frame"]
        self.server = viser.ViserServer(host=p["host"], port=int(p["port"]), verbose=False)
        self.url = f"http://{p['host']}:{self.server.get_port()}/"
        self.goal_pub = self.create_publisher(PoseStamped, GOAL_POSE, QoSProfile(depth=10))
        self.reach_client = ActionClient(self, Reach, REACH_ACTION)
        self.reach_action = self.resolve_topic_name(REACH_ACTION)  # e.g. /left/controller/reach
        self.viewer = ArmViewer(self.server, model, on_goal=self._publish_goal, on_reach=self._send_reach,
                                goal_stream_hz=float(p["goal_stream_hz"]), base_frame=self.base_frame)
        if scene is not None:
            self.viewer.set_markers("scene", scene_markers(scene))
        if floor is not None:
            self.viewer.set_placement(floor, p["placement"])
        self.status = Status()
        self.rates = {"joint_states": RateMeter(), "controller": RateMeter()}
        self._joints: tuple[list[str], list[float]] | None = None
        self._joints_drawn = True
        self._markers: dict[str, list[MarkerSpec]] = {}
        self._driver_rate = math.nan
        self._description = ""
        self._reach_request: tuple[np.ndarray, np.ndarray] | None = None  # the Reach button's pose
        # Wiring.
        self._js_sub = self.create_subscription(JointState, JOINT_STATES, self._on_joint_states, 20)
        self._state_sub = self.create_subscription(ControllerState, CONTROLLER_STATE, self._on_state, 20)
        self.create_subscription(MarkerArray, CONTROLLER_MARKERS,
                                 lambda m: self._on_markers("controller", m), 5)
        self.create_subscription(MarkerArray, OBSTACLES, lambda m: self._on_markers("obstacles", m), 5)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(String, ROBOT_DESCRIPTION, self._on_description, latched)
        self.create_timer(1.0 / float(p["update_rate_hz"]), self._redraw)
        self.create_timer(0.5, self._refresh_status)
        goals = self.goal_pub.topic_name
        self.get_logger().info(f"view ready: {self.url} (arm {p['arm']}, goals on {goals} in "
                               f"{self.base_frame!r})")

    # -- inputs: store, the timers draw ---------------------------------------------------------------
    def _on_joint_states(self, msg: JointState) -> None:
        self.rates["joint_states"].tick()
        self._joints = (list(msg.name), list(msg.position))
        self._joints_drawn = False

    def _on_state(self, msg: ControllerState) -> None:
        self.rates["controller"].tick()
        s = self.status
        s.phase, s.message = msg.phase, msg.message
        s.swivel, s.swivel_desired = msg.swivel, msg.swivel_desired
        s.clearance, s.distance_to_goal = msg.clearance, msg.distance_to_goal
        if msg.message.startswith(REACH_REJECTED):  # the controller says why it rejected a Reach goal
            s.reach = msg.message

    def _on_markers(self, group: str, msg: MarkerArray) -> None:
        self._markers.setdefault(group, []).extend(marker_spec(m) for m in msg.markers)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for st in msg.status:
            if st.name != DRIVER_LOOP_STATUS:
                continue
            values = {kv.key: kv.value for kv in st.values}
            self.status.driver_state = values.get("state", "")
            self.status.driver_message = st.message
            try:
                self._driver_rate = float(values.get("rate_hz_achieved", "nan"))
            except ValueError:
                self._driver_rate = math.nan

    def _on_description(self, msg: String) -> None:
        if msg.data == self._description:
            return
        try:
            model = UrdfModel.from_string(msg.data)
        except InvalidInputError as exc:
            self.get_logger().warning(f"/robot_description not drawn: {exc}")
            return
        self._description = msg.data
        self.viewer.set_model(model)
        self.get_logger().info(f"drawing the URDF from /robot_description ({model.name}, "
                               f"{len(model.movable_joint_names)} joints)")

    # -- output ---------------------------------------------------------------------------------------
    def _publish_goal(self, position: np.ndarray, quat_xyzw: np.ndarray) -> None:
        # Called from viser's threads; rclpy publishers may be used from any thread.
        msg = PoseStamped()
        msg.header.frame_id = self.base_frame
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in position)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quat_xyzw)
        self.goal_pub.publish(msg)

    def _send_reach(self, position: np.ndarray, quat_xyzw: np.ndarray) -> None:
        # Called from viser's threads: the executor sends it (the action client is not thread-safe).
        self._reach_request = (np.array(position, dtype=float), np.array(quat_xyzw, dtype=float))

    def _send_reach_goal(self, position: np.ndarray, quat_xyzw: np.ndarray) -> None:
        if not self.reach_client.server_is_ready():
            self.status.reach = f"no action server {self.reach_action}"
            return
        goal = Reach.Goal()
        goal.target.header.frame_id = self.base_frame
        goal.target.pose.position.x, goal.target.pose.position.y, goal.target.pose.position.z = (
            float(v) for v in position)
        o = goal.target.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quat_xyzw)
        self.status.reach = "goal sent"
        self.reach_client.send_goal_async(goal, feedback_callback=self._on_reach_feedback) \
            .add_done_callback(self._on_reach_answer)

    def _on_reach_feedback(self, msg: Any) -> None:
        f = msg.feedback
        self.status.reach = f"{f.phase}, {f.distance_to_goal:.4f} m to go"

    def _on_reach_answer(self, future: Any) -> None:
        handle = future.result()
        if not handle.accepted:
            if not self.status.reach.startswith(REACH_REJECTED):  # the reason comes on /controller/state
                self.status.reach = "rejected"
            return
        handle.get_result_async().add_done_callback(self._on_reach_result)

    def _on_reach_result(self, future: Any) -> None:
        r = future.result().result
        name = next((n for n in dir(Reach.Result) if n.isupper() and getattr(Reach.Result, n) == r.status),
                    str(r.status))
        self.status.reach = f"{name}: {r.message} ({r.position_error * 1e3:.2f} mm)"

    # -- timers ---------------------------------------------------------------------------------------
    def _redraw(self) -> None:
        request, self._reach_request = self._reach_request, None
        if request is not None:
            self._send_reach_goal(*request)
        if self._joints is not None and not self._joints_drawn:
            self._joints_drawn = True
            self.viewer.set_joints(*self._joints)
        pending, self._markers = self._markers, {}
        for group, specs in pending.items():
            self.viewer.set_markers(group, specs)

    def _refresh_status(self) -> None:
        now = time.monotonic()
        rates = {self._js_sub.topic_name: self.rates["joint_states"].rate(now),
                 self._state_sub.topic_name: self.rates["controller"].rate(now)}
        if math.isfinite(self._driver_rate):
            rates["driver loop (diagnostics)"] = self._driver_rate
        self.status.rates_hz = rates
        self.viewer.set_status(self.status)

    def close(self) -> None:
        """Stop the web server and the action client (called by the standard main before destroy_node)."""
        self.server.stop()
        self.reach_client.destroy()


def _load_scene(name: str) -> dict[str, Any]:
    from redarm_ros.geometry.obstacles import load_scene

    return load_scene(name).to_dict()


def build_parser() -> argparse.ArgumentParser:
    """The shorthand options of ``redarm-view`` (each sets the parameter of the same name)."""
    ap = argparse.ArgumentParser(prog="redarm-view",
                                 description="The arm in a web browser, live from ROS topics (viser).",
                                 epilog="Anything after --ros-args goes to ROS (e.g. -p goal_stream_hz:=10).")
    ap.add_argument("--host", help="bind address (default 127.0.0.1)")
    ap.add_argument("--port", type=int, help="TCP port (default 8080; 0 = any free port)")
    ap.add_argument("--arm", help="arm model drawn until /robot_description arrives (default pa10)")
    ap.add_argument("--scene", help="scene drawn as markers (config/scenes name or YAML path)")
    ap.add_argument("--placement", help="placements.npz of redarm-placement: its heat map on the floor")
    return ap


def ros_argv(argv: Sequence[str]) -> list[str]:
    """``argv`` with the shorthand options turned into ``--ros-args -p name:=value`` overrides."""
    argv = list(argv)
    ros: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros = argv[:i], argv[i:]
    ns = build_parser().parse_args(argv)
    params = [f"{k}:={v}" for k, v in vars(ns).items() if v is not None]
    if not params:
        return ros
    extra = [x for p in params for x in ("-p", p)]
    return (ros + extra) if ros else ["--ros-args", *extra]


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``ros2 run redarm_ros view``, ``redarm-view``)."""
    argv = list(sys.argv[1:] if args is None else args)
    return run_node(ViewNode, [sys.argv[0], *ros_argv(argv)])


if __name__ == "__main__":
    raise SystemExit(main())
