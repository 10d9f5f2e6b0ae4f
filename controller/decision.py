"""Decision tables as data: the states, the commands, the rows and their validation.

IRSS report 2.2.4: one decision table per layer. A table reads the command coming
from the layer above and the status of the layer below (never anything further
away), checks the subordinate for errors, then - a "large case statement" on the
command - updates the layer's status and the command going to the layer below.
Section 2.2.6 gives the states and commands (capitalised in the report) and the
power-up / shut-down sequences; this module holds them as data.

A table's inputs (every combination is enumerated when the table is validated):

========  ==========================================================================
command   the command from the layer above (:class:`Command`)
status    this layer's own status (:class:`Status`)
sub       the status of the layer below (:class:`Status`; ``NO_SUBORDINATE`` for the
          bottom layer)
task      the layer's sequence-task mailbox (:class:`TaskState`): the init, start-up,
          shut-down, safe or reset task the table itself created (report 2.4.3: task
          mail boxes are "written to by initialization or shut down tasks and operated
          upon in decision tables")
fault     the layer's own fault flag (its periodic tasks found an error; for Data
          Acquisition, the hardware checks)
========  ==========================================================================

A table's output: the next status, the command to the layer below (``KEEP`` = leave
it as it is) and an action (start one of the layer's sequence tasks, or clear the
mailbox).

Rows are grouped in **sections** evaluated in order, as the report's tables are: the
first section is the error check of the subordinate (and of the layer itself), the
second the case statement on the command. Validation at start (:func:`compile_table`)
proves, for every input combination, that

* **determinism**: within a section at most one row matches;
* **completeness**: some section has a matching row;
* no row is dead (every row decides at least one combination), and every output is a
  legal status/command/action.

The compiled table is a flat tuple indexed by the encoded inputs: one lookup per
layer per minor frame.
"""

from __future__ import annotations

import enum
import itertools
from dataclasses import dataclass, field
from functools import lru_cache

from pfma.errors import ConfigError


class Command(enum.IntEnum):
    """Commands a layer sends to the layer below (report 2.2.6)."""

    NONE = 0
    INIT_TO_START = 1
    START_UP = 2
    SHUT_DOWN = 3
    ERROR_RESET = 4


class Status(enum.IntEnum):
    """Layer states (report 2.2.6). ``START_UP`` is "start up in progress";
    ``SHUT_DOWN_IN_PROGRESS`` and ``ERROR_RESET`` are the in-progress states of the
    shut-down and error-reset sequences (the report's tables have them implicitly:
    "each layer will directly pass a shut down command to the layer below itself
    before it ever reaches a shut down state"). ``NO_SUBORDINATE`` is what the
    bottom layer reads as its subordinate's status."""

    SHUT_DOWN = 0
    INITIALIZATION_IN_PROGRESS = 1
    WAITING_FOR_SUBORDINATE_TO_INIT = 2
    INITIALIZATION_COMPLETE = 3
    START_UP = 4
    START_UP_COMPLETE = 5
    SHUT_DOWN_IN_PROGRESS = 6
    ERROR = 7
    ERROR_RESET = 8
    NO_SUBORDINATE = 9


#: statuses a layer itself can be in (NO_SUBORDINATE is only ever read from below)
LAYER_STATUSES = tuple(s for s in Status if s != Status.NO_SUBORDINATE)


class TaskState(enum.IntEnum):
    """A layer's sequence-task mailbox."""

    IDLE = 0
    RUNNING = 1
    DONE = 2
    FAILED = 3


class Action(enum.IntEnum):
    """What a table row asks of the layer besides status and command."""

    NONE = 0
    INIT = 1  #: start the initialisation task
    STARTUP = 2  #: start the start-up task
    SHUTDOWN = 3  #: start the shut-down task
    SAFE = 4  #: start the safe (error) task: drive this layer's outputs safe
    RESET = 5  #: start the error-reset task
    CLEAR = 6  #: set the mailbox to IDLE (a new phase begins)


#: output "command down" value meaning: leave the command to the layer below unchanged
KEEP = -1

SHORT = {
    Status.SHUT_DOWN: "SD", Status.INITIALIZATION_IN_PROGRESS: "INIT..",
    Status.WAITING_FOR_SUBORDINATE_TO_INIT: "WAITSUB", Status.INITIALIZATION_COMPLETE: "INITOK",
    Status.START_UP: "START..", Status.START_UP_COMPLETE: "UP", Status.SHUT_DOWN_IN_PROGRESS: "SD..",
    Status.ERROR: "ERROR", Status.ERROR_RESET: "RESET..", Status.NO_SUBORDINATE: "-",
}
SHORT_CMD = {Command.NONE: "NONE", Command.INIT_TO_START: "INIT", Command.START_UP: "START",
             Command.SHUT_DOWN: "SHUT", Command.ERROR_RESET: "RESET"}


