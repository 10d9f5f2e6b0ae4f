"""Camera routes: the user I/F box's switches -> the matrix switcher's route byte.

THE one place for the switch-to-route table (docs/cameras.md). The IRSS report says only
that the user I/F box's switches "control the Camera Matrix Switcher" (section 3.5.4),
that the switcher "will direct video signals from three active camera to two monitors"
(3.5.3), and that the box is read on the MVME410 at 0x0040 (3.4.2); the wiring drawings
(849IRS20800, 849IRS40000/40004) are not public. Everything below marked ASSUMED is
therefore a choice, named once here:

- ASSUMED **switch table** (:data:`USER_IF_SWITCHES`): port 0 of the box (input bits
  0..7) carries the camera selection, four switches per monitor: bits 0, 1, 2 put camera
  1, 2, 3 on monitor 1 and bit 3 blanks it; bits 4, 5, 6 put camera 1, 2, 3 on monitor 2
  and bit 7 blanks it. Port 1 (bits 8..15) is the pan, tilt and zoom the report says was
  never implemented: ignored.
- ASSUMED **active low**: a closed switch pulls its line to 0 V; an open line reads 1
  (the board's pull-ups: undriven MVME410 inputs read high, the hardware-registers
  reference notes), so a box that is not plugged in (0xFFFF) selects nothing.
- ASSUMED **a selection acts when it changes**: a monitor's selection is the one of its
  four switches that is closed (none, or more than one closed: no selection). The route
  changes when a monitor's selection changes to a new one, so momentary push-buttons and a
  held selector switch both work, and a route chosen at the console stands until a box
  switch moves.
- The route byte itself (2-bit source code per monitor, 0 = blank, 1..3 = camera; bits 7..4
  written 0) is what the controller posts in the Bit3 field ``outputs.matrix_route`` and
  the service writes unchanged to the switcher. The controller encodes it here
  (:func:`encode_matrix_route`, :func:`decode_matrix_route`) because it may not import the
  drivers (the house, docs/architecture.md); the driver and the fake keep the register
  table, :data:`drivers.pio.registers.MATRIX_SWITCHER` (also ASSUMED). Two encodings of one
  byte, on two sibling floors: ``tests/controller/test_route_encoding.py`` proves they agree
  on every route and reject the same cameras.

The switch table and the route requests are the controller's (it reads the box's word and
chooses the route); tools import them from here.
"""

from __future__ import annotations

#: monitors and cameras of the switcher (IRSS report 3.5.3); camera 0 = blank
MONITORS: tuple[int, ...] = (1, 2)
CAMERAS: tuple[int, ...] = (1, 2, 3)
BLANK = 0

#: the route byte (ASSUMED, the same as ``drivers.pio.registers.MATRIX_SWITCHER``): monitor ->
#: shift of its 2-bit source code; bits 7..4 carry no source (written 0)
MONITOR_SHIFT: dict[int, int] = {1: 0, 2: 2}
_SOURCE_MASK = 0x3


def encode_matrix_route(monitor_1_camera: int, monitor_2_camera: int) -> int:
    """Route byte for the matrix switcher.

    :param monitor_1_camera: 0 = blank, 1..3 = camera
    :param monitor_2_camera: 0 = blank, 1..3 = camera
    :raises ValueError: for a camera number outside 0..3
    """
    value = 0
    for monitor, cam in ((1, monitor_1_camera), (2, monitor_2_camera)):
        if cam not in (BLANK, *CAMERAS):
            raise ValueError(f"matrix switcher monitor {monitor}: camera {cam} not in 0..3")
        value |= cam << MONITOR_SHIFT[monitor]
    return value


def decode_matrix_route(value: int) -> tuple[int, int]:
    """(monitor 1 camera, monitor 2 camera) from a route byte (0 = blank)."""
    return (value >> MONITOR_SHIFT[1]) & _SOURCE_MASK, (value >> MONITOR_SHIFT[2]) & _SOURCE_MASK


