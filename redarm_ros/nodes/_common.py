"""Small rclpy helpers shared by the redarm_ros nodes: the standard ``main()`` and parameter plumbing.

Parameters are described once as :class:`ParamSpec` (name, default, description,
validator); :func:`declare_params` declares them with descriptors and installs
one on-set callback that runs the validators, so a bad ``ros2 param set`` (or a
bad YAML value at start-up) is refused with a reason instead of reaching the
node's logic.
"""

from __future__ import annotations

import logging
import math
import os
import re
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import Pose
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from redarm_ros.errors import InvalidInputError
from redarm_ros.kinematics.quaternion import pose_to_matrix

_LOG = logging.getLogger(__name__)

# A validator returns None when the value is fine, else the reason it is refused.
Validator = Callable[[Any], str | None]


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: ``name``, ``default`` (fixes the type), ``description``, optional ``validate``.

    ``read_only`` parameters can only be set at start-up (overrides / YAML). ``range`` (lo, hi),
    for a float or integer parameter, is declared in the descriptor (``ros2 param describe`` shows
    it, rclpy enforces it) and checked by the validator too.
    """

    name: str
    default: Any
    description: str
    validate: Validator | None = None
    read_only: bool = False
    range: tuple[float, float] | None = None


#: The ``nice`` parameter of the nodes on the control path (controller, can_driver): ahead of ordinary
#: work on the machine, behind the real-time chain (cycle, simulator, bus server at SCHED_FIFO).
NICE_PARAM = ParamSpec(
    "nice", -10, "Nice level of this node's process (-20..0; 0 = leave it): ordinary work beside the stack "
    "must not starve the control path. Falls back to the best level permitted, with one log line.",
    read_only=True, range=(-20, 0))


#: The ``realtime_priority`` parameter of a node whose whole process is on the control path (the
#: controller): SCHED_FIFO below the CAN chain (cycle, simulator, bus server at 50). On two cores the
#: stack itself fills the machine, and at nice -10 the controller still lost a fifth to half of its
#: 100 Hz steps to the other processes (more with a thousand obstacles); at SCHED_FIFO it keeps them.
PROCESS_RT_PARAM = ParamSpec(
    "realtime_priority", 20, "SCHED_FIFO priority of this node's whole process (1..49, below the CAN "
    "chain's 50; 0 = none, nice only). Falls back to the nice parameter, with one log line, when not "
    "permitted.", read_only=True, range=(0, 49))


def apply_scheduling(node: Node, level: int, fifo_priority: int = 0) -> None:
    """Run ``node``'s process at SCHED_FIFO ``fifo_priority`` if asked (see :data:`PROCESS_RT_PARAM`),
    else (or when refused) at nice ``level`` (see :data:`NICE_PARAM`), and log the outcome once.
    :func:`run_node` calls it for a node that declares ``nice``, before the node's timers start its
    threads and child processes (they inherit the setting); a node built inside another program leaves
    that program's scheduling alone."""
    from redarm_ros.can import realtime  # (a shell may use the driver's scheduling helper)

    who = f"{node.get_name()} node"
    refused = ""
    if fifo_priority > 0:
        rt = realtime.raise_process_priority(fifo_priority, who=who)
        if rt.realtime:
            node.get_logger().info(rt.message)
            return
        refused = f"{rt.message}; "
    prio = realtime.raise_nice(level, who=who)
    if refused:
        node.get_logger().warning(f"{refused}falling back: {prio.message}")
        return
    if prio.policy is realtime.Policy.NICE or level >= 0:
        node.get_logger().info(prio.message)
    else:
        node.get_logger().warning(prio.message)


