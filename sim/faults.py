"""Faults of the simulated rack, written as short specs: one grammar for every tool.

``pfma serve --rack fake --fault SPEC``, ``pfma fault inject|clear|list``, scenario files
(:mod:`sim.scenario`) and ``pfma checkout --sim-fault SPEC`` all parse the same specs
here. A spec names one fault; :func:`parse_fault` turns it into a :class:`Fault` with
``apply(world)``, ``clear(world)`` and a one-line ``description``. Every fault acts on
the register-level fakes (or on the far end of a serial cable) exactly where the
hardware fault would be, so the service sees it only through registers and bytes:

========================================  ==================================================
spec                                      what the hardware does
========================================  ==================================================
``bus-error:BOARD``                       the board stops answering: every access is a bus error
``bus-error:BOARD@0xOFF`` / ``@REG``      one register (its 16-bit word) stops answering
``stuck-bit:BOARD@REG:BIT=0|1``           a data bit of a register (or DAC latch) stuck at 0/1
``adc-busy-stuck[:BOARD]``                the A/D converter's BUSY stays set, EOC never comes
``resolver-los:SIGNAL[:freeze|zero]``     resolver loss of signal: status bit set, reading
                                          frozen (default) or zero
``serial-noise[:LINE]``                   garbage bursts interleaved in a line's bytes
``serial-drop:LINE``                      bytes lost from a line's stream
``serial-stall:LINE``                     the far end sends nothing until cleared
``serial-disconnect:LINE``                the far end goes silent (it neither sends nor hears)
``ft-unplugged``                          the F/T sensor's cable pulled from its MVME400 port
``hand-unplugged``                        the CRL hand controller's cable pulled (and a USB
                                          6-axis: :func:`attach_usb_hand_controller`)
``tach-reversed:JOINT``                   the tachometer reads -1 x the joint rate
``adc-dead:SIGNAL=VOLTS``                 an A/D input stuck at VOLTS whatever it is fed
``brake-held:JOINT``                      the joint's brake stays on whatever its current limit
``amp-off:JOINT``                         the joint's PWM stage is off: no motor current at all
``load:JOINT=NM``                         an external torque of NM N*m on the joint (a snag,
                                          an unexpected payload, a collision)
``panel-off:28v``                         servo chassis front panel (IRSS 3.6): the +28 VDC
                                          supply off: no drive on any axis, every brake set,
                                          and the +/-15 V converter unpowered (as below)
``panel-off:15v``                         the +/-15 V DC-DC converter off: no motor current,
                                          current monitors and tach outputs 0 V, brakes set
``panel-off:pwm:JOINT``                   the PWM output stage switch of a joint or the
                                          gripper off: no motor current on that axis
``panel-off:brake:JOINT``                 a joint's brake release switch off: its brake stays
                                          set whatever the current limit (not the gripper)
``ft-noise``                              = ``serial-noise:`` the F/T line (the checkout's name)
========================================  ==================================================

BOARD is a board name of the rack (``rtd1``, ``adc`` ...), SIGNAL a channel's signal name,
LINE a serial channel's signal name (``ft_sensor``, ``crl_hand_controller``), REG a
register name of the board's table (``CSR``, ``CH0``, ``SCAN[3]``, ``DAC[5]``; ``pfma regs
KIND``) or a byte offset from the board's base (``0x04``). An unknown kind, board,
signal, line or register is a :class:`~pfma.errors.ConfigError` with the closest names.

:class:`FaultSet` keeps the faults active on one world (inject, clear one, clear all,
list); it refuses a second copy of an active fault.
"""

from __future__ import annotations

import re
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

from pfma.errors import ConfigError, did_you_mean
from pfma.rack import RackConfig

#: noise on a serial line: this burst after every NOISE_EVERY_BYTES bytes of the far end's
#: output (assumed: three bytes that are no valid record or frame start, every ~300 bytes,
#: about six bursts a second at 19200 baud; the checkout's ft-noise always used these)
NOISE_BURST = b"\x55\xaa\x13"
NOISE_EVERY_BYTES = 300
#: drops on a serial line: DROP_BYTES bytes lost after every DROP_EVERY_BYTES (assumed, as
#: the noise: a record or frame damaged a few times a second)
DROP_BYTES = 3
DROP_EVERY_BYTES = 300
#: ``tach-reversed``: the SimErrors tach scale error that makes tach volts = -K_w qdot
TACH_REVERSED_ERROR = -2.0

