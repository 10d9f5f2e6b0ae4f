"""Rack configuration: boards, addresses and every channel's name, units and rate.

The default (``pfma/rack_default.toml``) is the IRSS report's tables, section 3.4.2.
Nothing else in the project hard-codes a channel number: code asks this module.
Invalid configuration is refused with a :class:`ConfigError` naming file and line.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import NoReturn

from pfma import envelope as envelope_cfg
from pfma import nominal
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


class _Lines:
    """Finds the line of a board, one of its keys, or a channel entry in the TOML text.

    Channel entries are counted as TOML writes them: inline tables (``{ ... }``, one line
    each, several allowed per line, keys in any order) inside a board's ``channels``
    array, or ``[[board.channels]]`` tables.
    """

    _HEADER = re.compile(r"^\[\[?\s*([A-Za-z0-9_.\s]+?)\s*\]\]?\s*(#.*)?$")

    def __init__(self, text: str) -> None:
        self.board_lines: list[int] = []
        self.key_lines: list[dict[str, int]] = []
        self.channel_lines: list[list[int]] = []
        in_board = in_channels = False
        self._depth = 0  # bracket depth inside a channels = [...] array
        for n, line in enumerate(text.splitlines(), start=1):
            s = line.strip()
            header = self._HEADER.match(s)
            if header:
                name = header.group(1).replace(" ", "")
                in_channels = False
                if s.startswith("[[") and name == "board":
                    in_board = True
                    self.board_lines.append(n)
                    self.key_lines.append({})
                    self.channel_lines.append([])
                elif s.startswith("[[") and name == "board.channels" and in_board:
                    self.channel_lines[-1].append(n)
                else:
                    in_board = False
                continue
            if not in_board:
                continue
            key = re.match(r"^([A-Za-z0-9_]+)\s*=", s)
            if key and not in_channels:
                self.key_lines[-1].setdefault(key.group(1), n)
                if key.group(1) != "channels":
                    continue
                in_channels, self._depth = True, 0
                s = s[key.end():]
            if in_channels:
                in_channels = self._scan_channels(s, n)

    @staticmethod
    def _code(s: str) -> str:
        """``s`` without string contents and comments."""
        out, quote, i = [], None, 0
        while i < len(s):
            c = s[i]
            if quote:
                if c == "\\" and quote == '"':
                    i += 1
                elif c == quote:
                    quote = None
            elif c in "\"'":
                quote = c
            elif c == "#":
                break
            else:
                out.append(c)
            i += 1
        return "".join(out)

    def _scan_channels(self, s: str, n: int) -> bool:
        """Note line ``n`` for each channel table opened on it; False once the array closed."""
        for c in self._code(s):
            if c in "[{":
                if c == "{" and self._depth == 1:
                    self.channel_lines[-1].append(n)
                self._depth += 1
            elif c in "]}":
                self._depth -= 1
                if self._depth == 0:
                    return False
        return True

    def of(self, board: int, channel: int | None = None, key: str | None = None) -> int | None:
        if board >= len(self.board_lines):
            return None
        if channel is not None and channel < len(self.channel_lines[board]):
            return self.channel_lines[board][channel]
        if key is not None and key in self.key_lines[board]:
            return self.key_lines[board][key]
        return self.board_lines[board]


def load_rack(path: str | Path | None = None) -> RackConfig:
    """Load and validate a rack file (the seed's default when ``path`` is None or "fake").

    :raises ConfigError: naming file and line of the first problem
    """
    p = DEFAULT_RACK if path in (None, "fake", "default") else Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise ConfigError(f"cannot read rack file {p}: {err.strerror}") from err
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        line = raw.count(b"\n", 0, err.start) + 1
        raise ConfigError(f"{p}:{line}: not UTF-8 text (byte 0x{raw[err.start]:02X} at offset "
                          f"{err.start}); TOML files are UTF-8") from None
    return parse_rack(text, str(p))


def _is_number(v) -> bool:
    """An int or float TOML value (not a bool), finite."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _section_key_line(text: str, section: str, key: str | None = None) -> int | None:
    """Line of ``[section]`` (or of ``key = ...`` inside it) in TOML text."""
    header = None
    for n, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s.startswith("["):
            if header is not None:
                break
            if re.match(rf"^\[\s*{re.escape(section)}\s*\]\s*(#.*)?$", s):
                header = n
                if key is None:
                    return n
            continue
        # key is a str here: with key=None the function returned at the header line
        if header is not None and re.match(rf"^{re.escape(key)}\s*=", s):  # type: ignore[type-var]
            return n
    return header


def parse_rack(text: str, source: str = "<string>") -> RackConfig:
    """Parse and validate rack TOML text. See :func:`load_rack`."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{source}: not valid TOML: {err}") from err
    except RecursionError:
        raise ConfigError(f"{source}: not a rack file: arrays or tables nested too deeply to read") from None
    lines = _Lines(text)

    def fail(msg: str, board: int | None = None, channel: int | None = None,
             key: str | None = None) -> NoReturn:
        line = lines.of(board, channel, key) if board is not None else None
        where = f"{source}:{line}" if line else source
        raise ConfigError(f"{where}: {msg}")

    rack = data.get("rack", {})
    if not isinstance(rack, dict):
        fail("[rack] must be a table")
    boards_raw = data.get("board")
    if not isinstance(boards_raw, list) or not boards_raw:
        fail("no [[board]] entries")
    unknown_top = set(data) - {"rack", "bit3", "board", "commands", "arm", "checks", "amplifier_enable", "envelope"}
    if unknown_top:
        fail(f"unknown top-level section(s): {', '.join(sorted(unknown_top))}")

    overrides = _overrides(data.get("checks", {}), text, source)
    nonnominal: list[tuple[str, str]] = []
    boards: list[BoardConfig] = []
    signals: dict[str, tuple[int, int]] = {}
    roles: dict[tuple[str, str], str] = {}  # (joint, quantity) -> signal
    for bi, b in enumerate(boards_raw):
        if not isinstance(b, dict):
            fail(f"board entry {bi + 1} is not a table", bi)
        extra = set(b) - BOARD_KEYS
        if extra:
            fail(f"board entry has unknown key(s) {', '.join(sorted(extra))}", bi)
        for key in ("name", "kind", "base", "channels"):
            if key not in b:
                fail(f"board entry is missing {key!r}", bi)
        name, kind = b["name"], b["kind"]
        if not isinstance(name, str) or not name:
            fail(f"board name must be a string, not {name!r}", bi, key="name")
        catalog = _catalog().CATALOG
        if not isinstance(kind, str) or kind not in catalog:
            fail(f"board {name}: unknown device kind {kind!r}; known: {', '.join(sorted(catalog))}", bi,
                 key="kind")
        entry = catalog[kind]
        device, n_channels = entry.device, entry.channels
        if b.get("device", device) != device:
            fail(f"board {name}: kind {kind} is a {device} board, not {b['device']!r}", bi, key="device")
        base = b["base"]
        if not _is_int(base) or not 0 <= base <= 0xFFFF:
            fail(f"board {name}: base {base!r} is not an A16 address (integer 0..0xFFFF)", bi, key="base")
        if base % 2:
            fail(f"board {name}: base 0x{base:04X} is odd; the boards' 16-bit registers need an "
                 f"even A16 base", bi, key="base")
        window = entry.window
        if base + window > 0x10000:
            fail(f"board {name}: window 0x{base:04X}+0x{window:X} runs past the A16 space", bi, key="base")
        for other in boards:
            if base < other.base + other.window and other.base < base + window:
                fail(f"board {name} at 0x{base:04X}-0x{base + window - 1:04X} overlaps board "
                     f"{other.name} at 0x{other.base:04X}-0x{other.base + other.window - 1:04X}", bi,
                     key="base")
            if other.name == name:
                fail(f"board name {name!r} used twice", bi, key="name")
        scheduled = SCHEDULED_RATES_HZ.get(device)
        rate = b.get("rate_hz", scheduled or 0)
        if not _is_number(rate):
            fail(f"board {name}: rate_hz must be a number (Hz), not {rate!r}", bi, key="rate_hz")
        rate = float(rate)
        if rate <= 0:
            fail(f"board {name}: rate_hz must be positive", bi, key="rate_hz")
        if scheduled is not None and abs(rate - scheduled) > 1e-9:
            fail(f"board {name}: rate_hz = {rate:g}, but the service's schedule runs {device} boards at "
                 f"{scheduled:g} Hz; rate_hz only documents the schedule (write {scheduled:g} or leave it "
                 f"out; the supported rates are {_scheduled_rates()}; pfma serve --frame-rate or "
                 f"--schedule sets what runs)", bi, key="rate_hz")
        if not isinstance(b["channels"], list):
            fail(f"board {name}: channels must be an array of channel tables", bi, key="channels")
        chans: list[Channel] = []
        seen: set[int] = set()
        for ci, c in enumerate(b["channels"]):
            if not isinstance(c, dict):
                fail(f"board {name}: channel entry {ci} is not a table", bi, ci)
            extra = set(c) - CHANNEL_KEYS
            if extra:
                fail(f"board {name}: channel entry has unknown key(s) {', '.join(sorted(extra))}", bi, ci)
            for key in ("ch", "signal", "label", "units"):
                if key not in c:
                    fail(f"board {name}: channel entry is missing {key!r}", bi, ci)
            ch = c["ch"]
            if not _is_int(ch) or not 0 <= ch < n_channels:
                fail(f"board {name}: channel {ch!r} out of range 0..{n_channels - 1} for a {kind}", bi, ci)
            if ch in seen:
                fail(f"board {name}: channel {ch} listed twice", bi, ci)
            seen.add(ch)
            sig = c["signal"]
            if not isinstance(sig, str) or not SIGNAL_RE.match(sig):
                fail(f"board {name}: signal {sig!r} is not a snake_case name", bi, ci)
            if sig in signals:
                fail(f"signal {sig!r} used twice (also board entry {signals[sig][0] + 1})", bi, ci)
            signals[sig] = (bi, ci)
            direction = c.get("direction", DEFAULT_DIRECTION.get(device))
            if direction not in ("in", "out"):
                fail(f"board {name}: channel {ch} needs direction 'in' or 'out', not {direction!r}", bi, ci)
            for key in ("scale", "offset"):
                if key in c and not _is_number(c[key]):
                    fail(f"board {name}: channel {ch} {key} must be a number, not {c[key]!r}", bi, ci)
            scale = float(c.get("scale", 1.0))
            if scale == 0:
                fail(f"board {name}: channel {ch} scale must not be 0", bi, ci)
            baud = c.get("baud")
            if baud is not None:
                if device != "serial":
                    fail(f"board {name}: channel {ch}: 'baud' applies to serial channels only", bi, ci)
                rates = entry.serial_rates()
                if not _is_number(baud) or baud not in rates:
                    fail(f"board {name}: channel {ch} baud {baud!r} is not a rate the {kind} offers "
                         f"({', '.join(f'{r:g}' for r in rates)})", bi, ci)
            if not isinstance(c.get("spare", False), bool):
                fail(f"board {name}: channel {ch} spare must be true or false, not {c['spare']!r}", bi, ci)
            limit = c.get("limit")
            if limit is not None:
                if device != "dac":
                    fail(f"board {name}: channel {ch}: 'limit' applies to DAC command channels only", bi, ci)
                if isinstance(limit, bool) or not isinstance(limit, (int, float)) or \
                        not math.isfinite(limit) or limit <= 0:
                    fail(f"board {name}: channel {ch} limit must be a positive number, not {limit!r}", bi, ci)
                limit = float(limit)
            quantity, joint = c.get("quantity", ""), c.get("joint", "")
            if quantity and QUANTITIES.get(quantity) is None:
                fail(f"board {name}: channel {ch} quantity {quantity!r} is not one of "
                     f"{', '.join(QUANTITIES)}", bi, ci)
            if quantity and QUANTITIES[quantity] != device:
                fail(f"board {name}: channel {ch}: a {device} channel cannot carry {quantity!r} "
                     f"(a {QUANTITIES[quantity]} quantity)", bi, ci)
            if not isinstance(joint, str) or (joint and not SIGNAL_RE.match(joint)):
                fail(f"board {name}: channel {ch} joint {joint!r} is not a snake_case name", bi, ci)
            if joint and not quantity:
                fail(f"board {name}: channel {ch} names joint {joint!r} but no quantity", bi, ci)
            if quantity and quantity not in ("hand_controller", "force_torque") and not joint:
                fail(f"board {name}: channel {ch} quantity {quantity!r} needs the joint it belongs to", bi, ci)
            for finding in nominal.check(device, joint, quantity, str(c["units"]), scale,
                                         float(c.get("offset", 0.0)), limit):
                what = f"{sig}.{finding.field}"
                if finding.overridable and what in overrides:
                    nonnominal.append((what, f"{what} = {finding.value:g} accepted outside the nominal band "
                                             f"by [checks] allow_nonnominal ({source}): {finding.why}"))
                    continue
                fail(f"board {name}: channel {ch} ({sig}) {finding.field} = {finding.value:g}: {finding.why}"
                     + (f"; a lab that knows better lists \"{what}\" in [checks] allow_nonnominal"
                        if finding.overridable else ""), bi, ci)
            if joint:
                if (joint, quantity) in roles:
                    fail(f"joint {joint!r} has two {quantity} channels ({roles[(joint, quantity)]} "
                         f"and {sig})", bi, ci)
                roles[(joint, quantity)] = sig
            chans.append(Channel(
                device=device, board=name, kind=kind, address=base, channel=ch, signal=sig,
                label=str(c["label"]), units=str(c["units"]), direction=direction, rate_hz=rate,
                spare=bool(c.get("spare", False)), scale=scale, offset=float(c.get("offset", 0.0)),
                baud=c.get("baud"), limit=limit, joint=joint, quantity=quantity))
        missing = sorted(set(range(n_channels)) - seen)
        if missing:
            fail(f"board {name}: channel(s) {', '.join(map(str, missing))} not listed "
                 f"(list unused ones with spare = true)", bi)
        chans.sort(key=lambda x: x.channel)
        boards.append(BoardConfig(name=name, kind=kind, device=device, base=base, window=window,
                                  rate_hz=rate, title=str(b.get("title", kind)), channels=tuple(chans)))
    analog = {c.signal: c for b in boards for c in b.channels}
    for o in overrides:
        sig, _, fld = o.rpartition(".")
        c = analog.get(sig)
        if c is None or nominal.nominal(c.device, c.joint, c.quantity) is None:
            checked = [s for s, x in analog.items() if nominal.nominal(x.device, x.joint, x.quantity)]
            _section_fail(text, source, "checks", "allow_nonnominal",
                          f"[checks] allow_nonnominal names {o!r}, but {sig!r} is not a channel the "
                          f"nominal checks judge" + did_you_mean(sig, checked))
        if fld == "limit" and c.device != "dac":
            _section_fail(text, source, "checks", "allow_nonnominal",
                          f"[checks] allow_nonnominal names {o!r}, but only DAC channels have a limit")
    amp = data.get("amplifier_enable")
    joints = _arm_joints(data.get("arm", {}), roles, text, source)
    return RackConfig(name=str(rack.get("name", "rack")), boards=tuple(boards),
                      bit3=_bit3(data.get("bit3", {}), text, source), source=source,
                      commands=_command_policy(data.get("commands", {}), text, source),
                      joints=joints,
                      envelope=_envelope(data.get("envelope", {}), joints, text, source),
                      overrides=overrides, nonnominal=tuple(nonnominal),
                      amplifier_enable=None if amp is None else _amplifier_enable(amp, boards, text, source))


def _scheduled_rates() -> str:
    return ", ".join(f"{d} {r:g} Hz" for d, r in SCHEDULED_RATES_HZ.items())


def _section_fail(text: str, source: str, section: str, key: str | None, msg: str) -> NoReturn:
    line = _section_key_line(text, section, key)
    raise ConfigError(f"{source}:{line}: {msg}" if line else f"{source}: {msg}")


def _overrides(raw, text: str, source: str) -> tuple[str, ...]:
    """``[checks] allow_nonnominal``: a list of ``"signal.field"`` (field: scale, offset,
    limit); the signals are checked against the channels once they are read."""
    fail = _section(raw, "checks", CHECKS_KEYS, text, source)
    names = raw.get("allow_nonnominal", [])
    fields = nominal.OVERRIDABLE_FIELDS
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        fail(f"[checks] allow_nonnominal must be a list of \"signal.field\" strings, not {names!r}",
             "allow_nonnominal")
    for n in names:
        sig, dot, fld = n.rpartition(".")
        if not dot or not SIGNAL_RE.match(sig) or fld not in fields:
            fail(f"[checks] allow_nonnominal entry {n!r} is not \"signal.field\" with field one of "
                 f"{', '.join(fields)}", "allow_nonnominal")
    if len(set(names)) != len(names):
        fail(f"[checks] allow_nonnominal names an entry twice: {names!r}", "allow_nonnominal")
    return tuple(names)


def _amplifier_enable(raw, boards: list[BoardConfig], text: str, source: str) -> AmplifierEnable:
    """Validate ``[amplifier_enable]``: ``board`` a pio board of the rack, ``port`` one of
    its channels with ``direction = "out"`` and no other use (not the matrix switcher),
    ``bit`` 0..7."""
    fail = _section(raw, "amplifier_enable", AMPLIFIER_ENABLE_KEYS, text, source)
    missing = sorted(AMPLIFIER_ENABLE_KEYS - set(raw))
    if missing:
        fail(f"[amplifier_enable] needs {', '.join(missing)} (board = a pio board, port = 0..3, bit = 0..7)")
    name, port, bit = raw["board"], raw["port"], raw["bit"]
    pio = [b for b in boards if b.device == "pio"]
    found = [b for b in pio if b.name == name]
    if not found:
        fail(f"[amplifier_enable] board {name!r} is not a pio board of this rack; pio boards: "
             f"{', '.join(b.name for b in pio) or 'none'}", "board")
    board = found[0]
    if not _is_int(port) or not 0 <= port < len(board.channels):
        fail(f"[amplifier_enable] port must be an integer 0..{len(board.channels) - 1}, not {port!r}", "port")
    if not _is_int(bit) or not 0 <= bit <= 7:
        fail(f"[amplifier_enable] bit must be an integer 0..7, not {bit!r}", "bit")
    ch = board.signal(port)
    if ch.direction != "out" or ch.signal == "matrix_switcher_route" or ch.signal.startswith("user_if_box"):
        fail(f"[amplifier_enable] {name} port {port} ({ch.signal}) must be an output of its own: give "
             f"that channel direction = \"out\" and a signal of its own (not the matrix switcher's or "
             f"the user inputs')", "port")
    return AmplifierEnable(str(name), int(port), int(bit))


def _envelope(raw, joints: tuple[str, ...], text: str, source: str) -> envelope_cfg.Envelope:
    """``[envelope]``: the service's motion envelope per joint (:mod:`pfma.envelope`)."""
    if not isinstance(raw, dict):
        _section_fail(text, source, "envelope", None, "[envelope] must be a table")

    def fail(msg: str, key: str | None = None) -> NoReturn:
        _section_fail(text, source, "envelope", key, msg)
    return envelope_cfg.parse(raw, joints, fail)


def _arm_joints(raw, roles: dict[tuple[str, str], str], text: str, source: str) -> tuple[str, ...]:
    """Validate ``[arm] joints``: distinct names, each with an angle, a rate, a rate
    command and a current-limit channel in the rack (what the service and the controller
    need of a servoed joint)."""
    fail = _section(raw, "arm", ARM_KEYS, text, source)
    joints = raw.get("joints", [])
    if not isinstance(joints, list) or not all(isinstance(j, str) and SIGNAL_RE.match(j) for j in joints):
        fail(f"[arm] joints must be a list of snake_case joint names, not {joints!r}", "joints")
    if len(set(joints)) != len(joints):
        fail(f"[arm] joints lists a joint twice: {joints!r}", "joints")
    for j in joints:
        missing = [q for q in ("angle", "rate", "rate_command", "current_limit") if (j, q) not in roles]
        if missing:
            fail(f"[arm] joint {j!r} has no {', '.join(missing)} channel (channel keys joint = {j!r}, "
                 f"quantity = ...)", "joints")
    return tuple(joints)


def _section(raw, section: str, known: set[str], text: str, source: str):
    """Check that ``[section]`` is a table with only ``known`` keys; return its ``fail(msg,
    key=None)``, which raises a ConfigError naming the file and the line of the section (or
    of ``key`` in it)."""
    def fail(msg: str, key: str | None = None) -> NoReturn:
        _section_fail(text, source, section, key, msg)

    if not isinstance(raw, dict):
        fail(f"[{section}] must be a table")
    extra = set(raw) - known
    if extra:
        fail(f"[{section}]: unknown key(s) {', '.join(sorted(extra))}; known: {', '.join(sorted(known))}",
             sorted(extra)[0])
    return fail


def _command_policy(raw, text: str, source: str) -> CommandPolicy:
    fail = _section(raw, "commands", COMMANDS_KEYS, text, source)
    age = raw.get("max_input_age_frames", CommandPolicy.max_input_age_frames)
    if isinstance(age, bool) or not isinstance(age, int) or not 1 <= age <= 64:
        fail(f"[commands] max_input_age_frames must be an integer 1..64, not {age!r}", "max_input_age_frames")
    margin = raw.get("limit_margin", CommandPolicy.limit_margin)
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0 <= margin <= 0.5:
        fail(f"[commands] limit_margin must be a number 0..0.5, not {margin!r}", "limit_margin")
    return CommandPolicy(int(age), float(margin))



def _bit3(raw, text: str, source: str) -> dict:
    """Validate ``[bit3]``: ``size`` (32768, the adapter's window) and ``*_window`` keys,
    each ``[lo, hi]`` integers with ``hi - lo + 1 == size``."""
    fail = _section(raw, "bit3", BIT3_KEYS, text, source)
    size = raw.get("size", BIT3_SIZE)
    if not _is_int(size) or size != BIT3_SIZE:
        fail(f"[bit3] size must be {BIT3_SIZE} (the Bit3 window, bytes), not {size!r}", "size")
    out = {"size": size}
    for key in sorted(BIT3_KEYS - {"size"}):
        if key not in raw:
            continue
        w = raw[key]
        if not (isinstance(w, list) and len(w) == 2 and all(_is_int(x) and x >= 0 for x in w)):
            fail(f"[bit3] {key} must be a [lo, hi] pair of addresses (integers), not {w!r}", key)
        lo, hi = w
        if hi - lo + 1 != size:
            fail(f"[bit3] {key} [0x{lo:X}, 0x{hi:X}] spans {hi - lo + 1} bytes, not size {size}", key)
        out[key] = (lo, hi)
    return out
