"""redarm_ros.sim: the pybullet hardware stand-in (ROS-free).

* :mod:`~redarm_ros.sim.urdf` - URDF text from an arm model (link frames = ``arm.fk_frames``),
* :mod:`~redarm_ros.sim.ramp` - per-joint setpoint generator (velocity/acceleration limited),
* :mod:`~redarm_ros.sim.plant` - the pybullet plant (explicit client id, scene, headless snapshots),
* :mod:`~redarm_ros.sim.emulation` - one PowerCube module emulator per joint over the plant,
* :mod:`~redarm_ros.sim.hardware` - the ``redarm-sim`` process (``main``).

Nothing is imported here, so ``import redarm_ros.sim`` stays cheap and pybullet-free; see docs/sim.md.
"""
