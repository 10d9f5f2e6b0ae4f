"""Rack configuration: boards, addresses and every channel's name, units and rate.

The default (``pfma/rack_default.toml``) is the IRSS report's tables, section 3.4.2.
Nothing else in the project hard-codes a channel number: code asks this module.
Invalid configuration is refused with a :class:`ConfigError` naming file and line.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, NoReturn

import msgspec

from pfma import config, nominal
from pfma import envelope as envelope_cfg
from pfma.errors import ConfigError, did_you_mean

DEFAULT_RACK = Path(__file__).with_name("rack_default.toml")

DEFAULT_DIRECTION = {"rtd": "in", "adc": "in", "dac": "out", "serial": "in"}
BOARD_KEYS = {"name", "kind", "device", "base", "rate_hz", "title", "channels"}
CHANNEL_KEYS = {"ch", "signal", "label", "units", "direction", "spare", "scale", "offset", "baud", "limit",
                "joint", "quantity"}
#: what a channel measures or commands (the channel key ``quantity``), and the device class
#: that can carry it. Every quantity but the hand controller's belongs to one joint (key
#: ``joint``); tools and the service find a joint's channels by (joint, quantity), never by
#: the signal's name.
QUANTITIES: dict[str, str] = {
    "angle": "rtd",  # resolver angle, rad
    "rate": "adc",  # filtered tachometer
    "motor_current": "adc",  # amplifier current monitor
    "rate_command": "dac",  # a joint's rate command (the Bit3 command area's joint order)
    "current_limit": "dac",  # an amplifier's current limit (brake released above ~0.5 V)
    "gripper_command": "dac",  # the gripper's drive command
    "hand_controller": "adc",  # a CAE hand-controller axis or discrete (no joint)
    "force_torque": "serial",  # the wrist force/torque sensor's line (no joint)
}
#: ``[arm]`` keys: ``joints`` = the servoed arm joints, base to tool (the one joint list)
ARM_KEYS = {"joints"}
#: ``[commands]`` keys: how the service judges the command area (see :class:`CommandPolicy`)
COMMANDS_KEYS = {"max_input_age_frames", "limit_margin"}
#: ``[bit3]`` keys: the Bit3 shared-memory window (IRSS report 3.4.3)
BIT3_KEYS = {"size", "computational_window", "io_window"}
BIT3_SIZE = 32768  #: the Bit3 adapter's 32 KiB window
#: ``[checks]`` keys: ``allow_nonnominal`` = ``"signal.field"`` names whose values the file
#: checks (:mod:`pfma.nominal`) accept outside the nominal band (a lab that knows better)
CHECKS_KEYS = {"allow_nonnominal"}
#: the rate (Hz) the service's default schedule runs each device's boards at
#: (``ioservice.schedule``: 320 Hz minor frames; DAC every frame, resolvers and ADC every
#: 2nd, the serial lines every 4th, the parallel ports every 8th). A board's ``rate_hz``
#: documents it; it cannot change it, so any other value is refused at parse (the schedule
#: is set by ``pfma serve --frame-rate`` / ``--schedule``, and the service says so when the
#: schedule it runs differs from these). tests/ioservice checks this table against the
#: schedule's.
SCHEDULED_RATES_HZ = {"dac": 320.0, "rtd": 160.0, "adc": 160.0, "serial": 80.0, "pio": 40.0}
#: ``[amplifier_enable]`` keys: the optional charge-pump output (see :class:`AmplifierEnable`)
AMPLIFIER_ENABLE_KEYS = {"board", "port", "bit"}
SIGNAL_RE = re.compile(r"^[a-z][a-z0-9_]*$")


def _catalog():
    """The board catalogue (:mod:`drivers.catalog`): the one place the ground floor looks up.

    A rack file names board kinds; whether a kind exists, how many channels it has, how
    much A16 space it decodes and which bit rates it offers are the catalogue's facts.
    The import is deferred and is the only import of ``pfma`` from a higher package (the
    import-linter layers contract names it as its one exception).
    """
    from drivers import catalog
    return catalog


def board_description(kind: str):
    """The register table (``BoardDescription``) of a board kind (:mod:`drivers.catalog`)."""
    return _catalog().board_kind(kind).description()


@dataclass(frozen=True)
class Channel:
    """One channel of one board, as ``pfma channels`` prints it."""

    device: str  #: rtd, adc, dac, serial, pio
    board: str  #: board name from the rack file, e.g. "rtd1"
    kind: str  #: board kind, e.g. "vmivme4940"
    address: int  #: board base (A16)
    channel: int  #: 0-based index on that board
    signal: str  #: snake_case name, unique in the rack
    label: str  #: the seed's wording
    units: str  #: engineering units
    direction: str  #: "in" or "out"
    rate_hz: float
    spare: bool = False
    scale: float = 1.0  #: engineering units per volt (analog channels)
    offset: float = 0.0  #: engineering value at 0 V
    baud: int | None = None
    #: DAC command channels: the largest engineering command the service obeys (rates and
    #: the gripper: |value| <= limit; current limits: 0 <= value <= limit), within the
    #: rack's ``[commands] limit_margin``; beyond it the service refuses the command and
    #: makes the outputs safe. None: the DAC's full range (10 V x scale).
    limit: float | None = None
    joint: str = ""  #: the joint this channel belongs to ("" for none), e.g. "elbow_pitch"
    quantity: str = ""  #: what it carries (:data:`QUANTITIES`), "" for none

    def as_dict(self) -> dict:
        d = {
            "device": self.device, "board": self.board, "kind": self.kind,
            "address": self.address, "channel": self.channel, "signal": self.signal,
            "label": self.label, "units": self.units, "direction": self.direction,
            "rate_hz": self.rate_hz, "spare": self.spare,
        }
        if self.device in ("adc", "dac"):
            d["scale"] = self.scale
            d["offset"] = self.offset
        if self.baud is not None:
            d["baud"] = self.baud
        if self.limit is not None:
            d["limit"] = self.limit
        if self.quantity:
            d["quantity"] = self.quantity
        if self.joint:
            d["joint"] = self.joint
        return d


@dataclass(frozen=True)
class BoardConfig:
    name: str
    kind: str
    device: str
    base: int
    window: int
    rate_hz: float
    title: str
    channels: tuple[Channel, ...]

    def signal(self, ch: int) -> Channel:
        for c in self.channels:
            if c.channel == ch:
                return c
        raise KeyError(f"board {self.name} has no channel {ch}")


@dataclass(frozen=True)
class CommandPolicy:
    """How the service judges the command area (rack file section ``[commands]``).

    :param max_input_age_frames: a rate channel is driven only from a command computed
        from inputs at most this many minor frames old (``commands.inputs_frame``); older
        commands drive the rate channels at 0 V. Default 4 (12.5 ms at 320 Hz), which
        must not exceed the command watchdog (checked when the service starts). Assumed:
        nominal age is 2-3 frames (servo at 160 Hz, output in the next frame), so one
        missed controller frame is tolerated and two are not.
    :param limit_margin: fraction of a channel's ``limit`` a command may exceed it by and
        still be obeyed (saturated at the limit, status bit set); beyond it the command is
        refused. Default 0.02 (assumed: rounding in a controller's own saturation).
    """

    max_input_age_frames: int = 4
    limit_margin: float = 0.02


@dataclass(frozen=True)
class AmplifierEnable:
    """The amplifier-enable charge pump (rack file section ``[amplifier_enable]``, optional;
    issue 28 item 5, docs/safety.md "Honest outputs"): one output bit of a parallel-port
    board that the service toggles every frame while it is ARMED and its DAC answers, as
    LinuxCNC's ``charge-pump``/``amp-enable-out``. A relay behind it (a retriggerable
    watchdog) holds the amplifiers enabled only while the bit keeps toggling, so a dead,
    stalled or faulted service, or one whose DAC stopped answering, drops the amplifiers.

    ASSUMED (named once here): the port carrying the bit is the charge pump's alone (its
    channel has ``direction = "out"``; the service writes its other bits 0), and the rack
    has no such output unless the file says so (the seed's rack has none: its DAC board is
    then a single point of failure the hardware E-stop must cover).
    """

    board: str  #: a ``pio`` board of the rack
    port: int  #: 0..3 (the board's channel of that number, an output)
    bit: int  #: 0..7

    def describe(self) -> str:
        return f"{self.board} port {self.port} bit {self.bit}"


@dataclass
class RackConfig:
    name: str
    boards: tuple[BoardConfig, ...]
    bit3: dict = field(default_factory=dict)
    source: str = "<default>"
    commands: CommandPolicy = field(default_factory=CommandPolicy)
    #: the servoed arm joints, base to tool (``[arm] joints``): the one joint list
    joints: tuple[str, ...] = ()
    #: the service's motion envelope (``[envelope]``, :mod:`pfma.envelope`): soft limits,
    #: braking deceleration and slew per joint, the overspeed factor
    envelope: envelope_cfg.Envelope = field(default_factory=lambda: envelope_cfg.Envelope(()))
    #: ``[checks] allow_nonnominal``: ``"signal.field"`` values a lab accepts outside the
    #: nominal band (:mod:`pfma.nominal`); calibrations of those fields are accepted too
    overrides: tuple[str, ...] = ()
    #: ``("signal.field", text)`` per value this file holds outside the nominal band under an
    #: override (the service names each in its start-up messages)
    nonnominal: tuple[tuple[str, str], ...] = ()
    #: the amplifier-enable charge pump (``[amplifier_enable]``), None: the rack has none
    amplifier_enable: AmplifierEnable | None = None

    def channels(self) -> list[Channel]:
        return [c for b in self.boards for c in b.channels]

    def channel(self, signal: str) -> Channel:
        for c in self.channels():
            if c.signal == signal:
                return c
        raise KeyError(f"no channel named {signal!r} in rack {self.name} ({self.source})"
                       + did_you_mean(signal, (c.signal for c in self.channels())))

    def board(self, name: str) -> BoardConfig:
        for b in self.boards:
            if b.name == name:
                return b
        raise KeyError(f"no board named {name!r} in rack {self.name}")

    def boards_of(self, device: str) -> list[BoardConfig]:
        return [b for b in self.boards if b.device == device]

    def find(self, joint: str, quantity: str) -> Channel | None:
        """The channel carrying ``quantity`` of ``joint`` (None when the rack has none)."""
        for c in self.channels():
            if c.joint == joint and c.quantity == quantity:
                return c
        return None

    def joint_channel(self, joint: str, quantity: str) -> Channel:
        """Like :meth:`find`, but a missing channel is a KeyError naming joint and quantity."""
        c = self.find(joint, quantity)
        if c is None:
            raise KeyError(f"rack {self.name} ({self.source}) has no {quantity} channel for joint {joint!r}")
        return c

    def with_quantity(self, quantity: str) -> list[Channel]:
        """Every channel carrying ``quantity``, in rack order (boards, then channels)."""
        return [c for c in self.channels() if c.quantity == quantity]


def load_rack(path: str | Path | None = None) -> RackConfig:
    """Load and validate a rack file (the seed's default when ``path`` is None or "fake").

    :raises ConfigError: naming file and line of the first problem
    """
    p = DEFAULT_RACK if path in (None, "fake", "default") else Path(path)
    text = config.read_text(p, "rack file")
    return parse_rack(text, str(p))


def _is_number(v) -> bool:
    """An int or float TOML value (not a bool), finite."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# --- the schema: keys, types and ranges of a rack file (checked by pfma.config) ----------
_Snake = Annotated[str, msgspec.Meta(pattern=SIGNAL_RE.pattern)]
_Address = Annotated[int, msgspec.Meta(ge=0)]


class _ChannelEntry(msgspec.Struct, forbid_unknown_fields=True):
    ch: int
    signal: _Snake
    label: str
    units: str
    direction: Literal["in", "out"] | None = None
    spare: bool = False
    scale: float = 1.0
    offset: float = 0.0
    baud: Any = None  # judged against the board kind's rates (code below)
    limit: float | None = None
    joint: Annotated[str, msgspec.Meta(pattern=r"^$|" + SIGNAL_RE.pattern)] = ""
    quantity: str = ""


class _BoardEntry(msgspec.Struct, forbid_unknown_fields=True):
    name: Annotated[str, msgspec.Meta(min_length=1)]
    kind: str
    base: Annotated[int, msgspec.Meta(ge=0, le=0xFFFF)]
    channels: list[_ChannelEntry]
    device: str | None = None
    rate_hz: float | None = None
    title: str | None = None


class _Bit3(msgspec.Struct, forbid_unknown_fields=True):
    size: Annotated[int, msgspec.Meta(ge=BIT3_SIZE, le=BIT3_SIZE)] = BIT3_SIZE
    computational_window: tuple[_Address, _Address] | None = None
    io_window: tuple[_Address, _Address] | None = None


class _Commands(msgspec.Struct, forbid_unknown_fields=True):
    max_input_age_frames: Annotated[int, msgspec.Meta(ge=1, le=64)] = CommandPolicy.max_input_age_frames
    limit_margin: Annotated[float, msgspec.Meta(ge=0, le=0.5)] = CommandPolicy.limit_margin


class _Arm(msgspec.Struct, forbid_unknown_fields=True):
    joints: list[_Snake] = msgspec.field(default_factory=list)


class _Checks(msgspec.Struct, forbid_unknown_fields=True):
    allow_nonnominal: list[str] = msgspec.field(default_factory=list)


class _AmplifierEnable(msgspec.Struct, forbid_unknown_fields=True):
    board: str
    port: int
    bit: Annotated[int, msgspec.Meta(ge=0, le=7)]


class _RackFile(msgspec.Struct, forbid_unknown_fields=True):
    board: Annotated[list[_BoardEntry], msgspec.Meta(min_length=1)]
    rack: dict[str, Any] = msgspec.field(default_factory=dict)
    bit3: _Bit3 = msgspec.field(default_factory=_Bit3)
    commands: _Commands = msgspec.field(default_factory=_Commands)
    arm: _Arm = msgspec.field(default_factory=_Arm)
    checks: _Checks = msgspec.field(default_factory=_Checks)
    amplifier_enable: _AmplifierEnable | None = None
    envelope: dict[str, Any] = msgspec.field(default_factory=dict)


_WINDOW = "[bit3] {key} must be a [lo, hi] pair of addresses (integers), not {%s!r}"
#: the rack file's own wording for a key of the wrong type or range (pfma.config.convert)
_MESSAGES = {
    "*": "unknown top-level section(s): {key}",
    "board": "no [[board]] entries",
    "board[]": "board entry {key} is not a table",
    "board[].*": "board entry has unknown key(s) {key}",
    "board[].name": "board name must be a string, not {value!r}",
    "board[].kind": "board {name}: unknown device kind {value!r}",
    "board[].base": "board {name}: base {value!r} is not an A16 address (integer 0..0xFFFF)",
    "board[].rate_hz": "board {name}: rate_hz must be a number (Hz), not {value!r}",
    "board[].device": "board {name}: device must be a string, not {value!r}",
    "board[].title": "board {name}: title must be a string, not {value!r}",
    "board[].channels": "board {name}: channels must be an array of channel tables",
    "board[].channels[]": "board {name}: channel entry {key} is not a table",
    "board[].channels[].*": "board {name}: channel entry has unknown key(s) {key}",
    "board[].channels[].ch": "board {name}: channel {value!r} is not a channel number (an integer 0..)",
    "board[].channels[].signal": "board {name}: signal {value!r} is not a snake_case name",
    "board[].channels[].label": "board {name}: channel {ch} label must be a string, not {value!r}",
    "board[].channels[].units": "board {name}: channel {ch} units must be a string, not {value!r}",
    "board[].channels[].direction": "board {name}: channel {ch} needs direction 'in' or 'out', not {value!r}",
    "board[].channels[].spare": "board {name}: channel {ch} spare must be true or false, not {value!r}",
    "board[].channels[].scale": "board {name}: channel {ch} scale must be a number, not {value!r}",
    "board[].channels[].offset": "board {name}: channel {ch} offset must be a number, not {value!r}",
    "board[].channels[].limit": "board {name}: channel {ch} limit must be a positive number, not {value!r}",
    "board[].channels[].joint": "board {name}: channel {ch} joint {value!r} is not a snake_case name",
    "board[].channels[].quantity": "board {name}: channel {ch} quantity {value!r} is not one of "
                                   + ", ".join(QUANTITIES),
    **{f"board[].{k}?": f"board entry is missing {k!r}" for k in ("name", "kind", "base", "channels")},
    **{f"board[].channels[].{k}?": f"board {{name}}: channel entry is missing {k!r}"
       for k in ("ch", "signal", "label", "units")},
    "rack": "[rack] must be a table",
    "bit3": "[bit3] must be a table",
    "bit3.*": "[bit3]: unknown key(s) {key}; known: " + ", ".join(sorted(BIT3_KEYS)),
    "bit3.size": "[bit3] size must be %d (the Bit3 window, bytes), not {value!r}" % BIT3_SIZE,
    "bit3.computational_window": _WINDOW % "computational_window",
    "bit3.computational_window[]": _WINDOW % "computational_window",
    "bit3.io_window": _WINDOW % "io_window",
    "bit3.io_window[]": _WINDOW % "io_window",
    "commands": "[commands] must be a table",
    "commands.*": "[commands]: unknown key(s) {key}; known: " + ", ".join(sorted(COMMANDS_KEYS)),
    "commands.max_input_age_frames": "[commands] max_input_age_frames must be an integer 1..64, not {value!r}",
    "commands.limit_margin": "[commands] limit_margin must be a number 0..0.5, not {value!r}",
    "arm": "[arm] must be a table",
    "arm.*": "[arm]: unknown key(s) {key}; known: " + ", ".join(sorted(ARM_KEYS)),
    "arm.joints": "[arm] joints must be a list of snake_case joint names, not {joints!r}",
    "arm.joints[]": "[arm] joints must be a list of snake_case joint names, not {joints!r}",
    "checks": "[checks] must be a table",
    "checks.*": "[checks]: unknown key(s) {key}; known: " + ", ".join(sorted(CHECKS_KEYS)),
    "checks.allow_nonnominal": "[checks] allow_nonnominal must be a list of \"signal.field\" strings, "
                               "not {allow_nonnominal!r}",
    "checks.allow_nonnominal[]": "[checks] allow_nonnominal must be a list of \"signal.field\" strings, "
                                 "not {allow_nonnominal!r}",
    "amplifier_enable": "[amplifier_enable] must be a table",
    "amplifier_enable.*": "[amplifier_enable]: unknown key(s) {key}; known: "
                          + ", ".join(sorted(AMPLIFIER_ENABLE_KEYS)),
    "amplifier_enable.board?": "[amplifier_enable] needs board (board = a pio board, port = 0..3, bit = 0..7)",
    "amplifier_enable.port?": "[amplifier_enable] needs port (board = a pio board, port = 0..3, bit = 0..7)",
    "amplifier_enable.bit?": "[amplifier_enable] needs bit (board = a pio board, port = 0..3, bit = 0..7)",
    "amplifier_enable.board": "[amplifier_enable] board {value!r} is not a pio board of this rack",
    "amplifier_enable.port": "[amplifier_enable] port must be an integer, not {value!r}",
    "amplifier_enable.bit": "[amplifier_enable] bit must be an integer 0..7, not {value!r}",
    "envelope": "[envelope] must be a table",
}


class _Reader:
    """One rack file being read: its text (for lines) and the first-problem ``fail``."""

    def __init__(self, text: str, source: str) -> None:
        self.text, self.source = text, source
        self.signals: dict[str, tuple[int, int]] = {}
        self.roles: dict[tuple[str, str], str] = {}  # (joint, quantity) -> signal
        self.overrides: tuple[str, ...] = ()
        self.nonnominal: list[tuple[str, str]] = []

    def fail(self, msg: str, *path: str | int) -> NoReturn:
        """A ConfigError ``SOURCE:LINE: msg``, the line that of ``path`` (or the nearest table)."""
        config.fail(self.source, self.text, path, msg, error=lambda p: ConfigError(str(p)))


def parse_rack(text: str, source: str = "<string>") -> RackConfig:
    """Parse and validate rack TOML text. See :func:`load_rack`."""
    data = config.parse_toml(text, source, "a rack file")
    if not data.get("board"):
        raise ConfigError(f"{source}: no [[board]] entries")
    raw = config.convert(data, _RackFile, source=source, text=text, messages=_MESSAGES,
                         error=lambda p: ConfigError(str(p)))
    r = _Reader(text, source)
    r.overrides = _overrides(raw.checks, r)
    boards: list[BoardConfig] = []
    for bi, b in enumerate(raw.board):
        boards.append(_board(b, bi, boards, r))
    _check_overrides(boards, r)
    joints = _arm_joints(raw.arm, r)
    return RackConfig(name=str(raw.rack.get("name", "rack")), boards=tuple(boards),
                      bit3=_bit3(raw.bit3, r), source=source,
                      commands=CommandPolicy(raw.commands.max_input_age_frames, float(raw.commands.limit_margin)),
                      joints=joints, envelope=_envelope(raw.envelope, joints, r),
                      overrides=r.overrides, nonnominal=tuple(r.nonnominal),
                      amplifier_enable=None if raw.amplifier_enable is None else
                      _amplifier_enable(raw.amplifier_enable, boards, r))


def _board(b: _BoardEntry, bi: int, boards: list[BoardConfig], r: _Reader) -> BoardConfig:
    """One ``[[board]]``: its kind, A16 window (no overlap), rate, then its channels."""
    name, kind, base = b.name, b.kind, b.base
    catalog = _catalog().CATALOG
    if kind not in catalog:
        r.fail(f"board {name}: unknown device kind {kind!r}; known: {', '.join(sorted(catalog))}", "board", bi, "kind")
    entry = catalog[kind]
    device, window = entry.device, entry.window
    if b.device is not None and b.device != device:
        r.fail(f"board {name}: kind {kind} is a {device} board, not {b.device!r}", "board", bi, "device")
    if base % 2:
        r.fail(f"board {name}: base 0x{base:04X} is odd; the boards' 16-bit registers need an "
               f"even A16 base", "board", bi, "base")
    if base + window > 0x10000:
        r.fail(f"board {name}: window 0x{base:04X}+0x{window:X} runs past the A16 space", "board", bi, "base")
    for other in boards:
        if base < other.base + other.window and other.base < base + window:
            r.fail(f"board {name} at 0x{base:04X}-0x{base + window - 1:04X} overlaps board "
                   f"{other.name} at 0x{other.base:04X}-0x{other.base + other.window - 1:04X}", "board", bi, "base")
        if other.name == name:
            r.fail(f"board name {name!r} used twice", "board", bi, "name")
    rate = _board_rate(b, bi, device, r)
    chans: list[Channel] = []
    seen: set[int] = set()
    for ci, c in enumerate(b.channels):
        chans.append(_channel(c, bi, ci, b, entry, rate, seen, r))
    missing = sorted(set(range(entry.channels)) - seen)
    if missing:
        r.fail(f"board {name}: channel(s) {', '.join(map(str, missing))} not listed "
               f"(list unused ones with spare = true)", "board", bi)
    chans.sort(key=lambda x: x.channel)
    return BoardConfig(name=name, kind=kind, device=device, base=base, window=window,
                       rate_hz=rate, title=b.title if b.title is not None else kind, channels=tuple(chans))


def _board_rate(b: _BoardEntry, bi: int, device: str, r: _Reader) -> float:
    """``rate_hz``: documents the service's schedule for the board's device class."""
    scheduled = SCHEDULED_RATES_HZ.get(device)
    rate = b.rate_hz if b.rate_hz is not None else (scheduled or 0)
    if not math.isfinite(rate):
        r.fail(f"board {b.name}: rate_hz must be a number (Hz), not {rate!r}", "board", bi, "rate_hz")
    rate = float(rate)
    if rate <= 0:
        r.fail(f"board {b.name}: rate_hz must be positive", "board", bi, "rate_hz")
    if scheduled is not None and abs(rate - scheduled) > 1e-9:
        r.fail(f"board {b.name}: rate_hz = {rate:g}, but the service's schedule runs {device} boards at "
               f"{scheduled:g} Hz; rate_hz only documents the schedule (write {scheduled:g} or leave it "
               f"out; the supported rates are {_scheduled_rates()}; pfma serve --frame-rate or "
               f"--schedule sets what runs)", "board", bi, "rate_hz")
    return rate


def _channel(c: _ChannelEntry, bi: int, ci: int, b: _BoardEntry, entry, rate: float, seen: set[int],
             r: _Reader) -> Channel:
    """One channel entry: its number on the board, a signal name unique in the rack, the
    direction, conversion, baud and limit its device class allows, its role."""
    name, kind, device, ch, sig = b.name, b.kind, entry.device, c.ch, c.signal

    def fail(msg: str) -> NoReturn:
        r.fail(msg, "board", bi, "channels", ci)

    if not 0 <= ch < entry.channels:
        fail(f"board {name}: channel {ch!r} out of range 0..{entry.channels - 1} for a {kind}")
    if ch in seen:
        fail(f"board {name}: channel {ch} listed twice")
    seen.add(ch)
    if sig in r.signals:
        fail(f"signal {sig!r} used twice (also board entry {r.signals[sig][0] + 1})")
    r.signals[sig] = (bi, ci)
    direction = c.direction or DEFAULT_DIRECTION.get(device)
    if direction not in ("in", "out"):
        fail(f"board {name}: channel {ch} needs direction 'in' or 'out', not {direction!r}")
    for key, v in (("scale", c.scale), ("offset", c.offset)):
        if not math.isfinite(v):
            fail(f"board {name}: channel {ch} {key} must be a number, not {v!r}")
    if c.scale == 0:
        fail(f"board {name}: channel {ch} scale must not be 0")
    if c.baud is not None:
        if device != "serial":
            fail(f"board {name}: channel {ch}: 'baud' applies to serial channels only")
        rates = entry.serial_rates()
        if not _is_number(c.baud) or c.baud not in rates:
            fail(f"board {name}: channel {ch} baud {c.baud!r} is not a rate the {kind} offers "
                 f"({', '.join(f'{x:g}' for x in rates)})")
    limit = c.limit
    if limit is not None:
        if device != "dac":
            fail(f"board {name}: channel {ch}: 'limit' applies to DAC command channels only")
        if not math.isfinite(limit) or limit <= 0:
            fail(f"board {name}: channel {ch} limit must be a positive number, not {limit!r}")
        limit = float(limit)
    _role(c, device, name, fail, r)
    _nominal(c, device, name, limit, fail, r)
    return Channel(device=device, board=name, kind=kind, address=b.base, channel=ch, signal=sig,
                   label=c.label, units=c.units, direction=direction, rate_hz=rate, spare=c.spare,
                   scale=float(c.scale), offset=float(c.offset), baud=c.baud, limit=limit, joint=c.joint,
                   quantity=c.quantity)


def _role(c: _ChannelEntry, device: str, name: str, fail: Callable[[str], NoReturn], r: _Reader) -> None:
    """``quantity`` and ``joint``: a quantity of this device class, a joint when it needs
    one, and one channel per (joint, quantity) in the rack."""
    ch, quantity, joint = c.ch, c.quantity, c.joint
    if quantity and QUANTITIES.get(quantity) is None:
        fail(f"board {name}: channel {ch} quantity {quantity!r} is not one of {', '.join(QUANTITIES)}")
    if quantity and QUANTITIES[quantity] != device:
        fail(f"board {name}: channel {ch}: a {device} channel cannot carry {quantity!r} "
             f"(a {QUANTITIES[quantity]} quantity)")
    if joint and not quantity:
        fail(f"board {name}: channel {ch} names joint {joint!r} but no quantity")
    if quantity and quantity not in ("hand_controller", "force_torque") and not joint:
        fail(f"board {name}: channel {ch} quantity {quantity!r} needs the joint it belongs to")
    if joint:
        if (joint, quantity) in r.roles:
            fail(f"joint {joint!r} has two {quantity} channels ({r.roles[(joint, quantity)]} and {c.signal})")
        r.roles[(joint, quantity)] = c.signal


def _nominal(c: _ChannelEntry, device: str, name: str, limit: float | None, fail: Callable[[str], NoReturn],
             r: _Reader) -> None:
    """The file checks of :mod:`pfma.nominal` (a value outside the band is refused unless
    ``[checks] allow_nonnominal`` names it)."""
    for finding in nominal.check(device, c.joint, c.quantity, c.units, float(c.scale), float(c.offset), limit):
        what = f"{c.signal}.{finding.field}"
        if finding.overridable and what in r.overrides:
            r.nonnominal.append((what, f"{what} = {finding.value:g} accepted outside the nominal band "
                                       f"by [checks] allow_nonnominal ({r.source}): {finding.why}"))
            continue
        fail(f"board {name}: channel {c.ch} ({c.signal}) {finding.field} = {finding.value:g}: {finding.why}"
             + (f"; a lab that knows better lists \"{what}\" in [checks] allow_nonnominal"
                if finding.overridable else ""))


def _scheduled_rates() -> str:
    return ", ".join(f"{d} {r:g} Hz" for d, r in SCHEDULED_RATES_HZ.items())


def _overrides(raw: _Checks, r: _Reader) -> tuple[str, ...]:
    """``[checks] allow_nonnominal``: a list of ``"signal.field"`` (field: scale, offset,
    limit); the signals are checked against the channels once they are read."""
    names = raw.allow_nonnominal
    fields = nominal.OVERRIDABLE_FIELDS
    for n in names:
        sig, dot, fld = n.rpartition(".")
        if not dot or not SIGNAL_RE.match(sig) or fld not in fields:
            r.fail(f"[checks] allow_nonnominal entry {n!r} is not \"signal.field\" with field one of "
                   f"{', '.join(fields)}", "checks", "allow_nonnominal")
    if len(set(names)) != len(names):
        r.fail(f"[checks] allow_nonnominal names an entry twice: {names!r}", "checks", "allow_nonnominal")
    return tuple(names)


def _check_overrides(boards: list[BoardConfig], r: _Reader) -> None:
    """Each ``allow_nonnominal`` entry names a channel the nominal checks judge (a limit: a DAC's)."""
    analog = {c.signal: c for b in boards for c in b.channels}
    for o in r.overrides:
        sig, _, fld = o.rpartition(".")
        c = analog.get(sig)
        if c is None or nominal.nominal(c.device, c.joint, c.quantity) is None:
            checked = [s for s, x in analog.items() if nominal.nominal(x.device, x.joint, x.quantity)]
            r.fail(f"[checks] allow_nonnominal names {o!r}, but {sig!r} is not a channel the "
                   f"nominal checks judge" + did_you_mean(sig, checked), "checks", "allow_nonnominal")
        if fld == "limit" and c.device != "dac":
            r.fail(f"[checks] allow_nonnominal names {o!r}, but only DAC channels have a limit",
                   "checks", "allow_nonnominal")


def _amplifier_enable(raw: _AmplifierEnable, boards: list[BoardConfig], r: _Reader) -> AmplifierEnable:
    """Validate ``[amplifier_enable]``: ``board`` a pio board of the rack, ``port`` one of
    its channels with ``direction = "out"`` and no other use (not the matrix switcher),
    ``bit`` 0..7."""
    name, port, bit = raw.board, raw.port, raw.bit
    pio = [b for b in boards if b.device == "pio"]
    found = [b for b in pio if b.name == name]
    if not found:
        r.fail(f"[amplifier_enable] board {name!r} is not a pio board of this rack; pio boards: "
               f"{', '.join(b.name for b in pio) or 'none'}", "amplifier_enable", "board")
    board = found[0]
    if not 0 <= port < len(board.channels):
        r.fail(f"[amplifier_enable] port must be an integer 0..{len(board.channels) - 1}, not {port!r}",
               "amplifier_enable", "port")
    ch = board.signal(port)
    if ch.direction != "out" or ch.signal == "matrix_switcher_route" or ch.signal.startswith("user_if_box"):
        r.fail(f"[amplifier_enable] {name} port {port} ({ch.signal}) must be an output of its own: give "
               f"that channel direction = \"out\" and a signal of its own (not the matrix switcher's or "
               f"the user inputs')", "amplifier_enable", "port")
    return AmplifierEnable(name, port, bit)


def _envelope(raw: dict, joints: tuple[str, ...], r: _Reader) -> envelope_cfg.Envelope:
    """``[envelope]``: the service's motion envelope per joint (:mod:`pfma.envelope`)."""
    def fail(msg: str, key: str | None = None) -> NoReturn:
        r.fail(msg, "envelope", *([key] if key else []))
    return envelope_cfg.parse(raw, joints, fail)


def _arm_joints(raw: _Arm, r: _Reader) -> tuple[str, ...]:
    """Validate ``[arm] joints``: distinct names, each with an angle, a rate, a rate
    command and a current-limit channel in the rack (what the service and the controller
    need of a servoed joint)."""
    joints = raw.joints
    if len(set(joints)) != len(joints):
        r.fail(f"[arm] joints lists a joint twice: {joints!r}", "arm", "joints")
    for j in joints:
        missing = [q for q in ("angle", "rate", "rate_command", "current_limit") if (j, q) not in r.roles]
        if missing:
            r.fail(f"[arm] joint {j!r} has no {', '.join(missing)} channel (channel keys joint = {j!r}, "
                   f"quantity = ...)", "arm", "joints")
    return tuple(joints)


def _bit3(raw: _Bit3, r: _Reader) -> dict:
    """``[bit3]``: ``size`` (32768, the adapter's window) and ``*_window`` keys, each
    ``[lo, hi]`` with ``hi - lo + 1 == size``."""
    out: dict = {"size": raw.size}
    for key in sorted(BIT3_KEYS - {"size"}):
        w = getattr(raw, key)
        if w is None:
            continue
        lo, hi = w
        if hi - lo + 1 != raw.size:
            r.fail(f"[bit3] {key} [0x{lo:X}, 0x{hi:X}] spans {hi - lo + 1} bytes, not size {raw.size}", "bit3", key)
        out[key] = (lo, hi)
    return out
