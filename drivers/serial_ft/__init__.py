"""Lord/ATI force/torque sensor: serial protocol driver (any pyserial-like byte port)
and a CAN transport. Protocol table and codecs: :mod:`drivers.serial_ft.protocol`;
documentation: docs/ft-protocol.md.
"""

from .ftsensor import BytePort, FtReader, FtReading, FtSensor, LinkStats, open_ft
from .protocol import NOMINAL, NominalSensor

__all__ = ["BytePort", "FtReader", "FtReading", "FtSensor", "LinkStats", "open_ft", "NOMINAL",
           "NominalSensor", "CanFtSensor"]


def __getattr__(name: str):  # python-can is imported only when the CAN transport is used
    if name == "CanFtSensor":
        from .can_ft import CanFtSensor
        return CanFtSensor
    raise AttributeError(name)
