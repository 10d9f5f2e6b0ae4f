"""The rows the layers' decision tables share (report 2.2.4), in named groups.

Six layers have a subordinate and run the same power-up, shut-down, error and error-reset
logic; Data Acquisition, the bottom, has none. Each layer's own table
(``controller/tables/<layer>.py``) takes its rows from here explicitly: where the layers
behave alike they share these rows; what differs is theirs (the periodic tasks each table
creates and deletes, the variables its first and last parts read and post).

The groups, in the report's parts: :data:`ERROR_CHECK` is part 2 (the error check of the
subordinate and of the layer itself, section 1 of the compiled table); the case
statement on the command (part 3, section 2) is one group per status the layer is in
(:func:`case`).
"""

from __future__ import annotations

from controller.decision import (
    LAYER_STATUSES, Action, Command, DecisionTable, Row, Status, TaskState, row,
)

S = Status
C = Command
T = TaskState
A = Action
ACTIVE = (S.SHUT_DOWN, S.INITIALIZATION_IN_PROGRESS, S.WAITING_FOR_SUBORDINATE_TO_INIT,
          S.INITIALIZATION_COMPLETE, S.START_UP, S.START_UP_COMPLETE, S.SHUT_DOWN_IN_PROGRESS)
NOT_ERROR = tuple(s for s in LAYER_STATUSES if s != S.ERROR)
PENDING = (T.IDLE, T.RUNNING)
ERR_OUT = dict(then=S.ERROR, down=C.SHUT_DOWN, action=A.SAFE)


def _common_tail(first_id: int, bottom: bool) -> list[Row]:
    """Rows shared by both tables: START UP COMPLETE, shut-down, error and error reset."""
    i = first_id
    sub_down = (S.NO_SUBORDINATE,) if bottom else (S.SHUT_DOWN,)
    sub_not_down = () if bottom else tuple(s for s in LAYER_STATUSES if s != S.SHUT_DOWN)
    rows = [
        # -- START UP COMPLETE: hold; a shut-down or reset command starts the shut-down
        row(i + 0, 2, status=S.START_UP_COMPLETE, command=C.START_UP,
            sub=None if bottom else S.START_UP_COMPLETE, then=S.START_UP_COMPLETE,
            note="powered up: hold"),
        row(i + 1, 2, status=S.START_UP_COMPLETE, command=(C.SHUT_DOWN, C.ERROR_RESET),
            then=S.SHUT_DOWN_IN_PROGRESS, down=C.SHUT_DOWN, action=A.SHUTDOWN,
            note="shut down: pass SHUT DOWN down at once, run own shut-down task"),
        row(i + 2, 2, status=S.START_UP_COMPLETE, command=(C.NONE, C.INIT_TO_START), **ERR_OUT,
            note="inappropriate command while powered up"),
        # -- SHUT DOWN IN PROGRESS: finish whatever the command; SHUT DOWN when own task and
        #    the subordinate are down
        row(i + 3, 2, status=S.SHUT_DOWN_IN_PROGRESS, task=PENDING, then=S.SHUT_DOWN_IN_PROGRESS,
            note="own shut-down task running"),
        row(i + 4, 2, status=S.SHUT_DOWN_IN_PROGRESS, task=T.DONE, sub=sub_down, then=S.SHUT_DOWN,
            note="shut down (own task done, subordinate down)"),
        # -- ERROR: stays until ERROR RESET, the safe task has finished and no fault is active
        row(i + 5, 2, status=S.ERROR, command=C.ERROR_RESET, fault=False, task=(T.DONE, T.FAILED),
            then=S.ERROR_RESET, down=C.ERROR_RESET, action=A.RESET, note="error reset: pass it down"),
        row(i + 6, 2, status=S.ERROR, command=C.ERROR_RESET, fault=True, then=S.ERROR,
            note="error reset refused: fault still present"),
        row(i + 7, 2, status=S.ERROR, command=C.ERROR_RESET, fault=False, task=PENDING, then=S.ERROR,
            note="error reset waits for the safe task"),
        row(i + 8, 2, status=S.ERROR, command=(C.NONE, C.INIT_TO_START, C.START_UP, C.SHUT_DOWN),
            then=S.ERROR, note="in ERROR: only ERROR RESET is accepted"),
        # -- ERROR RESET in progress
        row(i + 9, 2, status=S.ERROR_RESET, fault=True, **ERR_OUT, note="fault during error reset"),
        row(i + 10, 2, status=S.ERROR_RESET, fault=False, task=T.FAILED, **ERR_OUT,
            note="error-reset task failed"),
        row(i + 11, 2, status=S.ERROR_RESET, fault=False, task=PENDING, then=S.ERROR_RESET,
            note="own reset task running"),
        row(i + 12, 2, status=S.ERROR_RESET, fault=False, task=T.DONE, sub=sub_down, then=S.SHUT_DOWN,
            note="error reset complete: SHUT DOWN"),
    ]
    if not bottom:
        rows += [
            row(i + 13, 2, status=S.SHUT_DOWN_IN_PROGRESS, task=T.DONE, sub=sub_not_down,
                then=S.SHUT_DOWN_IN_PROGRESS, note="waiting for the subordinate to shut down"),
            row(i + 14, 2, status=S.ERROR_RESET, fault=False, task=T.DONE, sub=sub_not_down,
                then=S.ERROR_RESET, note="waiting for the subordinate's error reset"),
            row(i + 15, 2, status=S.START_UP_COMPLETE, command=C.START_UP,
                sub=tuple(s for s in LAYER_STATUSES if s not in (S.START_UP_COMPLETE, S.ERROR)), **ERR_OUT,
                note="subordinate left START UP COMPLETE"),
        ]
    return rows


