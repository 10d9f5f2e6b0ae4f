"""``pfma hand --deflect`` (issue 30 item 6): the simulated CAE stick of a running service,
held through its control endpoint (tools/faultctl.py), read back by the service's own CAE
driver into the Bit3 inputs, and let go after ``--for``; refused without a simulated rack.
In-process: a SimRig's service with the endpoint, the client in a thread while the test
steps the frames (tests/tools/cli/test_fault_cli.py's pattern)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from bit3.layout import HAND_CONTROLLERS
from drivers.crl.cae import CAE_AXES
from fakes.sim_rack import CAE_AXIS_SIGNALS
from sim.rig import SimRig
from tests.tools.cli.test_fault_cli import while_stepping
from tools.cli import main
from tools.cli.fault import install_serve_faults
from tools.faultctl import MSG_HAND
from tools.hand import parse_deflection

CAE = HAND_CONTROLLERS.index("cae")


@pytest.fixture
def rig():
    r = SimRig(prefix="pfma-hand-")
    try:
        install_serve_faults(argparse.Namespace(fault=[], scenario=None, buffer=r.name), r.svc, r.world)
        r.run_frames(4)
        yield r
    finally:
        r.close()


def _hand(rig, capsys, *argv):
    rc = while_stepping(rig, lambda: main(["hand", "--source", "cae", *argv, "--buffer", rig.name]))
    cap = capsys.readouterr()
    assert "Traceback" not in cap.out + cap.err
    return rc, cap.out, cap.err


def test_the_axes_map_through_the_drivers_table_onto_the_sticks_signals():
    assert tuple(s for s, _, _ in CAE_AXES) == CAE_AXIS_SIGNALS  # one order on both sides
    v = parse_deflection("x=0.4, y=0.5,yaw=-1")
    assert v == [0.0, 4.0, -5.0, -10.0, 0.0, 0.0]  # y left is right/left negative (CAE_AXES)


def test_a_deflection_with_the_deadman_reaches_the_inputs_then_springs_back(rig, capsys):
    rc, out, err = _hand(rig, capsys, "--deflect", "x=0.4,z=-0.25", "--deadman", "--for", "5")
    assert rc == 0, err
    said = [ln for ln in out.splitlines() if ln.startswith("pfma hand:")]  # (the service says it too, here)
    assert said[0].startswith("pfma hand: simulated CAE stick held at -2.50, +4.00, +0.00, +0.00, +0.00, +0.00 V, "
                          "deadman pressed, for 5 s")
    rig.run_frames(40)  # the ADC's next conversions (160 Hz)
    s = rig.reader.read_inputs()
    assert bool(s.hc_deadman[CAE]) and bool(s.hc_valid[CAE])
    axes = np.asarray(s.hc_axes[CAE])
    # x 0.4 and z -0.25 of full deflection through the driver's deadband (0.5 V) and its
    # square law (drivers/crl/cae.py CaeAxisCal)
    assert axes[0] == pytest.approx(((4.0 - 0.5) / 9.5) ** 2, abs=0.005)
    assert axes[2] == pytest.approx(-((2.5 - 0.5) / 9.5) ** 2, abs=0.005)
    assert np.allclose(axes[[1, 3, 4, 5]], 0.0)
    # (the client's thread steps frames while it waits, as many as its wall time allows: 5 s of
    # hold, 1600 frames, is far more than that, so the check above is inside the hold)
    rig.run_frames(1600)  # 5 s of 320 Hz frames: let go
    s = rig.reader.read_inputs()
    assert not bool(s.hc_deadman[CAE]) and np.allclose(np.asarray(s.hc_axes[CAE]), 0.0)
    texts = [m.text for m in rig.reader.messages() if m.code == MSG_HAND]
    assert texts[0].startswith("simulated CAE stick held at") and \
        texts[-1] == "simulated CAE stick released: centred, deadman up (its time ran out)"


def test_without_the_deadman_the_stick_moves_but_is_not_trusted(rig, capsys):
    rc, _, err = _hand(rig, capsys, "--deflect", "x=1", "--for", "2")
    assert rc == 0, err
    rig.run_frames(40)
    s = rig.reader.read_inputs()
    assert not bool(s.hc_deadman[CAE])


@pytest.mark.parametrize("argv,code,text", [
    (["--deflect", "q=0.3"], 2, "pfma hand: --deflect: no axis 'q' (axes: x y z roll pitch yaw)"),
    (["--deflect", "yw=0.3"], 2, "did you mean yaw?"),
    (["--deflect", "x=1.5"], 2, "'x=1.5': give NAME=VALUE with VALUE in -1..1"),
    (["--deflect", "x"], 2, "'x': give NAME=VALUE"),
    (["--deflect", "x=0.1", "--for", "11"], 2, "--for 11: at most 10 s (renew it to hold longer)"),
    (["--deadman"], 2, "--deadman goes with --deflect"),
])
def test_a_mistake_is_one_line_and_exit_2(capsys, argv, text, code):
    assert main(["hand", "--source", "cae", *argv, "--buffer", "pfma-no-such-service"]) == code
    err = capsys.readouterr().err
    assert text in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_another_source_and_a_service_without_the_simulated_rack_are_refused(capsys):
    assert main(["hand", "--source", "hid", "--deflect", "x=0.1"]) == 2
    assert "--deflect holds the simulated CAE stick (--source cae), not hid" in capsys.readouterr().err
    assert main(["hand", "--source", "cae", "--deflect", "x=0.1", "--buffer", "pfma-no-such-service"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("pfma hand: service pfma-no-such-service runs a real rack (or none): a stick is deflected "
                          "only on the simulated rack")
