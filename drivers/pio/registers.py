"""MC6821 PIA register pieces and the MVME410 dual-PIA parallel I/O board table.

Shared by the drivers (``drivers.pio.pia6821``, ``drivers.pio.mvme410``,
``drivers.mvme400``) and the fakes (``fakes.pia``, ``fakes.mvme410``).

Sources (copied from the hardware-registers reference notes, sections 0, 5, R5):

- MC6821 programming model: ``mamedev/mame: src/devices/machine/6821pia.cpp``.
- MVME410 PIA1 layout (+0x01 PRA/DDRA, +0x03 CRA, +0x05 PRB/DDRB, +0x07 CRB) and the
  printer handshake (CRA 0x38 / DDRA / 0x3C, strobe CRA 0x34 then 0x3C, ACK on CA1
  falling edge sets CRA b7, cleared by a dummy read of PRA): the VME/10 CP/M-68K
  ``bios.c`` "m410 driver for the VME/10" (repository not resolved).
- Odd-byte lanes (8-bit chips on D7..D0): same ``bios.c``; even-byte bus error is
  SOURCED for the sibling VM02 only, INFERRED here.
"""

from __future__ import annotations

from typing import TypedDict

from drivers.registers import BoardDescription, Field, Register

# -- MC6821 control register (CRA / CRB) bits: sourced, MAME 6821pia.cpp ------------------
CR_IRQ1 = 0x80  #: b7 (read-only) IRQx1 flag: active C1 edge seen; cleared by reading the port
CR_IRQ2 = 0x40  #: b6 (read-only) IRQx2 flag: active C2 edge seen (C2 input only)
CR_C2_OUTPUT = 0x20  #: b5 C2 is an output
CR_C2_B4 = 0x10  #: b4 input: 1 = rising edge active; output: 1 = set/reset mode, 0 = strobe mode
CR_C2_B3 = 0x08  #: b3 input: C2 IRQ enable; set/reset: C2 level; strobe: 1 = restore after one E cycle
CR_DATA = 0x04  #: b2 1 = peripheral data register at RS0/RS2, 0 = data direction register
CR_C1_RISING = 0x02  #: b1 C1 active edge: 1 = low-to-high, 0 = high-to-low
CR_C1_IRQ_EN = 0x01  #: b0 C1 interrupt enable (IRQx output)
CR_WRITABLE = 0x3F  #: writes to b7..b6 are ignored

# C2 control field values (CR b5..b3), as a 3-bit code shifted to bits 5..3.
C2_IN_FALLING = 0x00  #: C2 input, IRQx2 on falling edge, no interrupt
C2_IN_FALLING_IRQ = 0x08  #: C2 input, falling edge, interrupt enabled
C2_IN_RISING = 0x10  #: C2 input, IRQx2 on rising edge, no interrupt
C2_IN_RISING_IRQ = 0x18  #: C2 input, rising edge, interrupt enabled
C2_STROBE_C1 = 0x20  #: output strobe: low on PRA read (A) / PRB write (B), high on next active C1 edge
C2_STROBE_E = 0x28  #: output strobe: low on PRA read / PRB write, high after one E cycle
C2_LOW = 0x30  #: output, set/reset mode, C2 = 0
C2_HIGH = 0x38  #: output, set/reset mode, C2 = 1
C2_MASK = 0x38

#: register select RS1:RS0 -> (name with CRx b2 = 0, name with CRx b2 = 1)
RS_NAMES = {0: ("DDRA", "PRA"), 1: ("CRA", "CRA"), 2: ("DDRB", "PRB"), 3: ("CRB", "CRB")}

CR_FIELDS = (
    Field("irq1", 7, doc="IRQx1 flag (read-only): active C1 edge; cleared by reading the port data register"),
    Field("irq2", 6, doc="IRQx2 flag (read-only): active C2 edge while C2 is an input; cleared by port read"),
    Field("c2_control", 3, 3, doc="C2 mode: 0xx input (b4 edge, b3 IRQ enable), 10x strobe, 11x set/reset (b3 = level)"),
    Field("data_select", 2, doc="1 = peripheral data register, 0 = data direction register"),
    Field("c1_rising", 1, doc="C1 active edge: 1 = low-to-high, 0 = high-to-low"),
    Field("c1_irq_enable", 0, doc="C1 interrupt enable"),
)


def pia_registers(prefix: str, first_offset: int, source: str) -> tuple[Register, ...]:
    """The four registers of one MC6821 on odd bytes ``first_offset`` + 0, 2, 4, 6.

    :param prefix: register name prefix, e.g. ``"PIA1_"``
    :param first_offset: byte offset of RS = 0 (PRA/DDRA) from the board base
    :param source: provenance of the *placement* (the 6821 bit semantics are sourced)
    """
    return (
        Register(f"{prefix}PRA", first_offset, 8, "rw", 0x00,
                 doc="port A data (CRA b2 = 1) or DDRA (CRA b2 = 0); reading PRA clears CRA b7/b6",
                 source=source),
        Register(f"{prefix}CRA", first_offset + 2, 8, "rw", 0x00, CR_FIELDS,
                 doc="control register A (b7/b6 read-only flags)", source=source),
        Register(f"{prefix}PRB", first_offset + 4, 8, "rw", 0x00,
                 doc="port B data (CRB b2 = 1) or DDRB (CRB b2 = 0); reading PRB clears CRB b7/b6",
                 source=source),
        Register(f"{prefix}CRB", first_offset + 6, 8, "rw", 0x00, CR_FIELDS,
                 doc="control register B (b7/b6 read-only flags)", source=source),
    )


# -- MVME410 -------------------------------------------------------------------------------
PIA1_OFFSET = 0x01  #: sourced (bios.c m410 driver)
PIA2_OFFSET = 0x09  #: assumed (R5: by analogy with the MVME400's 16-byte odd-byte map)

