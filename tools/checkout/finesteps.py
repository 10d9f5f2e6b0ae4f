"""A DAC channel's lowest data bits, told from the motor-current monitor's noise (issue 32).

A bit b stuck (at 0 or at 1) makes a step of 2^b codes from a code whose low bits are all 0
add nothing: the output already had (stuck at 1) or never gets (stuck at 0) that bit. The
steps are 1 to 8 codes: a few mA to a few tens, a fraction of a monitor's A/D code to a few
codes. So each code's current is averaged over as many reads as the monitor's noise needs
(:class:`Level`: its mean and the mean's standard error), and a step is judged only when
the noise lets it be told from nothing (:func:`judge_steps`). What the rack measures is
the current against the set brake, as :class:`tools.checkout.runner.DacBits` places it.

Stuck at 0 and stuck at 1 read alike here, but for a constant 2^b codes over every code,
which the channel's own offset (the DAC's, the amplifier's) hides, so the value is not said.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterable

from drivers.adc.registers import DVME611
from drivers.dac.registers import VMIVME4100

#: the DAC's 0 V code (12-bit offset binary)
DAC_ZERO_CODE = int(VMIVME4100.constants["zero_code"])
#: one code of the DAC and of the A/D, in volts (their register tables)
DAC_VOLTS_PER_CODE = float(VMIVME4100.constants["lsb_volts"])
ADC_VOLTS_PER_CODE = float(DVME611.constants["lsb_volts"])
#: the A/D data bits an offset of an input is named by: D3 and up (a lower one is its noise)
ADC_OFFSET_BITS = range(3, int(DVME611.constants["adc_bits"]))

#: a step is called stuck when it falls this many standard errors short of half its worth
#: and half its worth is itself that many standard errors: a healthy step is then called
#: stuck only by an error of 2 x 2.5 = 5 standard errors (3 in 10 million steps; assumed)
FINE_SIGMAS = 2.5
#: a step the monitor resolves without noise: this many of its A/D codes (assumed; rounding
#: moves a mean by whole codes, so a step under one code can read as none)
MIN_STEP_CODES = 1.5
#: ...or read through at least this much noise (1 sigma, in codes), which dithers the
#: rounding so a mean follows the current (assumed; the seeded racks' A/D noise is 0.4..1.2)
DITHER_CODES = 0.4
#: the standard error each fine level is read to, in the monitor's A/D codes (assumed: a
#: tenth of a code; a noisier monitor reads until its ``..._max_s``)
FINE_SE_CODES = 0.1
#: ... or to a one-code step's worth over this (assumed: half a code's worth is then over 3.5
#: standard errors of a step, two levels' errors combined, with room to spare)
FINE_WORTHS = 14.0


@dataclass(frozen=True)
class Level:
    """One code's current (A, the monitor's zero taken off): the mean of ``n`` reads and the
    mean's standard error."""

    code: int  #: the code asked for
    got: int  #: the code the service wrote (read back)
    mean: float
    se: float
    n: int


@dataclass(frozen=True)
class Step:
    """Adding 2^``bit`` codes to the base: the current it added (``step``, A), its standard
    error, and its worth (``want``, A)."""

    bit: int
    step: float
    se: float
    want: float
    #: False when the monitor cannot resolve it: under :data:`MIN_STEP_CODES` of its codes
    #: with noise under :data:`DITHER_CODES` (its mean then moves by whole codes, not by the
    #: current: a 0.95-code step can read as none)
    resolvable: bool = True

    @property
    def verdict(self) -> str:
        """"ok" (it added at least half its worth), "stuck" (it added less, and the noise
        cannot explain the shortfall) or "noise" (neither, or not resolvable: not judged)."""
        half = 0.5 * self.want
        if self.step >= half:
            return "ok"
        told = self.resolvable and half >= FINE_SIGMAS * self.se  # the noise lets it be told
        return "stuck" if told and half - self.step >= FINE_SIGMAS * self.se else "noise"

    def text(self, milli: str = "mA") -> str:
        """The step in thousandths of its unit (``milli``: mA for a current, mV for a tach)."""
        return f"+2^{self.bit}: {self.step * 1e3:+.1f} {milli} of {self.want * 1e3:.1f} (+/-{self.se * 1e3:.1f})"


def level(code: int, got: int, reads: list[float], zero: float = 0.0) -> Level:
    """A :class:`Level` of ``reads`` (A) less the monitor's ``zero``."""
    n = len(reads)
    if n == 0:
        return Level(code, got, math.nan, math.inf, 0)
    m = sum(reads) / n
    var = sum((x - m) ** 2 for x in reads) / (n - 1) if n > 1 else math.inf
    return Level(code, got, m - zero, math.sqrt(var / n), n)


