"""Fixtures shared across the suite: a private Bit3 buffer (``shm_name``, ``buf``) and a spawn
multiprocessing context (``mp``) for cross-process tests.

The suite runs without real-time scheduling: ``PFMA_REALTIME=off`` (ioservice.loop.REALTIME_ENV)
is set here for every process a test starts, so ``pfma serve`` and ``pfma controller`` stay
time-shared and unpinned unless a test that is about real-time passes ``--realtime``; a
2-core CI host running everything as root is never filled with SCHED_FIFO processes. The
run's header says so once.
"""

import multiprocessing
import os
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from ioservice.loop import REALTIME_ENV

os.environ[REALTIME_ENV] = "off"


def pytest_report_header(config):
    return (f"real-time scheduling: off for the processes this suite starts ({REALTIME_ENV}=off); "
            f"only tests that pass --realtime take SCHED_FIFO")


@pytest.fixture
def shm_name():
    """A unique POSIX shared-memory name, removed after the test."""
    name = f"pfma_t{os.getpid()}_{uuid.uuid4().hex[:8]}"
    yield name
    Bit3Buffer.unlink(name)


@pytest.fixture
def buf(shm_name):
    b = Bit3Buffer.create(shm_name)
    yield b
    b.close()


@pytest.fixture(scope="session")
def mp():
    return multiprocessing.get_context("spawn")


@pytest.fixture
def shm_sim(monkeypatch):
    """A system simulator with its world model in shared memory (a unique name), for the
    ``pfma controller <request>`` verbs run in this process: their polls for an answer step
    the simulator one frame each (deterministic). Yields ``(sim, wm_name)``."""
    from controller.worldmodel import WorldModel
    from sim.system import SystemSimulator
    import tools.console.control as control
    monkeypatch.delenv("PFMA_WM_KEY", raising=False)
    name = f"pfma_wmsim{os.getpid()}_{uuid.uuid4().hex[:8]}"
    s = SystemSimulator(wm_name=name)
    s.step(10)
    monkeypatch.setattr(control.time, "sleep", lambda _s: s.step(1))
    yield s, name
    s.close()
    WorldModel.remove_segment(name)