def _layer_table() -> DecisionTable:
    """The table of every layer that has a subordinate (System Up/Down ... Servo Control)."""
    sub_ok = tuple(s for s in LAYER_STATUSES if s != S.ERROR)
    rows = [
        # ---- section 1: error check of the subordinate and of this layer
        row(1, 1, status=ACTIVE, sub=S.ERROR, **ERR_OUT, note="subordinate in ERROR"),
        row(2, 1, status=ACTIVE, sub=sub_ok, fault=True, **ERR_OUT, note="own fault"),
        row(3, 1, status=ACTIVE, sub=sub_ok, fault=False, task=T.FAILED, **ERR_OUT,
            note="own sequence task failed"),
        # ---- section 2: the case statement on the command
        # SHUT DOWN (powered down)
        row(10, 2, status=S.SHUT_DOWN, command=(C.NONE, C.SHUT_DOWN, C.ERROR_RESET), then=S.SHUT_DOWN,
            note="shut down: idle"),
        row(11, 2, status=S.SHUT_DOWN, command=C.INIT_TO_START, then=S.INITIALIZATION_IN_PROGRESS,
            action=A.INIT, note="INIT TO START: schedule own initialisation task"),
        row(12, 2, status=S.SHUT_DOWN, command=C.START_UP, **ERR_OUT,
            note="START UP before INITIALIZATION COMPLETE"),
        # INITIALIZATION IN PROGRESS (SHUT DOWN is not accepted before INITIALIZATION COMPLETE:
        # the initialisation goes on; the shut-down command is acted on once complete)
        row(20, 2, status=S.INITIALIZATION_IN_PROGRESS, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), task=PENDING, then=S.INITIALIZATION_IN_PROGRESS, note="own init task running"),
        row(21, 2, status=S.INITIALIZATION_IN_PROGRESS, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), task=T.DONE, then=S.WAITING_FOR_SUBORDINATE_TO_INIT, down=C.INIT_TO_START,
            action=A.CLEAR, note="own init done: command INIT TO START below"),
        row(22, 2, status=S.INITIALIZATION_IN_PROGRESS, command=C.START_UP, **ERR_OUT,
            note="START UP before INITIALIZATION COMPLETE"),
        # WAITING FOR SUBORDINATE TO INIT
        row(30, 2, status=S.WAITING_FOR_SUBORDINATE_TO_INIT, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), sub=(S.SHUT_DOWN, S.INITIALIZATION_IN_PROGRESS, S.WAITING_FOR_SUBORDINATE_TO_INIT),
            then=S.WAITING_FOR_SUBORDINATE_TO_INIT, note="waiting for the subordinate's INITIALIZATION COMPLETE"),
        row(31, 2, status=S.WAITING_FOR_SUBORDINATE_TO_INIT, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), sub=S.INITIALIZATION_COMPLETE, then=S.INITIALIZATION_COMPLETE,
            note="subordinate initialised: INITIALIZATION COMPLETE"),
        row(32, 2, status=S.WAITING_FOR_SUBORDINATE_TO_INIT, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), sub=(S.START_UP, S.START_UP_COMPLETE, S.SHUT_DOWN_IN_PROGRESS, S.ERROR_RESET),
            **ERR_OUT, note="subordinate in an impossible state during init"),
        row(33, 2, status=S.WAITING_FOR_SUBORDINATE_TO_INIT, command=C.START_UP, **ERR_OUT,
            note="START UP before INITIALIZATION COMPLETE"),
        # INITIALIZATION COMPLETE
        row(40, 2, status=S.INITIALIZATION_COMPLETE, command=(C.NONE, C.INIT_TO_START),
            sub=S.INITIALIZATION_COMPLETE, then=S.INITIALIZATION_COMPLETE, note="initialised: hold"),
        row(41, 2, status=S.INITIALIZATION_COMPLETE, command=(C.NONE, C.INIT_TO_START, C.START_UP),
            sub=tuple(s for s in sub_ok if s != S.INITIALIZATION_COMPLETE), **ERR_OUT,
            note="subordinate left INITIALIZATION COMPLETE"),
        row(42, 2, status=S.INITIALIZATION_COMPLETE, command=C.START_UP, sub=S.INITIALIZATION_COMPLETE,
            then=S.START_UP, down=C.START_UP, action=A.CLEAR, note="START UP: pass it down at once"),
        row(43, 2, status=S.INITIALIZATION_COMPLETE, command=(C.SHUT_DOWN, C.ERROR_RESET),
            then=S.SHUT_DOWN_IN_PROGRESS, down=C.SHUT_DOWN, action=A.SHUTDOWN,
            note="shut down: pass SHUT DOWN down at once, run own shut-down task"),
        # START UP (in progress): wait for the subordinate's START UP COMPLETE, then run the
        # own start-up task
        row(50, 2, status=S.START_UP, command=C.START_UP, sub=(S.INITIALIZATION_COMPLETE, S.START_UP),
            then=S.START_UP, note="waiting for the subordinate's START UP COMPLETE"),
        row(51, 2, status=S.START_UP, command=C.START_UP, sub=S.START_UP_COMPLETE, task=T.IDLE,
            then=S.START_UP, action=A.STARTUP, note="subordinate up: schedule own start-up task"),
        row(52, 2, status=S.START_UP, command=C.START_UP, sub=S.START_UP_COMPLETE, task=T.RUNNING,
            then=S.START_UP, note="own start-up task running"),
        row(53, 2, status=S.START_UP, command=C.START_UP, sub=S.START_UP_COMPLETE, task=T.DONE,
            then=S.START_UP_COMPLETE, note="START UP COMPLETE"),
        row(54, 2, status=S.START_UP, command=C.START_UP, sub=(S.SHUT_DOWN, S.INITIALIZATION_IN_PROGRESS,
            S.WAITING_FOR_SUBORDINATE_TO_INIT, S.SHUT_DOWN_IN_PROGRESS, S.ERROR_RESET), **ERR_OUT,
            note="subordinate in an impossible state during start-up"),
        row(55, 2, status=S.START_UP, command=(C.SHUT_DOWN, C.ERROR_RESET), then=S.SHUT_DOWN_IN_PROGRESS,
            down=C.SHUT_DOWN, action=A.SHUTDOWN, note="shut down during start-up"),
        row(56, 2, status=S.START_UP, command=(C.NONE, C.INIT_TO_START), **ERR_OUT,
            note="inappropriate command during start-up"),
    ] + _common_tail(60, bottom=False)
    return DecisionTable("layer", tuple(rows), True,
                         "every layer with a subordinate: System Up/Down down to Servo Control")


