"""Flying the simulated arm by hand on the live system (issue 30 item 6): real ``pfma serve``
(the simulated rack) and ``pfma controller --power-up --teleop cae`` processes on a private
buffer and world model; ``pfma hand --deflect`` as an operator types it. With the deadman
pressed the tool moves; without it, it holds; after ``--for`` the stick is let go and the
tool stops. Bounded polling of processes (real time)."""

from __future__ import annotations

import subprocess
import time
import uuid

import numpy as np
import pytest

from bit3.buffer import Bit3Buffer
from bit3.layout import HAND_CONTROLLERS, ServiceState
from controller.worldmodel import WorldModel
from tests.controller._live_support import RERUN_ON_HOST_TIMING, SLOW_HOST_CONTROLLER, host_timing_named, PY, ROOT, RT, armed_and_released, live_inputs, power_up_holding, stop, wait_for, start_service

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]

CAE = HAND_CONTROLLERS.index("cae")



def _tool(wm: str) -> np.ndarray:
    with WorldModel.attach(wm) as m:
        return np.array(m.get("joint.tool_pos_m"))


def _hand(name: str, *argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([*PY, "hand", "--source", "cae", "--buffer", name, *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=30)


def test_the_simulated_stick_flies_the_live_arm_with_the_deadman_only():
    name = "pfma-test-hd-" + uuid.uuid4().hex[:6]
    wm = name + "-wm"
    serve = start_service(name, "--duration", "90")
    ctl = None
    try:
        with host_timing_named(lambda: ctl):
            ctl = power_up_holding(
                lambda: subprocess.Popen([*PY, "controller", "--buffer", name, "--wm", wm, "--power-up", "--teleop",
                                          "cae", "--duration", "60", "--messages", "60", *RT, *SLOW_HOST_CONTROLLER], cwd=ROOT,
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True),
                lambda: armed_and_released(name))
            p0 = _tool(wm)
            r = _hand(name, "--deflect", "x=0.6", "--for", "1")  # no deadman: the stick is not trusted
            assert r.returncode == 0 and "deadman up, for 1 s" in r.stdout, r.stdout + r.stderr
            assert wait_for(lambda: not bool(live_inputs(name).hc_deadman[CAE]) and abs(live_inputs(name).hc_axes[CAE][0]) > 0.1,
                            5)
            p1 = _tool(wm)
            assert np.linalg.norm(p1 - p0) < 0.002, (p0, p1)
            r = _hand(name, "--deflect", "x=0.6", "--deadman", "--for", "1.5")
            assert r.returncode == 0 and "deadman pressed, for 1.5 s" in r.stdout, r.stdout + r.stderr
            assert wait_for(lambda: np.linalg.norm(_tool(wm) - p1) > 0.01, 10), \
                "the tool did not move with the deadman pressed"
            # let go after 1.5 s: the deadman comes up and the tool stops (the arm catches up with
            # its reference within half a second, then holds)
            assert wait_for(lambda: not bool(live_inputs(name).hc_deadman[CAE]), 10)
            time.sleep(0.5)
            p2 = _tool(wm)
            time.sleep(0.5)
            assert np.linalg.norm(_tool(wm) - p2) < 0.001, (p2, _tool(wm))
            assert int(live_inputs(name).service_state) == ServiceState.ARMED
    finally:
        stop(ctl, serve)
        Bit3Buffer.unlink(name)
        WorldModel.remove_segment(wm)