#: every kind: (syntax, one-line meaning), in the order ``list`` prints them
KINDS: dict[str, tuple[str, str]] = {
    "bus-error": ("bus-error:BOARD[@0xOFFSET|@REG]",
                  "the board (or one register of it) stops answering: every access is a bus error"),
    "stuck-bit": ("stuck-bit:BOARD@REG:BIT=0|1", "a data bit of a register stuck at 0 or 1"),
    "adc-busy-stuck": ("adc-busy-stuck[:BOARD]", "the A/D board's BUSY bit stays set; no conversion ends"),
    "resolver-los": ("resolver-los:SIGNAL[:freeze|zero]",
                     "resolver loss of signal: status bit set, reading frozen (default) or 0"),
    "serial-noise": ("serial-noise[:LINE]", "garbage bursts in a serial line's bytes (default: every line)"),
    "serial-drop": ("serial-drop:LINE", "bytes lost from a serial line's stream"),
    "serial-stall": ("serial-stall:LINE", "the far end of a serial line sends nothing until cleared"),
    "serial-disconnect": ("serial-disconnect:LINE", "the far end of a serial line goes silent and deaf"),
    "ft-unplugged": ("ft-unplugged", "the F/T sensor's cable pulled from its MVME400 port"),
    "hand-unplugged": ("hand-unplugged", "the CRL hand controller's cable pulled (and a USB 6-axis)"),
    "tach-reversed": ("tach-reversed:JOINT", "the joint's tachometer reads -1 x its rate"),
    "adc-dead": ("adc-dead:SIGNAL=VOLTS", "an A/D input stuck at VOLTS whatever it is fed"),
    "ft-noise": ("ft-noise", "garbage bursts on the F/T line (= serial-noise on the F/T line)"),
    "brake-held": ("brake-held:JOINT", "the joint's brake stays engaged whatever its current limit"),
    "amp-off": ("amp-off:JOINT", "the joint's amplifier (PWM stage) is off: no motor current"),
    "load": ("load:JOINT=NM", "an external torque of NM N*m on the joint (snag, payload, collision)"),
    "switcher-silent": ("switcher-silent", "the matrix video switcher never acknowledges a route (its strobe handshake)"),
    # the servo control chassis' front-panel switches (IRSS 3.6): one kind, a row per switch
    "panel-off:28v": ("panel-off:28v", "servo chassis +28 VDC off: no drive on any axis, every brake set, "
                                       "no +/-15 V either"),
    "panel-off:15v": ("panel-off:15v", "servo chassis +/-15 V converter off: no motor current, monitors and "
                                       "tachs read 0 V, brakes set"),
    "panel-off:pwm": ("panel-off:pwm:JOINT", "the front-panel switch of a joint's (or the gripper's) PWM "
                                             "stage off: no motor current"),
    "panel-off:brake": ("panel-off:brake:JOINT", "the front-panel brake release switch of a joint off: its "
                                                 "brake stays set"),
}


def kinds_help() -> list[str]:
    """One line per kind: its syntax and meaning (``pfma fault list``)."""
    width = max(len(s) for s, _ in KINDS.values())
    return [f"{syntax:<{width}}  {meaning}" for syntax, meaning in KINDS.values()]


class Fault:
    """One parsed fault. ``key`` identifies it among active faults (two specs with the same
    key are the same fault, e.g. ``resolver-los:X`` and ``resolver-los:X:freeze``)."""

    kind = ""

    def __init__(self, spec: str, key: tuple, description: str) -> None:
        self.spec = spec  #: the spec as written
        self.key = key
        self.description = description  #: one line

    def apply(self, world) -> None:
        raise NotImplementedError

    def clear(self, world) -> None:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<Fault {self.spec}>"


def _fail(spec: str, why: str) -> ConfigError:
    return ConfigError(f"fault {spec!r}: {why}")


# -- board faults --------------------------------------------------------------------------
class _BoardFault(Fault):
    """A named fault of one fake board (``FakeBoard.inject``)."""

    def __init__(self, spec: str, key: tuple, description: str, board: str, name: str,
                 params: dict) -> None:
        super().__init__(spec, key, description)
        self.board = board
        self.name = name  #: the fake's fault name
        self.params = params

    def apply(self, world) -> None:
        world.bus[self.board].inject(self.name, **self.params)

    def clear(self, world) -> None:
        # the fake clears a fault name as a whole; the same board's other active faults of
        # that name are put back by FaultSet.clear (they are stateless: a bit, a word)
        world.bus[self.board].clear(self.name)


class _LossOfSignal(_BoardFault):
    def clear(self, world) -> None:
        world.bus[self.board].clear("loss_of_signal", channel=self.params["channel"])


def _board(spec: str, name: str, rack: RackConfig):
    try:
        return rack.board(name)
    except KeyError:
        raise _fail(spec, f"no board {name!r} in rack {rack.name}"
                    + (did_you_mean(name, (b.name for b in rack.boards))
                       or f"; boards: {', '.join(b.name for b in rack.boards)}")) from None


def _fake_class(kind: str):
    from fakes.rack import fake_class
    return fake_class(kind)


def _resolve_description(kind: str):
    """The register table of a board kind (the one the driver and the fake share)."""
    return _fake_class(kind).description


def _register(spec: str, board, text: str) -> tuple[int, str]:
    """(byte offset, register name) of ``text`` on ``board``: a name of its register table
    (``CSR``, ``SCAN[3]``) or a byte offset from its base (``0x04``)."""
    from drivers.registers import register_name
    from fakes.testing import register_offset
    desc = _resolve_description(board.kind)
    if re.fullmatch(r"0[xX][0-9a-fA-F]+|\d+", text):
        off = int(text, 0)
        if not 0 <= off < desc.window:
            raise _fail(spec, f"offset 0x{off:X} is outside {board.name}'s 0x{desc.window:X}-byte "
                              f"window ({board.kind})")
        return off, register_name(desc, off)
    regs = target_registers(desc)
    names = [r.name for r in regs]
    listed = f"; registers: {', '.join(register_text(r) for r in regs)}"
    try:
        off = register_offset(desc, text)
    except KeyError:
        raise _fail(spec, f"{board.name} ({board.kind}) has no register {text!r}"
                    + (did_you_mean(text.partition("[")[0], names) or listed)
                    + f" (pfma regs {board.kind})") from None
    except (ValueError, IndexError) as err:
        raise _fail(spec, f"{board.name} register {text!r}: {err}") from None
    reg = desc.register_at(off)
    base = text.partition("[")[0]
    if reg is not None and reg.name != base:  # an overlay (the DAC's CTRL on DAC[0]'s word)
        raise _fail(spec, f"{board.name} {base} shares its address (+0x{off:02X}) with "
                          f"{register_name(desc, off)}: the board tells them apart by the word written, "
                          f"not by the address a fault acts on, so {base} is no fault target" + listed)
    if reg is None or (reg.count > 1 and "[" not in text and text != reg.name):
        raise _fail(spec, f"{board.name} register {text!r} not found")
    return off, register_name(desc, off)


