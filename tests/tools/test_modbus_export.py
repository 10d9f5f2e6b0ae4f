"""Modbus TCP export of the Bit3 buffer, read and written with a real pymodbus client.

Every server binds 127.0.0.1 on an ephemeral port; every buffer is a uniquely named
shared-memory segment removed by the ``shm_name`` fixture (conftest.py).
"""

import logging
import socket

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from bit3.client import Client
from bit3.layout import ServiceState, default_layout
from tools.modbus_export import (
    CHANNELS_BASE, IDENT_BASE, MAP_DOC_PATH, MAP_VERSION, STATS_BASE, ModbusExport,
    ModbusExportError, map_row, modbus_map_markdown, parse_host_port, register_map,
    start_export_from_args,
)
from bit3.buffer import OwnershipError
from pfma.errors import ConfigError
from tests.bit3 import _workers

DT = ModbusTcpClient.DATATYPE
ROWS = register_map()


@pytest.fixture(autouse=True)
def quiet_pymodbus():
    logger = logging.getLogger("pymodbus")
    old = logger.level
    logger.setLevel(logging.CRITICAL)
    yield
    logger.setLevel(old)


@pytest.fixture
def service(buf):
    """The test plays the I/O service: claims the service role, publishes known values."""
    lay = default_layout()
    buf.claim("service", "test-service")
    w = buf.writer("inputs")
    r = w.record
    r["frame"] = 123456789012
    r["t_s"] = 3.0625
    r["service_state"] = int(ServiceState.SAFE)
    r["outputs_enabled"] = 1
    r["brakes_released"] = 0
    r["watchdog_tripped"] = 1
    r["adc_value"][:] = np.arange(64) * 0.5 - 7.25
    r["rtd_angle_rad"][:] = np.linspace(-3.0, 3.0, 16)
    r["rtd_counts"][:] = np.arange(16) * 4001
    r["pio_port_bits"][:] = np.arange(16) + 0xA0
    r["ft_counts"] = [-1, 2, -300000, 4, 5, -6]
    r["hc_axes"][lay.slot("hc", "crl")] = [0.1, -0.2, 0.3, -0.4, 0.5, -0.6]
    r["dac_value"][:] = np.arange(32) * -0.125
    w.publish()
    s = buf.writer("stats")
    s.record["frame"] = 99
    s.record["rate_hz"] = 333.25
    s.record["work_p99_us"] = 71.5
    s.record["overruns"] = 7
    s.record["device_rate_hz"][:8] = [400.0, 200.0, 100.0, 50.0, 25.0, 12.5, 6.25, 0.0]
    s.publish()
    return buf


@pytest.fixture
def export(service):
    with ModbusExport(service, port=0) as ex:
        yield ex


def connect(port: int) -> ModbusTcpClient:
    c = ModbusTcpClient("127.0.0.1", port=port, timeout=2, retries=0)
    assert c.connect(), f"could not connect to the export on 127.0.0.1:{port}"
    return c


@pytest.fixture
def mb(export):
    c = connect(export.port)
    yield c
    c.close()


def read_ir(c: ModbusTcpClient, address: int, count: int, device_id: int = 1) -> list[int]:
    rr = c.read_input_registers(address, count=count, device_id=device_id)
    assert not rr.isError(), f"IR {address}+{count}: {rr}"
    return rr.registers


def read_hr(c: ModbusTcpClient, address: int, count: int) -> list[int]:
    rr = c.read_holding_registers(address, count=count, device_id=1)
    assert not rr.isError(), f"HR {address}+{count}: {rr}"
    return rr.registers


def value(c: ModbusTcpClient, name: str, i: int = 0, area: str | None = None,
          table: str = "input"):
    """Decode element ``i`` of a map row the way an HMI would."""
    row = map_row(ROWS, name, table, area)
    addr, n = row.element(i)
    regs = (read_ir if table == "input" else read_hr)(c, addr, n)
    if row.dtype == "UINT8":
        return regs[0] >> 8 if row.byte_in_register(i) == "high" else regs[0] & 0xFF
    return c.convert_from_registers(regs, getattr(DT, row.dtype))


# --- input registers -------------------------------------------------------------------


