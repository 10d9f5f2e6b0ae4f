"""CAE compact 6-axis rate hand controller, read as nine ADC voltages.

The seed (IRSS report section 3.4.2) wires it to the DVME-611 A/D, channels 16-24:
up/down, forward/backward, right/left, yaw, pitch, roll, discretes 1-3. Channel
numbers come from the rack configuration by signal name (``cae_up_down`` ...), never
from this file. Scaling follows pfma-model.md section 8.5 (ASSUMED there): +-10 V at
full deflection, software deadband +-0.5 V, then quadratic shaping
``u = sign(v) * ((|v| - 0.5) / 9.5)**2``.

Everything about polarity and the discretes is unknown and assumed, in the two
tables :data:`CAE_AXES` and :data:`CAE_DISCRETES` (one edit fixes them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

from drivers.crl.state import AXES, HandControllerState, safe_state
from pfma.clock import Clock, MonotonicClock
from pfma.errors import CalibrationError, PfmaError

#: (rack signal, state axis, assumed sign). ASSUMED polarity: positive volts = the first
#: direction named in the seed's label (up, forward, right) and, for rotations, a positive
#: right-hand rotation in the hand-controller frame (x fwd, y left, z up; see state.py).
#: "right" is -y, hence -1. Nothing public gives the CAE output polarity (pfma-model 2.1).
CAE_AXES: tuple[tuple[str, str, int], ...] = (
    ("cae_up_down", "z", +1),
    ("cae_forward_backward", "x", +1),
    ("cae_right_left", "y", -1),
    ("cae_yaw", "yaw", +1),
    ("cae_pitch", "pitch", +1),
    ("cae_roll", "roll", +1),
)

#: (rack signal, role, bit in HandControllerState.buttons). ASSUMED: the seed has only three
#: discretes and "a pushbutton switch informs the computer when hand controller movements
#: are valid" (seed 3.5.2), so discrete 1 is taken as the deadman (active high, pfma-model
#: 8.5); discretes 2 and 3 are 8.5's B1 (coarse/vernier) and B2 (frame select).
CAE_DISCRETES: tuple[tuple[str, str, int], ...] = (
    ("cae_discrete_1", "deadman", 0x01),
    ("cae_discrete_2", "coarse/vernier (B1)", 0x02),
    ("cae_discrete_3", "frame select base/tool (B2)", 0x04),
)

#: meaning of ``HandControllerState.buttons`` for source "cae"
BUTTONS: dict[int, str] = {bit: role for _, role, bit in CAE_DISCRETES}

#: the nine signals in rack order (the order of ``from_volts``'s argument with the default rack)
CAE_SIGNALS: tuple[str, ...] = tuple(s for s, _, _ in CAE_AXES) + tuple(s for s, _, _ in CAE_DISCRETES)

_N_AXES = len(CAE_AXES)
#: for each of AXES (the state's order): (axis name, its position in CAE_AXES)
_AXIS_SOURCE: tuple[tuple[str, int], ...] = tuple(
    (a, [axis for _, axis, _ in CAE_AXES].index(a)) for a in AXES)

FULL_SCALE_V = 10.0  #: +-10 V at full deflection (pfma-model 8.5, assumed)
DEADBAND_V = 0.5  #: +-5 % of full scale (pfma-model 8.5, assumed)
OVERRANGE_V = 10.5  #: beyond this an axis is reported as a fault (ADC rail / broken wire; assumed)
DISCRETE_THRESHOLD_V = 2.5  #: discrete on above this (TTL-like levels, assumed)
DISCRETE_HYSTERESIS_V = 0.5  #: +-0.25 V around the threshold (assumed)


@dataclass(frozen=True)
class CaeAxisCal:
    """Calibration of one CAE axis (volts at the ADC input)."""

    centre_v: float = 0.0  #: null voltage (stick released)
    deadband_v: float = DEADBAND_V  #: half-width of the deadband around the centre
    span_v: float = FULL_SCALE_V  #: deflection from centre that gives |u| = 1
    sign: int = 1  #: +1 or -1: polarity into the hand-controller frame

    def check(self, axis: str) -> None:
        """:raises CalibrationError: naming the axis, for an unusable calibration"""
        vals = (self.centre_v, self.deadband_v, self.span_v)
        if not all(math.isfinite(v) for v in vals):
            raise CalibrationError(f"CAE axis {axis}: non-finite calibration {vals}")
        if self.sign not in (1, -1):
            raise CalibrationError(f"CAE axis {axis}: sign must be +1 or -1, not {self.sign}")
        if not 0.0 <= self.deadband_v < self.span_v:
            raise CalibrationError(f"CAE axis {axis}: need 0 <= deadband_v ({self.deadband_v}) "
                                   f"< span_v ({self.span_v})")

    def shape(self, volts: float) -> float:
        """Volts -> shaped demand -1..1 (deadband, then quadratic; pfma-model 8.5)."""
        d = volts - self.centre_v
        a = abs(d) - self.deadband_v
        if a <= 0.0:
            return 0.0
        u = min(1.0, (a / (self.span_v - self.deadband_v)) ** 2)
        return math.copysign(u, d) * self.sign


def _default_axes() -> dict[str, CaeAxisCal]:
    return {axis: CaeAxisCal(sign=sign) for _, axis, sign in CAE_AXES}


@dataclass(frozen=True)
class CaeCalibration:
    """Calibration of the whole CAE controller: one :class:`CaeAxisCal` per axis name."""

    axes: dict[str, CaeAxisCal] = field(default_factory=_default_axes)  #: keyed "x" ... "yaw"
    discrete_threshold_v: float = DISCRETE_THRESHOLD_V
    discrete_hysteresis_v: float = DISCRETE_HYSTERESIS_V

    def __post_init__(self) -> None:
        missing = [a for a in AXES if a not in self.axes]
        if missing:
            raise CalibrationError(f"CAE calibration lacks axes {missing}")
        for a in AXES:
            self.axes[a].check(a)
        if not 0.0 <= self.discrete_hysteresis_v < 2 * abs(self.discrete_threshold_v) + 1e-12:
            raise CalibrationError(f"CAE calibration: bad discrete hysteresis {self.discrete_hysteresis_v}")


def _resolve_channels(rack: Any) -> tuple[int, ...]:
    """ADC channel of each of the nine CAE signals, from the rack configuration."""
    if rack is None:
        from pfma.rack import load_rack

        rack = load_rack()
    return tuple(rack.channel(s).channel for s in CAE_SIGNALS)


class CaeHandController:
    """CAE rate hand controller from its nine ADC voltages.

    :param calibration: per-axis centre/deadband/span/sign (default: pfma-model 8.5 values)
    :param rack: rack configuration (default: ``pfma.rack.load_rack()``); gives the channels
    :param clock: time base for ``t_s`` (default monotonic)
    """

    def __init__(self, calibration: CaeCalibration | None = None, rack: Any = None,
                 clock: Clock | None = None) -> None:
        self.calibration = calibration if calibration is not None else CaeCalibration()
        self.clock = clock if clock is not None else MonotonicClock()
        #: ADC channel per signal, in CAE_SIGNALS order (e.g. 16..24 with the default rack)
        self.channels: tuple[int, ...] = _resolve_channels(rack)
        order = sorted(self.channels)
        #: position of each CAE_SIGNALS entry in the ``volts_9`` argument (rack = channel order)
        self._index = tuple(order.index(ch) for ch in self.channels)
        self._discrete_on = [False] * len(CAE_DISCRETES)
        self._state = safe_state("cae", self.clock.now(), "no sample yet", fault=False)

    @property
    def state(self) -> HandControllerState:
        return self._state

    @property
    def adc_channels(self) -> tuple[int, ...]:
        """The nine ADC channels in rack (ascending channel) order: ``from_volts``'s order."""
        return tuple(sorted(self.channels))

    def _discrete(self, i: int, volts: float) -> bool:
        cal = self.calibration
        half = cal.discrete_hysteresis_v / 2
        if self._discrete_on[i]:
            on = volts > cal.discrete_threshold_v - half
        else:
            on = volts > cal.discrete_threshold_v + half
        self._discrete_on[i] = on
        return on

    def from_volts(self, volts_9: Sequence[float], t_s: float | None = None) -> HandControllerState:
        """Nine ADC voltages (rack order: 6 axes then 3 discretes) -> state.

        The discretes have hysteresis, so the result depends on the previous call too.
        A non-finite or over-range axis voltage gives a fault state (deadman released).

        :raises ValueError: when ``volts_9`` does not hold nine values
        """
        t = self.clock.now() if t_s is None else t_s
        if len(volts_9) != len(CAE_SIGNALS):
            raise ValueError(f"CAE hand controller needs {len(CAE_SIGNALS)} voltages (ADC channels "
                             f"{', '.join(map(str, self.adc_channels))}), got {len(volts_9)}")
        v = [float(volts_9[i]) for i in self._index]  # CAE_SIGNALS order
        isfinite = math.isfinite
        buttons = 0
        for i, (_, _, bit) in enumerate(CAE_DISCRETES):
            vi = v[_N_AXES + i]
            if isfinite(vi) and self._discrete(i, vi):
                buttons |= bit
        for k, x in enumerate(v):  # the first bad input names itself: axes over-range, any NaN
            if not isfinite(x) or (k < _N_AXES and abs(x) > OVERRANGE_V):
                self._state = safe_state("cae", t, f"{CAE_SIGNALS[k]} (ADC channel {self.channels[k]}) "
                                         f"reads {x!r} V: out of range", buttons=buttons)
                return self._state
        cal = self.calibration.axes
        deadman = bool(buttons & CAE_DISCRETES[0][2])
        self._state = HandControllerState(
            axes=tuple(cal[a].shape(v[k]) for a, k in _AXIS_SOURCE), deadman=deadman, buttons=buttons, source="cae",
            t_s=t, valid=True, fault=False, reason="", raw=tuple(float(x) for x in volts_9))
        return self._state

    def read(self, read_volts: Callable[[int], float]) -> HandControllerState:
        """Read the nine channels with ``read_volts(adc_channel) -> volts`` and convert.

        A ``PfmaError`` from the reader (e.g. ``BusError`` naming board and address)
        gives a fault state with its message as the reason.
        """
        t = self.clock.now()
        try:
            volts = [read_volts(ch) for ch in self.adc_channels]
        except PfmaError as err:
            self._state = safe_state("cae", t, f"ADC read failed: {err}")
            return self._state
        return self.from_volts(volts, t)

    def calibrate_null(self, samples: Sequence[Sequence[float]],
                       max_spread_v: float = 0.2) -> CaeCalibration:
        """New calibration whose centres are the mean of ``samples`` (volts_9 each).

        pfma-model 8.5: null offset = average of 0.5 s of data with the deadman released.

        :raises CalibrationError: no samples, deadman pressed, or an axis moved more than
            ``max_spread_v`` during the sampling
        """
        if not samples:
            raise CalibrationError("CAE null calibration: no samples")
        threshold = self.calibration.discrete_threshold_v
        axes = dict(self.calibration.axes)
        for k, (sig, axis, _) in enumerate(CAE_AXES):
            col = [float(s[self._index[k]]) for s in samples]
            if not all(math.isfinite(x) for x in col):
                raise CalibrationError(f"CAE null calibration: {sig} has non-finite samples")
            if max(col) - min(col) > max_spread_v:
                raise CalibrationError(f"CAE null calibration: {sig} (ADC channel {self.channels[k]}) "
                                       f"moved {max(col) - min(col):.3f} V; hold the stick still")
            axes[axis] = replace(axes[axis], centre_v=sum(col) / len(col))
        dm = self._index[len(CAE_AXES)]
        if any(float(s[dm]) > threshold for s in samples):
            raise CalibrationError("CAE null calibration: deadman pressed; release it while nulling")
        return replace(self.calibration, axes=axes)