def declare_params(node: Node, specs: Sequence[ParamSpec]) -> dict[str, Any]:
    """Declare ``specs`` on ``node``, validate start-up values, install the on-set validator.

    Returns name -> value as declared (after overrides from YAML / the command line).

    Raises:
        ValueError: a start-up value (override) fails its validator.
    """
    by_name = {s.name: s for s in specs}

    def on_set(params: list[Parameter]) -> SetParametersResult:
        for p in params:
            spec = by_name.get(p.name)
            if spec is None:
                continue
            value = p.value
            if _is_float_param(spec):
                # `-p rate_hz:=250` arrives as an integer; accept any number for a float parameter.
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    return SetParametersResult(successful=False, reason=f"{p.name}: must be a number")
                value = float(value)
            reason = spec.validate(value) if spec.validate is not None else None
            if reason is None and spec.range is not None:
                reason = in_range(*spec.range)(value)
            if reason is not None:
                return SetParametersResult(successful=False, reason=f"{p.name}: {reason}")
        return SetParametersResult(successful=True)

    # Installed before declaring so start-up overrides are validated too.
    node.add_on_set_parameters_callback(on_set)
    values: dict[str, Any] = {}
    for s in specs:
        desc = ParameterDescriptor(description=s.description, read_only=s.read_only,
                                   dynamic_typing=_is_float_param(s))
        if s.range is not None and _is_float_param(s):
            desc.floating_point_range = [FloatingPointRange(from_value=float(s.range[0]),
                                                            to_value=float(s.range[1]), step=0.0)]
        elif s.range is not None and isinstance(s.default, int) and not isinstance(s.default, bool):
            desc.integer_range = [IntegerRange(from_value=int(s.range[0]), to_value=int(s.range[1]), step=1)]
        try:
            value = node.declare_parameter(s.name, s.default, desc).value
        except (rclpy.exceptions.InvalidParameterValueException,
                rclpy.exceptions.InvalidParameterTypeException) as exc:
            raise ValueError(f"parameter {s.name}: {exc}") from exc
        values[s.name] = float(value) if _is_float_param(s) and value is not None else value
    return values


def _is_float_param(spec: ParamSpec) -> bool:
    return isinstance(spec.default, float)


def param_values(node: Node, names: Iterable[str]) -> dict[str, Any]:
    """Current values of the named parameters (integers given for float parameters stay integers)."""
    return {n: node.get_parameter(n).value for n in names}


# -- reusable validators -----------------------------------------------------------------------------
def positive(value: Any) -> str | None:
    """Validator: a number > 0."""
    return None if isinstance(value, (int, float)) and value > 0 else "must be > 0"


def non_negative(value: Any) -> str | None:
    """Validator: a number >= 0."""
    return None if isinstance(value, (int, float)) and value >= 0 else "must be >= 0"


def non_empty_string(value: Any) -> str | None:
    """Validator: a string that is not empty (frame ids, names)."""
    return None if isinstance(value, str) and value else "must be a non-empty string"


def any_string(value: Any) -> str | None:
    """Validator: a string (empty allowed: "not given")."""
    return None if isinstance(value, str) else "must be a string"


def urdf_arm_params(use: str) -> list[ParamSpec]:
    """The ``urdf``, ``base_link``, ``tip_link`` parameters of a node that takes its arm from a URDF file
    instead of ``arm`` (:func:`redarm_ros.kinematics.load_arm_or_urdf`); ``use``: what the node does with
    it (e.g. "Run")."""
    return [
        ParamSpec("urdf", "", f"{use} the arm of this URDF file instead of `arm` (the chain from "
                  "`base_link` to `tip_link`; docs/urdf.md).", any_string, read_only=True),
        ParamSpec("base_link", "", "The URDF arm's base link.", any_string, read_only=True),
        ParamSpec("tip_link", "", "The URDF arm's tip link.", any_string, read_only=True),
    ]


def in_range(lo: float, hi: float) -> Validator:
    """Validator factory: a number in [lo, hi]."""

    def check(value: Any) -> str | None:
        ok = isinstance(value, (int, float)) and lo <= value <= hi
        return None if ok else f"must be in [{lo}, {hi}]"

    return check


#: How long (s) main() waits at shutdown for callbacks still running in executor threads before it
#: destroys the node.
CALLBACK_DRAIN_S = 5.0


def _drain_callbacks(executor: SingleThreadedExecutor | MultiThreadedExecutor, timeout_s: float) -> bool:
    """Stop ``executor`` and wait up to ``timeout_s`` for callbacks still running in its threads.

    ``Executor.shutdown`` of this rclpy does not wait for them, and the multi-threaded executor's
    worker pool goes on running the callbacks it took. Destroying the node under a callback that is
    still publishing crashes inside rcl (seen as a SIGSEGV at Ctrl-C on a slow one-CPU machine).
    Returns False if some callback was still running after ``timeout_s``.
    """
    executor.shutdown(timeout_sec=0.0)
    pool = getattr(executor, "_executor", None)  # the MultiThreadedExecutor's ThreadPoolExecutor
    if not isinstance(pool, ThreadPoolExecutor):
        return True
    waiter = threading.Thread(target=pool.shutdown, kwargs={"wait": True, "cancel_futures": True},
                              name="drain-callbacks", daemon=True)
    waiter.start()
    waiter.join(timeout_s)
    return not waiter.is_alive()


