"""A current-limit channel's data bits where no brake holds the drive (issue 32).

The brake-set checks (:class:`tools.checkout.runner.DacBits`) keep a joint's current limit
under the brake-release cards' 0.3 V engage threshold (pfma-model.md 8.4): its D0..D5. A
limit with D6 or up set (64 codes, 0.31 V, and more) is over that threshold, and the jaw has
no brake at all. So a bit there stuck at 0 lowered the moves' limit unseen (the wrist pitch's
D7: 2 V became 1.38 V, and a wrist that draws K_a x V_cmd, 0.7 A, under either never showed
it), and the jaw's limit was never at its limit (it runs on its friction, 49 mA). Here:

- a **joint**, after its moves: the limit at 2^b codes alone for each bit b from D6 up to the
  moves' limit code's highest (so the current is never above the moves' limit), the rate
  command at the moves' rate, each way in turn. The command asks for more than the limit
  (K_a x V_cmd), so the current is the limit while the joint is held (the brake, its weight,
  its friction) or speeds up;
- the **jaw**, closed on its stop (its closed end, driven closed until its tach stops) and
  held there by the drive: D5 and up pulsed as a joint's, D0..D4 stepped from 32 codes
  through the monitor's noise (:mod:`tools.checkout.finesteps`), then opened back for as long.

Each pulse's current, less the monitor's zero (its reading with the limit at 0 and no
command), must be its code's worth within ``dac_bits_tolerance``. Under half of it with the
drive still (tach under ``DRIVE_STILL`` of the command): bit b stuck at 0 (the pulse's only
bit); over it: the excess codes' bit stuck at 1 (or the monitor's own bit); under it while
the joint ran: not judged (a running joint's current is its load's, not its limit).
ASSUMED: the amplifier's gain spread (+-10 %, sim/errors.py) and the DAC's offset (a few
codes) stay within the tolerance of 64 codes' worth and more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from tools.checkout.finesteps import (
    ADC_VOLTS_PER_CODE, DAC_VOLTS_PER_CODE, DAC_ZERO_CODE, FINE_SE_CODES, FINE_WORTHS, adc_offset_bit, bit_of_codes,
    judge_steps, place_code, read_fine, step_levels, steps_why, summary, worst_step,
)


#: the joints' pulsed bits start here: D0..D5 are the brake-set walk's (runner.DacBits)
JOINT_FIRST_BIT = 6
#: the jaw's: D0..D4 stepped from LOW_BASE on its stop, D5 and up pulsed
JAW_FIRST_BIT = 5
JAW_LOW_BITS = (0, 1, 2, 3, 4)
LOW_BASE = DAC_ZERO_CODE + 0x20
#: the top bit a pulse may set alone (D10: 5 V; D11 is the sign)
TOP_BIT = 10
#: the DAC data bits a step or an excess of codes is named by (D0..D10)
DAC_BITS = range(TOP_BIT + 1)
#: the drive is still when its tach's mean is under this fraction of the command (assumed;
#: the moves' diagnosis calls a tenth of the command "moved")
DRIVE_STILL = 0.1
#: at most this long for a joint to come still after a pulse (assumed: its rate loop stops it
#: within a few of its 1/40 s time constants, pfma-model.md 8.4)
STILL_MAX_S = 0.3
PULSE_CHECK = "DAC data bits: the current limit's high bits pulsed"
JAW_PULSE_CHECK = "DAC data bits: the jaw's current limit pulsed on its stop"
JAW_STEP_CHECK = "DAC data bits: the jaw's current limit stepped on its stop"


@dataclass(frozen=True)
class Pulse:
    """The limit at 2^``bit`` codes (``got``: the code written): the current drawn (A, the
    monitor's zero taken off, in the drive's direction) and the tach's mean over the window
    as a fraction of the command (how much the drive ran)."""

    bit: int
    got: int
    amps: float
    want: float
    ran: float


def pulse_bits(first: int, top_codes: float) -> list[int]:
    """The bits from ``first`` whose 2^b codes are at most ``top_codes`` (the moves' limit)."""
    return [b for b in range(first, TOP_BIT + 1) if (1 << b) <= top_codes]


class LimitPulses:
    """One current-limit channel's pulses and steps: ``set_limit(amps)`` writes its field,
    ``drive(sign)`` commands the drive that way (0 stops it), ``current`` and ``tach`` are
    the monitor and the tach read, ``command`` the drive's command in the tach's units
    (``drive(1)``'s). ``who`` names the joint (or the gripper) for its ``[joints]`` keys."""

    def __init__(self, co: Any, who: str, signal: str, current: str, tach: str, command: float,
                 set_limit: Callable[[float], None], drive: Callable[[int], None], hold: bool = False,
                 drew: bool = True) -> None:
        self.co, self.who, self.signal, self.current, self.tach = co, who, signal, current, tach
        self.command, self.set_limit, self.drive = abs(command), set_limit, drive
        self.hold = hold  #: the drive stays on between pulses (the jaw on its stop)
        #: a current flowed before (the brake-set checks): with none, a pulse without current
        #: is the drive's or the limit's D11 (the moves tell), not its own bit
        self.drew = drew
        #: the longest a low step's level is read (the jaw's own, ``[gripper]
        #: dac_bits_limit_fine_max_s``)
        self.fine_max_s = self.key("dac_bits_fine_max_s")
        self.per_code = DAC_VOLTS_PER_CODE * float(co.t.rack.channel(signal).scale)
        self.tol = float(co.cfg.joint(who, "dac_bits_tolerance"))
        self.zero = 0.0

    def key(self, name: str) -> float:
        return float(self.co.cfg.joint(self.who, name))

    def place(self, code: int) -> int:
        return place_code(self.co, self.set_limit, self.signal, code, self.per_code)

    def read_zero(self) -> None:
        """The monitor with the limit at 0 and no command, the drive still: no current can
        flow (a limit bit stuck at 1 leaves a limit, but a still drive asks for no current)."""
        self.drive(0)
        self.place(DAC_ZERO_CODE)
        self.until_still()
        self.co.t.wait(self.key("dac_bits_settle_s"))
        self.zero = float(np.mean(self.window()[0]))

    def window(self) -> tuple[list[float], list[float]]:
        """The monitor's and the tach's readings over ``dac_bits_pulse_s``."""
        cur, tach = [], []
        end = self.co.t.now() + self.key("dac_bits_pulse_s")
        while self.co.t.now() < end:
            s = self.co.inputs()
            cur.append(float(s.value(self.current)))
            tach.append(float(s.value(self.tach)))
            self.co.t.wait(self.co.poll_s)
        return cur, tach

    def pulse(self, bit: int, sign: int) -> Pulse:
        """The limit at 2^``bit`` codes, the drive on ``sign``'s way for the window (its
        first ``dac_bits_settle_s`` not read), then stopped for the settle (unless held)."""
        got = self.place(DAC_ZERO_CODE + (1 << bit))
        self.drive(sign)
        self.co.t.wait(self.key("dac_bits_settle_s"))
        cur, tach = self.window()
        if not self.hold:
            self.drive(0)
            self.until_still()
        amps = sign * (float(np.mean(cur)) - self.zero)
        ran = abs(float(np.mean(tach))) / self.command if self.command else 0.0
        return Pulse(bit, got, amps, (got - DAC_ZERO_CODE) * self.per_code, ran)

    def until_still(self) -> None:
        """After a pulse, the command 0: until the tach is under :data:`DRIVE_STILL` of the
        command (a joint that ran coasts and is stopped by its rate loop), at most
        ``STILL_MAX_S``, so the next pulse's tach is its own."""
        end = self.co.t.now() + STILL_MAX_S
        self.co.t.wait(self.key("dac_bits_settle_s"))
        while self.co.t.now() < end and abs(float(self.co.inputs().value(self.tach))) >= DRIVE_STILL * self.command:
            self.co.t.wait(self.co.poll_s)

    def pulses(self, bits: list[int], signs: Callable[[int], int]) -> list[Pulse]:
        return [self.pulse(b, signs(i)) for i, b in enumerate(bits)]

    def verdict(self, p: Pulse) -> str | None:
        """None when ``p`` is within the tolerance; "" when not judged (the drive ran); else
        what it says."""
        if abs(p.amps - p.want) <= self.tol * p.want:
            return None
        if p.amps > p.want:
            excess = (p.amps - p.want) / self.per_code
            b = bit_of_codes(excess, DAC_BITS)
            bit = (f"data bit D{b} of DAC channel {self.signal} stuck at 1 ({excess:+.0f} codes over the "
                   f"2^{p.bit} written)" if b is not None and b != p.bit else
                   f"a data bit of DAC channel {self.signal} stuck at 1 ({excess:+.0f} codes over the 2^{p.bit} "
                   f"written), or its amplifier's limit gain")
            return f"{bit}{self.monitor_excess(p.amps - p.want)}"
        if p.ran >= DRIVE_STILL:
            return ""
        if p.amps < 0.5 * p.want:
            return (f"data bit D{p.bit} of DAC channel {self.signal} stuck at 0 (the limit at 2^{p.bit} codes "
                    f"alone drew {p.amps * 1e3:+.1f} mA of {p.want * 1e3:.1f} with the drive held)")
        return (f"DAC channel {self.signal}'s limit is low at 2^{p.bit} codes: its amplifier's limit gain, or "
                f"the monitor {self.current}'s scale")

    def monitor_excess(self, excess_a: float) -> str:
        return monitor_excess(self.co.t.rack, self.current, excess_a)

    def pulse_row(self, check: str, ps: list[Pulse], where: str) -> None:
        """One row for the pulses: FAIL naming the first fault, else PASS (naming the bits not
        judged because the drive ran)."""
        if not ps:
            return
        if any(p.got != DAC_ZERO_CODE + (1 << p.bit) for p in ps):
            self.co.record("joints", self.signal, check, None,
                           detail=f"not run: the service wrote codes {[f'0x{p.got:03X}' for p in ps]}")
            return
        said = ", ".join(f"2^{p.bit}: {p.amps * 1e3:+.1f} mA of {p.want * 1e3:.1f}"
                         + (f" (ran at {p.ran:.2f} of the command)" if p.ran >= DRIVE_STILL else "") for p in ps)
        verdicts = [(p, self.verdict(p)) for p in ps]
        if not self.drew and all(p.amps < 0.5 * p.want and p.ran < DRIVE_STILL for p in ps):
            self.co.record("joints", self.signal, check, None, detail=(
                f"not judged here: no current at any limit ({said}), as against the brake: the drive, the "
                f"monitor or D11 of the limit channel (the moves tell)"))
            return
        bad, worst, why = _pulses_verdict(verdicts)
        self.co.record("joints", self.signal, check, not bad, round(worst, 3), None, self.tol, "of its worth",
                       f"{where}, the limit at each bit alone, less the monitor's zero {self.zero * 1e3:+.1f} mA "
                       f"({self.current}): {said}{why}")

    def low_steps_row(self) -> None:
        """The jaw's D0..D4 (:data:`JAW_LOW_BITS`) stepped from :data:`LOW_BASE` on its stop,
        each level read through the monitor's noise; one row."""
        monitor_code = ADC_VOLTS_PER_CODE * float(self.co.t.rack.channel(self.current).scale)
        target = max(FINE_SE_CODES * monitor_code, self.per_code / FINE_WORTHS)

        def at(code: int):
            got = self.place(code)
            self.co.t.wait(self.key("dac_bits_settle_s"))
            return read_fine(self.co, self.current, code, got, target, self.key("dac_bits_fine_window_s"),
                             self.fine_max_s, self.zero)

        self.drive(-1)
        read = step_levels(at, LOW_BASE, JAW_LOW_BITS)
        if read is None:
            self.co.record("joints", self.signal, JAW_STEP_CHECK, None,
                           detail="not run: the service wrote other codes")
            return
        base, levels = read
        # closing: the current is negative; the steps' size is its magnitude
        base = replace(base, mean=-base.mean)
        levels = [(b, replace(lv, mean=-lv.mean)) for b, lv in levels]
        steps = judge_steps(base, levels, self.per_code, monitor_code)
        stuck, unjudged = ([s.bit for s in group] for group in summary(steps))
        said = ", ".join(s.text() for s in steps)
        why = steps_why(stuck, unjudged, self.signal)
        self.co.record("joints", self.signal, JAW_STEP_CHECK, not stuck, round(worst_step(steps), 3), 0.5, None,
                       "of a step",
                       f"the jaw held closed on its stop, from 0x{LOW_BASE:03X} ({base.mean * 1e3:+.1f} mA): "
                       f"{said}{why}")


def _pulses_verdict(verdicts: list[tuple[Pulse, str | None]]) -> tuple[bool, float, str]:
    """Of the pulses and their verdicts (:meth:`LimitPulses.verdict`: a fault's text, "" not
    judged, None good): whether one failed, the worst of the pulses held still (a running one
    within the tolerance is no measure of its limit), as a fraction of its worth, and what the
    row adds: the first fault, else the bits not judged."""
    bad = [v for _, v in verdicts if v]
    unjudged = [p.bit for p, v in verdicts if v == ""]
    why = f": {bad[0]}" if bad else (
        "; not judged (the drive ran, so its current was its load's): " + ", ".join(f"D{b}" for b in unjudged)
        if unjudged else "")
    worst = max((abs(p.amps - p.want) / p.want for p, v in verdicts if v or p.ran < DRIVE_STILL), default=math.nan)
    return bool(bad), worst, why


def monitor_excess(rack: Any, current: str, excess_a: float) -> str:
    """The other reading of a current off its limit by ``excess_a``: the motor-current
    monitor ``current``'s own data bit, when the excess is within 30 % of 2^b of its A/D
    codes (D3 and up). "" when no bit fits."""
    codes, b = adc_offset_bit(rack, current, excess_a)
    if b is None:
        return ""
    return (f"; or the motor-current monitor {current}: {codes:+.0f} A/D codes off, its data bit D{b} "
            f"stuck at {int(codes > 0)}?")


def limit_low_hint(currents: list[float], i_lim: float, bound: float, per_code: float, signal: str,
                   tol: float) -> str:
    """Why a move that ran slow drew less than its limit: its current held flat (the middle
    half of its second half's magnitudes within 5 % of their median) at a plateau under
    (1 - ``tol``) of ``bound`` (the limit written, or less: what the held drive draws at the
    move's command, so a set brake's stall current is not read as a low limit), the missing
    codes one data bit's 2^b, and that bit set in the limit's code (a bit stuck at 0 takes
    away only a bit that was set). "" when not so. ASSUMED: a driven joint's current is flat
    under both only where the amplifier limits it."""
    if len(currents) < 8 or per_code <= 0:
        return ""
    half = np.abs(np.asarray(currents[len(currents) // 2:], dtype=float))
    plateau = float(np.median(half))
    q1, q3 = np.percentile(half, [25, 75])
    if plateau <= 0 or q3 - q1 > 0.05 * plateau or plateau > (1.0 - tol) * bound:
        return ""
    code = int(round(i_lim / per_code))
    missing = (i_lim - plateau) / per_code
    b = bit_of_codes(missing, DAC_BITS)
    if b is None or not code >> b & 1:
        return ""
    return (f"; the motor current held at {plateau:.3f} A, under the {i_lim:.2f} A limit written by "
            f"{missing:.0f} codes: data bit D{b} of DAC channel {signal} stuck at 0?")


def zeroing_bits(i_lim: float, scale: float) -> str:
    """The data bits of a limit code (``i_lim`` A at ``scale`` A/V) each of which, stuck at
    0, leaves it under the brake's 0.3 V (no current): "D11", or "D10 or D11" for 0xC00."""
    code = DAC_ZERO_CODE + int(round(i_lim / (DAC_VOLTS_PER_CODE * float(scale)))) if scale else DAC_ZERO_CODE
    bits = [b for b in range(12) if code >> b & 1 and ((code & ~(1 << b)) - DAC_ZERO_CODE) * DAC_VOLTS_PER_CODE < 0.3]
    return " or ".join(f"D{b}" for b in bits) or "D11"

