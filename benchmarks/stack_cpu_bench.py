"""CPU budget of the simulated stack: what each process of ``redarm-bringup`` costs, in three cases.

What runs: the stack as ``redarm-bringup`` starts it (:class:`redarm_ros.bringup.Stack`: loopback bus
server, pybullet simulator with seven emulated PowerCube modules, ``can_driver`` at 250 Hz with its
cycle in a child process, ``ik_service``, ``controller`` at 100 Hz, ``description``), in the demo's
scene, and this benchmark as an ordinary rclpy client. After the driver's homing the arm is moved to
the demo's ready pose through ``/joint_command``; then three cases are measured one after the other:

* **rest**: after a settle time, the arm still, no goal;
* **stream**: a Cartesian goal streamed on ``/goal_pose`` at 50 Hz along a small circle (radius
  0.05 m, one turn in 4 s) about the ready pose's tool position;
* **demo**: the demo's goal sequence (``redarm_ros.demo.GOALS``: five reachable goals and one out of
  reach), each sent once and waited for until the controller reports it reached or rejected.

Reported per case and process (each child's process group and descendants, so the driver's cycle
process and the simulator's physics process are counted on rows of their own): CPU seconds consumed
in the window (utime + stime from /proc/<pid>/stat) and the same as % of one core over the window's
wall time; the total; the load average before and after the case; the driver loop's achieved rate,
cycles, overruns and missed replies (the modules' ``lost`` counters) from its ``/diagnostics``, and
the controller's steps. CPU seconds are what a busy machine
inflates least; the percentages of a shared machine are noisy, so compare runs made back to back.
Targets (quiet machine): rest <= 40 %, stream <= 80 %, demo <= 100 % of one core in total, with the
driver loop at 250 Hz and 0 missed replies.

Run (ROS, the bus and pybullet run in child processes; wrap it in the DDS sandbox)::

    scripts/ros_sandbox.sh .venv/bin/python benchmarks/stack_cpu_bench.py

(``--repeat N``, default 3: N fresh stacks one after the other, and a summary of each case's total
per run and the median, which is what the targets are checked against, since a single run on a
shared machine swings by several points; ``--quick``: short windows and one stack for a smoke run;
``--label`` names the run in the results file, where every run is kept, newest first). Writes
``benchmarks/results/stack_cpu_bench.md`` unless ``--no-write``. What it does not cover: real
hardware, other arms, the browser view, a recorder.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from redarm_ros.bringup import Stack, StackConfig
from redarm_ros.procs import descendants, group_members

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_common, also when loaded by path
import bench_common  # noqa: E402
from host_speed import HostSpeedProbe  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "stack_cpu_bench.md"
ARM_NAME = "pa10"
STREAM_HZ = 50.0
CIRCLE_RADIUS_M = 0.05
CIRCLE_PERIOD_S = 4.0
TARGETS = {"rest": 40.0, "stream": 80.0, "demo": 100.0}
CLK_TCK = os.sysconf("SC_CLK_TCK")
RATES = ("rate_hz_achieved", "controller_rate_hz_achieved")  # windowed rates: the last value, not a delta


def proc_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) process ``pid`` has used, or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            fields = f.read().rsplit(")", 1)[-1].split()
    except OSError:
        return None
    # After the parenthesised name: state(0) ppid(1) ... utime(11) stime(12).
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def process_rows(stack: Stack) -> dict[str, list[int]]:
    """Row name -> pids: each child's process group and descendants; the others than the child itself
    (the driver's cycle process, the simulator's physics) get a row of their own."""
    rows: dict[str, list[int]] = {}
    for name, child in stack.children.items():
        # its process group and every descendant (the simulator's physics runs in a session of its own)
        members = sorted(set(group_members(child.pid) or [child.pid]) | set(descendants(child.pid)))
        rows[name] = [child.pid]
        others = [p for p in members if p != child.pid]
        if others:
            rows[f"{name} (cycle process)" if name == "can_driver" else f"{name} (children)"] = others
    return rows


def cpu_sample(rows: dict[str, list[int]]) -> dict[str, dict[int, float]]:
    return {name: {p: c for p in pids if (c := proc_cpu_s(p)) is not None} for name, pids in rows.items()}


@dataclass
class CaseResult:
    """One measured case: CPU seconds per row over ``wall_s``, load averages, driver figures."""

    name: str
    wall_s: float
    cpu_s: dict[str, float]
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float]
    driver: dict[str, float] = field(default_factory=dict)
    note: str = ""

    @property
    def total_s(self) -> float:
        return sum(self.cpu_s.values())

    def pct(self, row: str) -> float:
        return 100.0 * self.cpu_s.get(row, math.nan) / self.wall_s


class Client:
    """The benchmark's ROS side: goals, joint commands, controller state and diagnostics."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from redarm_interfaces.msg import ControllerState
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        from redarm_ros.nodes.controller import pose_to_msg  # imported now, not in a measured window

        self._pose_to_msg = pose_to_msg
        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = rclpy.create_node("stack_cpu_bench", context=self.ctx)
        self.CS = ControllerState
        self.PoseStamped = PoseStamped
        from std_srvs.srv import Trigger

        self.Trigger = Trigger
        self.recover_cli = self.node.create_client(Trigger, "/can_driver/recover")
        self.goal_pub = self.node.create_publisher(PoseStamped, "/goal_pose", 10)
        self.cmd_pub = self.node.create_publisher(JointTrajectory, "/joint_command", 10)
        self.lock = threading.Lock()
        self.states: list[Any] = []
        self.diag: dict[str, dict[str, str]] = {}
        self.node.create_subscription(ControllerState, "/controller/state", self._on_state, 50)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 20)
        self.counts = {"joint_states": 0, "state": 0}  # messages received (rates of what is published)
        self.node.create_subscription(JointState, "/joint_states", self._on_js, 50)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.stop_event, self.thread = bench_common.spin_in_background(self.ex)

    def _on_js(self, _msg: Any) -> None:
        self.counts["joint_states"] += 1

    def _on_state(self, msg: Any) -> None:
        with self.lock:
            self.counts["state"] += 1
            self.states.append(msg)
            del self.states[:-200]

    def _on_diag(self, msg: Any) -> None:
        with self.lock:
            for s in msg.status:
                self.diag[s.name] = {kv.key: kv.value for kv in s.values}

    def driver_figures(self) -> dict[str, float]:
        """The driver's cumulative loop counters from its last ``/diagnostics``."""
        with self.lock:
            loop = dict(self.diag.get("can_driver: loop", {}))
            mods = [v for k, v in self.diag.items() if k.startswith("can_driver: module")]
            ctrl = dict(self.diag.get("controller: loop", {}))
        out = {"lost": float(sum(int(m.get("lost", 0)) for m in mods))}
        for key in ("cycles", "overruns", "rate_hz_achieved"):
            if key in loop:
                out[key] = float(loop[key])
        for key in ("steps", "missed_ticks", "rate_hz_achieved"):
            if key in ctrl:
                out[f"controller_{key}"] = float(ctrl[key])
        return out

    def pose_msg(self, T: np.ndarray) -> Any:
        msg = self._pose_to_msg(T)
        msg.header.frame_id = "base_link"
        return msg

    def move_joints(self, names: list[str], q: tuple[float, ...], duration_s: float) -> None:
        from redarm_ros.nodes._common import joint_trajectory

        self.cmd_pub.publish(joint_trajectory(names, q, duration_s))

    def close(self) -> None:
        self.stop_event.set()
        self.thread.join(2.0)
        self.ex.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.ctx)


