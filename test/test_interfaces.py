"""redarm_interfaces: generated types, their fields and constants, and a cross-process round trip.

The package is built by scripts/setup_env.sh (colcon, merged into the .venv prefix). The round trip
runs a server in a child process (service, action and topic) and the client in this process, over
SHM-only DDS on the session's random domain (conftest ``ros_env``).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import pytest

try:
    from redarm_interfaces.action import Reach
    from redarm_interfaces.msg import ControllerState
    from redarm_interfaces.srv import SolveIK
except ImportError as exc:  # a missing build is a failure, not a skip: the set-up must provide it
    pytest.fail(
        f"redarm_interfaces is not importable ({exc}); run `make setup` (scripts/setup_env.sh)",
        pytrace=False,
    )

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

# Each interface's fields are written out in full on purpose: the expected interface, not read back
# from the .msg/.srv/.action files (so the tables look alike).


def test_solve_ik_request_fields() -> None:
    assert SolveIK.Request.get_fields_and_field_types() == {
        "target": "geometry_msgs/PoseStamped",
        "arm": "string",
        "swivel": "double",
        "swivel_given": "boolean",
        "seed": "sequence<double>",
        "all_solutions": "boolean",
        "timeout": "double",
        "ignore_collisions": "boolean",
    }
    req = SolveIK.Request()
    assert req.target.pose.orientation.w == 1.0  # identity quaternion (x, y, z, w) by default
    assert not req.swivel_given and not req.all_solutions
    assert req.timeout == 0.0 and len(req.seed) == 0


def test_solve_ik_response_fields_and_status_codes() -> None:
    assert SolveIK.Response.get_fields_and_field_types() == {
        "status": "uint8",
        "message": "string",
        "solution": "sensor_msgs/JointState",
        "solutions": "sequence<trajectory_msgs/JointTrajectoryPoint>",
        "swivel": "double",
        "position_error": "double",
        "orientation_error": "double",
        "clearance": "double",
        "base_offset": "geometry_msgs/Vector3",
        "base_offset_yaw": "double",
        "base_offset_valid": "boolean",
        "solver": "string",
    }
    codes = {
        name: getattr(SolveIK.Response, name)
        for name in ("SUCCESS", "NO_SOLUTION_IN_LIMITS", "OUT_OF_REACH", "INVALID_INPUT", "TIMEOUT",
                     "INTERNAL_ERROR", "ALL_SOLUTIONS_COLLIDE")
    }
    assert codes == {"SUCCESS": 0, "NO_SOLUTION_IN_LIMITS": 1, "OUT_OF_REACH": 2, "INVALID_INPUT": 3,
                     "TIMEOUT": 4, "INTERNAL_ERROR": 7, "ALL_SOLUTIONS_COLLIDE": 8}


def test_controller_state_fields_and_phases() -> None:
    assert ControllerState.get_fields_and_field_types() == {
        "header": "std_msgs/Header",
        "phase": "string",
        "swivel": "double",
        "swivel_desired": "double",
        "clearance": "double",
        "distance_to_goal": "double",
        "orientation_error": "double",
        "goal": "geometry_msgs/Pose",
        "message": "string",
        "goal_kind": "string",
        "goal_velocity": "geometry_msgs/Twist",
        "stream_rate": "double",
    }
    phases = [ControllerState.IDLE, ControllerState.REACHING, ControllerState.HOLDING,
              ControllerState.REJECTED, ControllerState.REACHED, ControllerState.TRACKING,
              ControllerState.REPLANNING, ControllerState.BLOCKED]
    assert phases == ["idle", "reaching", "holding", "rejected", "reached", "tracking", "replanning",
                      "blocked"]
    assert ControllerState(clearance=math.inf).clearance == math.inf


def test_reach_action_parts() -> None:
    assert Reach.Goal.get_fields_and_field_types() == {
        "target": "geometry_msgs/PoseStamped",
        "swivel_preference": "double",
        "use_swivel_preference": "boolean",
        "timeout": "double",
    }
    assert Reach.Result.get_fields_and_field_types() == {
        "status": "uint8",
        "message": "string",
        "position_error": "double",
        "orientation_error": "double",
    }
    assert Reach.Feedback.get_fields_and_field_types() == {
        "phase": "string",
        "distance_to_goal": "double",
        "orientation_error": "double",
        "swivel": "double",
        "clearance": "double",
        "message": "string",
    }
    # Result codes extend SolveIK's without renumbering them, and the controller outcomes do not reuse
    # SolveIK's other codes (INTERNAL_ERROR, ALL_SOLUTIONS_COLLIDE).
    for name in ("SUCCESS", "NO_SOLUTION_IN_LIMITS", "OUT_OF_REACH", "INVALID_INPUT", "TIMEOUT"):
        assert getattr(Reach.Result, name) == getattr(SolveIK.Response, name)
    assert (Reach.Result.REJECTED, Reach.Result.ABORTED) == (5, 6)
    outcomes = [Reach.Result.IN_COLLISION, Reach.Result.BLOCKED, Reach.Result.CANCELED,
                Reach.Result.PREEMPTED]
    assert len(set(outcomes)) == 4
    assert not set(outcomes) & {SolveIK.Response.INTERNAL_ERROR, SolveIK.Response.ALL_SOLUTIONS_COLLIDE,
                                *range(7)}


# A child process serving all three interfaces. It answers SolveIK by echoing the request into the
# response (so the test can check every field crossed the process boundary), publishes one latched
# ControllerState, and runs Reach with one feedback message.
_SERVER = r"""
import sys
import rclpy
from rclpy.action import ActionServer
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile
from redarm_interfaces.action import Reach
from redarm_interfaces.msg import ControllerState
from redarm_interfaces.srv import SolveIK
from trajectory_msgs.msg import JointTrajectoryPoint


