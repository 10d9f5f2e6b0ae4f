"""VMIC VMIVME-4940-04-06 resolver-to-digital board: the register table.

Sources: the IRSS report (section 3.4.2: "four 14 bit resolver to digital converters
each", bases 0x0100 and 0x0200). No public register map exists (hardware-registers.md
section 1), so the whole map below is the shared model R1 of
`the hardware-registers reference notes`: ASSUMED, and kept here so the lab can
correct it against the VMIVME-4940 Instruction Manual in one edit. The driver
(``drivers.rtd.vmivme4940``) and the fake (``fakes.rtd``) both read this table.

Justification of the angle word lives in one place: the ``angle`` field of the
``ANGLE`` template below (lsb 0, 14 bits = right-justified). A 16-bit binary-angle
board would be ``Field("angle", lsb=2, bits=14)`` (14 significant bits, left-justified)
or ``bits=16``; driver and fake follow the field.
"""

from __future__ import annotations

import math

from drivers.registers import BoardDescription, Field, Register

_R1 = "assumed: hardware-registers.md R1 (no public VMIVME-4940 register map)"

#: The angle inside a channel word. Right-justified natural binary, 0 = 0 rad (R1, assumed).
ANGLE = Field("angle", lsb=0, bits=14,
              doc="natural-binary angle, 0 = 0 deg, LSB = 360/2**bits deg; bits 15..14 read 0")

N_CHANNELS = 4


def _channel(n: int) -> Register:
    return Register(
        name=f"CH{n}", offset=2 * n, width=16, access="r", fields=(ANGLE,),
        doc=f"channel {n} angle; reads are latched (a word is never read mid-update); writes ignored",
        source=_R1)


STATUS = Register(
    name="STATUS", offset=0x08, width=16, access="r",
    fields=tuple(Field(f"fault{n}", lsb=n, doc=f"channel {n} loss of signal or BIT fail")
                 for n in range(N_CHANNELS))
    + (Field("reference_present", lsb=4, doc="400 Hz reference present"),),
    doc="per-channel fault bits b3..b0, reference present b4, other bits 0", source=_R1)

CONTROL = Register(
    name="CONTROL", offset=0x0A, width=16, access="rw", reset=0x0000,
    fields=tuple(Field(f"hold{n}", lsb=n, doc=f"freeze channel {n}'s reading while set")
                 for n in range(N_CHANNELS))
    + (Field("led_off", lsb=14, doc="1 = Fail LED off"),),
    doc="hold bits b3..b0 and Fail LED off b14; reset value 0x0000", source=_R1)

VMIVME4940 = BoardDescription(
    kind="vmivme4940",
    title="VMIC VMIVME-4940-04-06 4-channel 14-bit resolver-to-digital converter",
    window=0x20,
    registers=tuple(_channel(n) for n in range(N_CHANNELS)) + (STATUS, CONTROL),
    byte_lanes="word",
    constants={
        "n_channels": N_CHANNELS,  # IRSS report 3.4.2: four converters per board (sourced)
        "angle_bits": ANGLE.bits,  # IRSS report 3.4.2: 14-bit converters (sourced)
        "counts_per_rev": 1 << ANGLE.bits,
        "lsb_rad": 2.0 * math.pi / (1 << ANGLE.bits),  # 0.0219727 deg = 383.5 urad
        "reference_hz": 400.0,  # "-04-06" board, 400 Hz reference (hardware-registers.md s.1, inferred)
    },
    assumptions=(
        "Register map (CH0..CH3 at 0x00-0x06, STATUS 0x08, CONTROL 0x0A) is the shared model R1; "
        "no public VMIVME-4940 register map was found.",
        "Angle words are right-justified 14-bit natural binary (field ANGLE: lsb 0, 14 bits); "
        "a left-justified 16-bit binary-angle board needs only that field changed.",
        "Decoded window is 0x20 bytes; offsets 0x0C-0x1F are not decoded (bus error).",
        "Only D16 accesses are decoded; 8-bit accesses get no answer (bus error).",
        "Reads of a channel are latched (atomic); writes to CH0..CH3 and STATUS are ignored.",
        "Loss of the 400 Hz reference sets every channel's fault bit and freezes all readings.",
        "A channel with loss of signal freezes at its last reading (fake option: reads zero).",
        "The converter output is the instantaneous angle quantised by truncation (floor); "
        "no tracking lag is modelled (14-bit RDC tracking rate far exceeds PFMA joint rates).",
    ),
)
