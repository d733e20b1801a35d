"""Start-up CPU of the simulated stack's processes: what importing each entry point costs.

Every process ``redarm-bringup`` starts (bus server, simulator and its physics child, the driver node
and its cycle process, ik_service, controller, description) begins by importing its module; the test
suite starts such stacks dozens of times. This runs ``python -c "import MODULE"`` in a fresh
interpreter ``-n`` times per module (interleaved: module 1, 2, ..., 1, 2, ...; one discarded warm-up
each so the bytecode caches exist, as ``make test`` has them) and prints the median CPU
(user + system, from ``wait4``) per module, the bare interpreter's, and the sum over the list.

Run::

    .venv/bin/python benchmarks/startup_bench.py                 # 7 runs a module, this tree
    .venv/bin/python benchmarks/startup_bench.py --env OPENBLAS_NUM_THREADS=1      # as a stack child
    .venv/bin/python benchmarks/startup_bench.py --base /tmp/main_checkout --env OPENBLAS_NUM_THREADS=1
    scripts/ros_sandbox.sh .venv/bin/python benchmarks/startup_bench.py --stack -n 3  # + whole bringups

``--src DIR`` imports DIR's ``redarm_ros`` (the ``-c`` interpreter puts its working directory first on
``sys.path``; default: this tree). ``--base DIR`` measures a second tree A/B: every run of a module in
``--src`` is paired with one in DIR, alternately, and the table has both medians and each pair
(``--env`` applies to ``--src`` only, ``--base-env`` to DIR: each tree as its own stack would start
its children). ``--stack`` also starts ``redarm-bringup`` (needs the DDS sandbox), waits for the
description node's ready line, stops it with SIGINT and reports the CPU of the whole process tree
(everything its processes reaped); it includes the stack's first seconds of work, so it is noisier
than the import rows. CPU figures on a shared machine swing; compare trees interleaved.
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
from dataclasses import dataclass, field
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
BARE = "pass"  # the bare interpreter's row


@dataclass
class Tree:
    """A source tree and the environment its children get."""

    label: str
    src: Path
    env: dict[str, str] = field(default_factory=dict)

    def environ(self) -> dict[str, str]:
        env = dict(os.environ)
        env.pop("PYTHONDONTWRITEBYTECODE", None)  # the suite writes and uses bytecode caches
        env.update(self.env)
        return env


def child_cpu(cmd: list[str], tree: Tree) -> float:
    """CPU seconds (user + system) of ``cmd`` run to its end in ``tree``; raises on a non-zero exit."""
    proc = subprocess.Popen(cmd, cwd=tree.src, env=tree.environ(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    assert proc.stderr is not None
    err = proc.stderr.read().decode(errors="replace")
    proc.stderr.close()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-2000:]}")
    return ru.ru_utime + ru.ru_stime


def import_cpu(module: str, python: str, tree: Tree) -> float:
    """CPU seconds of a fresh interpreter importing ``module`` (``pass``: the bare interpreter)."""
    return child_cpu([python, "-c", "pass" if module == BARE else f"import {module}"], tree)


def stack_cpu(python: str, tree: Tree, timeout_s: float = 120.0) -> float:
    """CPU seconds of a whole ``redarm-bringup``: exec to its last ready line, then a SIGINT stop."""
    proc = subprocess.Popen([python, "-m", "redarm_ros.bringup"], cwd=tree.src, env=tree.environ(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    ready = re.compile(r"description ready:")
    lines: list[str] = []
    for line in proc.stdout:
        lines.append(line)
        if ready.search(line) or time.monotonic() > deadline:
            break
    proc.send_signal(signal.SIGINT)
    lines.extend(proc.stdout)  # drain, so the stop is not blocked on a full pipe
    _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if not any(ready.search(x) for x in lines):
        raise RuntimeError("the stack did not come up:\n" + "".join(lines[-40:]))
    return ru.ru_utime + ru.ru_stime


def _fmt(vals: list[float]) -> str:
    return " ".join(f"{v:.2f}" for v in vals)


def main(argv: list[str] | None = None) -> int:
    """Measure and print the table; the exit code is 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-n", type=int, default=7, help="measured runs per module and tree (after a warm-up)")
    ap.add_argument("--python", default=sys.executable, help="interpreter to run (default: this one)")
    ap.add_argument("--src", type=Path, default=REPO, help="source tree whose redarm_ros is imported")
    ap.add_argument("--base", type=Path, default=None, help="a second tree, measured A/B against --src")
    ap.add_argument("--modules", nargs="*", default=MODULES, help="modules to import (default: the stack's)")
    ap.add_argument("--stack", action="store_true", help="also time whole redarm-bringup starts and stops")
    ap.add_argument("--env", action="append", default=[], metavar="KEY=VALUE",
                    help="set in --src's children (e.g. OPENBLAS_NUM_THREADS=1, as its stack does)")
    ap.add_argument("--base-env", action="append", default=[], metavar="KEY=VALUE",
                    help="set in --base's children")
    ns = ap.parse_args(argv)

    trees = [Tree("B", ns.src, dict(kv.split("=", 1) for kv in ns.env))]
    if ns.base is not None:
        trees.insert(0, Tree("A", ns.base, dict(kv.split("=", 1) for kv in ns.base_env)))
    names = [BARE, *ns.modules]
    for m in names:  # warm-up: write the bytecode caches, check every import works
        for t in trees:
            import_cpu(m, ns.python, t)
    runs: dict[tuple[str, str], list[float]] = {(t.label, m): [] for t in trees for m in names}
    for _ in range(ns.n):
        for m in names:
            for t in trees:
                runs[t.label, m].append(import_cpu(m, ns.python, t))
    if ns.stack:
        for _ in range(ns.n):
            for t in trees:
                runs[t.label, "stack"] = [*runs.get((t.label, "stack"), []), stack_cpu(ns.python, t)]
        names.append("stack")

    for t in trees:
        print(f"{t.label}: {t.src} env {t.env or '-'}")
    print(f"CPU (user+sys) in s, median of {ns.n}" + (", A/B pairs interleaved" if len(trees) > 1 else ""))
    for m in names:
        label = {"pass": "(bare interpreter)", "stack": "redarm-bringup start+stop"}.get(m, m)
        meds = [statistics.median(runs[t.label, m]) for t in trees]
        if len(trees) == 1:
            print(f"  {label:34s} {meds[0]:6.3f}   [{_fmt(runs['B', m])}]")
        else:
            pairs = " ".join(f"{a:.2f}/{b:.2f}" for a, b in zip(runs["A", m], runs["B", m], strict=True))
            print(f"  {label:34s} A {meds[0]:6.3f}  B {meds[1]:6.3f}  B-A {meds[1] - meds[0]:+6.3f}   "
                  f"[A/B: {pairs}]")
    if not ns.modules:
        return 0
    sums = [sum(statistics.median(runs[t.label, m]) for m in ns.modules) for t in trees]
    print(f"  {'sum over the modules':34s} " + "  ".join(f"{t.label} {s:6.3f}" for t, s in zip(trees, sums,
                                                                                             strict=True)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
