"""What every ``pfma`` verb prints: JSON documents, rich tables, progress bars.

The rules, written once here (docs/checkout.md and docs/calibration.md point here):

- ``--json`` on a verb that reads prints ONE JSON document on stdout (``indent=1``), or for
  a stream (``watch``, ``ft``, ``hand``) one compact JSON object per line (JSON lines);
  exit codes do not change with ``--json``.
- Assumption (named once): a non-finite number (NaN, inf: a rate not yet measured, an
  empty percentile) is written as JSON ``null``, so every document is strict JSON that any
  parser reads, not Python's ``NaN`` extension.
- Tables go through :func:`table` / :func:`print_table`: rich writes the column names in bold on a terminal;
  on a pipe or a captured stream (scripts, tests, ``| grep``) the same table is written
  without colour, without trailing blanks and at a fixed width of
  :data:`PLAIN_WIDTH` columns, so the plain output is stable and each row stays on one line.
- Progress: :class:`ProgressBars` draws a bar on a terminal (calibration procedures, the
  checkout); on a pipe the plain step lines are printed as before.
- Exit codes: usage errors 2 (argparse, a bad option value), runtime failures 1 (no
  service, a failed read, a failed check); :data:`USAGE` and :data:`FAILURE`.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import IO, Any

#: exit code of a usage error (argparse uses the same)
USAGE = 2
#: exit code of a runtime failure
FAILURE = 1
#: width of a table written to a pipe or a captured stream (wide enough that a row never wraps)
PLAIN_WIDTH = 240


def add_json_flag(parser, what: str = "one JSON document") -> None:
    parser.add_argument("--json", action="store_true", help=f"print {what} instead of text")


def jsonable(v: Any) -> Any:
    """``v`` with numpy values, paths, tuples and dataclass-like objects turned into JSON
    types; non-finite floats become None (the assumption in the module docstring)."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, int):
        return int(v)
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, set, frozenset)):
        return [jsonable(x) for x in v]
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, bytes):
        return v.hex()
    try:
        import numpy as np
    except ImportError:  # pragma: no cover - numpy is a dependency
        np = None  # type: ignore[assignment]
    if np is not None:
        if isinstance(v, np.ndarray):
            return jsonable(v.tolist())
        if isinstance(v, np.bool_):
            return bool(v)
        if isinstance(v, np.integer):
            return int(v)
        if isinstance(v, np.floating):
            return jsonable(float(v))
    if hasattr(v, "as_dict"):
        return jsonable(v.as_dict())
    if hasattr(v, "__dataclass_fields__"):
        import dataclasses
        return jsonable(dataclasses.asdict(v))
    return str(v)


def print_json(doc: Any, *, line: bool = False, file: IO[str] | None = None) -> None:
    """One JSON document (``line=False``, indented) or one JSON line of a stream."""
    out = file or sys.stdout
    if line:
        print(json.dumps(jsonable(doc), allow_nan=False), file=out, flush=True)
    else:
        print(json.dumps(jsonable(doc), indent=1, allow_nan=False), file=out)


def is_terminal(file: IO[str] | None = None) -> bool:
    f = file or sys.stdout
    try:
        return bool(f.isatty())
    except (AttributeError, ValueError):
        return False


def console(file: IO[str] | None = None, *, stderr: bool = False):
    """A rich Console on ``file`` (default stdout): a terminal's own width and colours, or
    plain text at :data:`PLAIN_WIDTH` columns when ``file`` is not a terminal."""
    from rich.console import Console
    f = file or (sys.stderr if stderr else sys.stdout)
    if is_terminal(f):
        return Console(file=f, highlight=False)
    return Console(file=f, width=PLAIN_WIDTH, color_system=None, force_terminal=False,
                   force_interactive=False, highlight=False, emoji=False, soft_wrap=False)


def table(*columns: str, title: str | None = None, file: IO[str] | None = None):
    """A rich Table with these column headers (a header ending in ``>`` is right-aligned:
    ``"rate>"``). On a narrow terminal the last
    column (the free text: label, provenance) wraps; the others never do."""
    from rich.table import Table
    t = Table(title=title, box=None, header_style="bold" if is_terminal(file) else "",
              show_edge=False, pad_edge=False, title_justify="left", highlight=False)
    for k, c in enumerate(columns):
        right = c.endswith(">")
        last = k == len(columns) - 1
        t.add_column(c.rstrip(">"), justify="right" if right else "left", no_wrap=not last,
                     overflow="fold" if last else "ellipsis")
    return t


def print_table(t, file: IO[str] | None = None) -> None:
    """``t`` on ``file`` (default stdout); on a pipe without the trailing blanks rich pads
    its rows with."""
    f = file or sys.stdout
    if is_terminal(f):
        console(f).print(t, crop=False, overflow="ignore")
        return
    import io
    buf = io.StringIO()
    console(buf).print(t, crop=False, overflow="ignore")
    f.write("".join(line.rstrip() + "\n" for line in buf.getvalue().splitlines()))


def usage_error(verb: str, text: str) -> int:
    """Print ``pfma VERB: text`` on stderr and return the usage exit code (2): for an option
    value argparse cannot check (``--rate 0``, ``--json`` without ``--once``)."""
    print(f"pfma {verb}: {text}", file=sys.stderr)
    return USAGE


class ProgressBars:
    """Progress of a long job (a calibration procedure, a checkout) as a rich bar on a
    terminal. ``update(i, n, text)`` moves the bar (i of n done); ``say(text)`` prints a
    line above it; ``pause()`` takes the bar off the screen before the program reads from
    the keyboard (the next ``update`` draws a new one); ``close()`` at the end.

    Only for a terminal: on a pipe callers keep their plain, line-per-step output.
    """

    def __init__(self, file: IO[str] | None = None) -> None:
        self.file = file or sys.stdout
        self.console = console(self.file)
        self._bar: Any = None
        self._task: Any = None

    def update(self, i: int, n: int, text: str) -> None:
        if self._bar is None:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
            self._bar = Progress(BarColumn(), MofNCompleteColumn(), TextColumn("{task.description}"),
                                 TimeElapsedColumn(), console=self.console, transient=False)
            self._bar.start()
            self._task = self._bar.add_task(text, total=max(1, n))
        self._bar.update(self._task, completed=i, total=max(1, n), description=text)
        if i >= n:
            self.pause()

    def say(self, text: str) -> None:
        (self._bar.console if self._bar is not None else self.console).print(
            text, markup=False, highlight=False, crop=False, overflow="ignore")

    def pause(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = self._task = None

    def close(self) -> None:
        self.pause()
