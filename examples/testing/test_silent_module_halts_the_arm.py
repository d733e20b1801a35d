"""A module falls silent mid-motion: the driver halts every other module before the silent module's
own watchdog runs out (within the modules' watchdog time, at real-time priority), and says which
module it was."""

import pytest
from builtin_interfaces.msg import Duration
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from redarm_ros.can.protocol import ActState
from redarm_ros.testing import WATCHDOG_S


# The driver's default (5 missed replies of 20 ms) lets a module be quiet for the whole watchdog time;
# 3 misses (60 ms) leave the driver the time to halt the others first.
@pytest.mark.redarm_arm(driver=True, driver_params={"max_missed_replies": 3})
def test_silent_module_halts_every_module(redarm_arm, redarm_ros):
    pub = redarm_ros.node.create_publisher(JointTrajectory, "/joint_command", 10)
    goal = JointTrajectoryPoint(positions=[1.0, 0, 0, 0, 0, 0, 0], time_from_start=Duration(sec=3))
    command = JointTrajectory(joint_names=redarm_arm.joint_names, points=[goal])
    # Sent until the arm moves: discovery may match the driver's subscription a moment late.
    redarm_arm.wait_for(lambda st: pub.publish(command) or st.q[0] > 0.1, 10, what="joint 1 on its way")

    cycle = redarm_arm.driver.wait_for_line(r"can_driver cycle process: (real-time)?", from_start=True)
    realtime = cycle[1] is not None  # its scheduling, said once at start-up
    silent = redarm_arm.silence(3)  # the simulator's state right after module 3 fell silent
    others = [1, 2, 4, 5, 6, 7]
    halted = redarm_arm.wait_modules(ActState.HALTED, others, timeout=2.0)
    redarm_arm.driver.wait_for_line(r"HALTED: module 3 stopped answering: module 3 missed 3", timeout=5)
    own = redarm_arm.wait_modules(ActState.HALTED | ActState.COMM_ERROR, [3], timeout=2.0)  # its watchdog
    # When each module halted, as the simulator recorded it (not when this test got to look): module
    # 3's own watchdog ran out at most WATCHDOG_S after it last heard the driver ...
    watchdog_ran_out = own.modules[3].halted_at_s
    assert watchdog_ran_out <= silent.uptime_s + WATCHDOG_S
    # ... and the driver's HALT reached the others before that, where its cycle runs at real-time
    # priority (as it asks): then no other work on the machine delays it. Without (no CAP_SYS_NICE or
    # rtprio limit), a busy machine can delay the cycle past the watchdog; the others halt all the same.
    if realtime:
        assert max(halted.modules[i].halted_at_s for i in others) < watchdog_ran_out
    stopped = redarm_arm.wait_still(window_s=0.3)
    assert stopped.q[0] < 0.9  # braked well short of the goal
