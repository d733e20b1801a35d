"""A user's node: watches the driver's /diagnostics and keeps which modules halted the arm.

The example of "your node" in the testing examples (test_halt_monitor.py tests it against the
simulated arm); nothing in it knows about the simulator.
"""

from __future__ import annotations

import ast
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node

LOOP_STATUS = "can_driver: loop"


class HaltMonitor(Node):
    """``state`` is the driver loop's state (``running``, ``halted``, ...; None before the first
    message); ``halted_modules`` the modules its last fault names (empty while none)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("halt_monitor", **kwargs)
        self.state: str | None = None
        self.halted_modules: list[int] = []
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == LOOP_STATUS:
                values = {kv.key: kv.value for kv in status.values}
                self.state = values.get("state")
                self.halted_modules = list(ast.literal_eval(values.get("fault_modules", "[]")))
