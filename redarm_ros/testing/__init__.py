"""Test your software against the simulated arm (docs/testing.md).

* :class:`SimulatedArm` (a context manager): the loopback CAN bus (or a python-can bus of yours),
  the simulator, optionally ``can_driver``, ``controller`` and ``ik_service``, on a sandboxed ROS
  domain; stopped on exit, also when a test fails.
* :class:`SimStatus` / :class:`ModuleStatus`: the simulated joints and the modules' state, read
  from the simulator when asked (:class:`SimControl`, its control channel).
* Faults at run time: ``silence``, ``drop_replies``, ``delay_replies``, ``power_cycle``,
  ``module_error``, ``beyond_soft``, ``restart_sim``, ``restart_bus_server``.
* :func:`wait_until` / :func:`wait_for`: return as soon as a condition holds; on timeout a
  :class:`WaitTimeoutError` says what was last seen.
* The pytest plugin (:mod:`redarm_ros.testing.pytest_plugin`, loaded by pytest's entry point) has
  fixtures on top of these.

Nothing here imports rclpy or pybullet (:mod:`redarm_ros.testing.ros` imports rclpy).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# Imported when first used: the pytest plugin lives in this package, and loading it must cost
# nothing (python-can, numpy) in a session that does not use it.
_EXPORTS = {
    "WATCHDOG_S": "arm", "SimArmConfig": "arm", "SimulatedArm": "arm",
    "CanBusServer": "canbus", "start_canbus_server": "canbus",
    "ModuleStatus": "sim_control", "SimControl": "sim_control", "SimControlError": "sim_control",
    "SimStatus": "sim_control",
    "WaitTimeoutError": "waits", "wait_for": "waits", "wait_until": "waits",
}

__all__ = [
    "CanBusServer", "ModuleStatus", "SimArmConfig", "SimControl", "SimControlError", "SimStatus",
    "SimulatedArm", "WATCHDOG_S", "WaitTimeoutError", "start_canbus_server", "wait_for", "wait_until",
]

if TYPE_CHECKING:
    from redarm_ros.testing.arm import WATCHDOG_S, SimArmConfig, SimulatedArm
    from redarm_ros.testing.canbus import CanBusServer, start_canbus_server
    from redarm_ros.testing.sim_control import ModuleStatus, SimControl, SimControlError, SimStatus
    from redarm_ros.testing.waits import WaitTimeoutError, wait_for, wait_until


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'redarm_ros.testing' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"redarm_ros.testing.{module}"), name)
    globals()[name] = value
    return value
