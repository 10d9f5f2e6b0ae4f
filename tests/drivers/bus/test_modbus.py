"""ModbusTcpBus against a real pymodbus server (fakes.modbus_gateway) on 127.0.0.1."""

from __future__ import annotations

import socket

import pytest

from drivers.bus import open_bus
from drivers.bus.modbus import (DEFAULT_TIMEOUT_S, FREE_RECONNECTS, RECONNECT_INTERVAL_S, ModbusTcpBus,
                                open_modbus_bus)
from fakes.modbus_gateway import ModbusGateway
from pfma.errors import AlignmentError, BusError
from tests.drivers.bus.tinybus import TinyBus, free_port, quiet_pymodbus


@pytest.fixture
def tiny():
    return TinyBus()


@pytest.fixture
def gateway(tiny):
    with quiet_pymodbus(), ModbusGateway(tiny) as gw:
        yield gw


@pytest.fixture
def bus(gateway):
    with ModbusTcpBus("127.0.0.1", gateway.port, timeout=2.0) as b:
        yield b


# -- mapping ------------------------------------------------------------------------------
def test_holding_register_n_is_the_word_at_2n(bus, tiny):
    bus.write16(0xD000, 0xC100)
    assert tiny.log == [("w", 0xD000, 0xC100)]
    tiny.words[0x0102] = 0x1234
    assert bus.read16(0x0102) == 0x1234


def test_read8_takes_high_byte_for_even_low_byte_for_odd(bus, tiny):
    tiny.words[0x0040] = 0xABCD
    assert bus.read8(0x0040) == 0xAB
    assert bus.read8(0x0041) == 0xCD


def test_write8_odd_writes_zero_high_byte_without_reading_first(bus, tiny):
    tiny.words[0x0020] = 0xFFFF
    tiny.log.clear()
    bus.write8(0x0021, 0x5A)
    assert tiny.log == [("w", 0x0020, 0x005A)]  # no read: chip reads have side effects


def test_write8_even_is_refused_before_the_network(bus, gateway, tiny):
    before = gateway.requests
    with pytest.raises(AlignmentError) as info:
        bus.write8(0x0020, 0x12)
    assert isinstance(info.value, ValueError) and isinstance(info.value, BusError)
    assert (info.value.addr, info.value.width, info.value.op) == (0x0020, 8, "write")
    assert gateway.requests == before and tiny.log == []


def test_block_read_reads_only_the_requested_registers_in_order(bus, tiny):
    for i in range(4):
        tiny.words[0xC040 + 2 * i] = 0x100 + i
    assert bus.read_block16(0xC040, 4) == [0x100, 0x101, 0x102, 0x103]
    assert [a for op, a, _ in tiny.log] == [0xC040, 0xC042, 0xC044, 0xC046]


def test_any_unit_id_is_answered(gateway, tiny):
    tiny.words[0x0200] = 0x0042
    with ModbusTcpBus("127.0.0.1", gateway.port, unit=255, timeout=2.0) as b:
        assert b.read16(0x0200) == 0x0042


# -- exception responses -----------------------------------------------------------------
def test_nobody_answers_is_exception_2_and_a_bus_error(bus):
    with pytest.raises(BusError) as info:
        bus.read16(0x8000)
    err = info.value
    assert (err.addr, err.width, err.op) == (0x8000, 16, "read")
    assert "0x8000" in str(err) and "exception 2" in str(err)
    assert type(err.__cause__).__module__.startswith("pymodbus")


def test_byte_access_error_names_the_byte_address(bus):
    with pytest.raises(BusError) as info:
        bus.read8(0x8001)
    assert (info.value.addr, info.value.width) == (0x8001, 8)
    with pytest.raises(BusError) as info:
        bus.write8(0x8001, 1)
    assert (info.value.addr, info.value.width, info.value.op) == (0x8001, 8, "write")


def test_hosted_bus_failure_is_exception_4(bus):
    with pytest.raises(BusError) as info:
        bus.write16(0x9000, 1)
    assert "exception 4" in str(info.value) and info.value.op == "write"


def test_block_read_through_a_dead_address_fails_whole(bus, tiny):
    with pytest.raises(BusError) as info:
        bus.read_block16(0x7FFC, 4)
    assert info.value.addr == 0x7FFC