#: Signals that stop a node: Ctrl-C, and SIGTERM as ``docker stop``, systemd or ``kill`` send it.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: While spinning, :func:`run_node` looks at least this often (s) whether a stop signal came: a
#: KeyboardInterrupt raised where it is swallowed (a ``__del__``, a library's catch-all) is not lost.
STOP_POLL_S = 0.25


class _StopSignals:
    """Python's handler of SIGINT and SIGTERM for a node process: either stops the spin (the same
    clean path for both), and once teardown has begun a repeated one is noted, not raised.

    The handler raises KeyboardInterrupt (so a wait in the main thread ends at once) and also records
    the stop in :attr:`requested`, which :func:`run_node` checks before it spins and while it spins:
    a signal that came while the node was being built, inside code that swallowed the
    KeyboardInterrupt, is still acted on. A second signal (a supervisor's staged stop sends one after
    its grace period) raising KeyboardInterrupt inside the teardown would abandon it and end the
    process by the signal (exit code -2) instead of with its own code. SIGKILL remains the way to
    end it at once.
    """

    def __init__(self) -> None:
        self.tearing_down = False
        self.requested = False
        self._count = 0

    @classmethod
    def install(cls) -> _StopSignals:
        """Install the handler (only the main thread can); it stays until the process ends."""
        guard = cls()
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                signal.signal(sig, guard._on_signal)
        return guard

    def _on_signal(self, signum: int, _frame: object) -> None:
        self._count += 1
        self.requested = True
        if not self.tearing_down:
            raise KeyboardInterrupt
        # The first one can land here too: rclpy's own handler may have ended the spin before it ran.
        if self._count == 2:
            _LOG.warning("signal %d during shutdown: already stopping (SIGKILL ends the process at once)",
                         signum)


# -- parameter files (--params-file) -----------------------------------------------------------------
def params_file_paths(args: Sequence[str]) -> list[str]:
    """The ``--params-file`` paths given in the ``--ros-args`` sections of ``args``."""
    paths: list[str] = []
    in_ros = False
    items = iter(args)
    for a in items:
        if a == "--ros-args":
            in_ros = True
        elif a == "--":
            in_ros = False
        elif in_ros and a == "--params-file":
            paths.append(next(items, ""))
    return paths


def read_params_file(path: str) -> dict[str, Any]:
    """A ROS 2 parameter file as ``{node key: {"ros__parameters": ...}}``.

    Raises:
        ValueError: the file cannot be read, is not YAML (the message names the file, the line and the
            column), or is not a mapping of node keys.
    """
    import yaml  # (only the nodes' start-up needs it)

    from redarm_ros.yaml_safe import safe_load  # noqa: PLC0415

    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise ValueError(f"parameter file {path}: {exc.strerror or exc}") from exc
    try:
        doc = safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "YAML"
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ValueError(f"parameter file {path}, {where}: {problem} (not valid YAML)") from exc
    if doc is None:
        return {}
    if not isinstance(doc, dict) or not all(isinstance(k, str) for k in doc):
        raise ValueError(f"parameter file {path}: must map node names (e.g. /**: or /my_node:) to "
                         "ros__parameters")
    return doc


def node_key_matches(key: str, fully_qualified_name: str) -> bool:
    """True if the node key ``key`` of a parameter file applies to the node ``fully_qualified_name``.

    The rules of rcl/rclpy: a key is a node's full name, ``/`` prefixed or not (``can_driver`` is
    ``/can_driver``); ``*`` stands for one name token, ``**`` for any number of them, so ``/**`` is every
    node and ``/**/can_driver`` a ``can_driver`` in any namespace.
    """
    key = key if key.startswith("/") else "/" + key
    parts = [re.escape(tok) for tok in key.strip("/").split("/")]
    pattern = ""
    for tok in parts:
        if tok == re.escape("**"):
            pattern += "(/[^/]+)*"
        elif tok == re.escape("*"):
            pattern += "/[^/]+"
        else:
            pattern += "/" + tok.replace(re.escape("*"), "[^/]*")
    return re.fullmatch(pattern or "/", fully_qualified_name) is not None