def target_registers(desc) -> list:
    """The registers of a board's table a fault (``bus-error:B@REG``, ``stuck-bit:B@REG:..``)
    can name: every one but a register that overlays another's address (the VMIVME-4100's
    CTRL shares offset 0x00 with DAC[0]; the board tells them apart by D15 of the word
    written, which a fault on an address cannot)."""
    return [r for r in desc.registers if desc.register_at(r.offset) is r]


def register_text(reg) -> str:
    """``CSR``, or ``SCAN[0..31]`` for a register array."""
    return f"{reg.name}[0..{reg.count - 1}]" if reg.count > 1 else reg.name


def _parse_bus_error(spec: str, arg: str, rack: RackConfig) -> Fault:
    if not arg:
        raise _fail(spec, "needs a board: bus-error:BOARD or bus-error:BOARD@0xOFFSET")
    name, at, where = arg.partition("@")
    board = _board(spec, name, rack)
    if not at:
        return _BoardFault(spec, ("bus-error", board.name, None),
                           f"{board.name} (A16 0x{board.base:04X}) does not answer: every access "
                           f"is a bus error", board.name, "no_answer", {})
    if not where:
        raise _fail(spec, "nothing after '@': give a register name or 0xOFFSET")
    off, reg = _register(spec, board, where)
    return _BoardFault(spec, ("bus-error", board.name, off & ~1),
                       f"{board.name} {reg} (A16 0x{board.base + off:04X}) does not answer: "
                       f"bus error on that word", board.name, "no_answer", {"offset": off})


def _stuck_bit_boards(rack: RackConfig) -> list[str]:
    """The boards whose fake has the ``stuck_bit`` fault."""
    return [b.name for b in rack.boards if "stuck_bit" in getattr(_fake_class(b.kind), "FAULTS", ())]


def _parse_stuck_bit(spec: str, arg: str, rack: RackConfig) -> Fault:
    m = re.fullmatch(r"([^@:]+)@([^:]+):([^=]+)=(.*)", arg)
    if not m:
        raise _fail(spec, "expected stuck-bit:BOARD@REG:BIT=0|1 (e.g. stuck-bit:adc@SCAN[3]:11=1)")
    board = _board(spec, m.group(1), rack)
    able = _stuck_bit_boards(rack)
    if board.name not in able:
        raise _fail(spec, f"{board.name} ({board.kind}) has no stuck-bit fault; boards with one: "
                          f"{', '.join(able)}")
    off, reg = _register(spec, board, m.group(2))
    try:
        bit = int(m.group(3), 0)
    except ValueError:
        raise _fail(spec, f"bit {m.group(3)!r} is not a number 0..15") from None
    if not 0 <= bit <= 15:
        raise _fail(spec, f"bit {bit} outside 0..15")
    if m.group(4) not in ("0", "1"):
        raise _fail(spec, f"a stuck bit is 0 or 1, not {m.group(4)!r}")
    value = int(m.group(4))
    return _BoardFault(spec, ("stuck-bit", board.name, off, bit),
                       f"{board.name} {reg} bit {bit} stuck at {value}", board.name, "stuck_bit",
                       {"register": off, "bit": bit, "value": value})


class _Several(Fault):
    """One spec acting on several targets (every ADC board, every serial line)."""

    def __init__(self, spec: str, key: tuple, description: str, parts: list[Fault]) -> None:
        super().__init__(spec, key, description)
        self.parts = parts

    def apply(self, world) -> None:
        for p in self.parts:
            p.apply(world)

    def clear(self, world) -> None:
        for p in self.parts:
            p.clear(world)


def _parse_busy_stuck(spec: str, arg: str, rack: RackConfig) -> Fault:
    adcs = rack.boards_of("adc")
    if arg:
        board = _board(spec, arg, rack)
        if board.device != "adc":
            raise _fail(spec, f"{board.name} is a {board.kind}, not an A/D board; A/D boards: "
                              f"{', '.join(b.name for b in adcs) or 'none'}")
        adcs = [board]
    if not adcs:
        raise _fail(spec, f"rack {rack.name} has no A/D board")
    parts: list[Fault] = [_BoardFault(spec, ("adc-busy-stuck", b.name), "", b.name, "busy_stuck", {})
                          for b in adcs]
    names = ", ".join(b.name for b in adcs)
    return _Several(spec, ("adc-busy-stuck", tuple(b.name for b in adcs)),
                    f"A/D {names}: BUSY stuck set, no conversion ends", parts)


