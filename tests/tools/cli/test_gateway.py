"""``pfma gateway``: a real process serving the simulated rack over Modbus TCP on 127.0.0.1.

Nothing here is timed: the waits are bounded (a process that never prints its first line
fails the test after 30 s) and the assertions count words, requests and messages.
"""

from __future__ import annotations

import os
import re
import selectors
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.bus.modbus import ModbusTcpBus
from fakes.world import FakeWorld
from pfma.clock import SimClock
from tools.cli import main

ROOT = Path(__file__).resolve().parents[3]
#: bound on any wait for the gateway process (a hung start fails the test, it never hangs it)
WAIT_S = 30.0


def _first_line(proc: subprocess.Popen) -> str:
    """The gateway's start-up line, waiting at most WAIT_S."""
    assert proc.stdout is not None
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(WAIT_S):
        proc.kill()
        pytest.fail(f"pfma gateway printed nothing within {WAIT_S:g} s")
    return proc.stdout.readline()


@pytest.fixture
def gateway_process():
    proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "gateway", "--listen", "127.0.0.1:0"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = _first_line(proc)
        m = re.search(r"modbus://127\.0\.0\.1:(\d+)", line)
        assert m, f"no gateway URL in the start-up line: {line!r}"
        yield proc, int(m.group(1))
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(WAIT_S)


@pytest.mark.realtime
def test_gateway_answers_the_fake_racks_registers_and_stops_on_sigterm(gateway_process):
    proc, port = gateway_process
    local = FakeWorld(clock=SimClock()).bus  # the same simulated rack, in this process
    # registers whose values do not depend on time: the ADC's board id, the resolver
    # boards' status words (reference present, no faults)
    addrs = [0xC006, 0x0108, 0x0208]
    with ModbusTcpBus("127.0.0.1", port, timeout=WAIT_S) as bus:
        assert [bus.read16(a) for a in addrs] == [local.read16(a) for a in addrs]
        assert bus.read16(0xC006) == 0x0611
        assert bus.read_block16(0xC006, 1) == [0x0611]
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 0, err
    assert err == ""
    assert out.strip().splitlines() == ["pfma gateway: stopped after 5 requests"]


def test_gateway_on_a_busy_port_is_one_message_and_exit_1(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["gateway", "--listen", f"127.0.0.1:{port}", "--duration", "1"]) == 1
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.strip().splitlines() == [
        f"pfma gateway: cannot listen on 127.0.0.1:{port}: Address already in use"]


@pytest.mark.parametrize("listen, says", [("5020", "expected HOST:PORT"),
                                          ("127.0.0.1:http", "is not a number"),
                                          ("127.0.0.1:70000", "not 0..65535")])
def test_a_bad_listen_address_is_one_message(listen, says, capsys):
    assert main(["gateway", "--listen", listen, "--duration", "1"]) == 2  # a usage mistake
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err and err.startswith("pfma gateway: ")
