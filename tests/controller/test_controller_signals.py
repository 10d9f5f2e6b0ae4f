"""A live `pfma controller` whose service stops, and that is then stopped with SIGTERM:
it says once on the terminal that the service went quiet, and SIGTERM gets the orderly stop
Ctrl-C gets (exit 0 after its power-down, saying so; before, SIGTERM ended it at once with
-15) - also where the shell started it with SIGINT ignored. Processes and wall-clock waits (bounded): realtime."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from bit3.buffer import Bit3Buffer
from bit3.ring import FrameRing
from controller.worldmodel import WorldModel

pytestmark = pytest.mark.realtime

PFMA = str(Path(sys.executable).with_name("pfma"))
WAIT_S = 30.0


def _until(cond, what: str) -> None:
    end = time.monotonic() + WAIT_S
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"not within {WAIT_S:g} s: {what}")
        time.sleep(0.05)


def test_a_controller_says_its_service_went_quiet_and_stops_in_order_on_sigterm(tmp_path):
    name = "pfma-test-sig-" + uuid.uuid4().hex[:6]
    wm = name + "_wm"
    err = tmp_path / "controller.err"
    out = tmp_path / "controller.out"
    svc = subprocess.Popen([PFMA, "serve", "--rack", "fake", "--buffer", name],
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctl = None
    try:
        _until(lambda: os.path.exists(f"/dev/shm/{name}") or svc.poll() is not None, "the service's buffer")
        time.sleep(0.5)  # its first frames
        with open(err, "w") as f, open(out, "w") as o:
            # SIGINT ignored, as a shell's background job has it: SIGTERM must still stop it in order
            ctl = subprocess.Popen([PFMA, "controller", "--power-up", "--buffer", name, "--wm", wm],
                                   stdin=subprocess.DEVNULL, stdout=o, stderr=f,
                                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
        _until(lambda: os.path.exists(f"/dev/shm/{wm}") or ctl.poll() is not None, "the controller's world model")
        time.sleep(1.0)  # its first frames
        assert ctl.poll() is None, err.read_text()
        svc.send_signal(signal.SIGINT)  # the service stops: no more frames
        svc.wait(timeout=WAIT_S)
        _until(lambda: "no frame from the service" in err.read_text() or ctl.poll() is not None,
               "the controller's line about the quiet service")
        text = err.read_text()
        assert ctl.poll() is None, text  # it waits for frames; it does not exit by itself
        assert text.count("no frame from the service") == 1, text
        assert "stopped or stalled?" in text and "commands are 0" in text
        ctl.send_signal(signal.SIGTERM)
        assert ctl.wait(timeout=WAIT_S) == 0, err.read_text()
        assert "SIGTERM: stopping (powering down in order)" in err.read_text()
        assert "Traceback" not in err.read_text()
        # said as it happened (stdout): System Up/Down's changes; at the SIGTERM: the statuses,
        # the ERROR episode's first cause (its root, not the cascade) and the last messages
        said = out.read_text()
        assert "SHUT DOWN -> INITIALIZATION IN PROGRESS" in said and "START UP -> START UP COMPLETE" in said
        cause = next((l for l in said.splitlines() if l.startswith("first cause")), "")
        assert cause.startswith("first cause of the ERROR: "), said
        assert "subordinate in ERROR" not in cause, said
        assert "--- last 30 messages ---" in said
    finally:
        for p in (ctl, svc):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(timeout=WAIT_S)
        WorldModel.remove_segment(wm)
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)
