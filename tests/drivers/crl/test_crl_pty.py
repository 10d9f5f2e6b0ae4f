"""CrlHandController against FakeCrlMaster over a REAL pty.

Most tests step the link in simulated time (tests/drivers/crl/simline.py: the test moves the
bytes, a SimClock drives the watchdog), so they are deterministic. One test runs the
fake free in real time behind fakes.pty.PtyDevice, waiting on data with deadlines.
"""

from __future__ import annotations

import math
import random
import select
import time

import pytest

from drivers.crl import CrlHandController
from drivers.crl import crl_codec as codec
from fakes.crl import FakeCrlMaster
from pfma.clock import MonotonicClock, SimClock
from pfma.errors import LinkError
from tests.drivers.crl.simline import SimPtyLink

DT = codec.FRAME_PERIOD_S


@pytest.fixture
def rig():
    clock = SimClock()
    fake = FakeCrlMaster()
    link = SimPtyLink(fake, clock)
    drv = CrlHandController(link.port, clock)
    yield fake, link, drv, clock
    link.close()


def run(link, drv, n, dt=DT):
    states = []
    for _ in range(n):
        link.step(dt)
        states.append(drv.update())
    return states


def engage(fake, link, drv):
    """Frames flowing, deadman released once (re-arm), then pressed; one zero force frame
    sent (the fake's decoder confirms a first frame with the next one, as after any resync)."""
    run(link, drv, 3)
    fake.deadman = True
    st = run(link, drv, 2)[-1]
    assert st.active
    drv.send_force((0.0,) * 3, (0.0,) * 3)
    link.from_host(codec.FRAME_LEN)
    assert fake.last_force is None
    return st


def test_waits_for_frames_then_reports_axes_buttons_and_pose(rig):
    fake, link, drv, clock = rig
    st = drv.update()
    assert not st.valid and not st.fault and not st.deadman and st.source == "crl"
    fake.set_pose((0.10, -0.05, 0.0), (0.0, math.radians(30), -math.radians(60)))
    fake.set_buttons(deadman=False, index=True, trigger=True)
    st = run(link, drv, 3)[-1]
    assert st.valid and not st.fault and not st.deadman
    assert st.axes == pytest.approx((0.5, -0.25, 0.0, 0.0, 0.5, -1.0), abs=1e-4)
    assert st.buttons == codec.BTN_INDEX | codec.BTN_TRIGGER
    assert st.t_s == pytest.approx(clock.now())
    xyz_m, rpy_rad = drv.pose()
    assert xyz_m == pytest.approx((0.10, -0.05, 0.0), abs=1e-5)
    assert rpy_rad[1] == pytest.approx(math.radians(30), abs=1e-4)
    fake.deadman = True
    st = run(link, drv, 2)[-1]
    assert st.deadman and st.active
    assert drv.link_stats()["frames_ok"] >= 4 and drv.link_stats()["bytes_discarded"] == 0


def test_deadman_held_at_start_must_be_released_once(rig):
    fake, link, drv, _ = rig
    fake.set_buttons(deadman=True)
    st = run(link, drv, 4)[-1]
    assert st.valid and not st.deadman and "re-arm" in st.reason
    fake.deadman = False
    run(link, drv, 2)
    fake.deadman = True
    assert run(link, drv, 2)[-1].deadman


def test_stall_trips_watchdog_and_recovery_needs_a_release(rig):
    fake, link, drv, clock = rig
    engage(fake, link, drv)
    fake.stall(0.2)
    states = run(link, drv, 5)  # 100 ms without a frame
    # last good frame was seen just before the stall: frames 1-3 fine, then the trip
    assert [s.fault for s in states[:3]] == [False, False, False]
    assert states[3].fault and not states[3].valid and not states[3].deadman
    assert "watchdog" in states[3].reason
    assert drv.tripped and drv.link_stats()["watchdog_trips"] == 1
    st = run(link, drv, 10)[-1]  # frames are back, deadman still held
    assert st.valid and not st.fault and not st.deadman and "re-arm" in st.reason
    fake.deadman = False
    run(link, drv, 1)
    fake.deadman = True
    assert run(link, drv, 1)[-1].active
    assert drv.link_stats()["watchdog_trips"] == 1


