#!/bin/sh
# PID 1 of the redarm UML guest (see test/support/uml/runner.py and docs/socketcan.md).
#
# The root file system is the host's, read-only, over hostfs. Inputs arrive as
# kernel-command-line variables (unknown key=value options reach init as its
# environment):
#   REDARM_UML_OUT      host directory to mount read-write; the job and its
#                       results live there
#   REDARM_UML_MODULES  directory holding the UML kernel modules (.../kernel)
#   REDARM_UML_CAN      name of the vcan interface to create (default vcan0)
# Outputs in $REDARM_UML_OUT: init.log (this script's own trace), job.log
# (the job's stdout and stderr), job.rc (the job's exit code). linux.uml exits
# 0 on power-off whatever happened inside, so job.rc is the only verdict.

export PATH=/usr/sbin:/usr/bin:/sbin:/bin
OUT="${REDARM_UML_OUT:-}"
CAN="${REDARM_UML_CAN:-vcan0}"

power_off() {
    # Leftover job processes would keep the results mount busy: end them first.
    kill -9 -1 2>/dev/null
    sync
    [ -n "$OUT" ] && umount "$OUT" 2>/dev/null
    sync
    echo o > /proc/sysrq-trigger
    # sysrq power-off is asynchronous; PID 1 must not exit meanwhile (that panics).
    while :; do sleep 1; done
}

mount -t proc proc /proc
mount -t sysfs sysfs /sys
if [ -z "$OUT" ] || ! mount -t hostfs -o "$OUT" none "$OUT"; then
    echo "redarm-uml: cannot mount the results directory '$OUT' read-write" >&2
    power_off
fi
LOG="$OUT/init.log"
echo "stage=boot uname=$(uname -r) cpus=$(grep -c ^processor /proc/cpuinfo)" > "$LOG"

# Writable scratch space: the root is read-only. ROS needs /dev/shm (Fast DDS
# shared memory), HOME, ROS_LOG_DIR and TMPDIR writable; all live on one tmpfs.
mkdir -p /dev/shm
mount -t tmpfs -o mode=1777 tmpfs /dev/shm
mkdir -p /dev/shm/home /dev/shm/tmp /dev/shm/ros_log
export HOME=/dev/shm/home TMPDIR=/dev/shm/tmp ROS_LOG_DIR=/dev/shm/ros_log
ip link set lo up >> "$LOG" 2>&1

# CAN core, raw sockets, the CAN device layer, then vcan (this order: each needs the one before).
MODS="net/can/can.ko net/can/can-raw.ko drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko"
for m in $MODS; do
    f="${REDARM_UML_MODULES:-/nonexistent}/$m"
    if [ -f "$f" ]; then
        insmod "$f" >> "$LOG" 2>&1 || echo "insmod failed: $m" >> "$LOG"
    else
        echo "module not found (built in?): $m" >> "$LOG"
    fi
done
if ip link add dev "$CAN" type vcan >> "$LOG" 2>&1 && ip link set up "$CAN" >> "$LOG" 2>&1; then
    echo "stage=vcan_up" >> "$LOG"
    ip -details link show "$CAN" >> "$LOG" 2>&1
    cd "$OUT" || power_off
    /bin/sh "$OUT/job.sh" > "$OUT/job.log" 2>&1
    echo "$?" > "$OUT/job.rc"
    echo "stage=job_done rc=$(cat "$OUT/job.rc")" >> "$LOG"
else
    echo "stage=vcan_failed" >> "$LOG"
fi
cd /
power_off