def check_params_files(args: Sequence[str]) -> dict[str, list[str]]:
    """Read every ``--params-file`` of ``args`` before rclpy does (its own error is a traceback without
    the line); path -> the file's node keys.

    Raises:
        ValueError: one of the files is unreadable or not valid YAML (see :func:`read_params_file`).
    """
    return {path: list(read_params_file(path)) for path in params_file_paths(args)}


def warn_unmatched_params_files(node: Node, files: dict[str, list[str]]) -> list[str]:
    """Warn for each parameter file of which no node key applies to ``node`` (a misspelt ``/can_drvier:``,
    or ``/can_driver:`` given to a node under a namespace): its parameters would vanish without a word.
    Returns the paths warned about."""
    fqn = node.get_fully_qualified_name()
    unmatched = [path for path, keys in files.items()
                 if keys and not any(node_key_matches(k, fqn) for k in keys)]
    for path in unmatched:
        node.get_logger().warning(
            f"parameter file {path} has no section for this node {fqn} (its node keys: "
            f"{', '.join(files[path])}): none of its values apply. Use `/**:` (every node the file is given "
            f"to), `/**/{node.get_name()}:` or `{fqn}:`"
        )
    return unmatched


def single_threaded_executor() -> Any:
    """rclpy's events executor where it exists, else the single-threaded one. The events executor
    runs the wait and the dispatch in C++: measured, 250 Hz of joint states cost the recorder about 6 %
    of a core with it, 14 % with the single-threaded executor, and a controller following a goal stream
    (joint states, goals, its timer, its publishers) pays the same per-callback overhead."""
    try:
        from rclpy.experimental import EventsExecutor  # noqa: PLC0415 - optional (rclpy >= 7.1)
    except ImportError:
        return SingleThreadedExecutor()
    return EventsExecutor()


def _spin_until_stopped(executor: SingleThreadedExecutor | MultiThreadedExecutor, node: Node,
                        stop_signals: _StopSignals) -> None:
    """``executor.spin()``, that also ends within :data:`STOP_POLL_S` of a stop signal whose
    KeyboardInterrupt was swallowed."""
    context = node.context
    while context.ok() and not stop_signals.requested:
        executor.spin_once(timeout_sec=STOP_POLL_S)


def run_node(
    make_node: Callable[[], Node],
    args: Sequence[str] | None = None,
    *,
    multithreaded: bool = False,
) -> int:
    """The standard main(): init, build the node, spin, stop cleanly on Ctrl-C, SIGTERM or external
    shutdown (the same path for all, at any moment: see :class:`_StopSignals`).

    ``make_node`` is called after ``rclpy.init``. If the node has a ``close()`` method it is called
    as soon as spinning ends (to stop worker threads and end waits inside callbacks); then the
    callbacks still running are waited for (:data:`CALLBACK_DRAIN_S`) before ``destroy_node()``.
    Returns the process exit code (0 on a normal, Ctrl-C or SIGTERM stop, 1 if the node could not be
    built).
    """
    stop_signals = _StopSignals.install()
    argv = list(args) if args is not None else list(sys.argv)
    try:
        files = check_params_files(argv)
        # Without rclpy's own handlers: they shut the context down at the signal, before the teardown
        # (whose log lines then failed to reach /rosout: "Failed to publish log message to rosout"; a
        # node still being built failed with "context is not valid"). The spin wakes every STOP_POLL_S.
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - a bad parameter file or argument: one line, exit code 1
        logging.basicConfig()
        _LOG.error("could not start: %s", exc)
        return 1
    node: Node | None = None
    executor: SingleThreadedExecutor | MultiThreadedExecutor | None = None
    code = 0
    try:
        try:
            node = make_node()
        except (ValueError, RuntimeError, OSError) as exc:
            # Construction failures (bad parameters, unknown arm) end the process with one clear line.
            logging.basicConfig()
            _LOG.error("could not start: %s", exc)
            return 1
        warn_unmatched_params_files(node, files)
        if node.has_parameter(NICE_PARAM.name):  # a process-wide setting: only where the node owns it
            fifo = int(node.get_parameter(PROCESS_RT_PARAM.name).value) \
                if getattr(node, "PROCESS_REALTIME", False) else 0
            apply_scheduling(node, int(node.get_parameter(NICE_PARAM.name).value), fifo)
        if stop_signals.requested:  # a stop signal came while the node was built: do not start
            raise KeyboardInterrupt
        executor = MultiThreadedExecutor() if multithreaded else single_threaded_executor()
        executor.add_node(node)
        _spin_until_stopped(executor, node, stop_signals)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except DuplicateNodeError as exc:  # raised by UniqueNameCheck's timer or watch_duplicates
        # (before RuntimeError, its base class: one line and exit code 1, no traceback)
        logging.basicConfig()
        _LOG.error("could not start: %s", exc)
        code = 1
    except RuntimeError:
        # A take that raced Ctrl-C's shutdown of the context fails with a bare RuntimeError from
        # rclpy's bindings; the stop was asked for, so stop. Anything else is a real error.
        if rclpy.ok():
            raise
    finally:
        stop_signals.tearing_down = True  # first: from here a Ctrl-C must not abandon the teardown
        drained = True
        if node is not None:
            close = getattr(node, "close", None)
            if callable(close):
                close()
        if executor is not None:
            drained = _drain_callbacks(executor, CALLBACK_DRAIN_S)
        if node is not None:
            if drained:
                node.destroy_node()
            else:  # destroying it under a running callback would crash; the process ends anyway
                _LOG.warning("a callback was still running %.0f s after shutdown; node not destroyed",
                             CALLBACK_DRAIN_S)
        rclpy.try_shutdown()
    return code


