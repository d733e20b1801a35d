"""The stack CPU benchmark's measuring parts, without a stack: CPU seconds from /proc, a child's process
group split into its main process and the rest, and the results table (no speed assertions)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType, SimpleNamespace

import pytest

from redarm_ros.procs import descendants

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "stack_cpu_bench.py"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("stack_cpu_bench", BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["stack_cpu_bench"] = mod  # dataclasses look their module up there
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.modules.pop("stack_cpu_bench", None)


def test_cpu_seconds_of_a_busy_process_grow_and_a_gone_one_has_none(bench: ModuleType) -> None:
    c0 = bench.proc_cpu_s(os.getpid())
    end = time.process_time() + 0.2
    while time.process_time() < end:
        pass
    assert bench.proc_cpu_s(os.getpid()) >= c0 + 0.1
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    assert bench.proc_cpu_s(p.pid) is None


def test_a_childs_process_group_gives_its_own_row_and_one_for_the_rest(bench: ModuleType) -> None:
    # A leader in a session of its own with a child of its own, as the stack's can_driver and its cycle.
    leader = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time; subprocess.Popen("
                               "[sys.executable, '-c', 'import time; time.sleep(30)']); time.sleep(30)"],
                              start_new_session=True)
    try:
        stack = SimpleNamespace(children={"can_driver": SimpleNamespace(pid=leader.pid)})
        rows: dict[str, list[int]] = {}
        end = time.monotonic() + 10.0
        while time.monotonic() < end and len(rows) < 2:
            rows = bench.process_rows(stack)
            time.sleep(0.05)
        assert rows["can_driver"] == [leader.pid]
        assert len(rows["can_driver (cycle process)"]) == 1
    finally:
        os.killpg(leader.pid, 9)
        leader.wait()


def test_a_descendant_in_a_session_of_its_own_is_counted(bench: ModuleType) -> None:
    # As the simulator's physics process: a child that left its parent's process group.
    leader = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time; subprocess.Popen("
                               "[sys.executable, '-c', 'import time; time.sleep(30)'], "
                               "start_new_session=True); time.sleep(30)"],
                              start_new_session=True)
    try:
        end = time.monotonic() + 10.0
        while not any(os.getsid(p) == p for p in descendants(leader.pid)):  # the child's own session
            assert time.monotonic() < end
            time.sleep(0.05)
        rows = bench.process_rows(SimpleNamespace(children={"sim": SimpleNamespace(pid=leader.pid)}))
        assert rows["sim"] == [leader.pid]
        (child,) = rows["sim (children)"]
        assert os.getsid(child) == child
    finally:
        for pid in descendants(leader.pid):
            os.kill(pid, 9)
        os.killpg(leader.pid, 9)
        leader.wait()


def test_the_table_has_a_row_per_process_the_total_and_the_targets(bench: ModuleType) -> None:
    r = bench.CaseResult("rest", 10.0, {"sim": 2.0, "canbus": 1.0}, (1.0, 1.0, 1.0), (1.5, 1.0, 1.0),
                         {"cycles": 2500.0, "overruns": 0.0, "lost": 0.0, "rate_hz_achieved": 250.0})
    text = "\n".join(bench.table([r]))
    assert "| sim | 2.00 / 20.0 |" in text and "| canbus | 1.00 / 10.0 |" in text
    assert "**3.00 / 30.0**" in text and "<= 40" in text and "1.00 / 1.50" in text
    assert "| driver overruns, missed replies | 0, 0 |" in text


def test_the_summary_gives_each_runs_total_and_the_median_against_the_target(bench: ModuleType) -> None:
    def case(total_s: float, lost: float = 0.0) -> object:
        return bench.CaseResult("rest", 10.0, {"sim": total_s}, (1.0,) * 3, (1.0,) * 3, {"lost": lost})

    text = "\n".join(bench.summary([[case(3.0)], [case(4.5, lost=7.0)], [case(3.2)]]))
    assert "| rest | 30.0 | 45.0 | 32.0 | **32.0** | <= 40 | (7 missed replies in all)" in text
