"""tests/controller/_live_support.py's power_up_holding: a new power-up only after the one
fault a loaded host causes (missed service frames), named in the controller's output; any
other loss of the pose fails with that output. Small Python processes stand in for the
controller (the helper reads only their exit and output)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.controller._live_support import power_up_holding


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
    with pytest.raises(AssertionError, match="3 power-ups in a row ended in missed service frames"):
        power_up_holding(_say("fault 12: controller missed service frames"), _armed([True, False] * 3), hold_s=0.0)
