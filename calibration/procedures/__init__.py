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
    res = fn(ctx)
    ctx.operator.show(res.report())
    if save_to is not None and res.calibration is not None and (res.passed or save_failed):
        res.saved = save_calibration(res.calibration, save_to, rack=ctx.rack)
        ctx.operator.show(f"saved {res.saved.describe()}, hash {res.saved.hash().hex()}")
    elif save_to is not None:
        ctx.operator.show(f"not saved: the procedure failed; {save_to} is unchanged")
    return res


__all__ = ["PROCEDURES", "run_procedure", "Context", "ProcedureResult", "Check", "Calibration"]
