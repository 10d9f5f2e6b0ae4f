"""VMIC VMIVME-4100 16-channel 12-bit analog output board: the register table.

Sources (hardware-registers.md section 2 and R2):
 - epics-base/epics-base: src/drv/drvVmi4100.c, src/dev/devAoVmiVme4100.c,
   src/drv/module_types.c: 16 channels, 12-bit (slope /4095), channel n is the D16 word
   at offset 2n, the control word shares the space (``union {csr; data[16]}``), init
   writes 0xC100 "Fail LED off, enable P3 output", the board cannot be read back.
 - VMIVME-4105 datasheet text (sibling): D15 = 1 selects the control register, D15 = 0
   the DAC at the address; DAC data in D11..D0; control uses D14..D8; a read of any
   board address returns status.
 - VMIVME-4116 header (sibling): 0x4000 LED_OFF, 0x0100 AO_P3; outputs disconnected
   from the field and at 0 V after power-up.
Everything else (decode width, status content, reset values, range jumpers) is R2,
assumed, and listed in ``assumptions`` below.
"""

from __future__ import annotations

from drivers.registers import BoardDescription, Field, Register

N_CHANNELS = 16
SELECT_CTRL = 0x8000  #: D15 = 1: the word is a control word (4105 text; EPICS 0xC100)
LED_OFF = 0x4000  #: control b14: Fail LED off (inferred: EPICS comment, 4116 LED_OFF)
P3_ENABLE = 0x0100  #: control b8: outputs connected to P3 (inferred: EPICS, 4116 AO_P3)
ENABLE_WORD = SELECT_CTRL | LED_OFF | P3_ENABLE  #: 0xC100, written once at init by EPICS
DISABLE_WORD = SELECT_CTRL | LED_OFF  #: 0xC000: LED off, P3 disconnected (assumed safe state)
CTRL_MASK = 0x7F00  #: control register bits D14..D8 (4105 text)
DATA_MASK = 0x0FFF  #: DAC data D11..D0 (4105 text)

DAC = Register(
    name="DAC", offset=0x00, width=16, access="w", count=N_CHANNELS, reset=0x800,
    fields=(Field("code", lsb=0, bits=12, doc="12-bit DAC code, offset binary for bipolar ranges"),
            Field("select_ctrl", lsb=15, doc="must be 0 for a DAC write")),
    doc="channel n at offset 2n, written with D15 = 0; never readable",
    source="sourced: epics-base drvVmi4100.c (data[16] words), 4105 datasheet text (D15/D11..D0); "
           "reset value 0x800 assumed (R2)")

CTRL = Register(
    name="CTRL", offset=0x00, width=16, access="rw", reset=0x0000,
    fields=(Field("p3_enable", lsb=8, doc="1 = outputs connected to the P3 field connector"),
            Field("led_off", lsb=14, doc="1 = Fail LED off"),
            Field("select_ctrl", lsb=15, doc="1 = this word is a control word (not stored)")),
    doc="written with D15 = 1 at ANY offset 0x00-0x1E (stores D14..D8); a read of any offset "
        "returns it in bits 14..8, 0 elsewhere",
    source="sourced: epics-base drvVmi4100.c (union csr/data, 0xC100); bit meanings inferred from "
           "the 4116 header; read-back content assumed (R2)")

VMIVME4100 = BoardDescription(
    kind="vmivme4100",
    title="VMIC VMIVME-4100 16-channel 12-bit analog output",
    window=0x20,
    # DAC first: register_name() names offset 2n "DAC[n]"; CTRL overlays the same words.
    registers=(DAC, CTRL),
    byte_lanes="word",
    constants={
        "n_channels": N_CHANNELS,  # sourced: EPICS ao_num_channels[VMI4100] = 16
        "dac_bits": 12,  # sourced: EPICS slope (EGUF - EGUL)/4095
        "full_scale_counts": 4096,
        "range_volts": 10.0,  # inferred/assumed: +-10 V bipolar jumper setting (R2)
        "coding": "offset_binary",  # V = -range + 2*range*code/4096 (R2)
        "zero_code": 0x800,  # 0 V in +-10 V offset binary
        "lsb_volts": 20.0 / 4096,  # 4.883 mV
        "enable_word": ENABLE_WORD,
        "disable_word": DISABLE_WORD,
    },
    assumptions=(
        "Decoded window is 32 bytes (0x00-0x1F, A05-A15 decode, inferred from siblings); "
        "odd-address and 8-bit accesses get no answer (bus error).",
        "A write with D15 = 0 loads DAC[offset/2] from D11..D0 (D14..D12 ignored) and the output "
        "updates at once (no delayed-update mode).",
        "A read of any offset returns the control register in bits 14..8 and 0 elsewhere.",
        "Reset: every DAC register 0x800 and control 0x00 (LED on, P3 disconnected); "
        "the field output is 0 V whenever control b8 = 0.",
        "Output range is +-10 V offset binary (jumper on the board, not readable).",
        "Control bits 13..9 (test bus / delayed update on the 4116) are written 0.",
        "disable_outputs() writes 0xC000 (LED off, P3 disconnected) as the safe state.",
    ),
)
