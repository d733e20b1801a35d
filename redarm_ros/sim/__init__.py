"""redarm_ros.sim."""
