#!/usr/bin/env python3
"""Move the hand at a velocity for a second: TwistStamped on the controller's ~/target_twist at 50 Hz.

    python examples/send_twist.py                     # 5 cm/s along +y of base_link for 1 s
    python examples/send_twist.py --linear 0 0 -0.03 --frame tool --seconds 2

Each twist is held for the controller's ``twist_timeout_s`` (0.1 s); after the last one the hand
decelerates to rest. Start from a bent arm (send a goal first): at the homed pose the PA10 stands
stretched straight up, where the hand cannot move sideways.
"""

import argparse
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import TwistStamped
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import JointState

from redarm_ros.kinematics import load_arm


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--linear", type=float, nargs=3, default=[0.0, 0.05, 0.0], help="m/s")
    ap.add_argument("--angular", type=float, nargs=3, default=[0.0, 0.0, 0.0], help="rad/s")
    ap.add_argument("--frame", default="base_link", help="base_link (the controller's base_frame) or tool")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--arm", default="pa10", help="arm model, to print where the hand went")
    args = ap.parse_args(remove_ros_args(sys.argv)[1:])

    rclpy.init()
    node = rclpy.create_node("send_twist_example")
    pub = node.create_publisher(TwistStamped, "controller/target_twist", 10)  # controller's ~/target_twist
    joints: list[JointState] = []
    node.create_subscription(JointState, "joint_states", joints.append, 10)
    arm = load_arm(args.arm)

    def hand() -> np.ndarray:  # tool position (m) from the latest joint_states, by forward kinematics
        js = joints[-1]
        q = dict(zip(js.name, js.position, strict=True))
        return arm.fk([q[n] for n in arm.joint_names])[:3, 3]

    def spin_for(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.01)

    try:
        end = time.monotonic() + 30.0  # wait for the arm's joint_states and for the controller to listen
        while not (joints and pub.get_subscription_count()) and time.monotonic() < end:
            spin_for(0.1)
        if not (joints and pub.get_subscription_count()):
            print("no joint_states or no controller: is the stack running?", file=sys.stderr)
            return 1
        before = hand()
        msg = TwistStamped()
        msg.header.frame_id = args.frame
        msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z = args.linear
        msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z = args.angular
        start, count = time.monotonic(), int(args.seconds * 50)
        for k in range(count):
            msg.header.stamp = node.get_clock().now().to_msg()
            pub.publish(msg)
            spin_for(start + (k + 1) / 50.0 - time.monotonic())  # 50 Hz
        elapsed = time.monotonic() - start
        spin_for(1.0)  # the hand decelerates and the arm settles
        moved = hand() - before
        print(f"sent {count} twists in {elapsed:.2f} s; the hand moved by "
              f"({moved[0]:+.3f}, {moved[1]:+.3f}, {moved[2]:+.3f}) m")
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
