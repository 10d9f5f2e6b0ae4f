"""The Bit3 buffer's one layout definition: every area, field, offset and unit.

The IRSS I/O chassis and the computational chassis met in a 32 KB dual-port RAM on a
Bit3 bus repeater (IRSS report 3.4.3; ``[bit3] size = 32768`` in the rack file). This
module is the only place that knows where anything sits in that 32 KB. Everything else
(the buffer class, the client, ``pfma layout``, ``docs/bit3-layout.md``) is derived
from :func:`build_layout`.

Rules carried over from the IRSS world model (report 2.2.2 / 2.3.6):

1. a process writes only its own area (here: one *writer role* per area, claimed);
2. any process may read every area;
3. every variable has exactly one writer;
4. every variable always holds a valid value after initialisation (areas start zeroed,
   service state STARTING).

The IRSS communications frame locked the world model while it was updated (2.2.3,
"Assurance of World Model Access Validity", 2.3.6); here each area has a sequence lock
instead, so readers never block the writer and never see half a frame (see shm.py).

Layout shape (fixed; byte offsets in the 32768-byte buffer)::

    0      header              1024  magic, version, hash, area table, owners, frame, state
    1024   inputs             12288  seqlocked, service   - every channel, board, link, F/T, HC
    13312  stats               2048  seqlocked, service   - loop timing, per-device rates
    15360  commands            1024  seqlocked, controller- joint rates, limits, arm requests
    16384  service_messages    4096  seqlocked, service   - 50-entry circular message queue
    20480  controller_stats    2048  seqlocked, controller- the controller's frame timing
    22528  controller_messages 10240 seqlocked, controller- 127-entry circular message queue

Each seqlocked area starts with a 64-byte block holding its 8-byte sequence counter;
the area's *body* (a numpy structured record) follows at +64. Per-channel data sit in
fixed-capacity slot arrays (e.g. ``adc_value[64]``) so that the hot loop can fill a
whole device group with one numpy operation; the rack's channels are assigned slots in
rack order and every channel gets named entries (``Layout.channels``) with its own byte
offsets and units. Capacities leave spare room so that a larger rack keeps the same
field offsets (only the channel names, and hence the layout hash, change).
"""

from __future__ import annotations

import enum
import hashlib
import json
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

from pfma.errors import ConfigError, did_you_mean
from pfma.rack import RackConfig, load_rack
from pfma.show import flag_names

MAGIC = b"PFMABIT3"
#: 2: the controller's message queue holds 127 entries (it took the spare area)
LAYOUT_VERSION = 2
#: The Bit3 dual-port RAM size (IRSS report 3.4.3: windows 0x01ED0000-0x01ED7FFF and
#: 0x800000-0x807FFF, i.e. 32 KB; rack_default.toml ``[bit3] size``).
BUFFER_SIZE = 32768
#: Bytes before each seqlocked area's body: the 8-byte sequence counter, padded to a
#: cache line so the counter and the payload do not share one (perf-limits.md 9).
SEQ_BLOCK = 64
MAX_AREAS = 8
#: Capacity of each circular message queue: "These queues can hold up to 50 messages per
#: processor and are effectively a circular buffer" (IRSS report, user interface section).
MESSAGE_QUEUE_LEN = 50
#: Capacity of the controller's queue. Assumed: the report's seven layers ran on three
#: computational cards (IRSS report 2.4), each with its own 50-message queue; here one process
#: runs all seven, and a long message takes several entries, so its one queue gets every
#: entry the rest of the buffer holds (the former spare area): 127, about 2.5 cards' worth.
#: Measured: a power-up posts ~130 entries in half a second, a trip ~40 in one frame
#: (``sim.system``); with 50 entries a recorder starved for ~250 ms on a loaded host lost
#: entries in the soak (CI, 2026-11-29: 13 entries).
CONTROLLER_QUEUE_LEN = 127
#: entries of each message-queue area
QUEUE_LEN = {"service_messages": MESSAGE_QUEUE_LEN, "controller_messages": CONTROLLER_QUEUE_LEN}
MESSAGE_TEXT_BYTES = 56
#: a message longer than one entry's text continues in the next entries of its queue: every
#: entry of a message but its last has this bit set in its severity byte
#: (``bit3.buffer.MessageQueue`` posts and joins them; a message's entries are written in
#: one sequence-lock section, so a reader sees all or none of them)
MESSAGE_CONTINUES = 0x80
#: and every entry of a message but its first has this bit set: a reader whose window into
#: the ring starts inside a message (its first entries already overwritten) knows the
#: entry is not a message's beginning and skips the rest of that message
MESSAGE_CONTINUED = 0x40
#: the severity byte's bits that carry the severity itself (the rest: the two bits above)
MESSAGE_SEVERITY_MASK = 0x3F
#: entries one message may take: half the ring, so the ring always holds the newest message
#: whole beside others (the bound, stated once: a message carries up to
#: :data:`MESSAGE_MAX_BYTES` = 25 x 56 = 1400 bytes of UTF-8; a longer text is cut, ending "~")
MESSAGE_MAX_ENTRIES = MESSAGE_QUEUE_LEN // 2
MESSAGE_MAX_BYTES = MESSAGE_MAX_ENTRIES * MESSAGE_TEXT_BYTES
OWNER_NAME_BYTES = 32
#: ``owners[i].flags`` bits. CLAIMED: the slot holds a claim (written with the pid; clear
#: once released). SIMULATED: the claimer runs on a simulated rack, the register-level fakes
#: (the I/O service sets it in the slots of its areas when its register bus is the fake rack,
#: directly or through a spy; clear for a hardware bus: a device file, a VME bridge, a Modbus
#: gateway, whose far side the service cannot see). Readers: ``OwnerInfo.simulated``,
#: ``HeaderInfo.rack_kind``.
OWNER_FLAG_CLAIMED = 0x1
OWNER_FLAG_SIMULATED = 0x2

#: slot capacities of the per-channel groups (spare room beyond the default rack)
CAPACITY = {
    "rtd": 16,    # default rack: 2 boards x 4 = 8 (6 joints + 2 unused)
    "adc": 64,    # default rack: 32
    "dac": 32,    # default rack: 16
    "pio": 16,    # 8-bit PIA ports; default rack: 2 boards x 4 = 8
    "board": 16,  # default rack: 7
    "link": 8,    # serial channels of the rack, then EXTRA_LINKS
    "hc": 4,      # HAND_CONTROLLERS
    "device": 8,  # DEVICE_GROUPS
}
#: links that are not rack channels (USB HID hand controller)
EXTRA_LINKS: tuple[str, ...] = ("hid_hand_controller",)
#: hand-controller slots; the sources of drivers/crl/state.py (HandControllerState.source)
HAND_CONTROLLERS: tuple[str, ...] = ("cae", "crl", "hid")
#: HandControllerState axis order (drivers/crl/state.py AXES)
HC_AXES: tuple[str, ...] = ("x", "y", "z", "roll", "pitch", "yaw")
#: device groups with a sample time and a measured rate in the stats area
DEVICE_GROUPS: tuple[str, ...] = ("rtd", "adc", "dac", "ft", "pio", "crl", "hid")
N_JOINTS = 6
N_CURRENT_LIMITS = 7


class ServiceState(enum.IntEnum):
    """``header.service_state``: written by the inputs owner (the I/O service)."""

    STARTING = 0
    SAFE = 1      # outputs at zero, brakes set, waiting for an arm request
    ARMED = 2     # outputs follow the command area
    FAULT = 3     # a fault forced the outputs safe; needs a re-arm request
    STOPPED = 4
    HALTED = 5    # the controller is halted (single-stepping) and holds the outputs safe
    #              (0 V, brakes set) with a live heartbeat: not a fault; needs a re-arm request

    def __str__(self) -> str:
        """The name: ``print(state)`` and ``f"{state}"`` say ARMED, not 2 (issue 29 item 7);
        ``int(state)``, ``f"{state:d}"`` and JSON stay numbers."""
        return self.name


#: bytes of ``inputs.first_trip_text``: the first trip's or refusal's reason since the last
#: arm, cut to this many bytes (assumed: the guard's reasons are one sentence; the whole text
#: is in the service's message queue)
FIRST_TRIP_TEXT_BYTES = 120

