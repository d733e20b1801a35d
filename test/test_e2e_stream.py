"""End to end: a goal stream through the whole stack (bus server, pybullet simulator, can_driver,
controller as separate processes, started by redarm_ros.bringup). The test process is an ordinary
ROS client: from the homed (stretched) pose it sends one goal (the controller leaves the singular
pose in joint space by itself), then streams a short line at 50 Hz with header stamps, and checks the
hand (every measured /joint_states) followed it and the *simulated* tool (pybullet link state, read
from the simulator) settled on the last goal. The bounds are generous (a loaded machine); the
accuracy is measured by benchmarks/track_bench.py --stack."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from support.requires import require_ros

require_ros(stack=True)

from geometry_msgs.msg import PoseStamped  # noqa: E402
from redarm_interfaces.msg import ControllerState  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from support.stack_client import StackClient, client_in_context, stack_fixture  # noqa: E402
from support.stack_client import pose_down as pose  # noqa: E402
from trajectory_msgs.msg import JointTrajectory  # noqa: E402

from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.nodes.controller import pose_to_msg  # noqa: E402
from redarm_ros.testing import SimulatedArm  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

ARM = load_arm("pa10")


def line_path(t: float, duration: float = 2.0, length: float = 0.12) -> np.ndarray:
    """Along +y with minimum-jerk timing (at rest at both ends)."""
    x = min(max(t / duration, 0.0), 1.0)
    s = 10 * x ** 3 - 15 * x ** 4 + 6 * x ** 5
    return pose((0.65, -0.06 + length * s, 0.25))


stack = stack_fixture(arm="pa10", ready_timeout_s=60.0, ik_service=False,
                      sim_args=["--status-rate", "50"])


class Client(StackClient):
    SPIN_S = 0.005  # the stream is sent from the spin loop

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx, "e2e_stream_client")
        self.goal_pub = self.node.create_publisher(PoseStamped, "goal_pose", 50)
        self.recover = self.node.create_client(Trigger, "/can_driver/recover")
        self.states: list[ControllerState] = []
        self.node.create_subscription(ControllerState, "/controller/state", self.states.append, 200)
        self.stamped_commands = 0  # /joint_command segments with a header stamp (command_delay_s)
        self.node.create_subscription(JointTrajectory, "joint_command", self._on_cmd, 200)
        # (measured at, wall s; hand position): queued by DDS however late this process takes them
        self.hand: list[tuple[float, np.ndarray]] = []
        self.node.create_subscription(JointState, "/joint_states", self._on_joints, 1000)

    def _on_joints(self, msg: JointState) -> None:
        q = np.array([msg.position[msg.name.index(name)] for name in ARM.joint_names])
        self.hand.append((msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, ARM.fk(q)[:3, 3]))

    def _on_cmd(self, msg: JointTrajectory) -> None:
        self.stamped_commands += bool(msg.header.stamp.sec or msg.header.stamp.nanosec)

    def send(self, T: np.ndarray) -> None:
        msg = pose_to_msg(T)
        msg.header.frame_id = "base_link"
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.goal_pub.publish(msg)


@pytest.fixture(scope="module")
def client(stack: SimulatedArm, ros_env: Any) -> Iterator[Client]:
    with client_in_context(ros_env.domain_id, Client) as c:
        assert c.spin_until(lambda: len(c.states) > 0, 30.0), "no controller state"
        yield c


def sim_tool(stack: SimulatedArm) -> tuple[float, np.ndarray]:
    st = stack.status()
    return float(st.raw["wall_time"]), st.tool[:3, 3].copy()


def test_stream_followed_by_the_simulated_tool(stack: SimulatedArm, client: Client) -> None:
    start = line_path(0.0)

    def reached() -> bool:
        return any(s.phase == ControllerState.REACHED and abs(s.goal.position.y - start[1, 3]) < 1e-6
                   for s in client.states)

    # From the homed pose (arm straight up): the controller moves in joint space, then reaches.
    for attempt in range(3):
        client.send(start)
        if client.spin_until(reached, 40.0):
            break
        # A starved machine may let the module watchdog halt the arm at bring-up: recover, as an
        # operator would (retried: a recover itself can time out on a loaded machine), and say so.
        assert attempt < 2, f"start not reached: {client.states[-1]}"
        assert client.spin_until(client.recover.service_is_ready, 5.0)
        for _ in range(3):
            resp = client.call(client.recover, Trigger.Request(), 15.0)
            assert resp is not None, "~/recover did not answer"
            print(f"e2e stream set-up: ~/recover: {resp.message}")
            if resp.success:
                break
            client.spin_until(lambda: False, 1.0)
        client.spin_until(lambda: False, 1.0)  # the controller restarts from the still arm
    assert any(s.phase == ControllerState.REPLANNING and "stretched" in s.message for s in client.states)
    client.spin_until(lambda: False, 1.5)  # the elbow settles
    n = len(client.states)
    duration = 2.0
    end_y = line_path(duration, duration)[1, 3]

    def reached_end() -> bool:
        return any(s.phase == ControllerState.REACHED and abs(s.goal.position.y - end_y) < 1e-6
                   for s in client.states[n:])

    t0 = time.time()
    k = 0
    samples: list[tuple[float, np.ndarray]] = []
    while True:
        t = time.time() - t0
        if t >= k * 0.02 and k * 0.02 <= duration:
            client.send(line_path(k * 0.02, duration))
            k += 1
        w, p = sim_tool(stack)
        if not samples or w != samples[-1][0]:
            samples.append((w, p))
        # after the stream: until the controller has reached its last sample and the hand has stood
        # still for 0.5 s (a busy machine lags; the hand also stands while the controller holds for
        # joint_states that come late, which is not the end), at most 15 s
        if t > duration + 0.5:
            recent = [q for w, q in samples if w >= time.time() - 0.5]
            if t > duration + 15.0 or (reached_end() and len(recent) > 3
                                       and np.ptp(np.array(recent), axis=0).max() < 1e-4):
                break
        client.ex.spin_once(timeout_sec=0.002)
    stack.check()
    assert any(s.phase == ControllerState.TRACKING and s.goal_kind == "stream" for s in client.states[n:])
    # The hand as measured in every cycle the driver published (not the simulator polled from here: a
    # starved test process gets too few looks in 2 s) stays on the streamed path: distance to the path
    # as a curve, not to the point due at the sample's time, which a busy machine's latency shifts
    # (the timed error is a benchmark's).
    # (one callback per spin: the window's joint states may still wait in the reader's queue)
    assert client.spin_until(lambda: bool(client.hand) and client.hand[-1][0] > t0 + duration, 30.0)
    live = [(w - t0, p) for w, p in client.hand if 0.0 <= w - t0 <= duration]
    path = np.array([line_path(t, duration)[:3, 3] for t in np.linspace(0.0, duration, 2001)])
    err = np.array([np.min(np.linalg.norm(path - p, axis=1)) for _, p in live])
    assert len(err) > 20
    print(f"e2e stream: {len(err)} samples, off the path median {np.median(err) * 1e3:.1f} mm, max "
          f"{np.max(err) * 1e3:.1f} mm, {client.stamped_commands} stamped commands")
    # The driver shares the controller's clock: the segments go out stamped (played at a fixed delay).
    assert client.stamped_commands > 50
    assert np.median(err) < 0.005, f"median {np.median(err) * 1e3:.1f} mm off the path"
    final = np.linalg.norm(samples[-1][1] - line_path(duration, duration)[:3, 3])
    last = client.states[-1]
    assert final < 0.002, (f"final {final * 1e3:.2f} mm; controller {last.phase}: {last.message!r}, "
                           f"distance {last.distance_to_goal * 1e3:.2f} mm, "
                           f"goal y {last.goal.position.y:.4f}")
