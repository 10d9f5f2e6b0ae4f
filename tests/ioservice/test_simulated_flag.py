"""The service says whether its rack is simulated (issue 18: "rack: unknown" over a live
buffer): ``OWNER_FLAG_SIMULATED`` in its owner slots, decided from its register bus by
``ioservice.service.bus_is_simulated`` (the assumption is written there)."""

from __future__ import annotations

from drivers.bus import open_bus
from ioservice.service import bus_is_simulated
from sim.rig import SimRig


def test_the_simulated_rack_is_published_as_simulated():
    rig = SimRig(prefix="pfma-test-")
    try:
        rig.run(0.01)
        assert rig.svc.simulated
        assert rig.reader.header().rack_kind == "simulated"
        assert rig.reader.owners()["inputs"].simulated
    finally:
        rig.close()


def test_a_service_told_its_rack_is_real_clears_the_flag():
    rig = SimRig(prefix="pfma-test-", service_kw={"simulated": False})
    try:
        assert rig.reader.header().rack_kind == "real"
    finally:
        rig.close()


class _HardwareBus:  # a bus from no fakes module: a device file, a bridge ...
    def read16(self, addr: int) -> int:
        return 0


class _SaysSimulated(_HardwareBus):
    simulated = True


def test_which_buses_are_simulated():
    spy = open_bus("spy+fake")
    assert bus_is_simulated(open_bus("fake")) and bus_is_simulated(spy)
    assert not bus_is_simulated(_HardwareBus())
    assert bus_is_simulated(_SaysSimulated())
    modbus = open_bus("modbus://127.0.0.1:1")  # not connected until the first access
    try:
        assert not bus_is_simulated(modbus)  # a gateway: the service cannot see its far side
    finally:
        modbus.close()
