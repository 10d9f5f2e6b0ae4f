"""3Dconnexion SpaceMouse (USB HID) as a 6-axis hand controller, through hidapi.

Report formats (packages.md section 5, from PySpaceMouse's device tables):

- report ID 1, 7 bytes: translation x, y, z as int16 little-endian (bytes 1-6);
- report ID 2, 7 bytes: rotation rx, ry, rz as int16 LE (older devices send 1 then 2);
- report ID 3: button bitmask from byte 1 on (little-endian across bytes);
- newer wireless models: one 13-byte report ID 1 with all six axes.

On Linux the ``hidraw`` module of the hidapi wheel is used (kernel hidraw backend,
non-exclusive, permissions from a udev rule on /dev/hidraw*); elsewhere ``hid``.
The backend ("opener": anything with ``enumerate(vid, pid)`` and ``device()``) is
injectable, so tests run on :class:`fakes.hid.FakeHidBackend`.

Unplug and re-plug: a read error marks the device disconnected (state invalid, fault,
deadman released) and the driver retries enumerate/open every ``retry_s`` seconds of
its clock, without restarting anything. A caller that must not wait on enumerate/open
(the I/O service's frame: hidapi's enumerate walks udev) calls ``update(connect=False)``
and leaves the re-connection to another thread (:meth:`HidSpaceMouse.connect`, see
``ioservice.tasks.HandTask``).

Staleness: a SpaceMouse sends a report only when the puck or a button changes, so a
quiet device is not a stale one; the data are current while the device is open, and
stale (invalid, deadman released) from the first failed read on (ASSUMED: the kernel
fails the hidraw read at once on an unplug, as hidapi's ``read error`` on an unplugged
device shows in the packages reference notes).
"""

from __future__ import annotations

import struct
import sys
from typing import Any, Iterable

from drivers.crl.state import HandControllerState, clamp_unit, safe_state
from drivers.ratewindow import RateWindow
from pfma.clock import Clock, MonotonicClock

VENDOR_3DCONNEXION = 0x256F  #: packages.md 5
VENDOR_LOGITECH = 0x046D  #: older 3Dconnexion units (packages.md 5)

#: Logitech-vendor product ids that are 3Dconnexion devices. 0xC626 (SpaceNavigator) is from
#: packages.md 5; the rest are recalled from public device tables (assumed). Any other 0x046D
#: product (mice, keyboards) is ignored; every 0x256F product is accepted.
LOGITECH_SPACE_PIDS: frozenset[int] = frozenset(
    {0xC603, 0xC605, 0xC606, 0xC621, 0xC623, 0xC625, 0xC626, 0xC627, 0xC628, 0xC629, 0xC62B})

FULL_SCALE_COUNTS = 350.0  #: nominal full deflection (packages.md 5: "about +-350 counts")
READ_SIZE = 64  #: bytes asked per hid read
MAX_REPORTS_PER_UPDATE = 64  #: drain at most this many reports per update()

#: device axes (x, y, z, rx, ry, rz) -> hand-controller frame (state.py: x fwd, y left, z up).
#: ASSUMED device convention: x right, y toward the user, z down (PySpaceMouse flips y and z
#: to get "up" and "forward"). Then fwd = -y, left = -x, up = -z; the same proper rotation
#: maps the rotation vector: roll = -ry, pitch = -rx, yaw = -rz. Verify with the lab test.
#: Entries: (device axis index, sign) for state axes x, y, z, roll, pitch, yaw.
AXIS_MAP: tuple[tuple[int, int], ...] = ((1, -1), (0, -1), (2, -1), (4, -1), (3, -1), (5, -1))

#: HandControllerState.buttons for source "hid" is the device's own mask (bit0 = left button,
#: bit1 = right button on two-button models). DEADMAN_BUTTON_BIT is the button held as the
#: deadman (assumed: the left button; a SpaceMouse has no deadman of its own).
DEADMAN_BUTTON_BIT = 0


