"""Motorola MC6821 PIA and MVME410 parallel I/O drivers.

Exports are loaded lazily, so ``import drivers.pio.registers`` (used by the fakes)
does not import the driver modules.
"""

from __future__ import annotations

__all__ = ["Pia6821", "Mvme410"]


def __getattr__(name: str):
    if name == "Pia6821":
        from drivers.pio.pia6821 import Pia6821
        return Pia6821
    if name == "Mvme410":
        from drivers.pio.mvme410 import Mvme410
        return Mvme410
    raise AttributeError(f"module 'drivers.pio' has no attribute {name!r}")
