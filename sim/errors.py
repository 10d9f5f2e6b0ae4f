"""A simulated rack with a real rack's imperfections: seeded :class:`fakes.arm_params.SimErrors`.

``--sim-errors SEED`` on every tool that starts a simulated rack (``pfma serve``,
``checkout``, ``calibrate``, ``controller --sim``, ``console --sim``) and ``errors_seed`` in
a scenario file draw one set of errors from :data:`BOUNDS`, the same set for the same seed
and rack, so a run can be repeated and a test can compare a calibration's result with the
truth. Seed 0 is the perfect rack (every error zero), as without the option.

The errors are the fake's ground truth: they change what the boards read and what the arm
does, and ``pfma fault list --active`` says them (:func:`describe`); they are never in the
Bit3 buffer, so nothing downstream can read the answer instead of measuring it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fakes.arm_params import AXES, N_AXES, N_JOINTS, SimErrors
from pfma.rack import RackConfig, load_rack


@dataclass(frozen=True)
class Bound:
    """An error drawn uniformly in +-``limit`` (``units``); ``why`` names the basis."""

    limit: float
    units: str
    why: str


#: plausible bounds of each seeded error. ASSUMED (no PFMA rack data is public): typical
#: data-sheet figures for a 12-bit VME analog board, a brushless-resolver mount, a DC tach
#: and its filter card, a PWM rate servo card and a strain-gauge F/T transducer; large
#: enough that an uncalibrated rack is visibly wrong, small enough that every channel still
#: works. docs/simulated-arm.md "A rack's imperfections" lists them.
BOUNDS: dict[str, Bound] = {
    "adc_gain_error": Bound(0.003, "fraction", "12-bit ADC board gain error, +-0.3 % of reading"),
    "adc_offset_v": Bound(0.010, "V", "ADC offset, +-10 mV (2 LSB of a +-10 V 12-bit board is 9.8 mV)"),
    "dac_gain_error": Bound(0.003, "fraction", "12-bit DAC board gain error, +-0.3 %"),
    "dac_offset_v": Bound(0.010, "V", "DAC offset, +-10 mV"),
    "resolver_offset_rad": Bound(np.radians(2.0), "rad", "resolver zero against the joint's DH zero, +-2 deg "
                                                        "(mounting)"),
    "tach_scale_error": Bound(0.03, "fraction", "tach constant and filter-card gain, +-3 %"),
    "amp_gain_error": Bound(0.10, "fraction", "rate servo card gain spread, +-10 %"),
    "ft_offset_force": Bound(3.0, "N", "F/T transducer force bias, +-3 N"),
    "ft_offset_torque": Bound(0.15, "N*m", "F/T transducer torque bias, +-0.15 N*m"),
    "ft_drift_force": Bound(0.002, "N/s", "F/T force bias drift, +-0.002 N/s (7 N an hour, warming up)"),
    "ft_drift_torque": Bound(0.0001, "N*m/s", "F/T torque bias drift, +-0.0001 N*m/s"),
}

#: the seeded noise figures, drawn uniformly in ``low``..``limit`` (1 sigma, counts). ASSUMED
#: for the A/D (no DVME-611 noise figure is public: a 12-bit VME A/D's transition noise and the
#: rack wiring's pick-up); the resolver's from pfma-model 8.4 ("noise +-1 LSB", read as a
#: peak within about 3 sigma)
NOISE: dict[str, tuple[float, Bound]] = {
    "adc_noise_counts": (0.4, Bound(1.2, "counts", "A/D conversion noise, 0.4..1.2 LSB rms")),
    "resolver_noise_counts": (0.2, Bound(0.4, "counts", "resolver noise, 0.2..0.4 LSB rms (+-1 LSB peak)")),
}


def parse_seed(text: str) -> int:
    """``--sim-errors SEED``: a whole number >= 0 (0: the perfect rack).

    :raises ValueError: naming what was given"""
    try:
        seed = int(text, 10)
    except (TypeError, ValueError):
        raise ValueError(f"--sim-errors takes a seed, a whole number >= 0 (0: no errors), not {text!r}") from None
    if seed < 0:
        raise ValueError(f"--sim-errors takes a seed, a whole number >= 0 (0: no errors), not {text!r}")
    return seed


def seeded(seed: int, rack: RackConfig | None = None) -> SimErrors:
    """The errors of seed ``seed`` on ``rack`` (default: the report's): every ADC and DAC
    channel's gain and offset, every resolver's zero, every tach's scale, every amplifier's
    gain and the F/T bias and drift, each uniform within :data:`BOUNDS`, and the A/D and
    resolver noise within :data:`NOISE`. Seed 0: no errors, no noise.
    The motion faults and panel switches stay off (``--sim-fault`` sets those)."""
    if seed == 0:
        return SimErrors()
    rack = rack if rack is not None else load_rack()
    rng = np.random.default_rng(seed)

    def draw(name: str, n: int) -> list[float]:
        lim = BOUNDS[name].limit
        return [float(v) for v in rng.uniform(-lim, lim, n)]

    adc = [c.signal for c in rack.channels() if c.device == "adc"]
    dac = [c.signal for c in rack.channels() if c.device == "dac"]
    errors = dict(
        resolver_offset_rad=tuple(draw("resolver_offset_rad", N_JOINTS)),
        tach_scale_error=tuple(draw("tach_scale_error", N_AXES)),
        amp_gain_error=tuple(draw("amp_gain_error", N_AXES)),
        adc_gain_error=dict(zip(adc, draw("adc_gain_error", len(adc)))),
        adc_offset_v=dict(zip(adc, draw("adc_offset_v", len(adc)))),
        dac_gain_error=dict(zip(dac, draw("dac_gain_error", len(dac)))),
        dac_offset_v=dict(zip(dac, draw("dac_offset_v", len(dac)))),
        ft_offset=tuple(draw("ft_offset_force", 3) + draw("ft_offset_torque", 3)),
        ft_drift_per_s=tuple(draw("ft_drift_force", 3) + draw("ft_drift_torque", 3)),
    )
    # drawn after the errors above, so a seed's errors are the same as before noise was added
    for name, (low, b) in NOISE.items():
        errors[name] = float(rng.uniform(low, b.limit))
    return SimErrors(**errors, noise_seed=seed)


def describe(errors: SimErrors) -> list[str]:
    """The rack errors in force, one line per kind (``pfma fault list --active``); [] for a
    perfect rack."""
    out: list[str] = []

    def worst(values: dict[str, float] | tuple, scale: float, fmt: str, units: str) -> str | None:
        items = list(values.items()) if isinstance(values, dict) else \
            [(AXES[i].joint if i < len(AXES) else str(i), v) for i, v in enumerate(values)]
        items = [(k, v) for k, v in items if v]
        if not items:
            return None
        k, v = max(items, key=lambda kv: abs(kv[1]))
        return f"{len(items)} channel(s), largest {k} {v * scale:{fmt}} {units}"

    for label, values, scale, fmt, units in (
            ("ADC gain error", errors.adc_gain_error, 100.0, "+.3f", "%"),
            ("ADC offset", errors.adc_offset_v, 1e3, "+.2f", "mV"),
            ("DAC gain error", errors.dac_gain_error, 100.0, "+.3f", "%"),
            ("DAC offset", errors.dac_offset_v, 1e3, "+.2f", "mV"),
            ("resolver zero", errors.resolver_offset_rad, 180.0 / np.pi, "+.3f", "deg"),
            ("tach scale error", errors.tach_scale_error, 100.0, "+.2f", "%"),
            ("amplifier gain error", errors.amp_gain_error, 100.0, "+.1f", "%")):
        line = worst(values, scale, fmt, units)
        if line:
            out.append(f"rack error: {label}: {line}")
    if errors.adc_noise_counts or errors.resolver_noise_counts:
        out.append(f"rack error: noise (1 sigma): A/D {errors.adc_noise_counts:.2f} counts, resolvers "
                   f"{errors.resolver_noise_counts:.2f} counts")
    if any(errors.ft_offset) or any(errors.ft_drift_per_s):
        f, d = errors.ft_offset, errors.ft_drift_per_s
        out.append("rack error: F/T bias (N, N*m) " + " ".join(f"{v:+.3f}" for v in f)
                   + "; drift per hour " + " ".join(f"{v * 3600:+.2f}" for v in d))
    return out
