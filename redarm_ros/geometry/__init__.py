"""redarm_ros.geometry: the arm's capsule model, obstacle shapes and scenes, signed distances,
self-collision and the obstacle broad phase (numpy, no ROS).

Used by the IK front end (``kinematics/solve.py``, ``collision_ik.py``, ``base_placement.py``) and by
the controller, and imports neither: an arm enters as its five key points (base, shoulder, elbow,
wrist, tool; m) or as an object that gives them, described by the protocols of
:mod:`~redarm_ros.geometry.arm` (any kinematics model is one).
Modules: :mod:`~redarm_ros.geometry.obstacles` (shapes, scenes, capsules, clearance),
:mod:`~redarm_ros.geometry.self_collision`, :mod:`~redarm_ros.geometry.broadphase`.
"""
