"""Simulated or real, as the service's buffer says (issue 18: the console said "rack:
unknown" over every live buffer): the service's SIMULATED flag in its Bit3 owner slots
(``HeaderInfo.rack_kind``), shown by the console's World Status, ``pfma monitor`` and
``pfma read``. Simulated time; the rigs' services are in this process."""

from __future__ import annotations

import json
import uuid

import pytest

from bit3.client import Client
from sim.rig import SimRig
from tools.cli import main
from tools.cli.monitor import SIMULATED_LINE
from tools.console import view
from tools.console.app import ConsoleApp
from tools.console.control import ControllerLink
from tests.tools.console._pilot import frames, run_app


@pytest.fixture(scope="module")
def real_rig():
    """A service on the fake boards told its bus is hardware: what a service on a real bus publishes."""
    rig = SimRig(name="pfma-real-" + uuid.uuid4().hex[:8], service_kw={"simulated": False})
    rig.run(0.05)
    yield rig
    rig.close()


@pytest.fixture(scope="module")
def sim_rig():
    rig = SimRig(name="pfma-simr-" + uuid.uuid4().hex[:8])
    rig.run(0.05)
    yield rig
    rig.close()


def test_the_console_over_a_live_buffer_shows_what_the_service_says(sim, reader):
    app = ConsoleApp(view.Sources(reader, sim.rt.wm), ControllerLink(sim.rt.wm), auto_refresh=False)

    async def body(pilot):
        frames(sim, app, 4)
        await pilot.pause()
        assert app.sources.rack == "simulated"
        assert app.area_text("world").startswith("SIMULATED RACK: the boards, the arm and the sensors are fakes")
    run_app(app, body)


def test_a_hardware_bus_is_not_called_simulated(sim, real_rig):
    client = Client.attach(real_rig.name, layout=real_rig.layout)
    try:
        src = view.Sources(client, sim.rt.wm)  # the simulator's world model: only the rack line matters
        text = view.world_status(src.read(), src.rack)
    finally:
        client.close()
    assert src.rack == "real" and text.startswith("rack: real (the service's register bus is hardware")
    assert "SIMULATED" not in text


def test_a_buffer_no_service_has_claimed_is_unknown(sim):
    from bit3.buffer import Bit3Buffer
    name = "pfma-unclaimed-" + uuid.uuid4().hex[:8]
    buf = Bit3Buffer.create(name, sim.rig.layout)  # nobody claims it: no flags
    client = Client.attach(name, layout=sim.rig.layout)
    try:
        src = view.Sources(client, sim.rt.wm)
        text = view.world_status(src.read(), src.rack)
    finally:
        client.close()
        buf.close(unlink=True)
    assert src.rack == "unknown" and text.startswith("rack: unknown (the buffer does not say")


def _pfma(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_pfma_monitor_shows_the_flag(capsys, sim_rig, real_rig):
    rc, out, err = _pfma(capsys, "monitor", "--once", "--buffer", sim_rig.name)
    lines = out.splitlines()
    assert rc == 0 and lines[0].startswith("pfma monitor  buffer") and lines[1] == SIMULATED_LINE
    rc, out, err = _pfma(capsys, "monitor", "--once", "--json", "--buffer", sim_rig.name)
    assert rc == 0 and json.loads(out)["rack_kind"] == "simulated"
    rc, out, err = _pfma(capsys, "monitor", "--once", "--buffer", real_rig.name)
    assert rc == 0 and SIMULATED_LINE not in out and "SIMULATED" not in out
    rc, out, err = _pfma(capsys, "monitor", "--once", "--json", "--buffer", real_rig.name)
    assert rc == 0 and json.loads(out)["rack_kind"] == "real"


def test_pfma_read_from_the_service_shows_the_flag(capsys, sim_rig, real_rig):
    rc, out, err = _pfma(capsys, "read", "elbow_pitch_angle", "--buffer", sim_rig.name)
    assert rc == 0 and "(simulated rack) from the service (frame" in out, out + err
    rc, out, err = _pfma(capsys, "read", "elbow_pitch_angle", "--json", "--buffer", sim_rig.name)
    assert rc == 0 and json.loads(out)[0]["source"] == "simulated rack"
    rc, out, err = _pfma(capsys, "read", "elbow_pitch_angle", "--json", "--buffer", real_rig.name)
    assert rc == 0 and "source" not in json.loads(out)[0]
    rc, out, err = _pfma(capsys, "read", "elbow_pitch_angle", "--buffer", real_rig.name)
    assert rc == 0 and "simulated" not in out