#: Port number (rack channel) -> (PIA index 0/1, side "a"/"b"). Port order assumed (rack TOML).
PORTS = {0: (0, "a"), 1: (0, "b"), 2: (1, "a"), 3: (1, "b")}

# -- Matrix switcher on pio_video port 0: ONE table, ASSUMED (wiring drawings 849IRS20800
# are not public; the seed names only "an output interface for the Matrix Switcher").
# 3 cameras -> 2 monitors; a 2-bit source code per monitor.
class MatrixSwitcherTable(TypedDict):
    """The keys of ``MATRIX_SWITCHER`` and their types (a plain dict at run time)."""

    port: int
    monitor_fields: dict[int, Field]
    source_codes: dict[int, str]
    unused_bits: int
    strobe: str
    latch_edge: str
    ack: str
    ack_delay_s: float
    ack_polls: int


MATRIX_SWITCHER: MatrixSwitcherTable = {
    "port": 0,  #: MVME410 port carrying the route byte (PIA1 port A, all outputs)
    "monitor_fields": {1: Field("monitor_1_source", 0, 2), 2: Field("monitor_2_source", 2, 2)},
    "source_codes": {0: "no source (blank)", 1: "camera 1", 2: "camera 2", 3: "camera 3"},
    "unused_bits": 0xF0,  #: bits 7..4 written 0
    "strobe": "CA2 pulsed low then high in set/reset mode (CRA 0x34 then 0x3C), as bios.c strobes the printer",
    "latch_edge": "route latched by the switcher on the strobe's rising edge",
    "ack": "switcher pulses CA1 low then high; the falling edge sets CRA b7 (CRA b1 = 0)",
    "ack_delay_s": 20e-6,  #: fake switcher's acknowledge delay after the strobe
    "ack_polls": 1000,  #: driver's bounded poll count for the acknowledge
}


def encode_matrix_route(monitor_1_camera: int, monitor_2_camera: int) -> int:
    """Route byte for the matrix switcher (ASSUMED table ``MATRIX_SWITCHER``).

    :param monitor_1_camera: 0 = blank, 1..3 = camera
    :param monitor_2_camera: 0 = blank, 1..3 = camera
    :raises ValueError: for a camera number outside 0..3
    """
    fields = MATRIX_SWITCHER["monitor_fields"]
    value = 0
    for monitor, cam in ((1, monitor_1_camera), (2, monitor_2_camera)):
        if cam not in MATRIX_SWITCHER["source_codes"]:
            raise ValueError(f"matrix switcher monitor {monitor}: camera {cam} not in 0..3")
        value = fields[monitor].put(value, cam)
    return value


def decode_matrix_route(value: int) -> tuple[int, int]:
    """(monitor 1 camera, monitor 2 camera) from a route byte (0 = blank)."""
    fields = MATRIX_SWITCHER["monitor_fields"]
    return fields[1].get(value), fields[2].get(value)


#: The amplifier-enable charge-pump relay (issue 28 item 5; rack file ``[amplifier_enable]``):
#: ASSUMED (no drawing of such a relay exists for this rack; modelled on the charge-pump
#: watchdog boards LinuxCNC's ``charge-pump`` output drives). The relay holds the servo
#: amplifiers' enable while the output bit keeps changing level: it pulls in once two edges
#: come less than ``drop_s`` apart and drops ``drop_s`` after the last edge (a retriggerable
#: monostable), so a bit held at either level, whatever its level, drops it. The service
#: toggles the bit every frame (an edge every 3.125 ms at 320 Hz). Amplifiers without enable
#: give no current, and the brake-release card is fed through the same contact (fail-safe
#: brakes: unpowered = set).
CHARGE_PUMP = {
    "drop_s": 0.020,  #: no edge for this long: the relay drops (assumed 20 ms, > 6 frames at 320 Hz)
}


MVME410 = BoardDescription(
    kind="mvme410",
    title="Motorola MVME410 dual 16-bit parallel I/O (2 x MC6821 PIA)",
    window=0x20,
    registers=(
        pia_registers("PIA1_", PIA1_OFFSET, "sourced: VME/10 bios.c m410 driver (+0x01/03/05/07)")
        + pia_registers("PIA2_", PIA2_OFFSET,
                        "assumed: second PIA at +0x09/0B/0D/0F by analogy with the MVME400 map (R5)")
    ),
    byte_lanes="odd",
    constants={
        "ports": PORTS,
        "pia_offsets": (PIA1_OFFSET, PIA2_OFFSET),
        "matrix_switcher": MATRIX_SWITCHER,
    },
    assumptions=(
        "window 0x20 bytes: the rack's MVME410 bases are 0x20 apart (seed); only +0x01..+0x0F answer, "
        "+0x10..+0x1F give a bus error (assumed)",
        "each base is ONE board carrying two PIAs (R5); PIA2 at +0x09/0B/0D/0F (R5)",
        "even-byte accesses give a bus error (sourced for the VM02 sibling only, §0)",
        "ports 0..3 = PIA1 A, PIA1 B, PIA2 A, PIA2 B (rack_default.toml channel order)",
        "CA/CB lines are neither buffered-inverted nor jumpered differently on the connector",
        "undriven port B input pins read 1 (board pull-ups), like port A's internal pull-ups",
        "matrix switcher route byte: bits 1..0 = monitor 1 source, bits 3..2 = monitor 2 source "
        "(0 blank, 1..3 camera), bits 7..4 = 0; strobe on CA2, acknowledge on CA1 (MATRIX_SWITCHER)",
        "user I/F box: 16 inputs on ports 0 (bits 0-7) and 1 (bits 8-15) of pio_user",
    ),
)
