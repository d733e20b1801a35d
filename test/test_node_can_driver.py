"""In-process tests of the can_driver node: emulated modules on a python-can virtual bus.

The node runs in this process (its own rclpy context, executor on a thread); a client node in the
same context calls its services, publishes commands and reads /joint_states and /diagnostics.
Cross-process behaviour over the loopback bus is in test_hil_can_driver.py.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import closing
from typing import Any

import can
import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from builtin_interfaces.msg import Duration  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from support.waits import wait_until  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from redarm_ros.can.driver_loop import LoopState  # noqa: E402
from redarm_ros.can.module_emulator import EmulatedArm, EmulatorRunner  # noqa: E402
from redarm_ros.errors import ConfigError, InvalidInputError  # noqa: E402
from redarm_ros.kinematics import load_arm  # noqa: E402
from redarm_ros.nodes._common import call_resending  # noqa: E402
from redarm_ros.nodes.can_driver import (  # noqa: E402
    CanDriverNode,
    map_joint_names,
    module_info,
    parse_can_config,
    state_bit_names,
)

ARM = load_arm("pa10")


def test_parse_can_config() -> None:
    assert parse_can_config("") == {}
    assert parse_can_config("{bitrate: 500000, fd: false}") == {"bitrate": 500000, "fd": False}
    with pytest.raises(ConfigError):
        parse_can_config("[1, 2]")
    with pytest.raises(ConfigError):
        parse_can_config("{a: [")


def test_map_joint_names() -> None:
    names = ["a", "b", "c"]
    assert map_joint_names([], names) == [0, 1, 2]
    assert map_joint_names(["c", "a"], names) == [2, 0]
    with pytest.raises(InvalidInputError, match="unknown"):
        map_joint_names(["x"], names)
    with pytest.raises(InvalidInputError, match="repeated"):
        map_joint_names(["a", "a"], names)
    with pytest.raises(InvalidInputError, match="no joint_names"):
        map_joint_names([], names, empty_means_all=False)  # a trajectory names its joints


def test_state_bit_names() -> None:
    assert state_bit_names(0x2 | 0x800) == ["HOME_OK", "MOTION"]
    assert state_bit_names(0) == []


def test_a_module_warning_clears_when_its_cause_has_passed() -> None:
    from dataclasses import replace

    from redarm_ros.can.driver_core import ModuleStatsView
    from redarm_ros.can.driver_loop import CommandMode, LoopSnapshot

    stats = ModuleStatsView(module_id=1, replies=100, lost=0, late=0, malformed=0, implausible=3,
                            silent=False, latency_median_ms=1.0, latency_max_ms=2.0, implausible_age_s=0.5)
    snap = LoopSnapshot(state=LoopState.RUNNING, reason="holding position", period={}, cycles=100,
                        overruns=0, connects=1, bus_losses=0, clamps=0, command_mode=CommandMode.HOLD,
                        missing_modules=[], module_stats=[stats], last_result=None, positions=None)
    info = module_info(snap, 0, 1)
    assert info["_level"] == DiagnosticStatus.WARN and "3 implausible" in info["_message"]
    # A minute later, nothing refused since: OK again (the count stays in the values).
    snap.module_stats = [replace(stats, implausible_age_s=60.0)]
    info = module_info(snap, 0, 1)
    assert (info["_level"], info["_message"], info["implausible"]) == (DiagnosticStatus.OK, "ok", 3)


class Rig:
    """Emulated PA10 modules + the driver node + a client node, all in one rclpy context."""

    def __init__(self, ctx: Any, overrides: dict[str, Any] | None = None) -> None:
        self.channel = f"node-{uuid.uuid4().hex[:8]}"
        self.dev_bus = can.Bus(interface="virtual", channel=self.channel)
        q0 = np.clip(np.full(ARM.n, 0.05), ARM.lower, ARM.upper)
        self.arm = EmulatedArm.kinematic(ARM.lower, ARM.upper, ARM.max_vel, ARM.max_acc, q0=q0)
        self.runner = EmulatorRunner(self.dev_bus, self.arm, tick_s=0.002).start()
        # Emulator, driver and executor share this process's GIL, so a thread can stall for tens
        # of ms: generous reply timeouts, and no module watchdog (it is exercised by the HIL tests).
        params = {"can.interface": "virtual", "can.channel": self.channel, "rate_hz": 100.0,
                  "poll_hz": 20.0, "hold_on_stream_stop_s": 0.3, "reply_timeout_s": 0.1,
                  "max_missed_replies": 5, "watchdog": False, "duplicate_check_s": 0.0,
                  "realtime_priority": 0, **(overrides or {})}
        self.node = CanDriverNode(
            context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]
        )
        self.client = rclpy.create_node("can_driver_test_client", context=ctx)
        self.states: list[JointState] = []
        self.diags: list[DiagnosticArray] = []
        self.client.create_subscription(JointState, "/joint_states", self.states.append, 50)
        self.client.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        self.traj_pub = self.client.create_publisher(JointTrajectory, "/joint_command", 10)
        self.js_pub = self.client.create_publisher(JointState, "/joint_command_state", 10)
        self.executor = SingleThreadedExecutor(context=ctx)
        self.executor.add_node(self.node)
        self.executor.add_node(self.client)
        self._spin = threading.Thread(target=self.executor.spin, daemon=True)
        self._spin.start()

    def call(self, action: str, timeout: float = 30.0) -> Trigger.Response:
        cli = self.client.create_client(Trigger, f"/can_driver/{action}")
        assert cli.wait_for_service(timeout_sec=5.0)
        resp = call_resending(cli, Trigger.Request(), wait_until, timeout)
        self.client.destroy_client(cli)
        assert resp is not None, f"~/{action} did not answer"
        return resp

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self._spin.join(2.0)
        self.node.destroy_node()
        self.client.destroy_node()
        self.runner.stop()
        self.dev_bus.shutdown()


def wait_for(pred: Callable[[], bool], timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


@pytest.fixture
def rig(rclpy_context: Any) -> Iterator[Rig]:
    with closing(Rig(rclpy_context)) as r:
        yield r


def trajectory(names: list[str], points: list[list[float]], times: list[float]) -> JointTrajectory:
    msg = JointTrajectory()
    msg.joint_names = names
    for q, t in zip(points, times, strict=True):
        sec = int(t)
        msg.points.append(JointTrajectoryPoint(
            positions=[float(v) for v in q], time_from_start=Duration(sec=sec, nanosec=int((t - sec) * 1e9))))
    return msg


def test_node_init_follow_trajectory_and_diagnostics(rig: Rig) -> None:
    assert wait_for(lambda: rig.node.loop.state is LoopState.IDLE)
    # Idle: joint states are polled and published with the model's names.
    assert wait_for(lambda: len(rig.states) > 0)
    assert list(rig.states[-1].name) == ARM.joint_names
    # A command before init is ignored.
    rig.traj_pub.publish(trajectory(ARM.joint_names[:1], [[0.5]], [0.1]))
    time.sleep(0.3)
    np.testing.assert_allclose(rig.arm.positions()[0], 0.05, atol=1e-6)

    resp = rig.call("init")
    assert resp.success, resp.message
    np.testing.assert_allclose(rig.arm.positions(), 0.0, atol=1e-3)

    names = [ARM.joint_names[1], ARM.joint_names[3]]
    # Gentle (0.2 rad/s): the in-process kinematic plant overshoots when cycles jitter.
    rig.traj_pub.publish(trajectory(names, [[0.15, -0.2], [0.3, -0.4]], [0.75, 1.5]))
    goal = np.zeros(ARM.n)
    goal[1], goal[3] = 0.3, -0.4
    assert wait_for(lambda: np.allclose(rig.arm.positions(), goal, atol=3e-3), timeout=10), (
        rig.arm.positions(), rig.node.loop.snapshot().command_mode)
    # /joint_states carries each cycle's measured positions (delivered a little later).
    assert wait_for(lambda: np.allclose(rig.states[-1].position, goal, atol=5e-3), timeout=5)
    assert len(rig.states[-1].velocity) == ARM.n

    assert wait_for(lambda: any(s.name == "can_driver: loop" and s.level == DiagnosticStatus.OK
                                for d in rig.diags[-2:] for s in d.status), timeout=3)
    last = rig.diags[-1]
    loop_st = next(s for s in last.status if s.name == "can_driver: loop")
    values = {kv.key: kv.value for kv in loop_st.values}
    assert values["state"] == "running"
    assert float(values["rate_hz_achieved"]) > 0  # speed itself is measured in benchmarks/
    mods = [s for s in last.status if s.name.startswith("can_driver: module")]
    assert len(mods) == ARM.n
    mv = {kv.key: kv.value for kv in mods[0].values}
    assert "HOME_OK" in mv["state"] and mv["errors"] == "-"
    assert {"latency_median_ms", "lost", "malformed"} <= set(mv)


def test_node_stream_command_limits_and_bad_input(rig: Rig) -> None:
    assert wait_for(lambda: rig.node.loop.state is LoopState.IDLE)
    assert rig.call("init").success
    # Unknown joint name: refused, nothing moves, the node lives on.
    rig.traj_pub.publish(trajectory(["nope"], [[1.0]], [0.1]))
    bad = JointState(name=[ARM.joint_names[0]], position=[float("nan")])
    rig.js_pub.publish(bad)
    time.sleep(0.3)
    np.testing.assert_allclose(rig.arm.positions(), 0.0, atol=1e-3)
    # Streamed target beyond joint 2's limit (+-91 deg) by less than command_limit_tolerance_rad:
    # clamped at the limit, never beyond.
    j = 1
    # Generous deadline: the loop ends as soon as the joint arrives; a loaded CI machine is slower.
    end = time.monotonic() + 15.0
    while time.monotonic() < end and rig.arm.positions()[j] < ARM.upper[j] - 1e-3:
        rig.js_pub.publish(JointState(name=[ARM.joint_names[j]], position=[ARM.upper[j] + 0.004]))
        time.sleep(0.02)
        assert rig.arm.positions()[j] <= ARM.upper[j] + 1e-6
    assert rig.arm.positions()[j] == pytest.approx(ARM.upper[j], abs=2e-3)
    assert rig.arm.positions()[j] <= ARM.upper[j] + 1e-6
    assert rig.node.loop.snapshot().clamps > 0


def test_node_refuses_nameless_and_far_beyond_limit_commands_and_holds(rig: Rig) -> None:
    assert wait_for(lambda: rig.node.loop.state is LoopState.IDLE)
    assert rig.call("init").success
    warnings: list[str] = []
    warn = rig.node._warn_throttled
    rig.node._warn_throttled = lambda key, message, period_s=2.0: (  # type: ignore[method-assign]
        warnings.append(message), warn(key, message, period_s))
    # No joint_names: refused with a reason (it used to move every joint).
    rig.traj_pub.publish(trajectory([], [[0.3] * ARM.n], [0.5]))
    assert wait_for(lambda: any("no joint_names" in w for w in warnings), 3), warnings
    # A move under way, then a command 10 rad beyond every limit: refused, and the arm holds.
    goal = np.zeros(ARM.n)
    goal[0] = 0.6
    rig.traj_pub.publish(trajectory(ARM.joint_names, [goal], [3.0]))
    assert wait_for(lambda: rig.arm.positions()[0] > 0.1, 5)
    rig.traj_pub.publish(trajectory(ARM.joint_names, [[10.0] * ARM.n], [1.0]))
    assert wait_for(lambda: any("beyond the joint limits" in w for w in warnings), 3), warnings
    rig.js_pub.publish(JointState(name=[ARM.joint_names[6]], position=[10.0]))
    assert wait_for(lambda: any("joint state command refused" in w and "beyond" in w for w in warnings), 3)

    def settled() -> bool:  # the modules lag the reference: on a late cycle they brake past the hold point
        q0 = rig.arm.positions()
        time.sleep(0.2)
        return bool(np.abs(np.subtract(rig.arm.positions(), q0)).max() < 1e-5)

    assert wait_for(settled, 10)
    q = rig.arm.positions()
    time.sleep(0.5)
    np.testing.assert_allclose(rig.arm.positions(), q, atol=1e-4)  # at rest: held, not moving on
    assert q[0] < 0.5  # stopped short of the earlier goal: the refusal held the arm
    np.testing.assert_allclose(q[1:], 0.0, atol=1e-3)  # nothing went towards the 10 rad
    assert rig.node.loop.state is LoopState.RUNNING


def test_node_halt_and_recover_services(rig: Rig) -> None:
    assert wait_for(lambda: rig.node.loop.state is LoopState.IDLE)
    assert rig.call("init").success
    r = rig.call("halt")
    assert r.success and "halted" in r.message
    assert rig.node.loop.state is LoopState.HALTED
    r = rig.call("recover")
    assert r.success, r.message
    assert rig.node.loop.state is LoopState.RUNNING


def test_node_parameters_validated(rclpy_context: Any) -> None:
    # A refused node stays in this context's graph until shutdown: skip the duplicate-name check.
    no_dup = Parameter("duplicate_check_s", value=0.0)
    with pytest.raises(ValueError, match="rate_hz"):
        CanDriverNode(context=rclpy_context, parameter_overrides=[Parameter("rate_hz", value=-5.0), no_dup])
    with pytest.raises(ValueError, match="module_ids"):
        CanDriverNode(context=rclpy_context,
                      parameter_overrides=[Parameter("module_ids", value=[1, 2]), no_dup])
    with pytest.raises(ValueError, match="arm"):
        CanDriverNode(context=rclpy_context,
                      parameter_overrides=[Parameter("arm", value="no_such_arm"), no_dup])
    # 0 s would make every service, ~/halt included, give up before it could run.
    with pytest.raises(ValueError, match="request_timeout_s"):
        CanDriverNode(context=rclpy_context,
                      parameter_overrides=[Parameter("request_timeout_s", value=0.0), no_dup])


def test_node_runtime_parameter_updates(rig: Rig) -> None:
    res = rig.node.set_parameters([Parameter("hold_on_stream_stop_s", value=-1.0)])
    assert not res[0].successful
    res = rig.node.set_parameters([Parameter("hold_on_stream_stop_s", value=1.5)])
    assert res[0].successful
    assert rig.node.loop.commands.stream_timeout_s == 1.5
    res = rig.node.set_parameters([Parameter("rate_hz", value=100.0)])
    assert not res[0].successful  # read-only: takes effect at start only
    res = rig.node.set_parameters([Parameter("request_timeout_s", value=0.0)])
    assert not res[0].successful and "request_timeout_s" in res[0].reason
    res = rig.node.set_parameters([Parameter("request_timeout_s", value=0.5)])
    assert res[0].successful


def test_second_driver_with_the_same_name_refuses_to_start(rig: Rig, rclpy_context: Any) -> None:
    """Two drivers on one bus would fight over the modules: the second one must never start its cycle."""
    assert wait_for(lambda: rig.node.started)
    second = CanDriverNode(
        context=rclpy_context,
        parameter_overrides=[
            Parameter("can.interface", value="virtual"),
            Parameter("can.channel", value=rig.channel),
            Parameter("duplicate_check_s", value=1.0),
            Parameter("realtime_priority", value=0),
        ],
    )
    refusals: list[str] = []
    second.on_refused = refusals.append
    rig.executor.add_node(second)
    try:
        assert wait_for(lambda: bool(refusals), timeout=10.0)  # the callback runs after `refused` is set
        assert "already running" in refusals[0] and refusals == [second.refused]
        # No advice to rename it and run both: under another name it would still share the bus.
        assert "to run both" not in refusals[0] and "never run two on the same bus" in refusals[0]
        time.sleep(1.2)  # past its duplicate window: still not started, the bus never opened
        assert not second.started and second.loop.bus is None
    finally:
        rig.executor.remove_node(second)
        second.destroy_node()


def _announce_an_elder_twin(rig: Rig) -> None:
    """What an elder can_driver of the same name announces on ~/_instance (found late: discovery)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = rig.client.create_publisher(String, "/can_driver/_instance", latched)
    pub.publish(String(data=f"1 {uuid.uuid4().hex} 4242 1"))  # started at 1 ns: the elder


