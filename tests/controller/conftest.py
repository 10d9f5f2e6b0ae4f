"""Shared fixtures of the controller tests: a whole simulated system (`sim`), powered up (`powered`)."""

import pytest

from controller.decision import Status
from sim.system import SystemSimulator


@pytest.fixture
def sim():
    s = SystemSimulator()
    s.step(10)  # the service runs a few frames (F/T link opens) before anyone asks anything
    yield s
    s.close()


@pytest.fixture
def powered(sim):
    sim.power_up(max_frames=400)
    sim.step(20)
    assert sim.rt.all_status(Status.START_UP_COMPLETE)
    return sim
