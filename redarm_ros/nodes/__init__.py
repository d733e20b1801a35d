"""redarm_ros.nodes."""
