"""Modbus requests to a running controller (issue 28 item 6; docs/modbus-map.md,
"Requests to the controller"): a Modbus master on loopback TCP (pymodbus, as a hostile
client would use it) posts HALT and CAMERA ROUTE through the controller's world model,
which validates and answers them; everything that would arm or move the arm is refused
with an exception and changes nothing.

The whole stack runs in simulated time (SystemSimulator, its world model in shared
memory); only the loopback TCP round trips are real.
"""

from __future__ import annotations

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from bit3.layout import ServiceState
from controller.layers import Request, Response
from controller.routes import route_request_arg
from tools.modbus_export import REQUESTS_BASE, ModbusExport, map_row, register_map

pytestmark = pytest.mark.realtime  # a TCP server thread and a shared-memory world model


@pytest.fixture
def system(monkeypatch):
    from controller.worldmodel import WorldModel
    from sim.system import SystemSimulator
    from tests.controller import _wm_support as sup
    monkeypatch.delenv("PFMA_WM_KEY", raising=False)
    name = sup.unique_name()
    s = SystemSimulator(wm_name=name)
    s.step(10)
    yield s, name
    s.close()
    WorldModel.remove_segment(name)


def _answer(c) -> list[int]:
    rr = c.read_holding_registers(REQUESTS_BASE, count=5, device_id=1)
    assert not rr.isError()
    return list(rr.registers)


def test_a_modbus_master_posts_a_camera_route_the_controller_applies(system):
    sim, wm = system
    with ModbusExport(sim.name, port=0, allow_writes=True, requests_wm=wm, layout=sim.rig.layout) as ex:
        c = ModbusTcpClient("127.0.0.1", port=ex.port, timeout=2, retries=0)
        assert c.connect()
        try:
            arg = route_request_arg(1, 3)
            assert not c.write_registers(REQUESTS_BASE, [Request.ROUTE, arg], device_id=1).isError()
            kind, got_arg, seq, code, answered = _answer(c)
            assert (kind, got_arg) == (Request.ROUTE, arg) and seq >= 1
            for _ in range(400):  # the controller answers at its frames (simulated)
                sim.step(1)
                kind, got_arg, seq, code, answered = _answer(c)
                if answered == seq and code not in (Response.NONE, Response.IN_PROGRESS):
                    break
            assert (answered, code) == (seq, Response.COMPLETE)
            sim.step(72)  # three PIO periods: the service applies the route
            assert sim.world.bus["pio_video"].switcher.monitors == (3, 0)
            assert ex.posted == 1
            # HALT: posted, and answered by the controller (it validates: here, before power-up)
            assert not c.write_registers(REQUESTS_BASE, [Request.HALT, 0], device_id=1).isError()
            seq = _answer(c)[2]
            for _ in range(400):
                sim.step(1)
                _k, _a, seq, code, answered = _answer(c)
                if answered == seq and code not in (Response.NONE, Response.IN_PROGRESS):
                    break
            assert answered == seq and code in (Response.COMPLETE, Response.REFUSED)
            assert ex.posted == 2
            assert sim.client.read_inputs().service_state != ServiceState.ARMED
        finally:
            c.close()
    # the export never held the command area: the controller does
    assert sim.client.owners()["commands"].name == "controller"


@pytest.mark.parametrize("kind", [Request.POWER_UP, Request.RESUME, Request.STEP, Request.ERROR_RESET,
                                  Request.POWER_DOWN, 99])
def test_requests_that_arm_or_move_are_refused_with_an_exception(system, kind):
    sim, wm = system
    rows = register_map(sim.rig.layout)
    with ModbusExport(sim.name, port=0, allow_writes=True, requests_wm=wm, layout=sim.rig.layout) as ex:
        c = ModbusTcpClient("127.0.0.1", port=ex.port, timeout=2, retries=0)
        assert c.connect()
        try:
            seq0 = int(sim.updown_rt.wm.get("ui.request_seq"))
            rr = c.write_registers(REQUESTS_BASE, [kind, 1], device_id=1)
            assert rr.isError() and rr.exception_code == 3
            # the command area is the controller's: arming through it answers exception 2
            ar = map_row(rows, "arm_request", "holding")
            rr = c.write_register(ar.address, 0x0100, device_id=1)
            assert rr.isError() and rr.exception_code == 2
            jr = map_row(rows, "joint_rate_rad_s", "holding")
            rr = c.write_registers(jr.address, c.convert_to_registers(0.4, c.DATATYPE.FLOAT64), device_id=1)
            assert rr.isError() and rr.exception_code == 2
            sim.step(200)
            assert int(sim.updown_rt.wm.get("ui.request_seq")) == seq0  # nothing was posted
            assert ex.posted == 0 and ex.refused == 3
        finally:
            c.close()
    s = sim.client.read_inputs()
    assert s.service_state != ServiceState.ARMED
    assert np.all(np.asarray(sim.world.bus["dac"].output_volts_all()) == 0.0)


def test_a_request_without_a_controller_is_exception_4(shm_name, caplog):
    from bit3.buffer import Bit3Buffer
    buf = Bit3Buffer.create(shm_name)
    buf.claim("service", "test-service")
    buf.writer("inputs").publish()
    try:
        with ModbusExport(shm_name, port=0, allow_writes=True, requests_wm="pfma-no-such-wm-28") as ex:
            c = ModbusTcpClient("127.0.0.1", port=ex.port, timeout=2, retries=0)
            assert c.connect()
            try:
                rr = c.write_registers(REQUESTS_BASE, [Request.HALT, 0], device_id=1)
                assert rr.isError() and rr.exception_code == 4
            finally:
                c.close()
        assert "request HALT not posted" in caplog.text and "Traceback" not in caplog.text
    finally:
        buf.close()


def test_pfma_serve_passes_the_world_model_to_the_export_process():
    from tools.modbus_export import ExportProcess
    argv = ExportProcess("pfma", requests_wm="pfma_wm").argv()
    assert argv[argv.index("--requests") + 1] == "pfma_wm" and "--writes" not in argv
    assert "--requests" not in ExportProcess("pfma", allow_writes=True).argv()
