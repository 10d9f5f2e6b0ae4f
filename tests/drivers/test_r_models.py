"""Every VME driver against a second, independent model of R1-R5 (``r_models``), not fakes/.

Deterministic: the model's time moves only through the shared SimClock (the drivers'
waits, and for the ADC a timer that stands for wall-clock time passing while it polls).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.adc import Dvme611
from drivers.dac import Vmivme4100
from drivers.mvme400 import Mvme400
from drivers.pio import Mvme410
from drivers.rtd import Vmivme4940
from pfma.clock import SimClock
from pfma.errors import BoardError, BusError
from tests.drivers.r_models import RModelRack

LSB = 20.0 / 4096


@pytest.fixture
def rack():
    return RModelRack(SimClock())


class PollTimer:
    """Wall-clock stand-in for the ADC driver: each call is 1 us of time passing."""

    def __init__(self, clock: SimClock) -> None:
        self.clock = clock
        self.calls = 0

    def __call__(self) -> float:
        self.calls += 1
        self.clock.advance(1e-6)
        return self.clock.now()


# -- R1 -----------------------------------------------------------------------------------
def test_rtd_counts_angles_status_hold(rack):
    rack.rtd1.angle[:] = [0.0, math.pi / 2, math.pi, 2 * math.pi - 1e-4]
    rtd = Vmivme4940(rack, 0x0100, name="rtd1")
    assert rtd.read_counts() == (0, 4096, 8192, 16383)
    assert np.allclose(rtd.read_angles_rad(), [0, math.pi / 2, math.pi, 16383 * 2 * math.pi / 16384])
    assert rtd.status().ok
    rack.rtd1.fault[2], rack.rtd1.reference = True, False
    st = rtd.status()
    assert st.faults == (False, False, True, False) and not st.reference_present and not st.ok
    rtd.hold(1)
    rack.rtd1.angle[1] = 0.0
    assert rtd.read_counts()[1] == 4096  # frozen
    rtd.release(1)
    assert rtd.read_counts()[1] == 0
    rtd.set_fail_led(False)
    assert rack.rtd1.control == 0x4000
    rack.rtd2.angle[0] = 1.0
    assert Vmivme4940(rack, 0x0200).read_angle_rad(0) == pytest.approx(1.0, abs=2 * math.pi / 16384)


# -- R2 -----------------------------------------------------------------------------------
def test_dac_enable_write_disable(rack):
    dac = Vmivme4100(rack, 0xD000, name="dac")
    assert rack.dac.writes == []  # construction touches nothing
    dac.write_volts(3, 5.0)
    assert rack.dac.volts(3) == 0.0  # outputs start disconnected
    dac.enable_outputs()
    assert rack.dac.writes[-1] == (0, 0xC100) and rack.dac.ctrl == 0x41
    assert rack.dac.volts(3) == pytest.approx(5.0, abs=LSB)
    dac.write_counts(15, 0xFFF)
    dac.write_volts(0, -10.0)
    assert rack.dac.code[15] == 0xFFF and rack.dac.code[0] == 0 and rack.dac.ctrl == 0x41
    assert dac.outputs_connected() and dac.shadow_counts[15] == 0xFFF
    dac.disable_outputs()
    assert rack.dac.code == [0x800] * 16 and rack.dac.ctrl & 0x01 == 0
    assert not dac.outputs_connected()


# -- R3 -----------------------------------------------------------------------------------
def test_adc_conversion_on_real_time_is_not_declared_stuck(rack):
    """Polls that cost no model time: EOC comes only as (wall-clock) time passes.

    Regression: the driver used to give up after 64 CSR reads whatever the time, so on a
    model (or a board) that is faster to poll than 4 us / 64 it reported 'busy stuck'.
    """
    rack.adc.volts[:] = [-10 + 0.6 * ch for ch in range(32)]
    timer = PollTimer(rack.clock)
    adc = Dvme611(rack, 0xC000, name="adc", timer=timer)
    expected = [int(math.floor((v + 10) / 20 * 4096)) for v in rack.adc.volts]
    assert adc.read_counts(5) == expected[5]
    assert adc.read_volts(31) == pytest.approx(rack.adc.volts[31], abs=LSB)
    assert list(adc.scan()) == expected  # auto-increment through all 32
    assert np.allclose(adc.scan_volts(), rack.adc.volts, atol=LSB)
    assert timer.calls > 0


def test_adc_stuck_busy_still_bounded(rack):
    timer = PollTimer(rack.clock)
    adc = Dvme611(rack, 0xC000, name="adc", timer=timer, min_wait_s=50e-6)
    rack.adc.stuck_busy = True
    with pytest.raises(BoardError, match=r"adc: busy stuck converting channel 3: CSR at A16 0xC000"):
        adc.read_counts(3)
    assert 50 <= timer.calls <= 53  # the wall-clock bound, not a hang


def test_adc_scan_mode_against_the_independent_model(rack):
    """The table's scan mode on the second model: one START with b0 = 1, polls until the
    128 us scan ends (model time moves only with the driver's timer), one block of SCAN."""
    from drivers.adc.registers import DVME611

    assert DVME611.constants["scan_mode"]
    rack.adc.volts[:] = [9.5 - 0.6 * ch for ch in range(32)]
    timer = PollTimer(rack.clock)
    adc = Dvme611(rack, 0xC000, name="adc", timer=timer)
    expected = [int(math.floor((v + 10) / 20 * 4096)) for v in rack.adc.volts]
    assert adc.scan().tolist() == expected
    assert rack.adc.scan_buf == expected and rack.adc.ch == 0  # CSR channel left alone
    assert timer.calls >= 128  # the driver waited the whole scan on its (wall) timer


def test_adc_per_channel_fallback_against_the_independent_model(rack, monkeypatch):
    from drivers.adc.registers import DVME611

    monkeypatch.setitem(DVME611.constants, "scan_mode", False)
    rack.adc.volts[:] = [-3.0 + 0.2 * ch for ch in range(32)]
    adc = Dvme611(rack, 0xC000, name="adc", timer=PollTimer(rack.clock))
    expected = [int(math.floor((v + 10) / 20 * 4096)) for v in rack.adc.volts]
    assert adc.scan().tolist() == expected
    assert rack.adc.ch == 0 and rack.adc.autoinc  # 32 DATA reads went round to channel 0


def test_adc_scan_stuck_busy_still_bounded(rack):
    timer = PollTimer(rack.clock)
    adc = Dvme611(rack, 0xC000, name="adc", timer=timer, min_wait_s=50e-6)
    rack.adc.stuck_busy = True
    with pytest.raises(BoardError, match=r"adc: busy stuck scanning channels 0..31"):
        adc.scan()
    assert 32 * 50 <= timer.calls <= 32 * 50 + 3  # 32 conversions' wall-clock bound


# -- R5 -----------------------------------------------------------------------------------
def test_pio_user_inputs_and_ports(rack):
    user = Mvme410(rack, 0x0040, name="pio_user")
    user.configure(["in", "in", "in", "in"])
    rack.pio_user.pia1.pins["a"], rack.pio_user.pia1.pins["b"] = 0x5A, 0xC3
    assert user.read_user_inputs() == 0xC35A
    rack.pio_user.pia2.pins["a"] = 0x11
    assert user.read_port(2) == 0x11 and user.read_port(3) == 0xFF


def test_pio_matrix_switcher_strobe_handshake(rack):
    video = Mvme410(rack, 0x0020, name="pio_video")
    video.configure(["out", "in", "out", "out"])
    video.write_matrix_route(0x09)
    video.write_matrix_route(0x06)
    assert rack.pio_video.routes == [0x09, 0x06]
    assert not rack.pio_video.pia1.flag1["a"]  # acknowledge flag cleared afterwards
    video.write_port(3, 0xA5)
    assert rack.pio_video.pia2.output("b") == 0xA5 and video.read_port(3) == 0xA5
    rack.pio_video.acknowledge = False
    with pytest.raises(BoardError, match=r"pio_video: matrix switcher did not acknowledge.*0x0023"):
        video.write_matrix_route(0x01, max_polls=10)


# -- R4 -----------------------------------------------------------------------------------
def test_mvme400_byte_port_round_trip(rack):
    clock = rack.clock
    sio = Mvme400(rack, 0x0000, name="sio", clock=clock)
    sio.init(19200, 19200)
    assert rack.sio.ch[0].baud() == 19200 and rack.sio.pia.output("b") == 0xFF
    port = sio.port(0, timeout=0.1)
    assert port.write(b"hello") == 5
    port.flush()  # waits on the shared clock: the characters went out
    assert rack.sio.peer_recv(0) == b"hello"
    rack.sio.peer_send(0, b"ab")
    assert port.read(2) == b"ab"
    rack.sio.peer_send(0, b"xyz")
    assert port.in_waiting == 0  # not arrived yet: no time has passed
    clock.advance(3 * 10 / 19200)
    assert port.in_waiting == 3 and port.read(3) == b"xyz"
    rack.sio.peer_send(0, b"123456")  # 6 characters into a 3-deep FIFO, no poll meanwhile
    clock.advance(0.01)
    port.poll()
    assert port.stats.overruns == 1 and rack.sio.ch[0].overrun == 0  # counted and reset
    assert sio.dsr(0) and sio.dsr(1)
    sio.set_baud(1, 9600)
    rack.sio.ch[1].peer_baud = 9600
    pb = sio.port(1, timeout=0.1)
    pb.write(b"Q")
    pb.flush()
    assert rack.sio.peer_recv(1) == b"Q"


# -- bus errors: the model names nothing, the drivers name board, register, address --------
@pytest.mark.parametrize("call,words", [
    (lambda bus: Vmivme4940(bus, 0x0300, name="rtd9").read_counts(), "read16 rtd9 CH0 at A16 0x0300"),
    (lambda bus: Vmivme4940(bus, 0x0300, name="rtd9").status(), "read16 rtd9 STATUS at A16 0x0308"),
    (lambda bus: Dvme611(bus, 0xC100, name="adc2").read_counts(4), "write16 adc2 CSR (channel 4) at A16 0xC100"),
    (lambda bus: Vmivme4100(bus, 0xD100, name="dac2").write_counts(2, 1), "write16 dac2 DAC[2] at A16 0xD104"),
    (lambda bus: Vmivme4100(bus, 0xD100, name="dac2").enable_outputs(), "write16 dac2 DAC[0] at A16 0xD100"),
    (lambda bus: Mvme410(bus, 0x0060, name="pio9").configure(["in"] * 4), "write8 pio9.PIA1 CRA at A16 0x0063"),
    (lambda bus: Mvme400(bus, 0x0080, name="sio9").init(), "write8 sio9.PIA CRA at A16 0x0083"),
])
def test_bus_errors_name_board_register_address(rack, call, words):
    with pytest.raises(BusError) as exc:
        call(rack)
    assert words in str(exc.value)


def test_fresh_pio_driver_reads_without_resetting_control_lines(rack):
    """A second program (``pfma read``) reading a port the service configured must keep
    the control register: before, its driver wrote CRA = 0x04 (C2 to input, strobe line
    released) because its own shadow of CRA was the reset value."""
    from pfma.rack import load_rack
    from drivers.rackio import RackIO

    service = Mvme410(rack, 0x0020, name="pio_video")
    service.configure(["out", "in", "in", "in"])
    service.write_matrix_route(0x0E)
    pia = rack.pio_video.pia1
    assert pia.cr["a"] == 0x3C and pia.c2["a"] == 1
    reading = RackIO(rack, load_rack()).read_signal("matrix_switcher_route")
    assert reading.raw == 0x0E
    assert pia.cr["a"] == 0x3C and pia.c2["a"] == 1  # CA2 still an output, held high
    assert rack.pio_video.routes == [0x0E]  # no spurious strobe
    # a fresh driver on a board nobody configured still selects the data register
    other = Mvme410(rack, 0x0040, name="pio_user")
    assert other.read_port(0) == 0xFF and rack.pio_user.pia1.cr["a"] == 0x04
