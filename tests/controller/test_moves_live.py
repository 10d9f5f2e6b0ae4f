"""Moves on the live system (issue 30 item 5): real ``pfma serve`` (the simulated rack) and
``pfma controller --power-up`` processes on a private buffer and world model;
``pfma controller move`` from the shell, as an operator types it: a pose without an
orientation (the tool keeps its own) ends OK with its tracking error, the issue's identity
orientation is refused before anything moves, naming the target and the reason; then
docs/python.md's controller script, as written but for the world-model name. Bounded
polling of processes (real time)."""

from __future__ import annotations

import re
import subprocess
import sys
import uuid

import numpy as np
import pytest

from bit3.buffer import Bit3Buffer
from controller.decision import Status
from controller.worldmodel import WorldModel
from tests.controller._live_support import RERUN_ON_HOST_TIMING, SLOW_HOST_CONTROLLER, host_timing_named, PY, ROOT, RT, armed_and_released, power_up_holding, stop, wait_for, start_service

pytestmark = [pytest.mark.realtime, RERUN_ON_HOST_TIMING]






def _msp_up(wm: str) -> bool:
    try:
        with WorldModel.attach(wm) as m:
            return int(m.get("msp.status")) == int(Status.START_UP_COMPLETE)
    except Exception:  # noqa: BLE001 - not there yet
        return False


def _doc_script(wm: str) -> str:
    """docs/python.md's python block that moves through the controller, on world model ``wm``."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "python.md").read_text(), re.S)
    code = [b for b in blocks if "ControllerLink.attach" in b]
    assert len(code) == 1, "docs/python.md: no (or more than one) controller block"
    assert code[0].count('"pfma_wm"') == 1
    return code[0].replace('"pfma_wm"', repr(wm))


def _move(wm: str, *argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([*PY, "controller", "move", *argv, "--wm", wm, "--timeout", "30"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)


def test_move_from_the_shell_and_python_keeps_the_orientation_and_a_turning_one_is_refused(tmp_path):
    name = "pfma-test-mv-" + uuid.uuid4().hex[:6]
    wm = name + "-wm"
    serve = start_service(name, "--duration", "90")
    ctl = None
    try:
        with host_timing_named(lambda: ctl):
            ctl = power_up_holding(
                lambda: subprocess.Popen([*PY, "controller", "--buffer", name, "--wm", wm, "--power-up", "--duration",
                                          "60", "--messages", "60", *RT, *SLOW_HOST_CONTROLLER], cwd=ROOT, stdout=subprocess.PIPE,
                                         stderr=subprocess.STDOUT, text=True),
                lambda: armed_and_released(name))
            assert wait_for(lambda: _msp_up(wm)), "the path planner never started"
            with WorldModel.attach(wm) as m:
                p0 = np.array(m.get("joint.tool_pos_m"))
            x, y, z = p0 + [0.0, 0.03, 0.0]
            r = _move(wm, "--pose", f"{x:.4f},{y:.4f},{z:.4f}")
            if r.returncode:  # say what the controller said
                ctl.terminate()
                pytest.fail(r.stdout + r.stderr + "\n--- the controller ---\n" + ctl.communicate(timeout=30)[0])
            assert "cart.mode HOLD -> TRAJECTORY" in r.stdout and "move 1 sent" in r.stdout
            assert "move 1 done (worst tracking error" in r.stdout and r.stdout.rstrip().endswith("-> OK"), r.stdout
            with WorldModel.attach(wm) as m:
                p1 = np.array(m.get("joint.tool_pos_m"))
            assert abs(p1[1] - y) < 0.01
            r = _move(wm, "--pose", "1.55,0,-0.33,1,0,0,0")
            assert r.returncode == 1, r.stdout + r.stderr
            assert "move 2 refused before it started: the target: turns the tool" in r.stdout, r.stdout
            # the Python route, docs/python.md's block as written
            f = tmp_path / "moves.py"
            f.write_text(_doc_script(wm))
            r = subprocess.run([sys.executable, str(f)], cwd=ROOT, capture_output=True, text=True, timeout=120)
            assert r.returncode == 0, r.stdout + r.stderr
            lines = r.stdout.splitlines()
            assert lines[0] == "cart.mode already TRAJECTORY", r.stdout
            assert lines[1].startswith("move 3 done (worst tracking error") and lines[1].endswith("-> OK"), r.stdout
            assert lines[2].startswith("move 4 done (worst joint deviation") and lines[2].endswith("-> OK"), r.stdout
            assert lines[3].startswith("move 5 refused before it started: the target: turns the tool"), r.stdout
            ctl.terminate()
            out, _ = ctl.communicate(timeout=30)
            assert "move 2 refused before it started" in out
    finally:
        stop(ctl, serve)
        Bit3Buffer.unlink(name)
        WorldModel.remove_segment(wm)
