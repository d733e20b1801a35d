"""``redarm-demo`` / ``make demo``: the whole simulated stack reaching a sequence of Cartesian goals.

Headless. It brings the stack up as separate processes (:class:`redarm_ros.bringup.Stack`: loopback
CAN bus server, pybullet simulator answering as PowerCube modules, can_driver, ik_service,
controller) in a scene with a ball where the PA10's elbow would naturally be, then, as an ordinary
ROS client:

1. moves the arm from its homed (stretched, singular) pose to a ready pose through ``/joint_command``;
2. for each goal asks ``/ik_service/solve_ik`` about it and sends it on ``/goal_pose``; the
   controller's ``~/state`` tells when it is reached (or rejected); the errors are then measured on
   the *simulated* arm's tool (pybullet link state, from the simulator's status file), not on the
   command; a PNG snapshot of the simulated arm (its measured joints, with the goal drawn) is
   rendered after each goal;
3. records the run with ``redarm-record`` into ``<output>/demo.mcap`` (joint states, commands, goals,
   controller state and markers, diagnostics, the URDF on ``/robot_description`` and ``/tf`` computed
   from the joint states), then renders ``<output>/demo.gif`` from that recording;
4. prints a table, writes ``<output>/report.json`` (per goal ``reached``, ``pos_err_m``,
   ``rot_err_rad``, ``time_s``, ...; loop-rate statistics of controller, driver and simulator; the
   recording's topic counts) and the PNGs in ``<output>/snapshots``; the children's output goes to
   ``<output>/stack.log``.

With ``--placement`` it first runs the base-placement study (:mod:`redarm_ros.placement`) for its goal
set: prints the best base pose and whether the current one is valid, writes ``<output>/placement/``.

Exit code 0 only if every reachable goal was reached within 1 mm / 0.01 rad on the simulated tool,
the out-of-reach goal was reported as such and the recording (and GIF, unless ``--gif-fps 0``) was
written; 1 otherwise; 2 if the stack could not start.
Units: m, rad, s. See docs/demo.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import yaml

from redarm_ros.bringup import Stack, StackConfig
from redarm_ros.can.driver_process import DEFAULT_SAMPLE_RATE_HZ
from redarm_ros.procs import python_module_cmd, random_domain_id, stream_sink

POS_TOL_M = 1e-3
ROT_TOL_RAD = 0.01
#: The final error of a reached goal is read once every simulated joint has moved less than this
#: (rad) over --settle seconds, waited for at most REST_WAIT_S.
REST_TOL_RAD = 1e-4
REST_WAIT_S = 20.0
# What redarm-record writes into <output>/demo.mcap (plus /tf, computed from /joint_states).
RECORDED_TOPICS = ("/joint_states", "/joint_command", "/goal_pose", "/controller/state",
                   "/controller/markers", "/diagnostics", "/robot_description", "/obstacles")
# Topics the demo waits for the recorder to subscribe to before it moves the arm.
RECORD_BEFORE_START = ("/joint_states", "/goal_pose", "/controller/state", "/robot_description")
# Where the driver's homing leaves the PA10 (all zeros) the arm is stretched straight up: no elbow
# circle, so the demo first moves to this ready pose (elbow bent) in joint space.
READY_Q = (0.0, 0.5, 0.0, 1.3, 0.0, 1.0, 0.0)
# Table top at z = 0 and a ball where the elbow would be, at the controller's preferred (high) swivel,
# for the first goal: reaching it collision-free needs the elbow turned away.
DEMO_SCENE: dict[str, Any] = {
    "name": "demo_ball",
    "description": "table top and a ball in the way of the high elbow (redarm-demo)",
    "table_height": 0.0,
    "obstacles": [{"type": "sphere", "name": "ball", "center": [0.22, -0.20, 0.70], "radius": 0.07}],
}


@dataclass(frozen=True)
class Goal:
    """A demo goal: tool position (m, base frame), tool yaw (rad) about z of a downward-pointing tool.

    ``approach``: the tool axis that points down, ``"z"`` (the 7-DOF arms' tool z) or ``"x"`` (the
    6-DOF PowerCube arm's approach axis; its tool z, the wrist pitch axis, then points along ``yaw``).
    ``pitch`` (rad, with ``approach="x"``): the approach instead points along this elevation in the
    vertical plane through the goal (the 6-DOF arm's reachable orientations), turned by ``yaw`` about
    itself. ``base_move``: an unreachable goal whose rejection must carry a base-move suggestion."""

    name: str
    position: tuple[float, float, float]
    yaw: float = 0.0
    reachable: bool = True
    note: str = ""
    approach: str = "z"
    base_move: bool = False
    pitch: float | None = None

    def matrix(self) -> np.ndarray:
        """4x4 pose: the ``approach`` axis pointing down, turned by ``yaw`` about base z."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        T = np.eye(4)
        if self.approach == "x" and self.pitch is not None:
            az = math.atan2(self.position[1], self.position[0])
            a = np.array([math.cos(self.pitch) * math.cos(az), math.cos(self.pitch) * math.sin(az),
                          math.sin(self.pitch)])
            z0 = np.array([math.sin(az), -math.cos(az), 0.0])  # the wrist pitch axis at roll 0
            z = c * z0 + s * np.cross(a, z0)
            T[:3, :3] = np.column_stack([a, np.cross(z, a), z])
        elif self.approach == "x":
            x, z = np.array([0.0, 0.0, -1.0]), np.array([c, s, 0.0])
            T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        else:  # tool z down: a rotation by pi about x, then yaw about base z
            T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.0, -1.0, -1.0])
        T[:3, 3] = self.position
        return T


