"""The simulated-time rig for service tests (``sim.rig.SimRig``)."""

import pytest

from sim.rig import SimRig


@pytest.fixture
def rig():
    r = SimRig(prefix="pfma-test-")
    yield r
    r.close()
