"""argparse types for the numbers the verbs take: a value out of its range is a usage
mistake, reported by argparse as ``pfma VERB: error: argument --FLAG: ...`` with exit 2
before anything starts (never a run that does nothing, or a late exit 1)."""

from __future__ import annotations

import argparse
import math
from typing import Callable


def _number(kind: Callable[[str], float], text: str) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if kind is int else 'a number'}") \
            from None
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (durations, rates, speeds)."""
    v = _number(float, text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be greater than 0")
    return v


def nonneg_float(text: str) -> float:
    """A finite number >= 0 (waits where 0 has a meaning, delays)."""
    v = _number(float, text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text} must not be negative")
    return v


def whole_number(text: str) -> int:
    """Any whole number (a count whose range its verb checks with its own message)."""
    return int(_number(int, text))


def positive_int(text: str) -> int:
    """A whole number >= 1 (counts, frames)."""
    v = int(_number(int, text))
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text} must be 1 or more")
    return v


def nonneg_int(text: str) -> int:
    """A whole number >= 0 (counts where 0 means 'no limit')."""
    v = int(_number(int, text))
    if v < 0:
        raise argparse.ArgumentTypeError(f"{text} must not be negative")
    return v


def float_in(lo: float, hi: float, unit: str = "") -> Callable[[str], float]:
    """A finite number in [lo, hi]."""
    def check(text: str) -> float:
        v = _number(float, text)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{text} outside {lo:g}..{hi:g}{(' ' + unit) if unit else ''}")
        return v
    return check


def camera_number(text: str) -> int:
    """A camera of the matrix switcher: 1..3, or 0 = blank the monitor (docs/cameras.md)."""
    from controller.routes import BLANK, CAMERAS
    v = int(_number(int, text))
    if v != BLANK and v not in CAMERAS:
        raise argparse.ArgumentTypeError(f"{text} is not a camera: {CAMERAS[0]}..{CAMERAS[-1]}, or {BLANK} to blank "
                                         f"the monitor")
    return v


def monitor_number(text: str) -> int:
    """A monitor of the matrix switcher: 1..2 (docs/cameras.md)."""
    from controller.routes import MONITORS
    v = int(_number(int, text))
    if v not in MONITORS:
        raise argparse.ArgumentTypeError(f"{text} is not a monitor: {MONITORS[0]}..{MONITORS[-1]}")
    return v


def sim_errors_seed(text: str) -> int:
    """``--sim-errors SEED``: the seed of a simulated rack's imperfections (sim/errors.py);
    0 is the perfect rack."""
    from sim.errors import parse_seed
    try:
        return parse_seed(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("--sim-errors takes ")) from None


def add_sim_errors(parser) -> None:
    """``--sim-errors SEED`` on a verb that starts a simulated rack."""
    parser.add_argument("--sim-errors", type=sim_errors_seed, default=0, metavar="SEED",
                        help="simulated rack only: give it a real rack's imperfections, drawn from SEED: "
                             "ADC/DAC gain and offset, resolver zeros, tach scales, amplifier gains, F/T "
                             "bias and drift, A/D and resolver noise (docs/simulated-arm.md; 0, the default: "
                             "none)")


def shoulder_roll_degrees(text: str) -> int:
    """A shoulder-roll index position in degrees: -90, -45, 0, 45 or 90 (pfma-model 8.1);
    another value is refused naming them."""
    from pfma.arm import check_shoulder_roll_deg
    try:
        return check_shoulder_roll_deg(_number(float, text))
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