GOALS = (
    Goal("elbow_clears_ball", (0.50, -0.30, 0.25), 0.0, True,
         "with the elbow high the upper arm would hit the ball: the swivel turns it away"),
    Goal("front", (0.55, 0.00, 0.30), 0.3, True, "in front, tool turned by 0.3 rad"),
    Goal("left", (0.30, 0.45, 0.35), -0.4, True, "to the left"),
    Goal("out_of_reach", (1.60, 0.00, 0.40), 0.0, False, "1.6 m away: must be rejected"),
    Goal("low_left", (0.45, 0.25, 0.15), 0.0, True, "low over the table"),
    Goal("front_right", (0.65, -0.10, 0.20), 0.5, True, "far front right"),
)


@dataclass(frozen=True)
class ArmDemo:
    """The demo of one arm: its ready pose (rad), scene and goals. ``urdf``: the arm is the URDF arm of
    that name written in :mod:`redarm_ros.sim.urdf_arms`, run as a user's own arm (``--urdf``)."""

    arm: str
    ready_q: tuple[float, ...]
    scene: dict[str, Any]
    goals: tuple[Goal, ...]
    urdf: bool = False

    def load(self) -> Any:
        """The arm's kinematic model."""
        from redarm_ros.kinematics import load_arm
        from redarm_ros.sim.urdf_arms import load_shipped

        return load_shipped(self.arm) if self.urdf else load_arm(self.arm)


# The 7-module PowerCube arm (shoulder 0.30 m up, 0.65 m from shoulder to wrist) on a table.
POWERCUBE7_SCENE: dict[str, Any] = {
    "name": "demo_table",
    "description": "table top under the 7-module PowerCube arm (redarm-demo --arm powercube7)",
    "table_height": 0.0,
    "obstacles": [],
}
POWERCUBE7_GOALS = (
    Goal("front", (0.45, 0.00, 0.20), 0.3, True, "in front, tool turned by 0.3 rad"),
    Goal("right", (0.40, -0.25, 0.15), 0.0, True, "to the right"),
    Goal("left", (0.20, 0.40, 0.25), -0.4, True, "to the left"),
    Goal("out_of_reach", (1.20, 0.00, 0.30), 0.0, False, "1.2 m away: rejected with a base-move suggestion",
         base_move=True),
    Goal("low_left", (0.35, 0.20, 0.10), 0.0, True, "low over the table"),
    Goal("front_right", (0.50, -0.10, 0.12), 0.5, True, "far front right"),
)
# The 6-DOF PowerCube arm on its mobile robot: the deck (its ground plane, 0.15 m below the first
# joint) as the table. The approach (tool x) points down; the wrist pitch axis along the yaw.
POWERCUBE6_SCENE: dict[str, Any] = {
    "name": "demo_deck",
    "description": "the mobile robot's deck under the 6-DOF PowerCube arm (redarm-demo --arm powercube6)",
    "table_height": -0.15,
    "obstacles": [],
}
POWERCUBE6_GOALS = (
    Goal("front", (0.45, 0.00, 0.05), 0.0, True, "in front, gripper down", approach="x"),
    Goal("left", (0.25, 0.40, 0.10), 0.5, True, "to the left, wrist turned by 0.5 rad", approach="x"),
    Goal("out_of_reach", (1.20, 0.00, -0.05), 0.0, False,
         "1.2 m away: rejected with the base move that makes it reachable", approach="x", base_move=True),
    Goal("right_low", (0.35, -0.35, -0.02), -0.3, True, "low to the right, near the deck", approach="x"),
    Goal("elbow_down", (0.34, -0.15, 0.50), 0.0, True,
         "high up, gripper pointing up: only the elbow-down solution is within the limits, so the arm "
         "changes its elbow in joint space", approach="x", pitch=math.radians(84.0)),
)
# The iiwa14-like arm (shoulder 0.36 m up, 0.82 m from shoulder to wrist, its elbow within +-120 deg), on
# a table, from its URDF. Its joint 4 turns about -y: the elbow bends forward at a negative angle.
IIWA14_SCENE: dict[str, Any] = {
    "name": "demo_table",
    "description": "table top under the iiwa14-like arm (redarm-demo --arm iiwa14)",
    "table_height": 0.0,
    "obstacles": [],
}
IIWA14_GOALS = (
    Goal("front", (0.55, 0.00, 0.25), 0.3, True, "in front, tool turned by 0.3 rad"),
    Goal("right", (0.45, -0.35, 0.20), 0.0, True, "to the right"),
    Goal("left", (0.30, 0.50, 0.30), -0.4, True, "to the left"),
    Goal("out_of_reach", (1.50, 0.00, 0.40), 0.0, False, "1.5 m away: must be rejected"),
    Goal("low_left", (0.50, 0.25, 0.12), 0.0, True, "low over the table"),
    Goal("front_right", (0.70, -0.15, 0.20), 0.5, True, "far front right"),
)
DEMOS = {
    "pa10": ArmDemo("pa10", READY_Q, DEMO_SCENE, GOALS),
    "iiwa14": ArmDemo("iiwa14", (0.0, 0.5, 0.0, -1.3, 0.0, 1.0, 0.0), IIWA14_SCENE, IIWA14_GOALS, urdf=True),
    "powercube7": ArmDemo("powercube7", READY_Q, POWERCUBE7_SCENE, POWERCUBE7_GOALS),
    "powercube6": ArmDemo("powercube6", (0.0, 1.0, 0.0, -1.7, -0.9, 0.0), POWERCUBE6_SCENE, POWERCUBE6_GOALS),
}

