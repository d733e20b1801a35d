"""Soak test of the CAN path: the driver streaming at 250 Hz for 10 minutes on a machine kept busy.

What runs (separate processes over the loopback CAN bus, as in a deployment): ``redarm-canbus``,
``redarm-sim --arm pa10`` (pybullet, 1 kHz, seven emulated PowerCube modules with their 100 ms
watchdog), the ``can_driver`` node at 250 Hz, and this benchmark as an rclpy client that calls
``~/init`` and streams joint targets on ``/joint_command_state`` at 100 Hz (a slow sine on every
joint; joint 2's amplitude reaches past its joint limit, so the arm brakes onto that soft limit
every few seconds). Meanwhile:

* a CPU hog of twice the cores (``sh -c 'while :; do :; done'``, normal priority) runs throughout;
* every 30 s (``--newcomer-period``) a new Python process starts (imports numpy and rclpy, creates a
  node, spins 2 s: what the controller does at bring-up); a shorter period stresses that faster.

Reported (table row per run, with the load average): halts of the driver (``HALTED:`` lines; each is
answered with ``~/recover`` so the run goes on), missed replies (sum of the modules' ``lost``),
period error p99 / max of every cycle since the start (the node's since-start histogram, overruns
included), overruns, reply latency, limit faults (modules entering ERROR|BEYOND_SOFT, from the
simulator's status), watchdog trips (modules entering COMM_ERROR), implausible positions, the
simulator's own lag, its longest garbage collection (CPU) and request-to-reply time, and the
scheduling the real-time chain got. Target on a 2-core machine: 0 halts
and 0 faults.

Each missed reply is traced: the driver logs the wall time of the first cycle of a run of misses, the
bus server every frame it read 5 ms or more after its sender's stamp (slow hop), the simulator every
request read 5 ms or more after it was sent, every reply sent 5 ms or more after its request was read
and every physics wake-up 5 ms or more late; the benchmark notes when it started the hog and each new
process, and samples every 25 ms the run-queue wait of every thread of the bus server, the simulator
and the driver (``/proc/<pid>/task/*/schedstat``; waits of 4 ms or more are kept). For each miss it
prints what happened within 1 s of it (run-queue waits: 0.1 s), the timeline. Each run also records
whether the kernel shares the CPU per session first (``kernel.sched_autogroup_enabled``; every stack
process and the hog run in a session of their own) and the time the hypervisor stole from the machine.

Run: ``.venv/bin/python benchmarks/soak_bench.py`` (10 min; ``--quick`` = 60 s smoke, as ``make bench``
runs it; ``--no-hog``; ``--realtime-priority 0`` runs the chain and the driver node at normal
priority, nice 0; ``--hog 1`` keeps one core busy; ``--slice-ms MS`` the time slice of the threads on
the reply path, 0 = the kernel's default). The results give each run's longest run-queue waits of
those threads.
Writes ``benchmarks/results/soak_bench.md`` (every run kept, newest first) unless ``--no-write``.
What it does not cover: a real CAN bus or real modules, other arms, faults injected on purpose (the
HIL tests do those), memory growth.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from redarm_ros.procs import (
    ManagedProcess,
    ProcessGroup,
    descendants,
    group_members,
    python_module_cmd,
    random_domain_id,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common, also when loaded by path
import bench_common  # noqa: E402
from host_speed import HostSpeedProbe  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "soak_bench.md"
REPO = Path(__file__).resolve().parents[1]
ARM_NAME = "pa10"
STREAM_HZ = 100.0
NEWCOMER_PERIOD_S = 30.0
SCHEDSTAT_PERIOD_S = 0.025  # run-queue waits sampled this often
RUNQ_WAIT_EVENT_MS = 4.0  # a thread's run-queue wait in one sample period kept as an event
TIMELINE_S = 1.0  # a miss's timeline: events this close to it
RUNQ_TIMELINE_S = 0.1  # (run-queue waits: this close)
MAX_TIMELINES = 8  # timelines written to the results
WALL_RE = re.compile(r"wall time (\d+\.\d+)")
NEWCOMER = """
import time, numpy, rclpy
rclpy.init()
node = rclpy.create_node("soak_newcomer")
end = time.monotonic() + 2.0
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
node.destroy_node()
rclpy.shutdown()
"""


@dataclass
class Observed:
    """What the monitor thread saw."""

    halts: int = 0
    recoveries: int = 0
    recover_failures: int = 0
    limit_faults: int = 0
    watchdog_trips: int = 0
    error_modules: list[str] = field(default_factory=list)
    newcomers: int = 0
    loads: list[float] = field(default_factory=list)
    js_count: int = 0
    js_max_gap_ms: float = 0.0
    js_gaps_ms: list[float] = field(default_factory=list)  # header-stamp gaps of /joint_states (plot)
    stream_sent: int = 0
    last_diag: dict[str, dict[str, str]] = field(default_factory=dict)
    events: list[tuple[float, str]] = field(default_factory=list)  # (wall time, what): the benchmark's own
    misses: list[tuple[float, str]] = field(default_factory=list)  # (wall time, driver line)
    timelines: list[str] = field(default_factory=list)  # one text block per miss
    hop_lines: list[tuple[float, str]] = field(default_factory=list)  # the bus server's slow hops
    runq_waits: list[tuple[float, str]] = field(default_factory=list)  # the sampler's events


class SchedstatSampler:
    """Samples the run-queue wait of every thread of some process groups and their leaders'
    descendants (Linux schedstat) in a thread; waits of :data:`RUNQ_WAIT_EVENT_MS` or more within one
    sample period become events."""

    def __init__(self, groups: dict[str, int]) -> None:
        self.groups = groups  # label -> process group id
        self.events: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="schedstat", daemon=True)

    def start(self) -> SchedstatSampler:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def _tasks(self) -> list[tuple[str, str]]:
        out = []
        for label, pgid in self.groups.items():
            for pid in sorted(set(group_members(pgid)) | set(descendants(pgid))):
                try:
                    tids = os.listdir(f"/proc/{pid}/task")
                except OSError:
                    continue
                for tid in tids:
                    try:
                        comm = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
                    except OSError:
                        continue
                    out.append((f"{label}:{comm}({tid})", f"/proc/{pid}/task/{tid}/schedstat"))
        return out

    def _run(self) -> None:
        last: dict[str, float] = {}
        tasks: list[tuple[str, str]] = []
        next_list = 0.0
        while not self._stop.wait(SCHEDSTAT_PERIOD_S):
            now = time.time()
            if now >= next_list:
                tasks, next_list = self._tasks(), now + 1.0
            for name, path in tasks:
                try:
                    wait_ns = int(Path(path).read_text().split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                before = last.get(name)
                last[name] = wait_ns
                if before is not None and (wait_ns - before) / 1e6 >= RUNQ_WAIT_EVENT_MS:
                    self.events.append((now, f"run-queue wait {(wait_ns - before) / 1e6:.1f} ms of {name} "
                                             f"in the {SCHEDSTAT_PERIOD_S * 1e3:.0f} ms before"))


def line_events(proc: ManagedProcess, label: str, pattern: str) -> list[tuple[float, str]]:
    """(wall time, line) of every output line of ``proc`` holding ``pattern`` and a wall time."""
    out = []
    for line in proc.output():
        if pattern in line and (m := WALL_RE.search(line)):
            out.append((float(m.group(1)), f"{label}: {line.split(pattern, 1)[-1].strip()[:110]}"))
    return out


HOP_RE = re.compile(r"read ([0-9.]+) ms later")
READ_RE = re.compile(r"request sent to read \(bus thread since: ran ([0-9.]+) ms, run queue ([0-9.]+) ms\) "
                     r"([0-9.]+) ms")
ANSWER_RE = re.compile(r"request read to reply sent ([0-9.]+) ms")


RUNQ_RE = re.compile(r"run-queue wait ([0-9.]+) ms of (\w+):([^(]+)\(")
#: The threads every reply passes through (label:thread name as the sampler reports them).
REPLY_PATH = ("canbus:canbus-relay", "sim:sim-bus", "driver:can-cycle")


def worst_waits(events: list[tuple[float, str]]) -> str:
    """The longest run-queue wait (ms, per sample) and the count of waits of
    :data:`RUNQ_WAIT_EVENT_MS` or more of each thread on the reply path, e.g. ``sim:sim-bus 6.1 (2)``."""
    worst = {name: (0.0, 0) for name in REPLY_PATH}
    for _t, ev in events:
        if (m := RUNQ_RE.search(ev)) and (name := f"{m.group(2)}:{m.group(3)}") in worst:
            ms, n = worst[name]
            worst[name] = (max(ms, float(m.group(1))), n + 1)
    return ", ".join(f"{name} {ms:.1f} ({n})" for name, (ms, n) in worst.items())


def where_it_waited(t_miss: float, events: list[tuple[float, str]]) -> str:
    """One line on the missed cycle's requests (events up to the reply timeout after it): the bus
    server's hop, the simulator's read (and how much of it its bus thread ran or waited for a CPU; the
    rest it slept: for the frame, or for the interpreter lock), the simulator's answer."""
    hop = read = ran = queued = answer = 0.0
    for t, ev in events:
        if not -0.002 <= t - t_miss <= 0.025:
            continue
        if ev.startswith("canbus") and (m := HOP_RE.search(ev)):
            hop = max(hop, float(m.group(1)))
        elif (m := READ_RE.search(ev)) and float(m.group(3)) > read:
            ran, queued, read = (float(g) for g in m.groups())
        elif m := ANSWER_RE.search(ev):
            answer = max(answer, float(m.group(1)))
    if not (hop or read or answer):
        return "  no hop, read or answer of this cycle took 5 ms or more (the driver's side)"
    slept = max(0.0, read - hop - ran - queued)
    return (f"  bus server hop {hop:.1f} ms; simulator read {read:.1f} ms (its bus thread ran {ran:.1f}, "
            f"waited for a CPU {queued:.1f}, slept {slept:.1f} beyond the hop); answer {answer:.1f} ms")


