"""The browser view of the arm: URDF reading and forward kinematics (:mod:`.urdf_model`, numpy only)
and the viser scene and panels (:mod:`.viewer`, no ROS). The ROS node is :mod:`redarm_ros.nodes.view`."""
