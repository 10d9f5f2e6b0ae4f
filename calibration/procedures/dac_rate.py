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

Legs below breakaway (the joint did not move: Coulomb friction holds it against the
loop's drive) carry no gain information and would bias it: they are excluded, counted
and named in the report; the fit needs at least 4 moving legs, 2 each way, else FAIL
naming the excluded legs.

The proportional rate loop also droops in viscous friction: a perfect DAC and
amplifier give ``velocity / command = k K_w / (b + k K_w)`` (k = K_a N eta K_t, b the
viscous friction; pfma-model 8.3/8.4, assumed values via ``fakes.arm_params.NOMINAL``;
wrist roll 0.615, shoulder yaw 0.987). ``a`` is that loop gain times the DAC gain; the
report gives ``dac_gain = a / loop gain`` (1 on a perfect rack), and the scale still
takes ``a`` (so a commanded rate is reached at steady state). Override the expected
loop gain per joint with ``expected_gain={joint: value}``.

Tolerances (stated): gain to 1 %, null to 0.002 rad/s (or 1 % of the smallest leg);
fit residual <= 2 % of the largest velocity; DAC gain within 10 % of 1 (else FAIL: a
wrong answer, a sign or wiring fault, or a loop that is not the nominal one).

Default joints: shoulder yaw and wrist roll (no gravity torque at the ready pose);
others with ``joints=[...]`` where they are unloaded.
"""

from __future__ import annotations

import numpy as np

from calibration import fit as F
from calibration.plot import Fit, fit_grid, plot_fit
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from calibration.procedures.motion import run_legs
from fakes.arm_params import AXES, NOMINAL
from pfma.errors import CalibrationError

NAME = "dac-rate"
DEFAULT_JOINTS = ("shoulder_yaw", "wrist_roll")
FRACTIONS = (0.25, -0.25, 0.4, -0.4, 0.15, -0.15)
MIN_SPEED_RAD_S = 0.01  #: legs slower than this (stuck in friction) are left out
MIN_MOVING = 4  #: moving legs needed for the 3-unknown fit (2 each way)
DAC_GAIN_BAND = 0.10  #: |dac_gain - 1| above this fails
PLOT_COLUMNS = 3  #: small panels per row (one per joint)


def _check_service_calibration(ctx: Context) -> None:
    got = ctx.session.calibration_hash()
    if got is None:
        return
    want = ctx.calibration.hash()
    if got != want and any(got):
        raise CalibrationError(f"the service runs calibration {got.hex()}, this procedure starts from "
                               f"{want.hex()} ({ctx.calibration.describe()}); load it into the service first")


def expected_loop_gain(joint: str) -> float:
    """Steady-state velocity / command of the nominal proportional rate loop with viscous
    friction (pfma-model 8.3/8.4): ``k K_w / (b + k K_w)``, k = K_a N eta K_t."""
    i = next(n for n, a in enumerate(AXES) if a.joint == joint)
    a = AXES[i]
    k = NOMINAL.k_a()[i] * a.torque_per_amp
    return k * a.k_w / (a.viscous + k * a.k_w)


def split_moving(cmd: np.ndarray, vel: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """Mask of the legs that moved and the commands of those that did not (below breakaway)."""
    moving = np.abs(vel) >= MIN_SPEED_RAD_S
    return moving, [float(c) for c in cmd[~moving]]


def enough_moving(cmd: np.ndarray, moving: np.ndarray) -> bool:
    return int(moving.sum()) >= MIN_MOVING and int((cmd[moving] > 0).sum()) >= 2 and int((cmd[moving] < 0).sum()) >= 2


def run(ctx: Context) -> ProcedureResult:
    joints = list(ctx.options.get("joints") or DEFAULT_JOINTS)
    _check_service_calibration(ctx)
    fractions = list(ctx.options.get("fractions") or FRACTIONS)
    legs = run_legs(ctx, joints, fractions)
    res = ProcedureResult(NAME, tolerances={"gain": "1 %", "null": "0.002 rad/s",
                                            "residual": "<= 2 % of max velocity",
                                            "DAC gain": f"within {DAC_GAIN_BAND:.0%} of 1 (fit gain / nominal loop gain)",
                                            "legs": f">= {MIN_MOVING} moving, 2 each way; stuck legs excluded"})
    expected = dict(ctx.options.get("expected_gain") or {})
    fits = []
    for i, j in enumerate(joints):
        cmd = np.array([leg.rate_cmd[j] for leg in legs])
        vel = np.array([leg.velocity[j] for leg in legs])
        moving, stuck = split_moving(cmd, vel)
        ok = enough_moving(cmd, moving)
        excl = ", ".join(f"{c:+.3g}" for c in stuck) or "none"
        res.check(f"{j} legs moving (excluded below breakaway, commands rad/s: {excl})", int(moving.sum()),
                  None, "legs", ok=ok)
        if not ok:
            ctx.operator.show(f"  {j}: only {int(moving.sum())} of {len(cmd)} legs moved (need {MIN_MOVING}, "
                              f"2 each way); legs at {excl} rad/s stayed in Coulomb friction: no fit")
            continue
        cmd, vel = cmd[moving], vel[moving]
        a_mat = np.column_stack([cmd, np.ones_like(cmd), np.sign(cmd)])
        f = F.design(a_mat, vel, ("gain", "null", "friction"), f"DAC-to-rate {j}")
        sig = ctx.rack.joint_channel(j, "rate_command").signal
        e = ctx.calibration.channel(sig)
        s0, off0 = float(e["scale"]), float(e["offset"])
        scale, offset = f["gain"] * s0, f["null"] + f["gain"] * off0
        loop = float(expected.get(j) or expected_loop_gain(j))
        res.fits[sig] = f
        res.channels[sig] = {"scale": scale, "offset": offset,
                             "provenance": ctx.provenance("DAC-to-rate legs, resolver velocity", f,
                                                          gain=f["gain"], null_rad_s=f["null"],
                                                          friction_rad_s=f["friction"], loop_gain=loop,
                                                          excluded_legs=stuck,
                                                          x=["command rad/s", "1", "sign"], y="velocity rad/s")}
        dac_gain = f["gain"] / loop
        res.why[sig] = (f"the amplifier's proportional rate loop reaches {loop:.3f} of a commanded rate in viscous "
                        f"friction (pfma-model 8.3/8.4), times this channel's DAC gain {dac_gain:.4f}: the new "
                        f"scale makes a command reach its rate")
        res.found[sig] = {"gain": f["gain"], "null_rad_s": f["null"], "friction_rad_s": f["friction"],
                          "scale": scale, "offset": offset, "loop_gain": loop, "dac_gain": dac_gain,
                          "excluded_legs": stuck}
        res.check(f"{sig} max residual", f.max_abs, 0.02 * float(np.max(np.abs(vel))) + 1e-4, "rad/s")
        res.check(f"{sig} DAC gain - 1 (fit gain {f['gain']:.4f} / loop gain {loop:.4f})", dac_gain - 1.0,
                  DAC_GAIN_BAND)
        fits.append(Fit(j, cmd, vel, a_mat @ f.coef, f.residuals,
                        f"gain {f['gain']:.4f}, null {f['null']:+.4f} rad/s"))
    cols = max(1, min(PLOT_COLUMNS, len(fits)))
    res.plots.append(plot_fit(plot_name(ctx, NAME, "fit"),
                              fit_grid(fits, "command (rad/s)", "velocity (rad/s)", "rad/s", cols,
                                       fitted="fit with friction"),
                              "DAC-to-rate: velocity vs command per joint; residuals below",
                              width=max(2, cols) * 280, height_per_panel=200, columns=cols))
    return finish(ctx, res)
