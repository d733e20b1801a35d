"""realtime.raise_nice: every thread of the process, and the threads started later, run at the level
asked for; 0 asks for nothing; a level that is not permitted falls back and says so. Each case runs in
a subprocess so the test runner keeps its own nice level."""

from __future__ import annotations

import os
import shutil
import time

import pytest
from support.thread_probe import probe_threads


def _probe(level: int, prefix: tuple[str, ...] = (), start_nice: int | None = None) -> dict:
    return probe_threads("raise_nice", level, prefix, start_nice)


def _may_raise_priority() -> bool:
    try:
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0))  # a no-op, permitted
        return os.geteuid() == 0
    except OSError:
        return False


@pytest.mark.skipif(not _may_raise_priority(), reason="needs CAP_SYS_NICE (root) to raise a nice level")
def test_every_thread_and_later_ones_run_at_the_level() -> None:
    r = _probe(-5, start_nice=0)
    assert r["policy"] == "nice" and r["value"] == -5, r
    assert len(r["nice"]) >= 4 and set(r["nice"].values()) == {-5}, r["nice"]  # main, 2 before, 1 after
    assert all(r["nice"][str(t)] == -5 for t in [*r["before"], r["after"]])
    assert "nice -5" in r["message"]


def test_zero_asks_for_nothing() -> None:
    r = _probe(0)
    assert r["policy"] == "normal" and "not requested" in r["message"]
    assert set(r["nice"].values()) == {os.getpriority(os.PRIO_PROCESS, 0)}


@pytest.mark.skipif(shutil.which("setpriv") is None or os.geteuid() != 0,
                    reason="needs root and util-linux setpriv to take CAP_SYS_NICE away from the probe")
def test_not_permitted_falls_back_with_one_line() -> None:
    """Started at nice 5 without CAP_SYS_NICE (RLIMIT_NICE 0): an unprivileged user's view."""
    r = _probe(-10, ("setpriv", "--bounding-set", "-sys_nice", "--inh-caps", "-sys_nice"), start_nice=5)
    assert r["policy"] == "normal", r
    assert "not permitted" in r["message"] and "CAP_SYS_NICE" in r["message"]
    assert set(r["nice"].values()) == {5}


def test_thread_schedstat_counts_the_threads_own_cpu_time() -> None:
    from redarm_ros.can.realtime import ThreadSchedstat

    stat = ThreadSchedstat()
    ran0, queued0 = stat.read()
    end = time.thread_time() + 0.05
    while time.thread_time() < end:  # 50 ms of this thread's CPU
        pass
    ran1, queued1 = stat.read()
    stat.close()
    assert ran1 - ran0 >= 40.0 and queued1 >= queued0
    assert ThreadSchedstat(None).read() == (0.0, 0.0)


def test_per_second_limit_allows_so_many_events_in_each_wall_second() -> None:
    from redarm_ros.can.realtime import PerSecondLimit

    limit = PerSecondLimit(3)
    assert [limit.allow(100.0 + 0.1 * k) for k in range(5)] == [True, True, True, False, False]
    assert limit.allow(101.2) and limit.allow(101.3) and limit.allow(101.4) and not limit.allow(101.5)
