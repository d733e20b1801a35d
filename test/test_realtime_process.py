"""realtime.raise_process_priority: every thread of the process (those running already, as the
middleware's are in a ROS node, and those started later) runs at SCHED_FIFO; 0 asks for nothing; when
refused, no thread is left half-changed and the result says why. Each case runs in a subprocess so
the test runner keeps its own scheduling."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
from support.thread_probe import probe_threads


def _probe(priority: int, prefix: tuple[str, ...] = ()) -> dict:
    return probe_threads("raise_process_priority", priority, prefix)


def _fifo_permitted() -> bool:
    try:
        os.sched_setscheduler(0, os.sched_getscheduler(0), os.sched_getparam(0))  # a no-op
    except (OSError, AttributeError):
        return False
    return os.geteuid() == 0


@pytest.mark.skipif(not _fifo_permitted(), reason="needs CAP_SYS_NICE (root) for SCHED_FIFO")
def test_every_thread_and_later_ones_run_at_fifo() -> None:
    r = _probe(7)
    assert r["policy"] == "SCHED_FIFO" and r["value"] == 7, r
    assert len(r["sched"]) >= 4, r["sched"]  # main, two started before, one after
    assert all(v == [os.SCHED_FIFO, 7] for v in r["sched"].values()), r["sched"]
    assert r["sched"][str(r["after"])] == [os.SCHED_FIFO, 7]
    assert all(r["sched"][str(t)] == [os.SCHED_FIFO, 7] for t in r["before"])
    assert "SCHED_FIFO priority 7" in r["message"]
    assert r["rttime"] == [1_000_000, 3_000_000] and not r["sigxcpu_default"]  # the runaway guard


def test_zero_asks_for_nothing() -> None:
    r = _probe(0)
    assert r["policy"] == "normal" and "not requested" in r["message"]
    assert {v[0] for v in r["sched"].values()} == {os.sched_getscheduler(0)}


@pytest.mark.skipif(shutil.which("setpriv") is None or shutil.which("prlimit") is None or os.geteuid() != 0,
                    reason="needs root, setpriv and prlimit to take real-time rights away from the probe")
def test_refused_leaves_every_thread_normal_and_says_why() -> None:
    """Without CAP_SYS_NICE and with RLIMIT_RTPRIO 0: an unprivileged user's view."""
    r = _probe(7, ("prlimit", "--rtprio=0", "setpriv", "--bounding-set", "-sys_nice", "--inh-caps",
                   "-sys_nice"))
    assert r["policy"] == "normal", r
    assert "SCHED_FIFO refused" in r["message"]
    assert {v[0] for v in r["sched"].values()} == {os.SCHED_OTHER}, r["sched"]
    assert r["sigxcpu_default"]  # nothing real-time to guard: SIGXCPU handled as before


_RUNAWAY = r"""
import os, sys, time
from redarm_ros.can import realtime

prio = realtime.raise_process_priority(3, who="runaway probe", budget_s=(0.2, 1.0))
assert prio.realtime, prio.message
if sys.argv[1] == "python":
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.5 and os.sched_getscheduler(0) == os.SCHED_FIFO:
        pass  # spins at real-time priority until demoted (or 1.5 s: the test then fails)
    print("policy", os.sched_getscheduler(0), "after", round(time.monotonic() - t0, 2), flush=True)
else:
    sum(range(10**11))  # native code: the demoting handler never runs; the hard limit kills
    print("survived", flush=True)
"""


@pytest.mark.skipif(not _fifo_permitted(), reason="needs CAP_SYS_NICE (root) for SCHED_FIFO")
def test_a_runaway_real_time_loop_is_demoted() -> None:
    out = subprocess.run([sys.executable, "-c", _RUNAWAY, "python"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    words = out.stdout.split()
    assert words[:2] == ["policy", str(os.SCHED_OTHER)], out.stdout
    assert float(words[3]) < 1.4  # demoted after about 0.2 s of CPU, not at the probe's own limit
    assert "without blocking: back to normal scheduling" in out.stderr


@pytest.mark.skipif(not _fifo_permitted(), reason="needs CAP_SYS_NICE (root) for SCHED_FIFO")
def test_a_real_time_thread_stuck_in_native_code_is_killed_at_the_hard_limit() -> None:
    out = subprocess.run([sys.executable, "-c", _RUNAWAY, "native"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == -9, (out.returncode, out.stdout, out.stderr)
    assert "survived" not in out.stdout
