"""What a channel's conversion may be, judged against the nominal arm and the DAC range
(issue 28 item 7: files that cannot invert the loop).

A rack file (``pfma/rack.py``) and a calibration file (``calibration/files.py``) each give
every analog channel a conversion ``engineering = scale * volts + offset`` (a DAC writes
``volts = (engineering - offset) / scale``). A wrong sign there inverts a joint's rate loop
(a runaway: 99 deg in 7.5 s with the demo controller); a scale 100x too small makes it a
+-10 V limit cycle. This module is the one place that says which conversions a joint's
channels may have; both file readers ask it and word the refusal themselves.

Checked, for the channels of a joint the nominal arm knows (:data:`pfma.arm.JOINTS`, plus
the gripper's current limit and drive command):

- **sign**: the scale's sign is the nominal one (all nominal scales are positive);
- **magnitude**: ``|scale|`` lies within :data:`SCALE_BAND` of the nominal scale;
- **offset**: ``|offset|`` is at most :data:`OFFSET_MAX_V` volts' worth (``|scale|`` x 1 V;
  resolver channels: at most one turn, 2 pi rad);
- **limit** (DAC command channels): at most the joint's full scale (omega_fs, I_max,
  10 V for the gripper drive), and at most what the DAC can express (``10 V x |scale|``,
  :data:`DAC_FULL_SCALE_V`).

Every check but the DAC range is a judgement against the *nominal* model (assumed, not
measured: pfma-model.md 8.2), so a lab whose arm differs can accept a value outside the
band by naming it in the rack file's ``[checks] allow_nonnominal`` (``"signal.field"``);
the service names every such override in its start-up messages. The DAC range is a fact
of the board (the VMIVME-4100 saturates at +-10 V), not a model, and cannot be overridden.

Channels the model has no figure for (the hand-indexed shoulder roll, the CAE stick,
spares, joints of a rack not in the nominal table) are not checked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pfma.arm import GRIPPER_I_MAX_A, JOINT_NAMES, joint

#: accepted ``|scale| / nominal scale``. ASSUMED (this project): 0.5..2. A real amplifier's
#: gain or a tachometer's constant is trimmed within some 10-20 % of its data sheet, so a
#: factor 2 either way accepts any real trim and every calibration of a working arm; the
#: slips that distort the loop are all larger: a scale in deg (57x), rpm (9.5x), rev (6.3x)
#: or mV (1000x), a scale written for the wrong joint (the nominal scales of the shoulder
#: and the wrist roll differ 5x), or the 100x of issue 28. Inside the band the loop gain is
#: off by at most 2x, which the rate loop's integral action absorbs.
SCALE_BAND = (0.5, 2.0)
#: accepted ``|offset|`` of an ADC or DAC channel, in volts at the channel's scale. ASSUMED:
#: 1 V, 10 % of full scale. A 12-bit DAC's and an amplifier's offset errors are tens of mV;
#: a zero command that drives a joint at a tenth of its full-scale rate is not a trim.
OFFSET_MAX_V = 1.0
#: accepted ``|offset|`` of a resolver channel (rad): its zero, within one turn
ANGLE_OFFSET_MAX_RAD = 2.0 * math.pi
#: the DAC's full-scale output (V): the VMIVME-4100's +-10 V range (drivers/dac/vmivme4100.py)
DAC_FULL_SCALE_V = 10.0
#: fields a rack file's ``[checks] allow_nonnominal`` may name after a signal
OVERRIDABLE_FIELDS = ("scale", "offset", "limit")
#: relative tolerance of the comparisons (the file's decimal figures, e.g. 10 x 0.04)
_TOL = 1e-9


@dataclass(frozen=True)
class Nominal:
    """A channel's nominal conversion."""

    scale: float  #: engineering units per volt (resolvers: per rad)
    full_scale: float | None  #: DAC commands: the largest command the joint takes
    basis: str  #: where the figure comes from, e.g. "omega_fs 0.5 rad/s / 10 V"


