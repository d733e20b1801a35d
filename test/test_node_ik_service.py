"""ik_service node: bad requests answered with the right status (node keeps serving), FK round trips,
swivel mode, all solutions, in-process and across processes, and a second node of the same name."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from redarm_interfaces.srv import SolveIK  # noqa: E402

from redarm_ros.geometry.self_collision import self_collision, self_collision_batch  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.kinematics.quaternion import matrix_to_quat  # noqa: E402
from redarm_ros.nodes._common import call_resending, pose_msg_to_matrix, spin_until  # noqa: E402
from redarm_ros.nodes.ik_service import IKServiceNode  # noqa: E402
from redarm_ros.procs import python_module_cmd  # noqa: E402

ARMS = ["pa10", "pa10_7c", "powercube6", "powercube7"]
R = SolveIK.Response


def make_request(T: np.ndarray, arm: str = "", **fields: Any) -> SolveIK.Request:
    """A SolveIK request for the 4x4 pose T (quaternion converted to the message's x, y, z, w)."""
    req = SolveIK.Request()
    req.arm = arm
    p = req.target.pose.position
    p.x, p.y, p.z = (float(v) for v in T[:3, 3])
    w, x, y, z = (float(v) for v in matrix_to_quat(T[:3, :3]))
    o = req.target.pose.orientation
    o.x, o.y, o.z, o.w = x, y, z, w
    for k, v in fields.items():
        setattr(req, k, v)
    return req


class Caller:
    """Client side: call the service and spin until the answer is there (bounded)."""

    def __init__(
        self, ctx: Any, executor: SingleThreadedExecutor, service: str = "/ik_service/solve_ik"
    ) -> None:
        self.node = rclpy.create_node("ik_test_client", context=ctx)
        self.client = self.node.create_client(SolveIK, service)
        self.executor = executor
        executor.add_node(self.node)

    def wait_ready(self, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not self.client.service_is_ready():
            assert time.monotonic() < deadline, "service did not appear"
            self.executor.spin_once(timeout_sec=0.05)

    def __call__(self, req: SolveIK.Request, timeout: float = 10.0) -> SolveIK.Response:
        resp = call_resending(self.client, req, lambda p, t: spin_until(self.executor, p, t, 0.05), timeout)
        assert resp is not None, "no answer from the service"
        return resp


@pytest.fixture(scope="module")
def ctx(ros_env: Any) -> Iterator[Any]:
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros_env.domain_id)
    yield context
    rclpy.shutdown(context=context)


@pytest.fixture(scope="module")
def service(ctx: Any) -> Iterator[tuple[IKServiceNode, Caller]]:
    """One in-process ik_service node (all four arms) and a client in the same executor."""
    node = IKServiceNode(
        context=ctx,
        node_name="ik_service_inproc",  # the cross-process test below owns the default name
        parameter_overrides=[Parameter("arms", value=ARMS), Parameter("duplicate_check_s", value=0.0)],
    )
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    caller = Caller(ctx, executor, "/ik_service_inproc/solve_ik")
    caller.wait_ready()
    yield node, caller
    executor.shutdown()
    caller.node.destroy_node()
    node.destroy_node()


def random_pose(arm: Any, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A collision-free joint vector well inside the limits and its tool pose."""
    while True:
        q = rng.uniform(0.8 * arm.lower, 0.8 * arm.upper)
        if not self_collision(arm, q).colliding:
            return q, arm.fk(q)


def random_poses(arm: Any, seed: int, n: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``n`` draws of ``random_pose`` from a generator seeded with ``seed``."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield random_pose(arm, rng)


GOOD_T = load_arm("pa10").fk(np.array([0.3, 0.4, -0.2, 1.0, 0.3, 0.5, 0.1]))


def _bad(kind: str) -> SolveIK.Request:
    req = make_request(GOOD_T, "pa10")
    o = req.target.pose.orientation
    if kind == "nan_position":
        req.target.pose.position.y = math.nan
    elif kind == "nan_orientation":
        o.z = math.nan
    elif kind == "inf_position":
        req.target.pose.position.x = math.inf
    elif kind == "zero_quaternion":
        o.x = o.y = o.z = o.w = 0.0
    elif kind == "non_unit_quaternion":
        o.x, o.y, o.z, o.w = 0.0, 0.0, 0.0, 2.0
    elif kind == "unknown_arm":
        req.arm = "no_such_arm"
    elif kind == "seed_too_short":
        req.seed = [0.0, 0.1, 0.2]
    elif kind == "seed_too_long":
        req.seed = [0.0] * 8
    elif kind == "seed_nan":
        req.seed = [0.0, 0.0, math.nan, 0.0, 0.0, 0.0, 0.0]
    elif kind == "foreign_frame":
        req.target.header.frame_id = "camera_link"
    elif kind == "negative_timeout":
        req.timeout = -1.0
    elif kind == "nan_swivel":
        req.swivel_given, req.swivel = True, math.nan
    elif kind == "huge_swivel":  # its 2*pi copy would be round-off
        req.swivel_given, req.swivel = True, 1e300
    elif kind == "swivel_on_chain_without_swivel":
        req.arm = "powercube6"  # its analytic IK has no swivel; asking for one must not crash
        req.swivel_given, req.swivel = True, 0.3
    else:  # pragma: no cover - test table typo
        raise AssertionError(kind)
    return req


BAD = [
    "nan_position",
    "nan_orientation",
    "inf_position",
    "zero_quaternion",
    "non_unit_quaternion",
    "unknown_arm",
    "seed_too_short",
    "seed_too_long",
    "seed_nan",
    "foreign_frame",
    "negative_timeout",
    "nan_swivel",
    "huge_swivel",
]


@pytest.mark.parametrize("kind", BAD)
def test_bad_request_is_invalid_input_and_node_keeps_serving(service: Any, kind: str) -> None:
    node, call = service
    resp = call(_bad(kind))
    assert resp.status == R.INVALID_INPUT, (kind, resp.status, resp.message)
    assert resp.message, "a refusal must say why"
    assert len(resp.solution.position) == 0
    # The same node answers a good request right after.
    good = call(make_request(GOOD_T, "pa10"))
    assert good.status == R.SUCCESS, good.message


def test_messages_name_the_problem(service: Any) -> None:
    _, call = service
    assert "no_such_arm" in call(_bad("unknown_arm")).message
    assert "pa10" in call(_bad("unknown_arm")).message  # lists what is served
    assert "seed" in call(_bad("seed_too_short")).message
    assert "zero quaternion" in call(_bad("zero_quaternion")).message
    assert "camera_link" in call(_bad("foreign_frame")).message


def test_swivel_on_powercube6_is_answered(service: Any) -> None:
    """The 6-DOF arm: a swivel request is answered (solved or refused), never a crash."""
    _, call = service
    resp = call(_bad("swivel_on_chain_without_swivel"))
    assert resp.status in (R.SUCCESS, R.INVALID_INPUT, R.NO_SOLUTION_IN_LIMITS, R.OUT_OF_REACH)


@pytest.mark.parametrize("arm_name", ["pa10", "powercube6", "powercube7"])
def test_unreachable_is_out_of_reach_with_a_base_move_that_solves_it(service: Any, arm_name: str) -> None:
    _, call = service
    T = np.eye(4)
    T[:3, 3] = (3.0, 0.0, 0.5)  # metres beyond any of these arms
    resp = call(make_request(T, arm_name))
    assert resp.status == R.OUT_OF_REACH, resp.message
    assert len(resp.solution.position) == 0
    assert resp.base_offset_valid and "moving the base by" in resp.message
    assert resp.base_offset.z == 0.0 and resp.base_offset.x > 1.5
    # the target seen from the moved base (x, y, yaw) is solved
    c, s_ = math.cos(resp.base_offset_yaw), math.sin(resp.base_offset_yaw)
    B = np.eye(4)
    B[:2, :2] = [[c, -s_], [s_, c]]
    B[:2, 3] = resp.base_offset.x, resp.base_offset.y
    moved = call(make_request(np.linalg.inv(B) @ T, arm_name))
    assert moved.status == R.SUCCESS, moved.message
    assert not moved.base_offset_valid
    if arm_name != "powercube6":
        resp = call(make_request(T, arm_name, swivel_given=True, swivel=0.5))
        assert resp.status == R.OUT_OF_REACH, resp.message
        assert resp.base_offset_valid


@pytest.mark.parametrize("arm_name", ["pa10", "powercube6"])
def test_every_solution_colliding_is_reported_and_the_flag_allows_it(service: Any, arm_name: str) -> None:
    """Wrist and tool under the ground plane: ALL_SOLUTIONS_COLLIDE naming the links, no base move (a
    planar move keeps the height); ignore_collisions returns the solution."""
    _, call = service
    arm = load_arm(arm_name)
    q = np.radians([0, 90, 0, 90, 0, 0, 0] if arm.n == 7 else [0, -20, 0, -40, -30, 0])
    T = arm.fk(q)
    resp = call(make_request(T, arm_name))
    assert resp.status == R.ALL_SOLUTIONS_COLLIDE == 8, resp.message
    assert "ground" in resp.message and len(resp.solution.position) == 0
    assert not resp.base_offset_valid
    resp = call(make_request(T, arm_name, ignore_collisions=True, all_solutions=True))
    assert resp.status == R.SUCCESS, resp.message
    assert arm.pose_error(np.array(resp.solution.position), T)[0] < 1e-9
    assert math.isnan(resp.clearance)


@pytest.mark.parametrize("arm_name", ARMS)
def test_solutions_are_collision_free_and_carry_their_clearance(service: Any, arm_name: str) -> None:
    """Uniform postures over the whole range: every SUCCESS answer and every listed solution is
    collision-free; any other answer is ALL_SOLUTIONS_COLLIDE and hands out no solution (a pose whose
    every solution collides is the test above)."""
    _, call = service
    arm = load_arm(arm_name)
    rng = np.random.default_rng(17)
    statuses = set()
    for _ in range(20):
        q = rng.uniform(arm.lower, arm.upper)
        resp = call(make_request(arm.fk(q), arm_name, all_solutions=True))
        statuses.add(resp.status)
        assert resp.status in (R.SUCCESS, R.ALL_SOLUTIONS_COLLIDE), resp.message
        if resp.status == R.SUCCESS:
            sol = np.array(resp.solution.position)
            sc = self_collision(arm, sol)
            assert not sc.colliding and resp.clearance == pytest.approx(sc.min_distance, abs=1e-12)
            rows = np.array([pt.positions for pt in resp.solutions])
            assert not self_collision_batch(arm, rows).colliding.any()
        else:  # no solution handed out
            assert len(resp.solution.position) == 0 and len(resp.solutions) == 0
    assert R.SUCCESS in statuses


def test_slightly_non_unit_quaternion_is_renormalised(service: Any) -> None:
    _, call = service
    req = make_request(GOOD_T, "pa10")
    o = req.target.pose.orientation
    o.x, o.y, o.z, o.w = (1.0002 * v for v in (o.x, o.y, o.z, o.w))
    resp = call(req)
    assert resp.status == R.SUCCESS, resp.message
    assert resp.orientation_error < 1e-9


@pytest.mark.parametrize("arm_name", ARMS)
def test_fk_round_trip_all_solutions(service: Any, arm_name: str) -> None:
    _, call = service
    arm = load_arm(arm_name)
    for _, T in random_poses(arm, 7, 8):
        resp = call(make_request(T, arm_name, all_solutions=True))
        assert resp.status == R.SUCCESS, resp.message
        assert list(resp.solution.name) == list(arm.joint_names)
        assert resp.solution.header.frame_id == "base_link"
        q = np.array(resp.solution.position)
        assert arm.within_limits(q, 1e-9)
        pe, re = arm.pose_error(q, T)
        assert pe < 1e-9 and re < 1e-9
        assert resp.position_error == pytest.approx(pe, abs=1e-12)
        assert resp.orientation_error == pytest.approx(re, abs=1e-12)
        assert len(resp.solutions) >= 1
        for pt in resp.solutions:
            qs = np.array(pt.positions)
            assert qs.shape == (arm.n,) and arm.within_limits(qs, 1e-9)
            pe, re = arm.pose_error(qs, T)
            assert pe < 1e-9 and re < 1e-9


@pytest.mark.parametrize("arm_name", ["pa10", "powercube7"])
def test_seed_gives_nearest_solution(service: Any, arm_name: str) -> None:
    """With the true configuration as seed, the answer is that configuration (no branch flip)."""
    _, call = service
    arm = load_arm(arm_name)
    for q_true, T in random_poses(arm, 11, 8):
        resp = call(make_request(T, arm_name, seed=[float(v) for v in q_true]))
        assert resp.status == R.SUCCESS, resp.message
        assert np.max(np.abs(np.array(resp.solution.position) - q_true)) < 1e-6
        assert resp.swivel == pytest.approx(arm.swivel(q_true), abs=1e-6)


@pytest.mark.parametrize("arm_name", ["pa10", "pa10_7c", "powercube7"])
def test_swivel_given_solves_at_that_swivel(service: Any, arm_name: str) -> None:
    _, call = service
    arm = load_arm(arm_name)
    solved = 0
    for q_true, T in random_poses(arm, 3, 10):
        s = float(arm.swivel(q_true))
        resp = call(
            make_request(
                T, arm_name, swivel_given=True, swivel=s, all_solutions=True, seed=[float(v) for v in q_true]
            )
        )
        assert resp.status == R.SUCCESS, resp.message  # the true q is a solution at its own swivel
        solved += 1
        q = np.array(resp.solution.position)
        assert np.max(np.abs(q - q_true)) < 1e-6  # nearest to the seed among the (up to 8) solutions
        assert resp.swivel == pytest.approx(s, abs=1e-6)
        for pt in resp.solutions:
            assert arm.swivel(np.array(pt.positions)) == pytest.approx(s, abs=1e-6)
            assert arm.pose_error(np.array(pt.positions), T)[0] < 1e-9
    assert solved == 10


def test_swivel_without_in_limit_solution_says_so(service: Any) -> None:
    """A reachable pose at a swivel where every solution breaks a limit: NO_SOLUTION_IN_LIMITS."""
    _, call = service
    arm = load_arm("pa10")
    rng = np.random.default_rng(5)
    found = False
    for _ in range(200):
        _, T = random_pose(arm, rng)
        for s in np.linspace(-math.pi, math.pi, 24, endpoint=False):
            if len(arm.ik(T, s)) == 0:
                resp = call(make_request(T, "pa10", swivel_given=True, swivel=float(s)))
                assert resp.status == R.NO_SOLUTION_IN_LIMITS, resp.message
                assert "limit" in resp.message
                found = True
                break
        if found:
            break
    assert found, "no test pose found (widen the search)"


def test_default_arm_and_base_frame(service: Any) -> None:
    _, call = service
    req = make_request(GOOD_T, "")  # empty arm -> default (pa10)
    req.target.header.frame_id = "base_link"
    resp = call(req)
    assert resp.status == R.SUCCESS
    pa10 = load_arm("pa10")  # the default arm solved it (its joint names, its pose)
    assert list(resp.solution.name) == list(pa10.joint_names)
    assert pa10.pose_error(np.array(resp.solution.position), GOOD_T)[0] < 1e-9


def test_pose_msg_to_matrix_tolerance() -> None:
    from geometry_msgs.msg import Pose

    from redarm_ros.errors import InvalidInputError

    pose = Pose()
    pose.orientation.w = 1.0 + 5e-4
    T = pose_msg_to_matrix(pose, 1e-3)
    assert np.allclose(T, np.eye(4))
    with pytest.raises(InvalidInputError):
        pose_msg_to_matrix(pose, 1e-4)


@pytest.mark.parametrize(("arms", "default_arm", "extra", "match"), [
    (["pa10"], "powercube7", None, "default_arm"),  # the default is not among the served arms
    (["no_such_arm"], None, None, "no_such_arm"),
    (["pa10"], None, ("nearest_exhaustive", "yes"), "nearest_exhaustive"),  # not a bool
    (["pa10"], None, ("quaternion_tolerance", 5.0), "quaternion_tolerance"),  # norm 2 is no rotation
    (["pa10"], None, ("base_frame", ""), "base_frame"),
])
def test_bad_parameters_refuse_to_start(ctx: Any, arms: list[str], default_arm: str | None,
                                        extra: tuple[str, Any] | None, match: str) -> None:
    overrides = [Parameter("arms", value=arms), Parameter("duplicate_check_s", value=0.0)]
    if default_arm is not None:
        overrides.append(Parameter("default_arm", value=default_arm))
    if extra is not None:
        overrides.append(Parameter(extra[0], value=extra[1]))
    with pytest.raises(ValueError, match=match):
        IKServiceNode(context=ctx, node_name=f"ik_bad_{match}", parameter_overrides=overrides)


def test_nearest_exhaustive_parameter_reaches_the_solver(ctx: Any) -> None:
    overrides = [Parameter("arms", value=["pa10"]), Parameter("duplicate_check_s", value=0.0)]
    plain = IKServiceNode(context=ctx, node_name="ik_plain", parameter_overrides=overrides)
    exhaustive = IKServiceNode(context=ctx, node_name="ik_exhaustive",
                               parameter_overrides=[*overrides, Parameter("nearest_exhaustive", value=True)])
    try:
        assert plain.front.exhaustive_nearest is False
        assert exhaustive.front.exhaustive_nearest is True
    finally:
        plain.destroy_node()
        exhaustive.destroy_node()


PLACEMENT_TASKS = """\
arm: pa10
base_height: 0.3
grid: {x: [-0.6, 0.6], y: [-0.6, 0.6], step: 0.3, yaw_deg: [0, 90, 180, 270]}
tasks:
  - {position: [0.3, 0.2, 0.7], rpy_deg: [180, 0, 0]}
  - {position: [0.2, -0.3, 0.6], rpy_deg: [180, 0, 30]}
"""


def test_placement_tasks_ranked_at_start_up_published_latched_and_base_move_unchanged(
        ctx: Any, tmp_path: Any) -> None:
    """placement_tasks: the study runs once at start-up; a late subscriber gets the YAML summary (the
    study's own best poses); ~/solve_ik answers meanwhile, its base-move suggestion as without it."""
    import yaml
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import String

    from redarm_ros.placement import load_problem, place

    tasks = tmp_path / "tasks.yaml"
    tasks.write_text(PLACEMENT_TASKS)
    node = IKServiceNode(context=ctx, node_name="ik_placement", parameter_overrides=[
        Parameter("arms", value=["pa10"]), Parameter("duplicate_check_s", value=0.0),
        Parameter("placement_tasks", value=str(tasks))])
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    caller = Caller(ctx, executor, "/ik_placement/solve_ik")
    got: list[str] = []
    try:
        caller.wait_ready()
        T = np.eye(4)
        T[:3, 3] = (3.0, 0.0, 0.5)
        resp = caller(make_request(T, "pa10"))
        assert resp.status == R.OUT_OF_REACH and resp.base_offset_valid and resp.base_offset.x > 1.5
        assert node.placement_done.wait(120.0), "placement study did not finish"
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        caller.node.create_subscription(String, "/ik_placement/placement", lambda m: got.append(m.data),
                                        latched)
        deadline = time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert got, "no summary on ~/placement"
        summary = yaml.safe_load(got[0])
        ref = place(load_problem(tasks), workers=1)
        assert summary["tasks_file"] == str(tasks) and summary["valid"] == int(ref.valid.sum()) > 0
        assert summary["base_poses"] == 100 and summary["tasks"] == 2 and summary["arm"] == "pa10"
        assert len(summary["best"]) == 5
        for b, i in zip(summary["best"], ref.ranking(), strict=False):
            x, y, w = ref.poses[i]
            assert (b["x"], b["y"], b["yaw_deg"]) == (round(x, 6), round(y, 6), round(math.degrees(w), 6))
    finally:
        executor.shutdown()
        caller.node.destroy_node()
        node.destroy_node()


def test_bad_placement_tasks_refuse_to_start(ctx: Any, tmp_path: Any) -> None:
    bad = tmp_path / "tasks.yaml"
    bad.write_text("arm: pa10\ntasks: []\n")
    with pytest.raises(ValueError, match="placement_tasks: .*tasks must be a non-empty list"):
        IKServiceNode(context=ctx, node_name="ik_bad_placement", parameter_overrides=[
            Parameter("arms", value=["pa10"]), Parameter("duplicate_check_s", value=0.0),
            Parameter("placement_tasks", value=str(bad))])


# ---------------------------------------------------------------------------------------------
# Across processes
# ---------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_cross_process_service_and_duplicate_refused(procs: Any, ctx: Any) -> None:
    """The node as its own process: answers good and bad requests; a second one of the same name
    refuses to start with a clear message and exit code 1, and the first keeps serving."""
    first = procs.start(
        "ik_service",
        python_module_cmd("redarm_ros.nodes.ik_service"),
        ready=r"serving /ik_service/solve_ik",
        ready_timeout=30.0,
    )
    executor = SingleThreadedExecutor(context=ctx)
    call = Caller(ctx, executor)
    try:
        call.wait_ready(timeout=15.0)
        arm = load_arm("pa10")
        for _, T in random_poses(arm, 1, 5):
            resp = call(make_request(T, "pa10"))
            assert resp.status == R.SUCCESS, resp.message
            assert arm.pose_error(np.array(resp.solution.position), T)[0] < 1e-9
        assert call(_bad("nan_position")).status == R.INVALID_INPUT
        assert call(_bad("unknown_arm")).status == R.INVALID_INPUT

        # Discovery under load can take over a second: give the newcomer a generous window.
        second = procs.start(
            "ik_service_2",
            python_module_cmd("redarm_ros.nodes.ik_service", "--ros-args", "-p", "duplicate_check_s:=5.0"),
        )
        second.expect_exit()
        second.wait_for_line(r"already running", timeout=30.0)
        deadline = time.monotonic() + 15.0
        while second.returncode is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert second.returncode == 1
        # one line, not a traceback (DuplicateNodeError is a RuntimeError: caught before that)
        assert not any("Traceback" in line for line in second.output()), second.tail()
        assert first.is_running()
        resp = call(make_request(GOOD_T, "pa10"))
        assert resp.status == R.SUCCESS, resp.message
        # One forced past the start-up check (duplicate_check_s 0): the running node notices and says so.
        third = procs.start(
            "ik_service_3",
            python_module_cmd("redarm_ros.nodes.ik_service", "--ros-args", "-p", "duplicate_check_s:=0.0"),
            ready=r"serving /ik_service/solve_ik",
            ready_timeout=30.0,
        )
        first.wait_for_line(r"another node named /ik_service is running in this domain", timeout=20.0)
        procs.stop(third)
        # One whose start-up window (1 ms) passes before discovery shows the first: it serves for a
        # moment, then hears the first one's announcement and stops itself, the younger of the two
        fourth = procs.start(
            "ik_service_4",
            python_module_cmd("redarm_ros.nodes.ik_service", "--ros-args", "-p", "duplicate_check_s:=0.001"),
        )
        fourth.expect_exit()
        deadline = time.monotonic() + 30.0
        while fourth.returncode is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert fourth.returncode == 1, fourth.tail()
        assert any("already running" in line for line in fourth.output()), fourth.tail()
        assert first.is_running()
        resp = call(make_request(GOOD_T, "pa10"))
        assert resp.status == R.SUCCESS, resp.message
    finally:
        executor.shutdown()
        call.node.destroy_node()


# ---------------------------------------------------------------------------------------------
# Bursts: many requests outstanding at once are all answered (none dropped by the service's queue)
# ---------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_burst_of_2000_outstanding_requests_all_answered(procs: Any, ctx: Any) -> None:
    """4 clients keep 500 requests each outstanding (sent before any answer is read) against the node
    in its own process: every one of the 2000 gets its answer, and each answer is for its request.

    The service's queue (``request_queue_depth``, default 4096) holds the requests; with the old depth of
    10 only about 600 of these 2000 reached the node. The callers use response queues deep enough for
    every answer in flight (the middleware delivers the replies of all clients of a service to every
    client, which keeps only its own: a depth of 10 there loses answers on the caller's side).
    Bounded: 2000 requests, 600 s at most."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    procs.start(
        "ik_service_burst",
        python_module_cmd(
            "redarm_ros.nodes.ik_service",
            "--ros-args",
            "-r",
            "__node:=ik_burst",
            "-p",
            "arms:=[pa10]",
            "-p",
            "duplicate_check_s:=0.0",
        ),
        ready=r"serving /ik_burst/solve_ik",
        ready_timeout=60.0,
    )
    executor = SingleThreadedExecutor(context=ctx)
    qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4096, reliability=ReliabilityPolicy.RELIABLE)
    nodes = [rclpy.create_node(f"ik_burst_client_{k}", context=ctx) for k in range(4)]
    clients = [n.create_client(SolveIK, "/ik_burst/solve_ik", qos_profile=qos) for n in nodes]
    for n in nodes:
        executor.add_node(n)
    try:
        deadline = time.monotonic() + 60.0
        while not all(c.service_is_ready() for c in clients):
            assert time.monotonic() < deadline, "service did not appear"
            executor.spin_once(timeout_sec=0.05)
        arm = load_arm("pa10")
        rng = np.random.default_rng(21)
        Q = rng.uniform(0.8 * arm.lower, 0.8 * arm.upper, (3000, 7))
        Q = Q[self_collision_batch(arm, Q).free][:2000]  # poses the collision filter lets through
        assert len(Q) == 2000
        # The server drops an answer to a client whose reply reader it has not matched yet, and on a busy
        # machine that lags the client's own view of the service by seconds: one answered request per
        # client (sent again until answered) first, so the burst tests the queue, not discovery.
        for c in clients:
            warm = call_resending(c, make_request(arm.fk(Q[0]), "pa10"),
                                  lambda p, t: spin_until(executor, p, t, 0.05), 60.0)
            assert warm is not None, "no answer to a single request in 60 s"
        futures = []
        for i in range(500):  # interleaved: each client has all its 500 requests in flight
            for k, c in enumerate(clients):
                idx = 4 * i + k
                futures.append((idx, c.call_async(make_request(arm.fk(Q[idx]), "pa10"))))
        deadline = time.monotonic() + 600.0
        while not all(f.done() for _, f in futures) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        answered = [(idx, f.result()) for idx, f in futures if f.done()]
        assert len(answered) == 2000, f"{2000 - len(answered)} of 2000 requests never answered"
        for idx, resp in answered:  # each answer solves its own request
            assert resp.status == R.SUCCESS, resp.message
            assert arm.pose_error(np.array(resp.solution.position), arm.fk(Q[idx]))[0] < 1e-9
    finally:
        executor.shutdown()
        for n in nodes:
            n.destroy_node()


def test_empty_seed_uses_the_latest_joint_states(ctx: Any) -> None:
    """SolveIK.srv: an empty seed means the current joints (the latest joint_states of the node's
    namespace) when the service has them, else mid-range."""
    from sensor_msgs.msg import JointState

    arm = load_arm("pa10")
    q_now = np.array([2.4, 1.1, -2.2, 1.2, 2.1, 1.0, -2.6])  # far from mid-range (0), on another branch
    T = arm.fk(q_now)
    node = IKServiceNode(context=ctx, namespace="/seed_test",
                         parameter_overrides=[Parameter("duplicate_check_s", value=0.0)])
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    call = Caller(ctx, executor, "/seed_test/ik_service/solve_ik")
    pub = call.node.create_publisher(JointState, "/seed_test/joint_states", 10)
    try:
        call.wait_ready()
        mid = call(make_request(T, "pa10", ignore_collisions=True))
        assert mid.status == R.SUCCESS and node.last_seed_source == "mid-range"
        assert np.max(np.abs(np.array(mid.solution.position) - q_now)) > 0.5  # a different solution
        msg = JointState(name=list(arm.joint_names), position=[float(v) for v in q_now])
        assert spin_until(executor, lambda: (pub.publish(msg), bool(node.joint_positions))[1], 10.0, 0.05)
        now = call(make_request(T, "pa10", ignore_collisions=True))
        assert now.status == R.SUCCESS and node.last_seed_source == "joint_states"
        np.testing.assert_allclose(now.solution.position, q_now, atol=1e-6)
        # a seed in the request still wins
        given = call(make_request(T, "pa10", ignore_collisions=True,
                                  seed=[float(v) for v in mid.solution.position]))
        assert node.last_seed_source == "request"
        np.testing.assert_allclose(given.solution.position, mid.solution.position, atol=1e-6)
    finally:
        executor.shutdown()
        call.node.destroy_node()
        node.destroy_node()