def wait_for(cond: Callable[[], bool], timeout: float, period: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(period)
    return cond()


def measure(name: str, stack: Stack, client: Client, body: Callable[[], str]) -> CaseResult:
    """Run ``body`` (returns a note) and measure every process of the stack meanwhile."""
    stack.check()
    rows = process_rows(stack)
    load0 = os.getloadavg()
    d0 = client.driver_figures()
    n0 = dict(client.counts)
    c0 = cpu_sample(rows)
    t0 = time.monotonic()
    note = body()
    t1 = time.monotonic()
    c1 = cpu_sample(rows)
    n1 = dict(client.counts)
    time.sleep(1.2)  # one more diagnostics message (1 Hz) carries the window's last counters
    d1 = client.driver_figures()
    cpu = {row: sum(c - c0[row].get(p, 0.0) for p, c in c1[row].items()) for row in rows}
    driver = {k: d1[k] - d0.get(k, 0.0) for k in d1 if k not in RATES}
    for k in RATES:
        if k in d1:
            driver[k] = d1[k]
    if "cycles" in driver:
        driver["cycle_rate_hz"] = driver["cycles"] / (t1 - t0 + 1.2)
    for k in n1:
        driver[f"{k}_hz"] = (n1[k] - n0[k]) / (t1 - t0)
    stack.check()
    return CaseResult(name, t1 - t0, cpu, load0, os.getloadavg(), driver, note)


def run(args: argparse.Namespace) -> list[CaseResult]:
    from redarm_ros.demo import DEMO_SCENE, GOALS, READY_Q
    from redarm_ros.kinematics import load_arm

    arm = load_arm(ARM_NAME)
    settle, window = (3.0, 4.0) if args.quick else (args.settle, args.window)
    with tempfile.TemporaryDirectory(prefix="stack_cpu_bench_") as tmpdir:
        scene = Path(tmpdir) / "scene.yaml"
        scene.write_text(yaml.safe_dump(DEMO_SCENE, sort_keys=False), encoding="utf-8")
        cfg = StackConfig(arm=ARM_NAME, scene=str(scene), log_level="warn", ready_timeout_s=90.0)
        log = open(Path(tmpdir) / "stack.log", "w", encoding="utf-8")  # noqa: SIM115 - closed below
        stack = Stack(cfg, sink=log, domain_id=args.domain_id)
        client: Client | None = None
        try:
            stack.start()
            stack.children["can_driver"].wait_for_line(r"init done", timeout=60.0, from_start=True)
            client = Client(stack.domain_id)
            # A message published before discovery matched its subscriber is lost: wait for both.
            wait_for(lambda: bool(client.states) and bool(client.diag)
                     and client.cmd_pub.get_subscription_count() > 0
                     and client.goal_pub.get_subscription_count() > 0, 30.0)

            def at_ready() -> bool:
                st = stack.sim_status() or {}
                return bool(st) and float(np.max(np.abs(np.asarray(st["q"]) - READY_Q))) < 1e-3

            halts_noted: list[str] = []
            for attempt in (1, 2):
                client.move_joints(list(arm.joint_names), READY_Q, 3.0)
                if wait_for(at_ready, 30.0):
                    break
                halted = any("HALTED:" in line for line in stack.children["can_driver"].output())
                if attempt == 2 or not halted:
                    raise RuntimeError("the simulated arm did not reach the ready pose")
                # The driver halted the arm (a module answered late: a starved machine). As an operator
                # would: recover, then move again; the run's note says so.
                client.recover_cli.call_async(client.Trigger.Request())
                time.sleep(5.0)
                halts_noted.append("the driver halted the arm before the ready pose; recovered")
            T_ready = arm.fk(np.asarray(READY_Q))
            results: list[CaseResult] = []

            def rest() -> str:
                time.sleep(window)
                return f"arm still at the ready pose, {settle:g} s after it arrived" + "".join(
                    f" ({h})" for h in halts_noted)

            time.sleep(settle)
            results.append(measure("rest", stack, client, rest))

            def stream() -> str:
                n = 0
                t0 = time.monotonic()
                next_t = t0
                center = T_ready[:3, 3] - np.array([CIRCLE_RADIUS_M, 0.0, 0.0])
                while (now := time.monotonic()) - t0 < window:
                    a = 2 * math.pi * (now - t0) / CIRCLE_PERIOD_S
                    T = T_ready.copy()
                    T[:3, 3] = center + CIRCLE_RADIUS_M * np.array([math.cos(a), math.sin(a), 0.0])
                    client.goal_pub.publish(client.pose_msg(T))
                    n += 1
                    next_t += 1.0 / STREAM_HZ
                    time.sleep(max(0.0, next_t - time.monotonic()))
                return f"{n} goals at {n / window:.1f} Hz on a {CIRCLE_RADIUS_M * 100:g} cm circle"

            # The stream starts from rest: its first second (the controller turning towards the circle)
            # is part of what a user streaming goals costs, so it is measured too.
            results.append(measure("stream", stack, client, stream))

            goals = GOALS[:2] if args.quick else GOALS

            def demo() -> str:
                outcomes = []
                for g in goals:
                    n0 = len(client.states)
                    client.goal_pub.publish(client.pose_msg(g.matrix()))

                    def done(g: Any = g, n0: int = n0) -> bool:
                        with client.lock:
                            new = client.states[n0:] if len(client.states) > n0 else client.states[-5:]
                        return any((m.phase == client.CS.REACHED
                                    and np.allclose([m.goal.position.x, m.goal.position.y, m.goal.position.z],
                                                    g.position, atol=1e-6))
                                   or (not g.reachable and m.phase == client.CS.REJECTED) for m in new)

                    ok = wait_for(done, args.goal_timeout)
                    outcomes.append(f"{g.name} {'done' if ok else 'timeout'}")
                    time.sleep(0.5)
                return f"{len(goals)} demo goals: " + ", ".join(outcomes)

            results.append(measure("demo", stack, client, demo))
            return results
        except BaseException:
            log.flush()
            tail = (Path(tmpdir) / "stack.log").read_text(errors="replace").splitlines()[-40:]
            print("--- last lines of the stack's output ---", *tail, sep="\n", file=sys.stderr)
            raise
        finally:
            if client is not None:
                client.close()
            stack.close()
            log.close()


def table(results: list[CaseResult]) -> list[str]:
    rows: list[str] = []
    for r in results:
        for name in r.cpu_s:
            if name not in rows:
                rows.append(name)
    head = "| process | " + " | ".join(f"{r.name} CPU s / %" for r in results) + " |"
    out = [head, "|---|" + "---:|" * len(results)]
    for name in rows:
        out.append(f"| {name} | " + " | ".join(
            f"{r.cpu_s.get(name, math.nan):.2f} / {r.pct(name):.1f}" for r in results) + " |")
    out.append("| **total** | " + " | ".join(
        f"**{r.total_s:.2f} / {100 * r.total_s / r.wall_s:.1f}**" for r in results) + " |")
    out.append("| target (% of one core) | " + " | ".join(f"<= {TARGETS[r.name]:g}" for r in results) + " |")
    out.append("| window s | " + " | ".join(f"{r.wall_s:.1f}" for r in results) + " |")
    out.append("| load avg 1 min before / after | " + " | ".join(
        f"{r.load_before[0]:.2f} / {r.load_after[0]:.2f}" for r in results) + " |")

    def drv(r: CaseResult, key: str, fmt: str) -> str:
        return format(r.driver[key], fmt) if key in r.driver else "-"

    out.append("| driver cycles/s (rate_hz_achieved) | " + " | ".join(
        f"{drv(r, 'cycle_rate_hz', '.1f')} ({drv(r, 'rate_hz_achieved', '.1f')})" for r in results) + " |")
    out.append("| driver overruns, missed replies | " + " | ".join(
        f"{drv(r, 'overruns', '.0f')}, {drv(r, 'lost', '.0f')}" for r in results) + " |")
    out.append("| /joint_states, /controller/state received Hz | " + " | ".join(
        f"{drv(r, 'joint_states_hz', '.1f')}, {drv(r, 'state_hz', '.1f')}" for r in results) + " |")
    out.append("| controller steps/s | " + " | ".join(
        f"{r.driver['controller_steps'] / (r.wall_s + 1.2):.1f}" if "controller_steps" in r.driver else "-"
        for r in results) + " |")
    return out


def summary(runs: list[list[CaseResult]]) -> list[str]:
    """Each case's total (% of one core) per stack run, the median over the runs and the target."""
    cases = [r.name for r in runs[0]]
    out = ["| case | " + " | ".join(f"run {i + 1}" for i in range(len(runs))) + " | median | target |",
           "|---|" + "---:|" * (len(runs) + 2)]
    for k, name in enumerate(cases):
        pcts = [100 * run[k].total_s / run[k].wall_s for run in runs]
        missed = sum(run[k].driver.get("lost", 0.0) for run in runs)
        out.append(f"| {name} | " + " | ".join(f"{p:.1f}" for p in pcts)
                   + f" | **{float(np.median(pcts)):.1f}** | <= {TARGETS[name]:g} |"
                   + ("" if not missed else f" ({missed:.0f} missed replies in all)"))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short windows, two demo goals, one stack")
    ap.add_argument("--repeat", type=int, default=3, help="fresh stacks run one after the other (median)")
    ap.add_argument("--settle", type=float, default=10.0, help="seconds at rest before the rest window")
    ap.add_argument("--window", type=float, default=20.0, help="rest and stream window (s)")
    ap.add_argument("--goal-timeout", type=float, default=20.0, help="seconds to wait for each demo goal")
    ap.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: the sandbox's)")
    ap.add_argument("--label", default="", help="a name for this run in the results file")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results file")
    args = ap.parse_args(argv)
    t_start = time.time()
    load0 = os.getloadavg()
    if args.repeat < 1:
        ap.error("--repeat must be at least 1")
    with HostSpeedProbe() as probe:  # the host's own speed over the run: CPU figures scale with it
        runs = [run(args) for _ in range(1 if args.quick else args.repeat)]
    title = f"## Run {time.strftime('%Y-%m-%d %H:%M')}" + (f" — {args.label}" if args.label else "") + (
        " (quick)" if args.quick else "")
    lines = [title, "", "Total per case, % of one core:", "", *summary(runs), ""]
    for i, results in enumerate(runs):
        lines += [f"Stack run {i + 1} of {len(runs)}:", "", *table(results), ""]
        lines += [f"- {r.name}: {r.note}" for r in results]
        lines.append("")
    lines += [bench_common.load_line(load0, t_start), "",
              f"Host speed over the run: {probe.summary()} (`benchmarks/host_speed.py`; the same work costs "
              "more CPU on a slower host, and every CPU figure above with it).", ""]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        earlier: list[str] = []
        if args.out.exists():
            earlier = ["## Run " + p.strip() + "\n" for p in args.out.read_text().split("\n## Run ")[1:]]
        title = "# CPU budget of the simulated stack (`benchmarks/stack_cpu_bench.py`)"
        header = bench_common.doc_header(title, __doc__)
        header[2] = header[2].split("\n\nRun (")[0]
        header.append(f"Machine: {platform.node()}, {os.cpu_count()} CPUs, Python "
                      f"{platform.python_version()}; shared with other jobs unless said otherwise (see each "
                      "run's load average).\n")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join([*header, text, *earlier]))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
