"""Fresh-clone runs of the README's test command: how long ``CI=true make test`` takes on this machine
and whether it passes, quiet or with one core kept busy, and how much CPU it used.

Each run clones the repository at one commit into a new temporary folder (nothing of this checkout's
venv, build or caches comes along; the user's caches, pip's and the set-up's ``~/.cache/redarm_ros``, are
used as on CI), runs ``CI=true make test`` there (set-up included, as ``.ci/run`` does) and records the
wall time in all, the set-up phase's (until pytest starts: venv, wheels, interfaces, ruff, the collection
warm-up), pytest's own time and its summary line, the CPU time (user + sys) of everything the run
started, the exit code, the load average before and after, and the host's speed over the run (the
median CPU time of ``benchmarks/host_speed.py``'s reference work: the same suite costs more CPU where it
is higher). The CPU time counts processes that outlive
their parents too (this process is their subreaper); it is the measure to compare on a shared machine,
where wall times vary with the other load. ``--busy`` keeps one core busy for the whole run with a shell
loop at normal priority (started before the clone, ended by its PID after the run). The clone is removed
after each run; a failed run keeps its log under ``--log-dir``.

Run: ``python3 benchmarks/suite_bench.py --runs 3`` (each run takes 7-8 minutes on 2 cores);
``--busy`` for the busy-core condition; ``--commit REV`` (default HEAD). Appends one row per run to
``benchmarks/results/suite_bench.md`` unless ``--no-write``. Target (issue 34): at most 480 s in all,
passing 10 of 10 times quiet and 10 of 10 with a busy core.
What it does not cover: a machine other than this one; the network namespace the CI gives.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from host_speed import HostSpeedProbe  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "suite_bench.md"
TIMEOUT_S = 5400.0  # CI's limit
TARGET_S = 480.0
HEADER = [
    "# Fresh-clone runs of the test command (`benchmarks/suite_bench.py`)",
    "",
    "Each row: `git clone` of the commit into an empty folder, then `CI=true make test` there (set-up, "
    "ruff and pytest, as `.ci/run`). *busy*: one shell loop kept a core busy throughout. Target: at most "
    f"{TARGET_S:.0f} s in all, 10 of 10 passing in each condition. Newest first.",
    "",
    "| date (UTC) | commit | condition | in all s | pytest | result | load avg before / after |",
    "|---|---|---|---:|---|---|---|",
]
SUMMARY = re.compile(r"=+ (.*\b(passed|failed|error)\b.*) in ([0-9.]+)s(?: \(([0-9:]+)\))? =+")


def become_subreaper() -> None:
    """Orphans of our children are re-parented to us (Linux), so their CPU time is counted."""
    pr_set_child_subreaper = 36
    try:
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_child_subreaper, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def reap_orphans() -> None:
    """Collect every child that has ended (orphans included) so getrusage counts it."""
    while True:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return


def children_cpu_s() -> float:
    """User + system CPU seconds of all ended and collected children so far."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_timed(cmd: list[str], cwd: Path, env: dict[str, str], marker: str) -> tuple[int, str, float | None]:
    """Run ``cmd`` (output merged), return its exit code (-1: timed out), its output and the seconds
    until a line starting with ``marker`` appeared (None: never)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    lines: list[str] = []
    marked: list[float] = []

    def read() -> None:
        assert proc.stdout is not None
        for raw in proc.stdout:
            line = raw.decode(errors="replace")
            if not marked and line.startswith(marker):
                marked.append(time.monotonic() - t0)
            lines.append(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        rc = proc.wait(TIMEOUT_S)
    except subprocess.TimeoutExpired:
        stop(proc)
        rc = -1
        lines.append("\n(timed out)")
    reader.join(10.0)
    return rc, "".join(lines), (marked[0] if marked else None)


def start_hog() -> subprocess.Popen[bytes]:
    """One busy shell loop at normal priority, in its own process group."""
    return subprocess.Popen(["sh", "-c", "while :; do :; done"], start_new_session=True)


def stop(proc: subprocess.Popen[bytes]) -> None:
    """End a child we started: SIGINT, wait, SIGINT again, then SIGKILL."""
    for sig, wait_s in ((signal.SIGINT, 2.0), (signal.SIGINT, 2.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            return
        proc.send_signal(sig)
        try:
            proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            continue


def one_run(commit: str, busy: bool, log_dir: Path) -> dict[str, str]:
    """Clone ``commit``, run the test command, and return the row's fields."""
    load0 = os.getloadavg()
    probe = HostSpeedProbe()  # its CPU is not counted: it is collected after the run's figure
    hog = start_hog() if busy else None
    work = Path(tempfile.mkdtemp(prefix="redarm-suite-"))
    t0 = time.monotonic()
    try:
        src = work / "p"
        subprocess.run(["git", "clone", "-q", str(REPO), str(src)], check=True)
        subprocess.run(["git", "-C", str(src), "checkout", "-q", commit], check=True)
        env = dict(os.environ, CI="true")
        cpu0 = children_cpu_s()
        rc, text, setup_s = run_timed(["make", "test"], src, env, "+ pytest")
        reap_orphans()
        cpu = children_cpu_s() - cpu0
    finally:
        wall = time.monotonic() - t0
        if hog is not None:
            stop(hog)
        probe.stop()
        shutil.rmtree(work, ignore_errors=True)
    load1 = os.getloadavg()
    found = list(SUMMARY.finditer(text))
    m = found[-1] if found else None
    summary = m.group(1) if m else "no summary"
    pytest_time = (m.group(4) or f"{float(m.group(3)):.0f} s") if m else "-"
    if rc != 0:
        log_dir.mkdir(parents=True, exist_ok=True)
        log = log_dir / f"suite-{commit[:10]}-{int(time.time())}.log"
        log.write_text(text)
        print(f"suite_bench: run failed (exit {rc}), log in {log}", file=sys.stderr)
    result = ("passed: " if rc == 0 else f"FAILED (exit {rc}): ") + summary
    failed = sorted(set(re.findall(r"^FAILED (\S+)", text, flags=re.MULTILINE)))
    if failed:
        result += " (" + ", ".join(f"`{t}`" for t in failed) + ")"
    return {"date": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "commit": commit[:10],
            "condition": "busy" if busy else "quiet", "wall": f"{wall:.0f}", "pytest": pytest_time,
            "setup": "-" if setup_s is None else f"{setup_s:.0f}", "cpu": f"{cpu:.0f}",
            "host": "-" if probe.median_ms is None else f"{probe.median_ms:.1f}",
            "result": result,
            "load": f"{load0[0]:.2f} / {load1[0]:.2f}"}


