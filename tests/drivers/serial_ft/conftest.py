"""Fixtures for the F/T tests: a fake controller behind a real pty at 19200 baud."""

from __future__ import annotations

import contextlib

import pytest

from drivers.serial_ft.ftsensor import FtSensor, open_ft
from fakes.ft_sensor import FakeFtController
from fakes.pty import PtyDevice


def safe_load(t_s: float):
    """A varying load whose count bytes are never 0x00/0x01 (never a plausible status byte).

    With such data any framing slip puts a non-status byte where the decoder expects a
    status byte, so detection is certain and the tests are deterministic. The general
    case (counts whose bytes are 0) is covered, honestly, in test_protocol.py.
    """
    lo = 0x10 + int(t_s * 997) % 0xE0  # 0x10..0xEF, changes every sample
    fc = 0x0300 + lo  # counts, bytes 0x03 and lo
    tc = 0x0400 + (0xFF - lo)
    return (fc / 16.0, (fc + 1) / 16.0, (fc + 2) / 16.0), (tc / 200.0, (tc + 1) / 200.0, (tc + 2) / 200.0)


@pytest.fixture
def rig():
    """Factory: rig(mode="binary", checksum=False, load_fn=None) -> (model, dev, sensor)."""
    stack = contextlib.ExitStack()

    def make(mode: str = "binary", checksum: bool = False, load_fn=safe_load, **kw):
        model = FakeFtController(load_fn=load_fn, **kw)
        dev = stack.enter_context(PtyDevice(model, baud=19200))
        sensor: FtSensor = open_ft(dev.port_name, 19200, reply_timeout_s=0.5)
        stack.callback(sensor.port.close)
        sensor.set_mode(mode)
        if mode == "binary":
            sensor.set_checksum(checksum)
        return model, dev, sensor

    with stack:
        yield make


def ground_truth_check(model: FakeFtController, readings) -> int:
    """Every reading must equal a record the fake sent, in order. Returns how many sent
    records (from the first to the last matched) were not decoded."""
    sent = [r.counts for r in model.sent_records]
    i = 0
    first = None
    for r in readings:
        while i < len(sent) and sent[i] != r.counts:
            i += 1
        assert i < len(sent), f"reading {r} is not in the fake's ground truth (corrupt record returned)"
        first = i if first is None else first
        i += 1
    return (i - first) - len(readings) if readings else 0
