"""`pfma serve --rack fake` on a host too loaded to run the simulated rack's register
emulation within the bus budget at start: a warning naming the figures, and the service
runs (a real bus that slow is refused: tests/ioservice/test_serve_gateway.py)."""

from __future__ import annotations

import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.ring import FrameRing
from ioservice.schedule import BusTooSlow
from ioservice.service import IoService
from tools.cli import main

pytestmark = pytest.mark.realtime


def test_a_slow_simulated_rack_is_warned_about_not_refused(monkeypatch, capsys):
    def too_slow(self, slow=False, repeats=0):
        raise BusTooSlow("the bus fake cannot keep the schedule of ... (as measured at load 9)")
    monkeypatch.setattr(IoService, "fit_schedule", too_slow)
    name = "pfma-test-slowfake-" + uuid.uuid4().hex[:6]
    try:
        rc = main(["serve", "--rack", "fake", "--buffer", name, "--duration", "0.3"])
    finally:
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "warning: the simulated rack's register emulation is slow on this host now" in err
    assert "as measured at load 9" in err
