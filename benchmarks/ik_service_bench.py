"""Cross-process round trip of the ik_service node (SolveIK) against the bare kinematics core.

The node runs as its own process (``python -m redarm_ros.nodes.ik_service``); this process is the
client and waits for each answer by looping on ``spin_once`` until the future is done
(``spin_until_future_complete`` adds 20-80 ms per call here). Poses are FK of random in-limit joint
vectors (fixed seed), so every request is reachable. Modes:

* ``swivel``: swivel given (closed form at that swivel), seed = the true q;
* ``nearest``: no swivel, mid-range seed (``ik_nearest`` over all swivels);
* ``nearest+all``: as ``nearest`` and every solution at the found swivel;
* ``burst``: 4 clients each keep 500 requests outstanding (sent before any answer is read; 4 x 50 with
  ``--quick``): how many are answered and how long the whole burst takes. The clients use response
  queues as deep as the burst (see docs/nodes.md, "Bursts and queues").

Run: ``.venv/bin/python benchmarks/ik_service_bench.py [--calls 1000] [--quick]``; writes
``benchmarks/results/ik_service_bench.md`` unless ``--no-write``. Target: median round trip <= 1 ms.
Wall-clock numbers depend on the machine; tests never assert on them.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from redarm_ros.procs import ProcessGroup, python_module_cmd, random_domain_id

FLOOR_SERVER = """
import rclpy
from rclpy.executors import ExternalShutdownException
from std_srvs.srv import Trigger
rclpy.init()
node = rclpy.create_node("bench_floor")
node.create_service(Trigger, "~/trigger", lambda req, resp: resp)
print("floor ready", flush=True)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
rclpy.try_shutdown()
"""
RESULTS = Path(__file__).resolve().parent / "results" / "ik_service_bench.md"
REPO = Path(__file__).resolve().parents[1]


def _pct(xs: list[float], p: float) -> float:
    return float(np.percentile(np.asarray(xs), p))


def _row(name: str, xs_s: list[float], ok: int, total: int) -> str:
    ms = [x * 1e3 for x in xs_s]
    return (
        f"| {name} | {total} | {100.0 * ok / total:.1f} | {statistics.median(ms):.3f} | {_pct(ms, 90):.3f} | "
        f"{_pct(ms, 99):.3f} | {max(ms):.3f} |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=1000, help="requests per mode (default 1000)")
    ap.add_argument("--arm", default="pa10")
    ap.add_argument("--quick", action="store_true", help="200 requests per mode")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    args = ap.parse_args(argv)
    calls = 200 if args.quick else args.calls

    # Network rule: this process runs rclpy too, so it gets the same isolation as the child.
    os.environ["FASTDDS_BUILTIN_TRANSPORTS"] = "SHM"
    os.environ.setdefault("ROS_DOMAIN_ID", str(random_domain_id()))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from redarm_interfaces.srv import SolveIK

    from redarm_ros.kinematics import load_arm
    from redarm_ros.kinematics.quaternion import matrix_to_quat

    arm = load_arm(args.arm)
    rng = np.random.default_rng(2024)
    Q = rng.uniform(arm.lower, arm.upper, size=(calls, arm.n))
    Ts = [arm.fk(q) for q in Q]

    def request(T: np.ndarray) -> SolveIK.Request:
        req = SolveIK.Request()
        req.arm = args.arm
        p = req.target.pose.position
        p.x, p.y, p.z = (float(v) for v in T[:3, 3])
        w, x, y, z = (float(v) for v in matrix_to_quat(T[:3, :3]))
        o = req.target.pose.orientation
        o.x, o.y, o.z, o.w = x, y, z, w
        return req

    modes = {}
    for i, (q, T) in enumerate(zip(Q, Ts, strict=True)):
        r = request(T)
        r.swivel_given, r.swivel, r.seed = True, float(arm.swivel(q)), [float(v) for v in q]
        modes.setdefault("swivel", []).append(r)
        modes.setdefault("nearest", []).append(request(T))
        r = request(T)
        r.all_solutions = True
        modes.setdefault("nearest+all", []).append(r)
        del i

    # The bare core on the same requests, for the overhead column.
    seed_mid = (arm.lower + arm.upper) / 2
    core: dict[str, list[float]] = {"swivel": [], "nearest": []}
    for q, T in zip(Q, Ts, strict=True):
        t = time.perf_counter()
        arm.ik(T, float(arm.swivel(q)))
        core["swivel"].append(time.perf_counter() - t)
        t = time.perf_counter()
        arm.ik_nearest(T, seed_mid)
        core["nearest"].append(time.perf_counter() - t)

    lines: list[str] = []
    with ProcessGroup(pythonpath=[REPO], sink=sys.stderr) as group:
        group.start(
            "ik_service",
            python_module_cmd(
                "redarm_ros.nodes.ik_service",
                "--ros-args",
                "--log-level",
                "warn",
                "-p",
                f"arms:=[{args.arm}]",
                "-p",
                f"default_arm:={args.arm}",
            ),
        )
        # The floor: the same round trip to an empty std_srvs/Trigger service in its own process.
        group.start("floor", [sys.executable, "-c", FLOOR_SERVER], ready="floor ready")
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=group.domain_id)
        node = rclpy.create_node("ik_bench_client", context=ctx)
        cli = node.create_client(SolveIK, "/ik_service/solve_ik")
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        deadline = time.monotonic() + 30
        while not cli.service_is_ready():
            if time.monotonic() > deadline:
                raise SystemExit("ik_service did not come up in 30 s")
            ex.spin_once(timeout_sec=0.05)

        from redarm_ros.nodes._common import call_resending, spin_until

        def wait(pred: Callable[[], object], seconds: float) -> bool:
            return spin_until(ex, pred, seconds, 0.1)

        def call(req: SolveIK.Request) -> SolveIK.Response:
            resp = call_resending(cli, req, wait, 60.0)  # (a first answer may be lost: sent again)
            if resp is None:
                raise SystemExit("ik_service did not answer in 60 s")
            return resp

        for r in modes["swivel"][:50]:  # warm-up (discovery, caches)
            call(r)
        from std_srvs.srv import Trigger

        floor_cli = node.create_client(Trigger, "/bench_floor/trigger")
        while not floor_cli.service_is_ready():
            ex.spin_once(timeout_sec=0.05)
        if call_resending(floor_cli, Trigger.Request(), wait, 60.0) is None:  # the answer path is matched
            raise SystemExit("the floor service did not answer in 60 s")
        results: dict[str, tuple[list[float], int]] = {}
        times = []
        for i in range(calls + 50):
            t = time.perf_counter()
            fut = floor_cli.call_async(Trigger.Request())
            while not fut.done():
                ex.spin_once(timeout_sec=0.1)
            if i >= 50:
                times.append(time.perf_counter() - t)
        results["floor: empty Trigger service"] = (times, calls)
        for name, reqs in modes.items():
            times, ok = [], 0
            for r in reqs:
                t = time.perf_counter()
                resp = call(r)
                times.append(time.perf_counter() - t)
                ok += resp.status == SolveIK.Response.SUCCESS
            results[name] = (times, ok)
        # burst: 4 clients x per_client outstanding requests, all sent before any answer is taken
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

        per_client = 50 if args.quick else 500
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4096, reliability=ReliabilityPolicy.RELIABLE)
        bnodes = [rclpy.create_node(f"ik_bench_burst_{k}", context=ctx) for k in range(4)]
        bclients = [bn.create_client(SolveIK, "/ik_service/solve_ik", qos_profile=qos) for bn in bnodes]
        for bn in bnodes:
            ex.add_node(bn)
        while not all(c.service_is_ready() for c in bclients):
            ex.spin_once(timeout_sec=0.05)
        reqs = modes["nearest"]
        for c in bclients:  # one answered request each: the burst measures the queue, not discovery
            if call_resending(c, reqs[0], wait, 60.0) is None:
                raise SystemExit("ik_service did not answer a burst client in 60 s")
        t0 = time.perf_counter()
        futs = [
            bclients[k].call_async(reqs[(4 * i + k) % len(reqs)]) for i in range(per_client) for k in range(4)
        ]
        deadline = time.monotonic() + 300.0
        while not all(f.done() for f in futs) and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        burst_s = time.perf_counter() - t0
        answered = sum(f.done() for f in futs)
        burst_ok = sum(f.done() and f.result().status == SolveIK.Response.SUCCESS for f in futs)
        for bn in bnodes:
            bn.destroy_node()
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)

    load = os.getloadavg()[0]
    lines.append(f"# ik_service round trip ({args.arm}, {calls} requests per mode)\n")
    lines.append(
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
        f"load average at the end {load:.1f}; node and client in separate processes, Fast DDS over "
        "SHM; client loops on spin_once.\n"
    )
    lines.append("| mode | requests | solved % | median ms | p90 ms | p99 ms | max ms |")
    lines.append("|---|---|---|---|---|---|---|")
    for name, (times, ok) in results.items():
        lines.append(_row(name, times, ok, calls))
    lines.append("")
    lines.append("Bare kinematics core, same poses, same process (no ROS):\n")
    lines.append("| call | median ms | p99 ms |")
    lines.append("|---|---|---|")
    lines.append(
        f"| arm.ik(T, swivel) | {statistics.median(core['swivel']) * 1e3:.3f} | "
        f"{_pct(core['swivel'], 99) * 1e3:.3f} |"
    )
    lines.append(
        f"| arm.ik_nearest(T, mid-range seed) | {statistics.median(core['nearest']) * 1e3:.3f} | "
        f"{_pct(core['nearest'], 99) * 1e3:.3f} |"
    )
    lines.append("")
    lines.append(
        f"Burst: 4 clients x {per_client} outstanding requests: {answered} of {4 * per_client} answered "
        f"({burst_ok} solved) in {burst_s:.2f} s ({4 * per_client / burst_s:.0f} requests/s)."
    )
    med = statistics.median(results["swivel"][0]) * 1e3
    lines.append("")
    lines.append(
        f"Target: median cross-process round trip <= 1 ms: swivel mode {med:.3f} ms "
        f"({'met' if med <= 1.0 else 'NOT met'})."
    )
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