def test_three_bad_frames_trip_two_do_not(rig):
    fake, link, drv, _ = rig
    engage(fake, link, drv)
    fake.corrupt_next(2)
    states = run(link, drv, 4)
    assert not any(s.fault for s in states) and drv.link_stats()["watchdog_trips"] == 0
    fake.corrupt_next(3)
    states = run(link, drv, 3)
    assert [s.fault for s in states] == [False, False, True]
    assert "bad frames" in states[2].reason and not states[2].deadman


def test_noise_flood_trips_without_time_passing(rig):
    fake, link, drv, _ = rig
    engage(fake, link, drv)
    link.to_host(bytes(range(0x70, 0x90)) * 2)  # 64 bytes of garbage, clock not moved
    st = drv.update()
    assert st.fault and "bad frames" in st.reason


def test_noise_drops_and_corruption_never_give_a_corrupt_state(rig):
    fake, link, drv, _ = rig
    rng = random.Random(11)
    fake.axes_fn = lambda t: tuple(math.sin(2 * math.pi * (t / 0.9 + k / 6)) for k in range(6))
    engage(fake, link, drv)
    good = 0
    for i in range(400):
        r = rng.random()
        if r < 0.08:
            fake.inject_noise(bytes(rng.choice((0x7E, rng.randrange(256))) for _ in range(rng.randint(1, 12))))
        elif r < 0.12:
            fake.drop_next(rng.randint(1, 3), after_bytes=rng.randrange(16))
        elif r < 0.15:
            fake.corrupt_next(1)
        fake.deadman = (i // 50) % 2 == 0
        link.step(DT)
        st = drv.update()
        truth = {(f.frame.axes_counts, f.frame.buttons) for f in fake.sent_frames if not f.corrupted}
        if st.valid:
            good += 1
            assert (st.raw, st.buttons) in truth  # every valid state is exactly a frame that was sent
            assert st.axes == tuple(codec.counts_to_unit(c) for c in st.raw)
        else:
            assert not st.deadman
    stats = drv.link_stats()
    assert good > 300
    assert stats["bytes_discarded"] > 0 and stats["frames_bad"] > 0 and stats["frames_lost"] > 0


def test_force_frames_reach_the_fake_saturated(rig):
    fake, link, drv, _ = rig
    engage(fake, link, drv)
    sent = drv.send_force((60.0, 80.0, 0.0), (0.0, 0.0, 5.0))  # 100 N, 5 N.m: over the limits
    link.from_host(codec.FRAME_LEN)
    got = fake.last_force
    assert got.frame == sent and got.frame.enabled
    assert got.force_n == pytest.approx((24.0, 32.0, 0.0), abs=2e-3)  # direction kept, |F| = 40 N
    assert got.torque_nm == pytest.approx((0.0, 0.0, 2.0), abs=1e-4)
    assert fake.displayed_force_n == pytest.approx((24.0, 32.0, 0.0), abs=2e-3)
    drv.send_force((5.0, -3.0, 1.0), (0.1, 0.2, -0.3))
    link.from_host(codec.FRAME_LEN)
    assert fake.last_force.force_n == pytest.approx((5.0, -3.0, 1.0), abs=2e-3)
    assert fake.last_force.frame.seq == (got.frame.seq + 1) & 0xFF
    assert drv.link_stats()["tx_frames"] == 3 and drv.link_stats()["tx_saturated"] == 1


def test_forces_are_zeroed_when_tripped_or_released(rig):
    fake, link, drv, _ = rig
    engage(fake, link, drv)
    drv.send_force((10.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    link.from_host(16)
    assert fake.displayed_force_n[0] == pytest.approx(10.0, abs=2e-3)
    fake.deadman = False
    run(link, drv, 1)
    drv.send_force((10.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    link.from_host(16)
    assert not fake.last_force.frame.enabled and fake.displayed_force_n == (0.0, 0.0, 0.0)
    fake.stall(1.0)
    run(link, drv, 4)
    assert drv.tripped
    drv.send_force((10.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    link.from_host(16)
    f = fake.last_force.frame
    assert f.wrench_counts == (0,) * 6 and not f.enabled and f.flags & codec.FLAG_FAULT


def test_non_finite_force_sends_zero_then_raises(rig):
    fake, link, drv, _ = rig
    engage(fake, link, drv)
    with pytest.raises(ValueError, match="non-finite"):
        drv.send_force((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0))
    link.from_host(16)
    assert fake.last_force.frame.wrench_counts == (0,) * 6 and not fake.last_force.frame.enabled


def test_fake_master_zeroes_its_display_when_force_frames_stop(rig):
    fake, link, drv, _ = rig
    engage(fake, link, drv)
    drv.send_force((0.0, 0.0, 20.0), (0.0, 0.0, 0.0))
    run(link, drv, 2)
    assert fake.displayed_force_n[2] == pytest.approx(20.0, abs=2e-3)
    run(link, drv, 2)  # 80 ms with no force frame
    assert fake.displayed_force_n == (0.0, 0.0, 0.0) and fake.watchdog_trips == 1


class BrokenPort:
    in_waiting = 16
    port = "/dev/ttyBROKEN"

    def read(self, n):
        raise OSError(5, "Input/output error")

    def write(self, data):
        raise OSError(5, "Input/output error")


def test_port_errors_give_a_fault_state_and_a_link_error():
    drv = CrlHandController(BrokenPort(), SimClock())
    st = drv.update()
    assert st.fault and not st.deadman and "/dev/ttyBROKEN" in st.reason
    with pytest.raises(LinkError, match="/dev/ttyBROKEN"):
        drv.send_force((0.0,) * 3, (0.0,) * 3)
    assert drv.link_stats()["port_errors"] == 2


def test_bad_force_arguments():
    drv = CrlHandController(BrokenPort(), SimClock())
    with pytest.raises(ValueError, match="3 forces"):
        drv.send_force((1.0, 2.0), (0.0, 0.0, 0.0))


def _wait_until(cond, port, timeout_s=3.0):
    deadline = time.monotonic() + timeout_s
    while not cond():
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        select.select([port.fileno()], [], [], min(left, 0.01))  # wake on data
    return True


@pytest.mark.realtime
def test_real_time_behind_ptydevice():
    import fakes.pty as pty
    fake = FakeCrlMaster(axes_fn=lambda t: (0.25, -0.5, 0.0, 0.0, 0.0, 0.75))
    with pty.PtyDevice(fake, baud=codec.BAUD) as dev:
        drv = CrlHandController.open(dev.port_name, MonotonicClock())
        try:
            assert _wait_until(lambda: drv.update().valid, drv.port)
            assert drv.state.axes == pytest.approx((0.25, -0.5, 0.0, 0.0, 0.0, 0.75), abs=1e-4)
            fake.deadman = True
            assert _wait_until(lambda: drv.update().deadman, drv.port)
            drv.send_force((0.0, 12.0, 0.0), (0.0, 0.0, 0.0))
            drv.send_force((0.0, 12.0, 0.0), (0.0, 0.0, 0.0))  # the 2nd confirms the 1st
            assert _wait_until(lambda: len(fake.received) == 2, drv.port)
            assert fake.last_force.force_n[1] == pytest.approx(12.0, abs=2e-3)
            dev.stall(0.3)
            assert _wait_until(lambda: drv.update().fault, drv.port)
            assert not drv.state.deadman and drv.link_stats()["watchdog_trips"] == 1
            assert _wait_until(lambda: drv.update().valid, drv.port)
            assert dev.error is None
        finally:
            drv.close()
