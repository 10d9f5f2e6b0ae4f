"""Every board of a rack configuration, with its driver, on one RegisterBus.

``RackIO(bus, rack)`` builds the driver of each board (imported lazily by device
class, so a tool that only reads an RTD never imports the serial driver) and reads
any channel by signal name in engineering units, for the checkout tools
(``pfma read``). Engineering value = ``scale * volts + offset`` for analog channels
(the rack file's convention, ``pfma/rack_default.toml`` header); RTD angles are
radians from the resolver counts; the DAC is write-only (hardware-registers.md
section 2: "can't read the VMIC 4100"), so its value is the driver's shadow.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.bus import RegisterBus
from drivers.catalog import board_kind, resolve
from pfma.clock import Clock
from pfma.errors import BoardError, ConfigError, did_you_mean
from pfma.rack import BoardConfig, Channel, RackConfig

__all__ = ["RackIO", "Reading"]



@dataclass(frozen=True)
class Reading:
    """One channel read by :meth:`RackIO.read_signal`."""

    signal: str
    value: float | int  #: engineering units
    units: str
    raw: int  #: counts (rtd, adc), shadow code (dac), port byte (pio)
    note: str = ""  #: e.g. "(shadow)" for the write-only DAC

    def __iter__(self):  # value, units, raw = rackio.read_signal(...)
        return iter((self.value, self.units, self.raw))


class RackIO:
    """The rack's drivers on ``bus``.

    :param bus: any RegisterBus (fake rack, Modbus gateway, device file)
    :param rack: the rack configuration (boards, addresses, channel scales)
    :param clock: passed to drivers that wait (the serial board); None: their default
    """

    def __init__(self, bus: RegisterBus, rack: RackConfig, clock: Clock | None = None) -> None:
        self.bus = bus
        self.rack = rack
        self.clock = clock
        self._drivers: dict[str, object] = {}

    def driver(self, board: str | BoardConfig):
        """The driver of one board (built on first use)."""
        cfg = board if isinstance(board, BoardConfig) else self._board(board)
        drv = self._drivers.get(cfg.name)
        if drv is None:
            drv = self._build(cfg)
            self._drivers[cfg.name] = drv
        return drv

    def drivers(self) -> dict[str, object]:
        """Every board's driver, by board name."""
        return {b.name: self.driver(b) for b in self.rack.boards}

    def _board(self, name: str) -> BoardConfig:
        try:
            return self.rack.board(name)
        except KeyError:
            known = ", ".join(b.name for b in self.rack.boards)
            raise ConfigError(f"no board named {name!r} in rack {self.rack.name} ({self.rack.source}); "
                              f"known: {known}") from None

    def _build(self, cfg: BoardConfig):
        target = board_kind(cfg.kind).driver
        try:
            cls = resolve(target)
        except (ImportError, AttributeError) as err:
            raise BoardError(f"board {cfg.name} ({cfg.kind} at A16 0x{cfg.base:04X}): driver "
                             f"{target} is not available: {err}") from err
        if cfg.device == "serial" and self.clock is not None:
            return cls(self.bus, cfg.base, name=cfg.name, clock=self.clock)
        return cls(self.bus, cfg.base, name=cfg.name)

    def channel(self, signal: str) -> Channel:
        try:
            return self.rack.channel(signal)
        except KeyError:
            hint = did_you_mean(signal, (c.signal for c in self.rack.channels())) or "; see `pfma channels`"
            raise ConfigError(f"no channel named {signal!r} in rack {self.rack.name} "
                              f"({self.rack.source}){hint}") from None

    def read_signal(self, signal: str) -> Reading:
        """Read one channel by signal name, in engineering units.

        :raises ConfigError: unknown signal
        :raises BoardError: a channel that has no value to read (serial lines)
        :raises BusError: naming board, register and address
        """
        ch = self.channel(signal)
        drv = self.driver(ch.board)
        where = f"{ch.signal} ({ch.board} channel {ch.channel} at A16 0x{ch.address:04X})"
        if ch.device == "rtd":
            counts = int(drv.read_channel_counts(ch.channel))  # one latched read
            return Reading(signal, counts * float(drv.lsb_rad), ch.units, counts)
        if ch.device == "adc":
            counts = int(drv.read_counts(ch.channel))
            volts = float(drv.volts_from_counts(counts))
            return Reading(signal, ch.scale * volts + ch.offset, ch.units, counts)
        if ch.device == "dac":
            volts = float(drv.shadow_volts[ch.channel])
            code = int(drv.shadow_counts[ch.channel])
            return Reading(signal, ch.scale * volts + ch.offset, ch.units, code,
                           "(shadow: the board is write-only)")
        if ch.device == "pio":
            byte = int(drv.read_port(ch.channel))
            return Reading(signal, byte, ch.units, byte)
        if ch.device == "serial":
            raise BoardError(f"{where} is a serial line ({ch.baud or '?'} baud), not a value; "
                             f"use the device's own tool")
        raise BoardError(f"{where}: device class {ch.device!r} cannot be read as a value")
