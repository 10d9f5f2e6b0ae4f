"""Motorola MVME400 dual RS-232C serial module: one uPD7201 MPSC + one MC6821 (baud select).

Shared by ``drivers.mvme400`` and ``fakes.mvme400``. Facts copied from
the hardware-registers reference notes section 4 and R4, whose sources are:

- ``bios.c``: CP/M-68K BIOS for the Motorola VME/10, "Driver for MVME400 Dual RS-232C
  Serial Port Module" (Motorola/DRI, c. 1984; repository not resolved): register layout,
  reference init values, baud code table, polled I/O.
- ``VM400.C`` v1.02 (Motorola 1984/85, DRI; repository not resolved): PIA bit use,
  "WR2 of both channels first, then WR4" init order, 8086 vector decode.
- ``siophysa.s`` (VME/10 GEM-DOS BIOS, 1985): offsets, 8085 vector decode.
- ``mamedev/mame: src/devices/machine/z80sio.cpp`` (``upd7201_new_device``): 7201 model.
"""

from __future__ import annotations

from drivers.pio.registers import pia_registers
from drivers.registers import BoardDescription, Field, Register

# -- uPD7201 write-register bits (sourced: bios.c, VM400.C constants, MAME) ---------------
WR0_PTR_MASK = 0x07  #: b2..0 register pointer (next control access; then back to 0)
WR0_CMD_MASK = 0x38  #: b5..3 command
CMD_NULL = 0x00
CMD_SEND_ABORT = 0x08  #: SDLC only
CMD_RESET_EXT_STATUS = 0x10  #: reset external/status interrupt
CMD_CHANNEL_RESET = 0x18
CMD_ENABLE_INT_NEXT_RX = 0x20
CMD_RESET_TX_INT = 0x28  #: reset Tx interrupt pending
CMD_ERROR_RESET = 0x30  #: clears latched parity/overrun (RR1 b4/b5)
CMD_END_OF_INTERRUPT = 0x38  #: channel A only

WR1_EXT_INT_EN = 0x01
WR1_TX_INT_EN = 0x02
WR1_STATUS_AFFECTS_VECTOR = 0x04  #: channel B's WR1 only
WR1_RX_INT_MASK = 0x18  #: 00 off, 01 first char, 10 all chars + parity special, 11 all chars

WR2A_BUS_MODE_MASK = 0x18  #: 00/01 8085 modes, 10 8086 mode
WR2A_8086 = 0x10

WR3_RX_ENABLE = 0x01
WR3_AUTO_ENABLES = 0x20  #: Rx gated by DCD, Tx by CTS
WR3_RX_BITS_MASK = 0xC0
WR3_RX_8BITS = 0xC0  #: 00 = 5, 01 = 7, 10 = 6, 11 = 8

WR4_PARITY_EN = 0x01
WR4_PARITY_EVEN = 0x02
WR4_STOP_MASK = 0x0C  #: 01 = 1, 10 = 1.5, 11 = 2, 00 = sync modes
WR4_STOP_1 = 0x04
WR4_CLOCK_MASK = 0xC0
WR4_X16 = 0x40  #: 00 x1, 01 x16, 10 x32, 11 x64
CLOCK_MULTIPLIERS = {0x00: 1, 0x40: 16, 0x80: 32, 0xC0: 64}

WR5_RTS = 0x02
WR5_TX_ENABLE = 0x08
WR5_SEND_BREAK = 0x10
WR5_TX_BITS_MASK = 0x60
WR5_TX_8BITS = 0x60  #: 00 = 5, 01 = 7, 10 = 6, 11 = 8
WR5_DTR = 0x80

# -- read registers -----------------------------------------------------------------------
RR0_RX_AVAILABLE = 0x01
RR0_INT_PENDING = 0x02  #: valid in channel A only
RR0_TX_EMPTY = 0x04
RR0_DCD = 0x08
RR0_SYNC_HUNT = 0x10
RR0_CTS = 0x20
RR0_TX_UNDERRUN = 0x40
RR0_BREAK = 0x80

RR1_ALL_SENT = 0x01
RR1_PARITY_ERROR = 0x10
RR1_RX_OVERRUN = 0x20
RR1_FRAMING_ERROR = 0x40  #: CRC/framing
RR1_END_OF_FRAME = 0x80
RR1_ERRORS = RR1_PARITY_ERROR | RR1_RX_OVERRUN | RR1_FRAMING_ERROR

RX_FIFO_DEPTH = 3  #: receive FIFO characters (sourced); Tx has a 1-character buffer

#: status-affects-vector codes (sourced: MAME i8274 read_vector, both VME/10 ISRs)
VECTOR_CODES = {
    "b_tx_empty": 0, "b_ext_status": 1, "b_rx_char": 2, "b_special_rx": 3,
    "a_tx_empty": 4, "a_ext_status": 5, "a_rx_char": 6, "a_special_rx": 7,
}
VECTOR_NONE = 7  #: code with no interrupt pending

# -- reference init (sourced: bios.c values) ----------------------------------------------
INIT_CHANNEL_RESET = 0x18  #: written twice to each channel's WR0 ("DO NOT OPTIMIZE")
INIT_WR2A = 0x14  #: both channels interrupt, priority bit, 8086 mode, non-vectored
INIT_WR2B = 0x00  #: vector
INIT_WR4 = 0x44  #: x16 clock, 1 stop bit, no parity
INIT_WR3 = 0xE1  #: 8-bit Rx, auto enables, Rx on
INIT_WR5 = 0xEA  #: DTR, 8-bit Tx, Tx on, RTS
INIT_WR1_SELECT = 0x29  #: WR0: select WR1 + reset Tx int pending
INIT_WR1A = 0x00
INIT_WR1B = 0x04  #: status affects vector

