#!/usr/bin/env python3
"""Send a Reach goal to the controller (redarm_interfaces/action/Reach), print its feedback and result.

    python examples/reach_action.py                          # tool down at (0.5, -0.3, 0.25) m
    python examples/reach_action.py --xyz 0.4 0.3 0.5 --quat 0 0 0 1 --timeout 20
    python examples/reach_action.py --cancel-after 1.0       # cancel after 1 s: the arm brakes to rest

Needs the controller and a driver (redarm-bringup). Exit code 0 when the goal ends as asked
(SUCCESS, or CANCELED after --cancel-after), else 1.
"""

import argparse
import sys
import time

import rclpy
from rclpy.action import ActionClient
from rclpy.utilities import remove_ros_args
from redarm_interfaces.action import Reach


def status_name(code: int) -> str:
    return next((n for n in dir(Reach.Result) if n.isupper() and getattr(Reach.Result, n) == code), str(code))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--xyz", type=float, nargs=3, default=[0.5, -0.3, 0.25], help="tool position (m)")
    ap.add_argument("--quat", type=float, nargs=4, default=[1.0, 0.0, 0.0, 0.0],
                    help="tool orientation x y z w (default: pointing down)")
    ap.add_argument("--timeout", type=float, default=30.0, help="goal time budget (s); 0 = none")
    ap.add_argument("--cancel-after", type=float, metavar="S", help="cancel the goal after S seconds")
    args = ap.parse_args(remove_ros_args(sys.argv)[1:])

    rclpy.init()
    node = rclpy.create_node("reach_action_example")
    client = ActionClient(node, Reach, "controller/reach")  # relative: /controller/reach
    try:
        if not client.wait_for_server(timeout_sec=30.0):
            print("no action server controller/reach: is the controller running?", file=sys.stderr)
            return 1
        goal = Reach.Goal()
        goal.target.header.frame_id = "base_link"
        p, o = goal.target.pose.position, goal.target.pose.orientation
        p.x, p.y, p.z = args.xyz
        o.x, o.y, o.z, o.w = args.quat
        goal.timeout = args.timeout

        def feedback(msg) -> None:  # a Reach feedback message: .feedback holds the fields
            f = msg.feedback
            print(f"feedback: {f.phase:<10} {f.distance_to_goal * 1000:7.1f} mm to go, "
                  f"swivel {f.swivel:+.3f} rad")

        sent = client.send_goal_async(goal, feedback_callback=feedback)
        rclpy.spin_until_future_complete(node, sent, timeout_sec=30.0)
        handle = sent.result()
        if handle is None or not handle.accepted:
            print("goal rejected (the controller's state message says why)")
            return 1
        print("goal accepted")
        result = handle.get_result_async()
        started = time.monotonic()
        canceled = False
        while not result.done():
            rclpy.spin_once(node, timeout_sec=0.05)
            due = args.cancel_after is not None and time.monotonic() - started >= args.cancel_after
            if due and not canceled:
                print(f"canceling after {args.cancel_after:g} s")
                handle.cancel_goal_async()  # the result comes once the arm stands still
                canceled = True
        r = result.result().result
        print(f"result: {status_name(r.status)} {r.message} "
              f"(position error {r.position_error * 1000:.2f} mm)")
        wanted = Reach.Result.CANCELED if canceled else Reach.Result.SUCCESS
        return 0 if r.status == wanted else 1
    finally:
        client.destroy()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
