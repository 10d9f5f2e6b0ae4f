"""Motor-current monitor offsets with the amplifiers disabled.

With the service SAFE (DAC outputs disconnected, current limits 0 V, brakes set) the
motor currents are zero, so whatever each current-monitor channel reads is its offset.
The gain (10 I / I_max, pfma-model 8.4) is not touched: it needs a current reference.

Tolerances (stated): the offset is found to 1 LSB of the ADC (4.9 mV: the 12-bit
converter's quantization; better only with noise to dither it); the
procedure fails when a channel reads more than 0.2 V (the amplifier is not disabled or
the monitor is faulty) or its noise exceeds 3 LSB rms while the arm is still.
"""

from __future__ import annotations

import numpy as np

from calibration import fit as F
from calibration.plot import Panel, Series, plot_fit
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from bit3.layout import ServiceState
from pfma.errors import CalibrationError

NAME = "current-offsets"
LSB_V = 20.0 / 4096
MAX_OFFSET_V = 0.2
MAX_NOISE_V = 3 * LSB_V


def run(ctx: Context) -> ProcedureResult:
    signals = list(ctx.options.get("signals") or [c.signal for c in ctx.rack.channels()
                                                  if c.device == "adc" and c.quantity == "motor_current"])
    res = ProcedureResult(NAME, tolerances={"resolution": f"{LSB_V * 1e3:.1f} mV",
                                            "offset": f"<= {MAX_OFFSET_V} V", "noise": f"<= {MAX_NOISE_V * 1e3:.1f} mV rms"})
    ctx.progress(0, 2, "amplifiers disabled?")
    state = ctx.session.read()["service_state"]
    if state == ServiceState.ARMED:
        raise CalibrationError("the service is ARMED: disarm (amplifiers disabled) before nulling current offsets")
    ctx.operator.prompt("current.disable", "Amplifiers disabled (service SAFE, current limits 0 V, brakes "
                        "set); keep the arm still")
    ctx.session.wait(0.05)
    ctx.progress(1, 2, "averaging 0.5 s")
    layout = ctx.session.layout
    slots = np.array([layout.slot("adc", s) for s in signals])
    smp = ctx.session.collect(ctx.options.get("average_s", 0.5), ("adc_volts", "service_state"), key="t_adc_s")
    if np.any(smp["service_state"] == ServiceState.ARMED):
        raise CalibrationError("the service armed while the current offsets were being measured")
    volts = smp["adc_volts"][:, slots]
    prev = ctx.calibration
    series = []
    for i, sig in enumerate(signals):
        f = F.mean_offset(volts[:, i], what=f"current offset {sig}")
        scale = float(prev.channel(sig)["scale"])
        res.fits[sig] = f
        res.channels[sig] = {"offset": -scale * f["mean"],
                             "provenance": ctx.provenance("current offset, amplifiers disabled", f,
                                                          offset_v=f["mean"], samples=len(volts))}
        res.found[sig] = {"offset_v": f["mean"]}
        res.check(f"{sig} offset", f["mean"], MAX_OFFSET_V, "V")
        res.check(f"{sig} noise rms", f.rms, MAX_NOISE_V, "V")
        series.append(Series(np.full(len(volts), i), volts[:, i], "points", "blue"))
    ctx.progress(2, 2, "done")
    res.plots.append(plot_fit(plot_name(ctx, NAME, "offsets"), [
        Panel(series, "monitor volts with the amplifiers disabled (every sample)", "motor-current monitor",
              "monitor (V)", zero_line=True, xticks=[s.removesuffix("_motor_current") for s in signals])],
        title="Motor-current monitor offsets"))
    return finish(ctx, res)