def parse_report(report: bytes | list[int]) -> dict:
    """One HID input report -> ``{"translation": (x,y,z)}``, ``{"rotation": ...}``,
    ``{"translation":..., "rotation":...}`` (13-byte form), ``{"buttons": mask}`` or ``{}``
    for a report this driver does not use. Values are raw counts.
    """
    data = bytes(report)
    if not data:
        return {}
    rid = data[0]
    if rid == 1 and len(data) >= 13:
        x, y, z, rx, ry, rz = struct.unpack_from("<6h", data, 1)
        return {"translation": (x, y, z), "rotation": (rx, ry, rz)}
    if rid == 1 and len(data) >= 7:
        return {"translation": struct.unpack_from("<3h", data, 1)}
    if rid == 2 and len(data) >= 7:
        return {"rotation": struct.unpack_from("<3h", data, 1)}
    if rid == 3 and len(data) >= 2:
        return {"buttons": int.from_bytes(data[1:], "little")}
    return {}


def default_opener() -> Any:
    """hidapi's ``hidraw`` module on Linux (non-exclusive), else its ``hid`` module.

    :raises ImportError: hidapi is not installed
    """
    if sys.platform.startswith("linux"):
        try:
            import hidraw  # hidapi's kernel-hidraw module (non-exclusive)

            return hidraw
        except ImportError:
            pass
    import hid

    return hid


_default_opener = default_opener  # older name


def _is_spacemouse(info: dict, vendor_ids: tuple[int, ...], product_id: int | None) -> bool:
    vid, pid = info.get("vendor_id"), info.get("product_id")
    if vid not in vendor_ids:
        return False
    if product_id is not None:
        return pid == product_id
    return vid != VENDOR_LOGITECH or pid in LOGITECH_SPACE_PIDS


