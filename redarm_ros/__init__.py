"""redarm_ros: drive a redundant anthropomorphic arm over CAN.

Subpackages: ``kinematics`` (numpy), ``control`` (numpy), ``can`` (python-can),
``sim`` (pybullet) are ROS-free cores; ``nodes`` holds the thin rclpy shells.
"""

__version__ = "0.1.0"
