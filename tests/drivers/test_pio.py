"""Pia6821 and Mvme410 drivers against the fake rack (and a minimal independent model)."""

from __future__ import annotations

import pytest

from drivers.pio import Mvme410, Pia6821
from drivers.pio.registers import MATRIX_SWITCHER, MVME410, decode_matrix_route, encode_matrix_route
from fakes.mvme410 import FakeMvme410
from fakes.rack import FakeRack
from fakes.testing import assert_register_writes
from pfma.clock import SimClock
from pfma.errors import BoardError, BusError


@pytest.fixture
def rack() -> FakeRack:
    return FakeRack(clock=SimClock())


@pytest.fixture
def video(rack) -> tuple[Mvme410, FakeMvme410]:
    fake = rack.add(0x0020, FakeMvme410(name="pio_video", clock=rack.clock))
    return Mvme410(rack, 0x0020, name="pio_video"), fake


@pytest.fixture
def user(rack) -> tuple[Mvme410, FakeMvme410]:
    fake = rack.add(0x0040, FakeMvme410(name="pio_user", clock=rack.clock))
    return Mvme410(rack, 0x0040, name="pio_user"), fake


def test_even_byte_access_is_bus_error_naming_board_register_address(rack, video):
    with pytest.raises(BusError) as e:
        rack.read8(0x0022)
    err = e.value
    assert (err.board, err.addr, err.width, err.op) == ("pio_video", 0x0022, 8, "read")
    assert "PIA1_CRA" in str(err) and "0x0022" in str(err)
    # a driver given even addresses fails the same way, with the board named
    bad = Pia6821(rack, 0x20, 0x22, 0x24, 0x26, name="wrong")
    with pytest.raises(BusError, match="pio_video"):
        bad.configure("a", 0xFF)


def test_bus_error_without_board_gets_driver_context():
    class DeadBus:
        def read8(self, addr):
            raise BusError(addr, 8, "read")

        write8 = read16 = write16 = read8

    pia = Pia6821(DeadBus(), 0x21, 0x23, 0x25, 0x27, name="pio_user.PIA1")
    with pytest.raises(BusError) as e:
        pia.read_control("b")
    assert e.value.board == "pio_user.PIA1" and e.value.register == "CRB"


def test_configure_follows_the_bios_sequence(video):
    drv, fake = video
    drv.configure(["out", "in", 0x0F, "in"])
    assert_register_writes(fake, [
        ("PIA1_CRA", 0x38), ("PIA1_PRA", 0xFF), ("PIA1_CRA", 0x3C),  # bios.c printer init A
        ("PIA1_CRB", 0x00), ("PIA1_PRB", 0x00), ("PIA1_CRB", 0x04),
        ("PIA2_CRA", 0x38), ("PIA2_PRA", 0x0F), ("PIA2_CRA", 0x3C),
        ("PIA2_CRB", 0x00), ("PIA2_PRB", 0x00), ("PIA2_CRB", 0x04),
    ], width=8)
    assert fake.pia1.ca2_level and fake.pia2.ddr("a") == 0x0F
    drv.write_port(2, 0xAB)
    assert fake.outputs(2) == 0x0B
    with pytest.raises(BoardError, match="port 1 is not configured as an output"):
        drv.write_port(1, 1)
    with pytest.raises(ValueError, match="port 4"):
        drv.read_port(4)
    with pytest.raises(ValueError, match="4 port directions"):
        drv.configure(["in"])


def test_user_inputs_read_back_what_the_hook_drives(user):
    drv, fake = user
    drv.configure(["in", "in", "in", "in"])
    fake.drive_inputs(0, 0x34)
    fake.drive_inputs(1, 0x12)
    assert drv.read_user_inputs() == 0x1234
    fake.drive_inputs(0, 0x00, mask=0x0F)
    assert drv.read_user_inputs() == 0x1230
    fake.drive_inputs(0, None)
    fake.drive_inputs(1, None)
    assert drv.read_user_inputs() == 0xFFFF  # open inputs read high


def test_matrix_route_latched_by_switcher_after_strobe_handshake(rack, video):
    drv, fake = video
    drv.configure(["out", "in", "in", "in"])
    route = encode_matrix_route(monitor_1_camera=2, monitor_2_camera=3)
    assert route == 0b1110 and decode_matrix_route(route) == (2, 3)
    mark = len(fake.traffic)
    t0 = rack.clock.now()
    drv.write_matrix_route(route)
    assert fake.route == route and fake.switcher.monitors == (2, 3)
    assert fake.switcher.strobes == 1
    # data, dummy read, CA2 low then high (bios.c: CRA 0x34, 0x3C)
    assert_register_writes(fake, [("PIA1_PRA", route), ("PIA1_CRA", 0x34), ("PIA1_CRA", 0x3C)],
                           width=8, since=mark)
    # the driver waited for the acknowledge: simulated time passed the switcher's delay
    assert rack.clock.now() - t0 >= MATRIX_SWITCHER["ack_delay_s"]
    assert not fake.pia1.control("a") & 0x80  # acknowledge flag cleared afterwards
    drv.write_matrix_route(encode_matrix_route(1, 0))
    assert fake.switcher.monitors == (1, 0) and fake.switcher.strobes == 2


