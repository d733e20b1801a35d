"""Pieces every benchmark shares: the plot module, the load-average line, the results writer, the
tool-down goal pose, the ramped arc-length timing of a path and the generators of the collision
benchmark's pose sets (the last three used by the tests too, through test/support).

The benches import this module as ``bench_common`` after putting their own folder on ``sys.path``
(the tests load benches, and this module, by file path, without benchmarks/ on ``sys.path``; it
imports nothing of the other benches).
"""

from __future__ import annotations

import importlib.util
import math
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

_PLOTS = "redarm_bench_plots"


def plots() -> ModuleType:
    """benchmarks/plots.py, loaded once by path under one module name (matplotlib only when drawn)."""
    if _PLOTS not in sys.modules:
        spec = importlib.util.spec_from_file_location(_PLOTS, Path(__file__).with_name("plots.py"))
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        sys.modules[_PLOTS] = mod
    return sys.modules[_PLOTS]


def pose_down(p: Any, yaw: float = 0.0) -> np.ndarray:
    """4x4 tool pose at ``p`` with the tool z axis pointing down, turned by ``yaw`` about the vertical."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = p
    return T


def mixed_collision_poses(
    arm: Any, model: Any, rng: np.random.Generator
) -> Iterator[tuple[np.ndarray, np.ndarray, Any]]:
    """Endless poses (T, every in-limit solution on a 0.1 deg swivel sweep, their self-collision
    result) of random postures above 0.3 m whose solutions are partly colliding, partly free."""
    from redarm_ros.geometry.self_collision import self_collision_batch  # noqa: PLC0415

    S = np.linspace(-math.pi, math.pi, 3600, endpoint=False)
    while True:
        T = arm.fk(rng.uniform(arm.lower, arm.upper))
        if T[2, 3] < 0.3:
            continue
        Q, valid = arm.ik_batch(np.broadcast_to(T, (len(S), 4, 4)), S)
        ii, bb = np.nonzero(valid)
        rows = Q[ii, bb]
        res = self_collision_batch(arm, rows, model=model)
        if res.free.any() and res.colliding.any():
            yield T, rows, res


def shifted_poses(arm: Any, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """Endless tool poses of collision-free postures (within 80 % of the limits) moved sideways by
    0.4-1.2 m: mostly out of the arm's reach from where it stands (the caller keeps those)."""
    from redarm_ros.geometry.self_collision import self_collision  # noqa: PLC0415

    while True:
        q = rng.uniform(0.8 * arm.lower, 0.8 * arm.upper)
        if self_collision(arm, q).colliding:
            continue
        T = arm.fk(q).copy()
        ang, dist = rng.uniform(-math.pi, math.pi), rng.uniform(0.4, 1.2)
        T[0, 3] += dist * math.cos(ang)
        T[1, 3] += dist * math.sin(ang)
        yield T


def add_plot_dir(ap: Any) -> None:
    """The ``--plot-dir`` option of a bench that draws its results (argparse parser ``ap``)."""
    ap.add_argument("--plot-dir", type=Path, default=None,
                    help="write the PNG plots here (default: beside the results file when it is written)")


def doc_header(title: str, doc: str) -> list[str]:
    """The opening lines of a results file: ``title`` and the bench's docstring up to its usage."""
    return [title, "", doc.split("    .venv/bin/python")[0].strip(), ""]


def ramp_arc(length: float, v: float, t_ramp: float = 0.5) -> tuple[Callable[[float], float], float]:
    """Arc length s(t) for a cruise at ``v`` with smooth (smoothstep-speed) ramps at both ends, and the
    duration: the timing of track_bench's paths and of test/test_control_tracking.py's circle."""
    d_ramp = 0.5 * v * t_ramp
    t_cruise = max(length - 2.0 * d_ramp, 0.0) / v
    total = 2.0 * t_ramp + t_cruise

    def s_of(t: float) -> float:
        t = min(max(t, 0.0), total)
        if t < t_ramp:
            x = t / t_ramp
            return v * t_ramp * (x**3 - 0.5 * x**4)
        if t < t_ramp + t_cruise:
            return d_ramp + v * (t - t_ramp)
        x = (total - t) / t_ramp
        return length - v * t_ramp * (x**3 - 0.5 * x**4)

    return s_of, total


def load_line(load0: tuple[float, float, float], t0: float) -> str:
    """The load average before (``load0``) and now, the machine and the wall time since ``t0``."""
    load1 = os.getloadavg()
    return (
        f"Load average (1/5/15 min) before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, after: "
        f"{load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}; {platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}, {time.time() - t0:.0f} s wall."
    )


def write_sections(path: Path, header: list[str], sections: dict[str, list[str]], footer: str) -> str:
    """Write ``header``, the sections (``## title`` -> lines) and ``footer`` to ``path``, keeping the
    sections of an earlier run that this run did not redo (e.g. the stack run is done apart)."""
    old: dict[str, list[str]] = {}
    if path.is_file():
        cur = None
        for line in path.read_text().splitlines():
            if line.startswith("## "):
                cur = line
                old[cur] = []
            elif cur is not None and line.startswith("What this does not cover"):
                cur = None
            elif cur is not None:
                old[cur].append(line)
    merged = dict(old)
    merged.update(sections)
    order = [k for k in merged if k.startswith("## In-process")]
    order += [k for k in merged if not k.startswith("## In-process")]
    out = list(header)
    for k in order:
        out.append(k)
        out += merged[k]
        while out and out[-1] == "":
            out.pop()
        out.append("")
    out.append(footer)
    text = "\n".join(out) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


def finish_sections(
    path: Path, header: list[str], sections: dict[str, list[str]], footer: str, no_write: bool
) -> str:
    """The report text of a sectioned bench: written to ``path`` (merged with earlier sections) unless
    ``no_write``, then printed and returned."""
    if no_write:
        text = "\n".join(header + [line for k, v in sections.items() for line in [k, *v]] + [footer])
    else:
        text = write_sections(path, header, sections, footer)
    print(text)
    return text


def spin_in_background(ex: Any) -> tuple[threading.Event, threading.Thread]:
    """Spin the rclpy executor ``ex`` on a daemon thread until the returned event is set."""
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    return stop, th


def wait_for_corridor_plan(ctl: Any) -> float:
    """Wait for the controller's corridor plan of the goal just set (its worker thread; the node's arm
    holds meanwhile) and return the wall time waited (s). In process the steps run faster than real
    time, so the benches wait instead of stepping through the hold: the move's time counts from the
    plan, and the planning time is reported on its own."""
    st = getattr(ctl, "_st", None)
    plan = getattr(st, "corridor_plan", None)
    if plan is None:
        return 0.0
    t0 = time.perf_counter()
    plan.result()
    return time.perf_counter() - t0
