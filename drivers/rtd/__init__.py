"""VMIC VMIVME-4940 resolver-to-digital board: register table and driver."""

from drivers.rtd.registers import VMIVME4940
from drivers.rtd.vmivme4940 import RtdStatus, Vmivme4940

__all__ = ["Vmivme4940", "RtdStatus", "VMIVME4940"]