@pytest.mark.parametrize("commanding", [False, True])
def test_a_twin_found_late_stops_the_younger_driver_safely(rclpy_context: Any, commanding: bool) -> None:
    with closing(Rig(rclpy_context, {"duplicate_check_s": 0.1})) as rig:
        refusals: list[str] = []
        rig.node.on_refused = refusals.append
        assert wait_for(lambda: rig.node.loop.state is LoopState.IDLE, 10)
        if commanding:
            assert rig.call("init").success
        _announce_an_elder_twin(rig)
        assert wait_for(lambda: bool(refusals), 10), "the younger driver did not stop"
        assert "already running" in refusals[0]
        # the driver's own advice, as at start-up: never two drivers on one bus (not "rename it")
        assert "never run two on the same bus" in refusals[0] and "second one)" not in refusals[0]
        assert rig.node.loop.state is LoopState.STOPPED  # its command stream ended
        halted = [bool(rig.arm[i].state() & 0x4) for i in range(1, ARM.n + 1)]
        # The elder's arm is halted only if this one was commanding the modules too.
        assert halted == [commanding] * ARM.n
        sent = {i: rig.arm[i].requests for i in range(1, ARM.n + 1)}
        time.sleep(0.3)
        assert {i: rig.arm[i].requests for i in range(1, ARM.n + 1)} == sent  # sends nothing more


