"""Wake-up latency with and without a shorter time slice (``realtime.request_slice``), arms side by side.

Each arm is a request/reply pair like one hop of the CAN path: a client process that sends a 16-byte
request every 4 ms (250 Hz) over a loopback TCP connection and waits for the answer, and a server
process that sleeps until a request arrives, works ``--work-ms`` of CPU (a reply's computation) and
answers. Client and server each run in a session of their own at nice 0 and ask for the arm's slice
(0: the kernel's default). All arms run at the same time, so they see the same load: a CPU hog of
``--hog`` busy shell loops and, every ``--newcomer-period`` s, a new Python process that imports
numpy (as the soak benchmark does). ``--rounds`` rounds, each starting the arms in another order.
Reported per arm and round, and over all rounds: round-trip time median / p99 / p99.9 / max and the
count of round trips of 5 ms and 20 ms or more (the driver's reply timeout is 20 ms).

Run: ``.venv/bin/python benchmarks/slice_bench.py`` (3 rounds of 120 s; ``--slice-ms 0 0.1 0.5`` are
the arms; ``--quick``: one round of 10 s). Writes ``benchmarks/results/slice_bench.md`` (every run
kept, newest first) unless ``--no-write``.
What it does not cover: the CAN chain itself (``soak_bench.py`` runs it), real-time scheduling, other
kernels than the one it runs on (the slice needs Linux 6.12 or later).
"""

from __future__ import annotations

import argparse
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from redarm_ros.can import realtime

RESULTS = Path(__file__).resolve().parent / "results" / "slice_bench.md"
PERIOD_S = 0.004
NEWCOMER = "import numpy, time; time.sleep(0.5)"


def _busy(ms: float) -> None:
    end = time.thread_time() + ms / 1e3
    while time.thread_time() < end:
        pass


def serve(port_fd: int, slice_ms: float, work_ms: float) -> None:
    """The server: one connection, answer every 16-byte request after ``work_ms`` of CPU."""
    if slice_ms > 0:
        realtime.request_slice(slice_ms, who="server")
    lsock = socket.socket(fileno=port_fd)
    conn, _ = lsock.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    while (data := conn.recv(16)):
        _busy(work_ms)
        conn.sendall(data)


def client(port: int, slice_ms: float, seconds: float, out: str) -> None:
    """The client: a request every :data:`PERIOD_S` on an absolute grid; round-trip times to ``out``."""
    got = realtime.request_slice(slice_ms, who="client") if slice_ms > 0 else None
    if got is not None and not got.applied:
        print(got.message, file=sys.stderr)
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    rtts = []
    t0 = next_t = time.monotonic()
    while next_t - t0 < seconds:
        time.sleep(max(0.0, next_t - time.monotonic()))
        start = time.monotonic()
        sock.sendall(b"x" * 16)
        n = 0
        while n < 16:
            n += len(sock.recv(16 - n))
        rtts.append(time.monotonic() - start)
        next_t = max(next_t + PERIOD_S, time.monotonic())
    sock.close()
    np.save(out, np.array(rtts) * 1e3)


