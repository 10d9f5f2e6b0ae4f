"""Calibration files and procedures from the command line: the logic of ``pfma calibrate``
(:mod:`tools.cli.calibrate`, whose help says what each does): the file's text (every
conversion with its provenance, the CAE and F/T blocks), its history and the diff of two
versions, each also as a JSON document; a procedure's options read and checked, the session
it runs in (the simulated rack or a running service) and the run itself. The verb parses
the options and prints (its tables and progress bars are :mod:`tools.cli.output`'s)."""

from __future__ import annotations

from pathlib import Path

from pfma.errors import CalibrationError

#: the columns of ``pfma calibrate show``'s table (a name ending in ``>`` is right-aligned)
CHANNEL_COLUMNS = ("signal", "dev", "units", "scale>", "offset>", "method / date / operator / rms")
#: the columns of ``pfma calibrate history``'s table
HISTORY_COLUMNS = ("#", "created", "hash", "file", "methods")


def rack_of(rack: str | None):
    """``--rack``: fake (or none, or default) the simulated rack's configuration, else a TOML."""
    from pfma.rack import load_rack
    return load_rack(None if rack in (None, "fake", "default") else rack)


def fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(fmt(x) for x in v) + "]" if len(v) <= 6 and not any(
            isinstance(x, list) for x in v) else f"({len(v)} rows)"
    return str(v)


# -- the file verbs -------------------------------------------------------------------------------
def init_file(rack: str | None, path: Path, operator: str) -> str:
    """``pfma calibrate init``: version 0 from the rack's nominal scales; the line saying so.

    :raises CalibrationError: the file exists
    """
    from calibration import files
    config = rack_of(rack)
    if path.exists():
        raise CalibrationError(f"{path} exists; procedures update it (history is kept)")
    cal = files.save_calibration(files.nominal_calibration(config, operator), path, rack=config)
    return f"wrote {cal.describe()}"


def show_doc(path: Path, cal) -> dict:
    """``pfma calibrate show --json``."""
    from calibration import files
    return {"file": str(path), "version": cal.version, "created": cal.created,
            "hash": files.calibration_hash(cal).hex(), "calibration": cal.data}


def show_header(cal) -> str:
    """The line above ``pfma calibrate show``'s table."""
    from calibration.files import calibration_hash
    return (f"calibration {cal.describe()}, created {cal.created}, {cal.data['software_version']}, "
            f"hash {calibration_hash(cal).hex()}")


def channel_rows(cal) -> list[tuple[str, ...]]:
    """``pfma calibrate show``'s table: one row (:data:`CHANNEL_COLUMNS`) a channel."""
    rows = []
    for sig, e in cal.channels.items():
        p = e["provenance"]
        rms = p.get("rms_residual")
        rows.append((sig, e["device"], e["units"], f"{e['scale']:.6g}", f"{e['offset']:.6g}",
                     f"{p['method']} / {p['date']} / {p['operator']}" + (f" / {rms:.3g}" if rms is not None else "")))
    return rows


def show_tail(cal) -> list[str]:
    """The lines under ``pfma calibrate show``'s table: the CAE hand controller, the F/T sensor."""
    lines = []
    if cal.cae:
        lines.append("CAE hand controller:")
        for axis, e in cal.cae.items():
            lines.append(f"  {axis:6s} centre {e['centre_v']:+.4f} V  deadband {e['deadband_v']:.4f} V  "
                         f"span {e['span_v']:.4f} V  sign {e['sign']:+d}  ({e['provenance']['method']}, "
                         f"{e['provenance']['date']})")
    if cal.ft:
        ft = cal.ft
        lines += ["F/T sensor:", f"  bias counts {fmt(ft['bias_counts'])}", "  matrix (counts -> N, N*m):"]
        lines += ["    " + " ".join(f"{x:+.6g}" for x in row) for row in ft["matrix"]]
        lines.append(f"  payload {ft['payload_mass_kg']:.4f} kg at {fmt(ft['payload_com_m'])} m")
        for k, p in ft.get("provenance", {}).items():
            if isinstance(p, dict) and "method" in p:
                lines.append(f"  {k}: {p['method']} / {p['date']} / {p.get('operator', '')}")
    return lines


def _methods(cal) -> list[str]:
    """The methods a calibration version's channels were calibrated by, sorted."""
    return sorted({e["provenance"]["method"] for e in cal.channels.values()})


def history_of(path: Path) -> list:
    """Every kept version of the file, oldest first.

    :raises CalibrationError: none
    """
    from calibration import files
    hist = files.history(path)
    if not hist:
        raise CalibrationError(f"no calibration at {path}")
    return hist


def history_doc(hist: list) -> list[dict]:
    """``pfma calibrate history --json``."""
    return [{"version": c.version, "created": c.created, "hash": c.hash().hex(), "path": c.path,
             "methods": _methods(c)} for c in hist]


def history_rows(hist: list) -> list[tuple[str, ...]]:
    """``pfma calibrate history``'s table: one row (:data:`HISTORY_COLUMNS`) a version."""
    return [(f"v{c.version}", c.created, c.hash().hex(), str(c.path), "; ".join(_methods(c))) for c in hist]


