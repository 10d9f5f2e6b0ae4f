"""A RegisterBus through a CAEN VME bridge, with CAEN's official binding (caen-libs).

A V1718 (USB) or a V2718/V3718/V4718 (optical CONET link through an A2818/A3818/A4818/
A5818 card, or USB/Ethernet on the V3718/V4718) is the crate's master; CAEN's VMELib
(``libCAENVME.so``, from CAEN, not from PyPI) runs every cycle and the ``caen-libs``
package (``pip install 'pfma-rack[caen]'``) is its Python binding. URL::

    caen://BOARD/LINK[?node=N&am=0x29]

- ``BOARD``: a ``caenvme.BoardType`` name, case-insensitive: ``V1718``, ``V2718``,
  ``USB_V3718``, ``PCIE_A3818_V3718``, ``USB_V4718``, ``ETH_V4718`` ... The names of a
  CONET *card* alone (``A2818``, ``A3818``, ``A5818``, ``USB_A4818_LOCAL``) and every
  ``*_LOCAL`` name open the card's or bridge's own registers, not the crate, and are
  refused with the URL to use instead (a V2718 behind an A3818 is ``caen://V2718/LINK``).
- ``LINK``: the link number (the USB device index for a V1718, the optical link of the
  PCI/PCIe card for a V2718); for ``ETH_V4718`` the bridge's IP address or host name.
- ``node``: the bridge's position in the CONET daisy chain (default 0).
- ``am``: the A16 address modifier, ``0x29`` (non-privileged data, the default) or
  ``0x2D`` (supervisory data).

**Assumption (address modifier):** the rack's boards answer A16 non-privileged data
cycles, AM 0x29. The VMIC boards are jumpered for supervisory and/or non-privileged
short I/O (0x2D/0x29, the hardware-registers reference notes); EPICS's VMIVME-4100
driver used supervisory, and the IRSS I/O processor, a 68k in supervisor mode, would
have issued 0x2D. If every access ends in a bus error, try ``?am=0x2D``.

Cycles (the binding's ``Device`` methods):

- ``read16/write16``: one ``read_cycle``/``write_cycle`` with ``DataWidth.D16``; the
  value is the VME word as D15..D0 carry it (big-endian), no swap.
- ``read8/write8``: one ``DataWidth.D8`` cycle: D08(O) at an odd address (where the
  8-bit chips of the MVME400/410 sit), D08(EO) at an even one. Whether a board answers
  a byte cycle is the board's business: a bus error comes back as :class:`BusError`.
- ``read_block16/write_block16``: VME defines no block-transfer address modifier for
  A16 (BLT/MBLT exist only for A24/A32), so there is no A16 BLT. A block is a list of
  single D16 cycles sent in **one** ``multi_read``/``multi_write`` call (VMELib's
  ``CAENVME_MultiRead/MultiWrite``: one USB or CONET transaction for the whole list, not
  one per word), at most :data:`MULTI_CYCLES_MAX` cycles per call. If the bridge says
  ``NOT_SUPPORTED``, the bus falls back, for good, to a loop of single cycles inside
  the one Python call.

Errors: a cycle the bridge reports as ``BUS_ERROR`` (BERR: nobody answered) is a
:class:`BusError` ``(addr, width, op, reason=...)`` raised ``from`` the binding's
``caenvme.Error``; so is any other failed cycle (``COMM_ERROR``: cable or link lost,
``TIMEOUT_ERROR`` ...), as on the Modbus bus, so drivers handle every failed access
the same way. In a failed multi-cycle write the bridge names the failed cycles; the
cycles after the first failure may or may not have run (VMELib does not say).
Opening: caen-libs missing, or CAEN's ``libCAENVME.so`` missing, is one
:class:`BusUrlError` saying what to install; a bridge that does not answer
``Device.open`` is a :class:`LinkError`.

One lock serialises the cycles of one bus object (VMELib calls release the GIL).
"""

from __future__ import annotations

import importlib
import re
import threading
from collections.abc import Sequence
from types import ModuleType
from typing import Any, Callable
from urllib.parse import parse_qsl, urlsplit