# -- timeouts and a missing gateway -------------------------------------------------------
@pytest.mark.realtime
def test_silent_gateway_times_out_with_a_bus_error():
    with socket.socket() as silent:  # accepts TCP (kernel backlog) but never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen(1)
        port = silent.getsockname()[1]
        with quiet_pymodbus(), ModbusTcpBus("127.0.0.1", port, timeout=0.2) as b:
            with pytest.raises(BusError) as info:
                b.read16(0xD000)
    assert "no reply" in str(info.value) and "0.2 s" in str(info.value)
    assert (info.value.addr, info.value.op) == (0xD000, "read")


@pytest.mark.realtime
def test_slow_gateway_times_out_then_recovers(gateway, tiny):
    tiny.words[0xD000] = 0x4100
    gateway.reply_delay_s = 1.0
    with ModbusTcpBus("127.0.0.1", gateway.port, timeout=0.1) as b:
        with pytest.raises(BusError, match="no reply"):
            b.read16(0xD000)
        gateway.reply_delay_s = 0.0
        assert b.read16(0xD000) == 0x4100  # a fresh connection; the late reply is never seen


def test_default_timeout_is_one_minor_frame():
    assert DEFAULT_TIMEOUT_S == 1.0 / 320.0  # 3.125 ms at 320 Hz
    b = open_bus("modbus://127.0.0.1:1502")
    assert b.timeout == DEFAULT_TIMEOUT_S and ModbusTcpBus("127.0.0.1", 1502).timeout == DEFAULT_TIMEOUT_S
    b.close()


def _five_accesses(b) -> list[str]:
    """read16, a 300-word block read (3 requests if answered), a 250-word block write,
    write16, read8: each must fail; returns the messages."""
    errors = []
    for access in (lambda: b.read16(0x1000), lambda: b.read_block16(0x1000, 300),
                   lambda: b.write_block16(0x1000, [1] * 250), lambda: b.write16(0x1000, 2),
                   lambda: b.read8(0x1001)):
        with pytest.raises(BusError) as info:
            access()
        errors.append(str(info.value))
    return errors