class FaultCode(enum.IntEnum):
    """``inputs.fault_code``: why the service is in FAULT (the service writes them, the
    controller and tools read them; the trips' messages carry the same number as their
    code). NONE, then: the heartbeat watchdog, a failed DAC write, failed input boards, an
    unexpected error in the frame; a refused command (SAFE, not FAULT: a field beyond its
    limit or NaN / a writer without the claim); DAC_UNREACHABLE while the DAC board does not
    answer (issue 28 item 5, docs/safety.md "Honest outputs": the service could not write 0 V
    and the outputs may hold their last values, NOT known safe: the console shows a banner),
    which becomes DAC (a DAC write failed, outputs since written 0 V) once a 0 V write
    succeeds again; AMP_ENABLE: the amplifier-enable charge pump could not be written (its
    relay drops the amplifiers); OVERSPEED: the envelope found a joint over speed (issue 28
    item 4). ``str()`` and ``format()`` give the number, as the bare integers did."""

    NONE = 0
    WATCHDOG = 1
    DAC = 2
    INPUTS = 3
    UNEXPECTED = 4
    COMMAND = 5
    FOREIGN = 6
    DAC_UNREACHABLE = 7
    AMP_ENABLE = 8
    OVERSPEED = 9


#: the fault codes by their older names (every importer of ``FAULT_*`` keeps working)
FAULT_NONE, FAULT_WATCHDOG, FAULT_DAC, FAULT_INPUTS, FAULT_UNEXPECTED = (
    FaultCode.NONE, FaultCode.WATCHDOG, FaultCode.DAC, FaultCode.INPUTS, FaultCode.UNEXPECTED)
FAULT_COMMAND, FAULT_FOREIGN = FaultCode.COMMAND, FaultCode.FOREIGN
FAULT_DAC_UNREACHABLE, FAULT_AMP_ENABLE = FaultCode.DAC_UNREACHABLE, FaultCode.AMP_ENABLE
FAULT_OVERSPEED = FaultCode.OVERSPEED
#: ``inputs.fault_code`` by name (``pfma stats``, ``monitor``, ``watch``, the console; pfma/show.py),
#: at most 11 characters (the console's World Status line): the watchdog tripped, a DAC
#: write failed, an input board failed, an unexpected error, a command refused, a foreign
#: writer, the DAC does not answer, the amplifier enable not written, a joint over speed
FAULT_CODE_NAMES = {FAULT_NONE: "none", FAULT_WATCHDOG: "WATCHDOG", FAULT_DAC: "DAC WRITE",
                    FAULT_INPUTS: "INPUT BOARD", FAULT_UNEXPECTED: "UNEXPECTED", FAULT_COMMAND: "CMD REFUSED",
                    FAULT_FOREIGN: "FOREIGN CMD", FAULT_DAC_UNREACHABLE: "DAC LOST", FAULT_AMP_ENABLE: "AMP ENABLE",
                    FAULT_OVERSPEED: "OVERSPEED"}


class MessageCode(enum.IntEnum):
    """The ``code`` of the I/O service's messages (``service_messages`` entries). A trip's
    message carries its :class:`FaultCode` as its code (1-9: one number space shared with
    the output guard's notices below; the severity tells a trip, ERROR, from a notice); the
    rest are named here, their values unchanged."""

    #: the output guard (ioservice/safety.py): arming and disarming
    DISARMED = 2
    ARM_PENDING = 3
    ARM_RATES_NOT_ZERO = 4
    ARMED = 5
    ARM_REFUSED = 6
    #: a command refused while ARMED, and a trip given no fault code (the guard's defaults)
    REFUSED = 7
    TRIPPED = 9
    #: the orderly stop's notice, and the halt's (not trips)
    STOP = 10
    HALT = 11
    #: start-up: started, schedule differs from the documented rates, a slower schedule for
    #: a slow bus, a non-nominal value let through, the direction check (ioservice/direction.py)
    STARTED = 100
    SCHEDULE_DIFFERS = 101
    SLOW_BUS = 102
    NONNOMINAL = 103
    DIRECTION_PENDING = 104
    DIRECTION_CONFIRMED = 105
    DIRECTION_DONE = 106
    #: boards: a start-up that failed, an input sample that failed
    BOARD_INIT_FAILED = 110
    INPUT_FAILED = 111
    #: the F/T sensor: not streaming, its port not opened, streaming after retries, serial
    #: lines not over a gateway, on a CAN node, CAN trouble
    FT_NOT_STREAMING = 120
    FT_PORT_FAILED = 121
    FT_RETRIED = 122
    SERIAL_NOT_OVER_GATEWAY = 123
    FT_CAN = 124
    FT_CAN_TROUBLE = 125
    #: hand controllers: CAE not available, HID open / not open / lost / reconnected
    CAE_UNAVAILABLE = 130
    HID_OPEN = 131
    HID_NOT_OPEN = 132
    HID_LOST = 133
    HID_RECONNECTED = 134
    #: parallel ports and the CRL: matrix route applied / failed, force reflection failed
    MATRIX_ROUTE = 140
    MATRIX_ROUTE_FAILED = 141
    CRL_FORCE_FAILED = 142
    #: stopping: DAC outputs not disabled, stopped, the bus lost
    DAC_NOT_DISABLED = 150
    STOPPED = 151
    BUS_LOST = 152
    CALIBRATION_LOADED = 160
    #: timing and commands: host stall, command status (stale, absent, foreign), long frame
    HOST_STALL = 170
    COMMAND_STATUS = 171
    LONG_FRAME = 172
    #: the motion envelope (ioservice/envelope.py): slew limit, soft-limit envelope, overspeed
    SLEW = 173
    ENVELOPE = 174
    OVERSPEED = 175


#: ``commands.mode`` value of a halted controller (IRSS halt / single step, docs/console.md):
#: it keeps writing (a fresh heartbeat) 0 rates, 0 current limits and no arm request, and the
#: service reports HALTED instead of SAFE; any other value is informational
MODE_HALTED = 2


class Severity(enum.IntEnum):
    """Message severity (message queues)."""

    DEBUG = 0
    INFO = 1
    WARNING = 2
    ERROR = 3
    FATAL = 4


#: writer role -> areas it owns. A role is claimed as a whole (see shm.Bit3Buffer.claim).
WRITER_ROLES: dict[str, tuple[str, ...]] = {
    "service": ("inputs", "stats", "service_messages"),
    "controller": ("commands", "controller_messages", "controller_stats"),
}
#: status bits of the input area, by name (the one definition: the service writes them,
#: the controller, checkout and tools read them)
BOARD_OK, BOARD_INIT, BOARD_FAULT = 1, 2, 4  #: ``board_status``
LINK_OPEN, LINK_SYNCED, LINK_FAULT, LINK_STALE = 1, 2, 4, 8  #: ``link_status``
DAC_CLIPPED, DAC_FORCED_SAFE = 1, 2  #: ``dac_status``: saturated within the limit margin / forced to 0 V
#: ``dac_status``: a rate command saturated by the service's slew limit / held at 0 V by its
#: envelope (braking distance of a soft limit; ioservice/envelope.py)
DAC_SLEWED, DAC_ENVELOPE = 4, 8
RTD_LOSS_OF_SIGNAL, RTD_NO_REFERENCE = 1, 2  #: ``rtd_status`` (from the VMIVME-4940's status)
CHANNEL_BUS_ERROR = 0x100  #: ``rtd_status`` / ``adc_status``: the board did not answer this sample
#: ``inputs.command_status`` bits: what the service made of this frame's command area
CMD_STALE = 1  #: computed from inputs older than the configured age: rate channels at 0 V
CMD_ABSENT = 2  #: no stable copy this frame (writer died mid-write / torn): the last good one kept
CMD_REFUSED = 4  #: a field was NaN, infinite or beyond its limit: outputs made safe
CMD_FOREIGN = 8  #: written by a process that does not hold the claim: refused, outputs made safe
CMD_STATUS_NAMES = {CMD_STALE: "stale", CMD_ABSENT: "absent", CMD_REFUSED: "refused",
                    CMD_FOREIGN: "foreign writer"}
