"""Start the simulated arm, run my node, silence module 3, assert my node reacts."""

import pytest
from halt_monitor import HaltMonitor


@pytest.mark.redarm_arm(driver=True)
def test_monitor_names_the_silent_module(redarm_arm, redarm_ros):
    monitor = redarm_ros.add_node(HaltMonitor(context=redarm_ros.context))
    redarm_ros.wait_until(lambda: monitor.state == "running", 15, what="driver running",
                          seen=lambda: monitor.state)
    redarm_arm.silence(3)
    redarm_ros.wait_until(lambda: monitor.halted_modules == [3], 5, what="monitor names module 3",
                          seen=lambda: (monitor.state, monitor.halted_modules))
