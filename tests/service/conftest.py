"""The simulated-time rig for service tests (``ioservice.simrig.SimRig``)."""

import pytest

from ioservice.simrig import SimRig


@pytest.fixture
def rig():
    r = SimRig(prefix="pfma-test-")
    yield r
    r.close()
