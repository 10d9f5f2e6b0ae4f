"""fakes.metered.MeteredBus: passes accesses through unchanged and counts their time."""

import pytest

from fakes.metered import MeteredBus
from fakes.rack import FakeRack
from pfma.clock import SimClock
from pfma.errors import BusError


def test_metered_bus_forwards_and_accumulates():
    rack = FakeRack.from_config(clock=SimClock())
    bus = MeteredBus(rack)
    dac = rack["dac"]
    before = bus.read16(0xD000)
    assert before == rack.read16(0xD000)
    bus.write16(0xD000, 0x1234)
    assert rack.read16(0xD000) == bus.read16(0xD000)
    assert bus.accesses == 3 and bus.sim_s > 0
    assert bus["dac"] is dac and bus.describe() == rack.describe()
    with pytest.raises(BusError):
        bus.read16(0x9000)  # nothing decodes it: the error passes through, and is counted
    assert bus.accesses == 4