#: ``ft_status``: the F/T controller's status byte (0 ok; 1 overload, |load| > 110 % of full
#: scale: assumed, drivers/serial_ft/protocol.py STATUS_CODES; the driver drops any other)
FT_OVERLOAD = 1
#: the names of each status word's bits, by the kind of entry it belongs to (the one table
#: ``pfma read``, ``watch``, ``monitor``, ``stats`` and the Python handle show them by)
STATUS_BIT_NAMES: dict[str, dict[int, str]] = {
    "rtd": {RTD_LOSS_OF_SIGNAL: "LOS", RTD_NO_REFERENCE: "NOREF", CHANNEL_BUS_ERROR: "BUSERR"},
    "adc": {CHANNEL_BUS_ERROR: "BUSERR"},
    "dac": {DAC_CLIPPED: "CLIPPED", DAC_FORCED_SAFE: "SAFE", DAC_SLEWED: "SLEWED", DAC_ENVELOPE: "ENVELOPE"},
    "pio": {},
    "ft": {FT_OVERLOAD: "OVERLOAD"},
    "board": {BOARD_OK: "PRESENT", BOARD_INIT: "INITIALISED", BOARD_FAULT: "FAULT"},
    "link": {LINK_OPEN: "OPEN", LINK_SYNCED: "SYNCED", LINK_FAULT: "FAULT", LINK_STALE: "STALE"},
}
#: the healthy status word of each kind: shown as ``ok`` (a channel: no bit set; a board:
#: present and initialised; a link: open and synchronised)
STATUS_HEALTHY: dict[str, int] = {"rtd": 0, "adc": 0, "dac": 0, "pio": 0, "ft": 0,
                                  "board": BOARD_OK | BOARD_INIT, "link": LINK_OPEN | LINK_SYNCED}


def status_text(kind: str, bits: int) -> str:
    """A status word as a person reads it: ``ok`` when healthy, else the names of its
    problem bits (``LOS``, ``BUSERR``: the value is the last good sample; a board's
    ``FAULT``; a link's ``STALE``), or what a board or link lacks (``NOT INITIALISED``,
    ``CLOSED``, ``NOT SYNCED``)."""
    bits = int(bits)
    healthy = STATUS_HEALTHY.get(kind, 0)
    if bits == healthy:
        return "ok"
    names = STATUS_BIT_NAMES.get(kind, {})
    problems = flag_names(bits & ~healthy, names, clear="")
    if kind == "board" and not problems:
        return "NOT INITIALISED"
    if kind == "link":
        missing = ("CLOSED" if not bits & LINK_OPEN else
                   "" if bits & (LINK_SYNCED | LINK_FAULT | LINK_STALE) else "NOT SYNCED")
        return "|".join(x for x in (problems, missing) if x)
    return problems or "ok"
#: other accepted spellings of a role: the name of its main area
ROLE_ALIASES = {"inputs": "service", "commands": "controller"}


@dataclass(frozen=True)
class FieldSpec:
    """One field of the buffer. ``offset`` is the absolute byte offset in the 32 KB."""

    name: str
    area: str
    offset: int
    dtype: str  # numpy dtype string of one element, e.g. "<f8"
    shape: tuple[int, ...]
    units: str
    doc: str

    @property
    def np_dtype(self) -> np.dtype:
        """numpy dtype of one element (the record types by their name)."""
        return RECORD_DTYPES[self.dtype] if self.dtype in RECORD_DTYPES else np.dtype(self.dtype)

    @property
    def nbytes(self) -> int:
        return int(self.np_dtype.itemsize * int(np.prod(self.shape, dtype=np.int64)))

    def as_dict(self) -> dict:
        return {"name": self.name, "area": self.area, "offset": self.offset, "dtype": self.dtype,
                "shape": list(self.shape), "nbytes": self.nbytes, "units": self.units, "doc": self.doc}


@dataclass(frozen=True)
class ChannelEntry:
    """Where one named channel (rack signal, board, link, hand controller) lives.

    ``fields`` is a tuple of (field name, slot index, absolute byte offset of that element).
    """

    name: str
    kind: str  # rtd, adc, dac, pio, board, link, hc (inputs), device (stats), command (commands)
    area: str
    slot: int
    units: str
    label: str
    fields: tuple[tuple[str, int, int], ...]
    board: str = ""
    channel: int = -1
    spare: bool = False
    #: the rack channel's role (``pfma.rack`` keys joint, quantity); not part of the layout
    #: hash: it says what a slot means, not where it is
    joint: str = ""
    quantity: str = ""

    def as_dict(self, roles: bool = False) -> dict:
        d = {"name": self.name, "kind": self.kind, "area": self.area, "slot": self.slot,
             "units": self.units,
             "label": self.label, "board": self.board, "channel": self.channel,
             "spare": self.spare,
             "fields": [{"field": f, "index": i, "offset": o} for f, i, o in self.fields]}
        if roles and self.quantity:
            d["joint"], d["quantity"] = self.joint, self.quantity
        return d


@dataclass(frozen=True)
class AreaSpec:
    """One area. ``body_dtype`` is the numpy record type of the body (None for spare)."""

    name: str
    index: int
    offset: int
    size: int
    writer: str  # writer role, "" for header/spare
    seqlocked: bool
    doc: str
    body_dtype: np.dtype | None = field(default=None, compare=False)

    @property
    def body_offset(self) -> int:
        return self.offset + (SEQ_BLOCK if self.seqlocked else 0)

    @property
    def body_size(self) -> int:
        return self.size - (SEQ_BLOCK if self.seqlocked else 0)

    def as_dict(self) -> dict:
        return {"name": self.name, "index": self.index, "offset": self.offset, "size": self.size,
                "writer": self.writer, "seqlocked": self.seqlocked,
                "body_offset": self.body_offset, "body_size": self.body_size, "doc": self.doc}


@dataclass(frozen=True)
class Layout:
    """The whole buffer: areas, fields (non-overlapping) and named channel entries."""

    rack_name: str
    areas: tuple[AreaSpec, ...]
    fields: tuple[FieldSpec, ...]
    channels: tuple[ChannelEntry, ...]
    joint_names: tuple[str, ...]
    current_limit_names: tuple[str, ...]
    hash: bytes = b""
    version: int = LAYOUT_VERSION
    size: int = BUFFER_SIZE

    def area(self, name: str) -> AreaSpec:
        for a in self.areas:
            if a.name == name:
                return a
        raise KeyError(f"no area {name!r} in the Bit3 layout; areas: "
                       f"{', '.join(a.name for a in self.areas)}")

    def field(self, name: str, area: str | None = None) -> FieldSpec:
        for f in self.fields:
            if f.name == name and (area is None or f.area == area):
                return f
        raise KeyError(f"no field {name!r}{' in area ' + area if area else ''} in the Bit3 layout")

    def channel(self, name: str, area: str | None = None) -> ChannelEntry:
        """A named entry; DAC signals have one in ``inputs`` (applied) and one in
        ``commands`` (requested), so give ``area`` when it matters (default: the first)."""
        c = self._channel_index.get((name, area))
        if c is not None:
            return c
        raise KeyError(f"no channel {name!r}{' in area ' + area if area else ''} in the Bit3 "
                       f"layout (rack {self.rack_name})"
                       + did_you_mean(name, {c.name for c in self.channels if area is None or c.area == area}))

    @cached_property
    def _channel_index(self) -> dict[tuple[str, str | None], ChannelEntry]:
        index: dict[tuple[str, str | None], ChannelEntry] = {}
        for c in self.channels:  # the first entry wins, with and without an area
            index.setdefault((c.name, c.area), c)
            index.setdefault((c.name, None), c)
        return index

    @cached_property
    def _slot_index(self) -> dict[tuple[str, str], int]:
        index: dict[tuple[str, str], int] = {}
        for c in self.channels:
            index.setdefault((c.kind, c.name), c.slot)  # the first entry wins, as before
        return index

    def slot(self, kind: str, name: str) -> int:
        """Slot index of a named entry of one group, e.g. ``slot("link", "ft_sensor")``
        (a dict lookup: the service calls this in its frame tasks)."""
        try:
            return self._slot_index[(kind, name)]
        except KeyError:
            raise KeyError(f"no {kind} entry named {name!r} in the Bit3 layout "
                           f"(rack {self.rack_name})"
                           + did_you_mean(name, [c.name for c in self.channels if c.kind == kind])) from None

    def canonical(self) -> dict:
        """The JSON-able description the hash is taken over (no docs)."""
        return {
            "magic": MAGIC.decode(), "version": self.version, "size": self.size,
            "areas": [{k: v for k, v in a.as_dict().items() if k != "doc"} for a in self.areas],
            "fields": [{k: v for k, v in f.as_dict().items() if k != "doc"} for f in self.fields],
            "channels": [c.as_dict() for c in self.channels],
        }

    def as_json(self) -> dict:
        return {"magic": MAGIC.decode(), "version": self.version, "size": self.size,
                "hash": self.hash.hex(), "rack": self.rack_name,
                "areas": [a.as_dict() for a in self.areas],
                "fields": [f.as_dict() for f in self.fields],
                "channels": [c.as_dict(roles=True) for c in self.channels]}

    @property
    def hash_hex(self) -> str:
        return self.hash.hex()

    @cached_property
    def _role_index(self) -> dict[tuple[str, str, str], ChannelEntry]:
        index: dict[tuple[str, str, str], ChannelEntry] = {}
        for c in self.channels:
            if c.quantity:
                index.setdefault((c.kind, c.joint, c.quantity), c)
        return index

    def joint_entry(self, kind: str, joint: str, quantity: str) -> ChannelEntry:
        """The entry of one group carrying ``quantity`` of ``joint`` (the rack's channel
        roles), e.g. ``joint_entry("rtd", "elbow_pitch", "angle")``."""
        try:
            return self._role_index[(kind, joint, quantity)]
        except KeyError:
            raise KeyError(f"no {kind} entry carries the {quantity} of joint {joint!r} in the Bit3 "
                           f"layout (rack {self.rack_name}: channel keys joint, quantity)") from None

    def joint_slot(self, kind: str, joint: str, quantity: str) -> int:
        """Slot of :meth:`joint_entry`."""
        return self.joint_entry(kind, joint, quantity).slot