def test_inputs_fields_decode_to_the_buffer_values(service, mb):
    rec = service.reader("inputs")
    rec.read()
    r = rec.record
    assert value(mb, "frame", area="inputs") == 123456789012
    assert value(mb, "t_s", area="inputs") == 3.0625
    assert value(mb, "service_state", area="inputs") == int(ServiceState.SAFE)
    assert value(mb, "outputs_enabled") == 1
    assert value(mb, "brakes_released") == 0
    assert value(mb, "watchdog_tripped") == 1
    for i in (0, 3, 31, 63):
        assert value(mb, "adc_value", i) == r["adc_value"][i]
    for i in (0, 5, 15):
        assert value(mb, "rtd_angle_rad", i) == r["rtd_angle_rad"][i]
        assert value(mb, "rtd_counts", i) == r["rtd_counts"][i]
    for i in (0, 1, 6, 15):
        assert value(mb, "pio_port_bits", i) == 0xA0 + i
    assert [value(mb, "ft_counts", i) for i in range(6)] == [-1, 2, -300000, 4, 5, -6]
    crl = default_layout().slot("hc", "crl")
    assert value(mb, "hc_axes", crl * 6 + 5) == pytest.approx(-0.6, abs=0)
    # a whole array field in one read decodes element-wise (big-endian words)
    row = map_row(ROWS, "adc_value")
    regs = read_ir(mb, row.address, 4 * 31)
    got = [mb.convert_from_registers(regs[4 * k:4 * k + 4], DT.FLOAT64) for k in range(31)]
    assert got == r["adc_value"][:31].tolist()


def test_stats_fields_decode_to_the_buffer_values(mb):
    assert value(mb, "frame", area="stats") == 99
    assert value(mb, "rate_hz") == 333.25
    assert value(mb, "work_p99_us") == 71.5
    assert value(mb, "overruns") == 7
    assert map_row(ROWS, "rate_hz").address >= STATS_BASE
    assert [value(mb, "device_rate_hz", i) for i in range(3)] == [400.0, 200.0, 100.0]


def test_channel_block_by_signal_names_equals_the_client_values(shm_name, mb):
    channels = [r for r in ROWS if r.base == CHANNELS_BASE]
    assert len(channels) == 64
    assert [r.address for r in channels] == [CHANNELS_BASE + 2 * i for i in range(64)]
    regs = read_ir(mb, CHANNELS_BASE, 100) + read_ir(mb, CHANNELS_BASE + 100, 28)
    with Client.attach(shm_name) as cl:
        snap = cl.read_inputs()
        for r in channels:
            k = r.address - CHANNELS_BASE
            got = mb.convert_from_registers(regs[k:k + 2], DT.FLOAT32)
            assert got == float(np.float32(snap.value(r.name))), r.name
        assert value(mb, "elbow_pitch_angle") == float(np.float32(snap.elbow_pitch_angle))
        assert value(mb, "elbow_pitch_motor_current") == snap.elbow_pitch_motor_current
        assert value(mb, "user_if_box_inputs_lo") == snap.user_if_box_inputs_lo


def test_identification_block_and_any_unit_id(mb):
    regs = read_ir(mb, IDENT_BASE, 6, device_id=255)
    raw = b"".join(r.to_bytes(2, "big") for r in regs[:4])
    assert raw == default_layout().hash
    assert regs[4] == MAP_VERSION and regs[5] == 64
    assert read_ir(mb, IDENT_BASE, 6, device_id=0) == read_ir(mb, IDENT_BASE, 6, device_id=17)