#: ``--placement``: the grid of base poses around the current base (world = the base frame at (0, 0, 0)).
PLACEMENT_GRID: dict[str, Any] = {"x": [-1.0, 1.0], "y": [-1.0, 1.0], "step": 0.1, "yaw_step_deg": 45.0}


def demo_placement_problem(demo: ArmDemo, grid: dict[str, Any] | None = None) -> Any:
    """The demo's goal set as a placement task set: the goals it expects to reach (the out-of-reach one
    is there to be rejected), in the arm's base frame as the world, base height 0, the demo's scene, and
    ``grid`` (task-file form; default :data:`PLACEMENT_GRID`)."""
    from redarm_ros.kinematics.quaternion import matrix_to_quat, to_xyzw
    from redarm_ros.placement import problem_from_dict

    tasks = []
    for g in demo.goals:
        if g.reachable:
            T = g.matrix()
            tasks.append({"name": g.name, "position": [float(v) for v in T[:3, 3]],
                          "quaternion_xyzw": [float(v) for v in to_xyzw(matrix_to_quat(T[:3, :3]))]})
    return problem_from_dict({"arm": demo.arm, "base_height": 0.0, "grid": grid or PLACEMENT_GRID,
                              "scene": demo.scene, "tasks": tasks})


def demo_placement(demo: ArmDemo, out_dir: Path, say: Callable[[str], None],
                   grid: dict[str, Any] | None = None, plots: bool = True, workers: int | None = None) -> Any:
    """Run the placement study for the demo's goals (:func:`demo_placement_problem`) on ``workers`` local
    processes (None: all cores; 1: this process; the results are the same), write ``redarm-placement``'s
    outputs (placements.npz, ranking.csv, heat maps) into ``out_dir``, say the best placement and whether
    the current base pose (0, 0, 0) is valid; return the PlacementResult."""
    from redarm_ros.placement import place
    from redarm_ros.placement.cli import write_outputs

    res = place(demo_placement_problem(demo, grid), workers=workers)
    write_outputs(res, out_dir, plots=plots)
    summary = res.summary(top=1)
    here = res.index_of(0.0, 0.0, 0.0)
    here_text = "not on the grid" if here is None else ("valid" if res.valid[here] else "NOT valid")
    if summary["best"]:
        b = summary["best"][0]
        best_text = f"best x {b['x']:+.2f} m, y {b['y']:+.2f} m, yaw {b['yaw_deg']:.0f} deg"
    else:
        best_text = "no valid placement"
    say(f"placement for the {len(res.problem.tasks)} reachable goals: {summary['valid']} of "
        f"{summary['base_poses']} base poses valid; {best_text}; the current base (0, 0, 0) is {here_text} "
        f"(heat maps in {out_dir})")
    return res


@dataclass
class GoalResult:
    """What happened to one goal (errors measured on the simulated tool)."""

    name: str
    position: list[float]
    quaternion_xyzw: list[float]
    reachable_expected: bool
    ik_status: str
    ik_message: str
    reached: bool
    rejected: bool
    controller_message: str
    pos_err_m: float
    rot_err_rad: float
    time_s: float
    min_clearance_m: float
    snapshot: str | None = None
    ok: bool = False
    note: str = ""
    driver_halts: int = 0
    diagnostics: dict[str, Any] = field(default_factory=dict)


@dataclass
class RateStats:
    """Achieved rate of a periodic stream from its arrival times."""

    target_hz: float
    achieved_hz: float = math.nan
    period_median_ms: float = math.nan
    period_p99_ms: float = math.nan
    samples: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_times(cls, times: list[float], target_hz: float) -> RateStats:
        """Statistics of arrival times ``times`` (s, monotonic)."""
        st = cls(target_hz=target_hz, samples=len(times))
        if len(times) > 2:
            d = np.diff(np.asarray(times))
            st.achieved_hz = float((len(times) - 1) / (times[-1] - times[0]))
            st.period_median_ms = float(np.median(d) * 1e3)
            st.period_p99_ms = float(np.percentile(d, 99) * 1e3)
        return st


def _rot_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (float(np.trace(Ra.T @ Rb)) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, c)))