def _signals(rack: RackConfig, device: str) -> list[str]:
    """The signal names of the rack's channels on ``device`` boards (rtd, adc)."""
    return [c.signal for c in rack.channels() if c.device == device]


def _channel(spec: str, signal: str, rack: RackConfig, device: str, what: str):
    try:
        ch = rack.channel(signal)
    except KeyError:
        known = _signals(rack, device)
        raise _fail(spec, f"no {what} {signal!r} in rack {rack.name}"
                    + did_you_mean(signal, known)) from None
    if ch.device != device:
        raise _fail(spec, f"{signal} is on {ch.device} board {ch.board}, not a {what}")
    return ch


def _parse_los(spec: str, arg: str, rack: RackConfig) -> Fault:
    signal, _, mode = arg.partition(":")
    if not signal:
        raise _fail(spec, "needs a resolver signal: resolver-los:SIGNAL[:freeze|zero]")
    ch = _channel(spec, signal, rack, "rtd", "resolver signal")
    mode = mode or "freeze"
    if mode not in ("freeze", "zero"):
        raise _fail(spec, f"mode {mode!r}: freeze or zero" + did_you_mean(mode, ("freeze", "zero")))
    reading = "frozen at its last value" if mode == "freeze" else "reading 0"
    return _LossOfSignal(spec, ("resolver-los", ch.signal),
                         f"loss of signal on {ch.signal} ({ch.board} channel {ch.channel}), {reading}",
                         ch.board, "loss_of_signal", {"channel": ch.channel, "mode": mode})


# -- serial lines --------------------------------------------------------------------------
#: the devices taken off their lines by an unplugged fault, per world (so a line fault
#: applied or cleared meanwhile still reaches the far end's model)
_UNPLUGGED: "weakref.WeakKeyDictionary[Any, dict[str, Any]]" = weakref.WeakKeyDictionary()


#: a USB 6-axis hand controller's fake (``fakes.hid.FakeHidDevice``) per world: the other
#: hand controller ``hand-unplugged`` pulls (the world itself has only the serial ones)
_USB_HAND: "weakref.WeakKeyDictionary[Any, Any]" = weakref.WeakKeyDictionary()


def attach_usb_hand_controller(world, device) -> None:
    """Tell the faults of ``world`` about a simulated USB 6-axis (anything with
    ``unplug()``/``replug()``, e.g. ``fakes.hid.FakeHidDevice``): ``hand-unplugged`` then
    pulls its cable too."""
    _USB_HAND[world] = device


def _serial_lines(rack: RackConfig) -> dict[str, tuple[str, int]]:
    """signal -> (serial board, channel) of every serial line of the rack."""
    return {c.signal: (b.name, c.channel) for b in rack.boards_of("serial") for c in b.channels}


def _line(spec: str, line: str, rack: RackConfig) -> tuple[str, int]:
    lines = _serial_lines(rack)
    if not line:
        raise _fail(spec, f"needs a line: one of {', '.join(lines) or '(none in this rack)'}")
    if line not in lines:
        raise _fail(spec, f"no serial line {line!r} in rack {rack.name}"
                    + (did_you_mean(line, lines) or f"; lines: {', '.join(lines) or 'none'}"))
    return lines[line]


def _far_end(world, line: str):
    """The model on the far end of ``line`` (also while its cable is unplugged)."""
    board, ch = _serial_lines(world.rack_config)[line]
    dev = world.bus[board].peer(ch).device
    if dev is None:
        dev = _UNPLUGGED.get(world, {}).get(line)
    if dev is None:
        raise ConfigError(f"serial line {line}: nothing is cabled to {board} port {'AB'[ch]}")
    return dev


class _LineFault(Fault):
    def __init__(self, spec: str, kind: str, line: str, description: str,
                 on: Callable[[Any], None], off: Callable[[Any], None]) -> None:
        super().__init__(spec, (kind, line), description)
        self.line = line
        self._on, self._off = on, off

    def apply(self, world) -> None:
        self._on(_far_end(world, self.line))

    def clear(self, world) -> None:
        self._off(_far_end(world, self.line))


_LINE_KINDS: dict[str, tuple[str, Callable[[Any], None], Callable[[Any], None]]] = {
    "serial-noise": ("noise bursts ({n} bytes every {e}) on {line}",
                     lambda d: d.noise_every(NOISE_BURST, NOISE_EVERY_BYTES), lambda d: d.stop_noise()),
    "serial-drop": ("{dn} bytes lost every {de} on {line}",
                    lambda d: d.drop_every(DROP_BYTES, DROP_EVERY_BYTES), lambda d: d.stop_drops()),
    "serial-stall": ("{line}: the far end sends nothing until cleared",
                     lambda d: d.stall(), lambda d: d.resume()),
    "serial-disconnect": ("{line}: the far end disconnected (silent and deaf)",
                          lambda d: d.disconnect(), lambda d: d.reconnect()),
}


def _line_fault(spec: str, kind: str, line: str) -> _LineFault:
    text, on, off = _LINE_KINDS[kind]
    return _LineFault(spec, kind, line, text.format(n=len(NOISE_BURST), e=NOISE_EVERY_BYTES, line=line,
                                                    dn=DROP_BYTES, de=DROP_EVERY_BYTES), on, off)


