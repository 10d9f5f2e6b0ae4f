"""Data Acquisition's decision table (report 2.2.4): the bottom layer, no subordinate.

Its fault flag is its own checks (the hardware checks and its output check,
controller/daq_layer.py); a fault while SHUT DOWN is only reported (the rack may be
idle). It has no periodic tasks: reading the service's inputs and writing the commands
are the first and last steps of every minor frame (controller/runtime.py).
"""

from controller.decision import DecisionTable
from controller.tables.shared import BOTTOM_ROWS

TABLE = DecisionTable("Data Acquisition", BOTTOM_ROWS, False, "the I/O chassis through the Bit3 buffer",
                      "daq", "Data Acquisition")
