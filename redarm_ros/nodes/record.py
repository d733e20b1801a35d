"""``redarm-record``: write ROS 2 topics to an MCAP file, as ``ros2 bag record -s mcap`` would.

Subscribes to the named topics (or all, ``--all``) as they appear in the graph, with the QoS the
publishers offer (reliable / transient local only when every publisher offers it, as rosbag2
adapts), and appends each message's serialized CDR bytes to the file with its ROS 2 schema
(:mod:`redarm_ros.record.mcap_io`). With ``--tf-from-joint-states`` it also writes ``/tf``
(``tf2_msgs/TFMessage``) computed from ``/joint_states`` through the arm's URDF (from
``/robot_description`` when that is published, else generated from ``--arm``), so the arm shows in
Foxglove's 3-D panel without a robot_state_publisher.

Prints ``record ready: writing PATH``, then ``recording TOPIC (TYPE)`` per topic; Ctrl-C / SIGTERM
(or ``--duration``) closes the file and prints the counts. See docs/view.md (recordings).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import re
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from redarm_ros.errors import InvalidInputError, RedarmError
from redarm_ros.nodes._common import single_threaded_executor
from redarm_ros.record.mcap_io import INFINITE_NS, QosOffer, Ros2McapWriter
from redarm_ros.record.schema import TF_MESSAGE_TYPE
from redarm_ros.record.tf import tf_message
from redarm_ros.view.urdf_model import UrdfModel, model_for_arm

_LOG = logging.getLogger("redarm_ros.record")
NODE_NAME = "redarm_record"
TF_TOPIC = "/tf"
# Relative: resolved in the recorder's namespace (a stack under __ns:=/left has /left/joint_states).
JOINT_STATES = "joint_states"
ROBOT_DESCRIPTION = "robot_description"


def _ns(duration: Any) -> int:
    ns = int(getattr(duration, "nanoseconds", 0))
    return INFINITE_NS if ns <= 0 or ns >= INFINITE_NS else ns


def offer_of(profile: QoSProfile) -> QosOffer:
    """The recorded form of a publisher's QoS profile (rclpy enums carry rmw's numbers)."""
    return QosOffer(history=int(profile.history), depth=int(profile.depth),
                    reliability=int(profile.reliability), durability=int(profile.durability),
                    deadline_ns=_ns(profile.deadline), lifespan_ns=_ns(profile.lifespan),
                    liveliness=int(profile.liveliness),
                    liveliness_lease_ns=_ns(profile.liveliness_lease_duration))


def message_class(type_name: str) -> Any:
    """The Python class of ``pkg/msg/Type``.

    Raises:
        InvalidInputError: the package is not importable or has no such message.
    """
    parts = type_name.split("/")
    try:
        return getattr(importlib.import_module(f"{parts[0]}.msg"), parts[-1])
    except (ImportError, AttributeError) as exc:
        raise InvalidInputError(f"message type {type_name} is not importable here: {exc}", field="type",
                                value=type_name) from exc


class RecorderNode(Node):
    """Records ``topics`` (None = every topic but those matching ``exclude``) into ``writer``.

    The caller owns the writer (closes it after destroying the node). Log times are this process's
    wall clock, advanced by the monotonic clock so they never step back within a recording.
    """

    def __init__(
        self,
        writer: Ros2McapWriter,
        topics: Sequence[str] | None = None,
        *,
        exclude: str = "",
        tf_from_joint_states: bool = False,
        tf_model: UrdfModel | None = None,
        tf_rate_hz: float = 30.0,
        base_frame: str = "base_link",
        discovery_period_s: float = 0.25,
        context: Any = None,
        parameter_overrides: list[Any] | None = None,
        node_name: str = NODE_NAME,
        namespace: str | None = None,
    ) -> None:
        # The keywords every redarm node takes; the recorder's own settings come before them.
        super().__init__(node_name, namespace=namespace, context=context,
                         parameter_overrides=parameter_overrides or [])
        self.writer = writer
        # relative names resolve in this node's namespace, as a node's own topics would
        self.wanted = None if topics is None else {self.resolve_topic_name(t) for t in topics}
        self.joint_states_topic = self.resolve_topic_name(JOINT_STATES)
        self.description_topic = self.resolve_topic_name(ROBOT_DESCRIPTION)
        self.exclude = re.compile(exclude) if exclude else None
        self.tf_model = tf_model
        self.tf_period_ns = int(1e9 / tf_rate_hz) if tf_rate_hz > 0 else 0
        self.base_frame = base_frame
        self._last_tf_ns = -(1 << 62)
        self._subs: dict[str, Any] = {}
        self._skipped: set[str] = set()
        self._t0_wall = time.time_ns()
        self._t0_mono = time.monotonic_ns()
        self._joint_state_cls: Any = None
        if tf_from_joint_states:
            from sensor_msgs.msg import JointState
            from std_msgs.msg import String

            self._joint_state_cls = JointState
            if self.tf_model is None:
                self.tf_model = model_for_arm("pa10")
            # The URDF on /robot_description (latched), when someone publishes it, replaces the model.
            latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.create_subscription(String, ROBOT_DESCRIPTION, self._on_description, latched)
            if self.joint_states_topic not in self._subs and self._wants(self.joint_states_topic) is False:
                # /tf needs the joint states even when they are not recorded themselves.
                self.create_subscription(JointState, JOINT_STATES, self._on_joint_state_for_tf, 50)
        self.create_timer(discovery_period_s, self.discover)
        self.discover()

    def now_ns(self) -> int:
        """Log time: wall clock at start + monotonic time since (ns)."""
        return self._t0_wall + (time.monotonic_ns() - self._t0_mono)

    def _wants(self, topic: str) -> bool:
        if self.wanted is not None:
            return topic in self.wanted
        if topic == TF_TOPIC and self._joint_state_cls is not None:
            return False  # /tf comes from the joint states here; a live /tf would interleave with it
        return not (self.exclude is not None and self.exclude.search(topic))

    # -- discovery ------------------------------------------------------------------------------------
    def discover(self) -> None:
        """Subscribe to every wanted topic that now has a publisher."""
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or topic in self._skipped or not self._wants(topic) or not types:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # QoS unknown until a publisher exists (rosbag2 waits the same way)
            type_name = types[0]
            try:
                cls = message_class(type_name)
                offers = [offer_of(i.qos_profile) for i in infos]
                h = infos[0].topic_type_hash
                type_hash = f"RIHS{h.version:02d}_{h.value.hex()}" if h.version > 0 else ""
                self.writer.add_topic(topic, type_name, offers=offers, type_hash=type_hash)
            except RedarmError as exc:
                self._skipped.add(topic)
                self.get_logger().warning(f"not recording {topic}: {exc}")
                continue
            reliable = all(o.reliability == int(ReliabilityPolicy.RELIABLE) for o in offers)
            latched = all(o.durability == int(DurabilityPolicy.TRANSIENT_LOCAL) for o in offers)
            qos = QoSProfile(
                history=HistoryPolicy.KEEP_LAST, depth=100,
                reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            self._subs[topic] = self.create_subscription(
                cls, topic, lambda data, t=topic: self._on_raw(t, data), qos, raw=True)
            self.get_logger().info(f"recording {topic} ({type_name})")

    @property
    def topics(self) -> list[str]:
        """Topics subscribed so far."""
        return sorted(self._subs)

    # -- messages -------------------------------------------------------------------------------------
    def _on_raw(self, topic: str, data: bytes) -> None:
        t = self.now_ns()
        self.writer.write(topic, data, t)
        if topic == self.joint_states_topic and self._joint_state_cls is not None and self._tf_due(t):
            from rclpy.serialization import deserialize_message  # only for the /tf samples

            self._tf_from(deserialize_message(data, self._joint_state_cls), t)

    def _on_joint_state_for_tf(self, msg: Any) -> None:
        self._tf_from(msg, self.now_ns())

    def _tf_due(self, t: int) -> bool:
        return self.tf_model is not None and t - self._last_tf_ns >= self.tf_period_ns

    def _tf_from(self, msg: Any, t: int) -> None:
        if not self._tf_due(t):
            return
        self._last_tf_ns = t
        if not self.writer.has_topic(TF_TOPIC):
            # What a tf broadcaster offers: reliable, volatile, keep last 100.
            self.writer.add_topic(TF_TOPIC, TF_MESSAGE_TYPE, offers=[QosOffer(depth=100)])
            self.get_logger().info(
                f"recording {TF_TOPIC} ({TF_MESSAGE_TYPE}, from {self.joint_states_topic})")
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        positions = dict(zip(msg.name, msg.position, strict=False))
        self.writer.write_dict(TF_TOPIC, tf_message(self.tf_model, positions, stamp or t, self.base_frame), t)

    def _on_description(self, msg: Any) -> None:
        try:
            model = UrdfModel.from_string(msg.data)
        except InvalidInputError as exc:
            self.get_logger().warning(f"{self.description_topic} not usable for /tf: {exc}")
            return
        if self.tf_model is None or model.text != self.tf_model.text:
            self.tf_model = model
            self.get_logger().info(f"/tf now from the URDF on {self.description_topic} ({model.name})")


def build_parser() -> argparse.ArgumentParser:
    """The ``redarm-record`` argument parser."""
    ap = argparse.ArgumentParser(prog="redarm-record", description="Write ROS 2 topics to an MCAP file "
                                 "with their schemas, as `ros2 bag record -s mcap` would.")
    ap.add_argument("topics", nargs="*", help="topics to record (e.g. /joint_states /goal_pose)")
    ap.add_argument("-a", "--all", action="store_true", help="record every topic (see --exclude)")
    ap.add_argument("-o", "--output", help="MCAP file to write (default redarm_YYYYmmdd-HHMMSS.mcap)")
    ap.add_argument("--exclude", default="", help="with --all: skip topics matching this regular expression")
    ap.add_argument("--tf-from-joint-states", action="store_true",
                    help="also write /tf (tf2_msgs/TFMessage) computed from /joint_states and the URDF")
    ap.add_argument("--arm", default="pa10", help="arm whose generated URDF gives /tf until "
                    "/robot_description is published (default pa10)")
    ap.add_argument("--base-frame", default="base_link",
                    help="frame the controller's markers use; /tf adds it as the URDF root's parent")
    ap.add_argument("--tf-rate", type=float, default=30.0, help="largest /tf rate written (Hz, default 30)")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0 = until "
                    "Ctrl-C / SIGTERM)")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                    help="chunk compression (default zstd)")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point. Exit codes: 0 recorded and closed, 1 bad arguments or start-up failure."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    args_all = list(sys.argv[1:] if argv is None else argv)
    ros_args = args_all[args_all.index("--ros-args"):] if "--ros-args" in args_all else []
    ns = build_parser().parse_args(args_all[: len(args_all) - len(ros_args)])
    logging.basicConfig(level=logging.INFO, format="[record] %(message)s", stream=sys.stderr)
    if not ns.all and not ns.topics:
        _LOG.error("name topics to record, or --all")
        return 1
    out = Path(ns.output or time.strftime("redarm_%Y%m%d-%H%M%S.mcap"))
    # Ctrl-C / SIGTERM only set a flag that the spin loop checks: an exception raised in the middle of
    # appending a message would leave a torn record inside the chunk being built.
    stop = threading.Event()

    def request_stop(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    rclpy.init(args=[sys.argv[0], *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    writer: Ros2McapWriter | None = None
    node: RecorderNode | None = None
    try:
        try:
            model = model_for_arm(ns.arm) if ns.tf_from_joint_states else None
            writer = Ros2McapWriter(out, compression=ns.compression)
            node = RecorderNode(writer, None if ns.all else ns.topics, exclude=ns.exclude,
                                tf_from_joint_states=ns.tf_from_joint_states, tf_model=model,
                                tf_rate_hz=ns.tf_rate, base_frame=ns.base_frame)
        except (RedarmError, OSError, ValueError) as exc:
            _LOG.error("could not start: %s", exc)
            return 1
        node.get_logger().info(f"record ready: writing {out}")
        ex = single_threaded_executor()
        ex.add_node(node)
        deadline = time.monotonic() + ns.duration if ns.duration > 0 else None
        try:
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                ex.spin_once(timeout_sec=0.1)
        except ExternalShutdownException:
            pass
        finally:
            ex.shutdown(timeout_sec=1.0)
    finally:
        if node is not None:
            node.destroy_node()
        if writer is not None:
            writer.close()
            total = sum(writer.counts.values())
            _LOG.info("recorded %d messages on %d topics to %s: %s", total, len(writer.counts), out,
                      ", ".join(f"{t} {n}" for t, n in sorted(writer.counts.items())))
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