def _parse_line_kind(kind: str) -> Callable[[str, str, RackConfig], Fault]:
    def parse(spec: str, arg: str, rack: RackConfig) -> Fault:
        if kind == "serial-noise" and not arg:
            lines = list(_serial_lines(rack))
            if not lines:
                raise _fail(spec, f"rack {rack.name} has no serial line")
            return _Several(spec, (kind, None), f"noise bursts on every serial line ({', '.join(lines)})",
                            [_line_fault(spec, kind, ln) for ln in lines])
        _line(spec, arg, rack)
        return _line_fault(spec, kind, arg)
    return parse


class _Unplugged(Fault):
    """A cable pulled from an MVME400 port: the far end's model is taken off the line, so
    nothing arrives and what the board sends goes nowhere. Assumed: the modem-control
    inputs (CTS, DCD, DSR) are strapped at the board's connector (the fake asserts them
    by default), so a pulled cable loses the data only."""

    def __init__(self, spec: str, line: str, description: str, hid: bool = False) -> None:
        super().__init__(spec, (spec, line), description)
        self.line = line
        self.hid = hid

    def apply(self, world) -> None:
        board, ch = _serial_lines(world.rack_config)[self.line]
        peer = world.bus[board].peer(ch)
        if peer.device is not None:
            _UNPLUGGED.setdefault(world, {})[self.line] = peer.device
            peer.attach(None)
        hid = _USB_HAND.get(world) if self.hid else None
        if hid is not None:
            hid.unplug()

    def clear(self, world) -> None:
        board, ch = _serial_lines(world.rack_config)[self.line]
        dev = _UNPLUGGED.get(world, {}).pop(self.line, None)
        if dev is not None:
            world.bus[board].peer(ch).attach(dev)
        hid = _USB_HAND.get(world) if self.hid else None
        if hid is not None:
            hid.replug()


def _ft_line(spec: str, rack: RackConfig) -> str:
    for b in rack.boards_of("serial"):
        for c in b.channels:
            if c.quantity == "force_torque":
                return c.signal
    raise _fail(spec, f"rack {rack.name} has no F/T sensor line (a serial channel with "
                      f"quantity force_torque)")


#: the CRL hand controller's line: by signal name (the rack has no quantity for it)
CRL_SIGNAL = "crl_hand_controller"


def _parse_unplugged(spec: str, arg: str, rack: RackConfig) -> Fault:
    kind = spec.partition(":")[0]
    if arg:
        raise _fail(spec, f"{kind} takes no argument")
    if kind == "ft-unplugged":
        line = _ft_line(spec, rack)
        return _Unplugged(spec, line, f"F/T sensor unplugged from {line} (no bytes either way)")
    if CRL_SIGNAL not in _serial_lines(rack):
        raise _fail(spec, f"rack {rack.name} has no {CRL_SIGNAL} line")
    return _Unplugged(spec, CRL_SIGNAL, f"CRL hand controller unplugged from {CRL_SIGNAL} "
                                        f"(no bytes either way)", hid=True)


def _parse_ft_noise(spec: str, arg: str, rack: RackConfig) -> Fault:
    if arg:
        raise _fail(spec, "ft-noise takes no argument (serial-noise:LINE names a line)")
    line = _ft_line(spec, rack)
    f = _line_fault(spec, "serial-noise", line)
    f.description = f"noise bursts on the F/T line {line} ({len(NOISE_BURST)} bytes every {NOISE_EVERY_BYTES})"
    return f


# -- the arm's truth errors (checkout faults) --------------------------------------------------
class _ErrorsFault(Fault):
    """A change of the simulated rack's truth errors (``SimulatedRack.set_errors``); clear
    puts back what this fault replaced."""

    def __init__(self, spec: str, key: tuple, description: str,
                 change: Callable[[Any], tuple[Any, Any]]) -> None:
        super().__init__(spec, key, description)
        self._change = change
        self._undo: Callable[[Any], Any] | None = None

    def apply(self, world) -> None:
        new, undo = self._change(world.sim.errors)
        world.sim.set_errors(new)
        self._undo = undo

    def clear(self, world) -> None:
        if self._undo is not None:
            world.sim.set_errors(self._undo(world.sim.errors))
            self._undo = None


def _joints() -> list[str]:
    """The simulated arm's joint names (the rack's), the gripper last."""
    from fakes.arm_params import AXES
    return [a.joint for a in AXES]


def _braked_joints() -> list[str]:
    """The joints with a brake (six; the gripper has none, IRSS 3.6)."""
    from fakes.arm_params import AXES
    return [a.joint for a in AXES if a.brake]


def _axis(spec: str, name: str) -> int:
    """The simulated arm's axis index of the joint ``name`` (the rack's joint names)."""
    stems = _joints()
    if name not in stems:
        raise _fail(spec, f"no joint {name!r}" + (did_you_mean(name, stems) or "")
                    + f"; joints: {', '.join(stems)}")
    return stems.index(name)


def _axis_error(spec: str, key: tuple, description: str, field: str, i: int, value) -> Fault:
    """A fault that sets one axis's entry of the SimErrors tuple ``field`` to ``value``."""
    def change(e):
        old = getattr(e, field)[i]
        new = list(getattr(e, field))
        new[i] = value

        def undo(e2):
            back = list(getattr(e2, field))
            back[i] = old
            return replace(e2, **{field: tuple(back)})
        return replace(e, **{field: tuple(new)}), undo
    return _ErrorsFault(spec, key, description, change)