class HidSpaceMouse:
    """A SpaceMouse over hidapi, with unplug/re-plug handling.

    :param vendor_id: one id or several (default 3Dconnexion 0x256F and legacy 0x046D)
    :param product_id: restrict to one product (default: any SpaceMouse)
    :param path: open this hidraw path instead of enumerating
    :param opener: hidapi-like module (``enumerate``, ``device``); default ``hidraw`` on Linux
    :param clock: time base for timestamps and retries (default monotonic)
    :param full_scale_counts: counts that give |axis| = 1 (default 350)
    :param retry_s: seconds between reconnection attempts
    :param deadman_button: button bit held as deadman; None = deadman whenever connected
    :param axis_map: (device index, sign) per state axis, default :data:`AXIS_MAP`
    """

    def __init__(self, vendor_id: int | Iterable[int] = (VENDOR_3DCONNEXION, VENDOR_LOGITECH),
                 product_id: int | None = None, path: bytes | str | None = None,
                 opener: Any = None, clock: Clock | None = None, *,
                 full_scale_counts: float = FULL_SCALE_COUNTS, retry_s: float = 1.0,
                 deadman_button: int | None = DEADMAN_BUTTON_BIT,
                 axis_map: tuple[tuple[int, int], ...] = AXIS_MAP) -> None:
        if full_scale_counts <= 0:
            raise ValueError(f"full_scale_counts must be > 0, got {full_scale_counts}")
        self.vendor_ids = (vendor_id,) if isinstance(vendor_id, int) else tuple(vendor_id)
        self.product_id = product_id
        self.path = path.encode() if isinstance(path, str) else path
        self.opener = opener if opener is not None else default_opener()
        self.clock = clock if clock is not None else MonotonicClock()
        self.full_scale_counts = float(full_scale_counts)
        self.retry_s = retry_s
        self.deadman_button = deadman_button
        self.axis_map = axis_map
        self.device: Any = None
        self.device_path: bytes | None = None
        self.product = ""
        self.connects = 0
        self.disconnects = 0
        self.reports = 0
        self.last_error = ""
        self._counts = [0] * 6  # device x, y, z, rx, ry, rz
        self._buttons = 0
        self._rate = RateWindow(1.0)  # reports per second over the last second
        self.t_last_report_s = self.clock.now()  #: clock time of the last report (or connect)
        self._next_try = self.clock.now()
        self._state = safe_state("hid", self._next_try, "not connected")

    @property
    def connected(self) -> bool:
        return self.device is not None

    @property
    def state(self) -> HandControllerState:
        return self._state

    def enumerate(self) -> list[dict]:
        """The SpaceMouse entries hidapi lists (generic-desktop multi-axis first)."""
        found = [d for vid in self.vendor_ids
                 for d in (self.opener.enumerate(vid, self.product_id or 0) or [])
                 if _is_spacemouse(d, self.vendor_ids, self.product_id)]
        # usage page 1 / usage 8 = multi-axis controller; prefer that interface
        found.sort(key=lambda d: (d.get("usage_page"), d.get("usage")) != (1, 8))
        return found

    def connect(self) -> bool:
        """Try once to find and open the device; True when open."""
        now = self.clock.now()
        self._next_try = now + self.retry_s
        path, product = self.path, ""
        if path is None:
            try:
                found = self.enumerate()
            except (OSError, ValueError) as err:
                self.last_error = f"SpaceMouse: enumerate failed: {err}"
                return False
            if not found:
                self.last_error = ("SpaceMouse: none found (vendor "
                                   + "/".join(f"0x{v:04X}" for v in self.vendor_ids) + ")")
                return False
            path, product = found[0].get("path"), found[0].get("product_string") or ""
        dev = self.opener.device()
        try:
            dev.open_path(path)
            dev.set_nonblocking(1)
        except (OSError, ValueError) as err:
            self.last_error = f"SpaceMouse: open {path!r} failed: {err} (udev permission on /dev/hidraw*?)"
            try:
                dev.close()
            except (OSError, ValueError):
                pass
            return False
        try:
            self.product = product or dev.get_product_string() or "SpaceMouse"
        except (OSError, ValueError, AttributeError):
            self.product = product or "SpaceMouse"
        self._counts = [0] * 6
        self._buttons = 0
        self.t_last_report_s = now
        self.connects += 1
        self.last_error = ""
        # the device last: a frame that calls update(connect=False) while another thread
        # connects sees either no device or a fully set-up one
        self.device_path = path
        self.device = dev
        return True

    def _disconnect(self, why: str) -> None:
        dev, self.device = self.device, None
        self.disconnects += 1
        self.last_error = why
        self._next_try = self.clock.now() + self.retry_s
        try:
            dev.close()
        except (OSError, ValueError):
            pass

    @property
    def reconnect_due(self) -> bool:
        """Disconnected, and ``retry_s`` has passed since the last attempt."""
        return self.device is None and self.clock.now() >= self._next_try

    def rate_hz(self, now: float | None = None) -> float:
        """Reports per second over the last second (0 for a puck at rest: it reports only
        on change)."""
        return self._rate.rate_hz(self.clock.now() if now is None else now)

    def update(self, connect: bool = True) -> HandControllerState:
        """Read every pending report (non-blocking) and return the current state.

        :param connect: while disconnected, try enumerate/open here when ``retry_s`` has
            passed; False leaves that to the caller (another thread calling :meth:`connect`)

        Never raises for device trouble; unplugged -> invalid state with ``fault=True``.
        """
        now = self.clock.now()
        if self.device is None and not (connect and now >= self._next_try and self.connect()):
            self._state = safe_state("hid", now, self.last_error or "not connected")
            return self._state
        for _ in range(MAX_REPORTS_PER_UPDATE):
            try:
                rep = self.device.read(READ_SIZE, 0)
            except (OSError, ValueError) as err:
                self._disconnect(f"SpaceMouse {self.device_path!r}: read failed ({err}); unplugged?")
                self._state = safe_state("hid", now, self.last_error)
                return self._state
            if not rep:
                break
            self._apply(parse_report(rep), now)
        return self._make_state(now)

    def _apply(self, parsed: dict, now: float) -> None:
        if not parsed:
            return
        self.reports += 1
        self.t_last_report_s = now
        self._rate.mark(now)
        if "translation" in parsed:
            self._counts[0:3] = parsed["translation"]
        if "rotation" in parsed:
            self._counts[3:6] = parsed["rotation"]
        if "buttons" in parsed:
            self._buttons = parsed["buttons"]

    def _make_state(self, now: float) -> HandControllerState:
        axes = tuple(clamp_unit(sign * self._counts[i] / self.full_scale_counts)
                     for i, sign in self.axis_map)
        if self.deadman_button is None:
            deadman = True
        else:
            deadman = bool(self._buttons >> self.deadman_button & 1)
        # the device reports only on change, so its last values are current: t_s = now
        self._state = HandControllerState(axes, deadman, self._buttons, "hid", now,
                                          True, False, "", tuple(self._counts))
        return self._state

    def close(self) -> None:
        if self.device is not None:
            dev, self.device = self.device, None
            try:
                dev.close()
            except (OSError, ValueError):
                pass
        self._state = safe_state("hid", self.clock.now(), "closed", fault=False)
