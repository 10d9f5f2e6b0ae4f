"""The process helpers every benchmark uses (``pfma.process``: a child with a bounded stop,
``until``, ``free_port``, ``pid_alive``; ``tools.attach.wait_for_frames``)."""

from __future__ import annotations

import os
import signal
import socket
import sys
import time
import uuid

from pfma.process import Child, free_port, pid_alive, until
from tools.attach import wait_for_frames


def test_a_child_that_stops_on_sigint_says_so(tmp_path):
    c = Child("sleeper", [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(30)"], tmp_path)
    try:
        assert until(lambda: "up" in c.text(), 20.0, must_live=(c,))
        assert c.stop(signal.SIGINT, 10.0) == "SIGINT -> exit -2"  # KeyboardInterrupt: Python ends by the signal
        assert not c.alive() and not pid_alive(c.pid)
        assert c.stop() == "SIGINT -> exit -2"  # asked again: how it ended, unchanged
    finally:
        c.close()


def test_a_child_that_ignores_sigint_is_killed_after_the_bound(tmp_path):
    code = ("import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); print('up', flush=True); "
            "time.sleep(30)")
    c = Child("stubborn", [sys.executable, "-c", code], tmp_path)
    try:
        assert until(lambda: "up" in c.text(), 20.0, must_live=(c,))
        t0 = time.monotonic()
        assert c.stop(signal.SIGINT, 0.5) == "needed SIGKILL (0.5 s after SIGINT)"
        assert time.monotonic() - t0 < 10.0
        assert not c.alive()
        assert c.tail(1) == "up"
    finally:
        c.close()


def test_until_returns_the_value_or_none():
    assert until(lambda: 7, 1.0) == 7
    t0 = time.monotonic()
    assert until(lambda: 1 / 0, 0.2) is None  # an exception is "not yet"
    assert 0.2 <= time.monotonic() - t0 < 5.0


def test_until_gives_up_when_a_process_it_needs_has_ended(tmp_path):
    c = Child("short", [sys.executable, "-c", "pass"], tmp_path)
    try:
        t0 = time.monotonic()
        assert until(lambda: False, 30.0, must_live=(c,)) is None
        assert time.monotonic() - t0 < 20.0
    finally:
        c.close()


def test_free_port_can_be_bound():
    port = free_port()
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))


def test_pid_alive():
    assert pid_alive(os.getpid())
    assert not pid_alive(2 ** 22 + 1)  # above the kernel's largest pid


def test_wait_for_frames_without_a_service_times_out_quietly(capsys):
    t0 = time.monotonic()
    assert wait_for_frames("pfma-test-none-" + uuid.uuid4().hex[:6], 2, timeout_s=0.3, poll_s=0.05) is None
    assert time.monotonic() - t0 < 5.0
    assert capsys.readouterr() == ("", "")


def test_wait_for_frames_stops_waiting_when_the_service_ended():
    t0 = time.monotonic()
    assert wait_for_frames("pfma-test-none-" + uuid.uuid4().hex[:6], timeout_s=30.0, alive=lambda: False) is None
    assert time.monotonic() - t0 < 5.0
