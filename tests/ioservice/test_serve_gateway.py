"""``pfma serve`` over a real Modbus TCP gateway on 127.0.0.1 (``fakes.modbus_gateway``).

Nothing is timed: the gateway's reply delay sets a lower bound on what a frame's bus work
costs (enough to refuse the 320 Hz schedule whatever the host), the waits are bounded,
and the assertions read exit codes, messages and the buffer.
"""

from __future__ import annotations

import os
import threading
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import ServiceState
from fakes.modbus_gateway import ModbusGateway
from fakes.world import FakeWorld
from pfma.clock import MonotonicClock
from tests.drivers.bus.tinybus import quiet_pymodbus
from tools.cli import main

pytestmark = pytest.mark.realtime

#: bound on any wait in these tests
WAIT_S = 30.0


@pytest.fixture
def buffer_name():
    name = "pfma-gw-" + uuid.uuid4().hex[:6]
    yield name
    Bit3Buffer.unlink(name)


def _gateway(reply_delay_s: float = 0.0) -> ModbusGateway:
    return ModbusGateway(FakeWorld(clock=MonotonicClock()).bus, reply_delay_s=reply_delay_s)


def test_a_schedule_the_gateway_cannot_keep_is_refused_with_the_figures(buffer_name, capsys):
    # every request answered 2 ms late: the busiest 320 Hz frame (DAC, two resolver boards,
    # ADC: at least four requests) needs at least 8 ms of a 3.125 ms frame
    with quiet_pymodbus(), _gateway(reply_delay_s=0.002) as gw:
        url = f"{gw.url}?timeout=1"
        assert main(["serve", "--bus", url, "--buffer", buffer_name, "--duration", "5"]) == 1
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert lines[0].startswith(f"pfma serve: serial lines cannot cross the register gateway "
                               f"127.0.0.1:{gw.port}")
    assert lines[1].startswith(f"pfma serve: the bus {url} cannot keep the schedule of resolvers "
                               f"160 Hz, ADC 160 Hz, DAC 320 Hz in 320 Hz frames: per task dac ")
    assert "; the busiest frame (dac+rtd+adc) needs " in lines[1]
    assert len(lines) == 2 and "Traceback" not in cap.err
    assert "stopped after" not in cap.out  # it never ran
    assert not os.path.exists(f"/dev/shm/{buffer_name}")  # a refused service leaves no buffer


def test_slow_runs_a_named_slower_schedule_over_the_gateway(buffer_name, capsys):
    with quiet_pymodbus(), _gateway(reply_delay_s=0.002) as gw:
        url = f"{gw.url}?timeout=1"
        assert main(["serve", "--bus", url, "--buffer", buffer_name, "--duration", "1",
                     "--schedule", "slow", "--watchdog-ms", "1000"]) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first.startswith("pfma serve: running resolvers ")
    assert f" Hz frames over {url}: the bus costs " in first
    assert "(it could not keep resolvers 160 Hz, ADC 160 Hz, DAC 320 Hz in 320 Hz frames: " in first
    c = Client.attach(buffer_name)
    try:
        assert c.read_inputs().service_state == ServiceState.STOPPED
        assert any(m.text.startswith("slow bus: rtd ") for m in c.messages())
    finally:
        c.close()


def test_a_gateway_that_stops_answering_ends_the_run_safe_and_names_it(buffer_name, capsys):
    silenced = threading.Event()
    with quiet_pymodbus(), _gateway() as gw:
        def silence_when_running() -> None:
            """Once the service has published 20 frames (bounded wait), the gateway goes quiet."""
            stop = threading.Event()
            for _ in range(int(WAIT_S / 0.05)):
                try:
                    c = Client.attach(buffer_name)
                except Exception:  # noqa: BLE001 - not created yet
                    stop.wait(0.05)
                    continue
                try:
                    while c.read_inputs().frame < 20 and not stop.wait(0.05):
                        pass
                finally:
                    c.close()
                break
            gw.silent = True
            silenced.set()

        t = threading.Thread(target=silence_when_running, daemon=True)
        t.start()
        rc = main(["serve", "--bus", gw.url, "--buffer", buffer_name, "--duration", "60",
                   "--schedule", "slow", "--watchdog-ms", "100"])
        t.join(WAIT_S)
    assert silenced.is_set()
    assert rc == 1
    cap = capsys.readouterr()
    assert f"pfma serve: the bus {gw.url} stopped answering: no register transaction succeeded for " in cap.err
    assert f"gateway 127.0.0.1:{gw.port}" in cap.err
    assert "Traceback" not in cap.err
    c = Client.attach(buffer_name)
    try:
        s = c.read_inputs()
        assert s.service_state == ServiceState.STOPPED and not s.outputs_enabled
        assert s.frame < 60 * 320  # it ended on the lost bus, not at the end of --duration
        texts = [m.text for m in c.messages()]
        assert f"bus lost: {gw.url}" in texts
        # the DAC did not take the 0 V: never called safe (issue 28 item 5)
        assert any(t.startswith("outputs NOT known safe: DAC not answering") for t in texts)
        assert not any("outputs safe" in t for t in texts)
    finally:
        c.close()