#: ASSUMED: user I/F box input bit -> (monitor, camera); camera 0 = blank the monitor
USER_IF_SWITCHES: dict[int, tuple[int, int]] = {
    0: (1, 1), 1: (1, 2), 2: (1, 3), 3: (1, BLANK),
    4: (2, 1), 5: (2, 2), 6: (2, 3), 7: (2, BLANK),
}
#: ASSUMED: a closed switch reads 0 (pull-ups; an unplugged box reads 0xFFFF: nothing closed)
SWITCH_ACTIVE_LOW = True
#: the box's input bits that select routes (the others are not camera routing)
ROUTE_SWITCH_MASK = sum(1 << b for b in USER_IF_SWITCHES)
#: every route the switcher can take: monitor 1 source x monitor 2 source (blank included)
ALL_ROUTES: tuple[int, ...] = tuple(encode_matrix_route(m1, m2) for m1 in (BLANK, *CAMERAS)
                                    for m2 in (BLANK, *CAMERAS))
#: route byte bits that carry no source (written 0)
UNUSED_BITS = 0xF0

_BITS_OF_MONITOR = {m: tuple(sorted((b, cam) for b, (mon, cam) in USER_IF_SWITCHES.items() if mon == m))
                    for m in MONITORS}


def camera_name(camera: int) -> str:
    """``"camera 2"``, or ``"blank"`` for 0."""
    return "blank" if camera == BLANK else f"camera {camera}"


def closed_switches(word: int) -> int:
    """The route switches closed in a box input word, as a mask of input bits."""
    closed = ~word if SWITCH_ACTIVE_LOW else word
    return closed & ROUTE_SWITCH_MASK


def box_selections(word: int) -> tuple[int | None, ...]:
    """Per monitor (1, 2): the camera its closed switch selects (0 = blank), or None when
    none or more than one of its switches is closed."""
    closed = closed_switches(word)
    out: list[int | None] = []
    for m in MONITORS:
        cams = [cam for b, cam in _BITS_OF_MONITOR[m] if closed >> b & 1]
        out.append(cams[0] if len(cams) == 1 else None)
    return tuple(out)


def switch_word(monitor: int, camera: int) -> int:
    """The 16-bit box word with only the switch for ``camera`` on ``monitor`` closed (what a
    test or a simulated operator drives on the fake box)."""
    for b, mc in USER_IF_SWITCHES.items():
        if mc == (monitor, camera):
            return (0xFFFF & ~(1 << b)) if SWITCH_ACTIVE_LOW else (1 << b)
    raise ValueError(f"no user I/F box switch for {camera_name(camera)} on monitor {monitor}")


#: the box word with no switch closed
BOX_IDLE = 0xFFFF if SWITCH_ACTIVE_LOW else 0x0000


def set_monitor(route: int, monitor: int, camera: int) -> int:
    """``route`` with ``monitor``'s source changed to ``camera`` (0 = blank).

    :raises ValueError: for a monitor not in 1..2 or a camera not in 0..3
    """
    if monitor not in MONITORS:
        raise ValueError(f"monitor {monitor} is not one of {', '.join(map(str, MONITORS))}")
    cams = list(decode_matrix_route(route))
    cams[monitor - 1] = camera
    return encode_matrix_route(cams[0], cams[1])


def route_text(route: int) -> str:
    """The route in words: ``"monitor 1: camera 2, monitor 2: blank"`` (and any set bit
    outside the table)."""
    m1, m2 = decode_matrix_route(route)
    text = f"monitor 1: {camera_name(m1)}, monitor 2: {camera_name(m2)}"
    extra = route & ~0x0F
    return text + (f" (bits 0x{extra:02X} outside the route table)" if extra else "")


# -- the console's request (Request.ROUTE, ui.request_arg): one monitor's source ------------
def route_request_arg(monitor: int, camera: int) -> int:
    """``ui.request_arg`` of a CAMERA ROUTE request: ``monitor * 16 + camera``."""
    parse_route_request(monitor * 16 + camera)
    return monitor * 16 + camera


def parse_route_request(arg: int) -> tuple[int, int]:
    """(monitor, camera) of a CAMERA ROUTE request's argument.

    :raises ValueError: an argument that names no monitor or camera (said in words)
    """
    monitor, camera = divmod(int(arg), 16)
    if monitor not in MONITORS or camera not in (BLANK, *CAMERAS):
        raise ValueError(f"camera route argument {arg} is not monitor*16 + camera "
                         f"(monitor 1..{MONITORS[-1]}, camera 0 = blank or 1..{CAMERAS[-1]})")
    return monitor, camera