from drivers.bus import BusUrlError, check_addr, check_block, check_value, check_words
from drivers.bus.base import BusBase
from pfma.errors import BusError, LinkError

__all__ = ["CaenBus", "open_caen_bus", "load_binding", "AM_A16_USER", "AM_A16_SUPER",
           "MULTI_CYCLES_MAX", "MISSING_BINDING", "MISSING_LIBRARY"]

AM_A16_USER = 0x29  #: A16 non-privileged data access (``AddressModifiers.A16_U``)
AM_A16_SUPER = 0x2D  #: A16 supervisory data access (``AddressModifiers.A16_S``)
#: cycles per ``multi_read``/``multi_write`` call. Assumed: VMELib documents no limit;
#: 64 D16 cycles are 128 data bytes, well inside one transaction of every bridge.
MULTI_CYCLES_MAX = 64

MISSING_BINDING = ("the caen bus needs CAEN's Python binding caen-libs, which is not installed; "
                   "install it with: pip install 'pfma-rack[caen]' (and CAEN's VMELib, "
                   "libCAENVME.so, from https://www.caen.it/)")
MISSING_LIBRARY = ("the caen bus needs CAEN's VMELib shared library libCAENVME.so, which was not "
                   "found (caen-libs is installed; it is only the binding); install CAEN VMELib "
                   "from https://www.caen.it/ (and the driver of your bridge: the CAEN USB driver "
                   "for a V1718, the A2818/A3818 driver for an optical link), or add its "
                   "directory to LD_LIBRARY_PATH")

#: board-type names that reach the card's or bridge's own registers, never the crate
_NOT_A_CRATE = re.compile(r"^(A2818|A3818|A5818|USB_A4818_LOCAL|.*_LOCAL)$")


def load_binding() -> ModuleType:
    """Import ``caen_libs.caenvme`` (it loads ``libCAENVME.so`` on import).

    :raises BusUrlError: one message naming what to install when caen-libs or CAEN's
        library is missing
    """
    try:  # by name: the optional extra may be absent when mypy runs
        caenvme = importlib.import_module("caen_libs.caenvme")
    except ImportError:
        raise BusUrlError(MISSING_BINDING) from None
    except (RuntimeError, OSError):  # _utils.Lib: "Library CAENVME not found ..."
        raise BusUrlError(MISSING_LIBRARY) from None
    except AttributeError as err:  # the library lacks a CAENVME_* symbol the binding binds
        raise BusUrlError(f"CAEN's libCAENVME.so is older than caen-libs expects ({err}); "
                          f"install the current CAEN VMELib from https://www.caen.it/") from None
    return caenvme


