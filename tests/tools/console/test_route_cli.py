"""``pfma controller route CAMERA MONITOR --wm NAME``: the console's CAMERA ROUTE request
from the command line (docs/console.md "Camera routes", docs/cameras.md). A running
controller's world model in shared memory; the CLI's real-time wait for the answer steps
the system simulator one frame per poll (deterministic, no wall-clock waits)."""

from __future__ import annotations


import pytest

from tools.cli import main



def _pfma(capsys, *argv):
    try:
        rc = main(list(argv))
    except SystemExit as e:  # argparse
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def test_a_route_from_the_cli_is_applied_by_the_service(shm_sim, capsys):
    sim, name = shm_sim
    switcher = sim.world.bus["pio_video"].switcher
    assert switcher.monitors == (0, 0)
    rc, out, err = _pfma(capsys, "controller", "route", "2", "1", "--wm", name)
    assert (rc, err) == (0, "")
    assert out == ("request 1: CAMERA ROUTE: applied by the service: monitor 1: camera 2, monitor 2: blank "
                   "-> COMPLETE\n")
    assert switcher.monitors == (2, 0)  # the fake matrix switcher latched it
    rc, out, err = _pfma(capsys, "controller", "route", "3", "2", "--wm", name)
    assert rc == 0 and "monitor 1: camera 2, monitor 2: camera 3 -> COMPLETE" in out
    rc, out, err = _pfma(capsys, "controller", "route", "0", "1", "--wm", name)  # blank monitor 1
    assert rc == 0 and "monitor 1: blank, monitor 2: camera 3 -> COMPLETE" in out
    assert switcher.monitors == (0, 3)


def test_a_switcher_that_does_not_answer_fails_with_exit_1(shm_sim, capsys):
    sim, name = shm_sim
    sim.world.bus["pio_video"].inject("switcher_silent")
    rc, out, err = _pfma(capsys, "controller", "route", "1", "2", "--wm", name)
    assert rc == 1 and err == "" and "CAMERA ROUTE" in out and out.rstrip().endswith("-> FAILED")


@pytest.mark.parametrize("argv, code, says", [
    (("route", "4", "1"), 2, "argument CAMERA: 4 is not a camera: 1..3, or 0 to blank the monitor"),
    (("route", "-1", "1"), 2, "argument CAMERA: -1 is not a camera"),
    (("route", "x", "1"), 2, "argument CAMERA: 'x' is not a whole number"),
    (("route", "2", "3"), 2, "argument MONITOR: 3 is not a monitor: 1..2"),
    (("route", "2", "0"), 2, "argument MONITOR: 0 is not a monitor"),
    (("route", "2", "one"), 2, "argument MONITOR: 'one' is not a whole number"),
    (("route", "2"), 2, "route: needs CAMERA MONITOR"),
    (("route",), 2, "route: needs CAMERA MONITOR"),
    (("route", "2", "1", "--rearm"), 2, "route: --rearm belongs to resume"),
    (("step", "3", "1"), 2, "step: takes no MONITOR"),
    (("route", "2", "1"), 1, "route: no world model 'pfma_wm_route_nobody'"),  # no controller
])
def test_bad_route_inputs_are_one_line_and_an_exit_code(capsys, argv, code, says):
    rc, out, err = _pfma(capsys, "controller", *argv, "--wm", "pfma_wm_route_nobody")
    assert rc == code and out == "" and "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("pfma controller")]
    assert len(lines) == 1 and says in lines[0], err