def test_unmapped_addresses_and_other_function_codes_are_exceptions(mb):
    n_inputs = default_layout().area("inputs").body_size // 2
    rr = mb.read_input_registers(n_inputs - 2, count=4, device_id=1)  # runs past the area
    assert rr.isError() and rr.exception_code == 2
    rr = mb.read_input_registers(CHANNELS_BASE + 128, count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 2
    rr = mb.read_holding_registers(480, count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 2
    rr = mb.read_coils(0, count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 1


@pytest.mark.realtime
def test_multi_register_reads_are_never_torn(buf, shm_name, mp):
    """A writer in another process publishes inputs frames flat out, every 8-byte word
    of the body = the frame number (tests/bit3/_workers.py); every 124-register
    read (31 float64 elements of adc_volts/adc_value, decoded as their 8-byte pattern)
    through the export must show one frame only."""
    first = map_row(ROWS, "adc_volts").address
    assert map_row(ROWS, "adc_value").address == first + 256  # one run of 8-byte elements
    started, stop, result = mp.Event(), mp.Event(), mp.Queue()
    child = mp.Process(target=_workers.flat_out_writer, args=(shm_name, started, stop, 20.0, result))
    child.start()
    try:
        assert started.wait(20.0), "writer process did not start"
        with ModbusExport(buf, port=0) as ex:
            c = connect(ex.port)
            try:
                frames = set()
                for k in range(20000):  # at least 200 reads, on until they met 10 frames
                    regs = read_ir(c, first + 4 * (k % 90), 124)
                    words = {c.convert_from_registers(regs[j:j + 4], DT.UINT64)
                             for j in range(0, 124, 4)}
                    assert len(words) == 1, f"torn read: {sorted(words)[:5]}"
                    frames |= words
                    if k >= 200 and len(frames) > 10:
                        break
            finally:
                c.close()
        stop.set()
        assert result.get(timeout=20.0) > 200
        assert len(frames) > 10  # the reads really met a moving writer
    finally:
        stop.set()
        child.join(20.0)
        if child.is_alive():
            child.kill()


def test_a_writer_stuck_mid_write_answers_device_failure(service, mb):
    """A writer that died inside a write leaves the counter odd: the read gives up after
    the buffer's bounded reader time-out (0.1 s) with exception 4; other areas still read."""
    lock = service.lock("inputs")
    lock.begin()
    try:
        rr = mb.read_input_registers(0, count=4, device_id=1)
        assert rr.isError() and rr.exception_code == 4
        assert value(mb, "rate_hz") == 333.25
    finally:
        lock.end()
    assert value(mb, "frame", area="inputs") == 123456789012


# --- holding registers -----------------------------------------------------------------


def test_writes_are_refused_without_allow_writes(shm_name, mb):
    reg = map_row(ROWS, "matrix_route", "holding").address
    rr = mb.write_register(reg, 5, device_id=1)
    assert rr.isError() and rr.exception_code == 1
    jr = map_row(ROWS, "joint_rate_rad_s", "holding")
    rr = mb.write_registers(jr.address, mb.convert_to_registers(0.5, DT.FLOAT64), device_id=1)
    assert rr.isError() and rr.exception_code == 1
    with Client.attach(shm_name) as cl:
        cmd = cl.read_commands()
        assert cmd.heartbeat == 0 and cmd.matrix_route == 0
        assert cl.owners()["commands"].pid == 0  # the export never claimed the controller role
    assert value(mb, "matrix_route", table="holding") == 0  # reads are allowed


def test_writes_are_applied_with_allow_writes_and_bump_the_heartbeat(shm_name, service):
    with ModbusExport(shm_name, port=0, allow_writes=True) as ex, Client.attach(shm_name) as cl:
        assert cl.owners()["commands"].name == "modbus-export"
        c = connect(ex.port)
        try:
            mr = map_row(ROWS, "matrix_route", "holding")
            assert not c.write_register(mr.address, 0x0009, device_id=1).isError()  # cameras 1 and 2
            cmd = cl.read_commands()
            assert cmd.matrix_route == 0x0009 and cmd.heartbeat == 1
            # the rest of the record is the safe command: no arm request, rates and limits 0
            assert cmd.arm_request == 0 and not any(cmd.joint_rate_rad_s) and not any(cmd.current_limit_a)
            # keep-alive: a write to the heartbeat register only bumps it
            hb = map_row(ROWS, "heartbeat", "holding")
            before = cl.read_commands().copy()
            assert not c.write_registers(hb.address, [0, 0, 0, 7], device_id=1).isError()
            after = cl.read_commands()
            assert after.heartbeat == before.heartbeat + 1
            assert after.t_s >= before.t_s
            assert after.matrix_route == 0x0009  # other fields keep their values
            # read back through Modbus (fc 3) shows the published record
            assert value(c, "heartbeat", table="holding") == after.heartbeat
            assert value(c, "matrix_route", table="holding") == 0x0009
            assert ex.writes == 2
        finally:
            c.close()
    with Client.attach(shm_name) as cl:
        assert cl.owners()["commands"].pid == 0  # stop() released the role


def test_only_the_camera_route_is_writable_and_it_must_be_in_the_route_table(shm_name, service):
    """issue 28 item 6: arming, re-arming, rates, current limits, gripper and mode answer
    exception 2 and change nothing; a route byte outside the table answers exception 3."""
    with ModbusExport(shm_name, port=0, allow_writes=True) as ex, Client.attach(shm_name) as cl:
        c = connect(ex.port)
        try:
            f64 = c.convert_to_registers(0.5, DT.FLOAT64)
            tries = {
                "joint_rate_rad_s": f64 * 6, "gripper": f64, "current_limit_a": f64 * 7,
                "rearm_counter": c.convert_to_registers(1, DT.UINT32),
                "mode": c.convert_to_registers(1, DT.UINT32),
                "inputs_frame": [0, 0, 0, 1], "controller_frame": [0, 0, 0, 1],
            }
            for name, regs in tries.items():
                rr = c.write_registers(map_row(ROWS, name, "holding").address, regs, device_id=1)
                assert rr.isError() and rr.exception_code == 2, name
            ar = map_row(ROWS, "arm_request", "holding")
            rr = c.write_register(ar.address, 0x0100, device_id=1)  # high byte: arm_request 1
            assert rr.isError() and rr.exception_code == 2
            mr = map_row(ROWS, "matrix_route", "holding")
            rr = c.write_register(mr.address, 0x00FF, device_id=1)  # not a route of the table
            assert rr.isError() and rr.exception_code == 3
            rr = c.write_registers(mr.address, [0x0009, 0x0100], device_id=1)  # route and arm_request
            assert rr.isError() and rr.exception_code == 2
            cmd = cl.read_commands()
            assert cmd.heartbeat == 0 and cmd.arm_request == 0 and cmd.matrix_route == 0
            assert ex.writes == 0 and ex.refused == len(tries) + 3
            assert any("writes of arm_request" in r for r in ex.refusals.total), ex.refusals.total
        finally:
            c.close()


def test_bad_writes_are_refused_and_change_nothing(shm_name, service):
    with ModbusExport(service, port=0, allow_writes=True) as ex, Client.attach(shm_name) as cl:
        c = connect(ex.port)
        try:
            g = map_row(ROWS, "gripper", "holding")
            regs = c.convert_to_registers(1.5, DT.FLOAT64)
            rr = c.write_registers(g.address, regs[:2], device_id=1)  # half a float64
            assert rr.isError() and rr.exception_code == 2
            rr = c.write_registers(g.address + 1, regs, device_id=1)  # straddles two fields
            assert rr.isError() and rr.exception_code == 2
            rr = c.write_register(400, 1, device_id=1)  # no command field there
            assert rr.isError() and rr.exception_code == 2
            mr = map_row(ROWS, "matrix_route", "holding")
            rr = c.write_register(mr.address, 0x1000, device_id=1)  # a bit outside the route byte
            assert rr.isError() and rr.exception_code == 3
            cmd = cl.read_commands()
            assert cmd.heartbeat == 0 and cmd.gripper == 0.0 and cmd.matrix_route == 0
            assert ex.refused == 4 and ex.writes == 0
        finally:
            c.close()


def test_second_writer_is_refused_naming_the_owner(shm_name, service):
    with Client.attach(shm_name, writer="commands", owner="lab-controller"):
        ex = ModbusExport(shm_name, port=0, allow_writes=True)
        with pytest.raises(OwnershipError, match="lab-controller"):
            ex.start()
        assert not ex.running
        with ModbusExport(shm_name, port=0) as ro:  # read-only export does not need the role
            c = connect(ro.port)
            assert read_ir(c, IDENT_BASE, 6)[4] == MAP_VERSION
            c.close()
    with ModbusExport(shm_name, port=0, allow_writes=True):
        with pytest.raises(OwnershipError, match="modbus-export"):
            Client.attach(shm_name, writer="commands", owner="lab-controller")


# --- start-up helpers --------------------------------------------------------------------


@pytest.mark.realtime
def test_start_export_from_args(shm_name, service):
    """``pfma serve --modbus``: the export in its own process."""
    ex = start_export_from_args(shm_name, "127.0.0.1:0", False)
    try:
        assert ex.running and ex.host == "127.0.0.1" and ex.port > 0 and not ex.allow_writes
        c = connect(ex.port)
        assert value(c, "frame", area="inputs") == 123456789012
        c.close()
    finally:
        ex.stop()
    assert not ex.running


@pytest.mark.realtime
def test_a_killed_export_of_pfma_serve_is_said_and_started_again_on_its_port():
    """``pfma serve --rack fake --modbus 127.0.0.1:0``: the port it prints is the one it
    listens on; its export process SIGKILLed -> the service says so in its message queue and
    starts another on the same port, which answers; Ctrl-C stops that one with the service."""
    import os
    import re
    import signal
    import subprocess
    import sys
    import time
    import uuid
    from pathlib import Path
    from bit3.buffer import Bit3Buffer
    from bit3.ring import FrameRing
    from tests.ioservice.test_guardian import _until, children_running
    name = "pfma-test-exrs-" + uuid.uuid4().hex[:6]
    svc = subprocess.Popen([str(Path(sys.executable).with_name("pfma")), "serve", "--rack", "fake", "--buffer", name,
                            "--modbus", "127.0.0.1:0", "--duration", "60"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        line = ""
        while "Modbus TCP export on" not in line:
            line = svc.stdout.readline()
            assert line, "pfma serve ended before its export started"
        port = int(re.search(r"export on 127\.0\.0\.1:(\d+)", line).group(1))
        assert port > 0
        c = connect(port)
        assert value(c, "frame", area="inputs") >= 0
        c.close()
        first = children_running(svc.pid, b"tools.modbus_export")
        assert len(first) == 1
        os.kill(first[0], signal.SIGKILL)
        cl = Client.attach(name)
        texts: list[str] = []

        def restarted() -> bool:
            texts[:] = [m.text for m in cl.messages()]
            return any(t.startswith("Modbus export restarted: pid") for t in texts)
        _until(restarted, "a new export")
        cl.close()
        assert any(t.startswith(f"Modbus export (pid {first[0]}) ended (killed by SIGKILL): Modbus clients get no "
                                "answers until it is back; restarting it") for t in texts), texts
        second = children_running(svc.pid, b"tools.modbus_export")
        assert len(second) == 1 and second != first
        c = connect(port)  # the same port
        f1 = value(c, "frame", area="inputs")
        time.sleep(0.05)
        assert value(c, "frame", area="inputs") > f1  # the service's frames, live
        c.close()
        svc.send_signal(signal.SIGINT)
        assert svc.wait(30) == 0
        assert not Path(f"/proc/{second[0]}").exists() or b"Z" in Path(f"/proc/{second[0]}/stat").read_bytes()
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait(30)
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)


def test_parse_host_port():
    assert parse_host_port("0.0.0.0:502") == ("0.0.0.0", 502)
    assert parse_host_port(":5020") == ("127.0.0.1", 5020)
    assert parse_host_port("1502") == ("127.0.0.1", 1502)
    assert parse_host_port("[::1]:5020") == ("::1", 5020)
    for bad in ("localhost:http", "127.0.0.1:70000", "[::1]5020", ""):
        with pytest.raises(ConfigError, match="--modbus"):
            parse_host_port(bad)


def test_busy_port_and_missing_buffer_are_clear(shm_name, service):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        with pytest.raises(ModbusExportError, match=f"127.0.0.1:{port}"):
            ModbusExport(service, port=port, allow_writes=True).start()
    with Client.attach(shm_name) as cl:  # the failed start released the controller role
        assert cl.owners()["commands"].pid == 0
    with pytest.raises(Exception, match="no Bit3 buffer 'pfma_no_such_buffer'"):
        ModbusExport("pfma_no_such_buffer", port=0).start()


# --- the generated map ---------------------------------------------------------------------


def test_map_covers_every_field_without_overlap():
    lay = default_layout()
    for area, table in (("inputs", "input"), ("stats", "input"), ("commands", "holding")):
        names = [f.name for f in lay.fields if f.area == area]
        rows = [r for r in ROWS if r.area == area and r.table == table and r.index is None]
        assert [r.name for r in rows] == names
        owner: dict[int, str] = {}
        for r in rows:
            if r.dtype == "UINT8":
                continue  # byte fields share registers by design
            for a in range(r.address, r.address + r.count):
                assert a not in owner, f"{r.name} overlaps {owner[a]} at {a}"
                owner[a] = r.name
    assert [r.name for r in ROWS if r.table == "holding" and r.writable] == ["matrix_route"]


def test_committed_map_doc_is_the_generated_one():
    assert MAP_DOC_PATH.read_text() == modbus_map_markdown(), (
        "docs/modbus-map.md is stale; regenerate with "
        "tools.modbus_export.write_modbus_map_doc()")


def test_an_export_whose_starter_died_before_reading_its_ready_line_stops_without_a_traceback(service, shm_name):
    """The kill matrix's case (SIGKILL of `pfma serve` at start-up, under a CPU hog): the
    export child's ready line meets a pipe nobody reads. One warning, exit 1, no traceback."""
    import os
    import subprocess
    import sys
    r, w = os.pipe()
    os.close(r)  # the starter is gone: nobody will ever read
    try:
        p = subprocess.run([sys.executable, "-m", "tools.modbus_export", "--buffer", shm_name, "--listen",
                            "127.0.0.1:0"], stdout=w, stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        os.close(w)
    assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr
    assert "the process that started it is gone; stopping" in p.stderr
