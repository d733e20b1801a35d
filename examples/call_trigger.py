#!/usr/bin/env python3
"""Call a std_srvs/Trigger service, e.g. the driver's init, halt, recover or park.

What ``ros2 service call /can_driver/init std_srvs/srv/Trigger`` does, for set-ups without the ros2 CLI.

    python examples/call_trigger.py can_driver/init      # reset + home the modules (moves the arm!)
    python examples/call_trigger.py can_driver/halt

Prints the answer; exit code 0 when it says success.
"""

import argparse
import sys

import rclpy
from rclpy.utilities import remove_ros_args
from std_srvs.srv import Trigger


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("service", help="service name, relative (can_driver/init) or absolute")
    ap.add_argument("--timeout", type=float, default=90.0, help="seconds to wait (homing takes a while)")
    args = ap.parse_args(remove_ros_args(sys.argv)[1:])
    rclpy.init()
    node = rclpy.create_node("call_trigger_example")
    client = node.create_client(Trigger, args.service)
    try:
        if not client.wait_for_service(timeout_sec=args.timeout):
            print(f"no service {client.srv_name}", file=sys.stderr)
            return 1
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, future, timeout_sec=args.timeout)
        resp = future.result() if future.done() else None
        if resp is None:
            print(f"{client.srv_name}: no answer in {args.timeout:g} s", file=sys.stderr)
            return 1
        print(f"{client.srv_name}: success={resp.success} {resp.message}")
        return 0 if resp.success else 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
