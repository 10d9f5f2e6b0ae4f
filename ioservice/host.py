"""What a device task may ask of the service it runs in: the one interface between
``ioservice.service`` and ``ioservice.tasks`` (and ``ioservice.chargepump``).

A task is wired once at start and run in the frames the schedule gives it. For that it
may: read the rack configuration (its own boards' config, their drivers through ``io``),
the Bit3 layout (its slots), the clock, the schedule and the command area's record
(the fields addressed to it: a matrix route, the CRL's force reflection); publish into the
input area (``values``: the record's field views, filled in place) and count its samples;
report a board's bus error, a board that answered again, an input sample that failed or
succeeded; post a message; and trip the service into FAULT with a fault code. It does not
reach the service's state otherwise; the service imports the tasks, never the reverse
(this module imports neither).

Hot path: the names below are plain attributes and bound methods of the service object,
looked up as before (``svc.values``, ``svc.input_ok``): no property, no wrapper per frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol

if TYPE_CHECKING:
    import numpy as np

    from bit3.layout import FaultCode, Layout
    from drivers.rackio import RackIO
    from ioservice.schedule import Schedule
    from pfma.clock import Clock
    from pfma.rack import BoardConfig, RackConfig


class TaskHost(Protocol):
    """The service as its device tasks see it (``ioservice.service.IoService`` is one)."""

    #: configuration and context, read only
    rack: RackConfig
    layout: Layout
    io: RackIO
    clock: Clock
    schedule: Schedule
    #: the input area's field views (name -> numpy view of the record), filled in place and
    #: published once per frame by the service
    values: dict[str, np.ndarray]
    #: start-up decisions and problems, in full (``pfma serve`` prints them)
    notes: list[str]
    init_errors: list[str]
    #: boards whose last transaction failed: a task that sees it non-empty after a good
    #: transaction calls :meth:`board_answered` (a healthy frame pays one truth test)
    faulted_boards: set[str]
    #: the command area's record (the last good copy, refreshed in place; read, never write)
    command: Any

    def armed(self) -> bool:
        """The output guard lets the commands drive the arm (ARMED)."""
        ...

    def post(self, severity: int, code: int, text: str) -> None:
        """A message in the service's queue."""
        ...

    def fault(self, code: FaultCode, reason: str, trip_code: int | None = None) -> None:
        """FAULT: the outputs made safe, ``code`` published as ``inputs.fault_code``, the
        reason posted by the guard with ``trip_code`` (default: ``code``)."""
        ...

    # the boards: start-up, slots, errors
    def init_board(self, cfg: BoardConfig, action: Callable[..., Any]) -> bool: ...

    def board_slot(self, board: str) -> int: ...

    def span(self, kind: str, channels) -> np.ndarray | slice: ...

    def board_error(self, board: str, err: Exception) -> None: ...

    def board_answered(self, board: str) -> None: ...

    # input samples: failed, good, counted
    def input_failed(self, board: str, group: str, err: Exception) -> None: ...

    def input_ok(self, board: str, slot: int) -> None: ...

    def sampled(self, group: str, t: float) -> None: ...

    def device_error(self, group: str) -> int:
        """Count an error of device group ``group``; returns its count so far."""
        ...

    def decode_serial(self, hand: bool = True) -> None:
        """Decode what the serial lines' buffers hold (F/T, and the CRL if ``hand``)."""
        ...
