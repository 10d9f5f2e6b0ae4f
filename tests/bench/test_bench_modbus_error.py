"""``pfma bench modbus``: a service that stops before its first frame is reported with the
last lines it wrote on stderr, not only its exit status (it is started against a real
loopback gateway; the service is replaced by a stand-in that fails as a service would)."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.realtime

FAILS = "import sys; sys.stderr.write('pfma serve: the bus stopped answering' + chr(10)); sys.exit(1)"


def test_a_service_that_exits_at_start_up_is_reported_with_what_it_said(monkeypatch):
    import bench.bench_modbus as bm
    if bm.available():
        pytest.skip(bm.available())
    real = subprocess.Popen

    def popen(argv, **kw):
        if "serve" in argv:
            argv = [sys.executable, "-c", FAILS]
        return real(argv, **kw)
    monkeypatch.setattr(bm.subprocess, "Popen", popen)
    rep = bm.figures(1.0)
    assert rep["error"].endswith("exited 1 before publishing frames: pfma serve: the bus stopped answering"), rep
