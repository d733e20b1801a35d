"""redarm_ros.control."""
