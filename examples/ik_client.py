#!/usr/bin/env python3
"""Ask ik_service for the joint angles that put the tool at a pose (redarm_interfaces/srv/SolveIK).

    python examples/ik_client.py                       # tool pointing down at (0.5, -0.3, 0.25) m
    python examples/ik_client.py --xyz 0.4 0.2 0.5 --quat 0 0 0 1 --arm pa10
    python examples/ik_client.py --ros-args -r __ns:=/left   # the stack started under /left

Needs a running ik_service (redarm-bringup, or ros2 run redarm_ros ik_service). Prints the status, the
solution (joint name = angle in rad) and its swivel angle; exit code 0 on SUCCESS, 1 otherwise.
"""

import argparse
import sys

import rclpy
from rclpy.utilities import remove_ros_args
from redarm_interfaces.srv import SolveIK


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--xyz", type=float, nargs=3, default=[0.5, -0.3, 0.25], help="tool position (m)")
    ap.add_argument("--quat", type=float, nargs=4, default=[1.0, 0.0, 0.0, 0.0],
                    help="tool orientation x y z w (default: pointing down)")
    ap.add_argument("--arm", default="", help="arm model (default: the service's default_arm)")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the service")
    args = ap.parse_args(remove_ros_args(sys.argv)[1:])

    rclpy.init()  # reads --ros-args from sys.argv (e.g. a namespace)
    node = rclpy.create_node("ik_client_example")
    # A relative name: /ik_service/solve_ik, or /left/ik_service/solve_ik under __ns:=/left.
    client = node.create_client(SolveIK, "ik_service/solve_ik")
    try:
        if not client.wait_for_service(timeout_sec=args.timeout):
            print(f"no service {client.srv_name}: is ik_service running?", file=sys.stderr)
            return 1
        req = SolveIK.Request()
        req.target.header.frame_id = "base_link"  # the service's base_frame
        p, o = req.target.pose.position, req.target.pose.orientation
        p.x, p.y, p.z = args.xyz
        o.x, o.y, o.z, o.w = args.quat
        req.arm = args.arm
        # req.seed left empty: the service starts from the arm's current joints (joint_states), so the
        # answer is the solution nearest to where the arm is; req.swivel_given=True fixes the elbow.
        # An answer can get lost while discovery is still matching this new client to the service: ask
        # again after a few seconds without one (an IK request can be repeated safely).
        resp = None
        for _ in range(max(1, int(args.timeout / 5.0))):
            future = client.call_async(req)
            rclpy.spin_until_future_complete(node, future, timeout_sec=5.0)
            if future.done():
                resp = future.result()
                break
            client.remove_pending_request(future)
        if resp is None:
            print("no answer", file=sys.stderr)
            return 1
        status = next(n for n in dir(SolveIK.Response)
                      if n.isupper() and getattr(SolveIK.Response, n) == resp.status)
        print(f"status: {status} {resp.message}")
        if resp.status != SolveIK.Response.SUCCESS:
            return 1
        for name, q in zip(resp.solution.name, resp.solution.position, strict=True):
            print(f"  {name} = {q:+.4f} rad")
        print(f"swivel: {resp.swivel:+.4f} rad, position error: {resp.position_error:.2e} m")
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
