"""Fake 3Dconnexion SpaceMouse behind the subset of hidapi the driver uses.

A :class:`FakeHidDevice` is the physical unit (settable axes and buttons, ``unplug()``
/ ``replug()``) and also an hidapi-like *opener*: ``enumerate(vid, pid)`` lists it
while plugged, ``device()`` returns a :class:`FakeHidHandle` with hidapi's
``hid.device`` surface (``open``, ``open_path``, ``set_nonblocking``,
``read(max_length, timeout_ms)``, ``get_product_string``, ``close``).

Behaviour copied from hidapi 0.15 (packages.md section 5): ``read`` returns a list
of ints, ``[]`` when nothing is pending, raises ``ValueError("not open")`` on an
unopened handle and ``OSError("read error")`` after an unplug; ``open`` of a missing
device raises ``OSError("open failed")``. A handle opened before an unplug stays dead
after the re-plug, as a real hidraw file descriptor does.

Report formats: report 1 = translation (3 x int16 LE), 2 = rotation, 3 = buttons, or
one 13-byte report 1 with all six axes (``combined=True``, newer wireless models).
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Sequence


def _i16(v: int) -> int:
    return max(-32768, min(32767, int(v)))


class FakeHidHandle:
    """What ``opener.device()`` returns: one (possibly opened) handle to the unit."""

    def __init__(self, unit: "FakeHidDevice") -> None:
        self._unit = unit
        self._generation: int | None = None  # plug generation the handle was opened in
        self.nonblocking = False

    def _open(self) -> None:
        if not self._unit.plugged:
            raise OSError("open failed")
        self._generation = self._unit.generation
        self._unit.opens += 1

    def open(self, vendor_id: int = 0, product_id: int = 0, serial_number: str | None = None) -> None:
        if (vendor_id, product_id) != (self._unit.vendor_id, self._unit.product_id):
            raise OSError("open failed")
        self._open()

    def open_path(self, path: bytes | str) -> None:
        p = path.encode() if isinstance(path, str) else bytes(path)
        if p != self._unit.path:
            raise OSError("open failed")
        self._open()

    def set_nonblocking(self, v: int | bool) -> int:
        self.nonblocking = bool(v)
        return 0

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        if self._generation is None:
            raise ValueError("not open")
        if not self._unit.plugged or self._generation != self._unit.generation:
            raise OSError("read error")
        self._unit.reads += 1
        if not self._unit.reports:
            return []  # timeout / nothing pending
        return list(self._unit.reports.popleft()[:max_length])

    def get_product_string(self) -> str:
        if self._generation is None:
            raise ValueError("not open")
        return self._unit.product_string

    def close(self) -> None:
        self._generation = None


class FakeHidDevice:
    """One fake SpaceMouse (the physical unit) and an hidapi-like opener for it.

    :param vendor_id: USB vendor id (default 0x256F, 3Dconnexion)
    :param product_id: USB product id (default 0xC635, SpaceMouse Compact)
    :param combined: send the 13-byte all-axes report instead of the 1 + 2 pair
    :param path: hidraw path reported by ``enumerate``
    """

    def __init__(self, vendor_id: int = 0x256F, product_id: int = 0xC635, *, combined: bool = False,
                 path: bytes = b"/dev/hidraw-fake0", product_string: str = "SpaceMouse Compact (fake)",
                 usage_page: int = 1, usage: int = 8) -> None:
        self.vendor_id = vendor_id
        self.product_id = product_id
        self.combined = combined
        self.path = path
        self.product_string = product_string
        self.usage_page = usage_page
        self.usage = usage
        self.plugged = True
        self.generation = 0  #: +1 per re-plug
        self.reports: deque[bytes] = deque()  #: input reports waiting to be read
        self.translation = (0, 0, 0)
        self.rotation = (0, 0, 0)
        self.buttons = 0
        self.opens = 0
        self.reads = 0

    # -- physical side ------------------------------------------------------------------
    def set_axes(self, translation: Sequence[int], rotation: Sequence[int] = (0, 0, 0)) -> None:
        """Move the puck (device counts, about +-350 full scale); queues the report(s)."""
        self.translation = tuple(_i16(v) for v in translation)
        self.rotation = tuple(_i16(v) for v in rotation)
        if self.combined:
            self.queue_report(struct.pack("<B6h", 1, *self.translation, *self.rotation))
        else:
            self.queue_report(struct.pack("<B3h", 1, *self.translation))
            self.queue_report(struct.pack("<B3h", 2, *self.rotation))

    def set_buttons(self, mask: int) -> None:
        """Button bitmask (bit0 left, bit1 right); queues report 3."""
        self.buttons = int(mask)
        self.queue_report(bytes([3]) + self.buttons.to_bytes(2, "little"))

    def queue_report(self, report: bytes) -> None:
        """Queue one raw input report (report id in byte 0) while plugged."""
        if self.plugged:
            self.reports.append(bytes(report))

    def unplug(self) -> None:
        """Pull the cable: pending reports are lost, open handles fail, enumerate is empty."""
        self.plugged = False
        self.reports.clear()

    def replug(self) -> None:
        """Plug it back in (a new hidraw node; old handles stay dead)."""
        self.plugged = True
        self.generation += 1

    # -- opener (hidapi module surface) ---------------------------------------------------
    def info(self) -> dict:
        return {"path": self.path, "vendor_id": self.vendor_id, "product_id": self.product_id,
                "product_string": self.product_string, "manufacturer_string": "3Dconnexion (fake)",
                "serial_number": "", "usage_page": self.usage_page, "usage": self.usage,
                "interface_number": 0, "release_number": 0x0100}

    def enumerate(self, vendor_id: int = 0, product_id: int = 0) -> list[dict]:
        if not self.plugged:
            return []
        if vendor_id and vendor_id != self.vendor_id:
            return []
        if product_id and product_id != self.product_id:
            return []
        return [self.info()]

    def device(self) -> FakeHidHandle:
        return FakeHidHandle(self)


class FakeHidBus:
    """Several fake HID units behind one opener (e.g. a SpaceMouse beside a plain mouse)."""

    def __init__(self, *units: FakeHidDevice) -> None:
        self.units = list(units)

    def enumerate(self, vendor_id: int = 0, product_id: int = 0) -> list[dict]:
        return [d for u in self.units for d in u.enumerate(vendor_id, product_id)]

    def device(self) -> "_BusHandle":
        return _BusHandle(self)


class _BusHandle:
    """A handle that binds to whichever unit ``open_path``/``open`` names."""

    def __init__(self, bus: FakeHidBus) -> None:
        self._bus = bus
        self._h: FakeHidHandle | None = None

    def open_path(self, path: bytes | str) -> None:
        p = path.encode() if isinstance(path, str) else bytes(path)
        for u in self._bus.units:
            if u.path == p:
                self._h = u.device()
                self._h.open_path(p)
                return
        raise OSError("open failed")

    def open(self, vendor_id: int = 0, product_id: int = 0, serial_number: str | None = None) -> None:
        for u in self._bus.units:
            if (u.vendor_id, u.product_id) == (vendor_id, product_id):
                self._h = u.device()
                self._h.open(vendor_id, product_id)
                return
        raise OSError("open failed")

    def __getattr__(self, name: str):
        if self._h is None:
            if name in ("read", "get_product_string"):
                def not_open(*args, **kwargs):
                    raise ValueError("not open")
                return not_open
            if name == "close":
                return lambda: None
            if name == "set_nonblocking":
                return lambda v: 0
            raise AttributeError(name)
        return getattr(self._h, name)