def write_row(row: dict[str, str]) -> None:
    """Put ``row`` first under the table (the file is created with its header when missing)."""
    lines = RESULTS.read_text().splitlines() if RESULTS.is_file() else list(HEADER)
    row = dict(row, wall=f"{row['wall']} (set-up {row['setup']}, CPU {row['cpu']}, host {row['host']} ms)")
    cells = [row[k] for k in ("date", "commit", "condition", "wall", "pytest", "result", "load")]
    at = len(HEADER)
    lines.insert(at, "| " + " | ".join(cells) + " |")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1, help="runs in a row (default 1)")
    ap.add_argument("--busy", action="store_true", help="keep one core busy during each run")
    ap.add_argument("--commit", default="HEAD", help="the commit to clone (default HEAD)")
    ap.add_argument("--log-dir", type=Path, default=Path(tempfile.gettempdir()) / "redarm-suite-logs",
                    help="where a failed run's output is kept")
    ap.add_argument("--no-write", action="store_true", help="do not write the results file")
    args = ap.parse_args(argv)
    become_subreaper()
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", args.commit], check=True,
                            stdout=subprocess.PIPE, text=True).stdout.strip()
    failed = 0
    for i in range(args.runs):
        row = one_run(commit, args.busy, args.log_dir)
        failed += not row["result"].startswith("passed")
        print(f"run {i + 1}/{args.runs}: {row['condition']} {row['wall']} s in all, set-up {row['setup']} s, "
              f"pytest {row['pytest']}, CPU {row['cpu']} s (user + sys), host ref {row['host']} ms, "
              f"load {row['load']}, {row['result']}",
              flush=True)
        if not args.no_write:
            write_row(row)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
