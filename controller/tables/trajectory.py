"""The Trajectory Path Planner's decision table (report 2.2.4).

Its planner task exists only while the layer is START UP COMPLETE: the row that reaches
it creates the task, every row that leaves it deletes the task, and the deletion
releases a segment in progress (answered as stopped: controller/trajectory.py).
"""

from controller.decision import Status
from controller.tables.shared import layer_table

TABLE = layer_table(
    "trajectory", "Trajectory Path Planner", "cartesian", "Cartesian Engine",
    (("trajectory_planner", frozenset({Status.START_UP_COMPLETE})),),
    "one Cartesian segment at a time, its speed profile")
