"""CAN driver node ``can_driver``: PowerCube (M5) modules on a CAN bus as a ROS 2 joint interface.

Wiring only. The protocol and the per-cycle work are in
:class:`redarm_ros.can.driver_core.PowerCubeArmDriver`; the cyclic thread, command
interpolation and failure handling are in :class:`redarm_ros.can.driver_loop.DriverLoop`.
This module declares parameters, converts messages, and publishes.

Interface (docs/can_driver.md has the details):

* publishes ``/joint_states`` (sensor_msgs/JointState, at ``joint_states_rate_hz``, default 100 Hz,
  0 = every cycle; at ``poll_hz`` while not running) and ``/diagnostics``
  (diagnostic_msgs/DiagnosticArray, ~2 Hz);
* subscribes ``/joint_command`` (trajectory_msgs/JointTrajectory: one or more points,
  ``time_from_start`` honoured by interpolation per cycle) and ``/joint_command_state``
  (sensor_msgs/JointState: streamed position targets; one topic cannot carry two types);
* services ``~/init`` (reset + home, then hold), ``~/halt``, ``~/recover`` and ``~/park`` (move to the
  arm's park posture; answers when it is there) (std_srvs/Trigger).

The cycle runs in a process of its own by default (:mod:`redarm_ros.can.driver_process`: real-time
priority when permitted, garbage collector kept out of the cycle), so the executor of this node
cannot delay it; ``separate_process:=false`` runs it in a thread of the node instead (python-can's
in-process ``virtual`` interface needs that). Nothing is started by the constructor: a timer first
watches the ROS graph for another driver of the same name (``duplicate_check_s``) and then starts
the cycle.

Run: ``ros2 run redarm_ros can_driver --ros-args --params-file config/can_driver.yaml
-p can.channel:=ws://127.0.0.1:PORT/`` (or ``python -m redarm_ros.nodes.can_driver``).

Units: rad, rad/s, s. Joint names and limits come from the arm model (config/arms/<arm>.yaml).
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import yaml
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

from redarm_ros.can import protocol as pc
from redarm_ros.can import realtime
from redarm_ros.can.bus import check_config as check_bus_config
from redarm_ros.can.driver_core import DEFAULT_PLAUSIBILITY_MARGIN
from redarm_ros.can.driver_loop import (
    DEFAULT_LIMIT_MARGIN,
    CycleSample,
    DriverLoop,
    LoopConfig,
    LoopSnapshot,
    LoopState,
)
from redarm_ros.can.driver_process import (
    DEFAULT_SAMPLE_RATE_HZ,
    DEFAULT_STILL_SAMPLE_RATE_HZ,
    DriverProcess,
    DriverSpec,
    build_loop,
)
from redarm_ros.errors import ConfigError, InvalidInputError, RedarmError
from redarm_ros.kinematics import load_arm_or_urdf
from redarm_ros.nodes._common import (
    NICE_PARAM,
    ParamNode,
    ParamSpec,
    non_empty_string,
    positive,
    run_node,
    urdf_arm_params,
    watch_duplicates,
)
from redarm_ros.yaml_safe import safe_load

NODE_NAME = "can_driver"
# What to do instead of a second driver of the same name: the start-up refusal and a late twin say it.
TWIN_DRIVER_REMEDY = (
    "two drivers on one CAN bus fight over the modules, whatever their names. A driver for another bus "
    "needs a name or namespace of its own (--ros-args -r __ns:=/<arm>); never run two on the same bus"
)
DIAGNOSTICS_PERIOD_S = 0.5
SERVICE_SHUTDOWN_S = 5.0  # wait at most this long (s) for service callbacks still running at shutdown
#: A module's status is WARN for this long (s) after it last sent an implausible position.
IMPLAUSIBLE_WARN_S = 10.0
FUTURE_STAMP_WARN_S = 1.0  # a trajectory stamped further ahead than this (s) is logged (clocks apart?)
#: Default of ``command_limit_tolerance_rad``: a command this far (rad) beyond a joint limit is clamped
#: to it (rounding upstream); further beyond, it is refused (a bug upstream, not a wish to go there).
DEFAULT_COMMAND_LIMIT_TOLERANCE = 0.005


def _module_ids(value: Any) -> str | None:
    if value is None:
        return None
    ids = list(value)
    if not all(isinstance(i, int) and 1 <= i <= 31 for i in ids) or len(set(ids)) != len(ids):
        return "must be distinct module ids in 1..31 (empty: 1..n)"
    return None


def _yaml_mapping(value: Any) -> str | None:
    try:
        parse_can_config(value)
    except ConfigError as exc:
        return str(exc)
    return None


class DuplicateNodeError(RuntimeError):
    """Another node of the same name runs in this ROS domain: this driver must not touch the bus."""


PARAMS = [
    ParamSpec("arm", "pa10", "Arm model (config/arms/<name>.yaml or a path): joint names, limits.",
              non_empty_string, read_only=True),
    *urdf_arm_params("Drive"),
    ParamSpec("module_ids", Parameter.Type.INTEGER_ARRAY,
              "CAN module id of each joint, in joint order (unset or empty: 1..n).", _module_ids,
              read_only=True),
    ParamSpec("rate_hz", 250.0, "Cycle rate of the FSTEP stream (Hz).", read_only=True, range=(1.0, 1000.0)),
    ParamSpec("joint_states_rate_hz", DEFAULT_SAMPLE_RATE_HZ, "Rate of /joint_states while the cycle runs "
              "(Hz, at most the cycle rate; 0 = every cycle).", read_only=True, range=(0.0, 1000.0)),
    ParamSpec("joint_states_still_rate_hz", DEFAULT_STILL_SAMPLE_RATE_HZ, "Rate of /joint_states while the "
              "cycle runs and no joint moves (Hz; back to joint_states_rate_hz on motion; 0 = no slowing).",
              read_only=True, range=(0.0, 1000.0)),
    ParamSpec("poll_hz", 10.0, "State polling rate while not running (idle/halted), Hz.", read_only=True,
              range=(0.5, 100.0)),
    ParamSpec("can.interface", "", "python-can interface (empty: CAN_INTERFACE / config files).",
              read_only=True),
    ParamSpec("can.channel", "", "python-can channel (empty: CAN_CHANNEL / config files).", read_only=True),
    ParamSpec("can.config", "", "More python-can keywords as a YAML/JSON mapping, e.g. '{bitrate: 500000}'.",
              _yaml_mapping, read_only=True),
    ParamSpec("reply_timeout_s", 0.02, "How long a cycle waits for the modules' replies (s).",
              read_only=True, range=(1e-4, 1.0)),
    ParamSpec("max_missed_replies", 5, "Consecutive missed replies after which a module counts as silent "
              "(everything is halted); with reply_timeout_s 0.02 a module may be quiet for 100 ms.",
              read_only=True, range=(1, 1000)),
    ParamSpec("hold_on_stream_stop_s", 0.5, "A /joint_command_state stream older than this (s) is "
              "dropped and the measured position held.", range=(0.001, 3600.0)),
    ParamSpec("duplicate_check_s", 1.0, "At start-up, watch the ROS graph this long (s) for another "
              "can_driver of the same name before starting the cycle, and refuse to start if there is one "
              "(two drivers on one bus would fight over the modules; 0 = no wait).", read_only=True,
              range=(0.0, 60.0)),
    ParamSpec("auto_init", False, "Run ~/init (reset + home) by itself once the bus is up.", read_only=True),
    ParamSpec("reconnect_max_s", 2.0, "Longest wait between reconnect attempts to a lost bus (s).",
              read_only=True, range=(0.01, 60.0)),
    ParamSpec("frame_id", "", "header.frame_id of /joint_states.", None),
    ParamSpec("watchdog", True, "Arm the modules' watchdog at init and recover and refresh it every cycle "
              "(a stalled or dead driver then halts the arm).", None, read_only=True),
    ParamSpec("request_timeout_s", 60.0, "Longest a ~/init, ~/halt, ~/recover or ~/park call may take (s); "
              "> 0 (~/halt is run even after its caller gave up).", positive, range=(0.001, 3600.0)),
    ParamSpec("park_tolerance_rad", 2e-3, "~/park succeeds once every measured joint is this close (rad) "
              "to the park posture.", read_only=True, range=(1e-5, 0.1)),
    ParamSpec("park_speed_scale", 0.9, "Fraction of the velocity and acceleration limits the ~/park move "
              "is planned with.", read_only=True, range=(0.01, 1.0)),
    ParamSpec("park_after_init", False, "After every successful ~/init (and auto_init), move to the park "
              "posture (homing leaves the arm at 0 rad).", read_only=True),
    ParamSpec("separate_process", True, "Run the CAN cycle in a process of its own, away from this node's "
              "executor (false: a thread of this node; needed for the in-process 'virtual' interface).",
              read_only=True),
    ParamSpec("realtime_priority", 50, "SCHED_FIFO priority of the CAN cycle (1..98; 0 = normal "
              "scheduling). Falls back to a raised nice level, with one log line, when not permitted.",
              read_only=True, range=(0, 98)),
    NICE_PARAM,
    ParamSpec("slice_ms", realtime.DEFAULT_SLICE_MS, "Time slice (ms) the CAN cycle asks for at normal "
              "scheduling (0 = the kernel's default): woken sooner, same CPU share (Linux 6.12+).",
              read_only=True, range=(0.0, 100.0)),
    ParamSpec("limit_margin_rad", DEFAULT_LIMIT_MARGIN, "How far (rad) the commanded reference stays inside "
              "each joint limit (the modules' soft limit).", read_only=True, range=(0.0, 0.1)),
    ParamSpec("command_limit_tolerance_rad", DEFAULT_COMMAND_LIMIT_TOLERANCE, "A joint command at most this "
              "far (rad) beyond a joint limit is clamped to the limit; one further beyond refuses the whole "
              "message and the arm holds.", read_only=True, range=(0.0, 0.5)),
    ParamSpec("plausibility_margin_rad", DEFAULT_PLAUSIBILITY_MARGIN, "A measured position may differ from "
              "the last one by max_vel * (elapsed + reply_timeout_s) plus this (rad), and lie at most the "
              "braking distance plus this outside the span of the last one and the targets sent since; more "
              "is a fault.",
              read_only=True, range=(0.0, 1.0)),
]


def parse_can_config(text: Any) -> dict[str, Any]:
    """The ``can.config`` parameter (YAML/JSON mapping text, empty = none) as a dict.

    Raises:
        ConfigError: not a mapping with string keys.
    """
    if text is None or (isinstance(text, str) and not text.strip()):
        return {}
    try:
        value = safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"can.config is not valid YAML: {exc}", field="can.config", value=text) from exc
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ConfigError("can.config must be a mapping like '{bitrate: 500000}'", field="can.config",
                          value=text)
    return value


def map_joint_names(names: Sequence[str], model_names: Sequence[str], *,
                    empty_means_all: bool = True) -> list[int]:
    """Model joint indices of ``names`` (empty ``names``: all joints in model order, if
    ``empty_means_all``).

    Raises:
        InvalidInputError: an unknown or repeated name, or no name when ``empty_means_all`` is False.
    """
    if not names:
        if not empty_means_all:
            raise InvalidInputError(f"no joint_names; name the joints commanded (this arm has "
                                    f"{list(model_names)})", field="joint_names", value=[])
        return list(range(len(model_names)))
    index = {n: i for i, n in enumerate(model_names)}
    unknown = [n for n in names if n not in index]
    if unknown:
        raise InvalidInputError(f"unknown joint names {unknown}; this arm has {list(model_names)}",
                                field="joint_names", value=list(names))
    if len(set(names)) != len(names):
        raise InvalidInputError("repeated joint names", field="joint_names", value=list(names))
    return [index[n] for n in names]


def _stamp(t: float) -> Time:
    """builtin_interfaces/Time of a wall-clock time ``t`` (s)."""
    sec = int(t)
    return Time(sec=sec, nanosec=int((t - sec) * 1e9))


def _duration_s(d: Any) -> float:
    return float(d.sec) + float(d.nanosec) * 1e-9


class CanDriverNode(ParamNode, node_name=NODE_NAME, params=PARAMS):
    """The ``can_driver`` node (importable for in-process tests; see the module docstring).

    The constructor only wires (parameters, topics, services, timers); the CAN cycle starts from a
    timer once the duplicate-name window has passed. :attr:`refused` holds the reason if another
    driver of the same name was seen (the cycle is then never started); ``on_refused``, if set,
    is called with it (``main()`` uses that to end the process with exit code 1).
    """

    def _setup(self, p: dict[str, Any]) -> None:
        try:
            self.arm = load_arm_or_urdf(p["arm"], p["urdf"], p["base_link"], p["tip_link"])
        except (RedarmError, OSError) as exc:
            raise ValueError(f"arm {p['urdf'] or p['arm']!r}: {exc}") from exc
        n = self.arm.n
        ids = list(p["module_ids"] or range(1, n + 1))
        if len(ids) != n:
            raise ValueError(f"module_ids has {len(ids)} ids but arm {self.arm.name} has {n} joints")
        self.module_ids = ids
        self.joint_names = list(self.arm.joint_names)
        can_kwargs = {"interface": p["can.interface"], "channel": p["can.channel"],
                      **parse_can_config(p["can.config"])}
        # A configuration that can never work ends the node here (BusConfigError is a ValueError: one line,
        # exit code 1); only transient failures (interface down, bus server restarting) are retried.
        check_bus_config(**can_kwargs)
        self._frame_id = p["frame_id"]
        self._request_timeout_s = float(p["request_timeout_s"])
        self._duplicate_check_s = float(p["duplicate_check_s"])
        self._command_limit_tolerance = float(p["command_limit_tolerance_rad"])
        cfg = LoopConfig(
            rate_hz=float(p["rate_hz"]), poll_hz=float(p["poll_hz"]),
            hold_on_stream_stop_s=float(p["hold_on_stream_stop_s"]),
            reconnect_max_s=float(p["reconnect_max_s"]), auto_init=bool(p["auto_init"]),
            limit_margin_rad=float(p["limit_margin_rad"]), slice_ms=float(p["slice_ms"]),
            park=None if self.arm.park is None else tuple(float(v) for v in self.arm.park),
            park_tolerance_rad=float(p["park_tolerance_rad"]),
            park_speed_scale=float(p["park_speed_scale"]),
            park_after_init=bool(p["park_after_init"]),
        )
        spec = DriverSpec(
            module_ids=tuple(ids), lower=tuple(self.arm.lower), upper=tuple(self.arm.upper),
            max_vel=tuple(self.arm.max_vel), max_acc=tuple(self.arm.max_acc), can_kwargs=can_kwargs,
            loop=cfg, reply_timeout_s=float(p["reply_timeout_s"]), max_missed=int(p["max_missed_replies"]),
            watchdog=bool(p["watchdog"]), plausibility_margin_rad=float(p["plausibility_margin_rad"]),
            realtime_priority=int(p["realtime_priority"]),
            sample_rate_hz=float(p["joint_states_rate_hz"]),
            still_sample_rate_hz=float(p["joint_states_still_rate_hz"]),
        )
        # Wiring: publishers, subscriptions, services, timers. Nothing runs until the start timer.
        self._js_pub = self.create_publisher(JointState, "joint_states", QoSProfile(depth=10))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self.create_subscription(JointTrajectory, "joint_command", self._on_trajectory, 10)
        self.create_subscription(JointState, "joint_command_state", self._on_joint_state_command, 10)
        # The Trigger services block for seconds (init homes, park waits for the arm) while ~/halt must
        # still be answered: they live on a hidden helper node spun by a multi-threaded executor of its
        # own, so this node's topics and timers run on the cheap single-threaded events executor (which
        # needs every callback to return at once). Their names stay ~/init etc. of this node.
        self._service_node = Node(f"_{self.get_name()}_services", namespace=self.get_namespace(),
                                  context=self.context, start_parameter_services=False)
        base = self.get_fully_qualified_name().rstrip("/")
        services = MutuallyExclusiveCallbackGroup()  # init and recover never run at once
        for action in ("init", "recover"):
            self._service_node.create_service(Trigger, f"{base}/{action}", self._trigger(action),
                                              callback_group=services)
        # halt must be served while init is homing (or recover runs): a group of its own; so must park,
        # which waits for the arm to arrive.
        for action in ("halt", "park"):
            self._service_node.create_service(Trigger, f"{base}/{action}", self._trigger(action),
                                              callback_group=MutuallyExclusiveCallbackGroup())
        self._service_executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self._service_executor.add_node(self._service_node)
        self._service_thread = threading.Thread(target=self._spin_services, name="can-driver-services",
                                                daemon=True)  # started by the first start-timer tick
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        self.add_post_set_parameters_callback(self._on_params_set)
        self._warn_times: dict[str, float] = {}
        self._warn_lock = threading.Lock()
        self.separate_process = bool(p["separate_process"])
        if self.separate_process and str(can_kwargs.get("interface") or "") == "virtual":
            self.get_logger().warning("python-can's 'virtual' interface is in-process only: running the CAN "
                                      "cycle in a thread of this node (separate_process ignored)")
            self.separate_process = False
        self.loop: DriverLoop | DriverProcess
        if self.separate_process:
            self.loop = DriverProcess(spec, on_sample=self._publish_joint_state, log=self._log)
        else:
            thread_cfg = replace(cfg, realtime_priority=int(p["realtime_priority"]))
            self.loop = build_loop(replace(spec, loop=thread_cfg), on_sample=self._publish_joint_state,
                                   log=self._log)
        self.refused: str | None = None
        self.on_refused: Callable[[str], None] | None = None
        self.started = False
        self._start_lock = threading.Lock()
        self._created = time.monotonic()
        self._start_timer = self.create_timer(0.05, self._on_start_timer)
        # A twin found after the start-up window: the younger one stops itself (see _yield_to_elder).
        watch_duplicates(self, yield_to_elder=self._duplicate_check_s > 0, on_yield=self._yield_to_elder,
                         remedy=TWIN_DRIVER_REMEDY)
        iface = can_kwargs.get("interface") or "$CAN_INTERFACE"
        chan = can_kwargs.get("channel") or "$CAN_CHANNEL"
        where = "its own process" if self.separate_process else "a thread"
        self.get_logger().info(
            f"{NODE_NAME} ready: arm {self.arm.name} ({n} joints, modules {ids}) "
            f"at {cfg.rate_hz:g} Hz on {iface}:{chan}, cycle in {where}"
        )

    # -- life cycle ---------------------------------------------------------------------------------
    def _start_when_unique(self) -> None:
        """Timer: watch the graph for ``duplicate_check_s`` (a twin appears after DDS discovery), then
        start the cycle; a twin of the same name means this driver never touches the bus. Idempotent."""
        with self._start_lock:
            if self.started or self.refused is not None:
                return
            me = (self.get_name(), self.get_namespace())
            twins = sum(1 for nm_ns in self.get_node_names_and_namespaces() if tuple(nm_ns) == me) - 1
            if twins > 0:
                self.refused = (
                    f"another node named {self.get_fully_qualified_name()} is already running in "
                    f"ROS_DOMAIN_ID {self.context.get_domain_id()}; refusing to start a second one: "
                    f"{TWIN_DRIVER_REMEDY}")
                self.get_logger().error(self.refused)
                if self.on_refused is not None:
                    self.on_refused(self.refused)
                return
            if time.monotonic() - self._created < self._duplicate_check_s:
                return
            self.loop.start()
            self.started = True

    def _yield_to_elder(self, reason: str) -> None:
        """A twin of this name that started earlier was found after the start-up window: stop this
        driver's own command stream (it sends nothing more). The elder's arm motion is left alone,
        unless this one was commanding the modules too (running: its FSTEPs reached the same modules,
        so what they did was a mix of both): then every module is halted first. Then :attr:`refused`
        is set and ``on_refused`` called (``main()`` ends the process with exit code 1)."""
        with self._start_lock:
            if self.refused is not None:
                return
            self.refused = reason
            started = self.started
        if started and self.loop.state is LoopState.RUNNING:
            ok, message = self.loop.request("halt", 5.0)
            self.get_logger().error(f"this driver was commanding the modules too: {message}" if ok
                                    else f"halting the modules before stopping failed: {message}")
        if started:
            self.loop.stop()  # sends nothing more
        self.get_logger().error("stopped this driver's CAN cycle; the elder driver keeps the bus")
        if self.on_refused is not None:
            self.on_refused(reason)

    def _on_start_timer(self) -> None:
        """The start timer: try to start; once started (or refused) the timer cancels itself. Only
        its own callback cancels it: a cancel from another thread can race the executor taking the
        timer, which rclpy turns into an error."""
        if self._service_thread.ident is None:
            self._service_thread.start()
        self._start_when_unique()
        if self.started or self.refused is not None:
            self._start_timer.cancel()

    def _wait_for_start(self, timeout: float) -> bool:
        """Block (a service callback, on the service thread) until the start timer started the cycle,
        refused it, or ``timeout`` s passed."""
        end = time.monotonic() + timeout
        while not self.started and self.refused is None and time.monotonic() < end:
            time.sleep(0.05)
        return self.started

    def _spin_services(self) -> None:
        """The service thread: serve the Trigger services until the executor is shut down."""
        try:
            self._service_executor.spin()
        except (ExternalShutdownException, RuntimeError):
            pass  # the context was shut down (Ctrl-C, SIGTERM): the node is stopping anyway

    def close(self) -> None:
        """Stop the CAN cycle and close the bus (called by main() before destroy_node); this ends the
        waits of service callbacks still running."""
        self.loop.stop()

    def destroy_node(self) -> None:
        """Stop the cycle first so nothing publishes on a destroyed node, then the service thread."""
        self.loop.stop()
        self._service_executor.shutdown(timeout_sec=SERVICE_SHUTDOWN_S)
        self._service_node.destroy_node()
        super().destroy_node()

    def _on_params_set(self, params: list[Parameter]) -> None:
        for prm in params:
            if prm.name == "hold_on_stream_stop_s":
                self.loop.commands.stream_timeout_s = float(prm.value)
            elif prm.name == "frame_id":
                self._frame_id = str(prm.value)
            elif prm.name == "request_timeout_s":
                self._request_timeout_s = float(prm.value)

    # -- logging (called from the loop thread too) ------------------------------------------------------
    def _log(self, level: int, message: str) -> None:
        logger = self.get_logger()
        if level >= logging.ERROR:
            logger.error(message)
        elif level >= logging.WARNING:
            logger.warning(message)
        elif level >= logging.INFO:
            logger.info(message)
        else:
            logger.debug(message)

    def _warn_throttled(self, key: str, message: str, period_s: float = 2.0) -> None:
        now = time.monotonic()
        with self._warn_lock:
            if now - self._warn_times.get(key, -1e9) < period_s:
                return
            self._warn_times[key] = now
        self.get_logger().warning(message)

    # -- commands -------------------------------------------------------------------------------------
    def _accepting(self) -> bool:
        ok, why = self.loop.accepting_commands()
        if not ok:
            self._warn_throttled("not-running", why)
        return ok

    def _check_limits(self, index: Sequence[int], q: np.ndarray) -> None:
        """Refuse positions ``q`` (k, m) for joints ``index`` further than ``command_limit_tolerance_rad``
        beyond a joint limit; warn (throttled) about those within it, which the loop clamps.

        Raises:
            InvalidInputError: a position beyond a limit by more than the tolerance.
        """
        lo, hi = self.arm.lower[list(index)], self.arm.upper[list(index)]
        excess = np.maximum(lo - q, q - hi)  # > 0: beyond a limit by that much (rad)
        worst = excess.max(axis=0)
        far = np.flatnonzero(worst > self._command_limit_tolerance)
        if far.size:
            what = ", ".join(
                f"{self.joint_names[index[k]]} by {worst[k]:.4f} rad (limits [{lo[k]:.4f}, {hi[k]:.4f}])"
                for k in far.tolist())
            raise InvalidInputError(
                f"positions beyond the joint limits: {what}; more than command_limit_tolerance_rad "
                f"({self._command_limit_tolerance:g} rad): holding position", field="positions")
        near = np.flatnonzero(worst > 0.0)
        if near.size:
            j = [self.joint_names[index[k]] for k in near.tolist()]
            self._warn_throttled("limits", f"command beyond joint limits for {j}: clamped to the limits")

    def _check_limits_or_hold(self, index: Sequence[int], q: np.ndarray) -> None:
        """:meth:`_check_limits`; a command refused for its limits also stops the one being followed:
        a wildly wrong target is a bug upstream, and whatever that sender commanded before is suspect."""
        try:
            self._check_limits(index, q)
        except InvalidInputError:
            self.loop.commands.clear(None)
            raise

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        if not self._accepting():
            return
        if not msg.points:
            # An empty trajectory stops the arm where it is.
            self.loop.commands.clear(None)
            self.get_logger().info("empty trajectory: holding position")
            return
        try:
            index = map_joint_names(list(msg.joint_names), self.joint_names, empty_means_all=False)
            if any(len(pt.positions) != len(index) for pt in msg.points):
                raise InvalidInputError(f"every point needs {len(index)} positions", field="points")
            points = np.array([pt.positions for pt in msg.points], dtype=float)
            times = [_duration_s(pt.time_from_start) for pt in msg.points]
            start = time.monotonic()
            stamp = msg.header.stamp
            if stamp.sec or stamp.nanosec:
                # A stamped trajectory starts at its stamp (ROS clock), mapped onto the monotonic clock.
                ahead = (stamp.sec + stamp.nanosec * 1e-9) - self.get_clock().now().nanoseconds * 1e-9
                start += ahead
                if ahead > FUTURE_STAMP_WARN_S:
                    self._warn_throttled("future-stamp", f"trajectory stamped {ahead:.1f} s ahead of this "
                                         "node's clock: it starts then (clocks not synchronised?)")
            if not np.all(np.isfinite(points)):
                raise InvalidInputError("trajectory contains NaN or inf", field="points")
            self._check_limits_or_hold(index, points)
            self.loop.commands.set_trajectory(index, times, points, start)
        except InvalidInputError as exc:
            self._warn_throttled("bad-trajectory", f"trajectory refused: {exc}", 0.5)

    def _on_joint_state_command(self, msg: JointState) -> None:
        if not self._accepting():
            return
        try:
            index = map_joint_names(list(msg.name), self.joint_names)
            q = np.array(msg.position, dtype=float)
            if q.size != len(index):
                raise InvalidInputError(f"{q.size} positions for {len(index)} joints", field="position")
            if not np.all(np.isfinite(q)):
                raise InvalidInputError("target contains NaN or inf", field="position")
            self._check_limits_or_hold(index, q[None, :])
            self.loop.commands.set_stream_target(index, q, time.monotonic())
        except InvalidInputError as exc:
            self._warn_throttled("bad-joint-state", f"joint state command refused: {exc}", 0.5)

    # -- services ---------------------------------------------------------------------------------------
    def _trigger(self, action: str) -> Any:
        def callback(_req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
            t0 = time.monotonic()
            if self._wait_for_start(self._request_timeout_s):
                left = max(0.0, self._request_timeout_s - (time.monotonic() - t0))
                ok, message = self.loop.request(action, left)
            else:
                ok, message = False, self.refused or f"{action}: the CAN cycle did not start in time"
            resp.success, resp.message = ok, message
            # One call site per severity: rclpy refuses a severity change at the same line.
            if ok:
                self.get_logger().info(f"~/{action}: {message}")
            else:
                self.get_logger().error(f"~/{action}: {message}")
            return resp

        return callback

    # -- publishing -------------------------------------------------------------------------------------
    def _publish_joint_state(self, s: CycleSample) -> None:
        if not self.context.ok():
            return  # shutting down: rclpy's context is gone before the loop thread stops
        msg = JointState()
        msg.header.stamp = _stamp(s.stamp)  # when the cycle measured, not when it got published
        msg.header.frame_id = self._frame_id
        msg.name = self.joint_names
        msg.position = s.positions.tolist()
        if s.velocities is not None:
            msg.velocity = s.velocities.tolist()
        try:
            self._js_pub.publish(msg)
        except Exception:
            if self.context.ok():
                raise
            # Ctrl-C shut the context down between the check above and the publish: nothing to report

    def _publish_diagnostics(self) -> None:
        if not self.started:
            return  # nothing to report before the cycle runs (or after a refusal)
        try:
            snap = self.loop.snapshot()
        except RedarmError as exc:  # the cycle process is gone
            self._warn_throttled("no-snapshot", f"no driver status: {exc}", 5.0)
            return
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self._loop_status(snap), *self._module_statuses(snap)]
        self._diag_pub.publish(arr)

    def _loop_status(self, snap: LoopSnapshot) -> DiagnosticStatus:
        st = DiagnosticStatus(name=f"{NODE_NAME}: loop", hardware_id=f"{self.arm.name}")
        if snap.state is LoopState.RUNNING:
            st.level = DiagnosticStatus.OK
        elif snap.state is LoopState.IDLE:
            st.level = DiagnosticStatus.WARN
        else:
            st.level = DiagnosticStatus.ERROR
        st.message = f"{snap.state.value}: {snap.reason}"
        per = snap.period
        values = {
            "state": snap.state.value,
            "reason": snap.reason,
            "command_mode": snap.command_mode.value,
            "rate_hz_target": f"{self.loop.config.rate_hz:g}",
            "rate_hz_achieved": f"{per['rate_hz']:.1f}",
            "period_error_median_ms": f"{per['period_err_median_ms']:.3f}",
            "period_error_p99_ms": f"{per['period_err_p99_ms']:.3f}",
            "period_error_max_ms": f"{per['period_err_max_ms']:.3f}",
            "cycle_busy_median_ms": f"{per['busy_median_ms']:.3f}",
            "cycle_busy_p99_ms": f"{per['busy_p99_ms']:.3f}",
            "cycles": str(snap.cycles),
            "overruns": str(snap.overruns),
            "bus_connects": str(snap.connects),
            "bus_losses": str(snap.bus_losses),
            "clamped_cycles": str(snap.clamps),
            "missing_modules": str(snap.missing_modules),
            "frames_per_s": f"{snap.frames_per_s:.0f}",
            "frames_tx": str(snap.frames_tx),
            "frames_rx": str(snap.frames_rx),
            "implausible_positions": str(snap.implausible),
            "fault": snap.fault.kind.value if snap.fault is not None else "-",
            "fault_modules": str(list(snap.fault.module_ids)) if snap.fault is not None else "[]",
            "cycle_scheduling": snap.priority or "-",
            # samples of the cycle process not published: a newer one was queued (a starved node)
            "joint_states_skipped": str(getattr(self.loop, "samples_skipped", 0)),
        }
        if snap.totals is not None:
            values["period_error_p99_total_ms"] = f"{snap.totals['period_err_p99_ms']:.3f}"
            values["period_error_max_total_ms"] = f"{snap.totals['period_err_max_ms']:.3f}"
        if snap.latency is not None:
            values["reply_latency_median_ms"] = f"{snap.latency['median_ms']:.3f}"
            values["reply_latency_p99_ms"] = f"{snap.latency['p99_ms']:.3f}"
            values["reply_latency_max_ms"] = f"{snap.latency['max_ms']:.3f}"
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        return st

    def _module_statuses(self, snap: LoopSnapshot) -> list[DiagnosticStatus]:
        out = []
        for j, mid in enumerate(self.module_ids):
            info = module_info(snap, j, mid)
            st = DiagnosticStatus(
                name=f"{NODE_NAME}: module {mid} ({self.joint_names[j]})", hardware_id=f"powercube:{mid}"
            )
            st.level, st.message = info.pop("_level"), info.pop("_message")
            st.values = [KeyValue(key=k, value=str(v)) for k, v in info.items()]
            out.append(st)
        return out


_ERROR_BITS = (pc.ActState.ERROR | pc.ActState.POWERFAULT | pc.ActState.TOW_ERROR | pc.ActState.COMM_ERROR
               | pc.ActState.CPU_OVERLOAD | pc.ActState.BEYOND_HARD | pc.ActState.BEYOND_SOFT)


def state_bit_names(bits: int) -> list[str]:
    """Names of the ACT_STATE bits set in ``bits`` (e.g. ['HOME_OK', 'MOTION'])."""
    return [f.name for f in pc.ActState if f.name and f.value & bits == f.value and f.value]


def module_info(snap: LoopSnapshot, j: int, module_id: int) -> dict[str, Any]:
    """Diagnostic values of joint ``j`` / ``module_id`` from a loop snapshot."""
    info: dict[str, Any] = {"module_id": module_id}
    level, message = DiagnosticStatus.OK, "ok"
    if module_id in snap.missing_modules:
        level, message = DiagnosticStatus.ERROR, "not found at discovery"
    if snap.positions is not None:
        info["position_rad"] = f"{snap.positions[j]:.5f}"
    if snap.last_result is not None:
        bits = int(snap.last_result.states[j])
        info["state_bits"] = f"0x{bits:08x}"
        info["state"] = " ".join(state_bit_names(bits)) or "-"
        err = bits & int(_ERROR_BITS)
        info["errors"] = " ".join(state_bit_names(err)) or "-"
        if err:
            level, message = DiagnosticStatus.ERROR, "error bits: " + info["errors"]
    if j < len(snap.module_stats):
        s = snap.module_stats[j]
        info["latency_median_ms"] = f"{s.latency_median_ms:.3f}"
        info["latency_max_ms"] = f"{s.latency_max_ms:.3f}"
        info["lost"], info["malformed"], info["late"] = s.lost, s.malformed, s.late
        info["implausible"] = s.implausible
        if s.silent and level != DiagnosticStatus.ERROR:
            level, message = DiagnosticStatus.ERROR, "not answering"
        elif s.implausible and s.implausible_age_s < IMPLAUSIBLE_WARN_S and level == DiagnosticStatus.OK:
            # a warning while it lasts, not for ever: the count stays in `implausible`
            level, message = DiagnosticStatus.WARN, (
                f"{s.implausible} implausible positions refused (the last {s.implausible_age_s:.0f} s ago)")
    if snap.state is LoopState.HALTED and snap.fault is not None and snap.fault.involves(module_id):
        level, message = DiagnosticStatus.ERROR, snap.fault.message
    info["_level"], info["_message"] = level, message
    return info


# The loop thread must get the GIL back promptly when its deadline comes while an executor
# thread runs Python; the default 5 ms switch interval would show up as period jitter.
SWITCH_INTERVAL_S = 5e-4


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``ros2 run redarm_ros can_driver``): the standard main(); exit code 1 with
    one error line if another driver of the same name runs."""
    sys.setswitchinterval(SWITCH_INTERVAL_S)

    def refuse(reason: str) -> None:
        raise DuplicateNodeError(reason)

    def make() -> CanDriverNode:
        node = CanDriverNode()
        node.on_refused = refuse
        return node

    try:
        return run_node(make, args)
    except DuplicateNodeError as exc:
        logging.basicConfig()
        logging.getLogger(NODE_NAME).error("could not start: %s", exc)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
