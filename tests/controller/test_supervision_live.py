"""Joint supervision on the live system (issue 28): real ``pfma serve`` (the simulated rack)
and ``pfma controller --power-up`` processes on a private buffer; a motion fault injected
with ``pfma fault inject`` while the arm holds its pose. The controller stops the joint
(every DAC channel 0 V: rates and current limits, brakes on) and prints one message naming
the joint and the likely cause. Bounded polling of processes (real time)."""

from __future__ import annotations

import subprocess
import uuid

import numpy as np
import pytest

from bit3.buffer import Bit3Buffer
from pfma.process import host_timing_cause
from tests.controller._live_support import RERUN_ON_HOST_TIMING, SLOW_HOST_CONTROLLER, host_timing_named, PY, ROOT, RT, live_inputs, powered_controller, stop, wait_for, start_service

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]






@pytest.mark.parametrize("spec,joint,cause", [
    # faults that show while the arm holds its pose (a reversed tach needs motion to show:
    # the system-simulator trials cover it, tests/controller/test_supervision.py)
    ("amp-off:shoulder_pitch", "shoulder_pitch", "amplifier, PWM stage or current limit off"),
    ("load:shoulder_pitch=-300", "shoulder_pitch", "unexpected load or collision"),
])
def test_a_motion_fault_on_the_live_arm_stops_it_and_names_joint_and_cause(spec, joint, cause):
    name = "pfma-test-sv-" + uuid.uuid4().hex[:6]
    serve = start_service(name, "--duration", "60")
    ctl = None
    try:
        with host_timing_named(lambda: ctl):
            ctl = powered_controller(name, "--duration", "8", "--messages", "400")
            inj = subprocess.run([*PY, "fault", "inject", "--buffer", name, spec], cwd=ROOT, capture_output=True,
                                 text=True, timeout=30)
            assert inj.returncode == 0, inj.stdout + inj.stderr
            # stopped: every DAC channel at 0 V (rates and current limits: brakes on)
            assert wait_for(lambda: (s := live_inputs(name)) is not None
                             and np.all(np.asarray(s.record["dac_volts"]) == 0.0), 10), "outputs not at 0 V"
            out, _ = ctl.communicate(timeout=60)
            lines = [ln for ln in out.splitlines() if "fault 1" in ln and joint in ln and "current limits 0" in ln]
            assert lines, out
            assert f"likely {cause}" in lines[0], lines[0]
    finally:
        stop(ctl, serve)
        Bit3Buffer.unlink(name)


def test_a_brake_switch_left_off_fails_the_live_power_up_naming_the_joint():
    """Issue 30 item 3, live: ``pfma serve`` with elbow pitch's brake-release switch off on
    the servo chassis panel (``panel-off:brake:elbow_pitch``); ``pfma controller --power-up``
    does not reach START UP COMPLETE: its brake test names the joint and the brake, and the
    outputs are at 0 V. (A controller stopped by a host-timing fault before its brake test ran
    is started again, as in power_up_holding, at most 3 times.)"""
    name = "pfma-test-bt-" + uuid.uuid4().hex[:6]
    serve = start_service(name, "--duration", "60", "--fault", "panel-off:brake:elbow_pitch")
    outs, ctl = [], None
    try:
        with host_timing_named(lambda: ctl):
            for _ in range(3):
                ctl = subprocess.Popen([*PY, "controller", "--buffer", name, "--wm", "none", "--power-up",
                                        "--duration", "4", "--messages", "400", *RT, *SLOW_HOST_CONTROLLER], cwd=ROOT,
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                out, _ = ctl.communicate(timeout=60)
                outs.append(out)
                if "brake test:" in out or not host_timing_cause(out):
                    break
            lines = [ln for ln in out.splitlines() if "fault 19: brake test: elbow_pitch did not move as told" in ln]
            assert lines, "\n---\n".join(outs)
            assert "likely brake not released (or a jam)" in lines[0] and "current limits 0" in lines[0], lines[0]
            assert "START UP COMPLETE after" not in out
            s = live_inputs(name)
            assert s is not None and np.all(np.asarray(s.record["dac_volts"]) == 0.0)
    finally:
        stop(serve)
        Bit3Buffer.unlink(name)
