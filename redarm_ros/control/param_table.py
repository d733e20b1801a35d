"""The old home of :mod:`redarm_ros.param_table`, which the docs named: code that imports
``redarm_ros.control.param_table`` keeps working and gets that very module, and
``python -m redarm_ros.control.param_table`` still prints the table. New code imports
``redarm_ros.param_table``.
"""

import sys

from redarm_ros import param_table

if __name__ == "__main__":
    raise SystemExit(param_table.main())
sys.modules[__name__] = param_table
