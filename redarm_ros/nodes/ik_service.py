"""IK service node: ``~/solve_ik`` (redarm_interfaces/srv/SolveIK) for one or more arm models.

Wiring only: the request handling lives in :class:`redarm_ros.kinematics.solve.IKFrontEnd` (the pose,
arm, swivel / seed and time budget in; one answer with a status out). This module turns the message
into a pose matrix, calls the front end and fills the response. Every request gets an answer with a
status code; a bad request never reaches the solver and never takes the node down.

Solutions whose links collide with each other or go below the arm's ground plane are filtered out
unless a request sets ``ignore_collisions``; a pose that cannot be solved at all carries a base-move
suggestion (``base_offset``, ``base_offset_yaw``, ``base_offset_valid``) when ``suggest_base_move`` is on.

A request with an empty ``seed`` is seeded with the latest ``joint_states`` (relative: the topic of the
stack in this node's namespace) when that message names every joint of the requested arm, else with
mid-range; the per-request debug line says which (``--log-level ik_service:=debug``).

With ``placement_tasks`` (a ``redarm-placement`` task file) the node also ranks the base poses for that
task set once at start-up (:mod:`redarm_ros.placement`, one process, in a thread of its own), logs the
best ones and publishes a YAML summary (``best``: x, y, yaw_deg, robustness; ``valid``: how many) on the
latched ``~/placement`` (std_msgs/String).

Requests wait in the service's middleware queue (reliable, KEEP_LAST with depth
``request_queue_depth``, default 4096, for requests and responses alike), so a burst of that many
outstanding calls is answered in order. Callers that keep many calls outstanding need a deep queue
on their side too (their client's QoS depth), or their own responses are dropped there.

Run: ``ros2 run redarm_ros ik_service --ros-args -p arms:="[pa10, powercube7]"``; an arm of your own
from its URDF: ``-p urdf:=robot.urdf -p base_link:=base_link -p tip_link:=tool0`` (or
``-p robot_description_topic:=/robot_description``): the response's ``solver`` names the IK that ran
(or ``python -m redarm_ros.nodes.ik_service``). Parameters, service and examples: docs/nodes.md.

Conventions: SI units (m, rad, s); quaternions in messages are (x, y, z, w) as in geometry_msgs and
converted to the kinematics core's (w, x, y, z) in :func:`pose_msg_to_matrix`.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Sequence
from typing import Any

import yaml
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from redarm_interfaces.srv import SolveIK
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from trajectory_msgs.msg import JointTrajectoryPoint

from redarm_ros.errors import InvalidInputError, RedarmError
from redarm_ros.kinematics import describe_solver, load_arm
from redarm_ros.kinematics.result import IKStatus
from redarm_ros.kinematics.solve import IKAnswer, IKFrontEnd
from redarm_ros.nodes._common import (
    ParamNode,
    ParamSpec,
    UniqueNameCheck,
    any_string,
    in_range,
    non_empty_string,
    non_negative,
    pose_msg_to_matrix,
    positive,
    run_node,
    watch_duplicates,
)
from redarm_ros.nodes.description import DESCRIPTION_QOS

__all__ = ["IKServiceNode", "IKFrontEnd", "IKAnswer", "main"]  # IKFrontEnd / IKAnswer: re-exported

NODE_NAME = "ik_service"
#: joint_states messages kept (serialized) for the seed: the newest of each of a few publishers.
JOINT_STATES_KEPT = 4

# IKStatus of the kinematics core -> SolveIK response code.
_STATUS_CODE = {
    IKStatus.SUCCESS: SolveIK.Response.SUCCESS,
    IKStatus.NO_SOLUTION_IN_LIMITS: SolveIK.Response.NO_SOLUTION_IN_LIMITS,
    IKStatus.OUT_OF_REACH: SolveIK.Response.OUT_OF_REACH,
    IKStatus.INVALID_INPUT: SolveIK.Response.INVALID_INPUT,
    IKStatus.TIMEOUT: SolveIK.Response.TIMEOUT,
    IKStatus.INTERNAL_ERROR: SolveIK.Response.INTERNAL_ERROR,
    IKStatus.ALL_SOLUTIONS_COLLIDE: SolveIK.Response.ALL_SOLUTIONS_COLLIDE,
}
STATUS_NAMES = {code: st.name for st, code in _STATUS_CODE.items()}


def _non_empty_string_list(value: Any) -> str | None:
    if not isinstance(value, (list, tuple)) or not value or not all(isinstance(v, str) and v for v in value):
        return "must be a non-empty list of arm names"
    return None


PARAMS = [
    ParamSpec(
        "arms",
        ["pa10", "pa10_7c", "powercube6", "powercube7"],
        "Arm models served (names of config/arms/<name>.yaml, or paths).",
        _non_empty_string_list,
        read_only=True,
    ),
    ParamSpec(
        "default_arm",
        "",
        "Arm used when a request leaves `arm` empty; must be served. Empty: the URDF arm if one is given, "
        "else the first of `arms`.",
        any_string,
        read_only=True,
    ),
    ParamSpec(
        "urdf",
        "",
        "Also serve the arm of this URDF file (the chain from `base_link` to `tip_link`): closed-form "
        "swivel IK for a spherical-shoulder / elbow / spherical-wrist 7R chain, numeric IK otherwise.",
        any_string,
        read_only=True,
    ),
    ParamSpec(
        "robot_description",
        "",
        "Also serve the arm of this URDF text (as ros2_control and MoveIt take it as a parameter).",
        any_string,
        read_only=True,
    ),
    ParamSpec(
        "robot_description_topic",
        "",
        "Also serve the arm of the URDF published on this topic (std_msgs/String, transient local, e.g. "
        "/robot_description); the service is offered once it has arrived. Empty: no topic.",
        any_string,
        read_only=True,
    ),
    ParamSpec("base_link", "", "The URDF arm's base link (the chain's root; targets are in its frame).",
              any_string, read_only=True),
    ParamSpec("tip_link", "", "The URDF arm's tip link (the tool frame the targets give).", any_string,
              read_only=True),
    ParamSpec("urdf_arm_name", "", "Name the URDF arm is served under (requests' `arm`); empty: the URDF's "
              "robot name.", any_string, read_only=True),
    ParamSpec(
        "base_frame",
        "base_link",
        "Frame the targets must be given in (an empty frame_id means this frame); the URDF arm's targets "
        "are in its `base_link` frame.",
        non_empty_string,
    ),
    ParamSpec(
        "quaternion_tolerance",
        1e-3,
        "Largest accepted | |q| - 1 | of a target quaternion; within it the quaternion is renormalised "
        "(1e-12 .. 0.1: beyond that a quaternion is not a rotation given with round-off).",
        in_range(1e-12, 0.1),
    ),
    ParamSpec(
        "default_timeout", 0.05, "Solver time budget (s) when a request leaves `timeout` at 0.", positive
    ),
    ParamSpec(
        "suggest_base_move",
        True,
        "On a pose that cannot be solved at all (out of reach, no in-limit or no collision-free solution), "
        "answer with the smallest planar base move that makes it solvable (base_offset).",
        lambda v: None if isinstance(v, bool) else "must be true or false",
        read_only=True,
    ),
    ParamSpec(
        "base_move_yaw",
        True,
        "The base-move suggestion may turn the base too (only when no translation alone works).",
        lambda v: None if isinstance(v, bool) else "must be true or false",
        read_only=True,
    ),
    ParamSpec(
        "base_move_timeout",
        0.5,
        "Time budget (s) of the base-move search, on top of the solve's own budget.",
        positive,
        read_only=True,
    ),
    ParamSpec(
        "nearest_exhaustive",
        False,
        "Requests without a swivel on a 7-DOF swivel arm: also bound every arc between the nearest "
        "search's samples (ik_nearest exhaustive=True): finds the rare optimum the default misses, at "
        "2-3x the solve time.",
        lambda v: None if isinstance(v, bool) else "must be true or false",
        read_only=True,
    ),
    ParamSpec(
        "placement_tasks",
        "",
        "Placement task file (redarm-placement's YAML): at start-up the node ranks the base poses for "
        "that task set once (in a thread of its own, one process), logs the best ones and publishes a "
        "YAML summary on the latched ~/placement ('' = off).",
        read_only=True,
    ),
    ParamSpec(
        "request_queue_depth",
        4096,
        "Requests (and responses) the service's middleware queue holds (reliable, KEEP_LAST): a burst "
        "of this many outstanding calls is answered in order.",
        lambda v: (
            None
            if isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 1_000_000
            else "must be an integer in [1, 1000000]"
        ),
        read_only=True,
    ),
    ParamSpec(
        "duplicate_check_s",
        1.0,
        "At start-up, watch the ROS graph this long (s) for another node of the same name and "
        "refuse to start if there is one (0 = no check).",
        non_negative,
        read_only=True,
    ),
]


# ----------------------------------------------------------------------------------------------
# The node
# ----------------------------------------------------------------------------------------------
class IKServiceNode(ParamNode, node_name=NODE_NAME, params=PARAMS):
    """``ik_service``: serves ``~/solve_ik`` (redarm_interfaces/srv/SolveIK) for the configured arms."""

    def _setup(self, p: dict[str, Any]) -> None:
        arms: dict[str, Any] = {}
        for name in p["arms"]:
            try:
                arm = load_arm(name)
            except RedarmError as exc:
                raise ValueError(f"parameter arms: cannot load arm {name!r}: {exc}") from exc
            arms[name] = arm
            if arm.name != name:  # a path was given: also answer to the model's own name
                arms.setdefault(arm.name, arm)
        self._p = p
        self._arms = arms
        self.front: IKFrontEnd | None = None
        self.urdf_arm: Any = None
        sources = [k for k in ("urdf", "robot_description", "robot_description_topic") if p[k]]
        if len(sources) > 1:
            raise ValueError(f"parameters {', '.join(sources)}: give one URDF source, not {len(sources)}")
        if sources and not (p["base_link"] and p["tip_link"]):
            raise ValueError(f"parameter {sources[0]}: a URDF arm needs the base_link and tip_link "
                             "parameters")
        self.requests = 0
        self.failures = 0
        self.srv = None
        self.last_seed_source = ""  # request, joint_states or mid-range (see seed_of)
        self._queue_depth = int(p["request_queue_depth"])
        # The latest measured joint positions by name: the seed of a request that gives none. The
        # messages are kept serialized and read only when a seed is needed (joint_states come at up to
        # 100 Hz; seeds are rare): the last few, so that joints published by several sources merge.
        self._joint_positions: dict[str, float] = {}
        self._js_raw: collections.deque[bytes] = collections.deque(maxlen=JOINT_STATES_KEPT)
        self.create_subscription(JointState, "joint_states", self._on_joint_states, 10, raw=True)
        self.placement: Any = None  # the PlacementResult of placement_tasks, once computed
        self._placement_lock = threading.Lock()
        self._closed = False
        if p["placement_tasks"]:
            self._start_placement(p["placement_tasks"])
        if sources and sources[0] != "robot_description_topic":
            self._add_urdf_arm(p[sources[0]], sources[0])
        self.description_sub = None
        if p["robot_description_topic"]:
            self.description_sub = self.create_subscription(
                String, p["robot_description_topic"], self._on_description, DESCRIPTION_QOS
            )
            self.get_logger().info(f"waiting for the URDF on {p['robot_description_topic']}")
        else:
            self._build_front()
        # The service is offered once the duplicate-name check has passed (a timer: no blocking here).
        self.name_check = UniqueNameCheck(self, p["duplicate_check_s"], on_passed=self._serve)
        watch_duplicates(self, yield_to_elder=p["duplicate_check_s"] > 0)

    def _add_urdf_arm(self, source: str, param: str) -> None:
        p = self._p
        try:
            arm = load_arm(source, base_link=p["base_link"], tip_link=p["tip_link"],
                           **({"arm_name": p["urdf_arm_name"]} if p["urdf_arm_name"] else {}))
        except RedarmError as exc:
            raise ValueError(f"parameter {param}: cannot load the URDF arm: {exc}") from exc
        self.urdf_arm = arm
        self._arms[arm.name] = arm
        self.get_logger().info(
            f"URDF arm {arm.name!r} ({p['base_link']} -> {p['tip_link']}, {arm.n} joints): "
            f"{describe_solver(arm)}"
        )

    def _on_description(self, msg: String) -> None:
        if self.front is not None:
            return  # the arm is served; a later description does not swap it under running requests
        try:
            self._add_urdf_arm(msg.data, "robot_description_topic")
            self._build_front()
        except ValueError as exc:
            self.get_logger().error(f"{exc}; waiting for another description")
            return
        if self.name_check.done:
            self._serve()

    def _build_front(self) -> None:
        p = self._p
        default = p["default_arm"] or (self.urdf_arm.name if self.urdf_arm is not None else p["arms"][0])
        try:
            self.front = IKFrontEnd(
                self._arms,
                default,
                suggest_base_move=p["suggest_base_move"],
                base_move_yaw=p["base_move_yaw"],
                base_move_timeout_s=float(p["base_move_timeout"]),
                exhaustive_nearest=p["nearest_exhaustive"],
            )
        except InvalidInputError as exc:
            raise ValueError(str(exc)) from exc
        self._serving_note = (
            f"serving {self.get_fully_qualified_name()}/solve_ik for arms {', '.join(sorted(self._arms))} "
            f"(default {default}, targets in frame '{p['base_frame']}'"
            + (f"; {self.urdf_arm.name}: '{p['base_link']}')" if self.urdf_arm is not None else ")")
        )

    def _serve(self) -> None:
        if self.front is None or self.srv is not None:  # (a URDF still to come on its topic, or served)
            return
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self._queue_depth,
            reliability=ReliabilityPolicy.RELIABLE,
        )
        self.srv = self.create_service(SolveIK, "~/solve_ik", self._on_solve, qos_profile=qos)
        self.get_logger().info(self._serving_note)

    def _on_joint_states(self, data: bytes) -> None:
        first = not self._joint_positions
        self._js_raw.append(data)
        if first and self.joint_positions:
            self.get_logger().info("empty seeds now use the latest joint_states")

    @property
    def joint_positions(self) -> dict[str, float]:
        """The latest measured joint positions by name, from the joint_states received so far."""
        pending = self._js_raw
        while pending:  # oldest first: the newest wins
            msg = deserialize_message(pending.popleft(), JointState)
            if len(msg.position) == len(msg.name):  # else not a measurement of positions
                self._joint_positions.update(zip(msg.name, (float(v) for v in msg.position), strict=True))
        return self._joint_positions

    def seed_of(self, req: SolveIK.Request) -> tuple[list[float], str]:
        """The seed for ``req`` and where it came from: the request's own (``request``), the latest
        joint_states when they name every joint of the arm (``joint_states``), else mid-range (``[]``,
        ``mid-range``)."""
        if len(req.seed):
            return list(req.seed), "request"
        try:
            names = self.front.arm_for(req.arm).joint_names
        except InvalidInputError:
            return [], "mid-range"  # the solve answers the unknown arm
        positions = self.joint_positions
        if names and all(n in positions for n in names):
            return [positions[n] for n in names], "joint_states"
        return [], "mid-range"

    def _start_placement(self, path: str) -> None:
        from redarm_ros.placement import load_problem

        try:
            problem = load_problem(path)  # a bad file refuses the start, like any bad parameter
        except RedarmError as exc:
            raise ValueError(f"parameter placement_tasks: {exc}") from exc
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.placement_pub = self.create_publisher(String, "~/placement", latched)
        self.placement_done = threading.Event()
        # A thread of its own: a large grid takes a while, and ~/solve_ik is served meanwhile.
        threading.Thread(target=self._run_placement, args=(path, problem), name="placement",
                         daemon=True).start()

    def _run_placement(self, path: str, problem: Any) -> None:
        from redarm_ros.placement import place

        try:
            res = place(problem, engine="local", workers=1)
        except Exception as exc:  # noqa: BLE001 - the study is advice: the service keeps running
            self.get_logger().error(f"placement study of {path} failed: {exc!r}")
            self.placement_done.set()
            return
        summary = {"tasks_file": path, **res.summary(top=5)}
        best = "; ".join(f"x {b['x']:+.2f} m, y {b['y']:+.2f} m, yaw {b['yaw_deg']:.0f} deg"
                         for b in summary["best"][:3]) or "none"
        msg = String(data=yaml.safe_dump(summary, sort_keys=False))
        with self._placement_lock:
            self.placement = res
            if not self._closed:
                self.get_logger().info(
                    f"placement for {path} ({summary['arm']}, {summary['tasks']} tasks): "
                    f"{summary['valid']} of {summary['base_poses']} base poses valid; best: {best}")
                self.placement_pub.publish(msg)
        self.placement_done.set()

    def destroy_node(self) -> None:
        lock = getattr(self, "_placement_lock", None)  # None: _setup refused the start before it
        if lock is not None:
            with lock:  # a placement study still running publishes nothing after this
                self._closed = True
        super().destroy_node()

    # Short callback: read parameters, delegate, convert.
    def _on_solve(self, req: SolveIK.Request, resp: SolveIK.Response) -> SolveIK.Response:
        self.requests += 1
        base_frame = self.get_parameter("base_frame").value
        if self.urdf_arm is not None and (req.arm or self.front.default_arm) == self.urdf_arm.name:
            base_frame = self._p["base_link"]  # a URDF arm's targets are in its base link's frame
        try:
            ans = self._answer(req, base_frame)
            if not ans.solver and ans.status is IKStatus.INVALID_INPUT:
                arm = self.front.arms.get(req.arm or self.front.default_arm)
                ans.solver = describe_solver(arm) if arm is not None else ""
        except InvalidInputError as exc:
            ans = IKAnswer(IKStatus.INVALID_INPUT, str(exc))
        except Exception as exc:  # noqa: BLE001 - a bug here must not take the service down
            self.get_logger().error(f"internal error on request for arm {req.arm!r}: {exc!r}")
            ans = IKAnswer(IKStatus.INTERNAL_ERROR, f"internal error: {type(exc).__name__}: {exc}")
        self._fill(resp, ans, base_frame)
        if ans.status is IKStatus.SUCCESS:
            self.get_logger().debug(
                f"solved for {req.arm or self.front.default_arm} (seed: {self.last_seed_source}): swivel "
                f"{ans.swivel:.4f}, pos err {ans.position_error:.2e} m"
            )
        else:
            self.failures += 1
            log = self.get_logger().error if ans.status is IKStatus.INTERNAL_ERROR else self.get_logger().info
            log(
                f"request {self.requests} ({req.arm or self.front.default_arm}): "
                f"{ans.status.name}: {ans.message}"
            )
        return resp

    def _answer(self, req: SolveIK.Request, base_frame: str) -> IKAnswer:
        frame = req.target.header.frame_id
        if frame and frame.lstrip("/") != base_frame:
            raise InvalidInputError(
                f"cannot transform the target from frame {frame!r}: this service has no tf; "
                f"give the pose in {base_frame!r} (or leave frame_id empty)",
                field="target.header.frame_id",
                value=frame,
            )
        T = pose_msg_to_matrix(req.target.pose, self.get_parameter("quaternion_tolerance").value)
        timeout = float(req.timeout)
        if not math.isfinite(timeout) or timeout < 0:
            raise InvalidInputError(f"timeout must be >= 0 s, got {timeout}", field="timeout", value=timeout)
        if timeout == 0:
            timeout = float(self.get_parameter("default_timeout").value)
        seed, self.last_seed_source = self.seed_of(req)
        return self.front.solve(
            T,
            req.arm,
            swivel=float(req.swivel) if req.swivel_given else None,
            seed=seed,
            all_solutions=req.all_solutions,
            timeout_s=timeout,
            check_collisions=not req.ignore_collisions,
        )

    def _fill(self, resp: SolveIK.Response, ans: IKAnswer, base_frame: str) -> None:
        resp.status = _STATUS_CODE[ans.status]
        resp.message = ans.message
        resp.swivel = float(ans.swivel)
        resp.position_error = float(ans.position_error)
        resp.orientation_error = float(ans.orientation_error)
        resp.clearance = float(ans.clearance)
        resp.solver = ans.solver
        bp = ans.base_offset
        if bp is not None and bp.valid:
            resp.base_offset.x, resp.base_offset.y, resp.base_offset.z = float(bp.x), float(bp.y), 0.0
            resp.base_offset_yaw = float(bp.yaw)
            resp.base_offset_valid = True
        if ans.q is not None and ans.status in (IKStatus.SUCCESS, IKStatus.TIMEOUT):
            js = resp.solution
            js.header.stamp = self.get_clock().now().to_msg()
            js.header.frame_id = base_frame
            js.name = ans.joint_names
            js.position = ans.q.tolist()
        if ans.solutions is not None:
            resp.solutions = [
                JointTrajectoryPoint(positions=[float(v) for v in row]) for row in ans.solutions
            ]


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``ros2 run redarm_ros ik_service``)."""
    return run_node(IKServiceNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
