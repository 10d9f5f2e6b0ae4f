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

from pfma.errors import CalibrationError

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
    return p


def _rack(args):
    from pfma.rack import load_rack
    return load_rack(None if args.rack in (None, "fake", "default") else args.rack)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]" if len(v) <= 6 and not any(
            isinstance(x, list) for x in v) else f"({len(v)} rows)"
    return str(v)


def _show(cal, out) -> None:
    from calibration.files import calibration_hash
    print(f"calibration {cal.describe()}, created {cal.created}, {cal.data['software_version']}, "
          f"hash {calibration_hash(cal).hex()}", file=out)
    from tools.cli.output import print_table, table
    t = table("signal", "dev", "units", "scale>", "offset>", "method / date / operator / rms", file=out)
    for sig, e in cal.channels.items():
        p = e["provenance"]
        rms = p.get("rms_residual")
        t.add_row(sig, e["device"], e["units"], f"{e['scale']:.6g}", f"{e['offset']:.6g}",
                  f"{p['method']} / {p['date']} / {p['operator']}" + (f" / {rms:.3g}" if rms is not None else ""))
    print_table(t, out)
    if cal.cae:
        print("CAE hand controller:", file=out)
        for axis, e in cal.cae.items():
            print(f"  {axis:6s} centre {e['centre_v']:+.4f} V  deadband {e['deadband_v']:.4f} V  "
                  f"span {e['span_v']:.4f} V  sign {e['sign']:+d}  ({e['provenance']['method']}, "
                  f"{e['provenance']['date']})", file=out)
    if cal.ft:
        ft = cal.ft
        print("F/T sensor:", file=out)
        print(f"  bias counts {_fmt(ft['bias_counts'])}", file=out)
        print("  matrix (counts -> N, N*m):", file=out)
        for row in ft["matrix"]:
            print("    " + " ".join(f"{x:+.6g}" for x in row), file=out)
        print(f"  payload {ft['payload_mass_kg']:.4f} kg at {_fmt(ft['payload_com_m'])} m", file=out)
        for k, p in ft.get("provenance", {}).items():
            if isinstance(p, dict) and "method" in p:
                print(f"  {k}: {p['method']} / {p['date']} / {p.get('operator', '')}", file=out)


def _file_verb(args, out) -> int:
    args.json = getattr(args, "json", False)  # callers that build the namespace themselves
    if args.json and args.what == "init":
        print("pfma calibrate: --json is for show, history and diff (init writes a file)", file=sys.stderr)
        return 2
    return _FILE_VERB_RUN.get(args.what, _file_diff)(args, Path(args.file), out)


def _file_init(args, path: Path, out) -> int:
    """``pfma calibrate init``: version 0 from the rack's nominal scales."""
    from calibration import files
    rack = _rack(args)
    if path.exists():
        raise CalibrationError(f"{path} exists; procedures update it (history is kept)")
    cal = files.save_calibration(files.nominal_calibration(rack, args.operator), path, rack=rack)
    print(f"wrote {cal.describe()}", file=out)
    return 0


def _file_show(args, path: Path, out) -> int:
    """``pfma calibrate show``: every conversion with its provenance."""
    from calibration import files
    from tools.cli.output import print_json
    cal = files.load_calibration(path)
    if args.json:
        print_json({"file": str(path), "version": cal.version, "created": cal.created,
                    "hash": files.calibration_hash(cal).hex(), "calibration": cal.data}, file=out)
        return 0
    _show(cal, out)
    return 0


def _methods(cal) -> list[str]:
    """The methods a calibration version's channels were calibrated by, sorted."""
    return sorted({e["provenance"]["method"] for e in cal.channels.values()})


def _file_history(args, path: Path, out) -> int:
    """``pfma calibrate history``: every kept version with date, hash and methods."""
    from calibration import files
    from tools.cli.output import print_json, print_table, table
    hist = files.history(path)
    if not hist:
        raise CalibrationError(f"no calibration at {path}")
    if args.json:
        print_json([{"version": c.version, "created": c.created, "hash": c.hash().hex(), "path": c.path,
                     "methods": _methods(c)}
                    for c in hist], file=out)
        return 0
    t = table("#", "created", "hash", "file", "methods", file=out)
    for c in hist:
        t.add_row(f"v{c.version}", c.created, c.hash().hex(), str(c.path), "; ".join(_methods(c)))
    print_table(t, out)
    return 0


def _diff_versions(args, path: Path) -> tuple:
    """The two versions ``pfma calibrate diff`` compares: ``--from``/``--to`` (``--to``
    default the current one, ``--from`` default the one before it), else the last two."""
    from calibration import files
    hist = files.history(path)
    if args.v_from is not None or args.v_to is not None:
        b = files.load_version(path, args.v_to) if args.v_to is not None else files.load_calibration(path)
        a = files.load_version(path, args.v_from) if args.v_from is not None else hist[max(0, hist.index(
            next(c for c in hist if c.version == b.version)) - 1)]
        return a, b
    if len(hist) < 2:
        raise CalibrationError(f"{path}: only {len(hist)} version(s); nothing to compare")
    return hist[-2], hist[-1]


