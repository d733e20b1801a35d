"""IK benchmark, TRAC-IK protocol: our closed form and numeric solvers against ikpy, same poses, one process.

Protocol (as TRAC-IK's published comparison): N random configurations uniform within the joint limits,
target T = fk(q), seed at mid-range, success = position error < 1e-5 m and orientation error < 1e-5 rad
(and the answer within the limits), 5 ms timeout for solvers that take one. Rows per arm:

* ``ik(T, s)``        closed form at the configuration's own swivel (all in-limit solutions)
* ``ik_nearest``      closed form, best solution over all swivels nearest the seed
* ``ik_batch``        vectorised closed form, all poses in one call (throughput in poses/s)
* ``DLS``             our damped least squares, 6-D, limits, restarts, 5 ms timeout
* ``Flow seq/batch``  the thesis' Jacobian-transpose update (position only: orientation not scored)
* ``ikpy``            ikpy 4.2 (scipy least squares, orientation_mode="all"); it has no timeout

Not a test: it asserts nothing; it prints one table and writes it to benchmarks/results/ik_bench.md.

    python benchmarks/ik_bench.py                 # full protocol, 10,000 poses per arm
    python benchmarks/ik_bench.py --quick         # smoke run (300 poses, 100 for the slow peers)
    python benchmarks/ik_bench.py --n 2000 --peer-n 500 --no-write
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from redarm_ros.kinematics import Arm, load_arm, pose_error
from redarm_ros.kinematics.numeric import solve_dls, solve_flow

TOL = 1e-5
TIMEOUT_S = 5e-3
RESULTS = Path(__file__).resolve().parent / "results" / "ik_bench.md"


@dataclass
class Row:
    arm: str
    solver: str
    n: int
    success: float  # fraction
    median_us: float
    p99_us: float
    note: str = ""


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF fixed-axis roll, pitch, yaw of a rotation matrix (R = Rz(y) Ry(p) Rx(r))."""
    return np.array(
        [
            math.atan2(R[2, 1], R[2, 2]),
            math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
            math.atan2(R[1, 0], R[0, 0]),
        ]
    )


def ikpy_chain(arm: Arm):  # noqa: ANN201 - ikpy type
    """The arm model as an ikpy Chain (base origin link, n revolute links, fixed tool link)."""
    from ikpy.chain import Chain
    from ikpy.link import OriginLink, URDFLink

    links = [OriginLink()]
    for j in arm.chain:
        links.append(
            URDFLink(
                j.name,
                origin_translation=j.origin[:3, 3],
                origin_orientation=_rpy(j.origin[:3, :3]),
                rotation=j.axis,
                bounds=(j.lower, j.upper),
            )
        )
    links.append(
        URDFLink(
            "tool",
            origin_translation=arm.tool[:3, 3],
            origin_orientation=_rpy(arm.tool[:3, :3]),
            joint_type="fixed",
        )
    )
    return Chain(links, active_links_mask=[False] + [True] * arm.n + [False])


def _ok(arm: Arm, q: np.ndarray | None, T: np.ndarray, position_only: bool = False) -> bool:
    if q is None or not arm.within_limits(q, tol=1e-9):
        return False
    pe, re = pose_error(arm.fk(q), T)
    return pe < TOL and (position_only or re < TOL)


def _timed(
    arm: Arm, Ts: np.ndarray, call: Callable[[int], np.ndarray | None], position_only: bool = False
) -> tuple[float, np.ndarray]:
    times = np.empty(len(Ts))
    ok = 0
    for i in range(len(Ts)):
        t0 = time.perf_counter()
        q = call(i)
        times[i] = time.perf_counter() - t0
        ok += _ok(arm, q, Ts[i], position_only)
    return ok / len(Ts), times


def _row(arm: Arm, name: str, success: float, times: np.ndarray, note: str = "") -> Row:
    return Row(
        arm.name,
        name,
        len(times),
        success,
        float(np.median(times) * 1e6),
        float(np.percentile(times, 99) * 1e6),
        note,
    )


