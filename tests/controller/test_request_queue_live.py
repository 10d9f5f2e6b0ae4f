"""Power-up frame by frame on live processes (issue 30 item 4): a running ``pfma serve`` and
``pfma controller``, and from the shell ``pfma controller halt``, ``power-up``, ``step`` and
``resume --rearm``. Shared memory only; bounded polling."""

from __future__ import annotations

import re
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import ServiceState
from controller.decision import Status
from controller.layers import Response, find_answer
from controller.runtime import LAYER_KEYS, first_cause_text
from controller.worldmodel import WorldModel
from pfma.process import host_timing_cause
from tests.controller._live_support import RERUN_ON_HOST_TIMING, host_timing_named, stop, wait_for
from tests.controller._live_support import RT  # --realtime where this user may (SCHED_FIFO)

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]

ROOT = Path(__file__).resolve().parents[2]
PY = [sys.executable, "-m", "tools.cli"]


def _service_state(name: str) -> int | None:
    try:
        with Client.attach(name) as c:
            return int(c.read_inputs().service_state)
    except Exception:  # noqa: BLE001 - not up yet
        return None


def _attach(wm_name: str) -> WorldModel | None:
    try:
        return WorldModel.attach(wm_name)
    except Exception:  # noqa: BLE001 - not there yet
        return None


def _statuses(w: WorldModel) -> dict[str, Status]:
    return {k: Status(int(w.get(f"{k}.status"))) for k in LAYER_KEYS}


def _outputs_safe(c: Client) -> bool:
    """The service holds the outputs safe: HALTED (the halted controller's command), or FAULT
    should a host stall on this shared machine let the heartbeat go stale (the watchdog);
    either way every DAC channel 0 V and the brakes set, never ARMED."""
    snap = c.read_inputs()
    return int(snap.service_state) in (ServiceState.HALTED, ServiceState.FAULT) and \
        not np.any(snap.dac_value) and not int(snap.brakes_released)


def _pfma(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([*PY, *argv], cwd=ROOT, capture_output=True, text=True, timeout=60)


def test_power_up_from_the_shell_while_halted_steps_then_resume_rearm_completes():
    name = "pfma-test-rq-" + uuid.uuid4().hex[:6]
    wm = name + "-wm"
    serve = subprocess.Popen([*PY, "serve", "--buffer", name, "--duration", "120", *RT], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctl = w = c = None
    try:
        with host_timing_named(lambda: ctl):
            assert wait_for(lambda: _service_state(name) is not None), "the service did not come up"
            ctl = subprocess.Popen([*PY, "controller", "--buffer", name, "--wm", wm, "--duration", "110", *RT], cwd=ROOT,
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            assert wait_for(lambda: _attach(wm) is not None), "the controller made no world model"
            # one attachment each, read while polling (attaching on every poll costs this loaded host)
            w, c = WorldModel.attach(wm), Client.attach(name)
            r = _pfma("controller", "halt", "--wm", wm)
            assert r.returncode == 0 and "-> COMPLETE" in r.stdout, (r.stdout, r.stderr)
            assert wait_for(lambda: int(c.read_inputs().service_state) == ServiceState.HALTED, 10)
            r = _pfma("controller", "power-up", "--wm", wm)
            assert r.returncode == 0 and "POWER UP: queued" in r.stdout and "-> QUEUED" in r.stdout, (r.stdout, r.stderr)
            assert r.stdout.startswith("POWER UP with the shoulder-roll index 0 deg"), r.stdout  # said first
            m = re.search(r"^request (\d+): ", r.stdout, re.M)
            assert m is not None, r.stdout
            seq = int(m.group(1))
            assert _statuses(w) == dict.fromkeys(LAYER_KEYS, Status.SHUT_DOWN)  # halted: nothing ran
            for _ in range(20):  # 10 frames a step until Data Acquisition waits in START UP for the arm
                r = _pfma("controller", "step", "10", "--wm", wm)
                assert r.returncode == 0 and "SINGLE STEP: 10 frame(s) run" in r.stdout, (r.stdout, r.stderr)
                assert len(r.stdout.splitlines()) >= 12  # the answer, the trace's header, its 10 frames
                assert _outputs_safe(c)
                if _statuses(w)["daq"] == Status.START_UP:
                    break
            st = _statuses(w)
            assert st["daq"] == Status.START_UP and st["updown"] == Status.START_UP, st
            code, _text = find_answer(w, seq) or (0, "")
            assert code == Response.IN_PROGRESS
            r = _pfma("controller", "resume", "--rearm", "--wm", wm)
            assert r.returncode == 0 and "re-armed" in r.stdout, (r.stdout, r.stderr)
            up = dict.fromkeys(LAYER_KEYS, Status.START_UP_COMPLETE)
            wait_for(lambda: _statuses(w) == up or _statuses(w)["updown"] == Status.ERROR, 20)
            retries = 0
            while _statuses(w) != up and retries < 2 and host_timing_cause(first_cause_text(w)):
                # on a shared 2-core host without SCHED_FIFO a controller descheduled for 3 frames is a
                # servo fault (max_missed_run), as in any running controller: then ERROR RESET and
                # POWER UP from the shell, at most twice (tests/controller/test_distributed_live.py too)
                retries += 1
                assert wait_for(lambda: _statuses(w)["updown"] == Status.ERROR, 10)
                r = _pfma("controller", "reset", "--wm", wm)
                assert r.returncode == 0 and "ERROR RESET: SHUT DOWN -> COMPLETE" in r.stdout, (r.stdout, r.stderr)
                r = _pfma("controller", "power-up", "--wm", wm)  # running: it waits for the final answer
                assert r.returncode == 0 or host_timing_cause(first_cause_text(w)), (r.stdout, r.stderr)
            assert _statuses(w) == up, (_statuses(w), first_cause_text(w))
            if not retries:
                assert find_answer(w, seq) == (Response.COMPLETE, "POWER UP: START UP COMPLETE")
            assert int(c.read_inputs().service_state) == ServiceState.ARMED
            ctl.terminate()  # an orderly power-down on the way out
            out, _ = ctl.communicate(timeout=30)
            assert ctl.returncode == 0 and "Traceback" not in out, out
            assert int(c.read_inputs().service_state) != ServiceState.ARMED
    finally:
        for h in (w, c):
            if h is not None:
                h.close()
        stop(ctl, serve)
        Bit3Buffer.unlink(name)
        WorldModel.remove_segment(wm)
