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
    """A named, ordered collection of rows; ``has_subordinate`` selects the input space.

    A layer's own table (``controller/tables/<layer>.py``) also names the layer
    (``key``, ``title``) and the layer below (``sub_key``: the variables of its parts 1
    and 4), and its periodic tasks with the statuses each runs in (``tasks``): from
    these the compiled rows' actions create and delete the tasks (:class:`Outcome`)."""

    name: str
    rows: tuple[Row, ...]
    has_subordinate: bool = True
    doc: str = ""
    key: str = ""
    title: str = ""
    sub_key: str = ""
    sub_title: str = ""
    #: (task name, the statuses it runs in): a task runs while its layer is in one of them
    tasks: tuple[tuple[str, frozenset], ...] = ()

    def running_in(self, status: int) -> frozenset:
        """The periodic tasks that run while the layer is in ``status``."""
        return frozenset(name for name, statuses in self.tasks if status in statuses)

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
    #: the periodic tasks this decision creates and deletes (they run, or stop, from the
    #: next minor frame: the tasks of a frame run in the status its table read)
    create: frozenset = frozenset()
    delete: frozenset = frozenset()


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
    names = [name for name, _ in table.tasks]
    if len(set(names)) != len(names):
        problems.append("periodic task names are not unique")
    for name, statuses in table.tasks:
        if not statuses or not set(statuses) <= set(LAYER_STATUSES):
            problems.append(f"task {name}: runs in no status, or in one that is not a layer status")
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
    outcomes: dict = {}  # (row, status): one Outcome object for each
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
        out = outcomes.get((decided.rid, s))
        if out is None:
            was, now = table.running_in(s), table.running_in(decided.next_status)
            out = outcomes[decided.rid, s] = Outcome(decided.next_status, decided.command_down, decided.action,
                                                     decided.rid, decided.note, now - was, was - now)
        lookup[encode(c, s, b, t, f)] = out
    problems += _tail_problems(missing, ambiguous, coverage)
    if problems:
        raise TableError(f"decision table {table.name}: " + "; ".join(problems))
    return CompiledTable(table, tuple(lookup), coverage)



def _status_names(statuses) -> str:
    if set(statuses) >= set(LAYER_STATUSES):
        return "every status"
    return "|".join(SHORT[st] for st in sorted(statuses))


def row_tasks(table: DecisionTable, r: Row) -> str:
    """The periodic tasks a row creates (+) and deletes (-), over the statuses it decides in."""
    create: set[str] = set()
    delete: set[str] = set()
    now = table.running_in(r.next_status)
    for st in (r.status if r.status is not None else LAYER_STATUSES):
        was = table.running_in(st)
        create |= now - was
        delete |= was - now
    return " ".join([f"+{n}" for n in sorted(create)] + [f"-{n}" for n in sorted(delete)])


def describe(table: DecisionTable) -> str:
    """The table as readable text in the report's four parts (docs, ``pfma controller
    --tables``): what it reads, the error check, the case statement on the command (each
    row with the periodic tasks it creates and deletes), what it posts."""
    def fmt(vals, enum_cls):
        if vals is None:
            return "*"
        return "|".join(sorted(SHORT.get(v, v.name) if enum_cls is Status else
                               (SHORT_CMD[v] if enum_cls is Command else v.name) for v in vals))
    k = table.key or "<layer>"
    title = f"{table.title} ({table.key})" if table.key else table.name
    sub = (f"{table.sub_key}.status ({table.sub_title})" if table.sub_key else "its subordinate's status") \
        if table.has_subordinate else "no subordinate (the bottom layer)"
    down = f"{table.sub_key}.command" if table.sub_key else "the subordinate's command"
    tasks = ", ".join(f"{n} ({_status_names(st)})" for n, st in table.tasks) or "none"
    head = (f"{'row':>4}  {'command':<22} {'status':<16} {'sub':<28} {'task':<14} "
            f"{'fault':<6} -> next / down / action   tasks   note")
    lines = [f"decision table {title}: {table.doc}",
             f"  part 1, read: {k}.command, {k}.status, {sub}, {k}.task (mailbox), the fault flag",
             f"  periodic tasks (running in): {tasks}"]
    for sec, label in ((1, "part 2, error check of the subordinate and of the layer"),
                       (2, "part 3, the case statement on the command")):
        lines += [f"  {label}:", head]
        for r in table.rows:
            if r.section != sec:
                continue
            fl = "*" if r.fault is None else "|".join(sorted("T" if x else "F" for x in r.fault))
            cmd = "keep" if r.command_down == KEEP else SHORT_CMD[Command(r.command_down)]
            tk = row_tasks(table, r) or "-"
            lines.append(f"{r.rid:>4}  {fmt(r.command, Command):<22} {fmt(r.status, Status):<16} "
                         f"{fmt(r.sub, Status):<28} {fmt(r.task, TaskState):<14} {fl:<6} -> "
                         f"{SHORT[r.next_status]} / {cmd} / {r.action.name}   {tk}   {r.note}")
    post = f"{k}.status, {down}" if table.has_subordinate else f"{k}.status"
    lines.append(f"  part 4, post: {post}, {k}.row, {k}.task; the tasks created and deleted "
                 f"(they run from the next minor frame)")
    return "\n".join(lines)
