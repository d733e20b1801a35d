#!/usr/bin/env bash
# A real PowerCube arm on a SocketCAN adapter, step by step (run the steps by hand the first time).
#
#   examples/real_arm.sh                              # socketcan can0 at 500 kbit/s, arm pa10
#   CAN_CHANNEL=can1 ARM=powercube7 examples/real_arm.sh
#
# Environment: CAN_INTERFACE (socketcan), CAN_CHANNEL (can0), CAN_BITRATE (500000), ARM (pa10),
# REDARM_CONFIG (the package's config/ directory; on a colcon install
# $(ros2 pkg prefix redarm_ros)/share/redarm_ros/config). CAN_INTERFACE and CAN_CHANNEL are
# python-can's own variables: with CAN_INTERFACE=remote CAN_CHANNEL=ws://127.0.0.1:PORT/ (the
# loopback bus server, redarm-canbus, with redarm-sim on it) step 1 is skipped and the same steps
# drive the simulated arm; that is how the test suite runs this script.
#
# On a ROS 2 install, `python -m redarm_ros.nodes.X` is `ros2 run redarm_ros X` and
# `call_trigger.py can_driver/init` is `ros2 service call /can_driver/init std_srvs/srv/Trigger`.
# redarm-bringup --hardware real --can-interface socketcan --can-channel can0 starts steps 2-3 at once.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
PYTHON="${PYTHON:-python}"
CAN_INTERFACE="${CAN_INTERFACE:-socketcan}"
CAN_CHANNEL="${CAN_CHANNEL:-can0}"
CAN_BITRATE="${CAN_BITRATE:-500000}"
ARM="${ARM:-pa10}"
CONFIG="${REDARM_CONFIG:-$HERE/../config}"

# 1. Bring the adapter up at the modules' bit rate (once per boot; needs root). If it is missing:
#    plug it in, check `ip link show`; if the driver later finds no module: the cable, its 120 ohm
#    termination, the modules' power.
if [ "$CAN_INTERFACE" = socketcan ]; then
    ip link show "$CAN_CHANNEL" | grep -q ",UP" \
        || sudo ip link set "$CAN_CHANNEL" up type can bitrate "$CAN_BITRATE"
fi

# 2. Start the driver. It opens the bus and finds the modules, but does not move them: auto_init is
#    false (the default), so it waits for step 4. Other adapters (pcan, kvaser, ...) take their bit
#    rate in can.config, e.g. -p can.config:="{bitrate: 500000}".
"$PYTHON" -m redarm_ros.nodes.can_driver --ros-args --params-file "$CONFIG/can_driver.yaml" \
    -p arm:="$ARM" -p can.interface:="$CAN_INTERFACE" -p can.channel:="$CAN_CHANNEL" &
DRIVER=$!

# 3. Start the controller: goals on goal_pose, twists, the Reach action.
"$PYTHON" -m redarm_ros.nodes.controller --ros-args --params-file "$CONFIG/controller.yaml" \
    -p arm:="$ARM" &
CONTROLLER=$!
trap 'kill -INT $CONTROLLER $DRIVER 2>/dev/null; wait' EXIT

# 4. Reset and home the modules: THE ARM MOVES (every joint to its home position). Until this call
#    the driver ignores every command.
"$PYTHON" "$HERE/call_trigger.py" can_driver/init

# 5. Send a goal and wait for the result (Ctrl-C, or `call_trigger.py can_driver/halt`, stops the arm).
"$PYTHON" "$HERE/reach_action.py" --xyz 0.5 -0.3 0.25

# 6. Halt the modules (brakes on), then the EXIT trap stops the controller and the driver.
"$PYTHON" "$HERE/call_trigger.py" can_driver/halt