def joint_trajectory(names: Sequence[str], q: Sequence[float], duration_s: float) -> Any:
    """A one-point ``trajectory_msgs/JointTrajectory``: ``names`` to ``q`` (rad) in ``duration_s`` (s)."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    sec = int(duration_s)
    pt = JointTrajectoryPoint(positions=[float(v) for v in q],
                              time_from_start=Duration(sec=sec, nanosec=int((duration_s - sec) * 1e9)))
    return JointTrajectory(joint_names=list(names), points=[pt])


def pose_msg_to_matrix(pose: Pose, quaternion_tolerance: float) -> np.ndarray:
    """4x4 base->tool transform from a geometry_msgs/Pose (quaternion x, y, z, w).

    Raises:
        InvalidInputError: NaN/inf anywhere, a zero quaternion, or | |q| - 1 | > quaternion_tolerance.
    """
    p = (pose.position.x, pose.position.y, pose.position.z)
    o = pose.orientation
    q_wxyz = (o.w, o.x, o.y, o.z)
    if not all(math.isfinite(v) for v in (*p, *q_wxyz)):
        raise InvalidInputError(
            f"target pose contains NaN or inf: position {p}, orientation (x, y, z, w) {(o.x, o.y, o.z, o.w)}",
            field="target.pose",
        )
    norm = math.sqrt(sum(v * v for v in q_wxyz))
    if norm < 1e-9:
        raise InvalidInputError(
            "target orientation is the zero quaternion (all of x, y, z, w are 0); "
            "the identity is (0, 0, 0, 1)",
            field="target.pose.orientation",
        )
    if abs(norm - 1.0) > quaternion_tolerance:
        raise InvalidInputError(
            f"target orientation is not a unit quaternion: norm {norm:.6g} differs from 1 by "
            f"more than {quaternion_tolerance:g}",
            field="target.pose.orientation",
        )
    return pose_to_matrix(p, [v / norm for v in q_wxyz], tol=1e-9)


def spin_until(executor: Any, cond: Callable[[], object], timeout: float, period: float = 0.02) -> bool:
    """Spin ``executor`` in steps of at most ``period`` s until ``cond()`` holds (True) or ``timeout``
    seconds passed (False): for clients and tools that wait on topics or services."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=period)
        if cond():
            return True
    return False


#: Seconds :func:`call_resending` waits for an answer before it sends the request again.
RESEND_AFTER_S = 8.0