def judge_steps(base: Level, steps: list[tuple[int, Level]], per_code: float | None = None,
                monitor_code: float = 0.0) -> list[Step]:
    """Each ``(bit, level)`` against ``base`` (the level's code is the base's plus 2^bit).
    ``per_code``: each code's worth in A; None: the median over the steps of step / 2^bit
    (the drive's K_a, not known to the checkout; one stuck bit among four does not move the
    median's middle two). ``monitor_code``: one A/D code of the monitor, in A."""
    raw = [(b, lv.mean - base.mean, math.hypot(lv.se, base.se), min(_sigma(lv), _sigma(base)))
           for b, lv in steps]
    if per_code is None:
        slopes = sorted(d / (1 << b) for b, d, _, _ in raw)
        k = len(slopes)
        per_code = 0.5 * (slopes[(k - 1) // 2] + slopes[k // 2]) if k else math.nan
    return [Step(b, d, se, (1 << b) * per_code,
                 (1 << b) * per_code >= MIN_STEP_CODES * monitor_code or sigma >= DITHER_CODES * monitor_code)
            for b, d, se, sigma in raw]


def _sigma(lv: Level) -> float:
    """The reads' own spread (A)."""
    return lv.se * math.sqrt(lv.n) if lv.n > 1 and math.isfinite(lv.se) else 0.0


def summary(steps: list[Step]) -> tuple[list[Step], list[Step]]:
    """The stuck steps and the steps the noise left unjudged."""
    return [s for s in steps if s.verdict == "stuck"], [s for s in steps if s.verdict == "noise"]


def place_code(co: Any, write: Callable[[float], None], signal: str, code: int, per_code: float) -> int:
    """Command (``write``, in the channel's units) what makes DAC channel ``signal`` latch
    ``code``: a few corrections from the code read back (``dac_counts``, the service's own
    calibration between units and codes); returns the code written."""
    x, got = (code - DAC_ZERO_CODE) * per_code, -1
    for _ in range(4):
        write(x)
        co.t.wait(0.01)
        got = int(co.inputs().channel(signal)["dac_counts"])
        if got == code:
            break
        x += (code - got) * per_code
    return got


def read_fine(co: Any, signal: str, code: int, got: int, target_se: float, window_s: float, max_s: float,
              zero: float = 0.0) -> Level:
    """A/D input ``signal`` read once a frame (a frame read twice is no new sample) until its
    mean's standard error is ``target_se`` or less, after at least ``window_s`` and at most
    ``max_s``: the :class:`Level` of ``code`` (``got`` written), ``zero`` taken off."""
    t0, reads, last = co.t.now(), [], None
    while True:
        s = co.inputs()
        if int(s.frame) != last:
            last = int(s.frame)
            reads.append(float(s.channel(signal)["adc_value"]))
        el = co.t.now() - t0
        if el >= max_s or (el >= window_s and level(code, got, reads).se <= target_se):
            return level(code, got, reads, zero)
        co.t.wait(co.poll_s)


def worst_step(steps: list[Step]) -> float:
    """The smallest step as a fraction of its worth (a steps row's value); nan with none."""
    return min((s.step / s.want for s in steps if s.want), default=math.nan)


def steps_why(stuck: list[int], unjudged: list[int], signal: str, added: str = "added nothing",
              hidden: str = "the monitor's noise hides the step") -> str:
    """What a steps row adds to its detail: the first ``stuck`` bit of DAC channel
    ``signal`` (its step of 2^b codes ``added``), else the bits left ``unjudged`` (the
    noise, ``hidden``), else nothing."""
    if stuck:
        b = stuck[0]
        return f": data bit D{b} of DAC channel {signal} stuck at 0 or at 1 (adding 2^{b} codes {added})"
    if unjudged:
        return f"; not judged ({hidden}): " + ", ".join(f"D{b}" for b in unjudged)
    return ""


def bit_of_codes(codes: float, bits: Iterable[int]) -> int | None:
    """The first data bit of ``bits`` whose 2^b codes ``codes`` is, within 30 %; None when
    none is."""
    return next((b for b in bits if abs(abs(codes) - (1 << b)) <= 0.3 * (1 << b)), None)


def adc_offset_bit(rack: Any, signal: str, offset: float) -> tuple[float, int | None]:
    """An offset of A/D input ``signal`` (``offset`` in its engineering units) in its codes,
    and the data bit (D3 and up) whose 2^b codes that is, within 30 % (None when none is)."""
    codes = offset / (float(rack.channel(signal).scale) or 1.0) / ADC_VOLTS_PER_CODE
    return codes, bit_of_codes(codes, ADC_OFFSET_BITS)


def step_levels(at: Callable[[int], Level], base: int,
                bits: Iterable[int]) -> tuple[Level, list[tuple[int, Level]]] | None:
    """The levels ``at`` reads at code ``base`` and at ``base`` + 2^b for each of ``bits``:
    the base's and each bit's; None when the service wrote other codes than those asked."""
    first = at(base)
    steps = [(b, at(base + (1 << b))) for b in bits]
    if any(lv.got != lv.code for lv in (first, *(lv for _, lv in steps))):
        return None
    return first, steps
