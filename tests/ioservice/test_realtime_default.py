"""Real-time by default where permitted (issue 29 item 2): ``pfma serve`` and ``pfma
controller`` take SCHED_FIFO and their pinned CPU when the user may, say so in one line,
``--no-realtime`` opts out; where not permitted one line says what the host lacks and what
it costs, and nothing is pinned without SCHED_FIFO. The suite itself runs with
``PFMA_REALTIME=off`` (tests/conftest.py); the live tests here clear it for the process
they start, as a user's shell would not have it."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from ioservice import loop
from ioservice.loop import REALTIME_ENV, realtime_default, realtime_start
from tests.controller._live_support import fifo_permitted, stop, wait_for


class _Sched:
    """The scheduler calls realtime_setup makes, recorded; FIFO refused when ``fifo_ok`` is False."""

    def __init__(self, fifo_ok: bool) -> None:
        self.fifo_ok, self.calls = fifo_ok, []

    def setscheduler(self, pid, policy, param):
        self.calls.append(("fifo", param.sched_priority))
        if not self.fifo_ok:
            raise PermissionError(1, "Operation not permitted")

    def setaffinity(self, pid, cpus):
        self.calls.append(("pin", set(cpus)))


@pytest.fixture
def sched(monkeypatch):
    def make(fifo_ok: bool) -> _Sched:
        s = _Sched(fifo_ok)
        monkeypatch.setattr(os, "sched_setscheduler", s.setscheduler)
        monkeypatch.setattr(os, "sched_setaffinity", s.setaffinity)
        return s
    return make


def test_permitted_it_takes_fifo_then_pins_and_says_so_in_one_line(sched, monkeypatch):
    monkeypatch.delenv(REALTIME_ENV)
    s = sched(True)
    lines = realtime_start("pfma serve", None, 1, 50, watchdog_ms=15)
    assert s.calls == [("fifo", 50), ("pin", {1})]
    assert lines == ["pfma serve: real-time: SCHED_FIFO priority 50, pinned to CPU 1 (--no-realtime opts out)"]


def test_not_permitted_nothing_is_pinned_and_one_line_says_what_is_lacking_and_what_it_costs(sched, monkeypatch):
    monkeypatch.delenv(REALTIME_ENV)
    s = sched(False)
    lines = realtime_start("pfma serve", None, 1, 50, watchdog_ms=15)
    assert s.calls == [("fifo", 50)]  # never pinned without SCHED_FIFO
    assert len(lines) == 1
    assert "real-time not permitted for this user" in lines[0] and "CAP_SYS_NICE" in lines[0]
    assert "15 ms watchdog" in lines[0]


def test_asked_for_and_not_permitted_says_the_same(sched):
    s = sched(False)
    lines = realtime_start("pfma controller", True, 0, 49)  # --realtime beats PFMA_REALTIME=off
    assert s.calls == [("fifo", 49)] and "not permitted" in lines[0]


def test_no_realtime_and_the_environment_turn_it_off(sched, monkeypatch):
    s = sched(True)
    assert realtime_start("pfma serve", False, 1, 50) == ["pfma serve: real-time off (--no-realtime): "
                                                          "time-shared, not pinned"]
    monkeypatch.setenv(REALTIME_ENV, "off")
    assert not realtime_default() and realtime_start("pfma serve", None, 1, 50) == []
    assert s.calls == []
    monkeypatch.setenv(REALTIME_ENV, "")
    assert realtime_default()


def test_the_suite_runs_with_the_default_off():
    assert os.environ[REALTIME_ENV] == "off" and not loop.realtime_default()



def _serve(name: str, *flags: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != REALTIME_ENV}  # a user's shell
    return subprocess.Popen([sys.executable, "-m", "tools.cli", "serve", "--rack", "fake", "--buffer", name,
                             *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _policy_and_cpus(pid: int) -> tuple[int, set[int]]:
    return os.sched_getscheduler(pid), os.sched_getaffinity(pid)


@pytest.mark.realtime
@pytest.mark.parametrize("flags", [(), ("--no-realtime",)])
def test_pfma_serve_by_default_and_opted_out(flags):
    name = f"pfma-rt-{uuid.uuid4().hex[:8]}"
    p = _serve(name, *flags)
    try:
        assert wait_for(lambda: os.path.exists(f"/dev/shm/{name}") or p.poll() is not None, 30)
        assert p.poll() is None
        policy, cpus = _policy_and_cpus(p.pid)
    finally:
        stop(p)
        Bit3Buffer.unlink(name)
    err = p.stderr.read() if p.stderr else ""
    ncpu = len(os.sched_getaffinity(0))
    if flags:
        assert policy == os.SCHED_OTHER and len(cpus) == ncpu, (policy, cpus)
        assert "real-time off (--no-realtime)" in err
    elif fifo_permitted():
        assert policy == os.SCHED_FIFO and len(cpus) == 1, (policy, cpus)
        assert "pfma serve: real-time: SCHED_FIFO priority 50, pinned to CPU" in err
    else:
        assert policy == os.SCHED_OTHER and len(cpus) == ncpu, (policy, cpus)
        assert "real-time not permitted for this user" in err
    assert "Traceback" not in err
