"""tests/controller/_live_support.py's power_up_holding: a new power-up only after the one
fault a loaded host causes (missed service frames), named in the controller's output; any
other loss of the pose fails with that output. Small Python processes stand in for the
controller (the helper reads only their exit and output)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.controller._live_support import HostTimingFault, host_timing_named, power_up_holding


def _controller(text: str) -> subprocess.Popen:
    """A stand-in controller that has printed ``text`` when this returns (it then closes a
    second pipe, waited for here) and runs until stopped."""
    r, w = os.pipe()
    p = subprocess.Popen([sys.executable, "-c", f"import os, time\nprint({text!r}, flush=True)\nos.close({w})\n"
                          "time.sleep(30)"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         pass_fds=(w,))
    os.close(w)
    os.read(r, 1)  # EOF: the child printed and closed its end
    os.close(r)
    return p


def _say(text: str):
    return lambda: _controller(text)


def _armed(pattern: list[bool]):
    """armed() answers from ``pattern`` in turn, then True."""
    it = iter(pattern)
    return lambda: next(it, True)


def test_a_missed_frames_fault_starts_a_new_power_up():
    starts = []

    def start():
        starts.append(1)
        return _controller("servo ERROR fault 12: controller missed service frames 88..91")
    # first attempt: armed, then dropped while holding; second: armed and holding
    ctl = power_up_holding(start, _armed([True, False]), hold_s=0.0)
    try:
        assert len(starts) == 2 and ctl.poll() is None
    finally:
        ctl.kill()
        ctl.communicate()


def test_another_cause_fails_with_the_controllers_output():
    with pytest.raises(AssertionError, match="the arm did not hold its pose\nfault 1: shoulder_pitch"):
        power_up_holding(_say("fault 1: shoulder_pitch following error"), _armed([True, False]), hold_s=0.0)


def test_three_missed_frames_faults_in_a_row_fail():
    with pytest.raises(HostTimingFault, match="3 power-ups in a row ended in a host-timing fault"):
        power_up_holding(_say("fault 12: controller missed service frames"), _armed([True, False] * 3), hold_s=0.0)


def test_a_stale_heartbeat_trip_starts_a_new_power_up_too():
    starts = []

    def start():
        starts.append(1)
        return _controller("daq ERROR service: command stale +1: outputs safe: stale heartbeat 15.3>15 ms (code 16)")
    ctl = power_up_holding(start, _armed([False] * 400 + [True]), hold_s=0.0)
    try:
        assert len(starts) >= 1 and ctl.poll() is None
    finally:
        ctl.kill()
        ctl.communicate()


def test_the_catch_up_warning_is_not_a_host_timing_fault():
    """The controller's own catch-up line is how it rides through a late frame, not a fault."""
    with pytest.raises(AssertionError, match="the arm did not hold its pose") as e:
        power_up_holding(_say("runtime WARNING missed service frames 12..13 (2): caught up servo_control"),
                         _armed([True, False]), hold_s=0.0)
    assert not isinstance(e.value, HostTimingFault)


def test_host_timing_named_names_the_cause_from_the_output_and_passes_other_failures(tmp_path):
    log = tmp_path / "controller.log"
    log.write_text("servo ERROR fault 12: controller missed service frames 1000..1002 (3 in a row > max_missed_run 2)\n")
    with pytest.raises(HostTimingFault, match="^the host, not the software: fault 12: controller missed service "
                                              "frames 1000..1002") as e:
        with host_timing_named(log):
            raise AssertionError("gripper request 1: OPEN -> REFUSED")
    assert "gripper request 1" in str(e.value)
    piped = _controller("service: command stale (computed from inputs frame 676, 7 frames old)")
    with pytest.raises(HostTimingFault, match="command stale"):
        with host_timing_named(lambda: piped):
            raise AssertionError("never armed")
    assert piped.poll() is not None  # stopped to read its output
    log.write_text("joint ERROR fault 1: shoulder_pitch following error\n")
    with pytest.raises(AssertionError, match="^tool did not move$") as e:
        with host_timing_named(log, lambda: None):
            raise AssertionError("tool did not move")
    assert not isinstance(e.value, HostTimingFault)


def test_a_pytest_fail_naming_a_host_timing_cause_is_a_host_timing_fault_too():
    """CI (this stop's fresh clone): test_moves_live failed through ``pytest.fail`` with the
    controller's "command stale" in its text, which is not an AssertionError, so it was not
    run again."""
    with pytest.raises(HostTimingFault, match="^the host, not the software: command stale"):
        with host_timing_named():
            pytest.fail("move 1 stopped\n--- the controller ---\nservice: command stale (computed from "
                        "inputs frame 2016, 5 frames old)")
    with pytest.raises(pytest.fail.Exception, match="^move 1 stopped: a wall$"):
        with host_timing_named():
            pytest.fail("move 1 stopped: a wall")


@pytest.mark.parametrize("line, cause", [
    ("servo ERROR fault 12: controller missed service frames 1000..1002 (3 in a row > max_missed_run 2): x",
     "fault 12: controller missed service frames 1000..1002 (3 in a row > max_missed_run 2): x"),
    ("outputs safe: stale heartbeat 15.3>15 ms (code 16)", "stale heartbeat 15.3>15 ms (code 16)"),
    ("service: command stale (computed from inputs frame 1332, 5 frames old)",
     "command stale (computed from inputs frame 1332, 5 frames old)"),
    ("daq ERROR fault 32: service frame 998 unchanged for 4 frames", "fault 32: service frame 998 unchanged for 4 frames"),
    ("runtime WARNING missed service frames 1812..1813 (2): caught up servo_control", None),
    ("joint ERROR fault 1: shoulder_pitch following error 2.1 deg", None),
    ("service: command foreign writer (computed from inputs frame 10282, 1 frames old)", None),
])
def test_host_timing_causes_are_the_hosts_only(line, cause):
    from pfma.process import host_timing_cause
    assert host_timing_cause("prefix\n" + line + "\nnext line") == cause
