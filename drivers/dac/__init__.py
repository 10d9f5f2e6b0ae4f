"""VMIC VMIVME-4100 analog output board: register table and driver."""

from drivers.dac.registers import VMIVME4100
from drivers.dac.vmivme4100 import Vmivme4100

__all__ = ["Vmivme4100", "VMIVME4100"]