# ----------------------------------------------------------------------------------------
# building records


class _Record:
    """Accumulates fields of one area body with natural alignment."""

    def __init__(self, area: str, body_offset: int, body_size: int) -> None:
        self.area = area
        self.body_offset = body_offset
        self.body_size = body_size
        self.names: list[str] = []
        self.formats: list = []
        self.offsets: list[int] = []
        self.specs: list[FieldSpec] = []
        self.pos = 0

    def add(self, name: str, dtype: str, shape: tuple[int, ...] = (), units: str = "",
            doc: str = "", align: int | None = None) -> int:
        dt = np.dtype(dtype)
        a = align or min(dt.alignment, 8)
        self.pos = (self.pos + a - 1) // a * a
        off = self.pos
        n = int(np.prod(shape, dtype=np.int64)) if shape else 1
        self.pos += dt.itemsize * n
        if self.pos > self.body_size:
            raise ConfigError(f"Bit3 layout: area {self.area} overflows its {self.body_size} "
                              f"bytes at field {name}")
        self.names.append(name)
        self.formats.append((dt, shape) if shape else dt)
        self.offsets.append(off)
        self.specs.append(FieldSpec(name, self.area, self.body_offset + off, dt.str, tuple(shape),
                                    units, doc))
        return self.body_offset + off

    def dtype(self) -> np.dtype:
        return np.dtype({"names": self.names, "formats": self.formats, "offsets": self.offsets,
                         "itemsize": self.body_size})


def _group(rec: _Record, kind: str, fields: list[tuple[str, str, tuple, str, str]]
           ) -> dict[str, tuple[int, int]]:
    """Add one slot array per field of a group; returns field -> (abs offset, element bytes)."""
    cap = CAPACITY[kind]
    out = {}
    for name, dtype, inner, units, doc in fields:
        off = rec.add(name, dtype, (cap, *inner), units, doc)
        out[name] = (off, np.dtype(dtype).itemsize * int(np.prod(inner, dtype=np.int64) if inner else 1))
    return out


def _entries(area: str, kind: str, names: list[tuple[str, str, str, str, int, bool]],
             group: dict[str, tuple[int, int]], field_units: dict[str, str] | None = None
             ) -> list[ChannelEntry]:
    """Channel entries for slot-ordered names: (name, units, label, board, channel, spare)."""
    cap = CAPACITY[kind]
    if len(names) > cap:
        raise ConfigError(f"Bit3 layout: the rack has {len(names)} {kind} entries but the layout "
                          f"has room for {cap} (raise CAPACITY[{kind!r}] and LAYOUT_VERSION)")
    out = []
    for slot, (name, units, label, board, ch, spare) in enumerate(names):
        fl = tuple((f, slot, off + slot * esize) for f, (off, esize) in group.items())
        out.append(ChannelEntry(name, kind, area, slot, units, label, fl, board, ch, spare))
    return out


# IRSS hardware facts used below (report 3.4.2): RTD = VMIVME-4940 resolver-to-digital
# (16-bit angle words), ADC = Datel DVME-611 12-bit, DAC = VMIVME-4100 12-bit, PIO =
# MVME410 MC6821 8-bit ports.