def timelines(misses: list[tuple[float, str]], events: list[tuple[float, str]]) -> list[str]:
    """For each miss, where its requests waited and the events within :data:`TIMELINE_S` of it, in
    time order, as a text block."""
    blocks = []
    events = sorted(events)
    for t_miss, what in misses:
        lines = [f"miss at wall time {t_miss:.4f}: {what}", where_it_waited(t_miss, events)]
        for t, ev in events:
            near = RUNQ_TIMELINE_S if ev.startswith("run-queue") else TIMELINE_S
            if abs(t - t_miss) <= near:
                lines.append(f"  {(t - t_miss) * 1e3:+8.1f} ms  {ev}")
        blocks.append("\n".join(lines))
    return blocks


def slice_args(slice_ms: float | None) -> list[str]:
    """``--slice-ms`` for the bus server and the simulator (none: their default)."""
    return [] if slice_ms is None else ["--slice-ms", f"{slice_ms:g}"]


def start_chain(group: ProcessGroup, tmp: Path, prio: int, physics: str = "process",
                slice_ms: float | None = None) -> tuple[str, Path, ManagedProcess, ManagedProcess]:
    bus = group.start("canbus", python_module_cmd("redarm_ros.can.bus_server", "--host", "127.0.0.1",
                                                  "--port", "0", "--realtime-priority", str(prio),
                                                  *slice_args(slice_ms)),
                      ready=r"REDARM_CANBUS_PORT=(\d+)")
    channel = f"ws://127.0.0.1:{int(bus.ready_match.group(1))}/"  # type: ignore[attr-defined]
    status = tmp / "sim.json"
    sim = group.start("sim", python_module_cmd("redarm_ros.sim.hardware", "--arm", ARM_NAME,
                                               "--can-interface", "remote", "--can-channel", channel,
                                               "--status-file", str(status), "--status-rate", "10",
                                               "--realtime-priority", str(prio), "--physics", physics,
                                               *slice_args(slice_ms)),
                ready=r"REDARM_SIM_READY", ready_timeout=60)
    return channel, status, bus, sim


