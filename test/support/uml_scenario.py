"""Scenario programs for the genuine-SocketCAN test: run inside the UML guest, or natively on a vcan.

Not a test module (pytest collects ``test_*.py`` only); ``test_uml_socketcan.py``
runs it as a separate program, inside the guest or on the host's own vcan.

Sub-commands (each prints, and with ``--result`` writes, a JSON result with ``"ok"`` and the
measurements):

* ``echo``: answer every frame on ``--request-id`` with the same data on
  ``--reply-id`` until ``--count`` frames were answered or ``--idle`` seconds
  pass without one; prints ``ECHO_READY`` once the bus is open.
* ``pingpong``: start ``echo`` as a second process, send ``--count`` frames and
  time each round trip; every reply must carry the data that was sent.
* ``hil``: the real driver core against the real ``redarm-sim`` (see :func:`cmd_hil`).
* ``ros``: the ``can_driver`` ROS node against ``redarm-sim``, driven by a client node
  (see :func:`cmd_ros`).
* ``suite``: all of the above in turn, ``result_<name>.json`` each into ``--out``.

The bus is opened from python-can configuration: ``--interface``/``--channel``
or, when absent, ``CAN_INTERFACE``/``CAN_CHANNEL`` as everywhere in redarm_ros.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np

from redarm_ros.motion.min_jerk import min_jerk
from redarm_ros.procs import ChildDiedError, ManagedProcess, ReadinessTimeoutError

_LOG = logging.getLogger("uml_scenario")
HERE = Path(__file__).resolve()


# Every process of the one-CPU guest runs at normal scheduling (SCHED_FIFO priority 0 = off): whichever ran
# at SCHED_FIFO starved the others there (the driver's cycle: RT throttling and 1.7 Hz joint_states; the
# simulator: physics 3.7 s behind, the arm 16 mrad short). Real modules answer in hardware; the host-side
# tests run the cycle and the simulator at SCHED_FIFO.
GUEST_RT_PRIORITY = 0
# The simulator steps its physics in a thread in the guest: its own process there (the default, so that no
# reply waits for the physics on a machine of two or more CPUs) only adds context switches, costly in a
# one-CPU user-mode guest: after that default came in, 2 of 2 full-suite runs failed a guest check
# (trajectory tracking 0.083 rad against 0.05; a ~/recover) that had not failed before.
GUEST_SIM_PHYSICS = "thread"


def _bus_kwargs(ns: argparse.Namespace) -> dict[str, Any]:
    kwargs: dict[str, Any] = {}
    interface = ns.interface or os.environ.get("CAN_INTERFACE")
    channel = ns.channel or os.environ.get("CAN_CHANNEL")
    if interface:
        kwargs["interface"] = interface
    if channel:
        kwargs["channel"] = channel
    return kwargs


def _write_result(path: str | None, result: dict[str, Any]) -> None:
    text = json.dumps(result, indent=2, sort_keys=True)
    if path:
        tmp = Path(path + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def cmd_echo(ns: argparse.Namespace) -> int:
    """Answer frames on request_id with the same payload on reply_id."""
    answered = 0
    with can.Bus(**_bus_kwargs(ns)) as bus:
        bus.set_filters([{"can_id": ns.request_id, "can_mask": 0x7FF, "extended": False}])
        sys.stdout.write("ECHO_READY\n")
        sys.stdout.flush()
        while answered < ns.count:
            msg = bus.recv(timeout=ns.idle)
            if msg is None:
                break
            if msg.arbitration_id != ns.request_id or msg.is_error_frame:
                continue
            bus.send(can.Message(arbitration_id=ns.reply_id, data=msg.data, is_extended_id=False, check=True))
            answered += 1
    _LOG.info("echo answered %d frames", answered)
    return 0 if answered == ns.count else 1


def _start_child(args: list[str], ready: str, timeout_s: float) -> ManagedProcess:
    """Start ``python uml_scenario.py ARGS`` and wait for its readiness line."""
    return _start_child_cmd([sys.executable, str(HERE), *args], ready, timeout_s)


def _start_child_cmd(
    cmd: list[str], ready: str, timeout_s: float, sink: Any = sys.stderr
) -> ManagedProcess:
    """Start ``cmd`` (output to ``sink``) and wait until a line of its output starts with ``ready``."""
    child = ManagedProcess(" ".join(cmd[1:3]), cmd, sink=sink)
    try:
        child.wait_for_line("^" + re.escape(ready), timeout_s)
    except (ReadinessTimeoutError, ChildDiedError) as exc:
        child.stop()
        raise RuntimeError(f"child {cmd[1:3]} did not print {ready} within {timeout_s} s") from exc
    return child


def _stop_child(child: ManagedProcess, timeout_s: float = 10.0, grace_s: float = 0.0) -> int | None:
    """Wait ``grace_s`` for a natural exit, then the staged stop (SIGINT, SIGINT, SIGKILL)."""
    if grace_s > 0:
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.popen.wait(timeout=grace_s)
    return child.stop((timeout_s, 3.0, 3.0))


def cmd_pingpong(ns: argparse.Namespace) -> int:
    """Round trips between this process and an echo process."""
    bus_args = []
    if ns.interface:
        bus_args += ["--interface", ns.interface]
    if ns.channel:
        bus_args += ["--channel", ns.channel]
    result: dict[str, Any] = {"ok": False, "count": ns.count, "bus": _bus_kwargs(ns)}
    t_start = time.monotonic()
    echo = _start_child(["echo", *bus_args, "--count", str(ns.count), "--idle", str(max(ns.timeout, 10.0)),
                         "--request-id", hex(ns.request_id), "--reply-id", hex(ns.reply_id)],
                        "ECHO_READY", ns.ready_timeout)
    result["echo_start_s"] = round(time.monotonic() - t_start, 3)
    rtts: list[float] = []
    mismatches = 0
    lost = 0
    try:
        with can.Bus(**_bus_kwargs(ns)) as bus:
            bus.set_filters([{"can_id": ns.reply_id, "can_mask": 0x7FF, "extended": False}])
            for i in range(ns.count):
                payload = i.to_bytes(4, "little") + bytes([0xA5, 0x5A, i & 0xFF, 0x3C])
                t0 = time.perf_counter()
                bus.send(can.Message(arbitration_id=ns.request_id, data=payload, is_extended_id=False,
                                     check=True))
                deadline = t0 + ns.timeout
                while True:
                    msg = bus.recv(timeout=max(0.0, deadline - time.perf_counter()))
                    if msg is None:
                        lost += 1
                        break
                    if msg.arbitration_id != ns.reply_id:
                        continue
                    if bytes(msg.data) != payload:
                        # A late reply to an earlier (lost) request: count it, keep waiting.
                        mismatches += 1
                        continue
                    rtts.append(time.perf_counter() - t0)
                    break
    finally:
        echo_rc = _stop_child(echo, grace_s=10.0)
    result.update(
        received=len(rtts),
        lost=lost,
        mismatches=mismatches,
        echo_rc=echo_rc,
        rtt_median_ms=round(statistics.median(rtts) * 1e3, 3) if rtts else None,
        rtt_p95_ms=round(sorted(rtts)[int(0.95 * (len(rtts) - 1))] * 1e3, 3) if rtts else None,
        rtt_max_ms=round(max(rtts) * 1e3, 3) if rtts else None,
        duration_s=round(time.monotonic() - t_start, 3),
    )
    result["ok"] = len(rtts) == ns.count and lost == 0 and echo_rc == 0
    _write_result(ns.result, result)
    return 0 if result["ok"] else 1


# --------------------------------------------------------------------------------------------
# HIL: the real driver core against the real redarm-sim, separate processes, one CAN bus
# --------------------------------------------------------------------------------------------

# Offsets (rad) from the homed position: every joint moves, all well inside the PA10 limits.
HIL_DELTA = (0.40, -0.30, 0.50, 0.60, -0.40, 0.30, 0.50)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _bus_cli(ns: argparse.Namespace, prefix: str = "--can-") -> list[str]:
    kw = _bus_kwargs(ns)
    out: list[str] = []
    if "interface" in kw:
        out += [f"{prefix}interface", kw["interface"]]
    if "channel" in kw:
        out += [f"{prefix}channel", kw["channel"]]
    return out


def _malformed_frames() -> list[can.Message]:
    """Well-formed CAN frames with malformed PowerCube content (each is valid for check=True).

    To modules: FSTEP with a NaN target (module 3), SETMOVE cut short (module 3), an unknown
    command byte (module 2), GETPARAM without its parameter byte (module 4). To the host: an
    extended SETMOVE acknowledgement of module 5 cut to 3 bytes.
    """
    import struct

    nan_fstep = struct.pack("<BBfH", 0x0B, 0x06, float("nan"), 20)
    frames = [
        (0x0E0 + 3, nan_fstep),
        (0x0E0 + 3, bytes([0x0B, 0x06, 0x00])),
        (0x0E0 + 2, bytes([0x55])),
        (0x0C0 + 4, bytes([0x0A])),
        (0x0A0 + 5, bytes([0x0B, 0x10, 0xFF])),
    ]
    return [can.Message(arbitration_id=i, data=d, is_extended_id=False, check=True) for i, d in frames]


def cmd_hil(ns: argparse.Namespace) -> int:
    """Discovery, init/home, a joint trajectory, malformed frames, halt/recover: driver core vs redarm-sim.

    The simulator runs as its own process (``python -m redarm_ros.sim.hardware``); this process
    owns a :class:`PowerCubeArmDriver` on its own bus. Timeouts are looser than the driver's
    defaults because the UML guest has one slow CPU shared by both processes (see ``--reply-timeout``).
    """
    from redarm_ros.can.bus import open_bus, safe_shutdown
    from redarm_ros.can.driver_core import DriverState, PowerCubeArmDriver
    from redarm_ros.kinematics import load_arm

    out = Path(ns.result).parent if ns.result else Path(os.environ.get("TMPDIR", "/tmp"))
    status_path = out / "sim_status.json"
    result: dict[str, Any] = {"ok": False, "bus": _bus_kwargs(ns), "cycle_hz": ns.rate,
                              "reply_timeout_s": ns.reply_timeout, "sim_rate_hz": ns.sim_rate}
    t_start = time.monotonic()
    arm = load_arm(ns.arm)
    sim = _start_child_cmd(
        [sys.executable, "-m", "redarm_ros.sim.hardware", "--arm", ns.arm, "--rate", str(ns.sim_rate),
         "--status-file", str(status_path), "--status-rate", "10", "--log-level", "WARNING",
         "--realtime-priority", str(GUEST_RT_PRIORITY), "--physics", GUEST_SIM_PHYSICS, *_bus_cli(ns)],
        "REDARM_SIM_READY", ns.ready_timeout)
    result["sim_start_s"] = round(time.monotonic() - t_start, 3)
    bus = None
    try:
        bus = open_bus(**_bus_kwargs(ns))
        drv = PowerCubeArmDriver(
            bus, list(range(1, arm.n + 1)), arm.lower, arm.upper, arm.max_vel, arm.max_acc,
            reply_timeout_s=ns.reply_timeout, max_missed=5, home_timeout_s=60.0, poll_interval_s=0.05,
        )
        # 1. discovery
        rep = drv.discover()
        result["discovery"] = {"found": sorted(rep.found), "missing": rep.missing,
                               "versions": sorted(set(rep.found.values()))}
        # 2. init: configure, reset, home
        t0 = time.monotonic()
        st = drv.init()
        result["init"] = {
            "duration_s": round(time.monotonic() - t0, 3),
            "positions": [round(float(x), 5) for x in st.positions],
            "home_ok": [bool(int(s) & 0x2) for s in st.states],
            "errors": {str(k): int(v) for k, v in st.errors.items()},
            "state": drv.state.value,
        }
        # 3. trajectory: minimum-jerk from the homed position to q0 + HIL_DELTA, then hold
        q0 = np.asarray(st.positions, dtype=float)
        goal = np.clip(q0 + np.asarray(HIL_DELTA[: arm.n]), arm.lower + 0.05, arm.upper - 0.05)
        dt = 1.0 / ns.rate
        n_move = int(round(ns.duration * ns.rate))
        n_total = n_move + int(round(ns.hold * ns.rate))
        inject_at = n_move // 2
        track_err: list[float] = []
        periods: list[float] = []
        lost = late = malformed_seen = 0
        latencies: list[float] = []
        prev_target = q0.copy()
        next_t = time.monotonic()
        prev_start = None
        injected = 0
        for k in range(1, n_total + 1):
            now = time.monotonic()
            if now < next_t:
                time.sleep(next_t - now)
            start = time.monotonic()
            if prev_start is not None:
                periods.append(start - prev_start)
            prev_start = start
            next_t = max(next_t + dt, start)  # absolute deadlines; no catch-up burst after a stall
            q_des = q0 + (goal - q0) * min_jerk(k / n_move)
            res = drv.cycle(q_des, dt)
            lost += res.lost
            late += res.late
            malformed_seen += res.malformed
            latencies.extend(float(x) for x in res.latency_s if np.isfinite(x))
            if res.fault:
                result["fault"] = str(res.fault)
                break
            # The acknowledged position is the one before this cycle's move: compare with the
            # previous cycle's commanded target (what the module was asked to reach by now).
            if res.replied.all():
                track_err.append(float(np.max(np.abs(res.positions - prev_target))))
            prev_target = res.targets.copy()
            if k == inject_at:
                with can.Bus(**_bus_kwargs(ns)) as raw:
                    for msg in _malformed_frames():
                        raw.send(msg)
                        injected += 1
        final = drv.read_state()
        final_err = np.abs(final.positions - goal)
        time.sleep(0.3)  # let the simulator write a fresh status
        sim_status = _read_json(status_path)
        sim_q = np.asarray(sim_status.get("q", [np.nan] * arm.n), dtype=float)
        result["trajectory"] = {
            "cycles": len(periods) + 1,
            "goal": [round(float(x), 5) for x in goal],
            "max_delta_rad": float(np.max(np.abs(goal - q0))),
            "tracking_err_max_rad": round(max(track_err), 5) if track_err else None,
            "tracking_err_median_rad": round(float(np.median(track_err)), 5) if track_err else None,
            "final_err_max_rad": round(float(final_err.max()), 5),
            "sim_final_err_max_rad": round(float(np.max(np.abs(sim_q - goal))), 5),
            "lost_replies": lost,
            "late_replies": late,
            "period_median_ms": round(statistics.median(periods) * 1e3, 3) if periods else None,
            "period_max_ms": round(max(periods) * 1e3, 3) if periods else None,
            "latency_median_ms": round(statistics.median(latencies) * 1e3, 3) if latencies else None,
            "latency_max_ms": round(max(latencies) * 1e3, 3) if latencies else None,
            "state": drv.state.value,
        }
        counters = sim_status.get("counters", {})
        result["malformed"] = {
            "injected": injected,
            "to_modules": 4,
            "to_host": 1,
            "sim_counted": counters.get("malformed"),
            "sim_handler_errors": counters.get("handler_errors"),
            "driver_counted": drv.decoder.malformed,
            "driver_cycle_counted": malformed_seen,
            "driver_state_after": drv.state.value,
        }
        # 4. halt and recover
        acked = drv.halt()
        held = drv.cycle(goal, dt)
        after_halt = drv.read_state()
        rec = drv.recover()
        result["halt_recover"] = {
            "halt_acked": sorted(acked),
            "cycle_holding_after_halt": bool(held.holding),
            "halted_bits": [bool(int(s) & 0x4) for s in after_halt.states],
            "state_after_recover": drv.state.value,
            "recover_errors": {str(k): int(v) for k, v in rec.errors.items()},
        }
        result["module_stats"] = [s.as_dict() for s in drv.stats]
        result["ok"] = drv.state is DriverState.READY
    finally:
        if bus is not None:
            safe_shutdown(bus)
        result["sim_rc"] = _stop_child(sim, grace_s=0.0)
        result["duration_s"] = round(time.monotonic() - t_start, 3)
        _write_result(ns.result, result)
    return 0 if result["ok"] else 1


# --------------------------------------------------------------------------------------------
# ROS: the can_driver node (its own process) against redarm-sim, driven from a client node
# --------------------------------------------------------------------------------------------


def _ros_env_defaults() -> None:
    """Keep DDS on this machine: SHM transport only and a private domain, unless already set."""
    import random

    os.environ.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "SHM")
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if os.environ["FASTDDS_BUILTIN_TRANSPORTS"] != "SHM":
        raise RuntimeError("refusing to start DDS without FASTDDS_BUILTIN_TRANSPORTS=SHM")


def cmd_ros(ns: argparse.Namespace) -> int:
    """``can_driver`` node + ``redarm-sim`` over the bus; a client node calls ~/init, sends a
    JointTrajectory on /joint_command, watches /joint_states, then ~/halt and ~/recover."""
    _ros_env_defaults()
    out = Path(ns.result).parent if ns.result else Path(os.environ.get("TMPDIR", "/tmp"))
    result: dict[str, Any] = {"ok": False, "bus": _bus_kwargs(ns), "rate_hz": ns.rate,
                              "reply_timeout_s": ns.reply_timeout, "domain_id": os.environ["ROS_DOMAIN_ID"]}
    t_start = time.monotonic()
    t0 = time.monotonic()
    import rclpy
    from builtin_interfaces.msg import Duration
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from redarm_ros.kinematics import load_arm
    from redarm_ros.nodes._common import call_resending

    result["import_rclpy_s"] = round(time.monotonic() - t0, 3)
    arm = load_arm(ns.arm)
    sim = _start_child_cmd(
        [sys.executable, "-m", "redarm_ros.sim.hardware", "--arm", ns.arm, "--rate", str(ns.sim_rate),
         "--status-file", str(out / "ros_sim_status.json"), "--status-rate", "10", "--log-level", "WARNING",
         "--realtime-priority", str(GUEST_RT_PRIORITY), "--physics", GUEST_SIM_PHYSICS, *_bus_cli(ns)],
        "REDARM_SIM_READY", ns.ready_timeout)
    kw = _bus_kwargs(ns)
    node_log = open(out / "can_driver_node.log", "w")  # closed in finally
    node_cmd = [sys.executable, "-m", "redarm_ros.nodes.can_driver", "--ros-args",
                "-p", f"arm:={ns.arm}", "-p", f"rate_hz:={float(ns.rate)}",
                "-p", f"reply_timeout_s:={float(ns.reply_timeout)}", "-p", "max_missed_replies:=5",
                "-p", "request_timeout_s:=60.0", "-p", f"watchdog:={ns.watchdog}",
                "-p", f"realtime_priority:={GUEST_RT_PRIORITY}"]
    if "interface" in kw:
        node_cmd += ["-p", f"can.interface:={kw['interface']}"]
    if "channel" in kw:
        node_cmd += ["-p", f"can.channel:={kw['channel']}"]
    t0 = time.monotonic()
    node_proc = ManagedProcess("can_driver", node_cmd, sink=node_log)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    client = None
    try:
        client = rclpy.create_node("uml_scenario_client", context=ctx)
        from rclpy.executors import SingleThreadedExecutor

        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(client)
        latest: dict[str, Any] = {"q": None, "count": 0}

        def on_js(msg: JointState) -> None:
            if list(msg.name) == list(arm.joint_names):
                latest["q"] = np.array(msg.position, dtype=float)
                latest["count"] += 1

        client.create_subscription(JointState, "/joint_states", on_js, 10)
        pub = client.create_publisher(JointTrajectory, "/joint_command", 10)
        services = {a: client.create_client(Trigger, f"/can_driver/{a}") for a in ("init", "halt", "recover")}

        def spin_until(pred: Any, timeout_s: float) -> bool:
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                if pred():
                    return True
                if not node_proc.is_running():
                    raise RuntimeError(f"can_driver exited with {node_proc.returncode}")
                ex.spin_once(timeout_sec=0.02)
            return bool(pred())

        def call(action: str) -> dict[str, Any]:
            t = time.monotonic()
            # spin_once until done: spin_until_future_complete adds 20-80 ms per call here. A slow
            # guest can take longer than the default resend interval to init.
            resp = call_resending(services[action], Trigger.Request(), spin_until, 90.0, resend_after_s=20.0)
            return {"success": bool(resp and resp.success), "message": resp.message if resp else "timeout",
                    "duration_s": round(time.monotonic() - t, 3)}

        if not spin_until(lambda: services["init"].service_is_ready(), ns.ready_timeout):
            raise RuntimeError("can_driver's ~/init service did not appear")
        result["node_start_s"] = round(time.monotonic() - t0, 3)
        result["init"] = call("init")
        got_state = spin_until(lambda: latest["q"] is not None, 20.0)
        result["joint_states_before"] = got_state
        spin_until(lambda: pub.get_subscription_count() > 0, 20.0)
        q0 = latest["q"].copy() if latest["q"] is not None else np.zeros(arm.n)
        goal = np.clip(q0 + np.asarray(HIL_DELTA[: arm.n]), arm.lower + 0.05, arm.upper - 0.05)
        traj = JointTrajectory()
        traj.joint_names = list(arm.joint_names)
        for frac, t_s in ((0.5, ns.duration / 2), (1.0, ns.duration)):
            pt = JointTrajectoryPoint()
            pt.positions = (q0 + (goal - q0) * frac).tolist()
            pt.time_from_start = Duration(sec=int(t_s), nanosec=int((t_s % 1) * 1e9))
            traj.points.append(pt)
        count0 = latest["count"]
        t_pub = time.monotonic()
        pub.publish(traj)
        reached = spin_until(
            lambda: latest["q"] is not None and float(np.max(np.abs(latest["q"] - goal))) < ns.tolerance,
            ns.duration + 15.0)
        time_to_reach = time.monotonic() - t_pub
        # settle for 1 s, then judge the final position; the error is traced every 0.1 s meanwhile (a
        # failure in the starved one-CPU guest must say whether the arm was still arriving or moved away)
        trace = []
        for _ in range(10):
            spin_until(lambda: False, 0.1)
            if latest["q"] is not None:
                trace.append(round(float(np.max(np.abs(latest["q"] - goal))), 5))
        dt_js = time.monotonic() - t_pub
        final_err = np.abs(latest["q"] - goal) if latest["q"] is not None else np.full(arm.n, np.inf)
        sim_q = np.asarray(_read_json(out / "ros_sim_status.json").get("q", [np.nan] * arm.n), dtype=float)
        result["trajectory"] = {
            "goal": [round(float(x), 5) for x in goal],
            "reached": reached,
            "time_to_reach_s": round(time_to_reach, 3),
            "final_err_max_rad": round(float(np.max(final_err)), 5),
            "final_err_rad": [round(float(x), 5) for x in final_err],
            "settle_err_trace_rad": trace,
            "sim_final_err_max_rad": round(float(np.max(np.abs(sim_q - goal))), 5),
            "joint_states_received": latest["count"] - count0,
            "joint_states_rate_hz": round((latest["count"] - count0) / dt_js, 1),
        }
        result["halt"] = call("halt")
        result["recover"] = call("recover")
        result["ok"] = bool(result["init"]["success"] and reached and result["halt"]["success"]
                            and result["recover"]["success"])
    finally:
        if client is not None:
            client.destroy_node()
        rclpy.try_shutdown(context=ctx)
        t_stop = time.monotonic()
        result["node_rc"] = _stop_child(node_proc, grace_s=0.0)
        result["node_stop_s"] = round(time.monotonic() - t_stop, 3)
        node_log.close()
        settled = result.get("trajectory", {}).get("final_err_max_rad", float("inf")) < ns.tolerance
        if not (result.get("ok") and settled and result["node_rc"] == 0):
            # the node's warnings (halts, missed replies, a traceback at exit...) say why
            lines = (out / "can_driver_node.log").read_text(errors="replace").splitlines()
            result["node_log_tail"] = lines[-40:]
        t_stop = time.monotonic()
        result["sim_rc"] = _stop_child(sim, grace_s=0.0)
        result["sim_stop_s"] = round(time.monotonic() - t_stop, 3)
        result["duration_s"] = round(time.monotonic() - t_start, 3)
        _write_result(ns.result, result)
    return 0 if result["ok"] else 1


SUITE = ("pingpong", "hil", "ros")


def cmd_suite(ns: argparse.Namespace) -> int:
    """Run every scenario in turn; each writes ``result_<name>.json`` into ``--out``."""
    out = Path(ns.out)
    out.mkdir(parents=True, exist_ok=True)
    bus_args = []
    if ns.interface:
        bus_args += ["--interface", ns.interface]
    if ns.channel:
        bus_args += ["--channel", ns.channel]
    failed = 0
    for name in ns.only or SUITE:
        result_path = out / f"result_{name}.json"
        t0 = time.monotonic()
        _LOG.info("scenario %s: start", name)
        try:
            sub_ns = build_parser().parse_args([name, *bus_args, "--result", str(result_path)])
            rc = int(sub_ns.func(sub_ns))
        except Exception as exc:  # one scenario's crash must not hide the others' results
            _LOG.exception("scenario %s crashed", name)
            _write_result(str(result_path), {"ok": False, "error": repr(exc)})
            rc = 1
        _LOG.info("scenario %s: rc=%d in %.1f s", name, rc, time.monotonic() - t0)
        failed += rc != 0
    return 1 if failed else 0


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of the scenario program."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)

    def command(name: str, summary: str,
                func: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
        """A sub-command running ``func``, with the options every scenario takes."""
        p = sub.add_parser(name, help=summary)
        p.add_argument("--interface", help="python-can interface (default: $CAN_INTERFACE)")
        p.add_argument("--channel", help="python-can channel (default: $CAN_CHANNEL)")
        p.add_argument("--result", help="write the JSON result here as well")
        p.set_defaults(func=func)
        return p

    def frames(p: argparse.ArgumentParser) -> None:  # the echo / pingpong frame ids and count
        p.add_argument("--request-id", type=lambda s: int(s, 0), default=0x123)
        p.add_argument("--reply-id", type=lambda s: int(s, 0), default=0x124)
        p.add_argument("--count", type=int, default=1000)

    def against_sim(p: argparse.ArgumentParser, rate_help: str, reply_help: str) -> None:
        """The arm, the host's cycle rate and reply timeout, the simulator's rate (hil / ros)."""
        p.add_argument("--arm", default="pa10")
        p.add_argument("--rate", type=float, default=50.0, help=rate_help)
        p.add_argument("--sim-rate", type=float, default=200.0,
                       help="simulator physics rate [Hz] (sim default 1000; the guest has one slow CPU)")
        p.add_argument("--reply-timeout", type=float, default=0.5, help=reply_help)

    p = command("echo", "answer frames (child of pingpong)", cmd_echo)
    frames(p)
    p.add_argument("--idle", type=float, default=10.0, help="give up after this long without a frame [s]")

    p = command("pingpong", "round trips between two processes", cmd_pingpong)
    frames(p)
    p.add_argument("--timeout", type=float, default=1.0, help="per round trip [s]")
    p.add_argument("--ready-timeout", type=float, default=60.0, help="echo start-up [s]")

    p = command("hil", "driver core against redarm-sim", cmd_hil)
    against_sim(p, "driver cycle rate [Hz]",
                "driver reply timeout [s] (driver default 0.02; the guest is slow)")
    p.add_argument("--duration", type=float, default=3.0, help="trajectory duration [s]")
    p.add_argument("--hold", type=float, default=1.0, help="hold at the goal afterwards [s]")
    p.add_argument("--ready-timeout", type=float, default=60.0, help="simulator start-up [s]")

    p = command("ros", "can_driver node against redarm-sim, driven over ROS", cmd_ros)
    against_sim(p, "node cycle rate [Hz] (node default 250)",
                "node reply_timeout_s [s] (node default 0.02; the guest is slow)")
    p.add_argument("--watchdog", choices=("true", "false"), default="false",
                   help="node 'watchdog' parameter (node default true; the modules' 100 ms watchdog "
                        "cannot be held by a loaded one-CPU guest)")
    p.add_argument("--duration", type=float, default=3.0, help="trajectory duration [s]")
    p.add_argument("--tolerance", type=float, default=0.01, help="goal reached within [rad]")
    p.add_argument("--ready-timeout", type=float, default=90.0, help="simulator / node start-up [s]")

    p = command("suite", "every scenario in turn, results into --out", cmd_suite)
    p.add_argument("--out", required=True, help="directory for result_<name>.json")
    p.add_argument("--only", nargs="*", choices=SUITE, help="run only these scenarios")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse, run the sub-command, return its exit code."""
    logging.basicConfig(level=logging.INFO, format="[%(name)s %(process)d] %(message)s", stream=sys.stderr)
    ns = build_parser().parse_args(argv)
    return int(ns.func(ns))


if __name__ == "__main__":
    sys.exit(main())
