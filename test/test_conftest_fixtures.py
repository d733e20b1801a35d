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
    c = procs.start("planned", [sys.executable, "-c", "print('up', flush=True)"], ready="up", exits=True)
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


HIL_FILE = '''
import os
import pytest

pytestmark = pytest.mark.hil

@pytest.mark.parametrize("i", range(4))
def test_hil(i, ros_env):
    with open(os.environ["OUT"], "a") as f:
        f.write(f"hil {i} {os.environ['PYTEST_XDIST_WORKER']} {ros_env.domain_id}\\n")
'''

PLAIN_FILE = '''
import os

def test_plain(ros_env):
    with open(os.environ["OUT"], "a") as f:
        f.write(f"plain 0 {os.environ['PYTEST_XDIST_WORKER']} {ros_env.domain_id}\\n")
'''

SLOW_FILE = PLAIN_FILE.replace("def test_plain", "@pytest.mark.slow\ndef test_slow").replace(
    "import os", "import os\nimport pytest").replace("plain 0", "slow 0")


def run_under_xdist(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch, workers: int, *args: str,
                    passed: int) -> list[list[str]]:
    """Run the files written in ``pytester`` on ``workers`` workers with the suite's conftest; check that
    ``passed`` tests passed and return the rows they wrote (kind, index, worker, domain)."""
    pytester.makeconftest((REPO / "test" / "conftest.py").read_text())
    pytester.makeini("[pytest]\nmarkers =\n    hil: processes over a loopback bus\n    slow: long\n")
    out = pytester.path / "ran.txt"
    monkeypatch.setenv("OUT", str(out))
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join([str(REPO), str(REPO / "test"), os.environ.get("PYTHONPATH", "")])
    )
    monkeypatch.delenv("REDARM_TEST_DOMAIN_ID", raising=False)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-q", "-n", str(workers), "--dist",
                                           "loadfile", *args, timeout=120)
    assert result.parseoutcomes().get("passed") == passed, result.stdout.str()
    return [line.split() for line in out.read_text().splitlines()]


def test_xdist_runs_the_hil_files_in_order_on_one_worker_each_worker_on_its_own_domain(
        pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("xdist")
    # Two hil files (one unit), more plain files than workers (spread), and a file with a slow test that
    # xdist alone would hand out last (as many tests as the others, last by name).
    pytester.makepyfile(test_a_hil=HIL_FILE, test_b_hil=HIL_FILE, test_z_slow=SLOW_FILE,
                        **{f"test_plain_{k}": PLAIN_FILE for k in range(4)})
    rows = run_under_xdist(pytester, monkeypatch, 2, passed=13)
    hil = [(int(i), w) for kind, i, w, _ in rows if kind == "hil"]
    assert len({w for _, w in hil}) == 1, hil  # one worker ...
    assert [i for i, _ in hil] == [0, 1, 2, 3, 0, 1, 2, 3], hil  # ... in order, file after file
    other = [kind for kind, _, w, _ in rows if w != hil[0][1]]
    assert other[0] == "slow", rows  # the other worker starts with the slow file
    domains = {w: int(d) for _, _, w, d in rows}
    assert len(domains) == 2 and len(set(domains.values())) == 2, domains  # a domain per worker
    assert all(1 <= d <= 200 for d in domains.values()), domains


def test_three_workers_run_the_hil_files_in_two_serial_units(
        pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    """With three workers the demo's unit and the other hil files go to two workers, each in order."""
    pytest.importorskip("xdist")
    (pytester.path / "test").mkdir()
    for name in ("test_e2e_demo", "test_examples", "test_a_hil", "test_b_hil"):  # 2 + 2 hil files
        (pytester.path / "test" / f"{name}.py").write_text(HIL_FILE.replace("hil {i}", f"{name} {{i}}"))
    for k in range(4):
        (pytester.path / "test" / f"test_plain_{k}.py").write_text(PLAIN_FILE)
    rows = run_under_xdist(pytester, monkeypatch, 3, "test", passed=20)
    worker_of = {kind: {w for k, _, w, _ in rows if k == kind} for kind, *_ in rows if kind != "plain"}
    assert all(len(ws) == 1 for ws in worker_of.values()), worker_of  # a hil file runs on one worker
    demo_unit = worker_of["test_e2e_demo"] | worker_of["test_examples"]
    rest_unit = worker_of["test_a_hil"] | worker_of["test_b_hil"]
    assert len(demo_unit) == 1 and len(rest_unit) == 1 and demo_unit != rest_unit, worker_of
    for unit in (demo_unit, rest_unit):  # each unit in order, file after file
        ran = [(k, int(i)) for k, i, w, _ in rows if w in unit and k != "plain"]
        assert [i for _, i in ran] == [0, 1, 2, 3, 0, 1, 2, 3], ran

def test_the_longest_files_are_queued_after_the_hil_units_and_before_the_rest() -> None:
    from conftest import LONGEST_FILES, SERIAL_UNIT, _unit_rank, marks_used

    for path in LONGEST_FILES:  # real files, none of them hil (those go in the serial units)
        assert (REPO / path).is_file() and "hil" not in marks_used(str(REPO / path)), path
    order = [SERIAL_UNIT, *LONGEST_FILES, "test/test_kin_swivel.py", "test/test_can_protocol.py"]
    assert "slow" in marks_used(str(REPO / order[-2])) and "slow" not in marks_used(str(REPO / order[-1]))
    ranks = [_unit_rank(REPO, scope) for scope in order]
    assert ranks == sorted(ranks) and len(set(ranks)) == len(ranks), list(zip(order, ranks, strict=True))


def test_worker_domains_are_distinct_and_in_range(monkeypatch: pytest.MonkeyPatch) -> None:
    from redarm_ros.testing.sandbox import DOMAIN_ENV, worker_domain_id

    monkeypatch.delenv(DOMAIN_ENV, raising=False)
    for run in ("a", "b", "c3f0", "x" * 40):
        for workers in (1, 2, 4, 16):
            ids = [worker_domain_id(w, workers, run) for w in range(workers)]
            assert len(set(ids)) == workers and all(1 <= d <= 200 for d in ids), (run, ids)
    monkeypatch.setenv(DOMAIN_ENV, "42")
    assert [worker_domain_id(w, 3, "a") for w in range(3)] == [42, 43, 44]


def test_a_mark_named_in_a_string_does_not_make_a_hil_file(tmp_path: Path) -> None:
    """The scheduler reads the marks a file's code uses: this file writes hil files, but is not one."""
    from conftest import marks_used

    f = tmp_path / "test_writes_files.py"
    f.write_text("import pytest\n\nHIL = 'pytestmark = pytest.mark.hil'\n\n@pytest.mark.slow\ndef test_x():\n"
                 "    pass\n", encoding="utf-8")
    assert marks_used(str(f)) == {"slow"}
    assert "hil" not in marks_used(__file__)
    assert "hil" in marks_used(str(REPO / "test" / "test_e2e_stack.py"))
