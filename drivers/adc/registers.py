"""Datel DVME-611B 32-channel 12-bit A/D board: the register table.

Sources: the IRSS report section 3.4.2 (32 single-ended multiplexed channels, 12-bit
successive approximation, 4 us per conversion, A16 0xC000-0xC0FF, i.e. a 256-byte
window). No public register map exists (hardware-registers.md section 3): every offset
and bit below is the shared model R3 of `the hardware-registers reference notes`,
ASSUMED, and kept here so the lab can correct it against Datel document
VME-DVME-611/612 in one edit. Driver (``drivers.adc.dvme611``) and fake
(``fakes.adc``) both read this table.
"""

from __future__ import annotations

from drivers.registers import BoardDescription, Field, Register

_R3 = "assumed: hardware-registers.md R3 (no public DVME-611 register map)"
N_CHANNELS = 32

CH_FIELD = Field("channel", lsb=0, bits=5, doc="channel select 0..31")
AUTOINC = Field("autoinc", lsb=5, doc="auto-increment: channel advances mod 32 after each DATA read")
GAIN = Field("gain", lsb=6, bits=2, doc="gain code 00 x1, 01 x2, 10 x4, 11 x8; reads 00 with no PGA")
BUSY = Field("busy", lsb=8, doc="(read-only) conversion in progress")
IE = Field("irq_enable", lsb=14, doc="interrupt enable (the fake never interrupts)")
EOC = Field("eoc", lsb=15, doc="(read-only) end of conversion; cleared by START or a DATA read")

CSR = Register(name="CSR", offset=0x00, width=16, access="rw", reset=0x0000,
               fields=(CH_FIELD, AUTOINC, GAIN, BUSY, IE, EOC),
               doc="control/status", source=_R3)
SCAN_CMD = Field("scan", lsb=0, doc="1 = scan: convert channels 0..31 in turn into SCAN (32 x 4 us); "
                 "0 = one conversion on the CSR channel")
START = Register(name="START", offset=0x02, width=16, access="w", fields=(SCAN_CMD,),
                 doc="a write starts a conversion: with b0 = 0 on the CSR channel (busy for 4 us, "
                     "then EOC); with b0 = 1 (SCAN) a scan of all 32 channels (busy for 32 x 4 us, "
                     "EOC at the end)",
                 source=_R3)
DATA = Register(name="DATA", offset=0x04, width=16, access="r",
                fields=(Field("code", lsb=0, bits=12, doc="offset binary for bipolar ranges"),),
                doc="12-bit result right-justified, b15..12 = 0; reading clears EOC and applies "
                    "auto-increment; while busy returns the previous result", source=_R3)
BOARD_ID = Register(name="BOARD_ID", offset=0x06, width=16, access="r", reset=0x0611,
                    doc="constant 0x0611: a fake aid only, the driver must not rely on it", source=_R3)
SCAN = Register(name="SCAN", offset=0x40, width=16, access="r", count=N_CHANNELS,
                doc="last result per channel (written by every conversion, single or scan); "
                    "reads have no side effects, so one block read returns a whole scan",
                source=_R3)

DVME611 = BoardDescription(
    kind="dvme611",
    title="Datel DVME-611B 32-channel 12-bit A/D",
    window=0x100,  # IRSS report 3.4.2: 0xC000-0xC0FF (sourced)
    registers=(CSR, START, DATA, BOARD_ID, SCAN),
    byte_lanes="word",
    constants={
        "n_channels": N_CHANNELS,  # IRSS report 3.4.2 (sourced)
        "adc_bits": 12,  # IRSS report 3.4.2 (sourced)
        "full_scale_counts": 4096,
        "conversion_time_s": 4e-6,  # IRSS report 3.4.2: "four microseconds" (sourced)
        "range_volts": 10.0,  # assumed: +-10 V bipolar (R3; pfma-model.md 8.4)
        "coding": "offset_binary",  # assumed (R3): V = -range + 2*range*code/4096
        "lsb_volts": 20.0 / 4096,  # 4.883 mV at +-10 V
        "board_id": 0x0611,  # assumed (R3), fake aid only
        # assumed (R3): the board has the scan mode (START b0); the driver scans with one
        # START, EOC polls and one block read of SCAN. False: the per-channel
        # auto-increment sequence (START, EOC, DATA per channel), for a board without it.
        "scan_mode": True,
    },
    assumptions=(
        "Register map (CSR 0x00, START 0x02, DATA 0x04, BOARD_ID 0x06, SCAN 0x40-0x7E) is the "
        "shared model R3; no public DVME-611 register map was found.",
        "Results are 12-bit right-justified, offset binary for +-10 V (0x000 = -10 V, 0x800 = 0 V).",
        "No PGA fitted: CSR gain bits read back 00; the driver writes gain 00 (x1).",
        "Inputs are clipped to the range and quantised by truncation (floor).",
        "Reading DATA while busy returns the previous result and neither clears EOC nor "
        "advances the auto-increment channel.",
        "The input is sampled when START is written; the result appears 4 us later.",
        "Scan mode: a START write with b0 = 1 converts channels 0..31 in turn, 4 us each: "
        "channel k is sampled 4k us after the START and its result is in SCAN[k] 4 us later; "
        "BUSY for the whole 32 x 4 us = 128 us, EOC at the end; DATA then holds channel 31's "
        "result; the CSR channel and auto-increment bits are left alone. START with b0 = 0 is "
        "the single conversion as before (the register table's constant scan_mode says "
        "whether the driver uses it).",
        "Only D16 accesses are decoded; 8-bit accesses get no answer (bus error). Offsets in "
        "the window that hold no register are not decoded (bus error); a read of START "
        "returns 0 and writes to read-only registers are ignored.",
    ),
)
