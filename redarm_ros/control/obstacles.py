"""The old home of :mod:`redarm_ros.geometry.obstacles`, which the docs named: code that imports
``redarm_ros.control.obstacles`` keeps working and gets that very module. New code imports from
``redarm_ros.geometry``.
"""

import sys

from redarm_ros.geometry import obstacles

sys.modules[__name__] = obstacles
