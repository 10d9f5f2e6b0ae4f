"""The shoulder-roll index from the command line (issue 30 item 2): ``pfma controller
--shoulder-roll DEG``, ``pfma serve --shoulder-roll DEG`` and ``pfma wm set
joint.shoulder_roll_deg``; another value is refused naming the index positions, and a
power-up on a rack the service does not report as simulated needs the index said. In
process; the simulator runs in simulated time."""

from __future__ import annotations

import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.layout import default_layout
from controller.worldmodel import WorldModel
from sim.system import SystemSimulator
from tests.controller import _wm_support as sup
from tools.cli import main

POSITIONS = "-90 deg, -45 deg, 0 deg, +45 deg, +90 deg (45 deg steps, pfma-model 8.1)"


def pfma(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("verb", [["controller", "--sim"], ["serve", "--duration", "1"]])
@pytest.mark.parametrize("value", ["30", "45.5", "-135", "up"])
def test_another_value_is_a_usage_error_naming_the_positions(capsys, verb, value):
    with pytest.raises(SystemExit) as e:
        main([*verb, "--shoulder-roll", value])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --shoulder-roll" in err
    assert POSITIONS in err or "is not a number" in err
    assert "Traceback" not in err


def test_controller_sim_pins_arm_and_controller_at_the_index_and_reports_it(capsys):
    rc, out, err = pfma(capsys, "controller", "--sim", "--wm", "none", "--shoulder-roll", "-45", "--power-up",
                        "--duration", "0.4", "--messages", "0", "-q")
    assert rc == 0, err
    assert "power-up with the shoulder-roll index -45 deg (the simulated arm is pinned there too)" in out
    assert ("shoulder-roll index -45 deg (joint.shoulder_roll_deg); the kinematics use -45 deg; the simulated "
            "arm is pinned at -45 deg") in out
    assert "UPDN=START UP COMPLETE" in out


def test_a_power_up_on_a_rack_not_reported_simulated_needs_the_index_said(capsys):
    """A buffer no simulated service has claimed: its rack is "unknown", so the operator must
    say where the roll is pinned (the joint has no sensor); nothing is powered up."""
    name = "pfma-test-roll-" + uuid.uuid4().hex[:6]
    buf = Bit3Buffer.create(name, default_layout())
    try:
        rc, out, err = pfma(capsys, "controller", "--buffer", name, "--wm", "none", "--power-up", "--duration", "0.1")
        assert rc == 2 and out == ""
        assert err.splitlines()[-1] == (
            "pfma controller: the shoulder roll is indexed by hand and has no sensor: --power-up on an unknown rack "
            f"needs --shoulder-roll DEG, the index the joint is pinned at ({POSITIONS}); check the joint, then say "
            "it (the controller's is 0 deg)")
    finally:
        buf.close(unlink=True)


def test_a_running_controllers_index_is_set_by_pfma_wm_set_and_refused_otherwise(capsys, monkeypatch):
    monkeypatch.delenv("PFMA_WM_KEY", raising=False)
    name = sup.unique_name()
    try:
        with SystemSimulator(wm_name=name) as sim:
            sim.step(5)
            key = sim.rt.wm.access_key
            rc, _, err = pfma(capsys, "wm", "set", "joint.shoulder_roll_deg", "30", "--key", key, "--wait", "0",
                              "--name", name)
            assert (rc, err) == (1, "pfma wm: joint.shoulder_roll_deg: 30 deg is not one of its values (-90, -45, "
                                    "0, 45, 90 deg)\n")
            rc, _, err = pfma(capsys, "wm", "set", "joint.shoulder_roll_deg", "+45", "--key", key, "--wait", "0",
                              "--name", name)
            assert rc == 0, err
            sim.step(1)
            assert sim.rt.wm.get("joint.shoulder_roll_deg") == 45.0
            sim.power_up()
            rc, _, err = pfma(capsys, "wm", "set", "joint.shoulder_roll_deg", "0", "--key", key, "--wait", "0",
                              "--name", name)
            assert (rc, err) == (1, "pfma wm: joint.shoulder_roll_deg is protected: it may be set only while powered "
                                    "down (the system is powered up)\n")
    finally:
        WorldModel.remove_segment(name)


@pytest.mark.parametrize("argv,text", [
    (["serve", "--rack", "pfma/rack_default.toml", "--bus", "modbus://127.0.0.1:1", "--shoulder-roll", "45"],
     "pfma serve: --shoulder-roll pins the simulated arm (--rack fake); a real arm's shoulder roll is pinned by "
     "hand (tell the controller: pfma controller --shoulder-roll DEG)"),
    (["controller", "halt", "--shoulder-roll", "45"],
     "pfma controller halt: takes no --shoulder-roll (a running controller's index: `pfma wm set "
     "joint.shoulder_roll_deg DEG` while it is powered down)"),
])
def test_shoulder_roll_where_it_does_not_belong_is_one_line_exit_2(capsys, argv, text):
    rc, out, err = pfma(capsys, *argv)
    assert (rc, out, err) == (2, "", text + "\n")