def nominal(device: str, joint_name: str, quantity: str) -> Nominal | None:
    """The nominal conversion of a joint's channel; None when the model has no figure."""
    if joint_name == "gripper":
        if quantity in ("current_limit", "motor_current"):
            return Nominal(GRIPPER_I_MAX_A / 10.0, GRIPPER_I_MAX_A if device == "dac" else None,
                           f"gripper I_max {GRIPPER_I_MAX_A:g} A / 10 V")
        if quantity == "gripper_command":
            return Nominal(1.0, DAC_FULL_SCALE_V, "the gripper drive takes volts")
        return None
    if joint_name not in JOINT_NAMES:
        return None
    j = joint(joint_name)
    if quantity in ("rate_command", "rate"):
        return Nominal(j.omega_fs_rad_s / 10.0, j.omega_fs_rad_s if device == "dac" else None,
                       f"omega_fs {j.omega_fs_rad_s:g} rad/s / 10 V, pfma-model 8.2")
    if quantity in ("current_limit", "motor_current"):
        return Nominal(j.i_max_a / 10.0, j.i_max_a if device == "dac" else None,
                       f"I_max {j.i_max_a:g} A / 10 V, pfma-model 8.2")
    if quantity == "angle":
        return Nominal(1.0, None, "the resolver reads radians")
    return None


@dataclass(frozen=True)
class Finding:
    """One value outside what the nominal arm or the DAC allows."""

    field: str  #: "scale", "offset" or "limit"
    value: float
    why: str  #: what is wrong and the accepted band, e.g. "sign inverted: ..."
    overridable: bool = True


def _band(nom: Nominal, units: str) -> str:
    lo, hi = SCALE_BAND
    return (f"{lo * nom.scale:g}..{hi * nom.scale:g} {units} per V ({lo:g}x..{hi:g}x the nominal "
            f"{nom.scale:g}: {nom.basis})")


def check(device: str, joint_name: str, quantity: str, units: str, scale: float, offset: float,
          limit: float | None = None) -> list[Finding]:
    """The findings (in the order scale, offset, limit) for one channel's conversion; empty
    when it is within the nominal bands or the model has no figure for the channel.

    ``limit`` is checked only when given (DAC command channels of a rack file).
    """
    nom = nominal(device, joint_name, quantity)
    if nom is None:
        return []
    out: list[Finding] = []
    lo, hi = SCALE_BAND
    per = "rad" if device == "rtd" else "V"
    if not math.isfinite(scale):
        out.append(Finding("scale", scale, f"not a finite number; accepted {_band(nom, units)}"))
    elif (scale > 0) != (nom.scale > 0):
        out.append(Finding("scale", scale, f"sign inverted against the nominal arm (it would invert "
                                           f"the joint's loop); accepted {_band(nom, units)}"))
    elif not lo * abs(nom.scale) * (1 - _TOL) <= abs(scale) <= hi * abs(nom.scale) * (1 + _TOL):
        out.append(Finding("scale", scale, f"{abs(scale) / abs(nom.scale):.3g}x the nominal scale; "
                                           f"accepted {_band(nom, units)}"))
    if device == "rtd":
        if not abs(offset) <= ANGLE_OFFSET_MAX_RAD * (1 + _TOL):
            out.append(Finding("offset", offset, f"more than one turn; accepted |offset| <= "
                                                 f"{ANGLE_OFFSET_MAX_RAD:.6g} rad"))
    elif math.isfinite(scale) and not abs(offset) <= OFFSET_MAX_V * abs(scale) * (1 + _TOL):
        out.append(Finding("offset", offset, f"{abs(offset) / abs(scale):.3g} {per} at scale {scale:g}; "
                                             f"accepted |offset| <= {OFFSET_MAX_V:g} V x |scale| = "
                                             f"{OFFSET_MAX_V * abs(scale):g} {units}"))
    if limit is not None and device == "dac":
        dac_range = DAC_FULL_SCALE_V * abs(scale)
        if math.isfinite(scale) and limit > dac_range * (1 + _TOL):
            out.append(Finding("limit", limit, f"beyond what the DAC can express: {DAC_FULL_SCALE_V:g} V x "
                                               f"|scale| {abs(scale):g} = {dac_range:g} {units}; accepted "
                                               f"limit <= {dac_range:g} {units} (a board fact, not "
                                               f"overridable)", overridable=False))
        if nom.full_scale is not None and limit > nom.full_scale * (1 + _TOL):
            out.append(Finding("limit", limit, f"beyond the joint's full scale; accepted limit <= "
                                               f"{nom.full_scale:g} {units} ({nom.basis})"))
    return out
