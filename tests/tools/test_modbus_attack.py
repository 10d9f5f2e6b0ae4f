"""The Modbus export under attack (issue 20 item 2), with raw sockets on 127.0.0.1.

Every function code outside the map answers exception 1; malformed, truncated, oversized
and pipelined requests; connection floods and readers that take no answers are bounded;
refused requests are counted and said in one log line per interval, never a traceback.
The export runs in-process (its server thread) on an ephemeral port, except in the tests
of :class:`ExportProcess` (``pfma serve --modbus``: its own process), marked realtime.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import struct
import subprocess
import sys
import time

import pytest

from bit3.layout import default_layout
from tools.modbus_export import (
    ExportLimits, ModbusExport, ModbusExportError, refusal_log, start_export_from_args,
)

#: function codes the map serves (docs/modbus-map.md)
MAPPED = {3, 4, 6, 16}
#: the codes issue 20 found answered normally by the pymodbus server (its diagnostics)
PYMODBUS_ANSWERED = (7, 8, 11, 12, 17, 20, 21, 24, 43)
#: a bound on every wait for the export (generous: a loaded host); never asserted as a time
WAIT_S = 10.0


def adu(pdu: bytes, tid: int = 1, unit: int = 1, proto: int = 0, length: int | None = None) -> bytes:
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1 if length is None else length, unit) + pdu


def read_ir(address: int = 0, count: int = 1) -> bytes:
    return struct.pack(">BHH", 4, address, count)


def recv_exact(s: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = s.recv(n - len(out))
        if not chunk:
            raise ConnectionError(f"closed after {len(out)} of {n} bytes")
        out += chunk
    return bytes(out)


def answer(s: socket.socket) -> tuple[int, bytes]:
    """(transaction id, PDU) of the next answer."""
    head = recv_exact(s, 7)
    tid, proto, length, _unit = struct.unpack(">HHHB", head)
    assert proto == 0
    return tid, recv_exact(s, length - 1)


def closed_by_peer(s: socket.socket) -> bool:
    """The export closed this connection (EOF or reset) within WAIT_S."""
    s.settimeout(WAIT_S)
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


@pytest.fixture
def service(buf):
    buf.claim("service", "test-service")
    w = buf.writer("inputs")
    w.record["frame"] = 77
    w.publish()
    return buf


@pytest.fixture
def caplog_export(caplog):
    caplog.set_level(logging.DEBUG)
    return caplog


def start(buf, **limits) -> ModbusExport:
    return ModbusExport(buf, port=0, limits=ExportLimits(**limits) if limits else None).start()


def connect(ex: ModbusExport, rcvbuf: int | None = None) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:  # before connect: a small TCP window
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(WAIT_S)
    s.connect(("127.0.0.1", ex.port))
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def no_traceback(caplog) -> None:
    assert "Traceback" not in caplog.text
    assert not [r for r in caplog.records if r.exc_info], [r.getMessage() for r in caplog.records if r.exc_info]


# --- function codes ------------------------------------------------------------------------


def test_every_function_code_outside_the_map_answers_exception_1(service, caplog_export):
    ex = start(service)
    try:
        with connect(ex) as s:
            for fc in range(256):
                if fc in MAPPED:
                    continue
                s.sendall(adu(bytes([fc, 0, 0, 0, 1]), tid=fc))
                tid, pdu = answer(s)
                assert (tid, pdu) == (fc, bytes([fc | 0x80, 1])), (fc, pdu.hex())
            # the connection still serves a good read after 252 refusals
            s.sendall(adu(read_ir(0, 4), tid=999))
            tid, pdu = answer(s)
            assert tid == 999 and pdu[:2] == b"\x04\x08" and len(pdu) == 10
    finally:
        ex.stop()
    assert ex.refused == 252 and ex.requests == 253
    no_traceback(caplog_export)


@pytest.mark.parametrize("fc", PYMODBUS_ANSWERED)
def test_the_codes_pymodbus_answered_itself_are_exception_1_with_any_body(service, fc):
    """Function codes 7, 8, 11, 12, 17, 20, 21, 24, 43 with the bodies pymodbus's own
    diagnostics take (empty, sub-function + data, MEI type)."""
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        for body in (b"", b"\x00\x00\x00\x01", b"\x0e\x01\x00"):
            s.sendall(adu(bytes([fc]) + body, tid=fc))
            assert answer(s) == (fc, bytes([fc | 0x80, 1]))


def test_function_codes_0x81_to_0xff_are_counted_and_summarised_not_logged_per_request(service, caplog_export):
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        for k in range(600):
            fc = 0x81 + k % 0x7F
            s.sendall(adu(bytes([fc, 0, 0, 0, 1]), tid=k))
            assert answer(s) == (k, bytes([fc, 1]))
    lines = [r for r in caplog_export.records
             if r.name == "tools.modbus_export" and "refused in the last" in r.getMessage()]
    # the first refusal is said at once, the rest at stop: two lines, not 600
    assert len(lines) == 2, [r.getMessage() for r in lines]
    assert "600" in lines[-1].getMessage()  # the total since the start
    assert ex.refused == 600
    no_traceback(caplog_export)


# --- malformed, truncated, oversized ----------------------------------------------------------


@pytest.mark.parametrize("pdu,code", [
    (b"\x04\x00\x00\x00", 3),                 # fc 4 one byte short
    (b"\x04\x00\x00\x00\x01\x00", 3),         # fc 4 one byte long
    (b"\x04\x00\x00\x00\x00", 3),             # count 0
    (b"\x04\x00\x00\x00\x7e", 3),             # count 126
    (b"\x03\xff\xff\x00\x7d", 2),             # past the end of the address space
    (b"\x04\x75\x30\x00\x07", 2),             # runs past the identification block
    (b"\x06\x00\x00", 3),                     # fc 6 short
    (b"\x10\x00\x00\x00\x02\x03\x00\x00\x00", 3),  # fc 16: byte count is not 2 x count
    (b"\x10\x00\x00\x00\x7c\xf8" + bytes(10), 3),  # fc 16: 124 registers (limit 123)
    (b"\x06\x00\x00\x00\x01", 1),             # a well-formed write to a read-only export
], ids=["fc4-short", "fc4-long", "count-0", "count-126", "past-65535", "past-ident", "fc6-short",
        "fc16-bytecount", "fc16-124", "write-read-only"])
def test_malformed_requests_of_mapped_codes_answer_an_exception(service, pdu, code):
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        s.sendall(adu(pdu, tid=5))
        assert answer(s) == (5, bytes([pdu[0] | 0x80, code]))
        s.sendall(adu(read_ir(), tid=6))  # and the connection goes on
        assert answer(s)[0] == 6


def test_a_request_in_pieces_is_answered_once_whole(service):
    """A truncated MBAP header or PDU waits for the rest (TCP may cut anywhere)."""
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        req = adu(read_ir(0, 4), tid=42)
        for b in req:  # one byte per segment
            s.sendall(bytes([b]))
        tid, pdu = answer(s)
        assert tid == 42 and pdu[:2] == b"\x04\x08"
        # a header cut short and the connection dropped: nothing breaks, others go on
        with connect(ex) as t:
            t.sendall(req[:5])
        s.sendall(adu(read_ir(), tid=43))
        assert answer(s)[0] == 43


@pytest.mark.parametrize("length", [0, 1, 255, 0xFFFF])
def test_an_mbap_length_outside_2_to_254_closes_that_connection_only(service, length, caplog_export):
    with ModbusExport(service, port=0) as ex, connect(ex) as good, connect(ex) as bad:
        bad.sendall(struct.pack(">HHHB", 9, 0, length, 1) + b"\x04" * 300)
        assert closed_by_peer(bad)
        good.sendall(adu(read_ir(), tid=10))
        assert answer(good)[0] == 10
        assert any(k.startswith("malformed MBAP header") for k in ex.refusals.total)
    no_traceback(caplog_export)


def test_a_protocol_id_other_than_0_is_not_answered_and_framing_holds(service):
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        s.sendall(adu(read_ir(), tid=1, proto=7) + adu(read_ir(), tid=2))
        assert answer(s)[0] == 2  # the first was skipped by its length, the second answered
        assert ex.refusals.total == {"requests with a protocol id other than 0 (not Modbus; not answered)": 1}


# --- pipelining ----------------------------------------------------------------------------


def test_two_requests_in_one_segment_are_both_answered_in_order(service):
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        s.sendall(adu(read_ir(0, 4), tid=100) + adu(read_ir(30000, 6), tid=101))
        t1, p1 = answer(s)
        t2, p2 = answer(s)
        assert (t1, t2) == (100, 101)
        assert p1[:2] == b"\x04\x08" and p2[:2] == b"\x04\x0c"
        lay = default_layout()
        assert p2[2:10] == lay.hash  # the identification block: the layout hash


def test_a_hundred_pipelined_requests_mixed_with_bad_ones_are_all_answered_in_order(service):
    reqs = []
    for k in range(100):
        pdu = read_ir(k % 8, 2) if k % 3 else bytes([0x2B, 0x0E, 0x01, 0x00])  # every third: fc 43
        reqs.append(adu(pdu, tid=1000 + k))
    with ModbusExport(service, port=0) as ex, connect(ex) as s:
        s.sendall(b"".join(reqs))
        for k in range(100):
            tid, pdu = answer(s)
            assert tid == 1000 + k
            if k % 3 == 0:
                assert pdu == b"\xab\x01"  # fc 43 refused
            else:
                assert pdu[:2] == b"\x04\x04" and len(pdu) == 6  # 2 registers read


# --- floods and slow readers -----------------------------------------------------------------


@pytest.mark.realtime
def test_connections_over_the_limit_are_closed_and_the_others_served(service):
    ex = start(service, max_connections=3)
    try:
        conns = [connect(ex) for _ in range(3)]
        for k, c in enumerate(conns):  # all three are served (and so registered)
            c.sendall(adu(read_ir(), tid=k))
            assert answer(c)[0] == k
        extra = connect(ex)  # the kernel accepts it; the export closes it at once
        assert closed_by_peer(extra)
        extra.close()
        for k, c in enumerate(conns):
            c.sendall(adu(read_ir(), tid=10 + k))
            assert answer(c)[0] == 10 + k
        conns.pop().close()
        deadline = time.monotonic() + WAIT_S  # the export sees the close, then a slot is free
        while ex.stats()["connections_open"] > 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        with connect(ex) as again:
            again.sendall(adu(read_ir(), tid=77))
            assert answer(again)[0] == 77
        for c in conns:
            c.close()
        assert ex.refusals.total == {"connections over the limit of 3 (closed)": 1}
    finally:
        ex.stop()


@pytest.mark.realtime
def test_a_connection_flood_is_bounded_counted_and_said_in_one_line(service, caplog_export):
    """40 connections at once against a limit of 8, then 60 connect-and-drop cycles as
    fast as the client can (fewer than the listen backlog of 64: more only make the kernel
    drop SYNs, which costs the test seconds and proves nothing of the export): 8 served,
    32 closed by the export, the slots given back; one summary line at the first refusal
    and one at stop; the export still answers."""
    ex = start(service, max_connections=8)
    try:
        conns = [connect(ex) for _ in range(40)]
        served, closed = [], []
        for k, c in enumerate(conns):
            try:
                c.sendall(adu(read_ir(), tid=k))
                c.settimeout(WAIT_S)
                served.append(answer(c)[0] == k)
            except (ConnectionError, OSError):
                closed.append(k)
        assert sum(served) == 8 and len(closed) == 32
        for c in conns:
            c.close()
        for _ in range(60):
            connect(ex).close()
        over = "connections over the limit of 8 (closed)"
        deadline = time.monotonic() + WAIT_S  # every one of the 100 seen, and every slot free
        while (ex.connections_total + ex.refusals.total.get(over, 0) < 100
               or ex.stats()["connections_open"]) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert ex.connections_total + ex.refusals.total[over] == 100
        assert ex.refusals.total[over] >= 32
        with connect(ex) as s:
            s.sendall(adu(read_ir(), tid=7))
            assert answer(s)[0] == 7
    finally:
        ex.stop()
    lines = [r for r in caplog_export.records if "refused in the last" in r.getMessage()]
    assert len(lines) == 2, [r.getMessage() for r in lines]
    no_traceback(caplog_export)


@pytest.mark.realtime
def test_a_reader_that_takes_no_answers_is_held_to_its_buffers_and_then_gets_them_all(service):
    """40,000 pipelined 125-register reads (10 MB of answers) from a client that reads
    nothing: the export stops answering (and reading) it once its answers fill
    ``out_buffer_bytes`` beyond what the kernel's socket buffers hold; its memory for the
    connection stays within the limits; then the client reads every answer, in order."""
    import threading
    lim = dict(in_buffer_bytes=512, out_buffer_bytes=2048)
    ex = start(service, **lim)
    n_req = 40000
    try:
        s = connect(ex, rcvbuf=4096)
        data = b"".join(adu(read_ir(0, 125), tid=k & 0xFFFF) for k in range(n_req))
        sender = threading.Thread(target=s.sendall, args=(data,), daemon=True)
        sender.start()  # blocks once the export stops reading: a thread
        deadline = time.monotonic() + WAIT_S
        conn = None
        while time.monotonic() < deadline:
            conn = next(iter(ex._server._server.connections), None)
            if conn is not None and conn._paused:
                break
            time.sleep(0.01)
        assert conn is not None and conn._paused  # held: not reading, not answering
        assert ex.requests < n_req
        assert conn.transport.get_write_buffer_size() <= lim["out_buffer_bytes"] + 260
        assert conn._n <= lim["in_buffer_bytes"]
        for k in range(n_req):
            tid, pdu = answer(s)
            assert tid == k & 0xFFFF and len(pdu) == 252
        sender.join(WAIT_S)
        assert not sender.is_alive()
        s.close()
        assert ex.requests == n_req and ex.refused == 0
    finally:
        ex.stop()


@pytest.mark.realtime
def test_an_idle_connection_is_closed_after_the_idle_time_out(service):
    ex = start(service, idle_timeout_s=0.3)
    try:
        with connect(ex) as s:
            s.sendall(adu(read_ir(), tid=1))
            assert answer(s)[0] == 1
            assert closed_by_peer(s)  # then silence: closed
        assert ex.refusals.total == {"connections closed after 0.3 s idle": 1}
    finally:
        ex.stop()


# --- the refusal summary -------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_refusals_are_said_at_once_then_at_most_once_per_interval():
    clock = FakeClock()
    logger = logging.getLogger("test.refusals")
    lines: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record) -> None:
            lines.append(record.getMessage())
    h = Keep()
    logger.addHandler(h)
    try:
        rl = refusal_log("127.0.0.1:5020", interval_s=60.0, clock=clock, logger=logger)
        rl.note("requests of function code 0x81 (not in the map)")
        assert len(lines) == 1 and "requests of function code 0x81 (not in the map): 1" in lines[0]
        for k in range(1, 60):
            clock.t = 1000.0 + k
            rl.note("requests of function code 0x81 (not in the map)")
            rl.note(f"requests of function code {k} (not in the map)")
            rl.tick()
        assert len(lines) == 1  # 59 s: nothing more said
        clock.t = 1060.0
        rl.tick()
        assert len(lines) == 2
        assert "requests of function code 0x81 (not in the map): 59" in lines[1]
        assert "54 more of 54 other kinds" in lines[1] and "totals since start: 119" in lines[1]
        rl.tick()
        rl.flush()
        assert len(lines) == 2  # nothing pending
        rl.note("connections over the limit of 16 (closed)")
        assert len(lines) == 2  # within the interval of the last line: held
        rl.flush()
        assert len(lines) == 3 and "connections over the limit of 16 (closed): 1" in lines[2]
    finally:
        logger.removeHandler(h)


# --- the export process (pfma serve --modbus) -----------------------------------------------------


@pytest.mark.realtime
def test_pfma_serve_runs_the_export_in_its_own_process(shm_name, service):
    ex = start_export_from_args(shm_name, "127.0.0.1:0", False)
    try:
        assert ex.running and ex.pid != os.getpid() and ex.port > 0
        with socket.create_connection(("127.0.0.1", ex.port), timeout=WAIT_S) as s:
            s.sendall(adu(read_ir(0, 4), tid=3) + adu(bytes([0x81, 0, 0, 0, 1]), tid=4))
            tid, pdu = answer(s)
            assert tid == 3 and struct.unpack(">Q", pdu[2:10])[0] != 0  # frame 77, big-endian words
            assert answer(s) == (4, b"\x81\x01")
    finally:
        ex.stop()
    assert not ex.running


@pytest.mark.realtime
def test_the_export_process_says_why_it_cannot_start_in_one_line(service):
    with pytest.raises(ModbusExportError, match="no Bit3 buffer 'pfma_no_such_buffer'"):
        start_export_from_args("pfma_no_such_buffer", "127.0.0.1:0", False)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        with pytest.raises(ModbusExportError, match=f"cannot listen on 127.0.0.1:{port}"):
            start_export_from_args(service.name, f"127.0.0.1:{port}", False)


@pytest.mark.realtime
def test_the_export_process_exits_when_its_service_is_killed(shm_name, service):
    """The parent (here a stand-in for pfma serve) dies by SIGKILL: the export goes too."""
    code = ("import sys, time; from tools.modbus_export import start_export_from_args; "
            f"ex = start_export_from_args({shm_name!r}, '127.0.0.1:0', False); "
            "print(ex.pid, flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        line = parent.stdout.readline()
        assert line.strip().isdigit(), line
        pid = int(line)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(WAIT_S)
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            try:
                with open(f"/proc/{pid}/stat") as f:
                    if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                        break  # exited (a zombie of init's until reaped)
            except FileNotFoundError:
                break
            time.sleep(0.05)
        else:
            os.kill(pid, signal.SIGKILL)
            pytest.fail(f"export process {pid} outlived its parent by {WAIT_S} s")
    finally:
        if parent.poll() is None:
            parent.kill()
        parent.stdout.close()


@pytest.mark.realtime
@pytest.mark.skipif(os.geteuid() != 0 or (os.cpu_count() or 1) < 2,
                    reason="SCHED_FIFO needs root; moving off the pinned CPU needs two CPUs")
def test_the_export_process_runs_below_a_realtime_service(shm_name, service):
    """Under ``pfma serve --realtime`` (SCHED_FIFO, pinned to the last CPU) the export
    process does not inherit the real-time class or the CPU: time-sharing, nice +5,
    on the other CPUs."""
    last = (os.cpu_count() or 2) - 1
    code = ("import os, time; from tools.modbus_export import start_export_from_args; "
            f"os.sched_setaffinity(0, {{{last}}}); "
            "os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10)); "
            f"ex = start_export_from_args({shm_name!r}, '127.0.0.1:0', False); "
            "print(ex.pid, os.getpriority(os.PRIO_PROCESS, 0), flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        pid, parent_nice = map(int, parent.stdout.readline().split())
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER
        assert last not in os.sched_getaffinity(pid)
        assert os.getpriority(os.PRIO_PROCESS, pid) == parent_nice + 5
    finally:
        parent.kill()  # the export follows its parent (PR_SET_PDEATHSIG)
        parent.wait(WAIT_S)
        parent.stdout.close()
