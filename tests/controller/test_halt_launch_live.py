"""``pfma controller --halt`` on a live service: the controller halts at its first frame and
goes on ticking while it waits for the keyboard, so the service holds HALTED (0 V, brakes set)
instead of tripping its watchdog; a typed ``s N`` runs exactly N frames. Real ``pfma serve``
and ``pfma controller`` processes (loopback nothing: shared memory only), bounded polling."""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import ServiceState
from tests.controller._live_support import RERUN_ON_HOST_TIMING, host_timing_named, stop, wait_for
from controller.worldmodel import WorldModel

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]

ROOT = Path(__file__).resolve().parents[2]


def _state(name: str) -> int | None:
    try:
        with Client.attach(name) as c:
            return int(c.read_inputs().service_state)
    except Exception:  # noqa: BLE001 - not up yet
        return None


def test_halt_at_launch_holds_halted_while_waiting_and_steps_on_command():
    name = "pfma-test-hl-" + uuid.uuid4().hex[:6]
    wm = name + "-wm"
    py = [sys.executable, "-m", "tools.cli"]
    serve = subprocess.Popen([*py, "serve", "--buffer", name, "--duration", "60"], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctl = None
    try:
        with host_timing_named(lambda: ctl):
            assert wait_for(lambda: _state(name) is not None), "the service did not come up"
            ctl = subprocess.Popen([*py, "controller", "--buffer", name, "--wm", wm, "--halt"], cwd=ROOT,
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            assert wait_for(lambda: _state(name) == ServiceState.HALTED), "the service never showed HALTED"
            time.sleep(0.5)  # waiting at the prompt: 160 service frames, thirty watchdog periods
            assert _state(name) == ServiceState.HALTED  # held, not tripped
            assert ctl.stdin is not None
            ctl.stdin.write("s 2\n")
            ctl.stdin.flush()
            time.sleep(0.5)
            ctl.stdin.write("q\n")
            ctl.stdin.flush()
            out, _ = ctl.communicate(timeout=30)
            assert ctl.returncode == 0, out
            assert "SINGLE STEP: 2 frame(s) run" in out, out
            with Client.attach(name) as c:
                texts = [m.text for m in c.messages()]
            assert any("halted by the controller" in t for t in texts), texts
            assert not any("stale heartbeat" in t for t in texts), texts  # no watchdog trip
    finally:
        stop(ctl, serve)
        Bit3Buffer.unlink(name)
        WorldModel.remove_segment(wm)
