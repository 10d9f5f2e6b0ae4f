"""The Joint Planner's decision table (report 2.2.4).

Its planner task exists from INITIALIZATION COMPLETE through START UP to START UP
COMPLETE: it publishes the tool pose and the joint command the servo holds while the
layers above start (created by the row that reaches INITIALIZATION COMPLETE, deleted by
every row that leaves the three).
"""

from controller.decision import Status
from controller.tables.shared import layer_table

TABLE = layer_table(
    "joint", "Joint Planner", "servo", "Servo Control",
    (("joint_planner", frozenset({Status.INITIALIZATION_COMPLETE, Status.START_UP, Status.START_UP_COMPLETE})),),
    "inverse kinematics: the Cartesian command -> joint positions for the servo")
