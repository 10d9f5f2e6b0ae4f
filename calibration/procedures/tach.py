"""Tachometer scale per joint: tach volts against the resolver-derived velocity.

Legs at +-25 % and +-40 % of full-scale rate (all selected joints together; the
fractions net to zero travel; the amplifiers' proportional rate loops droop by up to
0.3 rad/s in Coulomb friction (wrist roll, pfma-model 8.3/8.4), so slower legs would
stick); per joint the fit ``tach_volts = k * velocity + c``.
The ``<joint>_rate`` ADC channel's conversion becomes ``rate = v / k - c / k``: this
absorbs the tach's own scale error and the ADC channel's gain and offset together.

Tolerances (stated): fit residual <= 1 % of the largest tach reading + 2 ADC LSB;
k within 20 % of the nominal K_w (pfma-model 8.4) else fail (wiring/sign suspect).
Expected accuracy of k on the simulated rack: 0.3 %.
"""

from __future__ import annotations

import numpy as np

from calibration import fit as F
from calibration.plot import Fit, fit_grid, plot_fit
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from calibration.procedures.motion import full_scale_rad_s, run_legs

NAME = "tach"
LSB_V = 20.0 / 4096
FRACTIONS = (0.25, -0.25, 0.4, -0.4)
MIN_SPEED_RAD_S = 0.01  #: legs slower than this (stuck in friction) are left out
NOMINAL_BAND = 0.2
PLOT_COLUMNS = 3  #: small panels per row (one per joint)


def run(ctx: Context) -> ProcedureResult:
    joints = list(ctx.options.get("joints") or ctx.rack.joints)
    legs = run_legs(ctx, joints, list(ctx.options.get("fractions") or FRACTIONS))
    res = ProcedureResult(NAME, tolerances={"residual": "<= 1 % of max tach volts + 2 LSB",
                                            "k": f"within {NOMINAL_BAND:.0%} of nominal K_w"})
    fits = []
    for i, j in enumerate(joints):
        vel = np.array([leg.velocity[j] for leg in legs])
        tach = np.array([leg.tach_v[j] for leg in legs])
        moving = np.abs(vel) >= MIN_SPEED_RAD_S
        res.check(f"{j} legs moving", int(moving.sum()), None, "legs", ok=moving.sum() >= 3)
        if moving.sum() < 2:
            continue
        vel, tach = vel[moving], tach[moving]
        f = F.linear(vel, tach, what=f"tach {j}")
        k, c = f["gain"], f["offset"]
        sig = ctx.rack.joint_channel(j, "rate").signal
        k_nom = 10.0 / full_scale_rad_s(ctx, j)
        res.fits[sig] = f
        res.channels[sig] = {"scale": 1.0 / k, "offset": -c / k,
                             "provenance": ctx.provenance("tach vs resolver velocity, constant-rate legs", f,
                                                          k_v_per_rad_s=k, c_v=c, x="velocity rad/s",
                                                          y="tach V")}
        res.found[sig] = {"k_v_per_rad_s": k, "c_v": c, "k_nominal": k_nom}
        res.why[sig] = (f"the tach reads {k:.4g} V per rad/s against the nominal {k_nom:.4g} ({k / k_nom - 1:+.1%}): "
                        f"its own constant and its ADC channel's gain together")
        res.check(f"{sig} max residual", f.max_abs, 0.01 * float(np.max(np.abs(tach))) + 2 * LSB_V, "V")
        res.check(f"{sig} k / K_w nominal - 1", k / k_nom - 1.0, NOMINAL_BAND)
        fits.append(Fit(j, vel, tach, k * vel + c, f.residuals, f"k {k:.4g} V/(rad/s) ({k / k_nom - 1:+.1%})"))
    cols = max(1, min(PLOT_COLUMNS, len(fits)))
    res.plots.append(plot_fit(plot_name(ctx, NAME, "fit"),
                              fit_grid(fits, "velocity (rad/s)", "tach (V)", "V", cols),
                              "Tachometer scale: tach volts vs joint velocity (resolver) per joint, fitted line; "
                              "residuals below", width=max(2, cols) * 280, height_per_panel=200, columns=cols))
    return finish(ctx, res)
