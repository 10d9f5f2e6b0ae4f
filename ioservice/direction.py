"""The direction check after a change of polarity (issue 28 item 7), as drive
commissioning does it.

A joint's loop direction is the product of the signs of its rate command's, its tach's
and its resolver's scales (the rack file's, or the calibration's when one is in force). A
sign flipped in a file (on purpose, under ``[checks] allow_nonnominal``, or because the
wiring was changed and the file follows it) must be proven on the arm before the arm is
trusted with it. The service records the signs a direction check last confirmed in a small
JSON state file (``pfma serve --direction-state FILE``; by default
``<calibration>.direction.json`` beside ``--calibration``). At start it compares:

- a joint whose signs differ from the record (or every joint when there is no record, or
  the record cannot be read) is **pending**;
- while a joint is pending, an arm is a *direction-check arm*: the service refuses
  (ARMED -> SAFE, or "arm refused: ...") any command that releases more than one pending
  joint (current limit > 0), drives a pending joint faster than
  :data:`RATE_FRACTION` of its limit or gives it more than :data:`CURRENT_FRACTION` of
  its current limit. Joints already confirmed are not restricted;
- each frame a pending joint is the one released and driven, the service integrates
  its resolver travel since the command took that sign. Once it has moved
  :data:`CONFIRM_TRAVEL_RAD` the way it was commanded and its tach reads the same sign,
  the joint is **confirmed** (message). If it moved that far the *other* way, or the tach
  reads the other sign, the command is refused (outputs 0 V, brakes set) naming the
  joint, what moved and what to check;
- when no joint is pending the state file is written (atomically) and the restriction
  ends. ``pfma checkout`` (group ``joints``) makes exactly such moves, one joint at a
  time, both ways.

Without a state file (``IoService(direction_state=None)``: the simulated rigs, ``pfma
serve`` without ``--calibration`` or ``--direction-state``) nothing is checked.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from bit3.layout import MessageCode

FORMAT = "pfma-direction-check"
#: a pending joint's rate command, as a fraction of its rate limit (omega_fs). ASSUMED:
#: 0.3, the checkout's fastest open-loop test (the wrist roll's 0.3 omega_fs); a
#: runaway at that rate is caught after CONFIRM_TRAVEL_RAD, well inside the soft limits
RATE_FRACTION = 0.3
#: a pending joint's current limit, as a fraction of its limit (I_max). ASSUMED: 0.5,
#: the checkout's largest (the shoulder pitch holds its arm against gravity with it)
CURRENT_FRACTION = 0.5
#: resolver travel that confirms (or condemns) a direction. ASSUMED: 0.01 rad (0.57 deg):
#: 26 LSB of the 14-bit resolver, several times its noise, and a fifth of the checkout's
#: smallest move (0.15 x 0.4 rad/s x 0.6 s = 0.036 rad at the shoulder)
CONFIRM_TRAVEL_RAD = 0.01
#: message codes: pending at start, a joint confirmed, the check done (state written)
PENDING_CODE, CONFIRMED_CODE, DONE_CODE = (MessageCode.DIRECTION_PENDING, MessageCode.DIRECTION_CONFIRMED,
                                          MessageCode.DIRECTION_DONE)
#: the quantities whose scale signs make a joint's loop direction
QUANTITIES = ("rate_command", "rate", "angle")
_TWO_PI = 2.0 * math.pi
#: relative tolerance of the bounds (a tool's 0.3 x 10 V x 0.2 is 0.6000000000000001)
_TOL = 1e-9


def signature(rack) -> dict[str, dict[str, int]]:
    """``{joint: {quantity: +1 | -1}}`` of the rack's servoed joints (``[arm] joints``)."""
    return {j: {q: (1 if rack.joint_channel(j, q).scale > 0 else -1) for q in QUANTITIES} for j in rack.joints}


def default_path(calibration) -> Path | None:
    """``<calibration>.direction.json`` beside a calibration file; None without one."""
    if calibration is None or not isinstance(calibration, (str, Path)):
        return None
    p = Path(calibration)
    return p.with_name(p.name + ".direction.json")


