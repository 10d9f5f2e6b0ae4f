"""The ADC scan overlaps the frame's other bus work (issue 16: the fewest transactions and no
busy wait): in a frame the A/D runs in, the scan's START goes out before the DAC write, and
the scan is collected after the resolvers, so its 32 x 4 us of conversions are not waited
for by polling while there is other work to do (on the simulated rack each access takes 1 us
of model time and the other work ~30 accesses, so most of the EOC polls remain there; in the
live loop the DAC and resolver tasks take longer than the conversions)."""

from __future__ import annotations

from drivers.adc.registers import CSR, SCAN, START
from drivers.bus.spy import SpyBus
from sim.rig import SimRig


def _frame_log(rig: SimRig, spy: SpyBus, k: int) -> list:
    """The bus accesses of service frame ``k`` (the serial drains left out)."""
    while rig.svc.loop.k < k:
        rig.svc.run(frames=1)
    spy.log.clear()
    rig.svc.run(frames=1)
    return [a for a in spy.log if not (0x0000 <= a.addr < 0x0010)]


def test_adc_scan_starts_before_the_dac_and_is_read_after_the_resolvers():
    rig = SimRig(prefix="pfma-test-")
    try:
        spy = SpyBus(rig.world.bus, logger=None)
        for task in (rig.svc.adc, rig.svc.dac, rig.svc.rtd):  # the drivers talk through the spy
            for b in getattr(task, "boards", []):
                b[1].bus = spy
        rig.svc.dac.drv.bus = spy
        base = {n: rig.world.bus.bases[n] for n in ("adc", "dac", "rtd1")}
        log = _frame_log(rig, spy, 2)  # frame 2: DAC, resolvers and A/D (both every 2nd frame)
        where = {i: a for i, a in enumerate(log)}
        start = next(i for i, a in where.items() if a.op == "write" and a.addr == base["adc"] + START.offset)
        dac = next(i for i, a in where.items() if a.op == "write" and base["dac"] <= a.addr < base["dac"] + 0x40)
        rtd = next(i for i, a in where.items() if a.op == "read" and base["rtd1"] <= a.addr < base["rtd1"] + 0x10)
        scan = next(i for i, a in where.items() if a.block and a.addr == base["adc"] + SCAN.offset)
        assert start < dac < rtd < scan
        # the scan's EOC polls come after the resolvers, none between START and the DAC write
        polls = [i for i in range(start, scan) if log[i].addr == base["adc"] + CSR.offset]
        assert polls and min(polls) > rtd
        # what the service published is what the scan's block read returned
        assert list(rig.reader.read_inputs().record["adc_counts"][:32]) == list(log[scan].words)
    finally:
        rig.close()