def _bottom_table() -> DecisionTable:
    """The bottom layer's table (Data Acquisition): no subordinate; its fault flag is the
    hardware check. A fault while SHUT DOWN is only reported (the rack may be idle)."""
    rows = [
        row(1, 1, status=tuple(s for s in ACTIVE if s != S.SHUT_DOWN), fault=True, **ERR_OUT,
            note="hardware fault"),
        row(2, 1, status=tuple(s for s in ACTIVE if s != S.SHUT_DOWN), fault=False, task=T.FAILED,
            **ERR_OUT, note="own sequence task failed"),
        row(3, 1, status=S.SHUT_DOWN, task=T.FAILED, **ERR_OUT, note="own sequence task failed"),
        row(10, 2, status=S.SHUT_DOWN, command=(C.NONE, C.SHUT_DOWN, C.ERROR_RESET), task=(T.IDLE, T.RUNNING,
            T.DONE), then=S.SHUT_DOWN, note="shut down: idle (faults only reported)"),
        row(11, 2, status=S.SHUT_DOWN, command=C.INIT_TO_START, task=(T.IDLE, T.RUNNING, T.DONE),
            then=S.INITIALIZATION_IN_PROGRESS, action=A.INIT, note="INIT TO START: schedule init task"),
        row(12, 2, status=S.SHUT_DOWN, command=C.START_UP, task=(T.IDLE, T.RUNNING, T.DONE), **ERR_OUT,
            note="START UP before INITIALIZATION COMPLETE"),
        row(20, 2, status=S.INITIALIZATION_IN_PROGRESS, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), task=PENDING, then=S.INITIALIZATION_IN_PROGRESS, note="init task running"),
        row(21, 2, status=S.INITIALIZATION_IN_PROGRESS, command=(C.NONE, C.INIT_TO_START, C.SHUT_DOWN,
            C.ERROR_RESET), task=T.DONE, then=S.INITIALIZATION_COMPLETE, action=A.CLEAR,
            note="bottom layer initialised: INITIALIZATION COMPLETE"),
        row(22, 2, status=S.INITIALIZATION_IN_PROGRESS, command=C.START_UP, **ERR_OUT,
            note="START UP before INITIALIZATION COMPLETE"),
        row(30, 2, status=S.WAITING_FOR_SUBORDINATE_TO_INIT, **ERR_OUT,
            note="impossible: the bottom layer has no subordinate"),
        row(40, 2, status=S.INITIALIZATION_COMPLETE, command=(C.NONE, C.INIT_TO_START),
            then=S.INITIALIZATION_COMPLETE, note="initialised: hold"),
        row(42, 2, status=S.INITIALIZATION_COMPLETE, command=C.START_UP, then=S.START_UP,
            action=A.STARTUP, note="START UP reached the bottom: schedule the start-up task"),
        row(43, 2, status=S.INITIALIZATION_COMPLETE, command=(C.SHUT_DOWN, C.ERROR_RESET),
            then=S.SHUT_DOWN_IN_PROGRESS, action=A.SHUTDOWN, note="shut down: run the shut-down task"),
        row(50, 2, status=S.START_UP, command=C.START_UP, task=PENDING, then=S.START_UP,
            note="start-up task running"),
        row(53, 2, status=S.START_UP, command=C.START_UP, task=T.DONE, then=S.START_UP_COMPLETE,
            note="START UP COMPLETE"),
        row(55, 2, status=S.START_UP, command=(C.SHUT_DOWN, C.ERROR_RESET), then=S.SHUT_DOWN_IN_PROGRESS,
            action=A.SHUTDOWN, note="shut down during start-up"),
        row(56, 2, status=S.START_UP, command=(C.NONE, C.INIT_TO_START), **ERR_OUT,
            note="inappropriate command during start-up"),
    ] + _common_tail(60, bottom=True)
    return DecisionTable("bottom", tuple(rows), False, "the bottom layer: Data Acquisition")




