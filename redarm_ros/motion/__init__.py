"""Joint motion limits, in one place: position, velocity and acceleration limits and the braking law.

numpy only (plus a pure-Python scalar path for 1 kHz per-joint loops). The CAN driver's reference
shaper (:mod:`redarm_ros.can.driver_loop`) and the simulator's setpoint generator
(:mod:`redarm_ros.sim.ramp`) both use it; it depends on nothing else in the package, so any core
(``can/``, ``control/``, ``sim/``) may import it without an import circle.
"""

from redarm_ros.motion.limits import (
    JointLimits,
    LimitsView,
    braking_distance,
    braking_distance_scalar,
    braking_speed,
    braking_speed_scalar,
    velocity_bounds,
    velocity_bounds_scalar,
)

__all__ = [
    "JointLimits", "LimitsView", "braking_distance", "braking_distance_scalar", "braking_speed",
    "braking_speed_scalar", "velocity_bounds", "velocity_bounds_scalar",
]
