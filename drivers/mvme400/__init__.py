"""Motorola MVME400 dual RS-232C serial module (uPD7201 + MC6821) driver and byte port.

Exports are loaded lazily, so ``import drivers.mvme400.registers`` (used by the fake)
does not import the driver module.
"""

from __future__ import annotations

__all__ = ["Mvme400", "Mvme400Port"]


def __getattr__(name: str):
    if name in __all__:
        from drivers.mvme400 import mvme400
        return getattr(mvme400, name)
    raise AttributeError(f"module 'drivers.mvme400' has no attribute {name!r}")
