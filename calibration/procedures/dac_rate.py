"""DAC-to-rate gain and offset per joint (zero-drift nulling).

Legs at +-15 %, +-25 % and +-40 % of full-scale rate (a joint held by Coulomb
friction at a zero command shows no drift, so the null is the fit's intercept), commanded in rad/s through the service, which converts them to volts with the
DAC channel's scale/offset of the calibration in force; the joint velocity comes from
the resolvers. Per joint, least squares ``velocity = a * command + b + f * sign(command)``:
``f`` takes the Coulomb-friction droop of the amplifier's proportional rate loop, so
``a`` and ``b`` are the DAC/amplifier gain and zero drift. With the service's old
conversion ``V = (command - offset0) / scale0`` the new one is
``scale = a * scale0`` (rad/s per V) and ``offset = b + a * offset0`` (rad/s at 0 V).

Gravity on a joint also shows as a zero drift at the pose where the legs run: run it
where the joint carries no gravity torque (shoulder yaw and wrist roll at the ready
pose), or accept the pose-specific null.

The service must run the calibration this procedure starts from (its hash in the
buffer header is checked).

Tolerances (stated): gain to 1 %, null to 0.002 rad/s (or 1 % of the smallest leg);
fit residual <= 2 % of the largest velocity; gain within 50 % of nominal (the wrist
roll's proportional rate loop alone droops 37 % in viscous friction: K_a N eta K_t =
0.64 N*m/V against 2 N*m*s/rad, pfma-model 8.3/8.4).

Default joints: shoulder yaw and wrist roll (no gravity torque at the ready pose);
others with ``joints=[...]`` where they are unloaded.
"""

from __future__ import annotations

import numpy as np

from calibration import fit as F
from calibration.plot import Series, plot_fit
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from calibration.procedures.motion import run_legs
from pfma.errors import CalibrationError

NAME = "dac-rate"
DEFAULT_JOINTS = ("shoulder_yaw", "wrist_roll")
FRACTIONS = (0.25, -0.25, 0.4, -0.4, 0.15, -0.15)
MIN_SPEED_RAD_S = 0.01  #: legs slower than this (stuck in friction) are left out
COLOURS = ("blue", "red", "green", "orange", "purple", "black")


def _check_service_calibration(ctx: Context) -> None:
    got = ctx.session.calibration_hash()
    if got is None:
        return
    want = ctx.calibration.hash()
    if got != want and any(got):
        raise CalibrationError(f"the service runs calibration {got.hex()}, this procedure starts from "
                               f"{want.hex()} ({ctx.calibration.describe()}); load it into the service first")


def run(ctx: Context) -> ProcedureResult:
    joints = list(ctx.options.get("joints") or DEFAULT_JOINTS)
    _check_service_calibration(ctx)
    fractions = list(ctx.options.get("fractions") or FRACTIONS)
    legs = run_legs(ctx, joints, fractions)
    res = ProcedureResult(NAME, tolerances={"gain": "1 %", "null": "0.002 rad/s",
                                            "residual": "<= 2 % of max velocity", "nominal": "within 50 %"})
    pts, resid = [], []
    for i, j in enumerate(joints):
        cmd = np.array([leg.rate_cmd[j] for leg in legs])
        vel = np.array([leg.velocity[j] for leg in legs])
        moving = np.abs(vel) >= MIN_SPEED_RAD_S
        res.check(f"{j} legs moving", int(moving.sum()), None, "legs", ok=moving.sum() >= 4)
        if moving.sum() < 3:
            continue
        cmd, vel = cmd[moving], vel[moving]
        a_mat = np.column_stack([cmd, np.ones_like(cmd), np.sign(cmd)])
        f = F.design(a_mat, vel, ("gain", "null", "friction"), f"DAC-to-rate {j}")
        sig = f"{j}_command"
        e = ctx.calibration.channel(sig)
        s0, off0 = float(e["scale"]), float(e["offset"])
        scale, offset = f["gain"] * s0, f["null"] + f["gain"] * off0
        res.fits[sig] = f
        res.channels[sig] = {"scale": scale, "offset": offset,
                             "provenance": ctx.provenance("DAC-to-rate legs, resolver velocity", f,
                                                          gain=f["gain"], null_rad_s=f["null"],
                                                          friction_rad_s=f["friction"],
                                                          x=["command rad/s", "1", "sign"], y="velocity rad/s")}
        res.found[sig] = {"gain": f["gain"], "null_rad_s": f["null"], "friction_rad_s": f["friction"],
                          "scale": scale, "offset": offset}
        res.check(f"{sig} max residual", f.max_abs, 0.02 * float(np.max(np.abs(vel))) + 1e-4, "rad/s")
        res.check(f"{sig} gain - 1", f["gain"] - 1.0, 0.5)
        col = COLOURS[i % len(COLOURS)]
        pts += [Series(cmd, vel, "points", col), Series(cmd, a_mat @ f.coef, "line", col)]
        resid.append(Series(cmd, f.residuals, "points", col))
    res.plots.append(plot_fit(plot_name(ctx, NAME, "fit"), [pts, resid]))
    return finish(ctx, res)
