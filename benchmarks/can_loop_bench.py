"""Cycle rate and period jitter of the 7-joint PowerCube driver loop over the loopback remote bus.

A ``redarm-canbus`` server and a ``redarm-sim --arm pa10`` (pybullet, 1 kHz, one emulated module per
joint) run as separate processes; the arm follows a slow multi-joint sine trajectory throughout.
Two ways of driving it:

* ``core``: :class:`redarm_ros.can.driver_loop.DriverLoop` (the node's loop thread: absolute
  deadlines, one ``PowerCubeArmDriver.cycle()`` per tick: 7 FSTEP_EXT + STARTMOVE + watchdog
  refresh out, 7 extended replies in) running in this process, no ROS;
* ``node``: the ``can_driver`` ROS node as its own process; the numbers are the node's own
  measurements read from its ``/diagnostics`` (windows: the last 2500 periods, the last 500
  cycles' reply latencies), plus the rate at
  which ``/joint_states`` arrive in this process.

Measured per run: achieved cycle rate, absolute period error |period - 1/rate| (median, p99, max),
overruns (ticks skipped because a cycle ended after the next deadline), reply latency (command
sent -> its reply received; median, p99, max), CAN frames per second, replies lost. The physical
ceiling is what a real 1 Mbit/s (or 500 kbit/s) bus allows for one cycle's frames (an 8-byte frame takes
0.11-0.135 ms at 1 Mbit/s: 7 FSTEP commands, 7 replies and one STARTMOVE take about 1.7-2.0 ms).

Run: ``.venv/bin/python benchmarks/can_loop_bench.py [--seconds 30] [--rates 250,500] [--quick]``;
writes ``benchmarks/results/can_loop_bench.md`` unless ``--no-write``. Targets: 250 Hz sustained
with p99 period error < 1 ms; report how close 500 Hz gets. Wall-clock numbers depend on the
machine (2 cores here, shared by the bus server, the simulator and the driver); tests never
assert on them.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.procs import ProcessGroup, python_module_cmd, random_domain_id

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common, also when loaded by path
import bench_common  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "can_loop_bench.md"
REPO = Path(__file__).resolve().parents[1]
ARM_NAME = "pa10"


# ------------------------------------------------------------------------------------------------
# Physical budget of one cycle on a real bus
# ------------------------------------------------------------------------------------------------
def frame_bits(n_data: int) -> tuple[int, int]:
    """Bits of a classic CAN frame with an 11-bit id and ``n_data`` bytes: (no stuffing, worst stuffing).

    SOF 1 + id 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8n + CRC 15 + delimiters/ACK 3 + EOF 7 + IFS 3
    = 47 + 8n; stuffing can add one bit per 4 of the 34 + 8n stuffed bits.
    """
    base = 47 + 8 * n_data
    return base, base + (34 + 8 * n_data - 1) // 4


def cycle_budget_ms(n_joints: int, bitrate: float, watchdog: bool = True) -> tuple[float, float]:
    """(best, worst) bus time of one cycle in ms: n FSTEP_EXT (8 B) + n replies (8 B) + STARTMOVE (2 B)
    (+ watchdog refresh, 2 B)."""
    b8, w8 = frame_bits(8)
    b2, w2 = frame_bits(2)
    k2 = 2 if watchdog else 1
    best = 2 * n_joints * b8 + k2 * b2
    worst = 2 * n_joints * w8 + k2 * w2
    return best / bitrate * 1e3, worst / bitrate * 1e3


# ------------------------------------------------------------------------------------------------
# The stack
# ------------------------------------------------------------------------------------------------
def start_stack(group: ProcessGroup, tmp: Path) -> dict[str, Any]:
    bus = group.start(
        "canbus",
        python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1", "--port", "0"),
        ready=r"REDARM_CANBUS_PORT=(\d+)",
    )
    port = int(bus.ready_match.group(1))  # type: ignore[attr-defined]
    channel = f"ws://127.0.0.1:{port}/"
    group.start(
        "sim",
        python_module_cmd("redarm_ros.sim.hardware", "--arm", ARM_NAME, "--can-interface", "remote",
                          "--can-channel", channel, "--status-file", str(tmp / "sim.json"),
                          "--log-level", "WARNING"),
        ready=r"REDARM_SIM_READY",
        ready_timeout=30,
    )
    return {"interface": "remote", "channel": channel}


def sine_trajectory(arm: Any, seconds: float, dt: float = 0.25) -> tuple[list[float], np.ndarray]:
    """Times (s) and points (k, n) of a slow sine on every joint, within limits and speeds."""
    t = np.arange(dt, seconds + dt, dt)
    amp = np.minimum(0.3, 0.25 * (arm.upper - arm.lower))
    period = np.maximum(4.0, 2 * np.pi * amp / (0.5 * arm.max_vel))  # at most half the speed limit
    q = amp * np.sin(2 * np.pi * t[:, None] / period)
    return t.tolist(), q


@dataclass
class RunResult:
    mode: str
    rate: float
    seconds: float
    achieved_hz: float
    err_median_ms: float
    err_p99_ms: float
    err_max_ms: float
    overruns: int
    lat_median_ms: float
    lat_p99_ms: float
    lat_max_ms: float
    frames_per_s: float
    lost: int
    samples: int
    busy_median_ms: float = float("nan")
    busy_p99_ms: float = float("nan")
    js_hz: float | None = None
    periods_ms: np.ndarray | None = None  # raw periods for the plot (core: the loop's window; node:
    # gaps between the header stamps of the /joint_states received here)


def run_core(can_kwargs: dict[str, Any], rate: float, seconds: float) -> RunResult:
    """DriverLoop + PowerCubeArmDriver in this process (no ROS)."""
    from redarm_ros.can.bus import open_bus
    from redarm_ros.can.driver_core import PowerCubeArmDriver
    from redarm_ros.can.driver_loop import DriverLoop, LoopConfig, LoopState
    from redarm_ros.kinematics import load_arm

    arm = load_arm(ARM_NAME)

    def factory(bus: Any) -> PowerCubeArmDriver:
        return PowerCubeArmDriver(bus, list(range(1, arm.n + 1)), arm.lower, arm.upper, arm.max_vel,
                                  arm.max_acc, reply_timeout_s=0.02, max_missed=5, watchdog_refresh=True,
                                  enable_watchdog=True)

    loop = DriverLoop(factory, lambda: open_bus(**can_kwargs), arm.n, LoopConfig(rate_hz=rate))
    loop.start()
    try:
        end = time.monotonic() + 30
        while loop.state is not LoopState.IDLE and time.monotonic() < end:
            time.sleep(0.05)
        ok, msg = loop.request("init", 60)
        if not ok:
            raise RuntimeError(f"init failed: {msg}")
        times, pts = sine_trajectory(arm, seconds + 2)
        loop.commands.set_trajectory(list(range(arm.n)), times, pts, time.monotonic())
        time.sleep(1.0)  # settle into the stream, then measure a fresh window
        loop.reset_measurements()
        lost0 = sum(s.lost for s in loop.driver.stats)
        snap0 = loop.snapshot()
        t0 = time.monotonic()
        time.sleep(seconds)
        snap = loop.snapshot()
        with loop.stats._lock:  # the window's raw start-to-start periods (what snap.period summarises)
            periods_ms = np.fromiter(loop.stats._periods, dtype=float) * 1e3
        dt = time.monotonic() - t0
        lost = sum(s.lost for s in loop.driver.stats) - lost0
        if snap.state is not LoopState.RUNNING:
            raise RuntimeError(f"loop left RUNNING: {snap.state} {snap.reason}")
    finally:
        loop.stop()
    per, lat = snap.period, snap.latency or {"median_ms": np.nan, "p99_ms": np.nan, "max_ms": np.nan}
    frames = (snap.frames_tx + snap.frames_rx - snap0.frames_tx - snap0.frames_rx) / dt
    return RunResult("core", rate, seconds, per["rate_hz"], per["period_err_median_ms"],
                     per["period_err_p99_ms"], per["period_err_max_ms"], snap.overruns - snap0.overruns,
                     lat["median_ms"], lat["p99_ms"], lat["max_ms"], frames, lost, int(per["samples"]),
                     busy_median_ms=per["busy_median_ms"], busy_p99_ms=per["busy_p99_ms"],
                     periods_ms=periods_ms)


def run_node(group: ProcessGroup, can_kwargs: dict[str, Any], rate: float, seconds: float) -> RunResult:
    """The can_driver node as a process; its /diagnostics and /joint_states read from here."""
    import rclpy
    from builtin_interfaces.msg import Duration
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from redarm_ros.kinematics import load_arm
    from redarm_ros.nodes._common import call_resending
    from redarm_ros.procs import poll_until

    arm = load_arm(ARM_NAME)
    params = {"arm": ARM_NAME, "can.interface": can_kwargs["interface"], "can.channel": can_kwargs["channel"],
              "rate_hz": f"{rate:.1f}", "joint_states_rate_hz": "0"}  # every cycle: its stamps are measured
    ros_args = ["--ros-args"] + [a for k, v in params.items() for a in ("-p", f"{k}:={v}")]
    cmd = python_module_cmd("redarm_ros.nodes.can_driver", *ros_args)
    node_proc = group.start(f"can_driver_{rate:g}", cmd, ready=r"CAN bus connected", ready_timeout=30)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=group.domain_id)
    node = rclpy.create_node("can_loop_bench", context=ctx)
    lock = threading.Lock()
    js_stamps: list[float] = []
    js_header: list[float] = []  # header stamps: when the node's cycle measured (for the plot)
    diags: list[DiagnosticArray] = []

    def on_js(msg: JointState) -> None:
        with lock:
            js_stamps.append(time.monotonic())
            js_header.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)

    def on_diag(msg: DiagnosticArray) -> None:
        with lock:
            diags.append(msg)

    node.create_subscription(JointState, "/joint_states", on_js, 100)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    pub = node.create_publisher(JointTrajectory, "/joint_command", 10)
    cli = node.create_client(Trigger, "/can_driver/init")
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop, th = bench_common.spin_in_background(ex)
    try:
        if not cli.wait_for_service(timeout_sec=20):
            raise RuntimeError("/can_driver/init not available")
        resp = call_resending(cli, Trigger.Request(), poll_until, 60.0)
        if resp is None or not resp.success:
            raise RuntimeError(f"init failed: {resp if resp is not None else 'timeout'}")
        times, pts = sine_trajectory(arm, seconds + 12)
        msg = JointTrajectory(joint_names=arm.joint_names)
        for t, q in zip(times, pts, strict=True):
            msg.points.append(JointTrajectoryPoint(
                positions=q.tolist(), time_from_start=Duration(sec=int(t), nanosec=int((t % 1) * 1e9))))
        pub.publish(msg)
        time.sleep(1.0)
        with lock:
            n0 = len(js_stamps)
            d0 = len(diags)
        t0 = time.monotonic()
        time.sleep(seconds)
        t1 = time.monotonic()
        with lock:
            n1 = len(js_stamps)
            last = diags[-1] if len(diags) > d0 else None
            js_periods_ms = np.diff(np.asarray(js_header[n0:n1], dtype=float)) * 1e3
        if last is None:
            raise RuntimeError("no /diagnostics received")
        st = {s.name: {kv.key: kv.value for kv in s.values} for s in last.status}
        loop = st["can_driver: loop"]
        if loop["state"] != "running":
            raise RuntimeError(f"node not running: {loop}")
        lost = sum(int(v.get("lost", 0)) for k, v in st.items() if k.startswith("can_driver: module"))
        def f(key: str) -> float:
            return float(loop.get(key, "nan"))

        return RunResult(
            "node", rate, seconds, f("rate_hz_achieved"), f("period_error_median_ms"),
            f("period_error_p99_ms"), f("period_error_max_ms"), int(loop["overruns"]),
            f("reply_latency_median_ms"), f("reply_latency_p99_ms"), f("reply_latency_max_ms"),
            f("frames_per_s"), lost, min(2500, int(loop["cycles"])), busy_median_ms=f("cycle_busy_median_ms"),
            busy_p99_ms=f("cycle_busy_p99_ms"), js_hz=(n1 - n0) / (t1 - t0), periods_ms=js_periods_ms,
        )
    finally:
        stop.set()
        th.join(2)
        ex.shutdown(timeout_sec=1)
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        group.stop(node_proc)


# ------------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------------
HEADER = ("| mode | target Hz | achieved Hz | period err median ms | p99 ms | max ms | overruns | "
          "cycle busy median ms | p99 ms | reply latency median ms | p99 ms | max ms | frames/s | "
          "replies lost | /joint_states Hz |")
SEP = "|" + "---|" * 15


def row(r: RunResult) -> str:
    js = "-" if r.js_hz is None else f"{r.js_hz:.1f}"
    return (f"| {r.mode} | {r.rate:g} | {r.achieved_hz:.1f} | {r.err_median_ms:.3f} | {r.err_p99_ms:.3f} | "
            f"{r.err_max_ms:.3f} | {r.overruns} | {r.busy_median_ms:.3f} | {r.busy_p99_ms:.3f} | "
            f"{r.lat_median_ms:.3f} | {r.lat_p99_ms:.3f} | "
            f"{r.lat_max_ms:.3f} | {r.frames_per_s:.0f} | {r.lost} | {js} |")


def budget_table(n: int) -> list[str]:
    lines = ["| bus | one cycle on the wire (ms) | ceiling (Hz) |", "|---|---|---|"]
    for name, rate in (("1 Mbit/s", 1e6), ("500 kbit/s", 5e5)):
        best, worst = cycle_budget_ms(n, rate)
        lines.append(f"| {name} | {best:.2f} - {worst:.2f} | {1e3 / worst:.0f} - {1e3 / best:.0f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="measured seconds per run (default 30)")
    ap.add_argument("--quick", action="store_true", help="5 s per run")
    ap.add_argument("--rates", default="250,500", help="comma list of cycle rates (Hz)")
    ap.add_argument("--modes", default="core,node", help="comma list: core, node")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    bench_common.add_plot_dir(ap)
    args = ap.parse_args(argv)
    seconds = 5.0 if args.quick else args.seconds
    rates = [float(r) for r in args.rates.split(",") if r]
    modes = [m for m in args.modes.split(",") if m]
    domain = random_domain_id()
    # In-process rclpy (node mode) obeys the network rule too.
    os.environ.update(FASTDDS_BUILTIN_TRANSPORTS="SHM", ROS_DOMAIN_ID=str(domain),
                      ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    sys.setswitchinterval(5e-4)  # as the node's main() does
    results: list[RunResult] = []
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="can_loop_bench_") as tmp:
        os.environ["ROS_LOG_DIR"] = tmp
        with ProcessGroup(domain_id=domain, pythonpath=[REPO], sink=lambda _line: None) as group:
            can_kwargs = start_stack(group, Path(tmp))
            for mode in modes:
                for rate in rates:
                    print(f"running {mode} at {rate:g} Hz for {seconds:g} s ...", flush=True)
                    if mode == "core":
                        r = run_core(can_kwargs, rate, seconds)
                    else:
                        r = run_node(group, can_kwargs, rate, seconds)
                    results.append(r)
                    print(row(r), flush=True)
    load_after = os.getloadavg()[0]
    run = "\n".join([
        f"## Run {time.strftime('%Y-%m-%d %H:%M')} — {seconds:g} s per mode and rate, 1-min load average "
        f"{load_before:.2f} before / {load_after:.2f} after",
        "",
        HEADER,
        SEP,
        *[row(r) for r in results],
        "",
        f"Command: `.venv/bin/python benchmarks/can_loop_bench.py --seconds {seconds:g} --rates "
        f"{args.rates} --modes {args.modes}`",
        "",
    ])
    print()
    print(run)
    links: list[str] = []
    plot_dir = args.plot_dir or (None if args.no_write else RESULTS.parent)
    if plot_dir is not None:
        size = f"can_loop_bench.py: {seconds:g} s per mode and rate"
        pngs = write_plots(results, plot_dir, size, f"{load_before:.2f} (1 min)")
        links = [*bench_common.plots().markdown_links(pngs, RESULTS.parent, "of the newest run"), ""]
        print("\n".join(links))
    if not args.no_write:
        # Newest run first; earlier runs are kept: on a shared machine the spread is the result.
        earlier: list[str] = []
        if RESULTS.exists():
            old = RESULTS.read_text()
            earlier = ["## Run " + part.strip() + "\n" for part in old.split("\n## Run ")[1:]]
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text("\n".join([results_preamble(), *links, run, *earlier]))
        print(f"wrote {RESULTS}")
    return 0


PERIOD_LABELS = {
    "core": "core: DriverLoop start-to-start periods",
    "node": "node: gaps of /joint_states header stamps (a message lost in DDS doubles one)",
}


def write_plots(results: list[RunResult], out_dir: Path, run: str, load_before: str) -> list[Path]:
    """can_loop_bench_period_<rate>hz.png: histogram of the periods of every mode at that rate."""
    plots = bench_common.plots()
    out = []
    for rate in dict.fromkeys(r.rate for r in results):
        series = {PERIOD_LABELS.get(r.mode, r.mode): r.periods_ms for r in results
                  if r.rate == rate and r.periods_ms is not None}
        if series:
            out.append(plots.period_histogram(
                out_dir / f"can_loop_bench_period_{rate:g}hz.png", series, 1e3 / rate,
                title=f"CAN driver loop at {rate:g} Hz: cycle periods (7 PowerCube modules, loopback bus)",
                caption=plots.run_caption(run, load_before)))
    return out


def results_preamble(n: int = 7) -> str:
    """The fixed part of the results file: setup, definitions, the physical ceiling."""
    return "\n".join([
        "# CAN driver loop benchmark (`benchmarks/can_loop_bench.py`)",
        "",
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; other jobs "
        "share the CPUs (see each run's load average). Arm "
        f"{ARM_NAME} (7 modules) in `redarm-sim` (pybullet 1 kHz) over the loopback python-can-remote bus "
        "(`redarm-canbus`, 127.0.0.1); the arm follows a slow sine on every joint. Period error = "
        "|start-to-start period - 1/rate| (periods after skipped ticks excluded, those are counted as "
        "overruns); cycle busy = time from a cycle's start to the end of its work (9 frames out, 7 replies "
        "in); reply latency = FSTEP_EXT sent -> its extended reply received. `core` = DriverLoop + "
        "PowerCubeArmDriver in the benchmark process; `node` = the can_driver node process, numbers from "
        "its /diagnostics (periods: last 2500 cycles, latencies: last 500; replies lost since start).",
        "",
        "Physical ceiling for one cycle (7 FSTEP_EXT + 7 replies of 8 bytes, STARTMOVE and watchdog "
        "refresh of 2 bytes, 11-bit ids, without/with worst-case bit stuffing):",
        "",
        *budget_table(n),
        "",
    ])


if __name__ == "__main__":
    raise SystemExit(main())
