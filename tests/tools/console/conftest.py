"""What the console tests share: the system simulator (settled 10 frames), a reader client
of its buffer, and a console over both with its timer off (a test steps the simulator and
redraws: nothing depends on the wall clock)."""

from __future__ import annotations

import pytest

from bit3.client import Client
from sim.system import SystemSimulator
from tools.console import view
from tools.console.app import ConsoleApp
from tools.console.control import ControllerLink


@pytest.fixture
def sim():
    s = SystemSimulator()
    s.step(10)
    yield s
    s.close()


@pytest.fixture
def reader(sim):
    client = Client.attach(sim.name, layout=sim.rig.layout)  # a reader: the console claims nothing
    yield client
    client.close()


@pytest.fixture
def console(sim, reader):
    return ConsoleApp(view.Sources(reader, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                      auto_refresh=False)
