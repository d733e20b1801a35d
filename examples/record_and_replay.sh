#!/usr/bin/env bash
# Record a short run with redarm-record and read it back.
#
#   examples/record_and_replay.sh [OUT.mcap]        (default run.mcap; the stack must be running)
#
# redarm-record writes ROS 2 topics to an MCAP file the way `ros2 bag record -s mcap` does. On a ROS 2
# install, `ros2 bag play run.mcap` replays it and Foxglove opens it; here the file is read back with
# the package's MCAP reader (redarm_ros.record.mcap_io), which needs no ROS at all.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
OUT="${1:-run.mcap}"
PYTHON="${PYTHON:-python}"
if command -v redarm-record >/dev/null; then
    RECORD=(redarm-record)                      # a pip/venv install: the console script
else
    RECORD=(ros2 run redarm_ros redarm-record)  # a colcon install
fi

# 1. Record in the background: joint states, goals, the controller's state, and /tf computed from the
#    joint states through the arm's URDF (so Foxglove can draw the arm). Relative names are resolved
#    in the recorder's namespace (add --ros-args -r __ns:=/left for a stack under /left).
"${RECORD[@]}" -o "$OUT" --tf-from-joint-states joint_states goal_pose controller/state &
RECORDER=$!
sleep 3  # the recorder subscribes as the topics appear

# 2. Move the arm meanwhile (any client would do: a goal stream, the browser view, ...).
"$PYTHON" "$HERE/reach_action.py" --xyz 0.45 0.25 0.35 || true

# 3. Stop the recorder: SIGTERM (or Ctrl-C) closes the file and prints the counts per topic.
kill -TERM "$RECORDER"
wait "$RECORDER"

# 4. Read it back: what is in the file, and the arm's path through it.
"$PYTHON" - "$OUT" <<'PY'
import sys

from redarm_ros.record.mcap_io import read_messages, summarize

path = sys.argv[1]
profile, topics = summarize(path)
print(f"{path}: profile {profile}")
for name, t in sorted(topics.items()):
    if name != "*":
        print(f"  {name:<20} {t.schema_name:<30} {t.count:6d} messages")
joint_states = read_messages(path, ["/joint_states"])
(_, t_first, first), (_, t_last, last) = joint_states[0], joint_states[-1]
print(f"replayed {len(joint_states)} joint states over {(t_last - t_first) / 1e9:.1f} s")
print("  first:", " ".join(f"{q:+.3f}" for q in first.position))
print("  last: ", " ".join(f"{q:+.3f}" for q in last.position))
PY
