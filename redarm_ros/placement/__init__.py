"""Base placement for a task set: where the arm should stand so that every task pose is reachable.

ROS-free (numpy, PyYAML; Dask only as an optional engine). Sits above ``kinematics/`` and ``control/``:
it uses the exact swivel intervals and the capsule collision model, and nothing imports it back.

    from redarm_ros.placement import load_problem, place
    res = place(load_problem("tasks.yaml"), workers=2)
    best = res.ranking()[0]; x, y, yaw = res.poses[best]
"""

from redarm_ros.placement.problem import BaseGrid, PlacementProblem, load_problem, problem_from_dict
from redarm_ros.placement.study import PlacementResult, place

__all__ = ["BaseGrid", "PlacementProblem", "PlacementResult", "load_problem", "place", "problem_from_dict"]
