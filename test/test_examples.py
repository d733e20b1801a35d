"""The files in examples/ (the README's working examples) run against the simulated stack, each as a
subprocess the way a user runs it (``python examples/x.py`` in the sourced venv, no ``ros2`` CLI): exit
code and key output checked. ``real_arm.sh`` runs first, against a simulator on the loopback bus with
its own driver and controller (before this module's stack exists: one can_driver per ROS domain);
the others share one stack started as ``redarm-bringup`` does."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

import pytest
from support.requires import require_ros

require_ros(stack=True)

from support import stack_client as sc  # noqa: E402

from redarm_ros.bringup import Stack  # noqa: E402
from redarm_ros.nodes import can_driver, controller  # noqa: E402
from redarm_ros.procs import ChildDiedError, python_module_cmd  # noqa: E402
from redarm_ros.sim.hardware import READY_LINE  # noqa: E402

pytestmark = [pytest.mark.hil, pytest.mark.slow]

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _env() -> dict[str, str]:
    """The sourced environment: this interpreter's bin directory first on PATH (redarm-record, python)."""
    bindir = str(Path(sys.executable).parent)
    return {"PATH": f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHON": sys.executable}


def run_example(procs: Any, name: str, *args: str, env: dict[str, str] | None = None,
                timeout: float = 180.0) -> tuple[int, str]:
    """Run ``examples/<name>`` to its end as a child of ``procs``; (exit code, its output)."""
    path = EXAMPLES / name
    cmd = ["bash", str(path), *args] if name.endswith(".sh") else [sys.executable, str(path), *args]
    proc = procs.start(name, cmd, extra_env={**_env(), **(env or {})}, exits=True)
    with pytest.raises(ChildDiedError):  # raised once its output has ended: every line is read
        proc.wait_for_line(r"(?!)", timeout=timeout)
    return proc.returncode, "\n".join(proc.output())


def test_every_example_is_there_and_has_help(procs: Any) -> None:
    for name in ("ik_client.py", "stream_goals.py", "send_twist.py", "reach_action.py", "call_trigger.py"):
        code, out = run_example(procs, name, "--help", timeout=60.0)
        assert code == 0 and "usage:" in out, out
    for name in ("record_and_replay.sh", "real_arm.sh"):
        assert (EXAMPLES / name).is_file()


# -- first, before the module's stack: the real-arm steps on a simulated arm ---------------------------
def test_real_arm_script_names_only_real_parameters_and_services() -> None:
    text = (EXAMPLES / "real_arm.sh").read_text(encoding="utf-8")
    names = {s.name for s in (*can_driver.PARAMS, *controller.PARAMS)}
    used = set(re.findall(r"-p ([\w.]+):=", text))
    assert used and used <= names, sorted(used - names)
    assert set(re.findall(r"call_trigger\.py can_driver/(\w+)", text)) == {"init", "halt"}
    assert "ip link set \"$CAN_CHANNEL\" up type can bitrate" in text
    for config in re.findall(r"\$CONFIG/(\w+\.yaml)", text):
        assert (EXAMPLES.parent / "config" / config).is_file(), config


def test_real_arm_script_drives_a_simulated_arm(procs: Any, canbus_server: Any) -> None:
    sim = python_module_cmd("redarm_ros.sim.hardware", "--arm", "pa10", *canbus_server.cli_args())
    procs.start("sim", sim, ready=READY_LINE, ready_timeout=60.0)
    code, out = run_example(procs, "real_arm.sh", timeout=400.0,
                            env={"CAN_INTERFACE": "remote", "CAN_CHANNEL": canbus_server.channel})
    assert code == 0, out
    assert "can_driver/init: success=True" in out
    assert "result: SUCCESS" in out
    assert "can_driver/halt: success=True" in out


# -- the rest against one stack -------------------------------------------------------------------------
stack = sc.stack_fixture(arm="pa10", description=True, ready_timeout_s=90.0)  # as redarm-bringup


@pytest.fixture(autouse=True)
def driver_running(request: pytest.FixtureRequest, procs: Any) -> None:
    """Each test on the shared stack starts with its driver running. A halt (the modules' watchdog on
    a starved machine, a fault) outlasts the test it happened in, and every later test's arm would
    stand still; so a halt left behind is recovered with ``~/recover``, as a user would, and said."""
    if "stack" not in request.fixturenames:
        return
    arm = request.getfixturevalue("stack")
    halted = [m.id for m in arm.status().modules.values() if m.halted]
    if halted:
        code, out = run_example(procs, "call_trigger.py", "can_driver/recover")
        assert code == 0, f"the driver was halted (modules {halted}) and ~/recover failed: {out}"
        print(f"modules {halted} were halted before this test; {out.strip()}")


def test_ik_client(stack: Stack, procs: Any) -> None:
    code, out = run_example(procs, "ik_client.py")
    assert code == 0, out
    assert "status: SUCCESS" in out
    assert len(re.findall(r"joint_\d = [+-]\d\.\d{4} rad", out)) == 7, out
    code, out = run_example(procs, "ik_client.py", "--xyz", "3", "0", "0.5")  # far out of reach
    assert code == 1 and "status: OUT_OF_REACH" in out, out


def test_reach_action_with_feedback_and_cancel(stack: Stack, procs: Any) -> None:
    code, out = run_example(procs, "reach_action.py")
    assert code == 0, out
    assert "goal accepted" in out and "feedback: " in out and "result: SUCCESS" in out, out
    code, out = run_example(procs, "reach_action.py", "--xyz", "0.3", "0.5", "0.6", "--cancel-after", "0.5")
    assert code == 0, out
    assert "canceling after 0.5 s" in out and "result: CANCELED" in out, out


def test_stream_goals(stack: Stack, procs: Any) -> None:
    code, out = run_example(procs, "stream_goals.py")
    assert code == 0, out
    assert "reached the start of the circle" in out
    m = re.search(r"streamed (\d+) goals", out)
    assert m and int(m.group(1)) >= 150, out  # 50 Hz for 4 s, give or take a starved machine


def test_send_twist(stack: Stack, procs: Any) -> None:
    # The example starts from a bent arm, as its docstring says: stretched straight up (homed, or an
    # earlier test left it there) the hand cannot move sideways. A goal bends it, as a user would.
    if max(abs(q) for q in stack.status().q) < 0.1:
        code, out = run_example(procs, "reach_action.py")
        assert code == 0 and "result: SUCCESS" in out, out
    code, out = run_example(procs, "send_twist.py")
    assert code == 0, out
    m = re.search(r"in ([.\d]+) s; the hand moved by \(([-+.\d]+), ([-+.\d]+), ([-+.\d]+)\) m", out)
    assert m, out
    elapsed, dx, dy, dz = (float(v) for v in m.groups())
    # 5 cm/s along +y while the twists come (each held 0.1 s more), less the ramps at either end
    assert 0.01 < dy <= 0.05 * (elapsed + 0.1) + 0.005, out
    assert abs(dx) < 0.01 and abs(dz) < 0.01, out


def test_record_and_replay(stack: Stack, procs: Any, tmp_path: Path) -> None:
    out_file = tmp_path / "run.mcap"
    code, out = run_example(procs, "record_and_replay.sh", str(out_file))
    assert code == 0, out
    assert out_file.is_file()
    for topic in ("/joint_states", "/controller/state", "/tf"):
        assert re.search(rf"^  {re.escape(topic)} +\S+ +\d+ messages$", out, re.M), (topic, out)
    m = re.search(r"replayed (\d+) joint states", out)
    assert m and int(m.group(1)) > 100, out