def test_matrix_route_without_acknowledge_is_bounded_board_error(video):
    drv, fake = video
    drv.configure(["out", "in", "in", "in"])
    fake.inject("switcher_silent")
    mark = len(fake.traffic)
    with pytest.raises(BoardError, match=r"pio_video.*0x05.*CA1 within 50 polls.*0x0023"):
        drv.write_matrix_route(0x05, max_polls=50)
    cra_reads = [t for t in fake.traffic[mark:] if t[0] == "r" and t[2] == 0x03]
    assert len(cra_reads) == 50
    assert fake.route == 0x05  # latched, but never acknowledged
    fake.clear("switcher_silent")
    drv.write_matrix_route(0x06)
    assert fake.route == 0x06


def test_matrix_route_refuses_bad_use(video):
    drv, _ = video
    with pytest.raises(BoardError, match="configured 'out'"):
        drv.write_matrix_route(1)
    drv.configure(["out", "in", "in", "in"])
    with pytest.raises(ValueError, match="not 8 bits"):
        drv.write_matrix_route(0x100)
    with pytest.raises(ValueError, match="camera 4"):
        encode_matrix_route(4, 0)


def test_pia_c2_modes_through_the_rack(rack, video):
    drv, fake = video
    pia = drv.pia2
    pia.configure("b", 0xFF, "strobe_e")
    seen = []
    fake.pia2.on_c2 = lambda side, level: seen.append((side, level))
    pia.write_port("b", 0x42)  # CB2 write strobe
    assert seen == [("b", False), ("b", True)] and fake.outputs(3) == 0x42
    pia.configure("a", 0x00, "strobe_c1")
    seen.clear()
    pia.read_port("a")  # CA2 read strobe, held low until the CA1 edge
    assert seen == [("a", False)]
    fake.pia2.drive_ca1(False)
    assert fake.pia2.ca2_level
    assert pia.flags("a") == (True, False)
    pia.clear_flags("a")
    assert pia.flags("a") == (False, False)
    pia.set_c2("a", False)
    assert not fake.pia2.ca2_level
    with pytest.raises(ValueError, match="C2 mode"):
        pia.set_c2_mode("a", "sideways")


class DictPia:
    """Minimal independent 6821 model (documented behaviour only), dict-backed, odd bytes."""

    def __init__(self, base: int) -> None:
        self.base = base
        self.r = {"DDRA": 0, "PRA": 0, "CRA": 0, "DDRB": 0, "PRB": 0, "CRB": 0}
        self.pins = {"A": 0xFF, "B": 0xFF}
        self.writes = []

    def _name(self, addr: int) -> str:
        rs = (addr - self.base - 1) // 2
        side = "A" if rs < 2 else "B"
        if rs % 2:
            return "CR" + side
        return ("PR" if self.r["CR" + side] & 4 else "DDR") + side

    def read8(self, addr):
        n = self._name(addr)
        if n.startswith("PR"):
            s = n[2]
            self.r["CR" + s] &= 0x3F  # reading the port clears the flags
            return (self.r[n] & self.r["DDR" + s]) | (self.pins[s] & ~self.r["DDR" + s] & 0xFF)
        return self.r[n]

    def write8(self, addr, value):
        n = self._name(addr)
        self.writes.append((n, value))
        self.r[n] = (self.r[n] & 0xC0) | (value & 0x3F) if n.startswith("CR") else value

    def read16(self, addr):
        raise AssertionError("the driver must use 8-bit accesses")

    write16 = read16


def test_driver_depends_only_on_the_documented_model():
    bus = DictPia(0x0040)
    pia = Pia6821(bus, 0x41, 0x43, 0x45, 0x47, name="model")
    pia.configure("a", 0xFF, "high")
    pia.configure("b", 0x00)
    assert bus.writes == [("CRA", 0x38), ("DDRA", 0xFF), ("CRA", 0x3C),
                          ("CRB", 0x00), ("DDRB", 0x00), ("CRB", 0x04)]
    bus.pins["B"] = 0x81
    assert pia.read_port("b") == 0x81
    pia.write_port("a", 0x55)
    assert bus.r["PRA"] == 0x55
    bus.r["CRA"] |= 0x80  # an acknowledge edge
    assert pia.wait_flag1("a", 3)
    pia.clear_flags("a")
    assert not pia.wait_flag1("a", 3)
    pia.pulse_c2("a")
    assert bus.writes[-2:] == [("CRA", 0x34), ("CRA", 0x3C)]


def test_table_records_assumptions():
    assert MVME410.byte_lanes == "odd" and MVME410.window == 0x20
    assert MVME410.reg("PIA2_PRA").source.startswith("assumed")
    assert MVME410.reg("PIA1_CRA").source.startswith("sourced")
    assert any("matrix switcher" in a for a in MVME410.assumptions)