def start_driver(group: ProcessGroup, channel: str, prio: int,
                 slice_ms: float | None = None) -> ManagedProcess:
    params = {"arm": ARM_NAME, "can.interface": "remote", "can.channel": channel, "rate_hz": "250.0",
              "realtime_priority": str(prio), "joint_states_rate_hz": "0"}  # every cycle: stamps measured
    if slice_ms is not None:
        params["slice_ms"] = f"{float(slice_ms)!r}"
    if prio == 0:  # normal priority throughout: the node's own process at nice 0 too, not its default -10
        params["nice"] = "0"
    ros_args = ["--ros-args"] + [a for k, v in params.items() for a in ("-p", f"{k}:={v}")]
    drv = group.start("can_driver", python_module_cmd("redarm_ros.nodes.can_driver", *ros_args),
                      ready=r"can_driver ready", ready_timeout=60)
    drv.wait_for_line(r"CAN bus connected", 60, from_start=True)
    return drv


def stream_target(arm: Any, t: float) -> np.ndarray:
    """The streamed joint target at time ``t`` (s): slow sines; joint 2 reaches past its upper limit."""
    amp = np.minimum(0.3, 0.25 * (arm.upper - arm.lower))
    period = np.maximum(6.0, 2 * np.pi * amp / (0.5 * arm.max_vel))
    q = amp * np.sin(2 * np.pi * t / period)
    # Joint 2: 0.5 rad/s peak speed around 1.3 rad, up to 0.3 rad past the limit (clamped by the driver).
    q[1] = (arm.upper[1] - 0.3) + 0.6 * np.sin(2 * np.pi * t / 8.0)
    return q


