"""redarm_ros.kinematics."""
