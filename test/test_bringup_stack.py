"""redarm-bringup of the whole simulated stack: SIGINT stops every child (the hil part of test_bringup)."""

from __future__ import annotations

import signal
from typing import Any

import pytest

pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")

from test_bringup import UP, _alive, _child_pids, _wait_exit, _wait_gone  # noqa: E402

from redarm_ros.procs import python_module_cmd  # noqa: E402


@pytest.mark.hil
def test_full_stack_ctrl_c_stops_everything(procs: Any) -> None:
    """The simulated stack (bus server, simulator, driver, ik_service, controller, description): SIGINT
    stops all."""
    pytest.importorskip("redarm_ros.nodes.can_driver", reason="can_driver node not written yet")
    pytest.importorskip("redarm_ros.sim.hardware", reason="simulator not written yet")
    bringup = procs.start("bringup", python_module_cmd("redarm_ros.bringup", "--log-level", "warn"))
    pids = _child_pids(bringup.wait_for_line(UP, timeout=90.0))
    assert set(pids) == {"canbus", "sim", "can_driver", "ik_service", "controller", "description"}
    assert all(_alive(p) for p in pids.values())
    bringup.expect_exit()
    bringup.send_signal(signal.SIGINT)
    assert _wait_exit(bringup.popen, 60.0) == 0, bringup.tail(30)
    assert _wait_gone(list(pids.values()), 5.0) == [], "a child outlived the bring-up"
    out = "\n".join(bringup.output())
    for name in pids:
        assert f"{name} stopped (exit code" in out, name
