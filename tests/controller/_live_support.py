"""What the tests of live processes (``pfma serve``, ``pfma controller``) share: bounded
polling, an orderly end of every process a test started, and whether this user may run
SCHED_FIFO (``RT``)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pfma.process import host_timing_cause


def fifo_permitted() -> bool:
    """Whether this user may run SCHED_FIFO (root in CI)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return True
    except (OSError, AttributeError):
        return False


#: the flag live tests that fly the arm give ``pfma serve`` and ``pfma controller``: where
#: SCHED_FIFO is permitted both run with ``--realtime``, as a lab's should
#: (docs/deployment.md), so a loaded 2-core host's stalls do not stop the arm before the
#: test's point is reached (the suite's own default is PFMA_REALTIME=off: tests/conftest.py)
RT = ["--realtime"] if fifo_permitted() else []


#: The functional live tests (the gripper, a move, the stick, the shoulder-roll index, the
#: supervision's trips, each through real processes) run with the timing limits widened by 4
#: frames (12.5 ms): the service refuses a rate command older than 8 frames instead of 4 (and
#: its watchdog, which must cover that age, is 25 ms instead of 15), the controller's servo
#: fault 12 comes after 7 missed frames in a row instead of 3 (`pfma serve --max-input-age
#: --watchdog-ms`, `pfma controller --max-missed-run`: what a lab on a slow PC sets;
#: docs/controller.md "Missed frames and command freshness"). Why: on this project's
#: 2-core VMs the controller's frame costs p50 ~1 ms, p99 ~2.2 ms of the 3.125 ms period and
#: wakes 0.4-0.7 ms after the service's frame (measured 2026-11-29, `pfma stats` beside a live
#: `pfma serve --rack fake`), so a 3-frame run happened about once a minute even on the quiet
#: machine and in every attempt of two tests on CI's loaded one. These tests prove what the
#: processes do together; the default limits and what happens past them are proved in simulated
#: time (tests/controller/test_missed_frames.py, tests/ioservice/test_stall_freshness.py), by
#: the kill matrix and by the soak, which run the defaults.
SLOW_HOST_SERVICE = ["--max-input-age", "8", "--watchdog-ms", "25"]
SLOW_HOST_CONTROLLER = ["--max-missed-run", "6"]

#: the checkout's root and the ``pfma`` command as the live tests run it
ROOT = Path(__file__).resolve().parents[2]
PY = [sys.executable, "-m", "tools.cli"]


def live_inputs(name: str):
    """The newest Bit3 inputs of the service on buffer ``name`` (None: not up yet)."""
    from bit3.client import Client
    try:
        with Client.attach(name) as c:
            return c.read_inputs()
    except Exception:  # noqa: BLE001 - not up yet
        return None


def armed_and_released(name: str) -> bool:
    """The service on ``name`` ARMED with the brakes released (a powered-up arm)."""
    from bit3.layout import ServiceState
    s = live_inputs(name)
    return s is not None and s.service_state == ServiceState.ARMED and bool(s.brakes_released)


def wait_for(pred, timeout_s: float = 20.0) -> bool:
    """Poll ``pred`` every 50 ms until it is true or ``timeout_s`` has passed (a subprocess
    is waited for: bounded polling, not a sleep standing in for the world)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.05)
    return False


def stop(*procs: subprocess.Popen | None) -> None:
    """SIGTERM each process still running, then SIGKILL one that does not end in 10 s."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


class HostTimingFault(AssertionError):
    """A live test's failure that came with a host-timing cause (``pfma.process.HOST_TIMING_CAUSE``:
    a servo fault 12, the service's stale-heartbeat trip, a stale command) in what its
    processes printed: the host broke the run, not the software under test."""


#: a live test marked with this runs once more, at most twice, when it failed with a
#: :class:`HostTimingFault` (pytest-rerunfailures; each rerun shows as R and in the summary);
#: any other failure, and the third host-timing one, fails it
RERUN_ON_HOST_TIMING = pytest.mark.flaky(reruns=2, only_rerun=["^HostTimingFault: "])