def run_arms(slices: list[float], seconds: float, work_ms: float, hog: int,
             newcomer_period: float, tmp: str) -> dict[float, np.ndarray]:
    procs: list[subprocess.Popen[bytes]] = []
    clients: dict[float, tuple[subprocess.Popen[bytes], str]] = {}
    me = [sys.executable, os.path.abspath(__file__)]
    try:
        for _ in range(hog):
            procs.append(subprocess.Popen(["sh", "-c", "while :; do :; done"], start_new_session=True))
        for s in slices:
            lsock = socket.socket()
            lsock.bind(("127.0.0.1", 0))
            lsock.listen(1)
            port = lsock.getsockname()[1]
            procs.append(subprocess.Popen([*me, "serve", str(lsock.fileno()), str(s), str(work_ms)],
                                          pass_fds=(lsock.fileno(),), start_new_session=True))
            lsock.close()
            out = os.path.join(tmp, f"rtt_{s:g}.npy")
            clients[s] = (subprocess.Popen([*me, "client", str(port), str(s), str(seconds), out],
                                           start_new_session=True), out)
        end = time.monotonic() + seconds
        next_new = time.monotonic() + newcomer_period
        while time.monotonic() < end:
            time.sleep(0.1)
            if time.monotonic() >= next_new:
                procs.append(subprocess.Popen([sys.executable, "-c", NEWCOMER]))
                next_new += newcomer_period
        for c, _ in clients.values():
            c.wait(seconds + 60)
    finally:
        for p in [*procs, *(c for c, _ in clients.values())]:
            if p.poll() is None:
                p.kill()
            p.wait()
    return {s: np.load(out) for s, (_c, out) in clients.items()}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "serve":
        serve(int(argv[1]), float(argv[2]), float(argv[3]))
        return 0
    if argv and argv[0] == "client":
        client(int(argv[1]), float(argv[2]), float(argv[3]), argv[4])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="per round (default 120 s)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds, arms started in rotated order (default 3)")
    ap.add_argument("--quick", action="store_true", help="one round of 10 s")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    ap.add_argument("--slice-ms", type=float, nargs="+", default=[0.0, 0.1, 0.5], help="the arms' slices")
    ap.add_argument("--work-ms", type=float, default=0.3, help="CPU per reply (default 0.3 ms)")
    ap.add_argument("--hog", type=int, default=1, help="busy shell loops (default 1)")
    ap.add_argument("--newcomer-period", type=float, default=3.0, metavar="S")
    args = ap.parse_args(argv)
    import tempfile

    seconds, rounds = (10.0, 1) if args.quick else (args.seconds, args.rounds)
    arms = list(args.slice_ms)
    lines = [f"## Run {time.strftime('%Y-%m-%d %H:%M')} — {rounds} x {seconds:g} s, work {args.work_ms:g} ms "
             f"per reply, hog {args.hog}, a new process every {args.newcomer_period:g} s", ""]
    every: dict[float, list[np.ndarray]] = {s: [] for s in arms}
    for i in range(rounds):
        order = arms[i % len(arms):] + arms[:i % len(arms)]
        load_before = os.getloadavg()
        with tempfile.TemporaryDirectory(prefix="slice_bench_") as tmp:
            rtts = run_arms(order, seconds, args.work_ms, args.hog, args.newcomer_period, tmp)
        load_after = os.getloadavg()
        lines += [f"Round {i + 1}, arms started in the order {', '.join(f'{s:g}' for s in order)}; load "
                  f"average (1 min) {load_before[0]:.2f} before, {load_after[0]:.2f} after:", "",
                  *table(rtts), ""]
        for s, r in rtts.items():
            every[s].append(r)
        print("\n".join(lines[-len(arms) - 5:]), flush=True)
    if rounds > 1:
        lines += ["All rounds:", "", *table({s: np.concatenate(r) for s, r in every.items()}), ""]
    lines.append(f"Command: `.venv/bin/python benchmarks/slice_bench.py --seconds {seconds:g} "
                 f"--rounds {rounds} "
                 f"--slice-ms {' '.join(f'{s:g}' for s in arms)} --work-ms {args.work_ms:g} --hog {args.hog} "
                 f"--newcomer-period {args.newcomer_period:g}`")
    run = "\n".join(lines) + "\n"
    print(run)
    if not args.no_write:
        earlier = []
        if RESULTS.exists():
            earlier = ["## Run " + part.strip() + "\n" for part in RESULTS.read_text().split("\n## Run ")[1:]]
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text("\n".join([preamble(), run, *earlier]))
        print(f"wrote {RESULTS}")
    return 0


def table(rtts: dict[float, np.ndarray]) -> list[str]:
    """Markdown rows: per arm, round trips, median / p99 / p99.9 / max (ms), counts >= 5 and >= 20 ms."""
    out = ["| slice ms (0 = kernel's default) | round trips | median ms | p99 ms | p99.9 ms | max ms | "
           ">= 5 ms | >= 20 ms |", "|---|---|---|---|---|---|---|---|"]
    for s, r in sorted(rtts.items()):
        out.append(f"| {s:g} | {len(r)} | {np.median(r):.2f} | {np.percentile(r, 99):.2f} | "
                   f"{np.percentile(r, 99.9):.2f} | {r.max():.2f} | {(r >= 5).sum()} | {(r >= 20).sum()} |")
    return out


def preamble() -> str:
    return "\n".join([
        "# Wake-up latency with a shorter time slice (`benchmarks/slice_bench.py`)",
        "",
        f"Machine: {platform.node()}, {os.cpu_count()} CPUs, Linux {platform.release()}, Python "
        f"{platform.python_version()}; shared with other jobs (see each round's load average). Arms run side "
        "by side: per arm a client sends a request every 4 ms over loopback TCP and a server answers after "
        "the given CPU work; each process in a session of its own at nice 0, with the arm's time slice "
        "(`realtime.request_slice`; 0 = the kernel's default).",
        "",
    ])


if __name__ == "__main__":
    raise SystemExit(main())
