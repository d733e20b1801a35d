"""The workstation's client in test_two_hosts.py (run as a script inside the workstation namespace).

It talks to the stack only through ROS topics and services, as a user's program on the workstation
would: waits for /joint_states from the robot, asks /ik_service/solve_ik (on the workstation) for the
goal, moves the arm to a ready pose with one /joint_command trajectory, then publishes the goal on
/goal_pose and waits until the *measured* joints (the robot's /joint_states) put the tool on the goal.
On a starved machine the modules' 100 ms watchdog can halt the arm; the client then does what the
docs tell a user to do: /can_driver/init if the driver's own init failed (``--init``),
/can_driver/recover if the arm stopped short (at most twice per step, each reported). Progress lines
start with ``CLIENT``; the last is ``CLIENT REACHED {json}`` (exit 0) or ``CLIENT FAILED reason``.

    python two_hosts_client.py --goal Q1 ... Q7 --ready Q1 ... Q7 [--init] [--timeout S]
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import time
from collections.abc import Callable

import numpy as np
import rclpy
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from redarm_interfaces.srv import SolveIK
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import matrix_to_quat

POS_TOL, ROT_TOL = 1e-3, 0.01  # m, rad


def pose_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Position (m) and rotation angle (rad) between two 4x4 poses."""
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(math.acos(max(-1.0, min(1.0, c))))


def pose_msg(T: np.ndarray, frame: str = "base_link") -> PoseStamped:
    w, x, y, z = matrix_to_quat(T[:3, :3])  # kinematics core order (w, x, y, z)
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in T[:3, 3])
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = float(x), float(y), float(z), float(w)
    return msg


class Client:
    def __init__(self) -> None:
        self.node = rclpy.create_node("two_hosts_client")
        self.ex = SingleThreadedExecutor()
        self.ex.add_node(self.node)
        self.q: np.ndarray | None = None
        self.joint_states = 0
        self.node.create_subscription(JointState, "joint_states", self._on_js, 20)
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 10)
        self.cmd_pub = self.node.create_publisher(JointTrajectory, "joint_command", 10)
        self.ik = self.node.create_client(SolveIK, "/ik_service/solve_ik")
        self.recover = self.node.create_client(Trigger, "/can_driver/recover")
        self.init = self.node.create_client(Trigger, "/can_driver/init")

    def _on_js(self, msg: JointState) -> None:
        self.q = np.array(msg.position)
        self.joint_states += 1

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        from redarm_ros.nodes._common import spin_until

        return spin_until(self.ex, cond, timeout)

    def call(self, client: object, request: object, timeout: float) -> object | None:
        from redarm_ros.nodes._common import call_resending  # (sent again: a first answer may be lost)

        return call_resending(client, request, self.spin_until, timeout)


def say(*parts: object) -> None:
    print("CLIENT", *parts, flush=True)


def run(ns: argparse.Namespace) -> int:
    arm = load_arm(ns.arm)
    ready, goal_q = np.array(ns.ready), np.array(ns.goal)
    T_goal = arm.fk(goal_q)
    c = Client()
    t0 = time.monotonic()
    if not c.spin_until(lambda: c.joint_states >= 5, ns.timeout):
        say("FAILED no /joint_states from the robot")
        return 1
    say(f"joint_states arriving on {socket.gethostname()} ({c.joint_states} so far)")
    recoveries: list[str] = []

    def trigger(client: object, what: str) -> bool:
        if not c.spin_until(client.service_is_ready, 10.0):  # type: ignore[attr-defined]
            return False
        r = c.call(client, Trigger.Request(), 60.0)
        recoveries.append(f"{what}: {None if r is None else r.message}")
        say(recoveries[-1])
        return r is not None and r.success

    if ns.init:
        if not any(trigger(c.init, "driver init failed at start-up; ~/init") for _ in range(3)):
            say("FAILED ~/init did not succeed")
            return 1

    if not c.spin_until(c.ik.service_is_ready, 20.0):
        say("FAILED /ik_service/solve_ik not available")
        return 1
    req = SolveIK.Request(target=pose_msg(T_goal), seed=[float(v) for v in ready])
    resp = c.call(c.ik, req, 20.0)
    if resp is None or resp.status != SolveIK.Response.SUCCESS:
        say("FAILED ik_service:", None if resp is None else resp.message)
        return 1
    say(f"ik_service solved the goal: {list(np.round(resp.solution.position, 4))}")

    traj = JointTrajectory(joint_names=list(arm.joint_names))
    traj.points = [JointTrajectoryPoint(positions=[float(v) for v in ready], time_from_start=Duration(sec=3))]
    for attempt in range(3):
        c.cmd_pub.publish(traj)
        if c.spin_until(lambda: float(np.max(np.abs(c.q - ready))) < 2e-3, 15.0):
            break
        if attempt == 2 or not trigger(c.recover, "arm stopped before the ready pose; ~/recover"):
            say(f"FAILED arm not at the ready pose: {c.q}")
            return 1
    say("at the ready pose")
    c.spin_until(lambda: False, 0.6)  # the controller sees a still arm away from its plan: resync

    def on_goal() -> bool:
        pe, re = pose_error(arm.fk(c.q), T_goal)
        return pe < POS_TOL and re < ROT_TOL

    t_goal = time.monotonic()
    for attempt in range(3):
        # After a recover the controller restarts from the measured joints and re-plans to its goal;
        # publishing the goal again costs nothing.
        c.goal_pub.publish(pose_msg(T_goal))
        if c.spin_until(on_goal, ns.timeout):
            break
        pe, re = pose_error(arm.fk(c.q), T_goal)
        if attempt == 2 or not trigger(c.recover, f"arm stopped {pe * 1e3:.1f} mm from the goal; ~/recover"):
            say(f"FAILED measured tool {pe * 1e3:.3f} mm / {re:.4f} rad from the goal")
            return 1
    c.spin_until(lambda: False, 0.3)
    pe, re = pose_error(arm.fk(c.q), T_goal)
    say("REACHED", json.dumps({"pos_err_m": pe, "rot_err_rad": re, "joint_states": c.joint_states,
                               "reach_s": round(time.monotonic() - t_goal, 2),
                               "total_s": round(time.monotonic() - t0, 2), "recoveries": recoveries}))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arm", default="pa10")
    ap.add_argument("--ready", type=float, nargs="+", required=True)
    ap.add_argument("--goal", type=float, nargs="+", required=True)
    ap.add_argument("--init", action="store_true", help="call /can_driver/init first")
    ap.add_argument("--timeout", type=float, default=20.0, help="per attempt (s)")
    ns = ap.parse_args(argv)
    rclpy.init()
    try:
        return run(ns)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
