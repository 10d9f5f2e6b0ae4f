"""The Multi-Segment Path Planner's decision table (report 2.2.4).

Two tasks, never together: the planner (recording, files, playback, joint moves, gripper
steps) exists only while the layer is START UP COMPLETE, and its deletion ends what it
was doing (controller/paths/layer.py ``task_deleted``); in every other status the
requests task answers a move request at once, refused (the layer is not running).
"""

from controller.decision import LAYER_STATUSES, Status
from controller.tables.shared import layer_table

_UP = frozenset({Status.START_UP_COMPLETE})

TABLE = layer_table(
    "msp", "Multi-Segment Path Planner", "trajectory", "Trajectory Path Planner",
    (("msp_planner", _UP), ("msp_requests", frozenset(LAYER_STATUSES) - _UP)),
    "paths: recording, files, playback, joint moves, gripper steps")
