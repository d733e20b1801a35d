"""Former home of the controller's scalar rotation helpers, now in :mod:`redarm_ros.kinematics.quaternion`.

Only names, no code: kept so that code written against this module keeps importing; import from
:mod:`redarm_ros.kinematics.quaternion` in new code.
"""

from redarm_ros.kinematics.quaternion import (  # noqa: F401
    Quat,
    Vec3,
    matrix_from_quat,
    quat_angle,
    quat_between_vectors,
    quat_conj,
    quat_from_matrix,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    rotvec_between,
    slerp_vectors,
)
