"""Shared by the procedures that move joints: constant-rate legs, measured two ways.

Each leg commands a slow constant rate per joint through the command area, waits for
the rate loop and the 10 Hz tach filter to settle, then samples every resolver/ADC
frame: the joint velocity is the least-squares slope of the unwrapped resolver angle
(counts per revolution: ``drivers.rtd.registers`` counts_per_rev), the tach reading
is the mean raw ADC volts of the joint's tach channel (quantity ``rate``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration import fit as F
from calibration.procedures.base import Context
from drivers.rtd.registers import VMIVME4940

LSB_RAD = VMIVME4940.constants["lsb_rad"]
COUNTS_PER_REV = VMIVME4940.constants["counts_per_rev"]


@dataclass
class Leg:
    rate_cmd: dict[str, float]  #: commanded rate per joint, rad/s (engineering, through the service)
    velocity: dict[str, float]  #: resolver-derived velocity, rad/s
    tach_v: dict[str, float]  #: mean raw tach volts


def full_scale_rad_s(ctx: Context, joint: str) -> float:
    """Joint rate at a 10 V command, from the rack's nominal command scale (rad/s per V)."""
    return 10.0 * abs(ctx.rack.joint_channel(joint, "rate_command").scale)


def run_legs(ctx: Context, joints: list[str], fractions: list[float], settle_s: float = 0.4,
             measure_s: float = 0.8) -> list[Leg]:
    """Arm, run one leg per fraction of full-scale rate (all joints at once), disarm."""
    layout = ctx.session.layout
    rtd_slots = {j: layout.joint_slot("rtd", j, "angle") for j in joints}
    adc_slots = {j: layout.joint_slot("adc", j, "rate") for j in joints}
    legs = []
    ctx.operator.prompt("motion.clear", f"The arm will move joints {', '.join(joints)} slowly "
                        f"(up to {max(abs(f) for f in fractions):.0%} of full-scale rate); keep clear")
    ctx.session.arm()
    try:
        for k, frac in enumerate(fractions):
            rates = {j: frac * full_scale_rad_s(ctx, j) for j in joints}
            ctx.progress(k, len(fractions), f"leg {k + 1}: {frac:+.0%} of full-scale rate")
            ctx.session.set_rates(rates)
            ctx.session.wait(settle_s)
            smp = ctx.session.collect(measure_s, ("rtd_counts", "adc_volts", "t_adc_s"), key="t_rtd_s")
            vel, tach = {}, {}
            for j in joints:
                counts = smp["rtd_counts"][:, rtd_slots[j]].astype(float)
                ang = np.unwrap(counts * (2 * np.pi / COUNTS_PER_REV))
                vel[j] = F.slope(smp.t, ang)
                tach[j] = float(np.mean(smp["adc_volts"][:, adc_slots[j]]))
            legs.append(Leg(rates, vel, tach))
    finally:
        ctx.session.disarm()
    ctx.progress(len(fractions), len(fractions), "legs done, arm disarmed")
    return legs
