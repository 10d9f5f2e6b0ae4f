"""Datel DVME-611B A/D board: register table and driver."""

from drivers.adc.dvme611 import Dvme611
from drivers.adc.registers import DVME611

__all__ = ["Dvme611", "DVME611"]
