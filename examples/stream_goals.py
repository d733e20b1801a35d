#!/usr/bin/env python3
"""Stream Cartesian goals to the controller: a PoseStamped on goal_pose at 50 Hz along a circle.

    python examples/stream_goals.py                   # 5 cm circle at (0.5, 0, 0.4) m, tool down, 4 s
    python examples/stream_goals.py --radius 0.08 --period 6 --duration 12

The controller treats a goal as one more sample of a stream (and follows it without lag, estimating
its velocity from the header stamps) when it comes within ``stream_gap_s`` (0.5 s) of the previous one
and within ``stream_jump`` (5 cm) of where the stream was predicted to be at its stamp; anything else
is a new goal. So: stamp each pose with the time it belongs to, publish at a steady rate, move
smoothly. The first pose is far from the arm, so it is sent alone and reached first.
"""

import argparse
import math
import sys
import time

import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.utilities import remove_ros_args
from redarm_interfaces.msg import ControllerState

RATE_HZ = 50.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--center", type=float, nargs=3, default=[0.5, 0.0, 0.4], help="circle centre (m)")
    ap.add_argument("--radius", type=float, default=0.05, help="circle radius (m)")
    ap.add_argument("--period", type=float, default=4.0, help="seconds per turn")
    ap.add_argument("--duration", type=float, default=4.0, help="seconds of streaming")
    args = ap.parse_args(remove_ros_args(sys.argv)[1:])

    rclpy.init()
    node = rclpy.create_node("stream_goals_example")
    pub = node.create_publisher(PoseStamped, "goal_pose", 10)
    state: list[ControllerState] = []
    node.create_subscription(ControllerState, "controller/state", lambda m: state.append(m), 10)

    def pose_at(t: float) -> PoseStamped:
        msg = PoseStamped()
        msg.header.frame_id = "base_link"
        msg.header.stamp = node.get_clock().now().to_msg()  # the time this sample belongs to
        a = 2.0 * math.pi * t / args.period
        cx, cy, cz = args.center
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (
            cx + args.radius * math.cos(a), cy + args.radius * math.sin(a), cz)
        msg.pose.orientation.x, msg.pose.orientation.w = 1.0, 0.0  # tool pointing down
        return msg

    def spin_for(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.01)

    try:
        # 1. Go to the circle's start and wait until the controller reports it reached.
        first = pose_at(0.0).pose.position
        end = time.monotonic() + 60.0
        while not any(s.phase == ControllerState.REACHED and abs(s.goal.position.x - first.x) < 1e-6
                      and abs(s.goal.position.y - first.y) < 1e-6 for s in state[-5:]) \
                and time.monotonic() < end:
            pub.publish(pose_at(0.0))  # re-sent each second until the controller has it
            spin_for(1.0)
        if time.monotonic() >= end:
            print("the start of the circle was not reached; is the stack running?", file=sys.stderr)
            return 1
        print("reached the start of the circle")
        # 2. Stream: one stamped sample every 20 ms.
        state.clear()
        start, sent = time.monotonic(), 0
        while (t := time.monotonic() - start) < args.duration:
            pub.publish(pose_at(t))
            sent += 1
            spin_for(start + sent / RATE_HZ - time.monotonic())
        spin_for(0.3)
        tracking = [s.distance_to_goal for s in state if s.phase == ControllerState.TRACKING]
        print(f"streamed {sent} goals in {args.duration:g} s; controller reports: "
              f"{len(tracking)} tracking states, median distance to the goal "
              f"{sorted(tracking)[len(tracking) // 2] * 1000 if tracking else float('nan'):.1f} mm")
        return 0 if tracking else 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