def _inputs(area: AreaSpec, rack: RackConfig) -> tuple[_Record, list[ChannelEntry]]:
    r = _Record(area.name, area.body_offset, area.body_size)
    r.add("frame", "<u8", units="1", doc="minor-frame number of this snapshot")
    r.add("t_s", "<f8", units="s", doc="service clock time at the start of this frame")
    r.add("service_state", "<u4", units="enum", doc="ServiceState (copy of the header's)")
    r.add("fault_code", "<u4", units="enum", doc="why the service is in FAULT (0 = none)")
    r.add("outputs_enabled", "u1", units="bool", doc="DAC outputs follow the command area")
    r.add("brakes_released", "u1", units="bool", doc="current limits above zero (brakes off)")
    r.add("watchdog_tripped", "u1", units="bool", doc="command heartbeat went stale")
    r.add("command_heartbeat", "<u8", units="1", doc="commands.heartbeat last applied")
    r.add("command_age_s", "<f8", units="s", doc="age of the commands applied this frame")
    r.add("t_rtd_s", "<f8", units="s", doc="time of the resolver sample")
    r.add("t_adc_s", "<f8", units="s", doc="time of the ADC scan")
    r.add("t_ft_s", "<f8", units="s", doc="time of the latest F/T record")
    r.add("t_dac_s", "<f8", units="s", doc="time the DAC outputs were last applied")
    r.add("t_pio_s", "<f8", units="s", doc="time of the PIO input sample")

    rtd = _group(r, "rtd", [
        ("rtd_counts", "<u2", (), "counts", "RDC angle counts as the driver returns them (VMIVME-4940: 14-bit, 0..16383 = 0..2 pi)"),
        ("rtd_angle_rad", "<f8", (), "rad", "joint angle"),
        ("rtd_status", "<u2", (), "bits", "per-channel status bits (RDC LOS/DOS, bus error)"),
    ])
    adc = _group(r, "adc", [
        ("adc_counts", "<u2", (), "counts", "raw 12-bit conversion as read"),
        ("adc_volts", "<f8", (), "V", "input volts"),
        ("adc_value", "<f8", (), "per channel", "engineering value (units per channel)"),
        ("adc_status", "<u2", (), "bits", "per-channel status bits"),
    ])
    dac = _group(r, "dac", [
        ("dac_counts", "<u2", (), "counts", "12-bit code written (command shadow)"),
        ("dac_volts", "<f8", (), "V", "output volts applied"),
        ("dac_value", "<f8", (), "per channel", "engineering command applied (units per channel)"),
        ("dac_status", "<u2", (), "bits", "per-channel status bits (clipped, forced safe)"),
    ])
    pio = _group(r, "pio", [
        ("pio_port_bits", "u1", (), "bits", "8-bit PIA port value (read or written)"),
        ("pio_status", "u1", (), "bits", "per-port status bits"),
    ])
    r.add("pio_user_inputs", "<u2", units="bits", doc="the 16 user I/F box input bits")
    r.add("matrix_route", "<u2", units="bits", doc="matrix switcher route output applied")
    board = _group(r, "board", [
        ("board_status", "<u4", (), "bits", "board status bits (present, init ok, fault)"),
        ("board_errors", "<u4", (), "1", "error counter (bus errors, bad status)"),
        ("board_last_error_addr", "<u4", (), "A16", "address of the last failing access"),
        ("board_last_error_t_s", "<f8", (), "s", "time of the last error"),
    ])
    link = _group(r, "link", [
        ("link_status", "<u4", (), "bits", "link status bits (open, synced, fault)"),
        ("link_records", "<u8", (), "1", "good records received"),
        ("link_bad", "<u8", (), "1", "bad records (checksum, framing)"),
        ("link_resyncs", "<u8", (), "1", "resynchronisations"),
        ("link_errors", "<u8", (), "1", "I/O errors (disconnects, timeouts)"),
        ("link_rate_hz", "<f8", (), "Hz", "measured record rate"),
        ("link_age_s", "<f8", (), "s", "age of the latest good record"),
    ])
    r.add("ft_counts", "<i4", (6,), "counts", "F/T raw gauge/channel counts (Fx Fy Fz Tx Ty Tz)")
    r.add("ft_force_n", "<f8", (3,), "N", "force Fx Fy Fz (sensor frame)")
    r.add("ft_torque_nm", "<f8", (3,), "N*m", "torque Tx Ty Tz (sensor frame)")
    r.add("ft_status", "<u4", units="bits", doc="F/T sensor status word")
    r.add("ft_t_s", "<f8", units="s", doc="F/T record time")
    hc = _group(r, "hc", [
        ("hc_axes", "<f8", (6,), "1", "x y z roll pitch yaw, each -1..1"),
        ("hc_deadman", "u1", (), "bool", "deadman held and data trusted"),
        ("hc_valid", "u1", (), "bool", "axes hold real data"),
        ("hc_fault", "u1", (), "bool", "link or device fault"),
        ("hc_buttons", "<u4", (), "bits", "raw button mask"),
        ("hc_t_s", "<f8", (), "s", "sample time"),
    ])
    # command freshness and refusals (issue "the arm never moves on a stale command")
    r.add("command_inputs_frame", "<u8", units="1",
          doc="inputs frame the applied commands were computed from (commands.inputs_frame)")
    r.add("command_input_age_frames", "<u4", units="1",
          doc="this frame minus command_inputs_frame (rates drive 0 V beyond the configured age)")
    r.add("command_status", "<u4", units="bits",
          doc="1 stale inputs (rates 0 V), 2 absent (torn/stuck write), 4 refused (limit), 8 foreign writer")
    r.add("stale_commands", "<u8", units="1", doc="frames whose rate commands were too old (driven at 0 V)")
    r.add("absent_commands", "<u8", units="1", doc="frames with no stable copy of the command area")
    r.add("refused_commands", "<u8", units="1", doc="commands refused (NaN, inf, beyond limit): outputs safe")
    r.add("foreign_writes", "<u8", units="1", doc="command areas written by a process without the claim")
    r.add("host_stall_s", "<f8", units="s", doc="length of the latest host stall the service saw (0 = none)")
    r.add("host_stall_t_s", "<f8", units="s", doc="when that stall ended")
    # the first cause of the service's trip episode (issue 29 item 3)
    r.add("first_trip_code", "<u4", units="enum",
          doc="message code of the first trip or refusal since the last arm (0 = none)")
    r.add("first_trip_t_s", "<f8", units="s", doc="when that first trip or refusal happened")
    r.add("first_trip_text", "u1", (FIRST_TRIP_TEXT_BYTES,), "utf-8",
          "the first trip or refusal's reason since the last arm (zero-padded; cleared when armed again)")
    return r, _input_entries(area, rack, {"rtd": rtd, "adc": adc, "dac": dac, "pio": pio, "board": board,
                                          "link": link, "hc": hc})


def _input_entries(area: AreaSpec, rack: RackConfig, groups: dict[str, dict[str, tuple[int, int]]]) -> list[ChannelEntry]:
    """The named entries of the input area: every rack channel of the slot groups, every
    board, every serial link and extra link, every hand controller."""
    entries: list[ChannelEntry] = []
    for kind in ("rtd", "adc", "dac", "pio"):
        group = groups[kind]
        names = [(c.signal, c.units, c.label, c.board, c.channel, c.spare)
                 for b in rack.boards_of(kind) for c in b.channels]
        entries += _entries(area.name, kind, names, group)
    entries += _entries(area.name, "board", [(b.name, "", b.title, b.name, -1, False) for b in rack.boards],
                        groups["board"])
    links = [(c.signal, c.units, c.label, c.board, c.channel, c.spare)
             for b in rack.boards_of("serial") for c in b.channels]
    links += [(n, "", n.replace("_", " "), "", -1, False) for n in EXTRA_LINKS]
    entries += _entries(area.name, "link", links, groups["link"])
    entries += _entries(area.name, "hc", [(n, "1", f"{n} hand controller", "", -1, False)
                               for n in HAND_CONTROLLERS], groups["hc"])
    return entries


def _stats(area: AreaSpec) -> tuple[_Record, list[ChannelEntry]]:
    r = _Record(area.name, area.body_offset, area.body_size)
    r.add("frame", "<u8", units="1", doc="frame number when these statistics were computed")
    r.add("t_s", "<f8", units="s", doc="service clock time")
    r.add("frames", "<u8", units="1", doc="frames run since start")
    r.add("dropped_frames", "<u8", units="1", doc="deadlines skipped (never caught up)")
    r.add("overruns", "<u8", units="1", doc="frames whose work ended after the next deadline")
    r.add("stall_events", "<u8", units="1", doc="wake-ups more than 10 periods late")
    r.add("window_frames", "<u8", units="1", doc="frames in the statistics window below")
    r.add("period_s", "<f8", units="s", doc="nominal minor-frame period")
    r.add("rate_hz", "<f8", units="Hz", doc="measured frame rate")
    for n in ("p50", "p99", "p999", "max"):
        r.add(f"wake_latency_{n}_us", "<f8", units="us", doc=f"wake-up latency {n}")
    for n in ("p50", "p99", "max"):
        r.add(f"work_{n}_us", "<f8", units="us", doc=f"frame work time {n}")
    r.add("cpu_percent", "<f8", units="%", doc="service CPU use of one core")
    r.add("gc_gen2", "<u8", units="1", doc="full garbage collections since start")
    dev = _group(r, "device", [
        ("device_rate_hz", "<f8", (), "Hz", "measured sample rate"),
        ("device_t_s", "<f8", (), "s", "time of the latest sample / apply"),
        ("device_samples", "<u8", (), "1", "samples since start"),
        ("device_errors", "<u8", (), "1", "errors since start"),
    ])
    entries = _entries(area.name, "device", [(n, "Hz", f"{n} device group", "", -1, False)
                                  for n in DEVICE_GROUPS], dev)
    return r, entries


def _commands(area: AreaSpec, rack: RackConfig) -> tuple[_Record, list[ChannelEntry], tuple, tuple]:
    """Command area; joint order and limit order come from the rack's DAC channels."""
    joints, limits, grippers = _command_dacs(rack)
    r, offsets = _command_record(area, joints, limits, grippers)
    entries = _command_entries(area.name, joints, limits, grippers, offsets)
    return (r, entries, tuple(c.joint for c in joints),
            tuple(c.signal for c in limits))


def _command_dacs(rack: RackConfig) -> tuple[list, list, list]:
    """The rack's rate, current-limit and gripper DAC channels (in board order).

    :raises ConfigError: when there are more than the command area has room for
    """
    dac = [c for b in rack.boards_of("dac") for c in b.channels if not c.spare]
    joints = [c for c in dac if c.quantity == "rate_command"]
    limits = [c for c in dac if c.quantity == "current_limit"]
    grippers = [c for c in dac if c.quantity == "gripper_command"]
    if len(joints) > N_JOINTS or len(limits) > N_CURRENT_LIMITS or len(grippers) > 1:
        raise ConfigError(f"Bit3 layout: rack {rack.name} has {len(joints)} rate, {len(limits)} "
                          f"current-limit and {len(grippers)} gripper DAC channels; the command "
                          f"area has room for {N_JOINTS}, {N_CURRENT_LIMITS} and 1")
    return joints, limits, grippers