#: every status a layer can be in: a task that runs in all of them is never deleted
ALWAYS = frozenset(LAYER_STATUSES)
#: the generic tables: the shared rows alone (a layer with no table of its own, e.g. a
#: test's stand-in layer, runs these; no periodic tasks created or deleted)
LAYER_TABLE = _layer_table()
BOTTOM_TABLE = _bottom_table()
#: the rows of every layer with a subordinate, and of the bottom layer
LAYER_ROWS = LAYER_TABLE.rows
BOTTOM_ROWS = BOTTOM_TABLE.rows
#: part 2, the error check (section 1)
ERROR_CHECK = tuple(r for r in LAYER_ROWS if r.section == 1)
BOTTOM_ERROR_CHECK = tuple(r for r in BOTTOM_ROWS if r.section == 1)


def case(status: Status, bottom: bool = False) -> tuple[Row, ...]:
    """Part 3's rows for a layer in ``status`` (the case statement on the command)."""
    rows = BOTTOM_ROWS if bottom else LAYER_ROWS
    return tuple(r for r in rows if r.section == 2 and r.status == frozenset((status,)))


def layer_table(key: str, title: str, sub_key: str, sub_title: str, tasks, doc: str) -> DecisionTable:
    """A layer's own table on the shared rows (part 2 and 3 as every layer with a
    subordinate has them), with its own tasks and neighbours."""
    return DecisionTable(title, LAYER_ROWS, True, doc, key, title, sub_key, sub_title, tuple(tasks))
