"""The board catalogue: every board kind a rack file may name, and where its parts live.

One row per kind: the device class the service schedules it as, its channel count, and
the three parts a newcomer looks for -- the register table (shared by driver and fake),
the driver and the register-level fake -- as ``"module:attribute"`` references, resolved
only when asked for (a tool that reads one RTD never imports the serial driver, and this
module imports no board code at all). Channel counts are the IRSS report's (3.4.2).

Who asks: :mod:`pfma.rack` validates a rack file against :func:`board_kind` (device
class, channel count, register window, serial bit rates); :class:`drivers.rackio.RackIO`
builds drivers from :attr:`BoardKind.driver`; :class:`fakes.rack.FakeRack` builds
fakes from :attr:`BoardKind.fake`; ``pfma regs`` prints :meth:`BoardKind.description`.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from pfma.errors import ConfigError

__all__ = ["BoardKind", "CATALOG", "board_kind", "resolve"]


def resolve(target: str) -> Any:
    """The object a ``"module:attribute"`` reference names (imported on first use)."""
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)


@dataclass(frozen=True)
class BoardKind:
    """One board kind of the catalogue."""

    kind: str  #: the rack file's ``kind``, e.g. "vmivme4940"
    device: str  #: device class: rtd, adc, dac, serial, pio
    channels: int  #: channels a rack file lists for it (IRSS report 3.4.2)
    table: str  #: "module:ATTR" of its register table (a BoardDescription)
    driver: str  #: "module:Class" of its driver; constructor (bus, base, name=...)
    fake: str  #: "module:Class" of its register-level fake (used by fakes.rack only)

    def description(self):
        """The register table (``drivers.registers.BoardDescription``)."""
        return resolve(self.table)

    @property
    def window(self) -> int:
        """Bytes of A16 space the board decodes from its base (from the register table)."""
        return int(self.description().window)

    def serial_rates(self) -> tuple[float, ...]:
        """The bit rates a serial board's baud generator offers (empty for other devices)."""
        if self.device != "serial":
            return ()
        codes = resolve(self.table.partition(":")[0] + ":BAUD_CODES")
        return tuple(sorted(codes.values()))


#: kind -> row; the order is the order `pfma regs` lists them in
CATALOG: dict[str, BoardKind] = {b.kind: b for b in (
    BoardKind("vmivme4940", "rtd", 4, "drivers.rtd.registers:VMIVME4940",
              "drivers.rtd.vmivme4940:Vmivme4940", "fakes.rtd:FakeVmivme4940"),
    BoardKind("vmivme4100", "dac", 16, "drivers.dac.registers:VMIVME4100",
              "drivers.dac.vmivme4100:Vmivme4100", "fakes.dac:FakeVmivme4100"),
    BoardKind("dvme611", "adc", 32, "drivers.adc.registers:DVME611",
              "drivers.adc.dvme611:Dvme611", "fakes.adc:FakeDvme611"),
    BoardKind("mvme400", "serial", 2, "drivers.mvme400.registers:MVME400",
              "drivers.mvme400:Mvme400", "fakes.mvme400:FakeMvme400"),
    BoardKind("mvme410", "pio", 4, "drivers.pio.registers:MVME410",
              "drivers.pio.mvme410:Mvme410", "fakes.mvme410:FakeMvme410"),
)}


def board_kind(kind: str) -> BoardKind:
    """The catalogue row of ``kind``.

    :raises ConfigError: an unknown kind, naming the known ones
    """
    try:
        return CATALOG[kind]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown board kind {kind!r}; known: {', '.join(sorted(CATALOG))}") from None
