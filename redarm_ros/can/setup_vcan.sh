#!/bin/sh
# Create and bring up a virtual SocketCAN interface (default vcan0) on a real Linux host.
# Needs root. Idempotent: running it again leaves an existing, up interface as it is.
#
#   sudo redarm_ros/can/setup_vcan.sh            # vcan0
#   sudo redarm_ros/can/setup_vcan.sh can0       # a vcan named can0 (Schunk libm5api reads
#                                                # only 4 characters of the interface name)
# Then: CAN_INTERFACE=socketcan CAN_CHANNEL=vcan0 ros2 run redarm_ros can_driver
set -eu

IFACE="${1:-vcan0}"

if [ "$(id -u)" -ne 0 ]; then
    echo "setup_vcan.sh: needs root, run: sudo $0 $IFACE" >&2
    exit 1
fi

# The module may be built in or already loaded; only fail later if the link cannot be made.
modprobe vcan 2>/dev/null || true

if ip link show dev "$IFACE" >/dev/null 2>&1; then
    kind="$(ip -details link show dev "$IFACE" | sed -n 's/^ *\(vcan\|can\) .*/\1/p' | head -n 1)"
    if [ -z "$kind" ]; then
        echo "setup_vcan.sh: $IFACE exists but is not a CAN interface" >&2
        exit 1
    fi
else
    if ! ip link add dev "$IFACE" type vcan; then
        echo "setup_vcan.sh: cannot create $IFACE: this kernel has no vcan/SocketCAN support" >&2
        exit 1
    fi
fi

ip link set up "$IFACE"
echo "setup_vcan.sh: $IFACE is up"