class DemoClient:
    """The ROS side of the demo (an ordinary client of the stack); rclpy is imported here only."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from redarm_interfaces.msg import ControllerState
        from redarm_interfaces.srv import SolveIK
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("redarm_demo", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.SolveIK = SolveIK
        self.ControllerState = ControllerState
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 10)
        self.cmd_pub = self.node.create_publisher(JointTrajectory, "joint_command", 10)
        self.ik = self.node.create_client(SolveIK, "ik_service/solve_ik")
        from std_srvs.srv import Trigger

        self.recover_cli = self.node.create_client(Trigger, "can_driver/recover")
        self.Trigger = Trigger
        self.states: list[tuple[float, Any]] = []
        self.joint_times: list[float] = []
        self.node.create_subscription(ControllerState, "controller/state",
                                      lambda m: self.states.append((time.monotonic(), m)), 100)
        self.node.create_subscription(JointState, "joint_states",
                                      lambda m: self.joint_times.append(time.monotonic()), 100)

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        from redarm_ros.nodes._common import spin_until

        return spin_until(self.ex, cond, timeout)

    def pose_msg(self, T: np.ndarray) -> Any:
        from redarm_ros.nodes.controller import pose_to_msg

        msg = pose_to_msg(T)
        msg.header.frame_id = "base_link"
        return msg

    def solve_ik(self, T: np.ndarray, seed: list[float], arm: str = "") -> Any:
        req = self.SolveIK.Request()
        req.target = self.pose_msg(T)
        req.arm = arm
        req.seed = [float(v) for v in seed]
        from redarm_ros.nodes._common import call_resending

        return call_resending(self.ik, req, self.spin_until, 10.0)

    def recover(self) -> tuple[bool, str]:
        """Call the driver's ``~/recover`` (reset the modules, resume from the measured pose)."""
        if not self.spin_until(self.recover_cli.service_is_ready, 5.0):
            return False, "~/recover not available"
        from redarm_ros.nodes._common import call_resending

        r = call_resending(self.recover_cli, self.Trigger.Request(), self.spin_until, 30.0)
        if r is None:
            return False, "~/recover did not answer"
        return bool(r.success), r.message

    def move_joints(self, names: list[str], q: tuple[float, ...], duration_s: float) -> None:
        from redarm_ros.nodes._common import joint_trajectory

        self.cmd_pub.publish(joint_trajectory(names, q, duration_s))

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.ctx)


