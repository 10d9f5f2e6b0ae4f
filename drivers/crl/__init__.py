"""Hand controllers: CAE rate controller (ADC volts), CRL force-reflecting master
(serial, placeholder framing in :mod:`drivers.crl.crl_codec`) and a USB SpaceMouse
(hidapi). All three produce one :class:`HandControllerState` (frame and signs in
:mod:`drivers.crl.state`).

Exports are loaded lazily, so ``fakes.crl`` can import the protocol table
``drivers.crl.crl_codec`` without loading any driver.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "AXES": "drivers.crl.state",
    "HandControllerState": "drivers.crl.state",
    "CaeAxisCal": "drivers.crl.cae",
    "CaeCalibration": "drivers.crl.cae",
    "CaeHandController": "drivers.crl.cae",
    "CrlHandController": "drivers.crl.crl",
    "HidSpaceMouse": "drivers.crl.hid",
    "parse_report": "drivers.crl.hid",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    try:
        module = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'drivers.crl' has no attribute {name!r}") from None
    return getattr(importlib.import_module(module), name)


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