def soak(seconds: float, hog: int, prio: int, newcomer_period: float = NEWCOMER_PERIOD_S,
         physics: str = "process",
         slice_ms: float | None = None) -> tuple[Observed, dict[str, Any], dict[str, Any]]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    from redarm_ros.kinematics import load_arm
    from redarm_ros.nodes._common import call_resending
    from redarm_ros.procs import poll_until

    arm = load_arm(ARM_NAME)
    obs = Observed()
    domain = random_domain_id()
    os.environ.update(FASTDDS_BUILTIN_TRANSPORTS="SHM", ROS_DOMAIN_ID=str(domain),
                      ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    with tempfile.TemporaryDirectory(prefix="soak_bench_") as tmpdir, \
            ProcessGroup(domain_id=domain, pythonpath=[REPO], sink=lambda _line: None,
                         log_dir=Path(tmpdir) / "ros_log") as group:
        tmp = Path(tmpdir)
        os.environ["ROS_LOG_DIR"] = str(tmp / "ros_log")
        channel, status_file, bus_proc, sim_proc = start_chain(group, tmp, prio, physics, slice_ms)
        driver = start_driver(group, channel, prio, slice_ms)
        sampler = SchedstatSampler({"canbus": bus_proc.pid, "sim": sim_proc.pid, "driver": driver.pid})
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=domain)
        node = rclpy.create_node("soak_bench", context=ctx)
        lock = threading.Lock()
        js_last = [0.0]

        def on_js(msg: JointState) -> None:
            t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            with lock:
                if js_last[0] and obs.js_count:
                    obs.js_max_gap_ms = max(obs.js_max_gap_ms, (t - js_last[0]) * 1e3)
                    obs.js_gaps_ms.append((t - js_last[0]) * 1e3)
                js_last[0] = t
                obs.js_count += 1

        def on_diag(msg: DiagnosticArray) -> None:
            with lock:
                obs.last_diag = {s.name: {kv.key: kv.value for kv in s.values} for s in msg.status}

        node.create_subscription(JointState, "/joint_states", on_js, 200)
        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
        pub = node.create_publisher(JointState, "/joint_command_state", 10)
        clients = {a: node.create_client(Trigger, f"/can_driver/{a}") for a in ("init", "recover")}
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        stop, _ = bench_common.spin_in_background(ex)

        def call(action: str, timeout: float = 60.0) -> bool:
            cli = clients[action]
            if not cli.wait_for_service(timeout_sec=30.0):
                return False
            resp = call_resending(cli, Trigger.Request(), poll_until, timeout)
            return resp is not None and bool(resp.success)

        hogs: list[ManagedProcess] = []
        try:
            if not call("init"):
                raise RuntimeError("~/init failed")
            sampler.start()
            for i in range(hog):
                hogs.append(group.start(f"hog{i}", ["sh", "-c", "while :; do :; done"]))
                obs.events.append((time.time(), f"bench: hog {i} started"))
            t0 = time.monotonic()
            next_pub = t0
            next_newcomer = t0 + 5.0
            next_poll = t0
            halts_seen = 0
            prev_flags: dict[int, set[str]] = {}
            newcomers: list[subprocess.Popen[bytes]] = []
            while (now := time.monotonic()) - t0 < seconds:
                if now >= next_pub:
                    q = stream_target(arm, now - t0)
                    pub.publish(JointState(name=list(arm.joint_names), position=q.tolist()))
                    obs.stream_sent += 1
                    next_pub = max(next_pub + 1.0 / STREAM_HZ, now)
                if now >= next_newcomer:
                    newcomers.append(subprocess.Popen([sys.executable, "-c", NEWCOMER],
                                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
                    obs.newcomers += 1
                    obs.events.append((time.time(), f"bench: new process {obs.newcomers} started"))
                    next_newcomer += newcomer_period
                if now >= next_poll:
                    next_poll = now + 0.2
                    obs.loads.append(os.getloadavg()[0])
                    newcomers = [p for p in newcomers if p.poll() is None]
                    halts = sum("HALTED:" in line for line in driver.output())
                    if halts > halts_seen:
                        obs.halts += halts - halts_seen
                        halts_seen = halts
                        if call("recover"):
                            obs.recoveries += 1
                        else:
                            obs.recover_failures += 1
                    try:
                        st = json.loads(status_file.read_text())
                    except (OSError, ValueError):
                        st = None
                    for m in (st or {}).get("modules", []):
                        flags = set(m["flags"])
                        before = prev_flags.get(m["id"], set())
                        if "BEYOND_SOFT" in flags and "BEYOND_SOFT" not in before:
                            obs.limit_faults += 1
                            obs.error_modules.append(f"{m['id']}:BEYOND_SOFT")
                        if "COMM_ERROR" in flags and "COMM_ERROR" not in before:
                            obs.watchdog_trips += 1
                            obs.error_modules.append(f"{m['id']}:COMM_ERROR")
                        prev_flags[m["id"]] = flags
                time.sleep(max(0.0, min(next_pub, next_poll) - time.monotonic()))
            time.sleep(1.0)  # a last diagnostics message after the run
            sim_status = json.loads(status_file.read_text())
            for p in newcomers:
                p.wait(30)
            obs.misses = line_events(driver, "driver", "missed replies")
            obs.hop_lines = line_events(bus_proc, "canbus", "slow hop:")
            events = [*obs.events, *sampler.events, *obs.hop_lines, *line_events(sim_proc, "sim", "slow:")]
            obs.timelines = timelines(obs.misses, events)
            obs.runq_waits = sampler.events
        finally:
            sampler.stop()
            for h in hogs:
                group.stop(h)
            stop.set()
            ex.shutdown(timeout_sec=1)
            node.destroy_node()
            rclpy.shutdown(context=ctx)
        with lock:
            diag = dict(obs.last_diag)
        return obs, diag, sim_status


@dataclass
class Row:
    seconds: float
    hog: int
    prio: int
    load_mean: float
    load_max: float
    halts: int
    lost: int
    cycles: int
    overruns: int
    p99_ms: float
    max_ms: float
    lat_p99_ms: float
    lat_max_ms: float
    limit_faults: int
    watchdog_trips: int
    implausible: int
    js_hz: float
    js_max_gap_ms: float
    sim_max_lag_ms: float
    sim_resyncs: int
    newcomers: int
    scheduling: str
    sim_gc_max_pause_ms: float
    sim_gc_collections: int
    sim_reply_max_ms: float


HEADER = ("| duration | hog | RT prio | load avg mean / max | halts | missed replies | cycles | overruns | "
          "period err p99 / max ms | reply latency p99 / max ms | limit faults | watchdog trips | "
          "implausible | /joint_states Hz, max gap ms | sim max lag ms, resyncs | new processes |")
SEP = "|" + "---|" * 16


def autogroup_setting() -> str:
    """The kernel's per-session CPU grouping (``kernel.sched_autogroup_enabled``): with it on, the CPU
    is shared between sessions first and between the threads of a session second. Every stack process
    and the hog run in a session of their own."""
    try:
        on = Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return "autogroup: not in this kernel"
    return "autogroup on (CPU shared per session)" if on else "autogroup off (CPU shared per thread)"


def steal_ticks() -> int:
    """CPU time the hypervisor gave to others while this machine's CPUs wanted it (/proc/stat, ticks)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
        return int(fields[8])
    except (OSError, IndexError, ValueError):
        return 0


def row_text(r: Row) -> str:
    return (f"| {r.seconds:g} s | {r.hog} | {r.prio} | {r.load_mean:.2f} / {r.load_max:.2f} | {r.halts} | "
            f"{r.lost} | {r.cycles} | {r.overruns} | {r.p99_ms:.2f} / {r.max_ms:.2f} | "
            f"{r.lat_p99_ms:.2f} / {r.lat_max_ms:.2f} | {r.limit_faults} | {r.watchdog_trips} | "
            f"{r.implausible} | {r.js_hz:.1f}, {r.js_max_gap_ms:.1f} | {r.sim_max_lag_ms:.1f}, "
            f"{r.sim_resyncs} | {r.newcomers} |")


def summarise(seconds: float, hog: int, prio: int, obs: Observed, diag: dict[str, dict[str, str]],
              sim: dict[str, Any]) -> Row:
    loop = diag.get("can_driver: loop", {})
    mods = [v for k, v in diag.items() if k.startswith("can_driver: module")]

    def f(key: str) -> float:
        return float(loop.get(key, "nan"))

    c = sim.get("counters", {})
    return Row(
        seconds=seconds, hog=hog, prio=prio,
        load_mean=float(np.mean(obs.loads)) if obs.loads else float("nan"),
        load_max=float(np.max(obs.loads)) if obs.loads else float("nan"),
        halts=obs.halts, lost=sum(int(m.get("lost", 0)) for m in mods), cycles=int(f("cycles")),
        overruns=int(f("overruns")), p99_ms=f("period_error_p99_total_ms"),
        max_ms=f("period_error_max_total_ms"),
        lat_p99_ms=f("reply_latency_p99_ms"), lat_max_ms=f("reply_latency_max_ms"),
        limit_faults=obs.limit_faults, watchdog_trips=obs.watchdog_trips,
        implausible=int(f("implausible_positions")) if "implausible_positions" in loop else 0,
        js_hz=obs.js_count / seconds, js_max_gap_ms=obs.js_max_gap_ms,
        sim_max_lag_ms=float(c.get("max_lag_ms", float("nan"))), sim_resyncs=int(c.get("resyncs", 0)),
        newcomers=obs.newcomers, scheduling=loop.get("cycle_scheduling", "-"),
        sim_gc_max_pause_ms=float(c.get("gc_max_pause_ms", float("nan"))),
        sim_gc_collections=int(c.get("gc_collections", 0)),
        sim_reply_max_ms=float(c.get("reply_latency_max_ms", float("nan"))),
    )


def sim_counts(sim: dict[str, Any]) -> str:
    c = sim.get("counters", {})
    return (f"{c.get('slow_reads', 0)} requests read >= 5 ms after sending, {c.get('slow_replies', 0)} "
            f"replies >= 5 ms after reading, {c.get('lag_spikes', 0)} physics wake-ups >= 5 ms late")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="soak duration (default 600 s)")
    ap.add_argument("--quick", action="store_true", help="a 60 s smoke run")
    ap.add_argument("--hog", type=int, default=None, help="busy processes (default: twice the CPUs)")
    ap.add_argument("--no-hog", action="store_true", help="no CPU hog")
    ap.add_argument("--realtime-priority", type=int, default=50,
                    help="SCHED_FIFO priority of bus server, simulator and driver cycle (0: normal)")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    ap.add_argument("--newcomer-period", type=float, default=NEWCOMER_PERIOD_S, metavar="S",
                    help=f"start a new Python process every S seconds (default {NEWCOMER_PERIOD_S:g})")
    ap.add_argument("--sim-physics", choices=("process", "thread"), default="process",
                    help="the simulator's --physics (default process; thread: as before, for comparison)")
    ap.add_argument("--slice-ms", type=float, default=None, metavar="MS",
                    help="time slice of the threads on the reply path (bus server relay, simulator bus "
                    "thread, driver cycle; 0 = the kernel's default; default: theirs)")
    ap.add_argument("--plot-dir", type=Path, default=None,
                    help="write the PNG plot here (default: beside the results file when it is written)")
    args = ap.parse_args(argv)
    seconds = 60.0 if args.quick else args.seconds
    hog = 0 if args.no_hog else (args.hog if args.hog is not None else 2 * (os.cpu_count() or 1))
    print(f"soak: {seconds:g} s at 250 Hz, hog {hog}, real-time priority {args.realtime_priority} ...",
          flush=True)
    load_before = os.getloadavg()
    steal_before = steal_ticks()
    if not args.newcomer_period > 0:
        ap.error("--newcomer-period must be > 0")
    with HostSpeedProbe() as probe:
        obs, diag, sim = soak(seconds, hog, args.realtime_priority, args.newcomer_period, args.sim_physics,
                              args.slice_ms)
    load_after = os.getloadavg()
    steal_ms = (steal_ticks() - steal_before) * 1e3 / os.sysconf("SC_CLK_TCK")
    r = summarise(seconds, hog, args.realtime_priority, obs, diag, sim)
    run = "\n".join([
        f"## Run {time.strftime('%Y-%m-%d %H:%M')} — {seconds:g} s, load average (1/5/15 min) "
        f"{load_before[0]:.2f}/{load_before[1]:.2f}/{load_before[2]:.2f} before, "
        f"{load_after[0]:.2f}/{load_after[1]:.2f}/{load_after[2]:.2f} after",
        "",
        HEADER,
        SEP,
        row_text(r),
        "",
        f"Driver cycle scheduling: {r.scheduling}. Recoveries after halts: {obs.recoveries} "
        f"(failed: {obs.recover_failures}); modules entering an error: {obs.error_modules or 'none'}; "
        f"stream targets sent: {obs.stream_sent}. Simulator: longest garbage collection "
        f"{r.sim_gc_max_pause_ms:.2f} ms CPU ({r.sim_gc_collections} collections), longest "
        f"request-to-reply {r.sim_reply_max_ms:.2f} ms.",
        "",
        f"Kernel: {autogroup_setting()}; time stolen by the hypervisor over the run: {steal_ms:.0f} ms. "
        f"Host speed: {probe.summary()} (`benchmarks/host_speed.py`).",
        "",
        f"Slow events: simulator {sim_counts(sim)}; bus server slow hops {len(obs.hop_lines)}. Longest "
        f"run-queue wait in a {SCHEDSTAT_PERIOD_S * 1e3:.0f} ms sample, ms (samples of "
        f"{RUNQ_WAIT_EVENT_MS:g} ms or more), of the threads on the reply path: "
        f"{worst_waits(obs.runq_waits)}.",
        "",
        f"Command: `.venv/bin/python benchmarks/soak_bench.py --seconds {seconds:g}"
        + (" --no-hog" if args.no_hog else f" --hog {hog}")
        + f" --realtime-priority {args.realtime_priority}"
        + (f" --newcomer-period {args.newcomer_period:g}"
           if args.newcomer_period != NEWCOMER_PERIOD_S else "")
        + (f" --sim-physics {args.sim_physics}" if args.sim_physics != "process" else "")
        + (f" --slice-ms {args.slice_ms:g}" if args.slice_ms is not None else "")
        + "`",
        "",
        *([f"Timelines of the missed replies (first {MAX_TIMELINES}; times relative to the missed cycle):",
           "", "```", *obs.timelines[:MAX_TIMELINES], "```", ""] if obs.timelines else []),
    ])
    print()
    print(run)
    links: list[str] = []
    plot_dir = args.plot_dir or (None if args.no_write else RESULTS.parent)
    if plot_dir is not None and obs.js_gaps_ms:
        plots = bench_common.plots()
        run_text = (f"soak_bench.py: {seconds:g} s at 250 Hz, hog {hog}, real-time priority "
                    f"{args.realtime_priority}; sampled load mean {r.load_mean:.2f} / max {r.load_max:.2f}")
        png = plots.period_histogram(
            plot_dir / "soak_bench_period.png", {"/joint_states header-stamp gaps": obs.js_gaps_ms}, 4.0,
            title="Soak: can_driver cycle periods at 250 Hz under load (/joint_states stamps)",
            caption=plots.run_caption(run_text, load_before))
        links = [*plots.markdown_links([png], RESULTS.parent, "of the newest run"), ""]
        print("\n".join(links))
    if not args.no_write:
        earlier: list[str] = []
        if RESULTS.exists():
            earlier = ["## Run " + part.strip() + "\n" for part in RESULTS.read_text().split("\n## Run ")[1:]]
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text("\n".join([preamble(), *links, run, *earlier]))
        print(f"wrote {RESULTS}")
    return 0 if r.halts == 0 and r.limit_faults == 0 else 1


def preamble() -> str:
    return "\n".join([
        "# Soak benchmark of the CAN path (`benchmarks/soak_bench.py`)",
        "",
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; the "
        "machine is shared with other jobs (see each run's load average, sampled every 0.2 s during the "
        "run). "
        "Bus server, simulator (pybullet 1 kHz, 7 emulated PowerCube modules, 100 ms watchdog) and the "
        "can_driver node (250 Hz, cycle in its own process) run as separate processes; the benchmark "
        "streams joint targets at 100 Hz (joint 2 driven past its limit: the arm brakes onto the soft "
        "limit every 8 s), runs a CPU hog of busy shell loops and starts a new Python process (numpy + "
        "rclpy + a node) every 30 s. Period error = |start-to-start period - 4 ms| over every cycle of the "
        "run (overruns included; 0.05 ms resolution); missed replies = replies that did not come within "
        "reply_timeout_s (20 ms); limit faults = modules entering BEYOND_SOFT; watchdog trips = modules "
        "entering COMM_ERROR; halts are answered with ~/recover so the run continues. Target: 0 halts and 0 "
        "faults.",
        "",
    ])


if __name__ == "__main__":
    raise SystemExit(main())
