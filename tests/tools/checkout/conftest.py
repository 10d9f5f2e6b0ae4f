"""Fixtures: the checkout's simulated target, and the service tests' Rig (reused by import)."""

import uuid

import pytest

from tools.checkout import load_checkout_config, make_sim_target
from sim.rig import SimRig as Rig


@pytest.fixture
def sim():
    t = make_sim_target()
    yield t
    t.close()


@pytest.fixture
def cfg():
    return load_checkout_config()


@pytest.fixture
def rig():
    r = Rig(name="pfma-cotest-" + uuid.uuid4().hex[:8])
    yield r
    r.close()