def _parse_tach(spec: str, arg: str, rack: RackConfig) -> Fault:
    i = _axis(spec, arg)
    # tach volts = K_w (1 + e) qdot = -K_w qdot
    return _axis_error(spec, ("tach-reversed", arg), f"tachometer of {arg} reversed",
                       "tach_scale_error", i, TACH_REVERSED_ERROR)


def _parse_brake_held(spec: str, arg: str, rack: RackConfig) -> Fault:
    i = _axis(spec, arg)
    if arg not in _braked_joints():
        raise _fail(spec, f"the {arg} has no brake (IRSS 3.6: six brake release cards)")
    return _axis_error(spec, ("brake-held", arg), f"brake of {arg} held on", "brake_held", i, True)


def _parse_amp_off(spec: str, arg: str, rack: RackConfig) -> Fault:
    i = _axis(spec, arg)
    return _axis_error(spec, ("amp-off", arg), f"amplifier (PWM stage) of {arg} off", "amp_off", i, True)


#: the servo control chassis' front-panel switches (IRSS 3.6), ``panel-off:SWITCH[:JOINT]``:
#: switch -> (the SimErrors field it sets, what it is)
PANEL_SWITCHES: dict[str, tuple[str, str]] = {
    "28v": ("panel_28v_off", "+28 VDC"),
    "15v": ("panel_15v_off", "+/-15 V converter"),
    "pwm": ("panel_pwm_off", "PWM stage switch"),
    "brake": ("panel_brake_off", "brake release switch"),
}
PANEL_SYNTAX = "panel-off:28v|15v|pwm:JOINT|brake:JOINT"


def _parse_panel(spec: str, arg: str, rack: RackConfig) -> Fault:
    """A front-panel switch of the servo control chassis turned off (its own SimErrors
    fields: clearing it never clears a ``brake-held`` or ``amp-off``, nor they it)."""
    switch, _, name = arg.partition(":")
    if not switch:
        raise _fail(spec, f"needs a switch: {PANEL_SYNTAX}")
    if switch not in PANEL_SWITCHES:
        raise _fail(spec, f"unknown switch {switch!r}"
                    + (did_you_mean(switch, PANEL_SWITCHES) or "") + f"; switches: {PANEL_SYNTAX}")
    field, what = PANEL_SWITCHES[switch]
    kind = f"panel-off:{switch}"
    if switch in ("28v", "15v"):
        if name:
            raise _fail(spec, f"{kind} takes no joint (one switch for the whole chassis)")
        if switch == "28v":
            text = (f"servo chassis {what} off: no PWM drive on any axis, every brake set, "
                    "the +/-15 V converter unpowered")
        else:
            text = (f"servo chassis {what} off: no motor current, current monitors and "
                    "tach filter outputs at 0 V, every brake set")

        def change(e):
            old = getattr(e, field)
            return replace(e, **{field: True}), lambda e2: replace(e2, **{field: old})
        fault: Fault = _ErrorsFault(spec, ("panel-off", switch), text, change)
    else:
        if not name:
            raise _fail(spec, f"needs a joint: {kind}:JOINT")
        if switch == "brake":
            if name == "gripper":
                raise _fail(spec, "the gripper has no brake: the right-hand panel switches release the "
                                  "six joints' brakes (IRSS 3.6)")
            braked = _braked_joints()
            if name not in braked:
                raise _fail(spec, f"no joint {name!r}" + (did_you_mean(name, braked) or "")
                            + f"; joints with a brake: {', '.join(braked)}")
            text = f"front-panel {what} of {name} off: brake set whatever the current limit"
        else:
            text = f"front-panel {what} of {name} off: no motor current"
        fault = _axis_error(spec, ("panel-off", switch, name), text, field, _axis(spec, name), True)
    fault.kind = kind
    return fault


#: the largest ``load:JOINT=NM`` accepted: well beyond any joint's brake (1.5 x 192 N*m)
LOAD_MAX_NM = 1000.0


def _parse_load(spec: str, arg: str, rack: RackConfig) -> Fault:
    name, eq, value = arg.partition("=")
    if not eq:
        raise _fail(spec, "needs a torque: load:JOINT=NM (N*m; the gripper: N)")
    i = _axis(spec, name)
    try:
        nm = float(value)
    except ValueError:
        raise _fail(spec, f"NM {value!r} is not a number") from None
    if not abs(nm) <= LOAD_MAX_NM:  # also refuses NaN
        raise _fail(spec, f"{value} N*m is outside -{LOAD_MAX_NM:g}..{LOAD_MAX_NM:g}")
    return _axis_error(spec, ("load", name), f"external load {nm:g} N*m on {name}", "load_nm", i, nm)


