"""The service's motion envelope per joint (issue 28 item 4): the last line of defence,
whatever the controller does. The rack file's ``[envelope]`` section sets it; every value
is checked against the nominal arm (:mod:`pfma.arm`) when the file is read.

``[envelope]`` (every key optional; absent: the defaults below, from the nominal arm)::

    overspeed_factor = 1.2          # a joint's resolver rate beyond this x omega_fs trips
    [envelope.shoulder_pitch]       # per joint (the [arm] joints)
    soft_lo_deg = -25.0             # the soft limits the service keeps the joint inside
    soft_hi_deg = 115.0
    brake_rad_s2 = 1.2              # the deceleration the braking distance assumes
    slew_rad_s2 = 8.0               # the rate command may change at most this fast

Defaults (assumed, this project's choice; docs/safety.md):

- soft limits: the nominal arm's (pfma-model 8.2), the controller's too;
- ``brake_rad_s2``: half the deceleration the joint's motor gives at the run current limit
  (``0.5 x N eta K_t x I_max/2 / J``: shoulder 1.2, elbow 3.0, wrist 10, wrist roll 45
  rad/s^2): the rate loop brakes with at least that, so the joint stops inside the distance;
- ``slew_rad_s2``: 20 x omega_fs per second (a full-scale change in 50 ms, beyond what any
  joint's motor can follow at the run current, so the servo's commands never meet it; a
  command flipping +-full scale every frame is cut to a small dither);
- ``overspeed_factor``: 1.2 (as the controller's supervision).

Checked: soft limits inside the nominal hard limits and lo < hi; ``brake_rad_s2`` > 0 and
no more than the deceleration at I_max (a larger figure would make the braking distance a
promise the motor cannot keep); ``slew_rad_s2`` > 0 and at most 100 x omega_fs per second;
``overspeed_factor`` in (1, 2].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pfma.arm import JOINTS, RUN_CURRENT_FRACTION, JointFacts

DEG = math.pi / 180.0
BRAKE_FRACTION = 0.5
SLEW_FS_PER_S = 20.0
SLEW_FS_PER_S_MAX = 100.0
OVERSPEED_FACTOR = 1.2
KEYS = {"soft_lo_deg", "soft_hi_deg", "brake_rad_s2", "slew_rad_s2"}


@dataclass(frozen=True)
class JointEnvelope:
    joint: str
    soft_lo_rad: float
    soft_hi_rad: float
    brake_rad_s2: float
    slew_rad_s2: float


@dataclass(frozen=True)
class Envelope:
    joints: tuple[JointEnvelope, ...]
    overspeed_factor: float = OVERSPEED_FACTOR

    def of(self, joint: str) -> JointEnvelope | None:
        return next((j for j in self.joints if j.joint == joint), None)


def decel_at(jf: JointFacts, fraction: float) -> float:
    """The deceleration the joint's motor gives at ``fraction`` of I_max, rad/s^2."""
    return jf.torque_per_amp * fraction * jf.i_max_a / jf.inertia_kg_m2


def default(jf: JointFacts) -> JointEnvelope:
    return JointEnvelope(jf.name, jf.soft_lo_rad, jf.soft_hi_rad,
                         BRAKE_FRACTION * decel_at(jf, RUN_CURRENT_FRACTION), SLEW_FS_PER_S * jf.omega_fs_rad_s)


def parse(raw: dict, joints: tuple[str, ...], fail) -> Envelope:
    """``[envelope]`` of a rack file -> :class:`Envelope` for ``joints``; ``fail(msg, key)``
    raises the file's ConfigError (naming its line)."""
    nominal = {j.name: j for j in JOINTS}
    extra = set(raw) - {"overspeed_factor"} - set(joints)
    if extra:
        fail(f"[envelope]: unknown key(s) {', '.join(sorted(extra))}; known: overspeed_factor and the "
             f"[arm] joints ({', '.join(joints)})", sorted(extra)[0])
    factor = raw.get("overspeed_factor", OVERSPEED_FACTOR)
    if not _num(factor) or not 1.0 < factor <= 2.0:
        fail(f"[envelope] overspeed_factor must be a number in (1, 2], not {factor!r}", "overspeed_factor")
    out = []
    for name in joints:
        jf = nominal.get(name)
        sub = raw.get(name, {})
        if jf is None:
            if sub:
                fail(f"[envelope.{name}]: the nominal arm has no joint {name!r} to check it against", name)
            continue
        if not isinstance(sub, dict):
            fail(f"[envelope] {name} must be a table of {', '.join(sorted(KEYS))}", name)
        bad = set(sub) - KEYS
        if bad:
            fail(f"[envelope.{name}]: unknown key(s) {', '.join(sorted(bad))}; known: {', '.join(sorted(KEYS))}",
                 name)
        d = default(jf)
        for key in sub:
            if not _num(sub[key]):
                fail(f"[envelope.{name}] {key} must be a finite number, not {sub[key]!r}", name)
        lo = sub.get("soft_lo_deg", d.soft_lo_rad / DEG) * DEG
        hi = sub.get("soft_hi_deg", d.soft_hi_rad / DEG) * DEG
        if not jf.hard_lo_rad <= lo < hi <= jf.hard_hi_rad:
            fail(f"[envelope.{name}] soft limits {lo / DEG:g}..{hi / DEG:g} deg must lie inside the nominal "
                 f"hard limits {jf.hard_lo_rad / DEG:g}..{jf.hard_hi_rad / DEG:g} deg, lo < hi", name)
        brake = sub.get("brake_rad_s2", d.brake_rad_s2)
        top = decel_at(jf, 1.0)
        if not 0 < brake <= top:
            fail(f"[envelope.{name}] brake_rad_s2 {brake:g} must be in (0, {top:.3g}]: the deceleration "
                 f"the motor gives at I_max (nominal arm)", name)
        slew = sub.get("slew_rad_s2", d.slew_rad_s2)
        if not 0 < slew <= SLEW_FS_PER_S_MAX * jf.omega_fs_rad_s:
            fail(f"[envelope.{name}] slew_rad_s2 {slew:g} must be in (0, "
                 f"{SLEW_FS_PER_S_MAX * jf.omega_fs_rad_s:g}] ({SLEW_FS_PER_S_MAX:g} x omega_fs per s)", name)
        out.append(JointEnvelope(name, lo, hi, float(brake), float(slew)))
    return Envelope(tuple(out), float(factor))


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
