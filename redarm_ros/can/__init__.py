"""redarm_ros.can."""
