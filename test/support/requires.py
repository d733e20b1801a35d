"""Module-level skips for tests that need ROS 2: call at the top of a test module, before its ROS
imports."""

from __future__ import annotations

import pytest


def require_ros(stack: bool = False) -> None:
    """Skip the calling module without rclpy or the built redarm_interfaces; with ``stack``, also
    without the can_driver node and the simulator (the whole stack started by bringup)."""
    pytest.importorskip("rclpy")
    pytest.importorskip("redarm_interfaces", reason="redarm_interfaces not built (run scripts/setup_env.sh)")
    if stack:
        pytest.importorskip("redarm_ros.nodes.can_driver", reason="can_driver node not written yet")
        pytest.importorskip("redarm_ros.sim.hardware", reason="simulator not written yet")