def call_resending(client: Any, request: Any, wait: Callable[[Callable[[], bool], float], bool],
                   timeout: float, resend_after_s: float = RESEND_AFTER_S,
                   on_resend: Callable[[int], None] | None = None) -> Any | None:
    """Call the service ``client`` with ``request``; its response, or None after ``timeout`` s.

    The server drops a response when it has not yet matched the caller's reply reader (Fast DDS
    logs "failed to send response (timeout): client will not receive response"), and discovery on a
    busy machine can lag the request by seconds. So the request goes out again every
    ``resend_after_s`` s without an answer, and the first answer to any copy is taken: for
    idempotent requests only (init, recover, halt, park, IK). ``wait(pred, seconds)`` waits until
    ``pred()`` holds, spinning the caller's executor if nobody else does; ``on_resend(n)`` hears of
    the n-th extra copy.
    """
    deadline = time.monotonic() + timeout
    futures: list[Any] = []

    def answered() -> bool:
        return any(f.done() for f in futures)

    while True:
        futures.append(client.call_async(request))
        left = deadline - time.monotonic()
        if wait(answered, max(0.0, min(resend_after_s, left))) or answered():
            break
        if deadline - time.monotonic() <= 0.0:
            break
        if on_resend is not None:
            on_resend(len(futures))
    done = [f for f in futures if f.done()]
    for f in futures:
        if not f.done():
            client.remove_pending_request(f)  # a late answer to an abandoned copy goes nowhere
    return done[0].result() if done else None


class ParamNode(Node):
    """Base of the redarm_ros nodes: the one constructor signature all of them share.

    A subclass names itself and its parameters in the class statement,
    ``class ViewNode(ParamNode, node_name=NODE_NAME, params=PARAMS)``, and wires itself in
    :meth:`_setup` from the declared values; the constructor takes ``context``,
    ``parameter_overrides``, ``node_name`` (default: the class's) and ``namespace``, keywords only.
    """

    NODE_NAME: str = ""
    PARAMS: Sequence[ParamSpec] = ()

    def __init_subclass__(cls, *, node_name: str = "", params: Sequence[ParamSpec] = (), **kw: Any) -> None:
        super().__init_subclass__(**kw)
        cls.NODE_NAME = node_name or cls.NODE_NAME
        cls.PARAMS = params or cls.PARAMS

    def __init__(self, *, context: Any = None, parameter_overrides: list[Any] | None = None,
                 node_name: str | None = None, namespace: str | None = None) -> None:
        super().__init__(node_name or self.NODE_NAME, namespace=namespace, context=context,
                         parameter_overrides=parameter_overrides or [])
        self._setup(declare_params(self, self.PARAMS))
        # a misspelt -p name:=value or YAML key would otherwise vanish without a word
        overrides = getattr(self, "_parameter_overrides", {})
        self.unknown_parameters = sorted(k for k in overrides if not self.has_parameter(k))
        if self.unknown_parameters:
            self.get_logger().warning(
                f"unknown parameter(s) {', '.join(self.unknown_parameters)} ignored: this node has no "
                f"such parameter (`ros2 param list {self.get_fully_qualified_name()}` lists its own)"
            )

    def _setup(self, p: dict[str, Any]) -> None:
        """Wire the node (topics, services, timers) from its declared parameter values ``p``."""


class DuplicateNodeError(RuntimeError):
    """Another node of this node's name runs in the domain: this one refuses to start."""


class UniqueNameCheck:
    """The start-up duplicate-name check as a timer, so the constructor never blocks.

    Every 50 ms for ``wait_s`` seconds it looks at the graph (discovery takes a moment, so a twin
    started just before us may appear only after a few tens of ms). A twin sets :attr:`refused`,
    logs it and calls ``on_refused(reason)``; without a callback it raises
    :class:`DuplicateNodeError` out of the executor's spin, which :func:`run_node` turns into exit
    code 1. :attr:`done` turns True once the window passed without a twin; a node that must not act
    before that (e.g. send commands) checks it, and ``on_passed`` (if given) is called then: a node
    that offers its endpoints only from there never has its own window open while it serves, so a
    twin started later refuses itself rather than the node already in service.
    """

    def __init__(self, node: Node, wait_s: float, poll_s: float = 0.05,
                 on_passed: Callable[[], None] | None = None) -> None:
        self._node = node
        self._wait_s = float(wait_s)
        self._created = time.monotonic()
        self.refused: str | None = None
        self.on_refused: Callable[[str], None] | None = None
        self.on_passed = on_passed
        self.done = self._wait_s <= 0
        self._timer = None if self.done else node.create_timer(poll_s, self._tick)
        if self.done and on_passed is not None:
            on_passed()

    def _tick(self) -> None:
        if self.done or self.refused is not None:
            return
        node = self._node
        me = (node.get_name(), node.get_namespace())
        if sum(1 for nm_ns in node.get_node_names_and_namespaces() if tuple(nm_ns) == me) > 1:
            self.refused = (
                f"another node named {node.get_fully_qualified_name()} is already running in "
                f"ROS_DOMAIN_ID {node.context.get_domain_id()}; refusing to start a second one "
                f"(remap the name with --ros-args -r __node:=<name> to run both)"
            )
            self._cancel()  # from its own callback: a cancel from another thread can race the executor
            node.get_logger().error(self.refused)
            if self.on_refused is not None:
                self.on_refused(self.refused)
                return
            raise DuplicateNodeError(self.refused)
        if time.monotonic() - self._created >= self._wait_s:
            self.done = True
            self._cancel()
            if self.on_passed is not None:
                self.on_passed()

    def _cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()


