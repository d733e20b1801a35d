"""The old home of :mod:`redarm_ros.geometry.self_collision`, which the docs named: code that imports
``redarm_ros.control.self_collision`` keeps working and gets that very module. New code imports from
``redarm_ros.geometry``.
"""

import sys

from redarm_ros.geometry import self_collision

sys.modules[__name__] = self_collision
