"""``redarm-bringup``: the whole simulated stack as supervised child processes, without ``ros2 launch``.

Starts, in order, each waiting for its readiness line:

1. ``redarm-canbus``  - the loopback CAN bus server (python-can-remote on 127.0.0.1, ephemeral port);
2. ``redarm-sim``     - the pybullet arm answering as PowerCube modules on that bus;
3. ``can_driver``     - the ROS driver node (``/joint_states``, ``/joint_command``, ``~/init``...);
4. ``ik_service``     - the SolveIK service node;
5. ``controller``     - the attractor-dynamics reaching controller (``/goal_pose``);
6. ``description``    - the arm's URDF on ``/robot_description`` (transient local).
7. ``view``           - with ``--view``: the browser view (``redarm-view``, http://127.0.0.1:8080/);
   ``--view-placement NPZ`` has it draw a ``redarm-placement`` heat map on the floor.

Every child gets the workplace DDS rules (``FASTDDS_BUILTIN_TRANSPORTS=SHM``, its own
``ROS_DOMAIN_ID``: the caller's if set, else a random one in 1..200), its output is forwarded line by
line with a ``[name]`` prefix, Ctrl-C (SIGINT) or SIGTERM stops them all in reverse order (SIGINT,
wait, SIGINT, SIGKILL), and a child that dies on its own is reported; the rest are then stopped and
the exit code is 1. ``--hardware real`` skips the bus server and the simulator and points the driver
at a python-can configuration instead; ``--hardware none`` starts only the ROS nodes.

The same machinery is importable: :class:`Stack` (a context manager) is what ``redarm-demo`` and the
end-to-end tests use. Nothing here imports rclpy.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

from redarm_ros.procs import ChildDiedError, ManagedProcess, ProcessGroup, python_module_cmd, random_domain_id

_LOG = logging.getLogger("redarm_ros.bringup")

REPO_ROOT = Path(__file__).resolve().parents[1]

# Readiness lines, one per child (regular expressions searched in its output).
READY = {
    "canbus": r"REDARM_CANBUS_PORT=(\d+)",
    "sim": r"REDARM_SIM_READY",
    "can_driver": r"can_driver ready:",
    "ik_service": r"serving /\S*solve_ik",
    "controller": r"controller ready:",
    "description": r"description ready:",
    "view": r"view ready: (http://\S+)",
}


def config_dir() -> Path:
    """``config/`` of the source tree, or ``share/redarm_ros/config`` of an install."""
    candidates = [REPO_ROOT / "config", Path(sys.prefix) / "share" / "redarm_ros" / "config"]
    try:  # an ament install
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory("redarm_ros")) / "config")
    except Exception:  # noqa: BLE001 - not installed the ament way
        pass
    for c in candidates:
        if c.is_dir():
            return c
    return candidates[0]


def _params_file(name: str) -> list[str]:
    """``--params-file <config>/<name>.yaml`` if the file exists, else nothing."""
    path = config_dir() / f"{name}.yaml"
    return ["--params-file", str(path)] if path.is_file() else []


def _yaml_list(values: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(v):.9g}" for v in values) + "]"


@dataclass
class StackConfig:
    """What to start and how. Units: Hz, s, rad.

    ``hardware``: ``sim`` (bus server + simulator + driver), ``real`` (driver on ``can_interface`` /
    ``can_channel``), ``none`` (no driver). With ``sim`` and a ``can_interface`` given (e.g.
    ``socketcan`` on ``vcan0``), the simulator and the driver share that bus and no bus server is
    started. ``driver`` False leaves the driver out (the simulator alone answers on the bus).
    ``sim_control``: the simulator serves its control channel (``--control-port 0``,
    :mod:`redarm_ros.sim.control_channel`). ``scene`` is a scene name or YAML path shared by the
    simulator (objects drawn and collidable) and the controller (obstacles to avoid).
    """

    arm: str = "pa10"
    urdf: str | None = None  # an arm of its own: this URDF file's chain base_link -> tip_link (docs/urdf.md)
    base_link: str | None = None
    tip_link: str | None = None
    hardware: str = "sim"
    driver: bool = True
    ik_service: bool = True
    controller: bool = True
    description: bool = True
    scene: str | None = None
    gui: bool = False
    status_file: Path | None = None
    control_file: Path | None = None
    snapshot_dir: Path | None = None
    initial_q: list[float] | None = None
    start: str | None = None  # sim: "zero" or "park" (power on in the park posture, park again after homing)
    driver_rate_hz: float = 250.0
    control_rate_hz: float = 100.0
    can_interface: str | None = None
    can_channel: str | None = None
    log_level: str = "info"
    ready_timeout_s: float = 60.0
    sim_control: bool = False  # the simulator serves its control channel on 127.0.0.1
    auto_init: bool = False  # real hardware: let can_driver reset + home by itself (the sim always does)
    view: bool = False  # also start the browser view (redarm-view) on 127.0.0.1:view_port
    view_port: int = 8080
    namespace: str | None = None  # ROS namespace of every node (e.g. /left: /left/joint_states, ...)
    view_placement: str = ""  # placements.npz of redarm-placement drawn by the view ('' = none)
    extra_args: dict[str, list[str]] = field(default_factory=dict)  # per child: appended arguments


class Stack:
    """The supervised stack; use as a context manager (``start()`` on enter, ``stop()`` on exit).

    Attributes after :meth:`start`: ``group`` (the :class:`ProcessGroup`), ``children`` (name ->
    :class:`ManagedProcess`), ``can_channel`` (python-can channel of the bus, sim mode),
    ``status_file`` (the simulator's JSON status), ``domain_id``.
    """

    def __init__(
        self,
        cfg: StackConfig,
        *,
        sink: Callable[[str], None] | IO[str] | None = None,
        domain_id: int | None = None,
    ) -> None:
        self.cfg = cfg
        if domain_id is None:
            env_id = os.environ.get("ROS_DOMAIN_ID", "").strip()
            domain_id = int(env_id) if env_id.isdigit() else random_domain_id()
        self.domain_id = domain_id
        self._tmp = tempfile.TemporaryDirectory(prefix="redarm_stack_")
        tmp = Path(self._tmp.name)
        self.status_file = Path(cfg.status_file) if cfg.status_file else tmp / "sim_status.json"
        self.control_file = Path(cfg.control_file) if cfg.control_file else tmp / "sim_control.json"
        self.group = ProcessGroup(
            domain_id=domain_id,
            sink=sink if sink is not None else sys.stderr,
            log_dir=Path(self._tmp.name) / "ros_log",
            pythonpath=self._pythonpath(),
        )
        self.children: dict[str, ManagedProcess] = {}
        self.can_channel: str | None = cfg.can_channel
        self.can_interface: str | None = cfg.can_interface
        self._control_seq = 0

    @staticmethod
    def _pythonpath() -> list[Path]:
        # Running from a source tree without `pip install -e .`: make the children find the package.
        return [REPO_ROOT] if (REPO_ROOT / "redarm_ros" / "__init__.py").is_file() else []

    # -- start ------------------------------------------------------------------------------------
    def _start(self, name: str, cmd: list[str], ready: str | None) -> ManagedProcess:
        cmd = cmd + self.cfg.extra_args.get(name, [])
        _LOG.info("starting %s: %s", name, " ".join(cmd))
        child = self.group.start(name, cmd, ready=ready, ready_timeout=self.cfg.ready_timeout_s)
        self.children[name] = child
        _LOG.info("%s is up (pid %d)", name, child.pid)
        return child

    def _start_node(self, node: str, params: dict[str, str]) -> ManagedProcess:
        """Start ``redarm_ros.nodes.<node>`` with ``params`` and wait for its readiness line."""
        return self._start(node, python_module_cmd(f"redarm_ros.nodes.{node}", *self._ros_args(node, params)),
                           READY[node])

    def _urdf_params(self) -> dict[str, str]:
        """The URDF arm's node parameters (urdf, base_link, tip_link), or {} for a bundled arm."""
        cfg = self.cfg
        if not cfg.urdf:
            return {}
        return {"urdf": cfg.urdf, "base_link": cfg.base_link or "", "tip_link": cfg.tip_link or ""}

    def _ros_args(self, node: str, params: dict[str, str]) -> list[str]:
        args = ["--ros-args", "--log-level", self.cfg.log_level, *_params_file(node)]
        if self.cfg.namespace:
            args += ["-r", f"__ns:={self.cfg.namespace}"]
        if self.cfg.log_level in ("warn", "error", "fatal"):
            # The readiness line is an info message of the node's own logger (named after the namespace
            # and the node: left.can_driver under /left): keep that one at info.
            logger = ".".join([*(self.cfg.namespace or "").strip("/").split("/"), node]).lstrip(".")
            args += ["--log-level", f"{logger}:=info"]
        for k, v in params.items():
            args += ["-p", f"{k}:={v}"]
        return args

    def start(self) -> Stack:
        """Start every configured child in order, each waiting for its readiness line.

        Raises:
            ChildDiedError, ReadinessTimeoutError: a child failed to come up (everything started so
                far is stopped again).
        """
        cfg = self.cfg
        if cfg.hardware not in ("sim", "real", "none"):
            raise ValueError(f"hardware must be sim, real or none, got {cfg.hardware!r}")
        if cfg.namespace and not cfg.namespace.startswith("/"):
            raise ValueError(f"namespace must start with '/', got {cfg.namespace!r}")
        if cfg.urdf and not (cfg.base_link and cfg.tip_link):
            raise ValueError("--urdf needs --base-link and --tip-link (the chain's ends)")
        try:
            if cfg.hardware == "sim":
                if not cfg.can_interface:
                    self.start_canbus()
                self.start_sim()
            if cfg.hardware == "real" or (cfg.hardware == "sim" and cfg.driver):
                if not self.can_interface:
                    raise ValueError("--hardware real needs --can-interface (and usually --can-channel)")
                params = {
                    "arm": cfg.arm,
                    **self._urdf_params(),
                    "rate_hz": f"{cfg.driver_rate_hz:g}",
                    # Homing moves the arm: automatic only on the simulator, a real arm waits for ~/init
                    # (or --auto-init).
                    "auto_init": "true" if cfg.hardware == "sim" or cfg.auto_init else "false",
                    "can.interface": self.can_interface,
                }
                if self.can_channel:
                    params["can.channel"] = self.can_channel
                if cfg.start == "park":
                    params["park_after_init"] = "true"  # homing runs to 0 rad; come back to park
                self._start_node("can_driver", params)
            if cfg.ik_service:
                self._start_node("ik_service", self._urdf_params() or {"default_arm": cfg.arm})
            if cfg.controller:
                params = {"arm": cfg.arm, **self._urdf_params(), "rate_hz": f"{cfg.control_rate_hz:g}"}
                if cfg.urdf:  # goals, twists and obstacles in the URDF arm's base link frame
                    params["base_frame"] = cfg.base_link or ""
                if cfg.scene:
                    params["scene"] = cfg.scene
                self._start_node("controller", params)
            if cfg.description:
                self._start_node("description", {"urdf_file": cfg.urdf} if cfg.urdf else {"arm": cfg.arm})
            if cfg.view:
                params = {"arm": cfg.arm, "port": str(int(cfg.view_port))}
                if cfg.scene and not cfg.controller:  # the controller's markers already show its scene
                    params["scene"] = cfg.scene
                if cfg.view_placement:
                    params["placement"] = cfg.view_placement
                self._start_node("view", params)
        except BaseException:
            self.stop()
            raise
        return self

    def start_canbus(self, name: str = "canbus", port: int = 0) -> ManagedProcess:
        """Start the loopback bus server (``port`` 0: ephemeral; a previous port: the same bus again)
        and point the stack's CAN settings at it."""
        bus = self._start(
            name,
            python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", str(int(port))),
            READY["canbus"],
        )
        port = int(bus.ready_match.group(1))  # type: ignore[attr-defined]
        self.can_interface, self.can_channel = "remote", f"ws://127.0.0.1:{port}/"
        return bus

    def start_sim(self, name: str = "sim", initial_q: Sequence[float] | None = None) -> ManagedProcess:
        """Start the simulator on the stack's bus (``initial_q``: power on there instead of the
        configured posture) and wait for its ready line."""
        cfg = self.cfg
        if not self.can_interface:
            raise ValueError("the simulator needs a bus: start_canbus() first or give can_interface")
        sim_cmd = python_module_cmd(
            "redarm_ros.sim.hardware", "--arm", cfg.arm, "--can-interface", self.can_interface,
            "--status-file", str(self.status_file), "--control-file", str(self.control_file),
        )
        if self.can_channel:
            sim_cmd += ["--can-channel", self.can_channel]
        if cfg.urdf:
            sim_cmd += ["--urdf", cfg.urdf, "--base-link", cfg.base_link or "",
                        "--tip-link", cfg.tip_link or ""]
        if cfg.gui:
            sim_cmd.append("--gui")
        if cfg.scene:
            sim_cmd += ["--scene", cfg.scene]
        if cfg.snapshot_dir:
            sim_cmd += ["--snapshot-dir", str(cfg.snapshot_dir)]
        q0 = initial_q if initial_q is not None else cfg.initial_q
        if q0 is not None and len(q0):
            # One "=" argument: a leading negative value would otherwise read as an option.
            sim_cmd.append("--initial-q=" + ",".join(f"{float(v):.9g}" for v in q0))
        elif cfg.start:
            sim_cmd += ["--start", cfg.start]
        if cfg.sim_control:
            sim_cmd += ["--control-port", "0"]
        return self._start(name, sim_cmd, READY["sim"])

    # -- talk to the simulator ------------------------------------------------------------------
    def sim_status(self) -> dict[str, Any] | None:
        """The simulator's last JSON status (joint positions ``q``, ``tool`` pose from pybullet's link
        state: ``position`` m and ``quaternion_xyzw``), or None if there is none yet."""
        try:
            return json.loads(self.status_file.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def sim_still(self, window_s: float, tol_rad: float) -> Callable[[], bool]:
        """A polling condition: True once the simulated joints have each moved less than ``tol_rad``
        over the last ``window_s`` seconds. A reached goal's elbow may still be settling about its
        preferred swivel, and a busy machine settles later, so callers poll it with their own limit."""
        seen: list[tuple[float, list[float]]] = []

        def still() -> bool:
            st = self.sim_status()
            if st is None:
                return False
            now = time.monotonic()
            seen.append((now, [float(v) for v in st["q"]]))
            while len(seen) > 1 and seen[1][0] <= now - window_s:  # keep one sample >= window_s old
                seen.pop(0)
            if now - seen[0][0] < window_s:
                return False
            return max(max(col) - min(col) for col in zip(*(q for _, q in seen), strict=True)) < tol_rad

        return still

    def sim_control(self, **data: Any) -> None:
        """Write the simulator's control file (atomically), e.g. ``sim_control(snapshot="goal_1")``.

        Keys (see docs/sim.md): ``snapshot`` (PNG name in the snapshot dir), ``silence``,
        ``drop_replies``, ``delay_replies_ms``, ``stop``. The simulator polls the file every 50 ms
        and acts when its modification time or size changes.
        """
        self._control_seq += 1
        tmp = self.control_file.with_name(f".{self.control_file.name}.{self._control_seq}.tmp")
        # Alternate a trailing space so two identical requests still differ in size.
        tmp.write_text(json.dumps(data) + " " * (self._control_seq % 2), encoding="utf-8")
        os.replace(tmp, self.control_file)

    def request_snapshot(self, name: str, timeout_s: float = 10.0) -> Path | None:
        """Ask the simulator for ``<snapshot_dir>/<name>.png`` and wait until its status lists it.

        Returns the path, or None without a snapshot directory / simulator or if it did not appear.
        """
        if self.cfg.snapshot_dir is None or self.cfg.hardware != "sim":
            return None
        self.sim_control(snapshot=name)
        want = (Path(self.cfg.snapshot_dir) / f"{name}.png").resolve()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self.sim_status() or {}
            if any(Path(p).resolve() == want for p in st.get("snapshots", [])):
                return want
            time.sleep(0.05)
        return None

    # -- supervise / stop -------------------------------------------------------------------------
    def check(self) -> None:
        """Raise :class:`ChildDiedError` if a child died without being asked to."""
        self.group.check()

    def wait(self, poll_s: float = 0.2) -> None:
        """Block until a child dies (raises ChildDiedError) or KeyboardInterrupt."""
        while True:
            self.check()
            time.sleep(poll_s)

    def stop(self) -> dict[str, int]:
        """Stop every child in reverse start order; returns name -> exit code."""
        codes = self.group.stop_all()
        for name, rc in codes.items():
            _LOG.info("%s stopped (exit code %d)", name, rc)
        return codes

    def close(self) -> None:
        """Stop the children and remove the temp directory."""
        self.stop()
        self._tmp.cleanup()

    def __enter__(self) -> Stack:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- command line --------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    """The ``redarm-bringup`` argument parser."""
    ap = argparse.ArgumentParser(
        prog="redarm-bringup",
        description="Start the simulated redarm stack (bus server, simulator, can_driver, ik_service, "
        "controller, description) as supervised processes; Ctrl-C stops them all.",
    )
    ap.add_argument("--arm", default="pa10", help="arm model (config/arms/<name>.yaml), default pa10")
    ap.add_argument("--urdf", help="an arm of your own: this URDF file (with --base-link, --tip-link; "
                    "docs/urdf.md); replaces --arm")
    ap.add_argument("--base-link", help="the URDF arm's base link")
    ap.add_argument("--tip-link", help="the URDF arm's tip link")
    ap.add_argument(
        "--hardware",
        choices=("sim", "real", "none"),
        default="sim",
        help="sim: bus server + pybullet simulator + driver (default); real: driver on the "
        "python-can bus given by --can-interface/--can-channel; none: no driver",
    )
    ap.add_argument("--can-interface", help="python-can interface for --hardware real (e.g. socketcan)")
    ap.add_argument("--can-channel", help="python-can channel for --hardware real (e.g. can0)")
    ap.add_argument("--auto-init", action="store_true",
                    help="--hardware real: let can_driver reset and home the modules by itself (moves the "
                    "arm!); otherwise call /can_driver/init when ready. The simulator is always initialised")
    ap.add_argument("--no-controller", action="store_true", help="do not start the controller node")
    ap.add_argument("--no-ik-service", action="store_true", help="do not start the ik_service node")
    ap.add_argument("--no-description", action="store_true",
                    help="do not start the description node (/robot_description)")
    ap.add_argument("--scene", help="scene name (config/scenes) or YAML path, for simulator and controller")
    ap.add_argument("--view", action="store_true",
                    help="also start the browser view (redarm-view) on http://127.0.0.1:VIEW_PORT/")
    ap.add_argument("--view-port", type=int, default=8080, help="port of the browser view (default 8080)")
    ap.add_argument("--namespace", help="ROS namespace of every node (e.g. /left: topics /left/joint_states, "
                    "/left/goal_pose, services /left/can_driver/init, ...); default none")
    ap.add_argument("--view-placement", default="", metavar="NPZ",
                    help="placements.npz of redarm-placement: the view draws its heat map on the floor")
    ap.add_argument("--gui", action="store_true", help="open the pybullet GUI (needs a display)")
    ap.add_argument("--status-file", type=Path, help="where the simulator writes its JSON status")
    ap.add_argument("--snapshot-dir", type=Path, help="where the simulator writes PNG snapshots")
    ap.add_argument("--control-file", type=Path, help="the simulator's control file (docs/sim.md)")
    ap.add_argument(
        "--initial-q", type=float, nargs="+", help="initial joint angles of the simulated arm (rad)"
    )
    ap.add_argument("--start", choices=("zero", "park"),
                    help="posture the simulated arm powers on in (default zero); park: its park posture, "
                    "and can_driver moves back there after homing (park_after_init)")
    ap.add_argument("--driver-rate", type=float, default=250.0, help="can_driver cycle rate (Hz)")
    ap.add_argument("--control-rate", type=float, default=100.0, help="controller rate (Hz)")
    ap.add_argument("--log-level", default="info", choices=("debug", "info", "warn", "error"))
    ap.add_argument(
        "--domain-id", type=int, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID, else random 1..200)"
    )
    ap.add_argument(
        "--ready-timeout", type=float, default=60.0, help="seconds each child may take to come up"
    )
    return ap


def config_from_args(ns: argparse.Namespace) -> StackConfig:
    """A :class:`StackConfig` from parsed ``redarm-bringup`` arguments."""
    return StackConfig(
        arm=ns.arm,
        urdf=str(Path(ns.urdf).resolve()) if ns.urdf else None,
        base_link=ns.base_link,
        tip_link=ns.tip_link,
        hardware=ns.hardware,
        ik_service=not ns.no_ik_service,
        controller=not ns.no_controller,
        description=not ns.no_description,
        scene=ns.scene,
        gui=ns.gui,
        status_file=ns.status_file,
        control_file=ns.control_file,
        snapshot_dir=ns.snapshot_dir,
        initial_q=ns.initial_q,
        start=ns.start,
        driver_rate_hz=ns.driver_rate,
        control_rate_hz=ns.control_rate,
        can_interface=ns.can_interface,
        can_channel=ns.can_channel,
        log_level=ns.log_level,
        ready_timeout_s=ns.ready_timeout,
        auto_init=ns.auto_init,
        view=ns.view,
        view_port=ns.view_port,
        namespace=ns.namespace,
        view_placement=ns.view_placement,
    )


def _raise_keyboard_interrupt(signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point. Exit codes: 0 stopped by Ctrl-C/SIGTERM, 1 a child died or failed to start."""
    ns = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[bringup] %(message)s", stream=sys.stderr)
    # SIGTERM (systemd, a test, `kill`) takes the same clean path as Ctrl-C. SIGINT is set too: a
    # script's background job starts with it ignored, and then neither Ctrl-C nor `kill -INT` would
    # stop the stack (the children, started after this, get the default handling back).
    signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
    signal.signal(signal.SIGINT, _raise_keyboard_interrupt)
    cfg = config_from_args(ns)
    stack = Stack(cfg, domain_id=ns.domain_id)
    _LOG.info("ROS_DOMAIN_ID=%d, FASTDDS_BUILTIN_TRANSPORTS=SHM", stack.domain_id)
    code = 0
    try:
        stack.start()
        _LOG.info(
            "stack up: %s; Ctrl-C to stop", ", ".join(f"{n} (pid {c.pid})" for n, c in stack.children.items())
        )
        if "view" in stack.children:
            _LOG.info("browser view: %s", stack.children["view"].ready_match.group(1))  # type: ignore[attr-defined]
        stack.wait()
    except KeyboardInterrupt:
        _LOG.info("stopping (Ctrl-C)")
    except ChildDiedError as exc:
        _LOG.error(
            "child %s died unexpectedly (exit code %s); stopping the others. Last output:\n%s",
            exc.name,
            exc.returncode,
            "\n".join(exc.tail[-15:]),
        )
        code = 1
    except Exception as exc:  # noqa: BLE001 - report start-up failures in one line, then clean up
        _LOG.error("could not bring the stack up: %s", exc)
        code = 1
    finally:
        # A second Ctrl-C while stopping must not abandon children: ignore it until all are down.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        stack.close()
        _LOG.info("all children stopped")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
