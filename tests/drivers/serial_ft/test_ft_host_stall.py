"""Issue 14: a host stall on the F/T line through the MVME400, in simulated time.

A host stall is the service not running while the line goes on: the simulated clock is
moved on without the service's hooks (no drains), so the fake board's 3-deep Rx FIFO
fills and every further character is lost, exactly as on the rack (the fake is not
changed). The service must then lose only the records whose characters were lost, decode
the first whole record after the stall as soon as it is complete (one record period of
the line), and not flag the link stale for a 20 ms or a 60 ms stall.
"""

from __future__ import annotations

import pytest

from drivers.serial_ft import protocol as P
from sim.rig import SimRig

RECORD_S = P.record_bytes("binary", True) * P.BITS_PER_CHAR / 19200  # 7.29 ms on the wire
STALLS = ((0.5, 0.020), (1.0, 0.060))  # (simulated time it starts, length)


def _capture_port_bytes(ft) -> bytearray:
    """Every byte the driver takes from the port, in order (a tap: behaviour unchanged)."""
    got = bytearray()
    port = ft.port
    inner = port.read

    def read(size=1):
        data = inner(size)
        got.extend(data)
        return data

    port.read = read
    return got


def _run_with_stalls(rig: SimRig, stalls, seconds: float):
    """Run the service; at each stall time move the clock on without running the service."""
    svc = rig.svc
    pending = sorted(stalls)
    ends = []
    published = []  # (t, link_age, stale) per frame

    def stall_hook(info):
        if pending and rig.clock.now() >= pending[0][0]:
            _t, length = pending.pop(0)
            rig.clock.advance(length)  # no drains, no frames: the host did not run us
            ends.append(rig.clock.now())

    def after(info):
        s = rig.reader.read_inputs()
        link = rig.reader.layout.slot("link", "ft_sensor")
        published.append((rig.clock.now(), float(s.link_age_s[link]), int(s.link_status[link])))

    rig.on_frame.append(stall_hook)
    rig.after_frame.append(after)
    decoded = []
    inner = svc._ft.read_records

    def read_records():
        recs = inner()
        decoded.extend(recs)
        return recs

    svc._ft.read_records = read_records
    rig.run(seconds)
    return ends, published, decoded


def _ramp(t_s: float):
    """A load that changes every sample (each record on the wire is unique)."""
    return (20.0 * (t_s % 2.0), 5.0, -14.7), (0.1, -0.2, 0.05)


@pytest.fixture
def stall_rig():
    r = SimRig(prefix="pfma-test-ftstall-")
    r.world.ft.load_fn = _ramp  # instead of the resting arm's constant load
    yield r
    r.close()


def _delays(rig, decoded):
    """Per decoded record: (time it went on the wire, decode time - that time)."""
    sent = {(r.status, tuple(r.counts)): r.t_s for r in rig.world.ft.sent_records}
    out = []
    for r in decoded:
        t0 = sent.get((r.status, tuple(r.counts)))
        assert t0 is not None, f"decoded a record that was never sent: {r}"
        out.append((t0, r.t_s - t0))
    return out


#: a record is decoded when its last byte and the next status byte are in (line time of
#: one record plus one character), at the next drain (a tick)
DUE_S = RECORD_S + 10 / 19200 + 0.0007 + 0.0005


def test_a_20ms_then_60ms_host_stall_costs_only_the_lost_records_and_resyncs_at_the_next_record(stall_rig):
    rig = stall_rig
    rig.run(0.2)  # streaming
    ft = rig.svc._ft
    wire = _capture_port_bytes(ft)
    sent0 = rig.world.ft.records_sent
    bad0 = ft.stats().bad_records
    ends, published, decoded = _run_with_stalls(rig, STALLS, 1.5)
    assert len(ends) == 2
    delays = _delays(rig, decoded)  # also: nothing decoded that was not sent
    truth = [(r.status, tuple(r.counts)) for r in rig.world.ft.sent_records if r.index >= sent0]
    got = {(r.status, tuple(r.counts)) for r in decoded}

    # physically intact = the record's 14 bytes reached the driver back to back
    intact = [t for t in truth if P.encode_binary(*t, True) in wire]
    lost_physically = len(truth) - len(intact)
    assert lost_physically >= 2 + 8  # 20 ms = 2.7 records on the wire, 60 ms = 8.2
    # every intact record is decoded (but the last one or two, still on the wire), except a
    # whole record whose successor's first byte was lost: the one-byte look-ahead cannot
    # confirm it (at most one per stall; trusting the checksum alone would let more corrupt
    # records through, see BinaryStreamDecoder.trust_checksum)
    unconfirmed = [t for t in intact[:-2] if t not in got]
    assert len(unconfirmed) <= len(ends)
    for t in unconfirmed:
        nxt = truth[truth.index(t) + 1]
        assert P.encode_binary(*t, True) + P.encode_binary(*nxt, True)[:1] not in wire
    assert ft.stats().bad_records - bad0 >= 2  # each stall cut a record: counted
    # and none late: not the first after a stall either (no wait for a second record)
    assert max(d for _t0, d in delays) <= DUE_S
    for end in ends:
        first = min(t0 for t0, _d in delays if t0 >= end)
        assert first - end <= RECORD_S + 1e-3  # the first record put on the wire after the stall

    # the link is never flagged stale: the largest age is the stall plus about two records
    worst = max(age for _t, age, _st in published)
    assert worst < 0.060 + 3 * RECORD_S + 0.005
    assert not any(st & 8 for _t, _age, st in published)  # LINK_STALE


def test_without_the_fix_the_first_record_after_a_stall_waits_for_a_second(stall_rig):
    """The same run with the old two-record re-sync (and no decoding between frames): the
    first whole record after each stall is only decoded once a second one has arrived."""
    rig = stall_rig
    rig.svc._ft_in_tick = False
    ft = rig.svc._ft
    ft.resync_records = 2
    ft._decoder = ft._new_decoder()
    rig.run(0.2)
    ends, _published, decoded = _run_with_stalls(rig, STALLS, 1.5)
    delays = _delays(rig, decoded)
    for end in ends:
        first = min((t0, d) for t0, d in delays if t0 >= end)
        assert first[1] > RECORD_S + DUE_S - 0.001  # one more record on the wire before it