def _file_diff(args, path: Path, out) -> int:
    """``pfma calibrate diff``: what changed between two versions."""
    from calibration import files
    from tools.cli.output import print_json
    a, b = _diff_versions(args, path)
    rows = files.diff(a, b)
    if args.json:
        print_json({"file": str(path), "from": a.version, "to": b.version, "changes": rows}, file=out)
        return 0
    print(f"diff v{a.version} -> v{b.version}: {len(rows)} change(s)", file=out)
    for r in rows:
        ch = r["change"]
        print(f"  {r['entry']:44s} {_fmt(r['old']):>14s} -> {_fmt(r['new']):<14s}"
              + (f" ({ch:+.4g})" if isinstance(ch, float) else "")
              + (f"  [{r['method']}]" if r.get("method") else ""), file=out)
    return 0


#: the file verbs (anything else reaching _file_verb is a diff, as before)
_FILE_VERB_RUN = {"init": _file_init, "show": _file_show, "history": _file_history, "diff": _file_diff}


def run(args, out=None) -> int:
    out = out or sys.stdout
    if args.what in FILE_VERBS:
        return _file_verb(args, out)
    if getattr(args, "json", False):
        print(f"pfma calibrate: --json is for show, history and diff, not for the {args.what} procedure "
              f"(its report is the calibration file: pfma calibrate show --json)", file=sys.stderr)
        return 2
    from calibration import files
    rack = _rack(args)
    path = Path(args.file)
    options = _options(args)
    _check_names(rack, options)  # before anything is written
    if not path.exists():  # version 0 = the nominal scales, so history starts there
        files.save_calibration(files.nominal_calibration(rack, args.operator), path, rack=rack)
        print(f"pfma calibrate: created {path} (version 0, nominal scales)", file=out)
    cal = files.load_calibration(path, rack)
    plot_dir = Path(args.plots) if args.plots else path.parent / (path.stem + "-plots")
    return _run_procedure(args, rack, cal, path, plot_dir, options, out)


def _options(args) -> dict:
    """The procedure's options from ``--joints``, ``--signals`` and ``--index``."""
    options: dict = {}
    if args.joints:
        options["joints"] = [j.strip() for j in args.joints.split(",") if j.strip()]
    if args.signals:
        options["signals"] = [s.strip() for s in args.signals.split(",") if s.strip()]
    if args.index:
        try:
            options["index_rad"] = {k.strip(): float(v) for k, v in (kv.split("=") for kv in args.index.split(","))}
        except ValueError:
            raise CalibrationError(f"--index {args.index!r}: expected JOINT=RAD,... e.g. wrist_roll=0.5") from None
    return options


def _session(args, cal, out) -> tuple:
    """The session, operator and (simulated rack only) rig a procedure runs with:
    ``--buffer`` a running service and the person at the terminal, else the simulated rack."""
    from calibration.session import ConsoleOperator, LiveSession, SimSession
    if args.buffer:
        session = LiveSession(args.buffer, rack=None if args.rack in (None, "fake", "default") else args.rack)
        return session, ConsoleOperator(out, interactive=not args.non_interactive), None
    from sim.calibration import CalibrationRig, SimOperator
    rig = CalibrationRig(calibration=cal)
    session = SimSession(rig)
    operator = SimOperator(rig.world, out=out)
    operator.show = lambda text: print(text, file=out, flush=True)
    print("pfma calibrate: simulated rack, simulated time, simulated operator", file=out)
    return session, operator, rig


def _run_procedure(args, rack, cal, path: Path, plot_dir: Path, options: dict, out) -> int:
    """Run procedure ``args.what`` (progress bars on a terminal); 0 when it passed, else 1."""
    from calibration.procedures import Context, run_procedure
    from tools.cli.output import ProgressBars, is_terminal
    session, operator, rig = _session(args, cal, out)
    bars = None
    if is_terminal(out):  # a bar on a terminal; a pipe keeps the plain [###...] lines
        bars = ProgressBars(out)
        _draw_progress(operator, bars)
    try:
        ctx = Context(session, operator, cal, rack, plot_dir, operator_name=args.operator, options=options)
        res = run_procedure(args.what, ctx, save_to=path, save_failed=args.save_failed)
    finally:
        if bars is not None:
            bars.close()
        session.close()
        if rig is not None:
            rig.close()
    return 0 if res.passed else 1


def _check_names(rack, options: dict) -> None:
    """Refuse an unknown ``--signals`` or ``--joints`` name with the closest known ones
    (one message, exit 1), before anything runs."""
    from pfma.errors import did_you_mean
    signals = [c.signal for c in rack.channels()]
    joints = sorted({c.joint for c in rack.channels() if c.joint})
    for s in options.get("signals", []):
        if s not in signals:
            raise CalibrationError(f"--signals: no channel named {s!r} in rack {rack.name}"
                                   + (did_you_mean(s, signals) or "; `pfma channels` lists them"))
    for j in options.get("joints", []):
        if j not in joints:
            raise CalibrationError(f"--joints: no joint named {j!r} in rack {rack.name}"
                                   + (did_you_mean(j, joints) or f"; joints: {', '.join(joints)}"))


def _draw_progress(operator, bars) -> None:
    """The operator's progress becomes ``bars``; its lines print above the bar, and the bar
    leaves the screen while the operator is asked something (the keyboard is read)."""
    show, prompt = operator.show, operator.prompt
    operator.progress = bars.update
    operator.show = lambda text: bars.say(text) if bars._bar is not None else show(text)

    def asked(step, text, **params):
        bars.pause()
        return prompt(step, text, **params)
    operator.prompt = asked