def test_constructor_starts_nothing_and_declares_ranges(rclpy_context: Any) -> None:
    # New Thread objects only: a thread of an earlier test may end meanwhile (and its ident be reused).
    before = set(threading.enumerate())
    node = CanDriverNode(context=rclpy_context, parameter_overrides=[
        Parameter("can.interface", value="virtual"), Parameter("can.channel", value="unused"),
        Parameter("duplicate_check_s", value=0.0)])
    try:
        assert set(threading.enumerate()) - before == set()  # no thread started by __init__
        assert not node.started and node.loop.bus is None
        rate = node.describe_parameter("rate_hz").floating_point_range[0]
        assert (rate.from_value, rate.to_value) == (1.0, 1000.0)
        prio = node.describe_parameter("realtime_priority").integer_range[0]
        assert (prio.from_value, prio.to_value) == (0, 98)
        res = node.set_parameters([Parameter("hold_on_stream_stop_s", value=1e6)])
        assert not res[0].successful  # beyond the declared range
    finally:
        node.destroy_node()


def test_halt_has_a_callback_group_of_its_own(rclpy_context: Any) -> None:
    # ~/init blocks its callback while homing: a ~/halt in the same mutually exclusive group would
    # wait for it (on the services' multi-threaded executor); on the node itself, run by the
    # single-threaded events executor, they would block its topics and each other.
    node = CanDriverNode(context=rclpy_context, parameter_overrides=[
        Parameter("can.interface", value="virtual"), Parameter("can.channel", value="unused"),
        Parameter("duplicate_check_s", value=0.0)])
    try:
        assert not [s for s in node.services if "Trigger" in str(s.srv_type)]
        groups = {s.srv_name: s.callback_group for s in node._service_node.services}
        assert {f"/can_driver/{a}" for a in ("init", "halt", "recover", "park")} <= set(groups)
        groups = {name.rsplit("/", 1)[-1]: g for name, g in groups.items()}
        others = [groups[a] for a in ("init", "recover", "park")]
        assert all(groups["halt"] is not g for g in others)
    finally:
        node.destroy_node()