def diff_versions(path: Path, v_from: int | None, v_to: int | None) -> tuple:
    """The two versions ``pfma calibrate diff`` compares: ``--from``/``--to`` (``--to``
    default the current one, ``--from`` default the one before it), else the last two."""
    from calibration import files
    hist = files.history(path)
    if v_from is not None or v_to is not None:
        b = files.load_version(path, v_to) if v_to is not None else files.load_calibration(path)
        a = files.load_version(path, v_from) if v_from is not None else hist[max(0, hist.index(
            next(c for c in hist if c.version == b.version)) - 1)]
        return a, b
    if len(hist) < 2:
        raise CalibrationError(f"{path}: only {len(hist)} version(s); nothing to compare")
    return hist[-2], hist[-1]


def diff_lines(a, b, rows: list[dict]) -> list[str]:
    """``pfma calibrate diff``: what changed between versions ``a`` and ``b`` (``rows`` from
    :func:`calibration.files.diff`)."""
    lines = [f"diff v{a.version} -> v{b.version}: {len(rows)} change(s)"]
    for r in rows:
        ch = r["change"]
        lines.append(f"  {r['entry']:44s} {fmt(r['old']):>14s} -> {fmt(r['new']):<14s}"
                     + (f" ({ch:+.4g})" if isinstance(ch, float) else "")
                     + (f"  [{r['method']}]" if r.get("method") else ""))
    return lines


# -- the procedures -------------------------------------------------------------------------------
def procedure_options(joints: str | None, signals: str | None, index: str | None) -> dict:
    """The procedure's options from ``--joints``, ``--signals`` and ``--index``."""
    options: dict = {}
    if joints:
        options["joints"] = [j.strip() for j in joints.split(",") if j.strip()]
    if signals:
        options["signals"] = [s.strip() for s in signals.split(",") if s.strip()]
    if index:
        try:
            options["index_rad"] = {k.strip(): float(v) for k, v in (kv.split("=") for kv in index.split(","))}
        except ValueError:
            raise CalibrationError(f"--index {index!r}: expected JOINT=RAD,... e.g. wrist_roll=0.5") from None
    return options


def check_names(rack, options: dict) -> None:
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


def _session(buffer: str | None, rack: str | None, interactive: bool, cal, out, sim_errors: int = 0,
             sim_faults: tuple[str, ...] = ()) -> tuple:
    """The session, operator and (simulated rack only) rig a procedure runs with:
    ``buffer`` a running service and the person at the terminal, else the simulated rack,
    with the imperfections of seed ``sim_errors`` (sim/errors.py) and the faults
    ``sim_faults`` (sim/faults.py specs, checked by the verb) in force from the start."""
    from calibration.session import ConsoleOperator, LiveSession, SimSession
    if buffer:
        session = LiveSession(buffer, rack=None if rack in (None, "fake", "default") else rack)
        return session, ConsoleOperator(out, interactive=interactive), None
    from sim.calibration import CalibrationRig, SimOperator
    from sim.errors import seeded
    from sim.faults import FaultSet
    rig = CalibrationRig(calibration=cal)
    rig.world.sim.set_errors(seeded(sim_errors, rig.world.rack_config))
    faults = FaultSet(rig.world)
    said = [faults.inject(spec, since=rig.clock.now()).description for spec in sim_faults]
    session = SimSession(rig)
    operator = SimOperator(rig.world, out=out)
    operator.show = lambda text: print(text, file=out, flush=True)
    rack_is = f"simulated rack with the imperfections of seed {sim_errors}" if sim_errors else "simulated rack"
    print(f"pfma calibrate: {rack_is}, simulated time, simulated operator", file=out)
    for text in said:
        print(f"pfma calibrate: simulated fault: {text}", file=out)
    return session, operator, rig


def run_on(what: str, args, config, cal, path: Path, plot_dir: Path, options: dict, out, bars=None) -> int:
    """Run procedure ``what`` on calibration ``cal`` of rack ``config``, saving to ``path``:
    on ``args.buffer``'s service with the person at the terminal, else on the simulated rack
    (``args`` has the verb's ``buffer``, ``rack``, ``non_interactive``, ``operator`` and
    ``save_failed``). ``bars`` (a terminal's :class:`tools.cli.output.ProgressBars`, or None
    for the plain ``[###...]`` lines) shows the progress. 0 when it passed, else 1."""
    from calibration.procedures import Context, run_procedure
    session, operator, rig = _session(args.buffer, args.rack, not args.non_interactive, cal, out,
                                      getattr(args, "sim_errors", 0), tuple(getattr(args, "sim_fault", None) or ()))
    if bars is not None:
        _draw_progress(operator, bars)
    try:
        ctx = Context(session, operator, cal, config, plot_dir, operator_name=args.operator, options=options)
        res = run_procedure(what, ctx, save_to=path, save_failed=args.save_failed)
    finally:
        if bars is not None:
            bars.close()
        session.close()
        if rig is not None:
            rig.close()
    return 0 if res.passed else 1


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