class Clock:
    """Simulated seconds for the reconnect interval (the timeouts stay real)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.mark.realtime
def test_a_gateway_that_stops_answering_costs_one_request_per_access_then_one_per_interval(gateway):
    """A real pymodbus server that receives requests and never replies: each of the first
    FREE_RECONNECTS accesses sends exactly one request (a block stops at its first unanswered
    request), waits one timeout (the default: one minor frame) and reconnects once; no retries.
    Then no storm: the accesses within RECONNECT_INTERVAL_S fail at once, saying the last
    error, without a connection; one after the interval sends one request again."""
    gateway.silent = True
    clock = Clock()
    with ModbusTcpBus("127.0.0.1", gateway.port, clock=clock) as b:
        errors = _five_accesses(b)
        assert b.requests == FREE_RECONNECTS and b.connects == FREE_RECONNECTS
        assert b.failures == 5
        clock.t += RECONNECT_INTERVAL_S
        with pytest.raises(BusError):
            b.read16(0x1000)
        assert (b.requests, b.connects) == (FREE_RECONNECTS + 1, FREE_RECONNECTS + 1)
    assert all(f"no reply from gateway 127.0.0.1:{gateway.port} within 0.003125 s" in e for e in errors)
    assert all(f"reconnecting every {RECONNECT_INTERVAL_S * 1e3:g} ms" in e for e in errors[FREE_RECONNECTS:])
    assert gateway.wait_requests(FREE_RECONNECTS + 1) == FREE_RECONNECTS + 1  # one per connection


@pytest.mark.realtime
def test_a_gateway_that_answers_again_is_used_again(gateway, tiny):
    tiny.words[0x1000] = 0x1234
    with ModbusTcpBus("127.0.0.1", gateway.port, timeout=0.2) as b:
        assert b.read16(0x1000) == 0x1234 and b.connects == 1
        gateway.silent = True
        with pytest.raises(BusError, match="no reply"):
            b.read16(0x1000)
        gateway.silent = False
        assert b.read16(0x1000) == 0x1234  # one reconnect, and the late reply is never seen
        assert b.read_block16(0x1000, 2) == [0x1234, 0]
        assert (b.requests, b.connects) == (4, 2)  # the connection is kept while it works


@pytest.mark.realtime
def test_a_gateway_that_is_gone_costs_one_connect_attempt_per_access_then_one_per_interval():
    port = free_port()
    clock = Clock()
    with quiet_pymodbus(), ModbusTcpBus("127.0.0.1", port, clock=clock) as b:
        errors = _five_accesses(b)
        assert (b.connects, b.requests) == (FREE_RECONNECTS, 0)
        clock.t += RECONNECT_INTERVAL_S
        with pytest.raises(BusError, match="unreachable"):
            b.read16(0x1000)
        assert (b.connects, b.requests) == (FREE_RECONNECTS + 1, 0)
    assert all("unreachable" in e for e in errors)


@pytest.mark.realtime
def test_a_gateway_back_after_the_interval_is_used_and_the_count_starts_again(gateway, tiny):
    tiny.words[0x1000] = 0x1234
    clock = Clock()
    with ModbusTcpBus("127.0.0.1", gateway.port, timeout=0.2, clock=clock) as b:
        gateway.silent = True
        for _ in range(FREE_RECONNECTS + 2):
            with pytest.raises(BusError, match="no reply"):
                b.read16(0x1000)
        gateway.silent = False
        with pytest.raises(BusError, match="accesses in a row failed"):
            b.read16(0x1000)  # within the interval: not tried, though the gateway is back
        clock.t += RECONNECT_INTERVAL_S
        assert b.read16(0x1000) == 0x1234 and b.failures == 0


@pytest.mark.realtime
def test_gateway_down_is_a_clear_bus_error():
    port = free_port()
    with quiet_pymodbus(), ModbusTcpBus("127.0.0.1", port, timeout=0.5) as b:
        with pytest.raises(BusError) as info:
            b.write16(0xD000, 0xC100)
    assert f"gateway 127.0.0.1:{port} unreachable" in str(info.value)
    assert (info.value.addr, info.value.width, info.value.op) == (0xD000, 16, "write")


@pytest.mark.realtime
def test_reconnects_after_the_gateway_restarts(tiny):
    with quiet_pymodbus():
        gw = ModbusGateway(tiny).start()
        port = gw.port
        tiny.words[0x0100] = 7
        with ModbusTcpBus("127.0.0.1", port, timeout=0.5) as b:
            assert b.read16(0x0100) == 7
            gw.stop()
            with pytest.raises(BusError, match="unreachable"):
                b.read16(0x0100)
            with ModbusGateway(tiny, port=port):
                assert b.read16(0x0100) == 7


def test_construction_does_not_touch_the_network():
    b = ModbusTcpBus("127.0.0.1", free_port())
    assert "holding register N = A16 word 2N" in b.describe()
    b.close()


# -- URLs ----------------------------------------------------------------------------------
def test_url_options():
    b = open_bus("modbus://127.0.0.1:1502?unit=3&timeout=0.25")
    assert isinstance(b, ModbusTcpBus)
    assert (b.host, b.port, b.unit, b.timeout) == ("127.0.0.1", 1502, 3, 0.25)
    b.close()


@pytest.mark.parametrize("url, words", [
    ("modbus://127.0.0.1:1502?slave=1", "unknown option 'slave'"),
    ("modbus://127.0.0.1", "needs a host and a port"),
    ("modbus://:1502", "needs a host and a port"),
    ("modbus://127.0.0.1:1502?timeout=soon", "timeout='soon' is not a number"),
    ("modbus://127.0.0.1:port", "port is not a number"),
])
def test_bad_urls_are_refused_by_name(url, words):
    with pytest.raises(ValueError) as info:
        open_modbus_bus(url)
    assert words in str(info.value)


def test_out_of_range_values_never_reach_the_gateway(bus, gateway):
    before = gateway.requests
    for bad in (0x10000, -1, 1.5):
        with pytest.raises(ValueError, match="0xD000"):
            bus.write16(0xD000, bad)
    with pytest.raises(ValueError, match="0x0021"):
        bus.write8(0x0021, 0x100)
    assert gateway.requests == before
