"""``pfma calibrate``: guided calibration procedures and calibration files.

Procedures (each with progress, operator prompts, pass/fail against its stated
tolerances, a least-squares fit with residuals, a PNG plot and the drift against the
previous calibration; a passing run saves the next version of the file)::

    pfma calibrate adc|current-offsets|tach|resolver|dac-rate|cae|ft-bias|ft-payload|ft-matrix
                   [--rack fake] [--buffer NAME] [--file CAL] [--operator NAME] [--non-interactive]

``--rack fake`` (default when no ``--buffer`` is given) runs on the simulated rack in
simulated time, with a simulated operator; ``--buffer NAME`` attaches to a running
service (``pfma serve``) and asks a person at the terminal.

Files::

    pfma calibrate show [--file CAL]             every channel's conversion and provenance
    pfma calibrate diff [--file CAL] [--from A] [--to B]   (default: previous vs current)
    pfma calibrate history [--file CAL]          every kept version with date, operator, hash
    pfma calibrate init [--file CAL]             version 0 from the rack's nominal scales
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tools import calibrate as calib
from tools.cli.args import add_sim_errors
from tools.cli.output import print_json, print_table, table

DEFAULT_FILE = "pfma-calibration.json"
FILE_VERBS = ("show", "diff", "history", "init")


def add_parser(sub):
    from calibration.procedures import PROCEDURES
    p = sub.add_parser("calibrate", help="guided calibration procedures; show/diff/history of calibration files",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=list(PROCEDURES) + list(FILE_VERBS), metavar="PROCEDURE|show|diff|history|init",
                   help="procedure (" + ", ".join(PROCEDURES) + ") or file command")
    p.add_argument("--from", dest="v_from", type=int, default=None, metavar="A", help="diff: older version")
    p.add_argument("--to", dest="v_to", type=int, default=None, metavar="B", help="diff: newer version (default current)")
    p.add_argument("--rack", default=None, help="fake (simulated rack) or a rack TOML (default: fake)")
    p.add_argument("--buffer", default=None, help="Bit3 buffer of a running service (live rack)")
    p.add_argument("--file", default=DEFAULT_FILE, help=f"calibration file (default {DEFAULT_FILE})")
    p.add_argument("--operator", default="", help="operator name for the provenance")
    p.add_argument("--non-interactive", action="store_true", help="do not wait for the operator at prompts")
    p.add_argument("--plots", default=None, help="directory for PNG plots (default: next to the file)")
    p.add_argument("--joints", default=None, help="comma-separated joints (tach, resolver, dac-rate)")
    p.add_argument("--signals", default=None, help="comma-separated ADC signals (adc, current-offsets)")
    p.add_argument("--index", default=None, metavar="JOINT=RAD,...",
                   help="resolver: known index positions (default: the DH zero of every joint, assumed)")
    p.add_argument("--save-failed", action="store_true", help="save the result even when a check failed")
    p.add_argument("--json", action="store_true", help="show, history, diff: one JSON document")
    add_sim_errors(p)
    p.add_argument("--sim-fault", action="append", default=[], metavar="SPEC",
                   help="simulated rack only: a fault in force from the start, any spec of `pfma fault list` "
                        "(as pfma checkout --sim-fault); repeatable; docs/faults.md")
    return p


def _print_lines(lines: list[str], out) -> int:
    for line in lines:
        print(line, file=out)
    return 0


def _table(columns: tuple[str, ...], rows: list[tuple[str, ...]], out) -> None:
    t = table(*columns, file=out)
    for row in rows:
        t.add_row(*row)
    print_table(t, out)


def _file_verb(args, out) -> int:
    args.json = getattr(args, "json", False)  # callers that build the namespace themselves
    if args.json and args.what == "init":
        print("pfma calibrate: --json is for show, history and diff (init writes a file)", file=sys.stderr)
        return 2
    return _FILE_VERB_RUN.get(args.what, _file_diff)(args, Path(args.file), out)


def _file_init(args, path: Path, out) -> int:
    """``pfma calibrate init``: version 0 from the rack's nominal scales."""
    return _print_lines([calib.init_file(args.rack, path, args.operator)], out)


def _file_show(args, path: Path, out) -> int:
    """``pfma calibrate show``: every conversion with its provenance."""
    from calibration import files
    cal = files.load_calibration(path)
    if args.json:
        print_json(calib.show_doc(path, cal), file=out)
        return 0
    print(calib.show_header(cal), file=out)
    _table(calib.CHANNEL_COLUMNS, calib.channel_rows(cal), out)
    return _print_lines(calib.show_tail(cal), out)


def _file_history(args, path: Path, out) -> int:
    """``pfma calibrate history``: every kept version with date, hash and methods."""
    hist = calib.history_of(path)
    if args.json:
        print_json(calib.history_doc(hist), file=out)
        return 0
    _table(calib.HISTORY_COLUMNS, calib.history_rows(hist), out)
    return 0


def _file_diff(args, path: Path, out) -> int:
    """``pfma calibrate diff``: what changed between two versions."""
    from calibration import files
    a, b = calib.diff_versions(path, args.v_from, args.v_to)
    rows = files.diff(a, b)
    if args.json:
        print_json({"file": str(path), "from": a.version, "to": b.version, "changes": rows}, file=out)
        return 0
    return _print_lines(calib.diff_lines(a, b, rows), out)


#: the file verbs (anything else reaching _file_verb is a diff, as before)
_FILE_VERB_RUN = {"init": _file_init, "show": _file_show, "history": _file_history, "diff": _file_diff}


def _sim_mistake(args, rack) -> str:
    """``--sim-errors``/``--sim-fault`` with a running service, or a fault spec that is not
    one: the message ("" when none), before anything is written."""
    from pfma.errors import ConfigError
    from sim.faults import parse_fault
    faults = getattr(args, "sim_fault", None) or []
    if args.buffer and (faults or getattr(args, "sim_errors", 0)):
        return "--sim-errors and --sim-fault need the simulated rack (no --buffer)"
    for spec in faults:
        try:
            parse_fault(spec, rack)
        except ConfigError as err:
            return f"--sim-fault {err}"
    return ""


def run(args, out=None) -> int:
    out = out or sys.stdout
    if args.what in FILE_VERBS:
        return _file_verb(args, out)
    if getattr(args, "json", False):
        print(f"pfma calibrate: --json is for show, history and diff, not for the {args.what} procedure "
              f"(its report is the calibration file: pfma calibrate show --json)", file=sys.stderr)
        return 2
    from calibration import files
    from tools.cli.output import ProgressBars, is_terminal
    rack = calib.rack_of(args.rack)
    why = _sim_mistake(args, rack)
    if why:
        print(f"pfma calibrate: {why}", file=sys.stderr)
        return 2
    path = Path(args.file)
    options = calib.procedure_options(args.joints, args.signals, args.index)
    calib.check_names(rack, options)  # before anything is written
    if not path.exists():  # version 0 = the nominal scales, so history starts there
        files.save_calibration(files.nominal_calibration(rack, args.operator), path, rack=rack)
        print(f"pfma calibrate: created {path} (version 0, nominal scales)", file=out)
    cal = files.load_calibration(path, rack)
    plot_dir = Path(args.plots) if args.plots else path.parent / (path.stem + "-plots")
    # a bar on a terminal; a pipe keeps the plain [###...] lines
    bars = ProgressBars(out) if is_terminal(out) else None
    return calib.run_on(args.what, args, rack, cal, path, plot_dir, options, out, bars)