class CaenBus(BusBase):
    """RegisterBus on an open ``caenvme.Device``: A16 cycles with address modifier ``am``.

    :param device: an open ``caenvme.Device`` (or a double with the same methods)
    :param binding: the ``caenvme`` module (or a double): ``AddressModifiers``,
        ``DataWidth``, ``Error``
    :param am: :data:`AM_A16_USER` (default) or :data:`AM_A16_SUPER`
    :param where: how messages name the bridge (``"V1718 link 0"``)
    """

    def __init__(self, device: Any, binding: Any, *, am: int = AM_A16_USER,
                 where: str = "CAEN bridge") -> None:
        if am not in (AM_A16_USER, AM_A16_SUPER):
            raise ValueError(f"A16 address modifier must be 0x29 (non-privileged data) or 0x2D "
                             f"(supervisory data), not 0x{am:02X}")
        self._dev = device
        self._cv = binding
        self.am = binding.AddressModifiers(am)
        self._d8 = binding.DataWidth.D8
        self._d16 = binding.DataWidth.D16
        self.where = where
        self._lock = threading.Lock()
        self._multi = True  # False once the bridge answered NOT_SUPPORTED to a multi cycle
        self._closed = False

    # -- helpers ------------------------------------------------------------------
    def _fail(self, addr: int, width: int, op: str, err: BaseException) -> BusError:
        code = getattr(err, "code", None)
        name = getattr(code, "name", None)
        if name == "BUS_ERROR":
            reason = f"VME bus error (BERR: no board answered AM 0x{int(self.am):02X}) via {self.where}"
        else:
            reason = f"{self.where}: {err}"
        return BusError(addr, width, op, reason=reason)

    def _cycle(self, addr: int, width: int, op: str, call: Callable[..., Any], *args: Any) -> Any:
        if self._closed:
            raise BusError(addr, width, op, reason=f"{self.where} is closed")
        with self._lock:
            try:
                return call(*args)
            except self._cv.Error as err:
                raise self._fail(addr, width, op, err) from err

    # -- RegisterBus ----------------------------------------------------------------
    def read8(self, addr: int) -> int:
        """One D8 cycle at A16 ``addr`` (D08(O) at an odd address)."""
        check_addr(addr)
        return int(self._cycle(addr, 8, "read", self._dev.read_cycle, addr, self.am, self._d8)) & 0xFF

    def read16(self, addr: int) -> int:
        """One D16 cycle at even A16 ``addr``; the big-endian word as the bus carries it."""
        self._even(addr, "read")
        return int(self._cycle(addr, 16, "read", self._dev.read_cycle, addr, self.am, self._d16)) & 0xFFFF

    def write8(self, addr: int, value: int) -> None:
        """One D8 write cycle at A16 ``addr``."""
        check_addr(addr)
        value = check_value(addr, value, 8)
        self._cycle(addr, 8, "write", self._dev.write_cycle, addr, value, self.am, self._d8)

    def write16(self, addr: int, value: int) -> None:
        """One D16 write cycle of ``value`` at even A16 ``addr``."""
        self._even(addr, "write")
        value = check_value(addr, value, 16)
        self._cycle(addr, 16, "write", self._dev.write_cycle, addr, value, self.am, self._d16)

    def read_block16(self, addr: int, n: int) -> list[int]:
        """``n`` words from even ``addr`` upward: D16 single cycles in one multi-read call
        per :data:`MULTI_CYCLES_MAX` words (A16 has no block transfer)."""
        check_block(addr, n, "read")
        out: list[int] = []
        for start in range(0, n, MULTI_CYCLES_MAX):
            base = addr + 2 * start
            addrs = [base + 2 * i for i in range(min(MULTI_CYCLES_MAX, n - start))]
            out.extend(v & 0xFFFF for v in self._multi_cycles("read", addrs, None))
        return out

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """Write ``words`` from even ``addr`` upward, in address order: D16 single cycles in
        one multi-write call per :data:`MULTI_CYCLES_MAX` words. Every value is checked
        before the first cycle."""
        values = check_words(addr, words)
        for start in range(0, len(values), MULTI_CYCLES_MAX):
            chunk = values[start:start + MULTI_CYCLES_MAX]
            base = addr + 2 * start
            self._multi_cycles("write", [base + 2 * i for i in range(len(chunk))], chunk)

    def _multi_cycles(self, op: str, addrs: list[int], data: list[int] | None) -> list[int]:
        if self._multi:
            ams = [self.am] * len(addrs)
            dws = [self._d16] * len(addrs)
            try:
                if data is None:
                    return list(self._cycle(addrs[0], 16, op, self._dev.multi_read, addrs, ams, dws))
                self._cycle(addrs[0], 16, op, self._dev.multi_write, addrs, data, ams, dws)
                return []
            except BusError as err:
                if getattr(getattr(err.__cause__, "code", None), "name", None) != "NOT_SUPPORTED":
                    raise
                self._multi = False  # nothing ran; from now on single cycles
            except RuntimeError as err:  # the binding: "multi_read failed at cycles {i: 'BUS_ERROR'}"
                raise self._multi_failure(op, addrs, err) from err
        if data is None:
            return self._read_singly(addrs)
        self._write_singly(addrs, data)
        return []

    def _multi_failure(self, op: str, addrs: list[int], err: RuntimeError) -> BusError:
        failed = re.findall(r"(\d+): '(\w+)'", str(err))
        if not failed:
            return BusError(addrs[0], 16, op, reason=f"{self.where}: {err}")
        i, code = int(failed[0][0]), failed[0][1]
        what = (f"VME bus error (BERR: no board answered AM 0x{int(self.am):02X})" if code == "BUS_ERROR"
                else code)
        more = f"; {len(failed) - 1} later cycle(s) of the block failed too" if len(failed) > 1 else ""
        return BusError(addrs[i] if i < len(addrs) else addrs[0], 16, op,
                        reason=f"{what} via {self.where}, cycle {i} of a {len(addrs)}-word block{more}")

    # -- lifetime ---------------------------------------------------------------------
    def describe(self) -> str:
        kind = "non-privileged" if int(self.am) == AM_A16_USER else "supervisory"
        return f"CAEN VMELib, {self.where}: A16 {kind} data (AM 0x{int(self.am):02X}), D16/D08(O) cycles"

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._lock:
            self._dev.close()

    def __repr__(self) -> str:
        return f"CaenBus({self.where!r}, am=0x{int(self.am):02X})"


