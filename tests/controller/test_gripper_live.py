"""The gripper on the live system: real ``pfma serve`` (the simulated rack) and ``pfma controller
--power-up`` processes on a private buffer and world model; ``pfma controller gripper open``
then ``close`` sent from the shell, as an operator would. The jaw opens to its stop and closes
on itself (nothing is between the jaws of the service's simulated arm): the controller's jaw
estimate goes from 100 mm to 0, the end-effector tach shows the closing motion, the answers are
COMPLETE. Bounded polling of processes (real time)."""

from __future__ import annotations

import subprocess
import threading
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import ServiceState
from controller.worldmodel import WorldModel
from pfma.gripper import GripperState
from tests.controller._live_support import RERUN_ON_HOST_TIMING, SLOW_HOST_CONTROLLER, host_timing_named, PY, ROOT, RT, armed_and_released, live_inputs, power_up_holding, stop, wait_for, start_service

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]





def _gripper(wm_name: str) -> dict | None:
    try:
        wm = WorldModel.attach(wm_name)
    except Exception:  # noqa: BLE001 - not up yet
        return None
    try:
        return dict(wm.get_task_inputs(("gripper.state", "gripper.jaw_m", "gripper.jaw_known")))
    finally:
        wm.close()


def test_pfma_controller_gripper_open_then_close_moves_the_live_jaw(tmp_path):
    name = "pfma-test-gr-" + uuid.uuid4().hex[:6]
    wm = name + "-wm"
    serve = start_service(name, "--duration", "90")
    ctl = None
    log = tmp_path / "controller.log"
    try:
        with host_timing_named(log):
            def start() -> subprocess.Popen:
                with open(log, "w") as out:
                    return subprocess.Popen([*PY, "controller", "--buffer", name, "--wm", wm, "--power-up", "--duration",
                                             "60", *RT, *SLOW_HOST_CONTROLLER], cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
            ctl = power_up_holding(start, lambda: armed_and_released(name), log=log)
            assert wait_for(lambda: (g := _gripper(wm)) is not None and int(g["gripper.state"]) == GripperState.STOPPED,
                            timeout_s=30), "the controller never powered the gripper up"
            assert int(live_inputs(name).service_state) == ServiceState.ARMED
            opened = subprocess.run([*PY, "controller", "gripper", "open", "--wm", wm], cwd=ROOT,
                                    capture_output=True, text=True, timeout=30)
            assert opened.returncode == 0, opened.stdout + opened.stderr + log.read_text()
            assert "OPEN: at the open stop" in opened.stdout and opened.stdout.rstrip().endswith("-> COMPLETE")
            g = _gripper(wm)
            assert int(g["gripper.state"]) == GripperState.OPEN and bool(g["gripper.jaw_known"])
            assert float(g["gripper.jaw_m"]) == pytest.approx(0.10, abs=1e-3)
            # the close, watched on the end-effector tach while the CLI waits for its answer
            rates: list[float] = []
            done = threading.Event()

            def watch() -> None:
                with Client.attach(name) as c:
                    slot = c.layout.joint_entry("adc", "gripper", "rate").slot
                    while not done.wait(0.05):
                        rates.append(float(c.read_inputs().record["adc_value"][slot]))
            watcher = threading.Thread(target=watch, daemon=True)
            watcher.start()
            closed = subprocess.run([*PY, "controller", "gripper", "close", "--force", "60", "--wm", wm], cwd=ROOT,
                                    capture_output=True, text=True, timeout=30)
            done.set()
            watcher.join(timeout=5)
            assert closed.returncode == 0, closed.stdout + closed.stderr + log.read_text()
            lines = closed.stdout.splitlines()
            assert lines[0].endswith("CLOSE: CLOSING at 20 mm/s, 60 N -> IN PROGRESS")
            assert "CLOSED after" in lines[-1] and "nothing between the jaws; holding at 60 N -> COMPLETE" in lines[-1]
            g = _gripper(wm)
            assert int(g["gripper.state"]) == GripperState.CLOSED and float(g["gripper.jaw_m"]) == pytest.approx(0.0, abs=1e-3)
            assert min(rates) < -3.0  # tach volts: about -4 V (20 mm/s closing at 200 V per m/s)
    finally:
        stop(ctl, serve)
        Bit3Buffer.unlink(name)
        WorldModel.remove_segment(wm)
