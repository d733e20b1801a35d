"""The simulated arm for a test: bus, simulator and (optionally) the ROS nodes, as child processes.

:class:`SimulatedArm` is a context manager over :class:`redarm_ros.bringup.Stack` with the
simulator's control channel on: it starts the loopback bus server (or uses a python-can bus you
give, e.g. SocketCAN ``vcan0``), ``redarm-sim`` and, if asked, ``can_driver``, ``controller`` and
``ik_service``; every child gets SHM-only DDS on the arm's own ``ROS_DOMAIN_ID``
(:mod:`redarm_ros.procs`), and every child is stopped on exit, also when the test failed. Its
methods read the simulated arm (:class:`~redarm_ros.testing.sim_control.SimStatus`) and inject the
faults a test needs. Nothing here imports rclpy or pybullet.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from typing import IO, Any

import numpy as np

from redarm_ros.bringup import Stack, StackConfig
from redarm_ros.can.protocol import ActState
from redarm_ros.procs import ManagedProcess, group_members
from redarm_ros.testing.sim_control import SimControl, SimStatus

#: The modules' watchdog time (s): a module that hears nothing for this long halts by itself.
WATCHDOG_S = 0.1


@dataclass
class SimArmConfig:
    """What to start (units rad, Hz, s).

    ``bus``: python-can keyword arguments of the bus to use (``{"interface": "socketcan",
    "channel": "vcan0"}``); None starts the loopback bus server. ``initial_q`` or ``start``
    (``"zero"``/``"park"``) is the posture the arm powers on in. ``driver_params``: ROS parameters of
    ``can_driver`` on top of the bring-up's (``{"max_missed_replies": 8}``); the driver homes the arm
    by itself unless ``driver_params`` sets ``auto_init`` false. ``wait_initialised``: with the driver,
    the arm is returned once the driver reports its modules initialised. ``sim_args``: more
    ``redarm-sim`` arguments; ``node_args``: more arguments per ROS node, after its own
    (``{"controller": ["-p", "max_speed:=0.15"]}``). ``namespace`` (every node under it), ``urdf`` with
    ``base_link``/``tip_link`` (an arm of its own, docs/urdf.md), ``view``/``view_port`` (the browser
    view): as :class:`~redarm_ros.bringup.StackConfig`.
    """

    arm: str = "pa10"
    scene: str | None = None
    initial_q: Sequence[float] | None = None
    start: str | None = None
    bus: Mapping[str, Any] | None = None
    driver: bool = False
    controller: bool = False
    ik_service: bool = False
    description: bool = False
    driver_rate_hz: float = 250.0
    driver_params: Mapping[str, Any] = field(default_factory=dict)
    wait_initialised: bool = True
    log_level: str = "warn"
    ready_timeout_s: float = 60.0
    sim_args: Sequence[str] = ()
    node_args: Mapping[str, Sequence[str]] = field(default_factory=dict)
    namespace: str | None = None
    urdf: str | None = None
    base_link: str | None = None
    tip_link: str | None = None
    view: bool = False
    view_port: int = 8080

    def stack_config(self) -> StackConfig:
        """The bring-up configuration for this arm."""
        bus = dict(self.bus) if self.bus else {}
        interface = bus.pop("interface", None)
        channel = bus.pop("channel", None)
        if bus:
            raise ValueError(f"bus takes interface and channel only (python-can config), got {sorted(bus)}")
        extra: dict[str, list[str]] = {name: list(args) for name, args in self.node_args.items()}
        extra["sim"] = ["--log-level", "WARNING", *self.sim_args]
        # The arm's ROS domain is its own: no twin driver to watch for before starting (saves 1 s).
        params = {"duplicate_check_s": 0.0, **self.driver_params}
        extra["can_driver"] = extra.get("can_driver", []) + [
            a for k, v in params.items() for a in ("-p", f"{k}:={_ros_value(v)}")]
        return StackConfig(
            arm=self.arm, hardware="sim", driver=self.driver, ik_service=self.ik_service,
            controller=self.controller, description=self.description, scene=self.scene,
            initial_q=None if self.initial_q is None else [float(v) for v in self.initial_q],
            start=self.start, driver_rate_hz=self.driver_rate_hz, can_interface=interface,
            can_channel=channel, log_level=self.log_level, ready_timeout_s=self.ready_timeout_s,
            sim_control=True, extra_args=extra, namespace=self.namespace, urdf=self.urdf,
            base_link=self.base_link, tip_link=self.tip_link, view=self.view, view_port=self.view_port,
        )


def _still(seen: list[tuple[float, np.ndarray]], st: SimStatus, window_s: float, tol: float) -> bool:
    """Add ``st`` to ``seen`` (kept to one sample at least ``window_s`` old); True if the joints
    spanned less than ``tol`` rad over a full window."""
    seen.append((st.uptime_s, st.q))
    while len(seen) > 1 and seen[1][0] <= st.uptime_s - window_s:
        seen.pop(0)
    span = np.ptp(np.array([q for _, q in seen]), axis=0)
    return st.uptime_s - seen[0][0] >= window_s and float(np.max(span)) < tol


def _ros_value(v: Any) -> str:
    return str(v).lower() if isinstance(v, bool) else str(v)


class SimulatedArm:
    """The simulated arm as processes; a context manager (starts on enter, stops everything on exit).

    >>> with SimulatedArm(driver=True) as arm:           # doctest: +SKIP
    ...     arm.silence(3)
    ...     arm.wait_for(lambda st: st.modules[1].halted, 1.0, what="module 1 halted")

    ``config`` or keyword overrides of :class:`SimArmConfig`; ``domain_id`` the ROS domain of its
    children (default: ``$ROS_DOMAIN_ID``, else a random one); ``sink`` gets their output lines.
    """

    def __init__(self, config: SimArmConfig | None = None, *, domain_id: int | None = None,
                 sink: Callable[[str], None] | IO[str] | None = None, **overrides: Any) -> None:
        unknown = set(overrides) - {f.name for f in fields(SimArmConfig)}
        if unknown:
            raise TypeError(f"SimulatedArm got unknown settings {sorted(unknown)}")
        cfg = replace(config or SimArmConfig(), **overrides)
        self.config = cfg
        self.stack = Stack(cfg.stack_config(), sink=sink, domain_id=domain_id)
        self._sim_control: SimControl | None = None
        self._last_status: SimStatus | None = None  # the simulator's, read as it was killed
        self._restarts = 0

    # -- life cycle -----------------------------------------------------------------------------------
    def start(self) -> SimulatedArm:
        """Start every configured child (each waits for its readiness line).

        Raises:
            ChildDiedError, ReadinessTimeoutError: a child did not come up (the others are stopped).
        """
        self.stack.start()
        try:
            self._sim_control = SimControl.from_ready_line(self.children["sim"].ready_match.string)  # type: ignore[attr-defined]
            if self.config.driver and self.config.wait_initialised and self._auto_init():
                self.driver.wait_for_line(r"init done", timeout=self.config.ready_timeout_s, from_start=True)
        except BaseException:
            self.close()
            raise
        return self

    def _auto_init(self) -> bool:
        return _ros_value(self.config.driver_params.get("auto_init", True)) == "true"

    def close(self) -> None:
        """Stop every child (reverse start order, SIGINT, SIGINT, SIGKILL) and remove temp files.

        Raises:
            AssertionError: a child's processes outlived the stop.
        """
        if self._sim_control is not None:
            self._sim_control.close()
        pids = [c.pid for c in self.stack.group.children]
        self.stack.close()
        left = [p for p in pids if group_members(p)]
        assert not left, f"processes of the simulated arm outlived its stop: {left}"

    def __enter__(self) -> SimulatedArm:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def check(self) -> None:
        """Raise :class:`~redarm_ros.procs.ChildDiedError` if a child died unannounced."""
        self.stack.check()

    # -- what runs ------------------------------------------------------------------------------------
    @property
    def domain_id(self) -> int:
        """The ROS domain of the arm's nodes."""
        return self.stack.domain_id

    @property
    def children(self) -> dict[str, ManagedProcess]:
        """Name -> the running child (``canbus``, ``sim``, ``can_driver``, ...)."""
        return self.stack.children

    @property
    def driver(self) -> ManagedProcess:
        """The ``can_driver`` process (its output: ``driver.wait_for_line(...)``)."""
        if "can_driver" not in self.children:
            raise KeyError("this arm was started without the driver (driver=True)")
        return self.children["can_driver"]

    @property
    def can_kwargs(self) -> dict[str, Any]:
        """python-can keyword arguments for a bus client of the test's own: ``can.Bus(**arm.can_kwargs)``."""
        out = {"interface": self.stack.can_interface}
        if self.stack.can_channel:
            out["channel"] = self.stack.can_channel
        return out

    @property
    def joint_names(self) -> list[str]:
        """The arm's joint names (the driver's /joint_states order)."""
        return list(self.status().raw["joint_names"])

    @contextmanager
    def bus(self) -> Iterator[Any]:
        """A python-can bus on the arm's CAN bus, shut down on exit."""
        import can

        bus = can.Bus(**self.can_kwargs)
        try:
            yield bus
        finally:
            bus.shutdown()

    @property
    def sim(self) -> SimControl:
        """The simulator's control channel (raw requests, the typed status)."""
        if self._sim_control is None:
            raise RuntimeError("the simulated arm is not started")
        return self._sim_control

    # -- the simulated arm ----------------------------------------------------------------------------
    def status(self) -> SimStatus:
        """The simulated arm now (read by the simulator when asked)."""
        return self.sim.status()

    @property
    def q(self) -> np.ndarray:
        """Measured joint positions now (rad)."""
        return self.status().q

    def wait_for(self, cond: Callable[[SimStatus], object], timeout: float, *, what: str = "simulator state"
                 ) -> SimStatus:
        """Poll the simulator until ``cond(status)`` holds; that status.

        Raises:
            WaitTimeoutError: not within ``timeout`` s (the message shows the last status).
        """
        return self.sim.wait_for(cond, timeout, what=what)

    def wait_at(self, q: Sequence[float], tol: float = 2e-3, timeout: float = 10.0) -> SimStatus:
        """Wait until every joint is within ``tol`` rad of ``q``."""
        target = np.asarray(q, float)
        return self.wait_for(lambda st: float(np.max(np.abs(st.q - target))) < tol, timeout,
                             what=f"arm at {np.round(target, 4).tolist()} (tol {tol:g} rad)")

    def still(self, window_s: float = 0.3, tol: float = 1e-4) -> Callable[[], bool]:
        """A polling condition: True once no joint has moved more than ``tol`` rad over the last
        ``window_s`` s of the simulator's clock (for callers that poll while spinning something)."""
        seen: list[tuple[float, np.ndarray]] = []

        def still() -> bool:
            return _still(seen, self.status(), window_s, tol)

        return still

    def wait_still(self, window_s: float = 0.3, tol: float = 1e-4, timeout: float = 10.0) -> SimStatus:
        """Wait until no joint has moved more than ``tol`` rad over the last ``window_s`` s."""
        seen: list[tuple[float, np.ndarray]] = []
        return self.wait_for(lambda st: _still(seen, st, window_s, tol), timeout,
                             what=f"arm still for {window_s:g} s")

    def wait_modules(self, bits: ActState, ids: Sequence[int] | None = None, timeout: float = 5.0
                     ) -> SimStatus:
        """Wait until every module (or those of ``ids``) shows every bit of ``bits``."""
        names = "|".join(f.name for f in ActState if f.name and f in bits)
        which = "every module" if ids is None else f"modules {list(ids)}"
        return self.wait_for(lambda st: st.all_modules(bits, ids), timeout, what=f"{which} {names}")

    # -- faults ---------------------------------------------------------------------------------------
    def silence(self, *module_ids: int) -> SimStatus:
        """These modules fall silent now (they ignore every frame, their watchdog runs on), in
        addition to those already silent. Returns the status right after."""
        now = set(self.sim.set_faults()["silenced"])
        self.sim.set_faults(silence=now | set(module_ids))
        return self.status()

    def unsilence(self, *module_ids: int) -> None:
        """These modules (all if none given) speak again."""
        now = set(self.sim.set_faults()["silenced"])
        self.sim.set_faults(silence=now - set(module_ids) if module_ids else set())

    def drop_replies(self, fraction: float) -> None:
        """Drop this fraction of the replies from now on (seeded: ``sim_args=["--seed", "N"]``)."""
        self.sim.set_faults(drop_replies=fraction)

    def delay_replies(self, ms: float) -> None:
        """Send every reply ``ms`` milliseconds after its request from now on."""
        self.sim.set_faults(delay_replies_ms=ms)

    def clear_faults(self) -> None:
        """No silenced module, no dropped or delayed reply."""
        self.sim.set_faults(silence=(), drop_replies=0.0, delay_replies_ms=0.0)

    def power_cycle(self, module_id: int, off_s: float = 0.0) -> None:
        """Switch one module off for ``off_s`` s (silent meanwhile) and on again: it comes back with
        factory settings and without HOME_OK, its joint held where it stopped."""
        if off_s > 0:
            self.silence(module_id)
            time.sleep(off_s)
        self.sim.power_cycle([module_id])

    def inject(self, module_id: int, bits: ActState = ActState.ERROR) -> None:
        """ERROR plus ``bits`` on one module now, the joint halted (RESET clears them)."""
        self.sim.inject(module_id, bits)

    def module_error(self, module_id: int) -> None:
        """The module reports ERROR (a module fault with no cause given)."""
        self.inject(module_id, ActState.ERROR)

    def beyond_soft(self, module_id: int) -> None:
        """The module reports ERROR | BEYOND_SOFT (past its soft limit), as the vendor library sees it."""
        self.inject(module_id, ActState.BEYOND_SOFT)

    def kill_sim(self) -> SimStatus | None:
        """SIGKILL the simulator (a crash: no clean-up, every module gone at once). Returns its last
        status, read just before, or None if it did not answer."""
        try:
            self._last_status = self.status()
        except Exception:  # noqa: BLE001 - a dead or stuck simulator has no status to give
            self._last_status = None
        self.sim.close()
        self.children["sim"].kill()
        return self._last_status

    def restart_sim(self, initial_q: Sequence[float] | None = None, *, kill: bool = True) -> ManagedProcess:
        """Start the simulator again (after :meth:`kill_sim`, or killing it now with ``kill``): its
        modules power on fresh (not homed, factory settings) where the arm stood when it was killed
        (``initial_q`` overrides). Returns the new process."""
        if kill and self.children["sim"].is_running():
            self.kill_sim()
        if initial_q is None and self._last_status is not None:
            initial_q = self._last_status.q
        elif initial_q is None:  # it died on its own: the last status it wrote
            st = self.stack.sim_status()
            initial_q = None if st is None else st["q"]
        self._restarts += 1
        name = f"sim_{self._restarts}"
        proc = self.stack.start_sim(name, initial_q=initial_q)
        self.children["sim"] = self.children.pop(name)
        self._sim_control = SimControl.from_ready_line(proc.ready_match.string)  # type: ignore[attr-defined]
        self._last_status = None
        return proc

    def restart_bus_server(self, down_s: float = 0.3) -> ManagedProcess:
        """Kill the loopback bus server (every client loses the bus), wait ``down_s`` s and start it
        again on the same port: the simulator and the driver reconnect by themselves.

        Raises:
            RuntimeError: the arm runs on a bus of your own (no server to restart).
        """
        if "canbus" not in self.children:
            raise RuntimeError("no bus server: this arm runs on the bus given as bus=")
        port = int(self.children["canbus"].ready_match.group(1))  # type: ignore[attr-defined]
        self.children["canbus"].kill()
        time.sleep(down_s)
        self._restarts += 1
        name = f"canbus_{self._restarts}"
        proc = self.stack.start_canbus(name, port=port)
        self.children["canbus"] = self.children.pop(name)
        return proc