def test_halt_is_answered_while_init_blocks_on_the_events_executor(rclpy_context: Any) -> None:
    # The node runs on the single-threaded events executor (as main() runs it): a blocking ~/init
    # must neither hold up ~/halt nor the node's own callbacks.
    from rclpy.experimental import EventsExecutor  # noqa: PLC0415 - the executor main() picks

    node = CanDriverNode(context=rclpy_context, parameter_overrides=[
        Parameter("can.interface", value="virtual"), Parameter("can.channel", value="unused"),
        Parameter("duplicate_check_s", value=0.0)])
    release, asked = threading.Event(), []

    def request(action: str, timeout: float = 60.0) -> tuple[bool, str]:
        asked.append(action)
        if action == "init":
            release.wait(10.0)
        return True, f"{action} done"

    node.loop.request = request  # type: ignore[method-assign]
    client_node = rclpy.create_node(f"halt_client_{uuid.uuid4().hex[:8]}", context=rclpy_context)
    executor = EventsExecutor(context=rclpy_context)
    executor.add_node(node)
    client_exec = SingleThreadedExecutor(context=rclpy_context)
    client_exec.add_node(client_node)

    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    try:
        init_cli = client_node.create_client(Trigger, "/can_driver/init")
        halt_cli = client_node.create_client(Trigger, "/can_driver/halt")
        assert init_cli.wait_for_service(10.0) and halt_cli.wait_for_service(10.0)
        init_future = init_cli.call_async(Trigger.Request())
        assert wait_until(lambda: asked == ["init"], 10.0)
        halt_future = halt_cli.call_async(Trigger.Request())
        client_exec.spin_until_future_complete(halt_future, timeout_sec=10.0)
        assert halt_future.done() and halt_future.result().success
        assert not init_future.done()  # init still blocked: halt did not wait for it
        release.set()
        client_exec.spin_until_future_complete(init_future, timeout_sec=10.0)
        assert init_future.result().message == "init done"
    finally:
        release.set()
        stop.set()
        spinner.join(5.0)
        client_node.destroy_node()
        node.destroy_node()
