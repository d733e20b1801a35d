"""How fast this host runs Python right now: the CPU time of one fixed piece of interpreter work.

The benchmarks' CPU figures (``stack_cpu_bench``, ``suite_bench``, ``soak_bench``) are CPU seconds of
Python processes, and on a shared virtual machine the same work can cost up to twice the CPU from one
minute to the next (a busy neighbour on the same physical core slows ours without showing as stolen
time). A :class:`HostSpeedProbe` runs beside a benchmark, in a process of its own (no interference
with the benchmark's interpreter lock): every ``period_s`` it times :func:`reference_work` by its own
thread CPU clock, which waiting for a CPU does not count. Rows taken on hosts with different probe
figures compare in proportion to them.

Standard library only: ``suite_bench`` runs on the system Python, before any venv exists.

Run alone: ``python3 benchmarks/host_speed.py [--seconds S]`` prints the probe figures over that time;
it writes no results file.
"""

from __future__ import annotations

import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

#: Loop count of :func:`reference_work`: about 20-40 ms of CPU on the 2-core machines here.
REFERENCE_ITERATIONS = 200_000


def reference_work(n: int = REFERENCE_ITERATIONS) -> int:
    """Interpreter-bound work of the kind the stack does (attribute and dict access, arithmetic,
    calls): the same instructions every time."""
    table = {i: i * 3 for i in range(64)}
    acc = 0
    for i in range(n):
        acc = (acc + table[i & 63] * (i % 7)) & 0xFFFFFF
    return acc


def reference_ms() -> float:
    """The thread CPU time of one :func:`reference_work`, ms."""
    t0 = time.thread_time()
    reference_work()
    return (time.thread_time() - t0) * 1e3


_CHILD = (
    "import sys, time\n"
    "sys.path.insert(0, {path!r})\n"
    "from host_speed import reference_ms\n"
    "try:\n"
    "    while True:\n"
    "        print(f'{{reference_ms():.2f}}', flush=True)\n"
    "        time.sleep({period!r})\n"
    "except (KeyboardInterrupt, BrokenPipeError):\n"
    "    pass\n"
)


class HostSpeedProbe:
    """Times :func:`reference_work` every ``period_s`` in a child process until :meth:`stop`.

    ``summary()`` says ``reference work 31.2 ms CPU (median of 40; 28.0-55.1)``; ``median_ms`` is
    None until a sample came."""

    def __init__(self, period_s: float = 5.0) -> None:
        self.samples: list[float] = []
        here = str(Path(__file__).resolve().parent)
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD.format(path=here, period=period_s)],
            stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
        self._reader = threading.Thread(target=self._read, name="host-speed", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            try:
                self.samples.append(float(line))
            except ValueError:
                continue

    def stop(self) -> None:
        """End the child (SIGINT, wait, SIGINT again, then SIGKILL) and collect its last lines."""
        for sig, wait_s in ((signal.SIGINT, 2.0), (signal.SIGINT, 2.0), (signal.SIGKILL, 5.0)):
            if self._proc.poll() is not None:
                break
            self._proc.send_signal(sig)
            try:
                self._proc.wait(wait_s)
            except subprocess.TimeoutExpired:
                continue
        self._reader.join(2.0)

    def __enter__(self) -> HostSpeedProbe:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    @property
    def median_ms(self) -> float | None:
        return statistics.median(self.samples) if self.samples else None

    def summary(self) -> str:
        if not self.samples:
            return "reference work: no sample"
        return (f"reference work {statistics.median(self.samples):.1f} ms CPU (median of "
                f"{len(self.samples)}; {min(self.samples):.1f}-{max(self.samples):.1f})")


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="how long to sample (one sample a second)")
    ap.add_argument("--quick", action="store_true", help="3 s")
    args = ap.parse_args(argv)
    with HostSpeedProbe(period_s=1.0) as probe:
        time.sleep(3.0 if args.quick else args.seconds)
    print(probe.summary())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