class Demo:
    """One demo run: the stack, the client, the goal sequence and the report."""

    def __init__(self, args: argparse.Namespace, out: IO[str]) -> None:
        self.args = args
        self.out = out
        self.output = Path(args.output).resolve()
        self.snap_dir = self.output / "snapshots"
        self.t_start = time.monotonic()
        self.halts = 0  # driver halts recovered from (reported; a healthy run has none)
        self.mcap_path = self.output / "demo.mcap"
        self.gif_path = self.output / "demo.gif"
        self.size = _size(args.snapshot_size)
        self._renderer: Any = None
        self._outcome: tuple[list[GoalResult], dict[str, Any]] | None = None
        self.demo = DEMOS[args.arm]

    def say(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()

    def sim_tool(self, stack: Stack) -> tuple[np.ndarray, np.ndarray] | None:
        from redarm_ros.kinematics.quaternion import from_xyzw, quat_to_matrix

        st = stack.sim_status()
        if not st or "tool" not in st:
            return None
        tool = st["tool"]
        return np.asarray(tool["position"], float), quat_to_matrix(from_xyzw(tool["quaternion_xyzw"]))

    def tool_error(self, stack: Stack, T: np.ndarray) -> tuple[float, float]:
        tool = self.sim_tool(stack)
        if tool is None:
            return math.inf, math.inf
        p, R = tool
        return float(np.linalg.norm(p - T[:3, 3])), _rot_angle(R, T[:3, :3])

    def run(self) -> int:
        self.output.mkdir(parents=True, exist_ok=True)
        self.snap_dir.mkdir(parents=True, exist_ok=True)
        for old in [*self.snap_dir.glob("*.png"), self.mcap_path, self.gif_path]:
            old.unlink(missing_ok=True)
        if self.args.placement:
            if self.demo.urdf:
                self.say("--placement: the placement study takes the bundled arms only")
                return 2
            demo_placement(self.demo, self.output / "placement", self.say)
        scene_path = self.output / "scene.yaml"
        scene_path.write_text(yaml.safe_dump(self.demo.scene, sort_keys=False), encoding="utf-8")
        log_path = self.output / "stack.log"
        domain = int(os.environ["ROS_DOMAIN_ID"])
        # The simulator renders only start.png (before the driver connects) and final.png (after it is
        # gone): rendering holds its process for tens of ms, longer than the driver's reply limit. The
        # pictures in between are rendered here, from the simulated arm's measured joints.
        urdf: dict[str, Any] = {}
        record_arm = ["--arm", self.demo.arm]
        if self.demo.urdf:  # the arm's URDF file, given to the stack as a user's own arm is
            from redarm_ros.sim.urdf_arms import SHIPPED

            text, base_link, tip_link = SHIPPED[self.demo.arm]
            urdf_path = self.output / f"{self.demo.arm}.urdf"
            urdf_path.write_text(text(), encoding="utf-8")
            urdf = {"urdf": str(urdf_path), "base_link": base_link, "tip_link": tip_link}
            record_arm = []  # /tf from the URDF the description node publishes
        arm_args = urdf or {"arm": self.demo.arm}
        cfg = StackConfig(**arm_args, scene=str(scene_path), snapshot_dir=self.snap_dir,
                          status_file=self.output / "sim_status.json", log_level=self.args.log_level,
                          control_rate_hz=self.args.control_rate, driver_rate_hz=self.args.driver_rate,
                          ready_timeout_s=60.0,
                          extra_args={"sim": ["--snapshot-size", self.args.snapshot_size]})
        with open(log_path, "w", encoding="utf-8") as log:
            lock_write = stream_sink(log)
            stack = Stack(cfg, sink=lock_write, domain_id=domain)
            self.say(f"redarm demo: starting the stack (ROS_DOMAIN_ID={domain}, logs in {log_path})")
            try:
                stack.start()
                stack.children["can_driver"].wait_for_line(r"init done", timeout=30.0, from_start=True)
                # The recorder, a child like the others: stopped first, so its file is complete.
                stack.children["record"] = stack.group.start("record", python_module_cmd(
                    "redarm_ros.nodes.record", "-o", str(self.mcap_path), *RECORDED_TOPICS,
                    "--tf-from-joint-states", *record_arm), ready=r"record ready",
                    ready_timeout=30.0)
            except Exception as exc:  # noqa: BLE001 - report, show the log tail, exit 2
                self.say(f"the stack did not come up: {exc}")
                stack.close()
                self._tail(log_path)
                return 2
            try:
                code = self._run_goals(stack, log_path)
            finally:
                stack.close()  # stops the recorder first (reverse start order): the MCAP is complete
            if self._renderer is not None:
                self._renderer.close()
            if self._outcome is None:
                return code
            return self._finish(*self._outcome)

    def _tail(self, log_path: Path, n: int = 30) -> None:
        try:
            lines = log_path.read_text(encoding="utf-8").splitlines()[-n:]
        except OSError:
            return
        self.say("--- last lines of the stack log ---")
        for line in lines:
            self.say(line)

    def _run_goals(self, stack: Stack, log_path: Path) -> int:
        arm = self.demo.load()
        ready_q = self.demo.ready_q
        client = DemoClient(stack.domain_id)
        CS = client.ControllerState
        results: list[GoalResult] = []
        try:
            if not client.spin_until(lambda: len(client.joint_times) > 5 and bool(client.states)
                                     and client.ik.service_is_ready(), 30.0):
                self.say("no joint_states / controller state / ik_service from the stack")
                self._tail(log_path)
                return 2
            recorder = stack.children["record"]
            for topic in RECORD_BEFORE_START:
                try:
                    recorder.wait_for_line(rf"recording {re.escape(topic)} ", 15.0, from_start=True)
                except Exception:  # noqa: BLE001 - a missing topic is reported, the run goes on
                    self.say(f"warning: the recorder has not subscribed to {topic}")
            self.say("stack up; moving to the ready pose through /joint_command")
            driver = stack.children["can_driver"]

            def recover_if_halted(where: str) -> int:
                # The driver halts every module when one answers too late (e.g. the simulator or the
                # driver starved of CPU); it stays halted until ~/recover. Do what an operator would:
                # recover, then carry on. Every halt is counted and reported.
                new = _count(driver.output(), "HALTED:") - self.halts
                if new <= 0:
                    return 0
                self.halts += new
                ok, why = client.recover()
                self.say(f"  the driver halted the arm ({where}); ~/recover: {why}")
                client.spin_until(lambda: False, 0.8)  # the controller restarts from the still arm
                return new

            def at_ready() -> bool:
                st = stack.sim_status() or {}
                return bool(st) and float(np.max(np.abs(np.asarray(st["q"]) - ready_q))) < 1e-3

            for attempt in (1, 2):
                recover_if_halted("before the ready pose")
                client.move_joints(list(arm.joint_names), ready_q, 3.0)
                if client.spin_until(at_ready, 20.0):
                    break
                if attempt == 1 and _count(driver.output(), "HALTED:") > self.halts:
                    continue
                self.say("the simulated arm did not reach the ready pose")
                self._tail(log_path)
                return 1
            client.spin_until(lambda: False, 0.6)  # the controller restarts from the still arm
            self.snapshot(stack, arm, "ready")
            seed = list(ready_q)
            for i, goal in enumerate(self.demo.goals, start=1):
                stack.check()
                halts = recover_if_halted(f"before goal {i}")
                res = self._one_goal(stack, client, CS, arm, goal, seed, i)
                if not res.ok and _count(driver.output(), "HALTED:") > self.halts:
                    halts += recover_if_halted(f"during goal {i}")
                    res = self._one_goal(stack, client, CS, arm, goal, seed, i, retry=True)
                    res.note = (res.note + "; " if res.note else "") + "retried after a driver halt"
                res.driver_halts = halts
                results.append(res)
                st = stack.sim_status()
                if st:
                    seed = list(st["q"])
                ok = "ok" if res.ok else "FAILED"
                self.say(f"  goal {i} {goal.name}: {ok} ({res.time_s:.2f} s)")
            rates = self._rates(stack, client)
        finally:
            client.close()
        self._outcome = (results, rates)
        return 0 if all(r.ok for r in results) else 1

    def snapshot(self, stack: Stack, arm: Any, name: str, goal: Goal | None = None,
                 goal_ok: bool = True) -> Path | None:
        """Render ``<snapshots>/<name>.png``: the simulated arm at its measured joints (simulator status),
        in the demo scene, with ``goal`` drawn. None if the simulator reported no joints yet."""
        from redarm_ros.kinematics.quaternion import matrix_to_quat
        from redarm_ros.record.animate import SceneRenderer, write_png

        st = stack.sim_status() or {}
        if "q" not in st:
            return None
        if self._renderer is None:
            self._renderer = SceneRenderer(arm, self.demo.scene, self.size)
        g = None
        if goal is not None:
            w, x, y, z = matrix_to_quat(goal.matrix()[:3, :3])
            g = (np.asarray(goal.position, float), np.array([x, y, z, w]))
        path = self.snap_dir / f"{name}.png"
        write_png(path, self._renderer.render(st["q"], g, goal_ok=goal_ok))
        return path

    def _one_goal(self, stack: Stack, client: DemoClient, CS: Any, arm: Any, goal: Goal, seed: list[float],
                  index: int, retry: bool = False) -> GoalResult:
        from redarm_ros.kinematics.quaternion import matrix_to_quat

        T = goal.matrix()
        w, x, y, z = (float(v) for v in matrix_to_quat(T[:3, :3]))
        ik = client.solve_ik(T, seed, "" if self.demo.urdf else self.demo.arm)  # "": the URDF arm
        ik_status = "NO_ANSWER" if ik is None else _status_name(client.SolveIK, ik.status)
        n = len(client.states)
        prev = client.states[-1][1] if client.states else None
        t0 = time.monotonic()
        client.goal_pub.publish(client.pose_msg(T))

        def outcome() -> tuple[float, Any] | None:
            # State messages already in flight still describe the previous goal: a REACHED counts only
            # with this goal in it, a REJECTED only if it is not the previous rejection repeated.
            for t, m in client.states[n:]:
                if m.phase == CS.REACHED and _same_position(m.goal.position, goal.position):
                    return t, m
                # (A retried unreachable goal's rejection repeats the first attempt's word for word.)
                again = retry and not goal.reachable
                if m.phase == CS.REJECTED and (again or not (prev is not None and prev.phase == CS.REJECTED
                                                             and prev.message == m.message)):
                    return t, m
            return None

        timeout = self.args.goal_timeout
        done = client.spin_until(lambda: outcome() is not None, timeout)
        hit = outcome()
        rejected = hit is not None and hit[1].phase == CS.REJECTED
        message = hit[1].message if hit is not None else ("timeout" if not done else "")
        t_end = hit[0] if hit is not None else time.monotonic()
        if hit is not None and not rejected:
            # Reached on the command: wait for the simulated tool to get within tolerance.
            def settled() -> bool:
                pe, re = self.tool_error(stack, T)
                return pe < POS_TOL_M and re < ROT_TOL_RAD

            if client.spin_until(settled, 10.0):
                t_end = time.monotonic()
                # The final error is read once the arm is at rest (every joint within REST_TOL_RAD
                # for `settle` s): after "reached" the elbow may still finish its self-motion towards
                # the preferred swivel for several seconds (more on a busy machine), and the joints'
                # tracking lag moves the tool transiently (up to ~1 mm) while it does.
                client.spin_until(stack.sim_still(self.args.settle, REST_TOL_RAD), REST_WAIT_S)
        else:
            client.spin_until(lambda: False, 0.5)  # let a rejected goal's stop settle for the snapshot
        pe, re = self.tool_error(stack, T)
        last = client.states[-1][1] if client.states else None
        st = stack.sim_status() or {}
        # Where a miss comes from: the command (controller) or the tracking (driver + simulated arm).
        diag = {
            "controller_phase": last.phase if last is not None else "",
            "controller_distance_m": float(last.distance_to_goal) if last is not None else math.nan,
            "controller_message_last": last.message if last is not None else "",
            "sim_setpoint_gap_rad": float(np.max(np.abs(np.subtract(st["q"], st["q_setpoint"]))))
            if "q_setpoint" in st else math.nan,
        }
        clear = [m.clearance for _, m in client.states[n:] if math.isfinite(m.clearance)]
        reached = hit is not None and not rejected and pe < POS_TOL_M and re < ROT_TOL_RAD
        if goal.reachable:
            ok = reached
        else:
            ok = rejected and "reach" in message and ik_status == "OUT_OF_REACH"
            if goal.base_move:  # the rejection says where the base should go
                ok = ok and "move the base by" in message
        snap = self.snapshot(stack, arm, f"goal_{index}_{goal.name}", goal, goal_ok=not rejected)
        return GoalResult(
            name=goal.name, position=[float(v) for v in goal.position], quaternion_xyzw=[x, y, z, w],
            reachable_expected=goal.reachable, ik_status=ik_status,
            ik_message="" if ik is None else ik.message, reached=reached, rejected=rejected,
            controller_message=message, pos_err_m=pe, rot_err_rad=re, time_s=t_end - t0,
            min_clearance_m=min(clear) if clear else math.inf,
            snapshot=None if snap is None else str(snap.relative_to(self.output)), ok=ok, note=goal.note,
            diagnostics=diag,
        )

    def _rates(self, stack: Stack, client: DemoClient) -> dict[str, Any]:
        ctl_times = [t for t, _ in client.states]
        st = stack.sim_status() or {}
        counters = st.get("counters", {})
        sim = RateStats(target_hz=float(st.get("rate_hz", math.nan)))
        if st.get("uptime_s"):
            sim.achieved_hz = float(st.get("steps", 0)) / float(st["uptime_s"])
        sim.samples = int(st.get("steps", 0))
        keys = ("overruns", "resyncs", "max_lag_ms", "reply_latency_mean_ms", "reply_latency_max_ms",
                "frames_rx", "malformed")
        sim.extra = {k: counters.get(k) for k in keys}
        return {
            "controller_state": asdict(RateStats.from_times(ctl_times, self.args.control_rate)),
            "driver_joint_states": asdict(RateStats.from_times(
                client.joint_times, min(self.args.driver_rate, DEFAULT_SAMPLE_RATE_HZ))),
            "simulator_physics": asdict(sim),
        }

    def _finish(self, results: list[GoalResult], rates: dict[str, Any]) -> int:
        """After the stack stopped: read the recording back, render the GIF, write the report."""
        recording = self._recording_summary()
        animation = self._animation() if self.args.gif_fps > 0 else {"gif": None}
        ok = all(r.ok for r in results) and recording["ok"] and (self.args.gif_fps <= 0 or animation["ok"])
        self._report(results, rates, ok, recording, animation)
        return 0 if ok else 1

    def _recording_summary(self) -> dict[str, Any]:
        from redarm_ros.record.mcap_io import summarize

        try:
            profile, topics = summarize(self.mcap_path)
        except Exception as exc:  # noqa: BLE001 - a broken recording is reported, not raised
            return {"file": self.mcap_path.name, "ok": False, "error": repr(exc)}
        counts = {t: s.count for t, s in sorted(topics.items()) if t != "*"}
        # What the demo promises: the joint states of the whole run, the URDF and /tf for 3-D viewers.
        ok = counts.get("/joint_states", 0) >= 1000 and counts.get("/tf", 0) > 0 \
            and counts.get("/robot_description", 0) > 0 and topics["*"].monotonic
        return {"file": self.mcap_path.name, "profile": profile, "messages": counts,
                "log_time_monotonic": topics["*"].monotonic,
                "schemas": {t: s.schema_name for t, s in sorted(topics.items()) if t != "*"}, "ok": ok}

    def _animation(self) -> dict[str, Any]:
        from redarm_ros.record.animate import (
            DEMO_CAMERA,
            SceneRenderer,
            frames,
            goal_caption,
            load_timeline,
            write_gif,
        )

        arm = self.demo.load()
        goals = self.demo.goals
        t0 = time.monotonic()
        try:
            tl = load_timeline(self.mcap_path, arm.joint_names)
            r = SceneRenderer(arm, self.demo.scene, self.size, camera=DEMO_CAMERA)
            try:
                cap = goal_caption([g.name for g in goals], [g.position for g in goals])
                n = write_gif(self.gif_path, frames(tl, r, fps=self.args.gif_fps, caption=cap),
                              fps=self.args.gif_fps, palette_extra=[r.swatch()])
            finally:
                r.close()
        except Exception as exc:  # noqa: BLE001 - reported in the table and the report
            return {"gif": self.gif_path.name, "ok": False, "error": repr(exc)}
        return {"gif": self.gif_path.name, "ok": True, "frames": n, "fps": self.args.gif_fps,
                "size": list(self.size), "bytes": self.gif_path.stat().st_size,
                "render_s": round(time.monotonic() - t0, 1)}

    def _report(self, results: list[GoalResult], rates: dict[str, Any], success: bool,
                recording: dict[str, Any], animation: dict[str, Any]) -> None:
        snaps = sorted(str(p.relative_to(self.output)) for p in self.snap_dir.glob("*.png"))
        report = {
            "arm": self.demo.arm,
            "scene": self.demo.scene,
            "tolerance": {"pos_m": POS_TOL_M, "rot_rad": ROT_TOL_RAD},
            "measured_on": "simulated tool: pybullet link state from the simulator's status file",
            "goals": [asdict(r) for r in results],
            "loop_rates": rates,
            "snapshots": snaps,
            "recording": recording,
            "animation": animation,
            "success": success,
            "driver_halts_recovered": self.halts,
            "wall_time_s": time.monotonic() - self.t_start,
        }
        path = self.output / "report.json"
        path.write_text(json.dumps(report, indent=2, default=_json_default), encoding="utf-8")
        self.say("")
        self.say(f"{'#':>2} {'goal':<18} {'expected':<9} {'IK':<13} {'result':<9} {'pos err mm':>10} "
                 f"{'rot err rad':>11} {'time s':>7} {'min clear m':>11}")
        for i, r in enumerate(results, start=1):
            result = "reached" if r.reached else ("rejected" if r.rejected else "missed")
            expected = "reach" if r.reachable_expected else "reject"
            self.say(f"{i:>2} {r.name:<18} {expected:<9} {r.ik_status:<13} {result:<9} "
                     f"{r.pos_err_m * 1e3:>10.3f} {r.rot_err_rad:>11.5f} {r.time_s:>7.2f} "
                     f"{r.min_clearance_m:>11.3f}  {'ok' if r.ok else 'FAILED'}")
            if r.driver_halts:
                self.say(f"   ({r.note})")
            if r.rejected:  # the controller's reason (and, out of reach, where the base should go)
                self.say(f"   controller: {r.controller_message}")
        c = rates["controller_state"]
        d = rates["driver_joint_states"]
        s = rates["simulator_physics"]
        self.say("")
        self.say(f"controller {c['achieved_hz']:.1f} Hz (target {c['target_hz']:g}, period median "
                 f"{c['period_median_ms']:.2f} ms, p99 {c['period_p99_ms']:.2f} ms); driver joint_states "
                 f"{d['achieved_hz']:.1f} Hz (target {d['target_hz']:g}, p99 period "
                 f"{d['period_p99_ms']:.2f} ms); simulator {s['achieved_hz']:.0f} Hz physics "
                 f"(target {s['target_hz']:g})")
        if self.halts:
            self.say(f"note: the driver halted the arm {self.halts} time(s) (late module replies, e.g. CPU "
                     "starvation); the demo recovered with ~/recover and retried")
        msgs = recording.get("messages", {})
        self.say(f"recording: {self.mcap_path} ({sum(msgs.values())} messages; " + ", ".join(
            f"{t} {msgs.get(t, 0)}" for t in ("/joint_states", "/tf", "/robot_description", "/goal_pose"))
            + (")" if recording["ok"] else f") INCOMPLETE {recording.get('error', '')}"))
        if animation.get("gif"):
            self.say(f"animation: {self.gif_path} ({animation.get('frames', 0)} frames at "
                     f"{self.args.gif_fps:g} fps, {self.size[0]}x{self.size[1]})"
                     if animation["ok"] else f"animation FAILED: {animation.get('error')}")
        self.say(f"report: {path}; snapshots: {len(snaps)} PNGs in {self.snap_dir}")
        self.say("demo " + ("PASSED" if success else "FAILED"))


def _same_position(p: Any, q: tuple[float, float, float], tol: float = 1e-6) -> bool:
    return abs(p.x - q[0]) < tol and abs(p.y - q[1]) < tol and abs(p.z - q[2]) < tol


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError as exc:
        raise SystemExit(f"--snapshot-size must be WIDTHxHEIGHT, got {text!r}") from exc
    return w, h


def _count(lines: list[str], needle: str) -> int:
    return sum(needle in line for line in lines)


def _status_name(SolveIK: Any, code: int) -> str:
    for name in ("SUCCESS", "NO_SOLUTION_IN_LIMITS", "OUT_OF_REACH", "INVALID_INPUT", "TIMEOUT"):
        if getattr(SolveIK.Response, name) == code:
            return name
    return f"CODE_{code}"


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def build_parser() -> argparse.ArgumentParser:
    """The ``redarm-demo`` argument parser."""
    ap = argparse.ArgumentParser(prog="redarm-demo", description=__doc__.splitlines()[0])
    ap.add_argument("--arm", default="pa10", choices=sorted(DEMOS),
                    help="arm and its goal set (default pa10; see docs/demo.md)")
    ap.add_argument("--output", default="demo_output", help="output directory (default ./demo_output)")
    ap.add_argument("--goal-timeout", type=float, default=40.0, help="seconds allowed per goal")
    ap.add_argument("--control-rate", type=float, default=100.0, help="controller rate (Hz)")
    ap.add_argument("--driver-rate", type=float, default=250.0, help="can_driver cycle rate (Hz)")
    ap.add_argument("--settle", type=float, default=0.5,
                    help="seconds the simulated joints must stay still (within 0.1 mrad) before the "
                    "final error is read (waited for at most 20 s)")
    ap.add_argument("--snapshot-size", default="640x480",
                    help="size of the PNG snapshots and the GIF, WIDTHxHEIGHT (default 640x480)")
    ap.add_argument("--gif-fps", type=float, default=10.0,
                    help="frame rate of <output>/demo.gif (recording time; 0 = no GIF)")
    ap.add_argument("--placement", action="store_true",
                    help="first compute where the base could stand for the demo's goals (+-1 m, yaw every "
                    "45 deg): prints the best placement, writes heat maps to <output>/placement")
    ap.add_argument("--log-level", default="info", choices=("debug", "info", "warn", "error"),
                    help="log level of the ROS nodes (their output goes to <output>/stack.log)")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Console entry point (``redarm-demo``, ``python -m redarm_ros.demo``)."""
    args = build_parser().parse_args(argv)
    # The network rule: this process runs rclpy too; keep DDS on shared memory, in a domain of its own.
    os.environ["FASTDDS_BUILTIN_TRANSPORTS"] = "SHM"
    if not os.environ.get("ROS_DOMAIN_ID", "").strip().isdigit():
        os.environ["ROS_DOMAIN_ID"] = str(random_domain_id())
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        return Demo(args, sys.stdout).run()
    except KeyboardInterrupt:
        sys.stdout.write("interrupted; the stack was stopped\n")
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
