"""Start-up CPU of the simulated stack's processes: what importing each entry point costs.

Every process ``redarm-bringup`` starts (bus server, simulator and its physics child, the driver node
and its cycle process, ik_service, controller, description) begins by importing its module; the test
suite starts such stacks dozens of times. This runs ``python -c "import MODULE"`` in a fresh
interpreter ``-n`` times per module (interleaved: module 1, 2, ..., 1, 2, ...; one discarded warm-up
each so the bytecode caches exist, as ``make test`` has them) and prints the median CPU
(user + system, from ``wait4``) per module, the bare interpreter's, and the sum over the list.

Run::

    .venv/bin/python benchmarks/startup_bench.py                 # 7 runs a module
    .venv/bin/python benchmarks/startup_bench.py -n 11 --src /tmp/other_checkout   # another tree's code
    .venv/bin/python benchmarks/startup_bench.py --env OPENBLAS_NUM_THREADS=1      # as a stack child
    scripts/ros_sandbox.sh .venv/bin/python benchmarks/startup_bench.py --stack  # + a whole bringup

``--src DIR`` runs the children in DIR (the ``-c`` interpreter puts its working directory first on
``sys.path``, so DIR's ``redarm_ros`` is the one imported): two trees can be compared A/B with the
same venv. ``--stack`` also starts ``redarm-bringup`` (needs the DDS sandbox), waits for its
description node's ready line, stops it with SIGINT and reports the CPU of the whole process tree
(everything its processes reaped); that figure includes the run's first seconds of work, so it is
noisier than the import rows. CPU figures on a shared machine swing; compare trees interleaved.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

# The entry points a simulated stack runs (python -m ...), and the cycle/physics children's modules.
MODULES = [
    "redarm_ros.can.bus_server",
    "redarm_ros.sim.hardware",
    "redarm_ros.sim.physics_process",
    "redarm_ros.nodes.can_driver",
    "redarm_ros.can.driver_process",
    "redarm_ros.nodes.ik_service",
    "redarm_ros.nodes.controller",
    "redarm_ros.nodes.description",
]

REPO = Path(__file__).resolve().parents[1]


_EXTRA_ENV: dict[str, str] = {}  # --env KEY=VALUE: what a tree's stack gives its children


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # the suite writes and uses bytecode caches
    env.update(_EXTRA_ENV)
    return env


def child_cpu(cmd: list[str], cwd: Path) -> float:
    """CPU seconds (user + system) of ``cmd`` run to its end; raises on a non-zero exit."""
    proc = subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if proc.stderr:
        proc.stderr.close()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-2000:]}")
    return ru.ru_utime + ru.ru_stime


def import_cpu(module: str, python: str, src: Path) -> float:
    """CPU seconds of a fresh interpreter importing ``module`` (``pass``: the bare interpreter)."""
    code = "pass" if module == "pass" else f"import {module}"
    return child_cpu([python, "-c", code], src)


def stack_cpu(python: str, src: Path, timeout_s: float = 120.0) -> float:
    """CPU seconds of a whole ``redarm-bringup`` from exec to its last ready line and a SIGINT stop."""
    cmd = [python, "-m", "redarm_ros.bringup"]
    proc = subprocess.Popen(cmd, cwd=src, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    ready = re.compile(r"description ready:")
    lines: list[str] = []
    for line in proc.stdout:
        lines.append(line)
        if ready.search(line):
            break
        if time.monotonic() > deadline:
            break
    proc.send_signal(signal.SIGINT)
    for line in proc.stdout:  # drain, so the stop is not blocked on a full pipe
        lines.append(line)
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if not any(ready.search(x) for x in lines):
        raise RuntimeError("the stack did not come up:\n" + "".join(lines[-40:]))
    return ru.ru_utime + ru.ru_stime


def main(argv: list[str] | None = None) -> int:
    """Measure and print the table; the exit code is 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-n", type=int, default=7, help="measured runs per module (after one warm-up)")
    ap.add_argument("--python", default=sys.executable, help="interpreter to run (default: this one)")
    ap.add_argument("--src", type=Path, default=REPO, help="source tree whose redarm_ros is imported")
    ap.add_argument("--modules", nargs="*", default=MODULES, help="modules to import (default: the stack's)")
    ap.add_argument("--stack", action="store_true", help="also time a whole redarm-bringup start and stop")
    ap.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                    help="set in the children's environment (e.g. OPENBLAS_NUM_THREADS=1, as the stack does)")
    ns = ap.parse_args(argv)
    _EXTRA_ENV.update(kv.split("=", 1) for kv in ns.env)

    names = ["pass", *ns.modules]
    for m in names:  # warm-up: write the bytecode caches, check every import works
        import_cpu(m, ns.python, ns.src)
    runs: dict[str, list[float]] = {m: [] for m in names}
    for _ in range(ns.n):
        for m in names:
            runs[m].append(import_cpu(m, ns.python, ns.src))
    print(f"import CPU (user+sys) in s, median of {ns.n}, src {ns.src}, env {ns.env or '-'}")
    for m in names:
        label = "(bare interpreter)" if m == "pass" else m
        vals = " ".join(f"{v:.2f}" for v in runs[m])
        print(f"  {label:34s} {statistics.median(runs[m]):6.3f}   [{vals}]")
    total = sum(statistics.median(runs[m]) for m in ns.modules)
    print(f"  {'sum over the modules':34s} {total:6.3f}")
    if ns.stack:
        s = [stack_cpu(ns.python, ns.src) for _ in range(max(1, ns.n // 3))]
        print(f"  {'redarm-bringup start+stop':34s} {statistics.median(s):6.3f}   "
              f"[{' '.join(f'{v:.2f}' for v in s)}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
