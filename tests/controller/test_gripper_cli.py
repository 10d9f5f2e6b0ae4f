"""``pfma controller gripper open|close|stop [--force N] --wm NAME`` and the gripper line of
``pfma wm`` against a running controller's world model in shared memory (the system
simulator): the CLI's real-time wait for the answer steps the simulator one frame per poll
(deterministic, no wall-clock waits)."""

from __future__ import annotations


import pytest

from pfma.arm import GRIPPER
from tools.cli import main



def _pfma(capsys, *argv):
    try:
        rc = main(list(argv))
    except SystemExit as e:  # argparse
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def test_open_close_and_force_from_the_cli_move_the_jaw(shm_sim, capsys):
    sim, name = shm_sim
    arm = sim.world.sim.arm
    rc, out, err = _pfma(capsys, "controller", "gripper", "close", "--wm", name)
    assert (rc, err) == (1, "")  # powered down: refused, said on stdout as every answer is
    assert out == ("gripper request 1: CLOSE: Servo Control is SHUT DOWN: the gripper drive is off (power up "
                   "first) -> REFUSED\n")
    sim.power_up()
    sim.step(20)
    arm.q[6] = 0.095
    rc, out, err = _pfma(capsys, "controller", "gripper", "open", "--wm", name)
    assert (rc, err) == (0, "")
    lines = out.splitlines()
    assert lines[0] == "gripper request 2: OPEN: OPENING at 20 mm/s, 40 N -> IN PROGRESS"
    assert lines[1].startswith("gripper request 2: OPEN: at the open stop after ") and lines[1].endswith("-> COMPLETE")
    assert len(lines) == 2 and arm.q[6] == pytest.approx(GRIPPER.travel_m, abs=2e-4)
    arm.place_jaw_object(0.09)
    rc, out, err = _pfma(capsys, "controller", "gripper", "close", "--force", "60", "--wm", name)
    assert (rc, err) == (0, "")
    assert out.splitlines()[0] == "gripper request 3: CLOSE: CLOSING at 20 mm/s, 60 N -> IN PROGRESS"
    assert "GRIPPING after" in out and "holding at 60 N; jaw ~90 mm -> COMPLETE" in out
    sim.step(160)
    assert arm.q[6] == pytest.approx(0.09, abs=2e-4) and abs(arm.jaw_force_n - 60.0) <= GRIPPER.coulomb_n + 0.5
    rc, out, err = _pfma(capsys, "controller", "gripper", "--force", "100", "--wm", name)
    assert (rc, out, err) == (0, "gripper request 4: FORCE: grip force 100 N, current limit 2.5 A -> COMPLETE\n", "")
    sim.step(160)
    assert abs(arm.jaw_force_n - 100.0) <= GRIPPER.coulomb_n + 0.5
    # pfma wm shows the gripper under its header
    rc, out, err = _pfma(capsys, "wm", "get", "gripper.state", "--wm", name)
    assert rc == 0 and "gripper GRIPPING  grip 100 N set, motor 100 N  jaw ~90 mm (tach estimate)" in out.splitlines()[1]
    rc, out, err = _pfma(capsys, "controller", "gripper", "stop", "--wm", name)
    assert (rc, err) == (0, "") and out.startswith("gripper request 5: STOP: stopped (GRIPPING ended), jaw ~90 mm")


@pytest.mark.parametrize("argv, code, says", [
    (("gripper", "grab"), 2, "gripper takes open, close or stop, not 'grab'"),
    (("gripper", "close", "--force", "500"), 2, "--force: grip force 500 N is outside 10..200 N (current limit "
                                                "0.25..5 A at 40 N/A)"),
    (("gripper", "close", "--force", "5"), 2, "grip force 5 N is outside 10..200 N"),
    (("gripper", "close", "--force", "-3"), 2, "argument --force"),
    (("gripper",), 2, "gripper: needs open, close or stop (and/or --force N)"),
    (("gripper", "open", "--rearm"), 2, "gripper: takes open|close|stop and --force N only"),
    (("halt", "--force", "50"), 2, "--force belongs to `pfma controller gripper`"),
    (("gripper", "close"), 1, "gripper: no world model 'pfma_wm_gripper_nobody'"),  # no controller
])
def test_bad_gripper_inputs_are_one_line_and_an_exit_code(capsys, argv, code, says):
    rc, out, err = _pfma(capsys, "controller", *argv, "--wm", "pfma_wm_gripper_nobody")
    assert rc == code and out == "" and "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("pfma controller")]
    assert len(lines) == 1 and says in lines[0], err