def _parse_adc_dead(spec: str, arg: str, rack: RackConfig) -> Fault:
    sig, eq, volts = arg.partition("=")
    if not sig:
        raise _fail(spec, "needs a signal: adc-dead:SIGNAL=VOLTS")
    _channel(spec, sig, rack, "adc", "A/D signal")
    try:
        v = float(volts) if eq else 0.0
    except ValueError:
        raise _fail(spec, f"VOLTS {volts!r} is not a number") from None
    if not -10.0 <= v <= 10.0:
        raise _fail(spec, f"{v:g} V is outside the A/D range -10..10 V")

    def change(e):
        gains, offsets = dict(e.adc_gain_error), dict(e.adc_offset_v)
        old = (gains.get(sig), offsets.get(sig))
        gains[sig], offsets[sig] = -1.0, v  # read = (1 + g) V + offset = offset

        def undo(e2):
            g2, o2 = dict(e2.adc_gain_error), dict(e2.adc_offset_v)
            for d, prev in ((g2, old[0]), (o2, old[1])):
                if prev is None:
                    d.pop(sig, None)
                else:
                    d[sig] = prev
            return replace(e2, adc_gain_error=g2, adc_offset_v=o2)
        return replace(e, adc_gain_error=gains, adc_offset_v=offsets), undo
    return _ErrorsFault(spec, ("adc-dead", sig), f"ADC input {sig} dead at {v:g} V", change)


def _parse_switcher_silent(spec: str, arg: str, rack: RackConfig) -> Fault:
    if arg:
        raise _fail(spec, "takes no argument (the rack has one matrix switcher)")
    for b in rack.boards_of("pio"):
        if any(c.signal == "matrix_switcher_route" for c in b.channels):
            return _BoardFault(spec, ("switcher-silent", b.name),
                               f"matrix switcher on {b.name} silent: no route acknowledged",
                               b.name, "switcher_silent", {})
    raise _fail(spec, f"rack {rack.name} has no matrix_switcher_route channel")


_PARSERS: dict[str, Callable[[str, str, RackConfig], Fault]] = {
    "bus-error": _parse_bus_error,
    "stuck-bit": _parse_stuck_bit,
    "adc-busy-stuck": _parse_busy_stuck,
    "resolver-los": _parse_los,
    "serial-noise": _parse_line_kind("serial-noise"),
    "serial-drop": _parse_line_kind("serial-drop"),
    "serial-stall": _parse_line_kind("serial-stall"),
    "serial-disconnect": _parse_line_kind("serial-disconnect"),
    "ft-unplugged": _parse_unplugged,
    "hand-unplugged": _parse_unplugged,
    "tach-reversed": _parse_tach,
    "brake-held": _parse_brake_held,
    "amp-off": _parse_amp_off,
    "load": _parse_load,
    "adc-dead": _parse_adc_dead,
    "ft-noise": _parse_ft_noise,
    "switcher-silent": _parse_switcher_silent,
    "panel-off": _parse_panel,
}
#: a kind with several switches has a row per switch in KINDS (``panel-off:28v`` ...)
assert set(_PARSERS) == {k.partition(":")[0] for k in KINDS}


def fault_targets(rack: RackConfig | None = None) -> dict[str, dict[str, Any]]:
    """The names each kind's argument accepts in ``rack`` (default: the simulated rack's),
    from the lists its parser checks against: kind (a :data:`KINDS` key) -> placeholder of
    its syntax (``BOARD``, ``REG``, ``SIGNAL``, ``LINE``, ``JOINT``, ``SWITCH``) -> the
    names, or for ``REG`` board -> the registers (a register array as ``SCAN[0..31]``; a
    byte offset ``0x04`` is accepted too). A kind with no argument maps to ``{}``."""
    if rack is None:
        from pfma.rack import load_rack
        rack = load_rack()
    boards = [b.name for b in rack.boards]
    stuck = _stuck_bit_boards(rack)

    def regs(names: list[str]) -> dict[str, list[str]]:
        return {n: [register_text(r) for r in target_registers(_resolve_description(rack.board(n).kind))]
                for n in names}
    lines = list(_serial_lines(rack))
    joints, braked = _joints(), _braked_joints()
    out: dict[str, dict[str, Any]] = {k: {} for k in KINDS}
    out["bus-error"] = {"BOARD": boards, "REG": regs(boards)}
    out["stuck-bit"] = {"BOARD": stuck, "REG": regs(stuck)}
    out["adc-busy-stuck"] = {"BOARD": [b.name for b in rack.boards_of("adc")]}
    out["resolver-los"] = {"SIGNAL": _signals(rack, "rtd")}
    out["adc-dead"] = {"SIGNAL": _signals(rack, "adc")}
    for kind in _LINE_KINDS:
        out[kind] = {"LINE": lines}
    for kind in ("tach-reversed", "amp-off", "load", "panel-off:pwm"):
        out[kind] = {"JOINT": joints}
    for kind in ("brake-held", "panel-off:brake"):
        out[kind] = {"JOINT": braked}
    out["panel-off:28v"] = out["panel-off:15v"] = {"SWITCH": list(PANEL_SWITCHES)}  # panel-off:SWITCH
    return out