INSTANCE_TOPIC = "~/_instance"  # hidden (leading underscore); the same topic for every twin of a name


def watch_duplicates(node: Node, period_s: float = 2.0, *, yield_to_elder: bool = False,
                     on_yield: Callable[[str], None] | None = None,
                     remedy: str = "remap the name with --ros-args -r __node:=<name> to run a second one",
                     ) -> None:
    """Keep looking for a node of the same name that the start-up check could not see yet (discovery
    under load can take longer than ``duplicate_check_s``) or that started later.

    Every node of a name announces its start time on one latched hidden topic (``~/_instance``), and
    again every ``period_s``. With
    ``yield_to_elder`` the younger of two twins stops itself as soon as it hears the elder
    (:class:`DuplicateNodeError` out of the executor's spin: exit code 1 through :func:`run_node`), so
    the node already in service keeps running however late discovery was; ``on_yield(reason)``, if
    given, is called instead of raising (once), for a node that must stop its own work safely first.
    ``remedy`` ends the younger twin's message: what the user should do instead.
    A twin that will not stop
    (one started with the checks off, or another program under this name) is logged once per
    appearance, from the announcement or from the graph.
    """
    from std_msgs.msg import String  # (only the nodes need std_msgs, not this module's other users)

    me = (node.get_name(), node.get_namespace())
    fqn = node.get_fully_qualified_name()
    start, uid = time.time_ns(), uuid.uuid4().hex
    state: dict[str, Any] = {"seen": False, "heard": set()}
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = node.create_publisher(String, INSTANCE_TOPIC, latched)
    announcement = String(data=f"{start} {uid} {os.getpid()} {int(yield_to_elder)}")
    pub.publish(announcement)

    def heard(msg: String) -> None:
        parts = msg.data.split()
        if len(parts) != 4 or parts[1] == uid or parts[1] in state["heard"]:
            return
        state["heard"].add(parts[1])
        try:
            other_is_elder = (int(parts[0]), parts[1]) < (start, uid)
        except ValueError:
            return  # not an announcement of ours
        pid, other_yields = parts[2], parts[3] == "1"
        if other_is_elder and yield_to_elder:
            reason = (
                f"another node named {fqn} is already running in ROS_DOMAIN_ID "
                f"{node.context.get_domain_id()} (pid {pid}, started before this one; discovery found it "
                f"only now); stopping this one ({remedy})"
            )
            node.get_logger().error(reason)
            if on_yield is None:
                raise DuplicateNodeError(reason)
            if not state.get("yielded"):
                state["yielded"] = True
                on_yield(reason)
            return
        if not other_is_elder and other_yields:
            node.get_logger().error(
                f"another node named {fqn} is running in this domain (pid {pid}, started later): it "
                "stops itself, this one keeps running"
            )
        else:
            node.get_logger().error(
                f"another node named {fqn} is running in this domain (pid {pid}): calls and topics now "
                "reach both; stop one or remap its name (--ros-args -r __node:=<name>)"
            )
        state["seen"] = True  # (said: the graph check below need not say it again)

    node.create_subscription(String, INSTANCE_TOPIC, heard, latched)

    def check() -> None:
        # again every period: a latched sample for a late joiner was seen not to arrive (in-process,
        # under load); a repeat costs one small message per period
        pub.publish(announcement)
        count = sum(1 for nm_ns in node.get_node_names_and_namespaces() if tuple(nm_ns) == me)
        if count > 1 and not state["seen"]:
            node.get_logger().error(
                f"another node named {fqn} is running in this domain: calls "
                "and topics now reach both; stop one or remap its name (--ros-args -r __node:=<name>)"
            )
        state["seen"] = count > 1

    node.create_timer(period_s, check)
