"""IK table demo: a few poses per arm, every solution at one swivel, the nearest solution to a seed.

Run with ``python -m redarm_ros.ik_demo`` (``--arms``, ``--swivel``, ``--reps``). ROS-free; it prints
readable tables to stdout. Angles in degrees, positions in metres, quaternions (x, y, z, w) as in ROS
messages.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from redarm_ros.kinematics import load_arm
from redarm_ros.kinematics.quaternion import matrix_to_quat, to_xyzw

# a few hand-picked configurations per arm (rad); their poses are the demo targets
POSES: dict[str, list[list[float]]] = {
    "pa10": [
        [0.3, 0.6, -0.4, 1.2, 0.5, -0.7, 0.9],
        [-1.0, 0.9, 0.5, 0.8, -1.5, 1.2, 2.5],
        [0.0, 0.4, 0.0, 2.0, 0.0, 0.7, 0.0],
    ],
    "pa10_7c": [[0.8, -0.5, 0.3, 1.5, 0.2, 0.9, -0.4], [2.0, 0.7, -1.0, 0.6, 1.0, -0.5, 0.3]],
    "powercube7": [[0.2, 0.8, 0.3, 1.3, -0.4, 0.9, 0.1], [-1.2, -0.6, 1.0, 1.6, 0.8, -1.1, -0.7]],
    "powercube6": [[0.5, 0.4, 0.0, 0.9, -0.6, 0.3], [-1.0, 1.1, 0.0, -0.8, 0.5, -1.2]],
}


def _out(line: str = "") -> None:
    sys.stdout.write(line + "\n")


def _deg(q: np.ndarray) -> str:
    return " ".join(f"{math.degrees(v):8.2f}" for v in q)


def _time_us(fn: Callable[[], Any], reps: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t0) / reps * 1e6


def demo_arm(name: str, swivel: float | None, reps: int) -> None:
    arm = load_arm(name)
    _out(f"=== {name}: {arm.n} joints, kind {arm.kind}, links {getattr(arm, 'link_lengths', '?')} m")
    for k, q in enumerate(POSES.get(name, [])):
        q = np.asarray(q, dtype=float)
        T = arm.fk(q)
        quat = to_xyzw(matrix_to_quat(T[:3, :3]))
        _out(
            f"pose {k + 1}: p = ({T[0, 3]:.4f}, {T[1, 3]:.4f}, {T[2, 3]:.4f}) m, "
            f"q_xyzw = ({quat[0]:.4f}, {quat[1]:.4f}, {quat[2]:.4f}, {quat[3]:.4f})"
        )
        if arm.has_swivel:
            s = arm.swivel(q) if swivel is None else swivel
            sols = arm.ik(T, s)
            t_ik = _time_us(lambda T=T, s=s: arm.ik(T, s), reps)
            what = "the generating configuration's" if swivel is None else "the requested"
            label = f"all solutions at {what} swivel {math.degrees(s):.2f} deg"
        else:
            sols = arm.ik(T)
            t_ik = _time_us(lambda T=T: arm.ik(T), reps)
            label = "all analytic solutions (joint 3 locked)"
        _out(f"  {label}: {len(sols)} in limits, {t_ik:.1f} us per call")
        header = (
            "    #  " + " ".join(f"{'q' + str(i + 1):>8}" for i in range(arm.n)) + "   pos err    rot err"
        )
        _out(header)
        for i, sol in enumerate(sols):
            pe, re = arm.pose_error(sol, T)
            _out(f"   {i + 1:2d}  {_deg(sol)}  {pe:9.1e}  {re:9.1e}")
        seed = q + np.linspace(-0.2, 0.2, arm.n)
        qn, info = arm.ik_nearest(T, seed)
        t_near = _time_us(lambda T=T, seed=seed: arm.ik_nearest(T, seed), max(1, reps // 4))
        _out(f"  seed            {_deg(seed)}")
        if qn is None:
            _out(f"  nearest: none ({info.status.value}: {info.message})")
        else:
            sw = "" if info.swivel is None else f", swivel {math.degrees(info.swivel):.2f} deg"
            _out(f"  nearest         {_deg(qn)}   ({t_near:.0f} us{sw}, pos err {info.pos_err:.1e} m)")
        _out()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="IK table demo (closed-form swivel IK, PowerCube 6-DOF IK)")
    ap.add_argument("--arms", nargs="+", default=list(POSES))
    ap.add_argument(
        "--swivel", type=float, default=None, help="swivel (rad) for the tables (default: each pose's own)"
    )
    ap.add_argument("--reps", type=int, default=200, help="repetitions for the timings")
    args = ap.parse_args(argv)
    for name in args.arms:
        demo_arm(name, args.swivel, args.reps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
