"""The composition roots of the service and the recorder (tools/stacks): what they build is
torn down on leaving, whatever path they leave by."""

from __future__ import annotations

import logging
import os
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.ring import FrameRing
from tools.stacks.recorder import RecorderConfig, RecorderStack
from tools.stacks.service import Refused, ServiceConfig, ServiceStack


def _left(name: str) -> list[str]:
    return sorted(f for f in os.listdir("/dev/shm") if f == name or f.startswith(name + "."))


def test_a_service_built_but_never_run_leaves_nothing_behind():
    name = "pfma-stk-" + uuid.uuid4().hex[:6]
    lines: list[str] = []
    try:
        with ServiceStack(ServiceConfig(buffer=name, quiet=True), out=lines.append) as stack:
            stack.open()
            assert stack.svc is not None and stack.svc.ring is not None
            assert name in _left(name) and f"{name}.ring" in _left(name)
        assert _left(name) == []  # never served: the buffer and the ring removed
        assert lines == []  # no figures for a service that never ran
    finally:
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)


def test_an_exception_while_building_closes_what_was_opened(monkeypatch):
    name = "pfma-stk-" + uuid.uuid4().hex[:6]
    closed: list[str] = []

    def no_ring(*a, **kw):
        from bit3.buffer import Bit3Error
        raise Bit3Error("no room for the frame ring (test)")
    monkeypatch.setattr(FrameRing, "create", no_ring)
    stack = ServiceStack(ServiceConfig(buffer=name, quiet=True))
    with pytest.raises(Refused) as err, stack:
        stack.open()
        closed.append("not reached")
    assert err.value.status == 1 and "no room for the frame ring" in str(err.value)
    assert closed == [] and _left(name) == []


def test_a_recorder_with_no_service_says_so_and_exits_1(tmp_path, caplog):
    name = "pfma-stk-none-" + uuid.uuid4().hex[:6]
    with caplog.at_level(logging.INFO):
        code = RecorderStack(RecorderConfig(str(tmp_path / "r.mcap"), buffer=name, wait_s=0.2)).run()
    assert code == 1
    assert any(f"no service on /dev/shm/{name} within 0.2 s; nothing recorded" in r.getMessage()
               and r.levelno == logging.ERROR for r in caplog.records)
    assert not (tmp_path / "r.mcap").exists()