def _output_of(src) -> str:
    """What ``src`` printed: a log file's text, a piped process's output (the process is
    stopped first; "" when its output was read already), or a string as it is."""
    if isinstance(src, Path):
        return src.read_text(errors="replace") if src.exists() else ""
    if isinstance(src, subprocess.Popen):
        if src.stdout is None or src.stdout.closed:
            return ""
        stop(src)
        try:
            return src.communicate(timeout=30)[0] or ""
        except (subprocess.TimeoutExpired, ValueError, OSError):
            return ""
    return str(src or "")


@contextlib.contextmanager
def host_timing_named(*sources):
    """Around a live test's body: an AssertionError (or ``pytest.fail``) whose message, or whose processes' output
    (``sources``: log files, piped Popens, or a callable giving one, e.g. ``lambda: ctl``;
    read after the failure), names a host-timing cause becomes a :class:`HostTimingFault` saying
    that cause first (and, with :data:`RERUN_ON_HOST_TIMING`, runs the test again). Any other
    failure passes through unchanged."""
    try:
        yield
    except HostTimingFault:
        raise
    except (AssertionError, pytest.fail.Exception) as err:  # a failed assert, or pytest.fail(...)
        texts = (_output_of(s() if callable(s) else s) for s in sources)
        cause = host_timing_cause(str(err)) or next((c for c in map(host_timing_cause, texts) if c), None)
        if cause is None:
            raise
        raise HostTimingFault(f"the host, not the software: {cause}\n{err}") from err


def power_up_holding(start, armed, hold_s: float = 0.5, attempts: int = 3, log=None) -> subprocess.Popen:
    """Start a live controller that powers up (``start()`` returns its Popen, stdout piped as
    text, or written to the file ``log``) and return it once the arm is powered up (``armed()``: the service ARMED with the
    brakes released) and still is after ``hold_s`` of holding its pose.

    A controller descheduled for more than ``max_missed_run`` service frames in a row is a
    servo fault (code 12, "missed service frames"; tests/controller/test_missed_frames.py), as
    in any running controller: a loaded 2-core CI host did it 0.8 s after power-up even under
    SCHED_FIFO; the service's watchdog trips on its late heartbeat or command the same way.
    Those causes (``pfma.process.HOST_TIMING_CAUSE``), named in the controller's output, start
    a new controller (at most ``attempts`` in all); any other way of not holding the pose fails
    the test with the controller's output."""
    outs = []
    for _ in range(attempts):
        ctl = start()
        up = wait_for(armed)
        if up:
            time.sleep(hold_s)  # holding its pose
            if armed() and ctl.poll() is None:
                return ctl
        stop(ctl)
        out = (ctl.communicate(timeout=30)[0] or "") if log is None else log.read_text()
        outs.append(out)
        assert host_timing_cause(out), ("the controller never powered up" if not up else
                                        "the arm did not hold its pose") + "\n" + out
    raise HostTimingFault(f"{attempts} power-ups in a row ended in a host-timing fault "
                          f"({host_timing_cause(outs[-1])}):\n" + "\n".join(outs))


def powered_controller(name: str, *args: str) -> subprocess.Popen:
    """``pfma controller --buffer NAME --wm none --power-up ARGS`` (real time where permitted,
    the limits of :data:`SLOW_HOST_CONTROLLER`, its output piped as text), once the arm is
    powered up and holds (:func:`power_up_holding`)."""
    return power_up_holding(
        lambda: subprocess.Popen([*PY, "controller", "--buffer", name, "--wm", "none", "--power-up", *args, *RT,
                                  *SLOW_HOST_CONTROLLER], cwd=ROOT, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True),
        lambda: armed_and_released(name))


def start_service(name: str, *args: str) -> subprocess.Popen:
    """``pfma serve --buffer NAME ARGS`` (real time where permitted, the age limit of
    :data:`SLOW_HOST_SERVICE`, output discarded), once it
    publishes frames (a service on a loaded host can take a while before its first); stopped,
    its buffer removed and the test failed when it does not."""
    serve = subprocess.Popen([*PY, "serve", "--buffer", name, *args, *RT, *SLOW_HOST_SERVICE], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if not wait_for(lambda: (s := live_inputs(name)) is not None and int(s.frame) > 10):
        stop(serve)
        from bit3.buffer import Bit3Buffer
        Bit3Buffer.unlink(name)
        raise AssertionError(f"the service on {name} did not come up")
    return serve

