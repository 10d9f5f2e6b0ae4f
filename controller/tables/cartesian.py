"""The Cartesian Engine's decision table (report 2.2.4).

Both its tasks (trajectory and hand-controller composition at 40 Hz, force/torque offsets
at 80 Hz) exist only while the layer is START UP COMPLETE: created by the row that
reaches it, deleted by every row that leaves it.
"""

from controller.decision import Status
from controller.tables.shared import layer_table

_UP = frozenset({Status.START_UP_COMPLETE})

TABLE = layer_table(
    "cartesian", "Cartesian Engine", "joint", "Joint Planner",
    (("cartesian_slow", _UP), ("cartesian_fast", _UP)),
    "the Cartesian command: trajectory, hand controller, force control")
