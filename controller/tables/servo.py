"""Servo Control's decision table (report 2.2.4).

Both its tasks run in every status: the servo task drives the rate and current-limit
commands safe (0, brakes set) whenever the loop is not closed and watches the brakes and
joints (controller/servo.py, controller/supervision.py); the gripper task likewise holds
the seventh amplifier at 0 unless the layer is up (controller/gripper.py). Deleting them
would leave the outputs without a writer.
"""

from controller.tables.shared import ALWAYS, layer_table

TABLE = layer_table(
    "servo", "Servo Control", "daq", "Data Acquisition",
    (("servo_control", ALWAYS), ("gripper_control", ALWAYS)),
    "compensators and limits: joint positions -> rate commands; the gripper; joint supervision")