def solve(req, res):
    res.status = SolveIK.Response.NO_SOLUTION_IN_LIMITS if req.swivel_given else SolveIK.Response.SUCCESS
    res.message = "arm=" + req.arm
    res.solution.header.frame_id = req.target.header.frame_id
    res.solution.name = ["j%d" % i for i in range(len(req.seed))]
    res.solution.position = [2.0 * v for v in req.seed]
    if req.all_solutions:
        res.solutions = [JointTrajectoryPoint(positions=list(req.seed)) for _ in range(3)]
    res.swivel = req.swivel
    res.position_error = req.target.pose.position.x
    res.orientation_error = req.timeout
    return res


def reach(handle):
    handle.publish_feedback(Reach.Feedback(distance_to_goal=0.25, swivel=handle.request.swivel_preference,
                                           clearance=0.1))
    handle.succeed()
    return Reach.Result(status=Reach.Result.SUCCESS, message="reached",
                        position_error=handle.request.target.pose.position.z, orientation_error=0.0)


def main():
    rclpy.init()
    node = rclpy.create_node("iface_server")
    node.create_service(SolveIK, "solve_ik", solve)
    ActionServer(node, Reach, "reach", reach)
    pub = node.create_publisher(ControllerState, "state",
                                QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    msg = ControllerState(phase=ControllerState.REACHED, swivel=0.5, clearance=float("inf"))
    msg.goal.position.y = -0.3
    pub.publish(msg)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print("SERVER READY", flush=True)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


main()
"""


def _spin_until(executor: Any, predicate: Any, timeout: float, what: str) -> None:
    # spin_once in a loop: spin_until_future_complete adds 20-80 ms per call.
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        executor.spin_once(timeout_sec=0.05)


@pytest.mark.slow
def test_cross_process_round_trip(procs: Any, rclpy_context: Any) -> None:
    """Service, action and topic between two processes over SHM DDS; every field survives."""
    import rclpy
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile

    server = procs.start("iface_server", [sys.executable, "-c", _SERVER], ready=r"SERVER READY",
                         ready_timeout=30.0)
    node = rclpy.create_node("iface_client", context=rclpy_context)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    try:
        states: list[ControllerState] = []
        node.create_subscription(ControllerState, "state", states.append,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        client = node.create_client(SolveIK, "solve_ik")
        _spin_until(executor, client.service_is_ready, 20.0, "the SolveIK service")

        req = SolveIK.Request(arm="pa10", swivel=0.7, swivel_given=False, seed=[0.1, -0.2, 0.3],
                              all_solutions=True, timeout=0.005)
        req.target.header.frame_id = "base_link"
        req.target.pose.position.x = 0.42
        future = client.call_async(req)
        _spin_until(executor, future.done, 10.0, "the SolveIK response")
        res = future.result()
        assert res.status == SolveIK.Response.SUCCESS
        assert res.message == "arm=pa10"
        assert res.solution.header.frame_id == "base_link"
        assert list(res.solution.name) == ["j0", "j1", "j2"]
        assert list(res.solution.position) == pytest.approx([0.2, -0.4, 0.6])
        assert len(res.solutions) == 3 and list(res.solutions[2].positions) == pytest.approx([0.1, -0.2, 0.3])
        assert (res.swivel, res.position_error, res.orientation_error) == (0.7, 0.42, 0.005)

        req.swivel_given = True
        req.all_solutions = False
        future = client.call_async(req)
        _spin_until(executor, future.done, 10.0, "the second SolveIK response")
        assert future.result().status == SolveIK.Response.NO_SOLUTION_IN_LIMITS
        assert len(future.result().solutions) == 0

        _spin_until(executor, lambda: bool(states), 10.0, "the latched ControllerState")
        assert states[0].phase == ControllerState.REACHED
        assert states[0].swivel == 0.5 and math.isinf(states[0].clearance)
        assert states[0].goal.position.y == -0.3

        action = ActionClient(node, Reach, "reach")
        _spin_until(executor, action.server_is_ready, 20.0, "the Reach action server")
        feedback: list[Reach.Feedback] = []
        goal = Reach.Goal(swivel_preference=-1.2, use_swivel_preference=True, timeout=3.0)
        goal.target.pose.position.z = 0.9
        send = action.send_goal_async(goal, feedback_callback=lambda fb: feedback.append(fb.feedback))
        _spin_until(executor, send.done, 10.0, "the Reach goal acceptance")
        handle = send.result()
        assert handle.accepted
        result_future = handle.get_result_async()
        _spin_until(executor, result_future.done, 10.0, "the Reach result")
        result = result_future.result().result
        assert (result.status, result.message) == (Reach.Result.SUCCESS, "reached")
        assert result.position_error == 0.9
        # Feedback is best effort relative to the result; if it came, it must carry the goal's swivel.
        for fb in feedback:
            assert (fb.distance_to_goal, fb.swivel, fb.clearance) == (0.25, -1.2, 0.1)
        action.destroy()
    finally:
        executor.shutdown()
        node.destroy_node()
    assert server.is_running, "the server process died during the round trip"