def _command_record(area: AreaSpec, joints: list, limits: list,
                    grippers: list) -> tuple[_Record, tuple[int, int, int]]:
    """The command area's record, and the offsets of its joint rates, gripper and current limits."""
    r = _Record(area.name, area.body_offset, area.body_size)
    r.add("heartbeat", "<u8", units="1", doc="incremented on every write by the controller")
    r.add("t_s", "<f8", units="s", doc="controller clock time of this write")
    jr = r.add("joint_rate_rad_s", "<f8", (N_JOINTS,), "rad/s",
               "joint rate commands, order: " + ", ".join(c.signal for c in joints))
    gr = r.add("gripper", "<f8", units=grippers[0].units if grippers else "V",
               doc="gripper command" + (f" ({grippers[0].signal})" if grippers else ""))
    cl = r.add("current_limit_a", "<f8", (N_CURRENT_LIMITS,), "A",
               "current limits, order: " + ", ".join(c.signal for c in limits))
    r.add("matrix_route", "<u2", units="bits", doc="matrix switcher route request")
    r.add("arm_request", "u1", units="bool", doc="1 = the controller wants outputs enabled")
    r.add("rearm_counter", "<u4", units="1", doc="increment to ask the service to leave FAULT")
    r.add("mode", "<u4", units="enum", doc="controller mode (informational)")
    r.add("crl_reflect_force_n", "<f8", (3,), "N",
          "force to display on the CRL hand controller (sent by the service at 40 Hz)")
    r.add("crl_reflect_torque_nm", "<f8", (3,), "N*m", "torque to display on the CRL hand controller")
    r.add("crl_reflect_enable", "u1", units="bool",
          doc="1 = the CRL displays the force above (0 = zero forces, disabled)")
    r.add("inputs_frame", "<u8", units="1",
          doc="inputs frame the rate commands were computed from (0 = none: rates drive 0 V)")
    r.add("controller_frame", "<u8", units="1", doc="the writer's own frame counter")
    r.add("writer_pid", "<i4", units="1", doc="pid of the writing process (must hold the claim)")
    r.add("writer_token", "<u8", units="1", doc="the claim's token (owners[commands].claimed_ns)")
    return r, (jr, gr, cl)


def _command_entries(area: str, joints: list, limits: list, grippers: list,
                     offsets: tuple[int, int, int]) -> list[ChannelEntry]:
    """The command channels: joint rates, the gripper, current limits (in that order)."""
    jr, gr, cl = offsets
    entries = []
    for i, c in enumerate(joints):
        entries.append(ChannelEntry(c.signal, "command", area, i, c.units, c.label,
                                    (("joint_rate_rad_s", i, jr + 8 * i),), c.board, c.channel))
    for c in grippers:
        entries.append(ChannelEntry(c.signal, "command", area, 0, c.units, c.label,
                                    (("gripper", 0, gr),), c.board, c.channel))
    for i, c in enumerate(limits):
        entries.append(ChannelEntry(c.signal, "command", area, i, c.units, c.label,
                                    (("current_limit_a", i, cl + 8 * i),), c.board, c.channel))
    return entries

def struct_field(dt: np.dtype | None, name: str) -> tuple[np.dtype, int]:
    """(dtype, byte offset) of field ``name`` of the structured dtype ``dt``.

    numpy types ``dtype.fields`` as optional (None for a plain dtype); every record dtype
    here is structured, so a plain one is a programming error (TypeError, as before).
    """
    fields = None if dt is None else dt.fields
    if fields is None:
        raise TypeError(f"{dt!r} is not a structured dtype")
    return fields[name][0], fields[name][1]


def struct_names(dt: np.dtype) -> tuple[str, ...]:
    """The field names of the structured dtype ``dt`` (see :func:`struct_field`)."""
    if dt.names is None:
        raise TypeError(f"{dt!r} is not a structured dtype")
    return dt.names


#: one message-queue entry (80 bytes)
MESSAGE_DTYPE = np.dtype({
    "names": ["seq", "t_s", "severity", "source", "code", "text"],
    "formats": ["<u8", "<f8", "u1", "<u2", "<u4", f"S{MESSAGE_TEXT_BYTES}"],
    "offsets": [0, 8, 16, 18, 20, 24],
    "itemsize": 24 + MESSAGE_TEXT_BYTES,
})


def _controller_stats(area: AreaSpec) -> _Record:
    """The controller's own frame timing (``pfma stats`` shows it beside the service's)."""
    r = _Record(area.name, area.body_offset, area.body_size)
    r.add("frame", "<u8", units="1", doc="service frame of the latest controller frame")
    r.add("t_s", "<f8", units="s", doc="controller clock time of this publish")
    r.add("frames", "<u8", units="1", doc="controller frames run since start")
    r.add("missed_frames", "<u8", units="1", doc="service frames the controller did not run")
    r.add("missed_events", "<u8", units="1", doc="times one or more frames were missed")
    r.add("missed_run", "<u4", units="1", doc="frames missed just before the latest frame")
    r.add("longest_missed_run", "<u4", units="1", doc="most frames missed in a row")
    r.add("max_missed_run", "<u4", units="1", doc="configured: more in a row is a fault")
    r.add("missed_task_slots", "<u8", units="1", doc="periodic task slots that did not run")
    r.add("overruns", "<u8", units="1", doc="frames whose work ended after the next service frame")
    r.add("period_s", "<f8", units="s", doc="nominal minor-frame period")
    r.add("rate_hz", "<f8", units="Hz", doc="measured frame rate")
    for n in ("p50", "p99", "max"):
        r.add(f"wake_latency_{n}_us", "<f8", units="us",
              doc=f"wake-up latency after the service's frame {n}")
    for n in ("p50", "p99", "max"):
        r.add(f"work_{n}_us", "<f8", units="us", doc=f"controller frame work time {n}")
    r.add("cpu_percent", "<f8", units="%", doc="controller CPU use of one core")
    r.add("gc_gen2", "<u8", units="1", doc="full garbage collections since start")
    return r


def _messages(area: AreaSpec) -> _Record:
    n = QUEUE_LEN[area.name]
    r = _Record(area.name, area.body_offset, area.body_size)
    r.add("head_seq", "<u8", units="1", doc="sequence number of the newest message (0 = none)")
    r.add("capacity", "<u4", units="1", doc=f"entries in the ring ({n})")
    off = r.add("entries", MESSAGE_DTYPE.str, (n,), "",
                f"ring; message seq s is in entries[(s - 1) % {n}]", align=8)
    # numpy needs the structured dtype itself, not its void string
    r.formats[-1] = (MESSAGE_DTYPE, (n,))
    r.specs[-1] = FieldSpec("entries", area.name, off, "message", (n,), "",
                            r.specs[-1].doc)
    return r


def _header(area: AreaSpec) -> _Record:
    r = _Record(area.name, area.offset, area.size)
    r.add("magic", "S8", units="", doc=f"{MAGIC.decode()}")
    r.add("layout_version", "<u4", units="1", doc="LAYOUT_VERSION")
    r.add("header_size", "<u4", units="B", doc="bytes of this header")
    r.add("buffer_size", "<u4", units="B", doc=f"{BUFFER_SIZE}")
    r.add("n_areas", "<u4", units="1", doc="entries used in area_table")
    r.add("layout_hash", "u1", (8,), "", "sha256 of the canonical layout JSON, first 8 bytes")
    r.add("calibration_hash", "u1", (8,), "", "hash of the calibration in use (calibration issue)")
    r.add("created_ns", "<u8", units="ns", doc="time.time_ns() when the buffer was initialised")
    r.add("service_state", "<u4", units="enum", doc="ServiceState; written by the inputs owner")
    r.add("frame", "<u8", units="1", doc="frame counter; written by the inputs owner")
    r.add("frame_t_s", "<f8", units="s", doc="time of that frame")
    r.add("rack_name", "S16", units="", doc="rack configuration name")
    r.pos = 128
    r.add("area_table", AREA_ENTRY_DTYPE.str, (MAX_AREAS,), "", "name, offset, size, "
          "body_offset, body_size of every area")
    r.formats[-1] = (AREA_ENTRY_DTYPE, (MAX_AREAS,))
    s = r.specs[-1]
    r.specs[-1] = FieldSpec(s.name, s.area, s.offset, "area_entry", s.shape, s.units, s.doc)
    r.pos = 384
    r.add("owners", OWNER_DTYPE.str, (MAX_AREAS,), "", "per area (index as area_table): "
          "owner pid, name, claim time, heartbeat")
    r.formats[-1] = (OWNER_DTYPE, (MAX_AREAS,))
    s = r.specs[-1]
    r.specs[-1] = FieldSpec(s.name, s.area, s.offset, "owner", s.shape, s.units, s.doc)
    return r


