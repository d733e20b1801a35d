"""Robot description node: the arm's URDF on ``robot_description`` (std_msgs/String, transient local).

This is what robot_state_publisher does with its ``robot_description`` parameter, for a stack without
it (the bring-up needs no ROS tools): the URDF is published once with a durable QoS (reliable,
transient local, depth 1), so a subscriber that joins later (RViz, MoveIt, a recorder) still gets it.

The text is built from the arm model by :func:`redarm_ros.sim.urdf.build_urdf`, the same generator
the build step uses for ``share/redarm_ros/urdf/<arm>.urdf``, so with the default (empty) ``prefix``
it is byte for byte the installed file. ``urdf_file`` publishes a given file instead.

Run: ``ros2 run redarm_ros description --ros-args -p arm:=pa10`` (or ``python -m
redarm_ros.nodes.description``). Parameters, frames and examples: docs/nodes.md.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from redarm_ros.errors import RedarmError
from redarm_ros.kinematics import load_arm
from redarm_ros.nodes._common import (
    ParamNode,
    ParamSpec,
    UniqueNameCheck,
    any_string,
    non_empty_string,
    non_negative,
    run_node,
    watch_duplicates,
)
from redarm_ros.sim.urdf import build_urdf

NODE_NAME = "description"
TOPIC = "robot_description"

# As robot_state_publisher publishes it: a late subscriber with transient-local durability gets the
# last message.
DESCRIPTION_QOS = QoSProfile(
    depth=1,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


PARAMS = [
    ParamSpec("arm", "pa10", "Arm model: name of config/arms/<name>.yaml, or a YAML path.",
              non_empty_string, read_only=True),
    ParamSpec("prefix", "", "Put in front of every link name and of the tool joint (e.g. 'left_'); "
              "joint names stay the model's.", any_string, read_only=True),
    ParamSpec("urdf_file", "", "Publish this URDF file instead of generating one from `arm`.",
              any_string, read_only=True),
    ParamSpec("duplicate_check_s", 1.0, "At start-up, watch the ROS graph this long (s) for another "
              "node of the same name and refuse to start if there is one (0 = no check).",
              non_negative, read_only=True),
]


@dataclass(frozen=True)
class DescriptionSummary:
    """What a URDF holds, for the start-up line: robot ``name``, ``root`` link, ``tips`` (leaf links),
    movable ``joints`` in document order."""

    name: str
    root: str
    tips: list[str]
    joints: list[str]


def robot_description(arm: str = "pa10", prefix: str = "", urdf_file: str = "") -> str:
    """URDF text: the file ``urdf_file`` if given, else generated from arm model ``arm``.

    Raises:
        ValueError: the file cannot be read, the arm model cannot be loaded or turned into a URDF.
    """
    if urdf_file:
        try:
            with open(urdf_file, encoding="utf-8") as fh:
                return fh.read()
        except OSError as exc:
            raise ValueError(f"parameter urdf_file: cannot read {urdf_file!r}: {exc}") from exc
    try:
        return build_urdf(load_arm(arm), prefix=prefix)
    except RedarmError as exc:
        raise ValueError(f"parameter arm: cannot build a URDF for {arm!r}: {exc}") from exc


def summarize(urdf: str) -> DescriptionSummary:
    """Robot name, root link, leaf links and movable joints of a URDF text.

    Raises:
        ValueError: not XML, not a <robot>, or not a single tree.
    """
    try:
        root = ET.fromstring(urdf)
    except ET.ParseError as exc:
        raise ValueError(f"robot description is not XML: {exc}") from exc
    if root.tag != "robot":
        raise ValueError(f"robot description has <{root.tag}> at the top, not <robot>")
    links = [e.get("name", "") for e in root.findall("link")]
    joints = root.findall("joint")
    children = {j.find("child").get("link") for j in joints if j.find("child") is not None}
    parents = {j.find("parent").get("link") for j in joints if j.find("parent") is not None}
    roots = [n for n in links if n not in children]
    if len(roots) != 1:
        raise ValueError(f"robot description must have exactly one root link, found {roots}")
    return DescriptionSummary(
        name=root.get("name", ""),
        root=roots[0],
        tips=[n for n in links if n not in parents],
        joints=[j.get("name", "") for j in joints if j.get("type") != "fixed"],
    )


class DescriptionNode(ParamNode, node_name=NODE_NAME, params=PARAMS):
    """``description``: publishes the URDF once on ``robot_description`` (transient local)."""

    def _setup(self, p: dict[str, Any]) -> None:
        self.urdf = robot_description(p["arm"], p["prefix"], p["urdf_file"])
        self.summary = summarize(self.urdf)
        self.name_check = UniqueNameCheck(self, p["duplicate_check_s"])  # a timer: no blocking here
        watch_duplicates(self, yield_to_elder=p["duplicate_check_s"] > 0)
        self.pub = self.create_publisher(String, TOPIC, DESCRIPTION_QOS)
        self.pub.publish(String(data=self.urdf))
        s = self.summary
        source = p["urdf_file"] or f"arm model {p['arm']}"
        self.get_logger().info(
            f"{NODE_NAME} ready: publishing {self.pub.topic_name} ({source}, robot '{s.name}', "
            f"{len(self.urdf)} bytes): root link {s.root}, tool {', '.join(s.tips)}, "
            f"joints {', '.join(s.joints)}"
        )


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``ros2 run redarm_ros description``)."""
    return run_node(DescriptionNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
