"""The shared fixtures fail the tests they should: a leaked child, a child that died, DDS rules set."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

REPO = Path(__file__).resolve().parents[1]

INNER = '''
import os, subprocess, sys, time

def test_leaks_a_child():
    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])

def test_child_dies(procs):
    c = procs.start("crasher", [sys.executable, "-c", "print('up', flush=True); raise SystemExit(3)"],
                    ready="up")
    c.popen.wait(10)

def test_announced_exit_is_fine(procs):
    c = procs.start("planned", [sys.executable, "-c", "print('up', flush=True)"], ready="up")
    c.expect_exit()
    c.popen.wait(10)

def test_env(ros_env):
    assert os.environ["FASTDDS_BUILTIN_TRANSPORTS"] == "SHM"
    assert 1 <= int(os.environ["ROS_DOMAIN_ID"]) <= 200
    assert os.environ["ROS_DOMAIN_ID"] == str(ros_env.domain_id)
'''


def test_fixtures_catch_leaks_and_deaths(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    pytester.makeconftest((REPO / "test" / "conftest.py").read_text())
    pytester.makepyfile(test_inner=INNER)
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join([str(REPO), str(REPO / "test"), os.environ.get("PYTHONPATH", "")])
    )
    monkeypatch.delenv("REDARM_TEST_DOMAIN_ID", raising=False)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-q", timeout=120)
    outcomes = result.parseoutcomes()
    # The leaking test and the dying child each error at teardown; the other two pass.
    assert outcomes.get("passed") == 4 and outcomes.get("errors") == 2, result.stdout.str()
    out = result.stdout.str()
    assert "test left child processes running" in out
    assert "crasher" in out and "died unexpectedly with code 3" in out