def status_text(value: int) -> str:
    """The report's spelling of a status ("START UP COMPLETE")."""
    try:
        return Status(value).name.replace("_", " ")
    except ValueError:
        return f"<bad status {value}>"


def command_text(value: int) -> str:
    try:
        return Command(value).name.replace("_", " ")
    except ValueError:
        return f"<bad command {value}>"


ANY = None  #: a wildcard in a row's condition


def _set(values, enum_cls) -> frozenset | None:
    if values is ANY:
        return None
    if isinstance(values, (enum.IntEnum, int)):
        values = (values,)
    return frozenset(enum_cls(v) for v in values)


@dataclass(frozen=True)
class Row:
    """One table row: conditions (a set of values each, ``ANY`` = wildcard) and outputs.

    :param section: evaluation group; lower sections are checked first
    :param rid: the row's number, shown in the trace (which row decided)
    """

    rid: int
    section: int
    command: frozenset | None
    status: frozenset | None
    sub: frozenset | None
    task: frozenset | None
    fault: frozenset | None
    next_status: Status
    command_down: int  #: a Command or KEEP
    action: Action
    note: str = ""

    def matches(self, c, s, b, t, f) -> bool:
        return ((self.command is None or c in self.command) and (self.status is None or s in self.status)
                and (self.sub is None or b in self.sub) and (self.task is None or t in self.task)
                and (self.fault is None or f in self.fault))


def row(rid: int, section: int, *, command=ANY, status=ANY, sub=ANY, task=ANY, fault=ANY,
        then: Status, down: int = KEEP, action: Action = Action.NONE, note: str = "") -> Row:
    """Build a :class:`Row` from readable keyword conditions."""
    fl = None if fault is ANY else frozenset(bool(x) for x in ((fault,) if isinstance(fault, bool) else fault))
    return Row(rid, section, _set(command, Command), _set(status, Status), _set(sub, Status),
               _set(task, TaskState), fl, Status(then),
               KEEP if down == KEEP else int(Command(down)), Action(action), note)


@dataclass(frozen=True)
class DecisionTable:
    """A named, ordered collection of rows; ``has_subordinate`` selects the input space."""

    name: str
    rows: tuple[Row, ...]
    has_subordinate: bool = True
    doc: str = ""

    def input_space(self):
        subs = LAYER_STATUSES if self.has_subordinate else (Status.NO_SUBORDINATE,)
        return itertools.product(Command, LAYER_STATUSES, subs, TaskState, (False, True))


class TableError(ConfigError):
    """A decision table failed validation (incomplete, non-deterministic or dead rows)."""


@dataclass(frozen=True)
class Outcome:
    next_status: Status
    command_down: int
    action: Action
    rid: int
    note: str


def encode(c: int, s: int, b: int, t: int, f: bool) -> int:
    """Index of an input combination in a compiled table."""
    return ((((c * 10) + s) * 10 + b) * 4 + t) * 2 + (1 if f else 0)


@dataclass(frozen=True)
class CompiledTable:
    table: DecisionTable
    lookup: tuple  #: Outcome or None, by :func:`encode`
    coverage: dict = field(default_factory=dict, compare=False)  #: rid -> combinations decided

    def decide(self, c: int, s: int, b: int, t: int, f: bool) -> Outcome:
        """The outcome for one input combination (validated to exist)."""
        try:
            out = self.lookup[encode(c, s, b, t, f)]
        except IndexError:
            out = None
        if out is None:
            raise TableError(f"decision table {self.table.name}: no decision for command={c} "
                             f"status={s} sub={b} task={t} fault={f} (value out of range)")
        return out


#: problems of each kind listed one by one; past this many only their count is given
_MAX_LISTED = 10


def _row_problems(table: DecisionTable) -> list[str]:
    """What is wrong with the rows themselves, whatever the inputs."""
    problems: list[str] = []
    ids = [r.rid for r in table.rows]
    if len(set(ids)) != len(ids):
        problems.append("row ids are not unique")
    for r in table.rows:
        if r.next_status == Status.NO_SUBORDINATE:
            problems.append(f"row {r.rid}: NO SUBORDINATE is not a layer status")
        if not table.has_subordinate and r.next_status == Status.WAITING_FOR_SUBORDINATE_TO_INIT:
            problems.append(f"row {r.rid}: a bottom layer cannot wait for a subordinate")
    return problems