class DirectionCheck:
    """The service's direction-check state (see the module text).

    :param rack: the rack as the service runs it (calibrated scales)
    :param layout: the Bit3 layout (joint entries of the DAC, resolver and ADC groups)
    :param path: the state file
    :param dac_limits: the DAC task's engineering limit per DAC channel
    """

    def __init__(self, rack, layout, path: str | Path, dac_limits: list[float]) -> None:
        self.path = Path(path)
        self.rack_name = rack.name
        self.signs = signature(rack)
        self.joints = {}
        for j in rack.joints:
            rate_ch = layout.joint_entry("dac", j, "rate_command").channel
            limit_ch = layout.joint_entry("dac", j, "current_limit").channel
            self.joints[j] = (rate_ch, limit_ch, layout.joint_slot("rtd", j, "angle"),
                              layout.joint_slot("adc", j, "rate"), dac_limits[rate_ch], dac_limits[limit_ch])
        #: joint -> why it is pending (empty: nothing to check)
        self.pending: dict[str, str] = self._compare()
        self._track: dict[str, tuple[int, float, float]] = {}  # joint -> (command sign, last angle, travel)
        self.events: list[tuple[int, int, str]] = []  # (severity 0/1/2, code, text) for the service to post

    # ------------------------------------------------------------------ the record
    def _compare(self) -> dict[str, str]:
        try:
            data = json.loads(self.path.read_text())
            recorded = data["signs"] if data.get("format") == FORMAT and data.get("rack") == self.rack_name else None
            if not isinstance(recorded, dict):
                raise ValueError("not a direction-check record of this rack")
        except FileNotFoundError:
            return {j: "no direction check recorded" for j in self.signs}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            return {j: f"the record {self.path} cannot be read ({err})" for j in self.signs}
        out = {}
        for j, now in self.signs.items():
            was = recorded.get(j)
            if not isinstance(was, dict):
                out[j] = "no direction check recorded for it"
                continue
            changed = [f"{q} {'+' if was.get(q, 0) > 0 else '-'} -> {'+' if s > 0 else '-'}"
                       for q, s in now.items() if was.get(q) != s]
            if changed:
                out[j] = "scale sign changed since the last direction check: " + ", ".join(changed)
        return out

    def _record(self) -> None:
        data = {"format": FORMAT, "format_version": 1, "rack": self.rack_name, "signs": self.signs}
        tmp = self.path.with_name(f".{self.path.name}.tmp-{os.getpid()}")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(tmp, "w") as f:
                f.write(json.dumps(data, indent=1) + "\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except OSError as err:
            self.events.append((1, DONE_CODE, f"direction check done, but {self.path} could not be written "
                                              f"({err.strerror or err}): the next start asks again"))
            return
        self.events.append((0, DONE_CODE, f"direction check done: every joint moved as commanded; "
                                          f"recorded in {self.path}"))

    def start_text(self) -> str | None:
        """The start-up message while joints are pending (None when none is)."""
        if not self.pending:
            return None
        why = "; ".join(f"{j}: {w}" for j, w in self.pending.items())
        return (f"direction check required before normal arming ({why}): arm for one joint at a time, "
                f"|rate| <= {RATE_FRACTION:g} x its limit, current limit <= {CURRENT_FRACTION:g} x its limit, "
                f"and move it {CONFIRM_TRAVEL_RAD:g} rad (pfma checkout, group joints, does this)")

    # ------------------------------------------------------------------ each frame
    def restriction(self, eng: list[float]) -> str | None:
        """Why this command is not a direction-check move (None when it is, or nothing is
        pending)."""
        if not self.pending:
            return None
        released = [j for j in self.pending if eng[self.joints[j][1]] > 0.0]
        if len(released) > 1:
            return (f"direction check pending: one joint at a time ({', '.join(released)} have current "
                    f"limits > 0)")
        for j in self.pending:
            rate_ch, limit_ch, _a, _t, rate_lim, i_lim = self.joints[j]
            if abs(eng[rate_ch]) > RATE_FRACTION * rate_lim * (1 + _TOL):
                return (f"direction check pending: {j} rate {eng[rate_ch]:.4g} beyond "
                        f"{RATE_FRACTION:g} x {rate_lim:g}")
            if eng[limit_ch] > CURRENT_FRACTION * i_lim * (1 + _TOL):
                return (f"direction check pending: {j} current limit {eng[limit_ch]:.4g} beyond "
                        f"{CURRENT_FRACTION:g} x {i_lim:g}")
        return None

    def observe(self, eng: list[float], angles, tachs, armed: bool) -> str | None:
        """Follow the pending joint being driven (``angles``/``tachs``: the latest published
        resolver angles and ADC values); a text when it moved the wrong way (the caller
        refuses the command), None otherwise. Confirmations are queued in :attr:`events`."""
        if not self.pending:
            return None
        for j in list(self.pending):
            rate_ch, limit_ch, a_slot, t_slot, _r, _i = self.joints[j]
            cmd = eng[rate_ch]
            if not armed or cmd == 0.0 or eng[limit_ch] <= 0.0:
                self._track.pop(j, None)
                continue
            sign = 1 if cmd > 0 else -1
            angle = float(angles[a_slot])
            was = self._track.get(j)
            if was is None or was[0] != sign:
                self._track[j] = (sign, angle, 0.0)
                continue
            travel = was[2] + (angle - was[1] + math.pi) % _TWO_PI - math.pi
            self._track[j] = (sign, angle, travel)
            tach = float(tachs[t_slot])
            if sign * travel <= -CONFIRM_TRAVEL_RAD:
                self._track.pop(j, None)
                return (f"direction check: {j} moved {travel:+.3f} rad for a {cmd:+.3g} rad/s command: the loop "
                        f"is inverted (rate command scale sign, amplifier or resolver wiring); outputs safe")
            if sign * travel >= CONFIRM_TRAVEL_RAD:
                self._track.pop(j, None)
                if sign * tach <= 0.0:
                    return (f"direction check: {j} moved {travel:+.3f} rad for a {cmd:+.3g} rad/s command but "
                            f"its tach reads {tach:+.3g} rad/s: tach polarity inverted (its scale sign or "
                            f"wiring); outputs safe")
                del self.pending[j]
                self.events.append((0, CONFIRMED_CODE, f"direction check: {j} moved {travel:+.3f} rad for a "
                                                       f"{cmd:+.3g} rad/s command, tach {tach:+.3g}: confirmed"
                                                       + (f" ({len(self.pending)} to go)" if self.pending else "")))
                if not self.pending:
                    self._record()
        return None
