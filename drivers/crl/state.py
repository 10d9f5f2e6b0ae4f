"""The one state every hand controller produces: :class:`HandControllerState`.

Frame and sign convention (the same for the CAE rate controller, the CRL
force-reflecting master and a USB SpaceMouse):

- the hand-controller frame is right-handed and sits at the grip centre, seen by the
  operator: **x forward** (away from the operator), **y left**, **z up**. It has the
  orientation of the arm's base frame 0 at q = 0 (pfma-model.md section 8.1: "z0 up,
  x0 forward, y0 to the arm's left"), so a positive deflection means "move the tool
  that way in the base frame" when the operator faces along the arm;
- **roll** is about +x, **pitch** about +y, **yaw** about +z, positive by the
  right-hand rule (so positive pitch tips the grip's nose down, positive yaw turns it
  to the left);
- each axis is normalised to -1..1 (full deflection). What the number means depends
  on the source: a shaped **rate** demand for the CAE controller (pfma-model 8.5), a
  **position** in the CRL master's workspace (8.6: 1.0 = 0.20 m or 60 degrees), a
  deflection for the SpaceMouse.

Safety rule: a consumer moves the arm only when ``valid and deadman and not fault``.
Every driver reports ``deadman=False`` whenever it cannot vouch for the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: axis names in order; ``state.axes[i]`` is ``AXES[i]``
AXES: tuple[str, ...] = ("x", "y", "z", "roll", "pitch", "yaw")

#: accepted values of ``HandControllerState.source``
SOURCES: tuple[str, ...] = ("cae", "crl", "hid")

ZERO_AXES: tuple[float, ...] = (0.0,) * 6


@dataclass(frozen=True)
class HandControllerState:
    """One sample of a hand controller (immutable; safe to hand between threads)."""

    axes: tuple[float, ...] = ZERO_AXES  #: x, y, z, roll, pitch, yaw, each -1..1 (see module doc)
    deadman: bool = False  #: True only while the operator holds the deadman AND the data are trusted
    buttons: int = 0  #: the source's raw button bitmask (bit meanings: BUTTONS of each driver)
    source: str = "cae"  #: "cae", "crl" or "hid"
    t_s: float = 0.0  #: clock time (seconds, the driver's clock) at which these data were taken
    valid: bool = False  #: the axes hold real data from the device (False before the first sample)
    fault: bool = False  #: link or device fault (watchdog, unplugged, ADC error); deadman is then False
    reason: str = ""  #: short human text explaining ``fault``/``valid`` (empty when all is well)
    raw: tuple[float, ...] = field(default=(), compare=False)  #: source units: volts or counts

    def __post_init__(self) -> None:
        if len(self.axes) != 6:
            raise ValueError(f"HandControllerState needs 6 axes, got {len(self.axes)}")
        if self.source not in SOURCES:
            raise ValueError(f"unknown hand-controller source {self.source!r}; known: {SOURCES}")
        for name, a in zip(AXES, self.axes):
            if not (math.isfinite(a) and -1.0 <= a <= 1.0):
                raise ValueError(f"hand-controller axis {name} = {a!r} outside -1..1")

    @property
    def active(self) -> bool:
        """True when motion may be commanded: valid, no fault, deadman held."""
        return self.valid and self.deadman and not self.fault

    def axis(self, name: str) -> float:
        """One axis by name (``"x"`` ... ``"yaw"``)."""
        return self.axes[AXES.index(name)]

    def as_dict(self) -> dict:
        d: dict[str, object] = {name: a for name, a in zip(AXES, self.axes)}
        d.update(deadman=self.deadman, buttons=self.buttons, source=self.source, t_s=self.t_s,
                 valid=self.valid, fault=self.fault, reason=self.reason)
        return d

    def format(self) -> str:
        """One fixed-width line for terminals."""
        ax = " ".join(f"{n}={a:+.3f}" for n, a in zip(AXES, self.axes))
        flags = ("DEADMAN" if self.deadman else "released") + (" VALID" if self.valid else " invalid")
        if self.fault:
            flags += " FAULT"
        txt = f"t={self.t_s:9.3f} {self.source} {ax} buttons=0x{self.buttons:02X} {flags}"
        return txt + (f" ({self.reason})" if self.reason else "")


def clamp_unit(v: float) -> float:
    """Clamp to -1..1; NaN becomes 0 (fail safe)."""
    if v != v:  # NaN
        return 0.0
    return -1.0 if v < -1.0 else 1.0 if v > 1.0 else float(v)


def safe_state(source: str, t_s: float, reason: str, *, fault: bool = True,
               buttons: int = 0) -> HandControllerState:
    """The fail-safe state: zero axes, deadman released, not valid."""
    return HandControllerState(ZERO_AXES, False, buttons, source, t_s, False, fault, reason)