def bench_arm(
    name: str, n: int, peer_n: int, seed: int, skip_ikpy: bool, log: Callable[[str], None]
) -> list[Row]:
    arm = load_arm(name)
    rng = np.random.default_rng(seed)
    Q = rng.uniform(arm.lower, arm.upper, size=(n, arm.n))
    Ts = arm.fk_batch(Q)
    sw = np.array([arm.swivel(q) for q in Q])
    q_mid = (arm.lower + arm.upper) / 2
    rows: list[Row] = []

    # closed form at the true swivel: success if some returned solution reaches T
    def closed(i: int) -> np.ndarray | None:
        sols = arm.ik(Ts[i], sw[i])
        return sols[0] if len(sols) else None

    times = np.empty(n)
    ok = 0
    for i in range(n):
        t0 = time.perf_counter()
        sols = arm.ik(Ts[i], sw[i])
        times[i] = time.perf_counter() - t0
        ok += any(_ok(arm, s, Ts[i]) for s in sols)
    rows.append(_row(arm, "ik(T, s) closed form", ok / n, times, "all in-limit solutions at the swivel"))
    log(f"{name}: ik done")

    succ, times = _timed(arm, Ts, lambda i: arm.ik_nearest(Ts[i], q_mid)[0])
    rows.append(_row(arm, "ik_nearest (all swivels)", succ, times, "nearest to the mid-range seed"))
    log(f"{name}: ik_nearest done")

    # vectorised batch: one call over all poses; success = a valid solution that reaches T
    t0 = time.perf_counter()
    Qb, valid = arm.ik_batch(Ts, sw)
    dt = time.perf_counter() - t0
    first = np.argmax(valid, axis=1)
    has = valid.any(axis=1)
    qf = Qb[np.arange(n), first]
    qf[~has] = 0.0
    Tf = arm.fk_batch(qf)
    pe = np.linalg.norm(Tf[:, :3, 3] - Ts[:, :3, 3], axis=1)
    re = np.abs(Tf[:, :3, :3] - Ts[:, :3, :3]).max(axis=(1, 2))  # entry error bounds the angle error
    bsucc = float(np.mean(has & (pe < TOL) & (re < TOL / 2)))
    rows.append(
        Row(name, "ik_batch (vectorised)", n, bsucc, dt / n * 1e6, math.nan, f"{n / dt:,.0f} poses/s")
    )
    log(f"{name}: batch done")

    m = min(peer_n, n)
    Tp = Ts[:m]
    succ, times = _timed(arm, Tp, lambda i: solve_dls(arm, Tp[i], q_mid, tol=TOL, timeout_s=TIMEOUT_S)[0])
    rows.append(_row(arm, "DLS (ours, numeric)", succ, times, "6-D, limits, restarts, 5 ms timeout"))
    log(f"{name}: DLS done")
    for variant in ("sequential", "batch"):
        succ, times = _timed(
            arm,
            Tp,
            lambda i, v=variant: solve_flow(arm, Tp[i], q_mid, variant=v, tol=TOL, timeout_s=TIMEOUT_S)[0],
            position_only=True,
        )
        rows.append(_row(arm, f"Flow {variant} (thesis)", succ, times, "position only, 5 ms timeout"))
        log(f"{name}: Flow {variant} done")
    if not skip_ikpy:
        chain = ikpy_chain(arm)
        init = [0.0, *q_mid.tolist(), 0.0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")

            def ikpy_call(i: int) -> np.ndarray:
                sol = chain.inverse_kinematics(
                    Tp[i][:3, 3], Tp[i][:3, :3], orientation_mode="all", initial_position=init
                )
                return np.asarray(sol[1:-1])

            succ, times = _timed(arm, Tp, ikpy_call)
        rows.append(_row(arm, "ikpy 4.2.1", succ, times, "orientation_mode='all', no timeout"))
        log(f"{name}: ikpy done")
    return rows


def _fmt_us(v: float) -> str:
    if math.isnan(v):
        return "-"
    return f"{v:,.1f} us" if v < 1000 else f"{v / 1000:,.2f} ms"


def table(rows: list[Row]) -> str:
    head = "| arm | solver | poses | success | median / call | p99 / call | note |\n"
    head += "|---|---|---:|---:|---:|---:|---|\n"
    body = "".join(
        f"| {r.arm} | {r.solver} | {r.n} | {100 * r.success:.2f} % | {_fmt_us(r.median_us)} | "
        f"{_fmt_us(r.p99_us)} | {r.note} |\n"
        for r in rows
    )
    return head + body


def targets(rows: list[Row]) -> str:
    out = []
    for arm in dict.fromkeys(r.arm for r in rows):
        by = {r.solver: r for r in rows if r.arm == arm}
        ik, near = by["ik(T, s) closed form"], by["ik_nearest (all swivels)"]
        batch = by["ik_batch (vectorised)"]
        pps = 1e6 / batch.median_us
        checks = [
            (f"success >= 99.9 % (ik_nearest {100 * near.success:.2f} %)", near.success >= 0.999),
            (f"ik(T, s) median <= 50 us ({ik.median_us:.1f} us)", ik.median_us <= 50),
            (f"ik_nearest median <= 0.3 ms ({near.median_us:.0f} us)", near.median_us <= 300),
            (f"batch >= 200,000 poses/s ({pps:,.0f})", pps >= 200_000),
        ]
        if "ikpy 4.2.1" in by:
            p = by["ikpy 4.2.1"]
            speed = p.median_us / near.median_us
            checks.append(
                (
                    f">= 20x faster than ikpy at a higher success (ik_nearest {speed:.0f}x, "
                    f"{100 * near.success:.2f} % vs {100 * p.success:.2f} %)",
                    speed >= 20 and near.success > p.success,
                )
            )
        for text, ok in checks:
            out.append(f"- {arm}: {'PASS' if ok else 'MISS'} {text}")
    return "\n".join(out) + "\n"


def _load() -> str:
    try:
        return ", ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000, help="random poses per arm (default 10000)")
    ap.add_argument("--peer-n", type=int, default=None, help="poses for DLS/Flow/ikpy (default: --n)")
    ap.add_argument("--arms", nargs="+", default=["pa10", "powercube7"])
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--quick", action="store_true", help="smoke run: 300 poses, 100 for the peers")
    ap.add_argument("--no-ikpy", action="store_true", help="skip the ikpy peer")
    ap.add_argument("--no-write", action="store_true", help="do not write benchmarks/results/ik_bench.md")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    n = 300 if args.quick else args.n
    peer_n = args.peer_n if args.peer_n is not None else (100 if args.quick else n)

    def log(msg: str) -> None:
        print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)

    load0 = _load()
    rows: list[Row] = []
    for name in args.arms:
        rows += bench_arm(name, n, peer_n, args.seed, args.no_ikpy, log)
    env = (
        f"Python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, "
        f"{os.cpu_count()} CPUs, OPENBLAS_CORETYPE={os.environ.get('OPENBLAS_CORETYPE', '(unset)')}, "
        f"load average at start {load0}, at end {_load()}"
    )
    text = (
        "# IK benchmark (TRAC-IK protocol)\n\n"
        f"Command: `python benchmarks/ik_bench.py {' '.join(argv if argv is not None else sys.argv[1:])}`"
        f"  \n{env}  \n"
        f"{n} random configurations per arm within the limits (seed {args.seed}), T = fk(q), seed at "
        f"mid-range, tolerance {TOL:g} m / {TOL:g} rad, timeout {TIMEOUT_S * 1e3:g} ms where a solver has "
        f"one; peers on the first {peer_n} of the same poses. Times are wall-clock per call in one Python "
        "process; ik_batch's median column is the amortised time per pose.\n\n"
        + table(rows)
        + "\nTargets:\n\n"
        + targets(rows)
    )
    print(text)
    if not args.no_write:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