#: one area-table entry in the header (32 bytes)
AREA_ENTRY_DTYPE = np.dtype({
    "names": ["name", "offset", "size", "body_offset", "body_size"],
    "formats": ["S16", "<u4", "<u4", "<u4", "<u4"],
    "offsets": [0, 16, 20, 24, 28], "itemsize": 32})
#: one owner slot in the header (80 bytes). ``seq`` guards pid/name/claimed_ns; heartbeat
#: and heartbeat_t_s are single aligned 8-byte words updated on every publish.
OWNER_DTYPE = np.dtype({
    "names": ["seq", "pid", "flags", "name", "claimed_ns", "heartbeat", "heartbeat_t_s",
              "takeovers"],
    "formats": ["<u8", "<i4", "<u4", f"S{OWNER_NAME_BYTES}", "<u8", "<u8", "<f8", "<u4"],
    "offsets": [0, 8, 12, 16, 48, 56, 64, 72], "itemsize": 80})

#: record element types named in FieldSpec.dtype
RECORD_DTYPES = {"area_entry": AREA_ENTRY_DTYPE, "owner": OWNER_DTYPE, "message": MESSAGE_DTYPE}

#: (name, offset, size, writer role, seqlocked, doc) - the fixed area map
AREA_MAP: tuple[tuple[str, int, int, str, bool, str], ...] = (
    ("header", 0, 1024, "", False, "identification, area table, owners, frame, state"),
    ("inputs", 1024, 12288, "service", True, "every sampled channel, boards, links, F/T, HCs"),
    ("stats", 13312, 2048, "service", True, "loop timing statistics, per-device rates"),
    ("commands", 15360, 1024, "controller", True, "joint rates, current limits, arm requests"),
    ("service_messages", 16384, 4096, "service", True, "50-entry message queue of the service"),
    ("controller_stats", 20480, 2048, "controller", True, "the controller's frame timing and missed frames"),
    ("controller_messages", 22528, 10240, "controller", True,
     "127-entry message queue of the controller"),
)


def build_layout(rack: RackConfig | None = None) -> Layout:
    """The layout for a rack (default: the IRSS report's rack). Deterministic."""
    rack = rack or load_rack()
    areas = [AreaSpec(n, i, off, size, w, s, doc) for i, (n, off, size, w, s, doc)
             in enumerate(AREA_MAP)]
    assert sum(a.size for a in areas) == BUFFER_SIZE and len(areas) <= MAX_AREAS
    records: dict[str, _Record] = {}
    channels: list[ChannelEntry] = []
    records["header"] = _header(areas[0])
    records["inputs"], ch = _inputs(areas[1], rack)
    channels += ch
    records["stats"], ch = _stats(areas[2])
    channels += ch
    records["commands"], ch, joints, limits = _commands(areas[3], rack)
    channels += ch
    records["service_messages"] = _messages(areas[4])
    records["controller_stats"] = _controller_stats(areas[5])
    records["controller_messages"] = _messages(areas[6])
    out_areas = tuple(AreaSpec(a.name, a.index, a.offset, a.size, a.writer, a.seqlocked, a.doc,
                               records[a.name].dtype() if a.name in records else None)
                      for a in areas)
    fields = tuple(f for a in areas if a.name in records for f in records[a.name].specs)
    roles = {c.signal: (c.joint, c.quantity) for c in rack.channels() if c.quantity}
    channels = [replace(e, joint=roles[e.name][0], quantity=roles[e.name][1])
                if e.board and e.name in roles else e for e in channels]
    lay = Layout(rack.name, out_areas, fields, tuple(channels), joints, limits)
    digest = hashlib.sha256(json.dumps(lay.canonical(), sort_keys=True,
                                       separators=(",", ":")).encode()).digest()[:8]
    return Layout(rack.name, out_areas, fields, tuple(channels), joints, limits, hash=digest)


@lru_cache(maxsize=1)
def default_layout() -> Layout:
    """The layout of the default rack (cached)."""
    return build_layout(load_rack())


def resolve_role(writer: str) -> str:
    """``"service"``/``"inputs"`` -> service, ``"controller"``/``"commands"`` -> controller."""
    role = ROLE_ALIASES.get(writer, writer)
    if role not in WRITER_ROLES:
        raise ConfigError(f"unknown Bit3 writer {writer!r}; use one of "
                          f"{', '.join(sorted(set(WRITER_ROLES) | set(ROLE_ALIASES)))}")
    return role


# ----------------------------------------------------------------------------------------
# generated document

DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "bit3-layout.md"


def _md_dtype(d: str) -> str:
    return d.lstrip("|")  # "|" (byte order not applicable) would split a markdown table cell


def _md_record(dt: np.dtype) -> str:
    """``name type @+offset, ...`` of a structured record dtype."""
    return ", ".join(f"{n} {_md_dtype(struct_field(dt, n)[0].str)} @+{struct_field(dt, n)[1]}"
                     for n in struct_names(dt))


def _shape(s: tuple[int, ...]) -> str:
    return "" if not s else "[" + ",".join(map(str, s)) + "]"


def _md_intro(lay: Layout) -> list[str]:
    """The document's head: the rack, the hash, the rules, and how to attach without the code."""
    return [
        "# Bit3 buffer layout",
        "",
        "<!-- GENERATED by bit3.layout.layout_markdown(); do not edit. "
        "Regenerate: pfma layout --markdown > docs/bit3-layout.md -->",
        "",
        f"Rack `{lay.rack_name}`, layout version {lay.version}, hash `{lay.hash_hex}`, "
        f"magic `{MAGIC.decode()}`, {lay.size} bytes (the Bit3 dual-port RAM, IRSS report "
        "3.4.3). All numbers little-endian; offsets are bytes from the start of the buffer.",
        "",
        "Rules (IRSS world model, report 2.2.2): each area has exactly one writer role, which "
        "claims it in the header (a live second writer is refused, a dead one's claim is taken "
        "over); anyone may read. Each seqlocked area starts with a 64-byte block whose first "
        "8 bytes are its sequence counter (even = stable, odd = write in progress); the body "
        "follows at +64. Readers copy the body and re-check the counter.",
        "",
        "## Attaching without the project's code",
        "",
        "Everything an independent reader (any language) needs; `pfma layout --json` gives the "
        "same areas and fields as JSON (`areas[]`: name, offset, size, body_offset, body_size, "
        "seqlocked; `fields[]`: name, area, offset, dtype, shape, nbytes, units; offsets are "
        "from the start of the buffer, also for fields inside a body).",
        "",
        "1. **Where.** `pfma serve --buffer NAME` (default `pfma`) creates POSIX shared memory "
        f"`NAME`, on Linux the file `/dev/shm/NAME`, exactly {lay.size} bytes. Open it "
        "read-only and map it shared (`mmap(PROT_READ, MAP_SHARED)`). Never write to an area "
        "you have not claimed.",
        f"2. **Check.** `magic` (offset 0) is `{MAGIC.decode()}` and the 8 `layout_hash` bytes "
        "(offset 24) are the layout hash above (as hex); otherwise the layout differs: stop.",
        "3. **Read an area (sequence lock).** The counter is the naturally aligned little-endian "
        "`<u8` at the area's `offset`; read it with one 8-byte load. Loop: `s1` = counter; if "
        "`s1` is odd a write is in progress, retry; copy `body_size` bytes from `body_offset`; "
        "`s2` = counter; accept the copy only if `s2 == s1`, else retry. Decode fields from "
        "the copy, never from the live memory. The writer sets the counter to `s+1`, writes "
        "the body and sets it to `s+2`, so a copy taken between two equal even values is one "
        "whole frame. x86-64 keeps loads in order; on a weakly ordered CPU put an acquire "
        "fence after the first load and before the second. Bound the retries: a counter odd "
        "for more than about 0.1 s means the writer died mid-write (check the owner's `pid` "
        "in `owners[i]`).",
        "4. **Clock.** Every `t_*` / `*_t_s` time is the service clock in seconds: "
        "`CLOCK_MONOTONIC` in `pfma serve` (Python `time.monotonic()`), simulated time in tests.",
        "5. **What refreshes when.** The service publishes the `inputs` area once per minor frame "
        "that it runs (320 Hz by default): `inputs.frame` goes up by 1 per frame and jumps by "
        "more than 1 when frames were dropped (a host stall; counted in `stats.dropped_frames`). "
        "A sample time changes exactly when that input was sampled or that output applied: "
        "`t_rtd_s` (resolvers, 160 Hz), `t_adc_s` (ADC scan, 160 Hz), `t_ft_s` (a new F/T "
        "record, 80 Hz), `t_dac_s` (DAC written, every frame, 320 Hz), `t_pio_s` (user I/F box, "
        "40 Hz); rates of the default schedule. The `stats` area is published twice a second: `stats.device_samples[slot]` "
        "counts every sample or apply since start and `stats.device_t_s[slot]` is the time of "
        "the latest (slots: the `device` rows of the channel table, "
        + ", ".join(f"`{g}` {i}" for i, g in enumerate(DEVICE_GROUPS))
        + "), so a reader that polls slower than a device can "
        "still compute its exact rate: difference of `device_samples` over difference of "
        "`stats.t_s`.",
        "",
    ]