def _board_type(binding: Any, name: str, url: str) -> Any:
    names = {m.name.upper(): m for m in binding.BoardType if m.name != "INVALID"}
    key = name.upper()
    if key not in names:
        known = ", ".join(sorted(n for n in names if not _NOT_A_CRATE.match(n)))
        raise ValueError(f"bus URL {url!r}: unknown CAEN board type {name!r}; known: {known}")
    if _NOT_A_CRATE.match(key):
        raise ValueError(f"bus URL {url!r}: {key} opens the CONET card's or bridge's own registers, "
                         f"not the VME crate; name the crate's bridge instead, e.g. caen://V2718/LINK"
                         f"?node=N for a V2718 behind an A2818/A3818, caen://PCIE_A3818_V3718/LINK "
                         f"for a V3718")
    return names[key]


def _int(text: str, name: str, url: str) -> int:
    try:
        v = int(text, 0)
    except ValueError:
        raise ValueError(f"bus URL {url!r}: {name}={text!r} is not an integer") from None
    if v < 0:
        raise ValueError(f"bus URL {url!r}: {name}={text!r} is negative")
    return v


def open_caen_bus(url: str, *, binding: Any = None) -> CaenBus:
    """``open_bus("caen://BOARD/LINK[?node=N&am=0x29]")``.

    :param binding: the ``caenvme`` module, or a double of it (tests); default: import it
    :raises BusUrlError: caen-libs or libCAENVME.so missing (what to install)
    :raises ValueError: a malformed URL, an unknown board type or option
    :raises LinkError: the bridge did not answer ``Device.open``
    """
    if not url.startswith("caen://"):
        raise ValueError(f"not a caen:// bus URL: {url!r}")
    parts = urlsplit(url)
    board = parts.netloc
    link = parts.path.strip("/")
    if not board or not link or "/" in link:
        raise ValueError(f"bus URL {url!r} needs a board type and a link: caen://V1718/0")
    opts = {"node": 0, "am": AM_A16_USER}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key not in opts:
            raise ValueError(f"bus URL {url!r}: unknown option {key!r}; known: am, node")
        opts[key] = _int(value, key, url)
    if opts["am"] not in (AM_A16_USER, AM_A16_SUPER):
        raise ValueError(f"bus URL {url!r}: am must be 0x29 (A16 non-privileged data) or 0x2D "
                         f"(A16 supervisory data)")
    arg: int | str
    if board.upper().startswith("ETH_"):
        arg = link  # the V4718's IP address or host name
    else:
        arg = _int(link, "link", url)
    cv = load_binding() if binding is None else binding
    board_type = _board_type(cv, board, url)
    where = f"{board_type.name} link {arg}" + (f" node {opts['node']}" if opts["node"] else "")
    try:
        device = cv.Device.open(board_type, arg, opts["node"])
    except cv.Error as err:
        raise LinkError(f"cannot open the CAEN bridge {where}: {err}; is it powered and "
                        f"connected, and its driver loaded (CAEN USB driver for a V1718, "
                        f"A2818/A3818 driver for an optical link)?") from err
    return CaenBus(device, cv, am=opts["am"], where=where)
