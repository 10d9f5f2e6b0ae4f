"""Fixtures shared across the suite: a private Bit3 buffer (``shm_name``, ``buf``) and a spawn
multiprocessing context (``mp``) for cross-process tests."""

import multiprocessing
import os
import uuid

import pytest

from bit3.buffer import Bit3Buffer


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
