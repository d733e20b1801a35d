"""redarm-bringup: Ctrl-C stops every child; a child that dies is reported and the rest are stopped.
The whole simulated stack's bring-up is in test_bringup_stack.py (a hil file)."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from typing import Any

import pytest

pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from redarm_ros import bringup  # noqa: E402
from redarm_ros.bringup import Stack, StackConfig, build_parser, config_from_args  # noqa: E402
from redarm_ros.procs import python_module_cmd  # noqa: E402

UP = r"stack up: (.*); Ctrl-C to stop"


def _child_pids(line_match: re.Match[str]) -> dict[str, int]:
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"(\w+) \(pid (\d+)\)", line_match.group(1))}


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            state = f.read().rsplit(")", 1)[-1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def _wait_exit(proc: Any, timeout: float) -> int | None:
    deadline = time.monotonic() + timeout
    while proc.returncode is None and time.monotonic() < deadline:
        time.sleep(0.05)
    return proc.returncode


def _wait_gone(pids: list[int], timeout: float) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        left = [p for p in pids if _alive(p)]
        if not left:
            return []
        time.sleep(0.05)
    return [p for p in pids if _alive(p)]


def test_sim_still_needs_a_full_quiet_window(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """`Stack.sim_still` is True only after every joint stayed within the tolerance for the whole
    window, and a late motion inside the window makes it False again."""
    clock = [100.0]
    monkeypatch.setattr(bringup.time, "monotonic", lambda: clock[0])
    status = tmp_path / "status.json"
    stack = Stack(StackConfig(status_file=str(status)), domain_id=1)
    still = stack.sim_still(0.5, 1e-4)
    assert not still(), "no status yet is not still"

    def at(t: float, q: list[float]) -> bool:
        clock[0] = t
        status.write_text(json.dumps({"q": q}), encoding="utf-8")
        return still()

    assert not at(100.0, [0.0, 1.0])
    assert not at(100.3, [0.0, 1.0 + 5e-5]), "the window is not full yet"
    assert at(100.6, [0.0, 1.0 + 9e-5]), "0.6 s within 1e-4 rad"
    assert not at(100.7, [3e-4, 1.0]), "joint 0 moved 0.3 mrad inside the window"
    assert not at(101.0, [3e-4, 1.0]), "the motion is still inside the last 0.5 s"
    assert at(101.3, [3e-4, 1.0]), "0.6 s still again"


def test_parser_defaults_and_flags() -> None:
    cfg = config_from_args(build_parser().parse_args([]))
    assert cfg == StackConfig(), "defaults of the CLI and of StackConfig must agree"
    cfg = config_from_args(
        build_parser().parse_args(
            ["--arm", "powercube7", "--no-controller", "--scene", "table_cylinder", "--hardware", "none"]
        )
    )
    assert (cfg.arm, cfg.controller, cfg.ik_service, cfg.scene, cfg.hardware) == (
        "powercube7",
        False,
        True,
        "table_cylinder",
        "none",
    )


def _start_light_bringup(procs: Any, sigint_ignored: bool = False) -> tuple[Any, dict[str, int]]:
    """bringup without hardware and controller (ik_service and description only), up; its child pids.
    ``sigint_ignored``: started as a script's background job (SIGINT ignored, inherited by exec)."""
    cmd = python_module_cmd("redarm_ros.bringup", "--hardware", "none", "--no-controller",
                            "--log-level", "warn")
    if sigint_ignored:
        cmd = ["bash", "-c", 'trap "" INT; exec "$@"', "bash", *cmd]
    bringup = procs.start("bringup", cmd)
    return bringup, _child_pids(bringup.wait_for_line(UP, timeout=60.0))


@pytest.mark.parametrize("sigint_ignored", [False, True], ids=["foreground", "sigint-ignored-at-start"])
def test_ctrl_c_stops_all_children(procs: Any, sigint_ignored: bool) -> None:
    bringup, pids = _start_light_bringup(procs, sigint_ignored)
    assert set(pids) == {"ik_service", "description"}
    assert all(_alive(p) for p in pids.values())
    bringup.expect_exit()
    bringup.send_signal(signal.SIGINT)  # what a terminal Ctrl-C delivers to the foreground process
    assert _wait_exit(bringup.popen, 30.0) == 0, bringup.tail(20)
    assert _wait_gone(list(pids.values()), 5.0) == [], "a child outlived the bring-up"
    out = "\n".join(bringup.output())
    assert "ik_service stopped (exit code 0)" in out
    assert "all children stopped" in out


def test_sigterm_stops_all_children(procs: Any) -> None:
    bringup, pids = _start_light_bringup(procs)
    bringup.expect_exit()
    bringup.send_signal(signal.SIGTERM)
    assert _wait_exit(bringup.popen, 30.0) == 0, bringup.tail(20)
    assert _wait_gone(list(pids.values()), 5.0) == []


def test_dead_child_is_reported(procs: Any) -> None:
    bringup, pids = _start_light_bringup(procs)
    bringup.expect_exit()
    os.kill(pids["ik_service"], signal.SIGKILL)  # a crash
    bringup.wait_for_line(r"child ik_service died unexpectedly \(exit code -9\)", timeout=15.0)
    assert _wait_exit(bringup.popen, 30.0) == 1
    assert _wait_gone(list(pids.values()), 5.0) == []


def test_child_that_cannot_start_is_reported() -> None:
    """In-process Stack: a node that exits during start-up raises ChildDiedError; nothing is left running."""
    from redarm_ros.bringup import Stack
    from redarm_ros.procs import ChildDiedError

    lines: list[str] = []
    cfg = StackConfig(
        hardware="none",
        controller=False,
        log_level="warn",
        extra_args={"ik_service": ["-p", "default_arm:=no_such_arm"]},
    )
    stack = Stack(cfg, sink=lines.append)
    with pytest.raises(ChildDiedError) as err:
        stack.start()
    assert err.value.name == "ik_service"
    assert any("no_such_arm" in line for line in lines), lines
    started = stack.group.children  # (stack.children lists only the children that came up)
    assert started and started[-1].name == "ik_service"
    assert all(not c.is_running() for c in started)
    stack.close()

