"""How a node starts, and refuses to start, from the command line (nodes/_common.run_node):

* a can_driver whose bus configuration can never work (no interface configured, an unknown interface
  type, no SocketCAN in the kernel) exits 1 with one line that says what to do, instead of retrying;
* a parameter file with a YAML syntax error is named with its line, without rclpy's traceback;
* a parameter file none of whose node keys applies to the node (a misspelt ``/can_drvier:``, or
  ``/description:`` given to ``/left/description``) is warned about;
* the node keys of the shipped config files apply under a namespace (``/**``), as rclpy matches them.
"""

from __future__ import annotations

import errno
import os
import socket
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("rclpy")

from redarm_ros.nodes._common import node_key_matches, params_file_paths, read_params_file  # noqa: E402
from redarm_ros.procs import ChildDiedError, python_module_cmd  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


# -- node keys, as rclpy Jazzy applies them (measured: a node /can_driver and /left/can_driver) -----------
@pytest.mark.parametrize(("key", "root", "left"), [
    ("/**", True, True),
    ("/**/can_driver", True, True),
    ("can_driver", True, False),
    ("/can_driver", True, False),
    ("/left/can_driver", False, True),
    ("left/can_driver", False, True),
    ("/*/can_driver", False, True),
    ("/can_drvier", False, False),
])
def test_node_keys_match_as_rclpy_applies_them(key: str, root: bool, left: bool) -> None:
    assert node_key_matches(key, "/can_driver") is root
    assert node_key_matches(key, "/left/can_driver") is left


@pytest.mark.parametrize("node", ["can_driver", "controller", "ik_service", "description"])
def test_shipped_config_applies_to_the_node_in_any_namespace(node: str) -> None:
    keys = list(read_params_file(str(REPO / "config" / f"{node}.yaml")))
    for fqn in (f"/{node}", f"/left/{node}", f"/robots/left/{node}"):
        assert any(node_key_matches(k, fqn) for k in keys), (node, fqn, keys)


def test_params_file_paths_only_inside_ros_args() -> None:
    argv = ["prog", "--params-file", "not_ros.yaml", "--ros-args", "-p", "a:=1", "--params-file", "a.yaml",
            "--", "--params-file", "x.yaml", "--ros-args", "--params-file", "b.yaml"]
    assert params_file_paths(argv) == ["a.yaml", "b.yaml"]


# -- processes ----------------------------------------------------------------------------------------
def _run(procs: Any, name: str, module: str, *ros_args: str, env: dict[str, str] | None = None,
         timeout: float = 60.0) -> tuple[int, list[str]]:
    """Run ``python -m module --ros-args ...`` to its end; (exit code, output lines)."""
    proc = procs.start(name, python_module_cmd(module, "--ros-args", *ros_args), extra_env=env, exits=True)
    with pytest.raises(ChildDiedError):  # raised once the child's output has ended: every line is read
        proc.wait_for_line(r"(?!)", timeout=timeout)
    return proc.returncode, proc.output()


def _kernel_has_socketcan() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        return exc.errno != errno.EAFNOSUPPORT
    return True


def _driver_case(case: str, tmp_path: Path) -> tuple[list[str], str]:
    if case == "unknown_interface":
        return ["-p", "can.interface:=no_such_interface", "-p", "can.channel:=x"], "invalid CAN configuration"
    if case == "no_configuration":
        return [], "no CAN interface configured"
    if case == "no_socketcan_in_kernel":
        if _kernel_has_socketcan():
            pytest.skip("this kernel has SocketCAN: errno 97 cannot happen")
        return ["-p", "can.interface:=socketcan", "-p", "can.channel:=can0"], "errno 97"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["unknown_interface", "no_configuration", "no_socketcan_in_kernel"])
def test_can_driver_with_a_bus_that_can_never_work_exits_1_with_one_line(procs: Any, tmp_path: Path,
                                                                          case: str) -> None:
    if any(os.environ.get(k) for k in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_CONFIG")):
        pytest.skip("CAN_* set in the environment")
    args, expected = _driver_case(case, tmp_path)
    # HOME without python-can config files: nothing configures the bus but these arguments.
    code, out = _run(procs, f"driver-{case}", "redarm_ros.nodes.can_driver", "-p", "duplicate_check_s:=0.0",
                     *args, env={"HOME": str(tmp_path)})
    assert code == 1, out
    said = [line for line in out if "could not start" in line]
    assert len(said) == 1 and expected in said[0], out
    assert not any("Traceback" in line or "retrying" in line for line in out), out


def test_yaml_syntax_error_names_the_file_and_line(procs: Any, tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    arm: [pa10\n    prefix: x\n", encoding="utf-8")
    code, out = _run(procs, "description-bad-yaml", "redarm_ros.nodes.description", "--params-file", str(bad))
    assert code == 1, out
    said = [line for line in out if "could not start" in line]
    assert len(said) == 1 and f"{bad}, line " in said[0], out
    assert not any("Traceback" in line for line in out), out


def test_a_params_file_with_no_section_for_the_node_is_warned(procs: Any, tmp_path: Path) -> None:
    typo = tmp_path / "typo.yaml"
    typo.write_text("/descripton:\n  ros__parameters:\n    prefix: left_\n", encoding="utf-8")
    cmd = python_module_cmd("redarm_ros.nodes.description", "--ros-args", "-r", "__ns:=/left",
                            "-p", "duplicate_check_s:=0.0", "--params-file", str(typo))
    proc = procs.start("description-typo", cmd, ready=r"description ready:", ready_timeout=60.0)
    line = proc.wait_for_line(r"has no section for this node", timeout=10.0, from_start=True).string
    assert str(typo) in line and "/left/description" in line and "/descripton" in line and "/**:" in line
    assert proc.stop() == 0
