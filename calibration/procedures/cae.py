"""CAE hand controller: centre, deadband and span per axis from a guided sweep.

1. The operator lets go of the stick several times (deadman released); each rest is
   averaged (pfma-model 8.5: the null is the average of 0.5 s with the deadman
   released; here 0.25 s per rest). The centre is the mean of the rests.
2. The deadband is ``max(MIN_DEADBAND_V, 1.5 x the largest rest deviation + 3 LSB)``:
   wherever the spring leaves the stick, the axis reads 0.
3. The operator pushes each axis fully in its positive direction (up, forward, right,
   +yaw, +pitch, +roll, as the seed labels them) and then fully negative; the span is
   the smaller of the two deflections from the centre (so |u| = 1 is reachable both
   ways), and the polarity is checked: a negative reading for the positive push flips
   the axis's sign.

Volts are the raw ADC volts the service feeds the CAE driver.

Tolerances (stated): centre to +-10 mV, span to +-20 mV; fail when a deflection is
under 5 V (not full), the two sides differ by more than 25 %, the deadband exceeds
1.5 V (the stick does not return) or a rest is noisy (> 3 LSB rms).
"""

from __future__ import annotations

import numpy as np

from calibration.plot import Panel, Series, plot_fit
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from drivers.crl.cae import CAE_AXES

NAME = "cae"
LSB_V = 20.0 / 4096
MIN_DEADBAND_V = 0.2
MAX_DEADBAND_V = 1.5
MIN_DEFLECTION_V = 5.0
MAX_ASYMMETRY = 0.25
RESTS = 5


def run(ctx: Context) -> ProcedureResult:
    layout = ctx.session.layout
    sigs = [s for s, _, _ in CAE_AXES]
    slots = np.array([layout.slot("adc", s) for s in sigs])
    n_rest = int(ctx.options.get("rests", RESTS))
    n_steps = n_rest + 2 * len(sigs)
    res = ProcedureResult(NAME, tolerances={"centre": "+-10 mV", "span": "+-20 mV",
                                            "deflection": f">= {MIN_DEFLECTION_V} V",
                                            "deadband": f"<= {MAX_DEADBAND_V} V"})
    rests, noise = [], []
    for k in range(n_rest):
        ctx.progress(k, n_steps, f"rest {k + 1}/{n_rest}")
        ctx.operator.prompt("cae.release", f"Move the stick anywhere, then let go (deadman released) "
                            f"[{k + 1}/{n_rest}]", k=k)
        ctx.session.wait(0.05)
        smp = ctx.session.collect(0.25, ("adc_volts",), key="t_adc_s")
        v = smp["adc_volts"][:, slots]
        rests.append(v.mean(axis=0))
        noise.append(v.std(axis=0))
    rests = np.array(rests)
    centre = rests.mean(axis=0)
    dev = np.max(np.abs(rests - centre), axis=0)
    deadband = np.maximum(MIN_DEADBAND_V, 1.5 * dev + 3 * LSB_V)
    ext = {}
    step = n_rest
    for i, (sig, axis, _) in enumerate(CAE_AXES):
        for d in (+1, -1):
            ctx.progress(step, n_steps, f"{sig} {'+' if d > 0 else '-'}")
            step += 1
            ctx.operator.prompt("cae.deflect", f"Push {sig} fully {'positive' if d > 0 else 'negative'} "
                                f"({'first' if d > 0 else 'second'} direction of the label) and hold",
                                axis=axis, signal=sig, direction=d)
            ctx.session.wait(0.05)
            smp = ctx.session.collect(0.1, ("adc_volts",), key="t_adc_s")
            ext[(axis, d)] = float(smp["adc_volts"][:, slots[i]].mean())
    ctx.operator.prompt("cae.release", "Let go of the stick", k=n_rest)
    ctx.progress(n_steps, n_steps, "done")
    cae_update = {}
    defaults = {axis: sign for _, axis, sign in CAE_AXES}
    prev = ctx.calibration.cae or {}
    pts: dict[str, list[float]] = {"plus": [], "minus": []}
    for i, (sig, axis, _) in enumerate(CAE_AXES):
        plus, minus = ext[(axis, 1)] - centre[i], ext[(axis, -1)] - centre[i]
        span = float(min(abs(plus), abs(minus)))
        polarity = 1 if plus > 0 else -1
        sign = defaults[axis] * polarity
        cae_update[axis] = {
            "centre_v": float(centre[i]), "deadband_v": float(deadband[i]), "span_v": span, "sign": sign,
            "provenance": ctx.provenance("CAE guided sweep", None, signal=sig,
                                         rests_v=rests[:, i], plus_v=ext[(axis, 1)], minus_v=ext[(axis, -1)],
                                         residuals=(rests[:, i] - centre[i]))}
        res.found[axis] = {"centre_v": float(centre[i]), "deadband_v": float(deadband[i]), "span_v": span,
                           "sign": sign, "plus_v": ext[(axis, 1)], "minus_v": ext[(axis, -1)]}
        res.check(f"{sig} deflection", span, None, "V", ok=span >= MIN_DEFLECTION_V)
        res.check(f"{sig} asymmetry", abs(abs(plus) - abs(minus)) / max(abs(plus), abs(minus), 1e-9),
                  MAX_ASYMMETRY)
        res.check(f"{sig} opposite sides", plus * minus, None, "V^2", ok=plus * minus < 0)
        res.check(f"{sig} deadband", float(deadband[i]), MAX_DEADBAND_V, "V")
        res.check(f"{sig} rest noise", float(np.max(np.array(noise)[:, i])), 3 * LSB_V, "V")
        if axis in prev:
            pass  # drift is reported by finish()
        pts["plus"].append(plus)
        pts["minus"].append(minus)
    res.cae = cae_update
    res.plots.append(plot_fit(plot_name(ctx, NAME, "sweep"), [
        Panel([Series(np.arange(len(sigs)), np.array(pts["plus"]), "points", "red", "full plus"),
               Series(np.arange(len(sigs)), np.array(pts["minus"]), "points", "blue", "full minus")],
              "stick at full plus and full minus, per axis (the rest is the null, 0 V)", "axis",
              "volts from null (V)", zero_line=True, xticks=sigs)],
        title="CAE hand controller sweep"))
    return finish(ctx, res)
