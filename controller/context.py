"""What a layer sees of the runtime that drives it: the layer-context protocol.

The layers (:mod:`controller.layers` and the layer modules) are called by
:class:`controller.runtime.ControllerRuntime` once per minor frame with the runtime as
their context; they use only what is named here. Typing the layers against this
protocol instead of the runtime class keeps the import graph one-way (the runtime
imports the layers, never the other way round).
"""

from __future__ import annotations

from typing import Any, Protocol

from controller.worldmodel import WorldModel


class LayerContext(Protocol):
    """The runtime as a layer sees it."""

    wm: WorldModel  #: the world model (the layers' only way to talk to each other)
    now: float  #: the runtime clock at the start of this minor frame (s)
    frame: int  #: the service frame this minor frame runs on
    last_rid: dict[str, int]  #: per layer key, the decision-table row that decided last
    servo_oldest_frame: int  #: the oldest servo stamp Data Acquisition may still send
    servo_catch_up: bool  #: this frame catches up a missed servo slot
    servo: Any  #: the Servo Control layer (Data Acquisition faults it for a missing output)
    halted: bool  #: halted (docs/console.md): frames run only as single steps, outputs held safe

    def post(self, source: str, level: Any, text: str) -> Any:
        """Post a message (source = layer key) to the controller's message board."""

    def task_period_s(self, name: str) -> float:
        """The period of a periodic task in the frame schedule (s)."""

    def on_status_change(self, layer: Any, old: int, new: int) -> None:
        """A layer's decision table changed its status."""