def _by_section(table: DecisionTable) -> list[list[Row]]:
    """The rows grouped by section, lowest section first, each group in table order."""
    sections = sorted({r.section for r in table.rows})
    return [[r for r in table.rows if r.section == sec] for sec in sections]


def _first_hits(groups: list[list[Row]], c, s, b, t, f) -> list[Row]:
    """The rows of the first section with a row matching the inputs (empty: none does);
    more than one is a non-deterministic table, the first of them decides."""
    for group in groups:
        hits = [r for r in group if r.matches(c, s, b, t, f)]
        if hits:
            return hits
    return []


def _inputs_text(c, s, b, t, f) -> str:
    return (f"command={Command(c).name} status={Status(s).name} "
            f"sub={Status(b).name} task={TaskState(t).name} fault={f}")


def _tail_problems(missing: int, ambiguous: int, coverage: dict) -> list[str]:
    """The count of combinations past the listed ones, then the dead rows."""
    problems: list[str] = []
    if missing > _MAX_LISTED or ambiguous > _MAX_LISTED:
        problems.append(f"({missing} incomplete and {ambiguous} ambiguous combinations in all)")
    dead = [rid for rid, n in coverage.items() if n == 0]
    if dead:
        problems.append(f"dead rows (never decide anything): {', '.join(map(str, dead))}")
    return problems


@lru_cache(maxsize=32)
def compile_table(table: DecisionTable) -> CompiledTable:
    """Validate ``table`` over its whole input space and build the lookup.

    :raises TableError: listing every incomplete or ambiguous combination (first 10) and
        every dead row
    """
    problems = _row_problems(table)
    size = encode(len(Command) - 1, 9, 9, 3, True) + 1
    lookup: list = [None] * size
    coverage = {r.rid: 0 for r in table.rows}
    groups = _by_section(table)
    missing = ambiguous = 0
    for c, s, b, t, f in table.input_space():
        hits = _first_hits(groups, c, s, b, t, f)
        if len(hits) > 1:
            ambiguous += 1
            if ambiguous <= _MAX_LISTED:
                problems.append(f"not deterministic: rows {', '.join(str(h.rid) for h in hits)} all "
                                f"match {_inputs_text(c, s, b, t, f)}")
        if not hits:
            missing += 1
            if missing <= _MAX_LISTED:
                problems.append(f"incomplete: no row for {_inputs_text(c, s, b, t, f)}")
            continue
        decided = hits[0]
        coverage[decided.rid] += 1
        lookup[encode(c, s, b, t, f)] = Outcome(decided.next_status, decided.command_down,
                                                decided.action, decided.rid, decided.note)
    problems += _tail_problems(missing, ambiguous, coverage)
    if problems:
        raise TableError(f"decision table {table.name}: " + "; ".join(problems))
    return CompiledTable(table, tuple(lookup), coverage)


# --------------------------------------------------------------------------------------
# The two tables of the seven layers
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


#: the table of System Up/Down ... Servo Control
LAYER_TABLE = _layer_table()
#: the table of Data Acquisition
BOTTOM_TABLE = _bottom_table()


def describe(table: DecisionTable) -> str:
    """The table as readable text (docs, ``pfma controller --tables``)."""
    def fmt(vals, enum_cls):
        if vals is None:
            return "*"
        return "|".join(sorted(SHORT.get(v, v.name) if enum_cls is Status else
                               (SHORT_CMD[v] if enum_cls is Command else v.name) for v in vals))
    lines = [f"decision table {table.name}: {table.doc}",
             f"{'row':>4} {'sec':>3}  {'command':<22} {'status':<16} {'sub':<28} {'task':<14} "
             f"{'fault':<6} -> next / down / action   note"]
    for r in table.rows:
        fl = "*" if r.fault is None else "|".join(sorted("T" if x else "F" for x in r.fault))
        down = "keep" if r.command_down == KEEP else SHORT_CMD[Command(r.command_down)]
        lines.append(f"{r.rid:>4} {r.section:>3}  {fmt(r.command, Command):<22} {fmt(r.status, Status):<16} "
                     f"{fmt(r.sub, Status):<28} {fmt(r.task, TaskState):<14} {fl:<6} -> "
                     f"{SHORT[r.next_status]} / {down} / {r.action.name}   {r.note}")
    return "\n".join(lines)
