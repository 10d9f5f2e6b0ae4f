"""The Multi-Segment Path Planner's decision table (report 2.2.4).

Its task runs in every status: while the layer is not START UP COMPLETE it only answers
the user's path and move requests (refused: not running) and leaves any path it was
following; it plans only while START UP COMPLETE (controller/paths/layer.py).
"""

from controller.tables.shared import ALWAYS, layer_table

TABLE = layer_table(
    "msp", "Multi-Segment Path Planner", "trajectory", "Trajectory Path Planner",
    (("msp_planner", ALWAYS),),
    "paths: recording, files, playback, joint moves, gripper steps")