def _md_areas(lay: Layout) -> list[str]:
    """The area table, the writer roles, the states and severities, the codes."""
    out = [
        "## Areas",
        "",
        "| area | offset | size | body offset | body size | writer | seqlock | contents |",
        "|---|---:|---:|---:|---:|---|---|---|",
    ]
    for a in lay.areas:
        out.append(f"| {a.name} | {a.offset} | {a.size} | {a.body_offset} | {a.body_size} | "
                   f"{a.writer or '-'} | {'yes' if a.seqlocked else 'no'} | {a.doc} |")
    out += ["", "Writer roles: " + "; ".join(f"`{r}` owns {', '.join(a)}"
                                              for r, a in WRITER_ROLES.items()) + ".", "",
            "Service states: " + ", ".join(f"{s.value} {s.name}" for s in ServiceState) + ". "
            "Severities: " + ", ".join(f"{s.value} {s.name}" for s in Severity) + ".", "",
            "Fault codes (`inputs.fault_code`, `bit3.layout.FaultCode`): "
            + ", ".join(f"{int(c)} {c.name}" for c in FaultCode) + ".", "",
            "Message codes of the I/O service (`code` of the `service_messages` entries, "
            "`bit3.layout.MessageCode`; a trip's message carries its fault code, 1-9, the output "
            "guard's notices share that range): "
            + ", ".join(f"{int(c)} {c.name}" for c in MessageCode) + ".", ""]
    return out


def _md_header_records() -> list[str]:
    """The header's record types (area table, owners) and the message entries."""
    return ["## Header records", "",
            "`area_table[i]` (32 B): " + _md_record(AREA_ENTRY_DTYPE) + ".", "",
            "`owners[i]` (80 B, i = area index): " + _md_record(OWNER_DTYPE) + ". "
            f"`flags` bits: 0x{OWNER_FLAG_CLAIMED:x} CLAIMED (the slot holds a live or dead claim; "
            f"0 once released), 0x{OWNER_FLAG_SIMULATED:x} SIMULATED (the claimer runs on the "
            "simulated rack, the register-level fakes: the I/O service sets it in its three slots "
            "when its register bus is the fake rack, directly or through a spy, and leaves it clear "
            "for a hardware bus such as a device file, a VME bridge or a Modbus gateway, whose far "
            "side it cannot see). The `inputs` slot answers whether the rack is simulated: "
            "SIMULATED set, simulated; CLAIMED alone, a hardware bus; pid 0, unknown (no service).",
            "",
            f"Message `entries[i]` ({MESSAGE_DTYPE.itemsize} B): " + _md_record(MESSAGE_DTYPE) + ". "
            f"A message longer than one entry's {MESSAGE_TEXT_BYTES} bytes of UTF-8 takes the next "
            f"entries (cut only between characters), all written in one sequence-lock section; "
            f"the `severity` byte's low bits (0x{MESSAGE_SEVERITY_MASK:02x}) are the severity, "
            f"0x{MESSAGE_CONTINUES:02x} is set on every entry of a message but its last (the text "
            f"goes on in the next entry) and 0x{MESSAGE_CONTINUED:02x} on every entry but its first "
            "(a reader whose window starts inside a message skips the rest of it); `t_s`, "
            "`source` and `code` are the same in every entry of a message. **The bound**: a "
            f"message takes at most {MESSAGE_MAX_ENTRIES} entries (half the ring), so it carries "
            f"up to {MESSAGE_MAX_BYTES} bytes of UTF-8; a longer text is cut there and ends \"~\".",
            ""]


def _md_fields(lay: Layout) -> list[str]:
    """One table of fields per area."""
    out: list[str] = []
    for a in lay.areas:
        fl = [f for f in lay.fields if f.area == a.name]
        if not fl:
            continue
        out += [f"## Area `{a.name}`", "",
                "| field | offset | dtype | shape | bytes | units | meaning |",
                "|---|---:|---|---|---:|---|---|"]
        for f in fl:
            out.append(f"| {f.name} | {f.offset} | {_md_dtype(f.dtype)} | {_shape(f.shape)} | {f.nbytes} | "
                       f"{f.units} | {f.doc} |")
        out.append("")
    return out


def _md_channels(lay: Layout) -> list[str]:
    """Every channel with its slot and element offsets."""
    out = ["## Channels", "",
            "Every rack channel, board, link, hand controller and device group, with the byte "
            "offset of its element in each slot array.", "",
            "| name | area | kind | slot | units | board/ch | element offsets | label |",
            "|---|---|---|---:|---|---|---|---|"]
    for c in lay.channels:
        where = f"{c.board}/{c.channel}" if c.channel >= 0 else (c.board or "-")
        offs = ", ".join(f"{f}[{i}]@{o}" for f, i, o in c.fields)
        out.append(f"| {c.name} | {c.area} | {c.kind} | {c.slot} | {c.units} | {where} | {offs} | "
                   f"{c.label}{' (spare)' if c.spare else ''} |")
    return out


def _md_names() -> list[str]:
    """How the tools name the enumerations and status words."""
    out = ["", "## Names of the numbers", "",
            "How every tool shows the enumerations and status words above (pfma/show.py; `--json` keeps "
            "the number beside the name). A status word that is healthy reads `ok`: a channel's with no "
            "bit set, a board's present and initialised, a link's open and synchronised; otherwise the "
            "names of its problem bits (`BUSERR`: the board did not answer, the value is its last good "
            "sample), or what a board or link lacks (`NOT INITIALISED`, `CLOSED`, `NOT SYNCED`).", "",
            "| word | value: name |", "|---|---|",
            "| service_state | " + ", ".join(f"{int(v)} {v.name}" for v in ServiceState) + " |",
            "| fault_code | " + ", ".join(f"{int(v)} {n}" for v, n in FAULT_CODE_NAMES.items()) + " |",
            "| command_status (bits) | " + ", ".join(f"{v} {n}" for v, n in CMD_STATUS_NAMES.items()) + " |"]
    for kind, names in STATUS_BIT_NAMES.items():
        if names:
            out.append(f"| {kind}_status (bits) | " + ", ".join(f"0x{v:x} {n}" for v, n in names.items())
                       + f"; healthy: 0x{STATUS_HEALTHY[kind]:x} |")
    out.append("")
    return out


def layout_markdown(layout: Layout | None = None) -> str:
    """The text of ``docs/bit3-layout.md`` (generated; a test compares the file with it)."""
    lay = layout or default_layout()
    out = _md_intro(lay) + _md_areas(lay) + _md_header_records() + _md_fields(lay) + _md_channels(lay) + _md_names()
    return "\n".join(out)