# -- PIA use on the MVME400 (sourced: VM400.C, bios.c) -------------------------------------
PIA_DDRA = 0x18  #: PA3, PA4 outputs
PIA_DDRB = 0xFF  #: port B all outputs: baud codes
PIA_CR_DDR = 0x00  #: CRx value selecting the DDR (no PIA interrupts)
PIA_CR_DATA = 0x04  #: CRx value selecting the data register
PA_JUMPERS = 0x07  #: b2..0 baud jumper code for the port chosen by b3 (meaning unknown)
PA_JUMPER_BANK = 0x08  #: out: 0 = port 1 jumpers, 1 = port 2 jumpers
PA_FAIL_LED = 0x10  #: out: 1 = FAIL LED on
PA_FAIL_LED_STATUS = 0x20  #: in: 1 = FAIL LED on
PA_DSR = (0x40, 0x80)  #: in: DSR of port 1 (channel A), port 2 (channel B)
PA_AFTER_INIT = 0x00  #: drivers write 0 after init: FAIL LED off

#: 4-bit baud code -> bit rate (sourced: bios.c table; 2000, 3600, 7200 inferred from the
#: COM5016/COM8116 family table at 5.0688 MHz). PB7..4 = channel A, PB3..0 = channel B.
BAUD_CODES: dict[int, float] = {
    0x0: 50, 0x1: 75, 0x2: 110, 0x3: 134.5, 0x4: 150, 0x5: 300, 0x6: 600, 0x7: 1200,
    0x8: 1800, 0x9: 2000, 0xA: 2400, 0xB: 3600, 0xC: 4800, 0xD: 7200, 0xE: 9600, 0xF: 19200,
}
BAUD_TO_CODE: dict[float, int] = {rate: code for code, rate in BAUD_CODES.items()}
BAUD_SHIFT = (4, 0)  #: port B nibble position of channel A, channel B

BITS_PER_CHAR = 10  #: 8N1: start + 8 data + stop


def char_time_s(baud: float) -> float:
    """Seconds per 8N1 character at ``baud`` (521 us at 19200)."""
    return BITS_PER_CHAR / baud


def max_poll_interval_s(baud: float) -> float:
    """Longest gap between Rx polls that cannot overrun the 3-deep FIFO: 3 characters.

    At 19200 baud this is 1.5625 ms, i.e. **less than one 3.125 ms frame** (6 characters
    arrive per frame at full line rate).
    """
    return RX_FIFO_DEPTH * char_time_s(baud)


_sio_src = "sourced: bios.c / siophysa.s offsets"
MVME400 = BoardDescription(
    kind="mvme400",
    title="Motorola MVME400 dual RS-232C serial (uPD7201 MPSC + MC6821 baud select)",
    window=0x20,
    registers=pia_registers("PIA_", 0x01, "sourced: bios.c / VM400.C (+0x01/03/05/07)") + (
        Register("SIO_DATA_A", 0x09, 8, "rw", doc="channel A data: read = Rx FIFO, write = Tx buffer",
                 source=_sio_src),
        Register("SIO_DATA_B", 0x0B, 8, "rw", doc="channel B data", source=_sio_src),
        Register("SIO_CTRL_A", 0x0D, 8, "rw",
                 fields=(Field("pointer", 0, 3), Field("command", 3, 3), Field("crc_reset", 6, 2)),
                 doc="channel A control: write WR0 (pointer/command) or WRn, read RR0 or RRn",
                 source=_sio_src),
        Register("SIO_CTRL_B", 0x0F, 8, "rw",
                 fields=(Field("pointer", 0, 3), Field("command", 3, 3), Field("crc_reset", 6, 2)),
                 doc="channel B control", source=_sio_src),
    ),
    byte_lanes="odd",
    constants={
        "baud_codes": BAUD_CODES,
        "rx_fifo_depth": RX_FIFO_DEPTH,
        "bits_per_char": BITS_PER_CHAR,
        "channels": ("A", "B"),  #: rack channel 0 = 7201 channel A ("port 1"), 1 = B ("port 2")
    },
    assumptions=(
        "window 0x20: decodes 32 bytes (boards at 0x20 steps on the VME/10), uses 16; "
        "+0x10..+0x1F give a bus error (assumed)",
        "even-byte accesses give a bus error (sourced for the VM02 sibling only, §0)",
        "baud codes 9 = 2000, 0xB = 3600, 0xD = 7200 are inferred from the COM5016 family table",
        "PA jumper bits read 7 for both ports (meaning unknown; nothing depends on it) (R4)",
        "DSR (PA6/PA7) asserted = 1; the DSR-to-CA/CB wiring is unknown and not modelled (R4)",
        "the baud generator sees no valid rate unless the PIA drives its port B nibble (DDRB bits = 1)",
        "a character that finds the 3-deep Rx FIFO full is lost; RR1 b5 latches until error reset",
        "RR1 b4 (parity) latches until error reset; RR1 b6 (framing) belongs to the FIFO's top character",
        "channel reset clears WR1/WR3/WR4/WR5, the FIFO, the Tx buffer and the error latches; "
        "WR2A/WR2B keep their value (inferred from the Z80 SIO family)",
        "RR2 of channel A and RR3..RR7 read 0x00",
        "CTS/DCD inputs asserted by default so the bios.c auto enables work (R4)",
        "far-end devices talk 8N1; a different programmed format is received with a framing error",
        "a character takes 10/baud s of model time (8N1) whatever the stop-bit setting",
    ),
)
