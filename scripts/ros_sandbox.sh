#!/usr/bin/env bash
# Run a command under the project's network rule: no ROS/DDS packet may leave loopback.
#
#   scripts/ros_sandbox.sh CMD [ARGS...]
#
# * FASTDDS_BUILTIN_TRANSPORTS=SHM (Fast DDS sends nothing over IP), ROS_AUTOMATIC_DISCOVERY_RANGE=
#   LOCALHOST, and a fresh random ROS_DOMAIN_ID in 1..200 for this run (REDARM_ROS_DOMAIN_ID
#   overrides it), ROS_LOG_DIR under .build/ros_log.
# * When possible (root, or unprivileged user namespaces), CMD also runs in a private network and
#   mount namespace: only `lo` exists there and /dev/shm is a private tmpfs, so even a transport that
#   slipped through has nowhere to send to, and parallel runs cannot see each other's SHM segments.
#   REDARM_NO_NETNS=1 skips the namespace (the environment variables are still set).
# The exit code is CMD's.
set -euo pipefail

[ "$#" -gt 0 ] || { echo "usage: $0 CMD [ARGS...]" >&2; exit 2; }

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
export FASTDDS_BUILTIN_TRANSPORTS=SHM
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${REDARM_ROS_DOMAIN_ID:-$(shuf -i 1-200 -n 1)}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-$REPO/.build/ros_log}"
export RCUTILS_COLORIZED_OUTPUT="${RCUTILS_COLORIZED_OUTPUT:-0}"
mkdir -p "$ROS_LOG_DIR"

# The body run inside the namespace: private /dev/shm, loopback up, then exec the command.
# shellcheck disable=SC2016
inner='mount -t tmpfs -o mode=1777 tmpfs /dev/shm && ip link set lo up && exec "$@"'

if [ "${REDARM_NO_NETNS:-0}" != 1 ] && command -v unshare >/dev/null 2>&1 && command -v ip >/dev/null 2>&1; then
    userns=()
    [ "$(id -u)" = 0 ] || userns=(--user --map-root-user)
    if unshare "${userns[@]}" --net --mount bash -c "$inner" probe true >/dev/null 2>&1; then
        echo "ros_sandbox: ROS_DOMAIN_ID=$ROS_DOMAIN_ID, SHM-only DDS, private network namespace (lo only)" >&2
        exec unshare "${userns[@]}" --net --mount bash -c "$inner" ros_sandbox "$@"
    fi
    echo "ros_sandbox: cannot create a network namespace here; relying on SHM-only DDS" >&2
fi
echo "ros_sandbox: ROS_DOMAIN_ID=$ROS_DOMAIN_ID, SHM-only DDS" >&2
exec "$@"
