"""System Up/Down's decision table (report 2.2.4, 2.2.6): the top layer.

Its command comes from the user through its own request task (``updown.command``,
written by ``updown_requests``: POWER UP, POWER DOWN, ERROR RESET). The request task runs
in every status: requests arrive and are answered whether the system is up or not.
"""

from controller.tables.shared import ALWAYS, layer_table

TABLE = layer_table(
    "updown", "System Up/Down", "msp", "Multi-Segment Path Planner",
    (("updown_requests", ALWAYS),),
    "master control; the user's requests become its command")