def targets_help(rack: RackConfig | None = None, width: int = 100) -> list[str]:
    """``pfma fault list``'s lines after :func:`kinds_help`: the names each placeholder
    accepts (:func:`fault_targets`), one entry per list, naming the kinds that take it,
    wrapped to ``width`` columns."""
    import textwrap
    if rack is None:
        from pfma.rack import load_rack
        rack = load_rack()
    groups: dict[tuple[str, tuple[str, ...]], list[str]] = {}  # (label, names) -> kinds
    for kind, args in fault_targets(rack).items():
        kind = kind.partition(":")[0] if kind in ("panel-off:28v", "panel-off:15v") else kind
        for ph, names in args.items():
            if ph == "REG":
                for board, regnames in names.items():
                    groups.setdefault((f"REG of {board}", tuple(regnames)), []).append(kind)
            else:
                groups.setdefault((ph, tuple(names)), []).append(kind)
    merged: dict[tuple[str, tuple[str, ...]], list[str]] = {}  # boards with the same registers
    for (label, names), kinds in groups.items():
        if label.startswith("REG of "):
            same = next((k for k in merged if k[0].startswith("REG of ") and k[1] == names
                         and merged[k] == kinds), None)
            if same is not None:
                merged[(f"{same[0]}, {label[7:]}", names)] = merged.pop(same)
                continue
        merged[(label, names)] = kinds
    order = ("BOARD", "REG", "SIGNAL", "LINE", "JOINT", "SWITCH")
    lines = [f"targets in rack {rack.name} (REG may also be a byte offset, e.g. 0x04):"]
    for (label, names), kinds in sorted(merged.items(), key=lambda kv: order.index(kv[0][0].split()[0])):
        head = f"  {label} ({', '.join(dict.fromkeys(kinds))}): "
        lines += textwrap.wrap(", ".join(names) or "none", width=width, initial_indent=head,
                               subsequent_indent="      ", break_long_words=False, break_on_hyphens=False)
    return lines


def parse_fault(spec: str, rack: RackConfig | None = None) -> Fault:
    """The :class:`Fault` a spec names, its names checked against ``rack`` (default: the
    rack the simulated rack runs, ``pfma/rack_default.toml``).

    :raises ConfigError: unknown kind, board, signal, line or register (with the closest
        known names), or a malformed argument
    """
    if rack is None:
        from pfma.rack import load_rack
        rack = load_rack()
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"fault {spec!r}: empty; kinds: {', '.join(KINDS)}")
    spec = spec.strip()
    kind, _, arg = spec.partition(":")
    parser = _PARSERS.get(kind)
    if parser is None:
        raise _fail(spec, f"unknown kind {kind!r}" + (did_you_mean(kind, _PARSERS) or "")
                    + f"; kinds: {', '.join(_PARSERS)} (pfma fault list)")
    fault = parser(spec, arg, rack)
    if not fault.kind:  # the panel's parser names its switch's row (panel-off:pwm)
        fault.kind = kind
    return fault


@dataclass
class Active:
    """A fault in force and when it was injected (the caller's time: seconds or frame)."""

    fault: Fault
    since: float | None = None

    def as_dict(self) -> dict:
        return {"spec": self.fault.spec, "kind": self.fault.kind,
                "description": self.fault.description, "since": self.since}


class FaultSet:
    """The faults in force on one simulated world.

    :param world: a :class:`fakes.world.FakeWorld` (boards on ``bus``, ``sim``, lines)
    """

    def __init__(self, world) -> None:
        self.world = world
        self.rack: RackConfig = world.rack_config
        self.active: list[Active] = []

    def parse(self, spec: str) -> Fault:
        return parse_fault(spec, self.rack)

    def inject(self, spec: str | Fault, since: float | None = None) -> Fault:
        """Parse (if needed) and apply a fault.

        :raises ConfigError: bad spec, or the same fault is already active
        """
        fault = spec if isinstance(spec, Fault) else self.parse(spec)
        for a in self.active:
            if a.fault.key == fault.key:
                raise ConfigError(f"fault {fault.spec!r} is already active (as {a.fault.spec!r})")
        fault.apply(self.world)
        self.active.append(Active(fault, since))
        return fault

    def find(self, spec: str) -> Active:
        """The active fault ``spec`` names (by its key: the same target and kind).

        :raises ConfigError: bad spec, or not active (naming the active ones)
        """
        fault = self.parse(spec)
        for a in self.active:
            if a.fault.key == fault.key:
                return a
        act = ", ".join(a.fault.spec for a in self.active) or "none"
        raise ConfigError(f"fault {fault.spec!r} is not active; active: {act}")

    def clear(self, spec: str) -> list[Fault]:
        """Clear one active fault (``spec``) or every one (``"all"``); returns those cleared."""
        if spec.strip() == "all":
            gone = [a.fault for a in reversed(self.active)]
            for f in gone:
                f.clear(self.world)
            self.active.clear()
            return gone[::-1]
        a = self.find(spec)
        a.fault.clear(self.world)
        self.active.remove(a)
        self._reapply_same_name(a.fault)
        return [a.fault]

    def _reapply_same_name(self, gone: Fault) -> None:
        """A board fault name is cleared as a whole by the fake: put back this board's other
        active faults of the same name (stuck bits, unanswered words)."""
        for g in _board_parts(gone):
            for a in self.active:
                for p in _board_parts(a.fault):
                    if p.board == g.board and p.name == g.name and not isinstance(p, _LossOfSignal):
                        p.apply(self.world)

    def listing(self) -> list[dict]:
        return [a.as_dict() for a in self.active]


def _board_parts(f: Fault) -> Iterable[_BoardFault]:
    if isinstance(f, _BoardFault):
        yield f
    elif isinstance(f, _Several):
        for p in f.parts:
            yield from _board_parts(p)


__all__ = ["Active", "Fault", "FaultSet", "KINDS", "PANEL_SWITCHES", "attach_usb_hand_controller", "kinds_help",
           "parse_fault"]
