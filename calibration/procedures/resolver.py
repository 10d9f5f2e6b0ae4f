"""Resolver zero offsets at known index positions.

For each joint the operator moves it to its index mark (the known joint angle
``index_rad``, by default the DH zero of pfma-model 8.1; ASSUMED: the PFMA's real
index marks are not public) and the procedure averages the raw resolver angle
(counts x LSB). The resolver's zero offset is ``raw - index`` (wrapped to +-pi); the
channel's engineering offset is its negative, so the service reports
``(raw + offset) mod 2 pi`` = the joint angle.

Tolerances (stated): offset found to 1 LSB (384 urad, 14-bit); the joint must be
still (spread <= 2 LSB, one reading left out at each end: :func:`_spread`); an offset
beyond 0.25 rad means the joint is not at its index mark (fail).
"""

from __future__ import annotations

import math

import numpy as np

from calibration.plot import Panel, Series, plot_fit
from calibration.procedures.base import Context, ProcedureResult, finish, plot_name
from calibration.procedures.motion import COUNTS_PER_REV, LSB_RAD
from calibration import fit as F

NAME = "resolver"
MAX_OFFSET_RAD = 0.25
MAX_SPREAD_RAD = 2 * LSB_RAD


def _spread(ang: np.ndarray) -> float:
    """How far a still joint's readings spread, in whole counts (rad): the highest less the
    lowest with one reading left out at each end (from 8 readings), so one noise excursion
    beyond the resolver's +-1 LSB peak (pfma-model 8.4; a seeded rack's noise is up to 0.4
    LSB rms, sim/errors.py) is not read as motion; a moving joint spreads over all of them.
    Whole counts: 2 LSB is exactly the limit, never a float's hair over it (rack seed 8's
    still wrist pitch read 2 LSB, 766.99 urad, and failed)."""
    counts = np.sort(np.rint(ang / LSB_RAD))
    if len(counts) >= 8:
        counts = counts[1:-1]
    return float(counts[-1] - counts[0]) * LSB_RAD if len(counts) else 0.0


def _wrap_pi(x: float) -> float:
    return (x + math.pi) % (2 * math.pi) - math.pi


def run(ctx: Context) -> ProcedureResult:
    joints = list(ctx.options.get("joints") or ctx.rack.joints)
    index = dict(ctx.options.get("index_rad") or {})
    res = ProcedureResult(NAME, tolerances={"offset": f"+-{LSB_RAD * 1e6:.0f} urad (1 LSB)",
                                            "spread": f"<= {MAX_SPREAD_RAD * 1e6:.0f} urad",
                                            "plausible": f"|offset| <= {MAX_OFFSET_RAD} rad"})
    layout = ctx.session.layout
    found, idx_list = [], []
    for k, j in enumerate(joints):
        ctx.progress(k, len(joints), f"{j}")
        target = float(index.get(j, 0.0))
        ctx.operator.prompt("resolver.index", f"Move {j.replace('_', ' ')} to its index mark "
                            f"({math.degrees(target):+.2f} deg) and hold it", axis=ctx.rack.joints.index(j),
                            joint=j, index_rad=target)
        ctx.session.wait(0.05)
        smp = ctx.session.collect(ctx.options.get("average_s", 0.1), ("rtd_counts",), key="t_rtd_s")
        counts = smp["rtd_counts"][:, layout.joint_slot("rtd", j, "angle")].astype(float)
        ang = np.unwrap(counts * (2 * np.pi / COUNTS_PER_REV))
        ang -= 2 * np.pi * np.round((np.mean(ang) - target) / (2 * np.pi))  # nearest the index
        raw = float(np.mean(ang))
        offset = _wrap_pi(raw - target)
        f = F.mean_offset(ang - target, what=f"resolver {j}")
        sig = ctx.rack.joint_channel(j, "angle").signal
        res.fits[sig] = f
        res.channels[sig] = {"scale": 1.0, "offset": 0.0 - offset,
                             "provenance": ctx.provenance("resolver reading at index mark", f,
                                                          index_rad=target, raw_rad=raw, resolver_offset_rad=offset)}
        res.found[sig] = {"resolver_offset_rad": offset}
        res.check(f"{sig} |offset|", offset, MAX_OFFSET_RAD, "rad")
        res.check(f"{sig} spread", _spread(ang), MAX_SPREAD_RAD, "rad")
        found.append(offset)
        idx_list.append(k)
    ctx.progress(len(joints), len(joints), "done")
    res.plots.append(plot_fit(plot_name(ctx, NAME, "offsets"), [
        Panel([Series(np.array(idx_list), np.array(found), "points", "blue")],
              "resolver offset at the index mark, per joint", "joint", "offset (rad)", zero_line=True,
              xticks=joints)], title="Resolver offsets"))
    return finish(ctx, res)
