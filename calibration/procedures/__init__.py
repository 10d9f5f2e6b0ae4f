"""Guided calibration procedures. Each takes a :class:`Context` and returns a
:class:`ProcedureResult`; :func:`run_procedure` runs one, reports it and saves the
new calibration version when it passed."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from calibration.files import Calibration, save_calibration
from calibration.procedures import adc, cae, current, dac_rate, ft, resolver, tach
from calibration.procedures.base import Check, Context, ProcedureResult

#: procedure name -> (function, one-line description)
PROCEDURES: dict[str, tuple[Callable[[Context], ProcedureResult], str]] = {
    "adc": (adc.run, "ADC channels: multi-point gain and offset from reference voltages"),
    "current-offsets": (current.run, "motor-current monitor offsets with the amplifiers disabled"),
    "tach": (tach.run, "tach scale per joint: constant-rate legs, tach volts vs resolver velocity"),
    "resolver": (resolver.run, "resolver zero offsets at known index positions"),
    "dac-rate": (dac_rate.run, "DAC-to-rate gain and offset per joint (zero-drift nulling)"),
    "cae": (cae.run, "CAE hand controller: centre, deadband and span per axis (guided sweep)"),
    "ft-bias": (ft.run_bias, "F/T bias with the sensor unloaded"),
    "ft-payload": (ft.run_payload, "F/T tool payload (mass, centre of mass) and sensor offset from wrist poses"),
    "ft-matrix": (ft.run_matrix, "full 6x6 F/T calibration matrix from known applied loads"),
}

#: what each procedure calibrates and what it does not (and why), said as it starts
SCOPE: dict[str, tuple[str, str]] = {
    "adc": ("gain and offset of the ADC channels the arm does not drive (the CAE inputs and the spares; "
            "--signals chooses), from five reference voltages",
            "the motor-current and rate channels (their sensors are in the loop: current-offsets and tach "
            "calibrate them)"),
    "current-offsets": ("the offset of each motor-current monitor, the amplifiers disabled",
                        "their gain (it needs a known current; the nominal 10 V at full current stays)"),
    "tach": ("each joint's rate channel, the tach's constant and its ADC channel's gain and offset together, "
             "from constant-rate legs of every chosen joint at the pose it is in (default: the six joints)",
             "the gripper (no resolver to compare its tach with); the resolvers (resolver does their zeros)"),
    "resolver": ("each joint's resolver zero at its index position (default: the DH zero of every joint; "
                 "--index gives others)", "the resolver's scale (exact: counts per turn)"),
    "dac-rate": ("each chosen joint's rate command end to end, DAC gain and offset, amplifier and tach as one "
                 "loop (default: shoulder yaw and wrist roll, no gravity torque at the ready pose; others "
                 "with --joints where they are unloaded)",
                 "the DAC's gain apart from the amplifier's (motion cannot tell them apart) and the "
                 "current-limit channels (nothing reads them back)"),
    "cae": ("the CAE stick's centre, deadband, span and sign per axis, from the operator's sweep",
            "the ADC channels under it (run adc first)"),
    "ft-bias": ("the F/T bias, the sensor unloaded", "its drift afterwards (bias again before force work)"),
    "ft-payload": ("the tool's mass and centre of mass and the sensor offset, from nine wrist poses (the "
                   "shoulder and elbow at the ready pose)",
                   "the 6x6 matrix (ft-matrix); it needs the resolver zeros first (the fit uses the arm's angles)"),
    "ft-matrix": ("the full 6x6 matrix and the bias, from known loads on the fixture", "the tool payload (ft-payload)"),
}


def _scope_lines(name: str, ctx: Context) -> list[str]:
    will, will_not = SCOPE[name]
    lines = [f"   calibrates: {will}", f"   does not: {will_not}"]
    chosen = [f"{k} {', '.join(map(str, v))}" for k in ("joints", "signals") if (v := ctx.options.get(k))]
    if chosen:
        lines.append("   this run: " + "; ".join(chosen))
    return lines


def run_procedure(name: str, ctx: Context, save_to: str | Path | None = None,
                  save_failed: bool = False) -> ProcedureResult:
    """Run procedure ``name``; show its report; save a new version of ``save_to`` when it
    passed (or ``save_failed``)."""
    try:
        fn = PROCEDURES[name][0]
    except KeyError:
        from pfma.errors import CalibrationError
        raise CalibrationError(f"unknown procedure {name!r}; known: {', '.join(PROCEDURES)}") from None
    ctx.operator.show(f"== {name}: {PROCEDURES[name][1]}")
    for line in _scope_lines(name, ctx):
        ctx.operator.show(line)
    res = fn(ctx)
    ctx.operator.show(res.report())
    if save_to is not None and res.calibration is not None and (res.passed or save_failed):
        res.saved = save_calibration(res.calibration, save_to, rack=ctx.rack)
        ctx.operator.show(f"saved {res.saved.describe()}, hash {res.saved.hash().hex()}")
    elif save_to is not None:
        ctx.operator.show(f"not saved: the procedure failed; {save_to} is unchanged")
    return res


__all__ = ["PROCEDURES", "run_procedure", "Context", "ProcedureResult", "Check", "Calibration"]
