"""pfma.process.HelperWatch: a helper process that ends while the service runs is said and
started again; a restart that fails is said and tried again after the back-off.

The helpers are real processes (a few lines of Python that print a first line and wait);
the watch's clock is a counter the test moves, so the look interval and the back-off are
deterministic. Marked realtime: it starts processes and waits (bounded) for their lines."""

from __future__ import annotations

import signal
import sys
import time

import pytest

from pfma.process import NO_WORD, READY_WITHIN_S, RESTART_BACKOFF_S, WATCH_EVERY_S, HelperWatch, first_line, spawn_helper

pytestmark = pytest.mark.realtime

UP = "helper up"
#: prints its first line (the argument; nothing for "") and waits to be stopped
SCRIPT = "import sys, time; sys.argv[1] and print(sys.argv[1], flush=True); time.sleep(120)"


class Helper:
    label = "test helper"
    lost = "nothing is helped until it is back"

    def __init__(self, lines: list[str]) -> None:
        self.lines = lines  # the first line of each start, in order (the last repeats)
        self.starts = 0
        self.proc = None

    def spawn(self):
        line = self.lines[min(self.starts, len(self.lines) - 1)]
        self.starts += 1
        self.proc = spawn_helper([sys.executable, "-c", SCRIPT, line])
        return self.proc

    def accept(self, line: str) -> str:
        return "" if line == UP else (line.removeprefix("error: ") or NO_WORD)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _watch() -> tuple[list[tuple[bool, str]], Clock, HelperWatch]:
    """(what the watch said: (error, text) each, its clock, the watch)."""
    said: list[tuple[bool, str]] = []
    clock = Clock()
    return said, clock, HelperWatch(lambda err, text: said.append((err, text)), now=clock)


def _started(h: Helper) -> None:
    h.spawn()
    assert first_line(h.proc, 30.0) == UP


def _tick_until(watch: HelperWatch, clock: Clock, cond, what: str) -> None:
    """Tick once per look interval (the test's clock) until ``cond``; the helper's own start
    is waited for in wall time, bounded."""
    end = time.monotonic() + 30.0
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"not within 30 s: {what}")
        clock.t += WATCH_EVERY_S
        watch.tick()
        time.sleep(0.01)


def test_a_helper_that_is_killed_is_said_and_started_again():
    said, clock, watch = _watch()
    h = Helper([UP])
    try:
        _started(h)
        watch.add(h)
        watch.tick()
        assert said == []  # running: nothing to say
        first = h.proc.pid
        h.proc.send_signal(signal.SIGKILL)
        h.proc.wait()
        clock.t += 0.1  # within the look interval: not looked at yet
        watch.tick()
        assert said == []
        _tick_until(watch, clock, lambda: watch.restarts == 1, "the restart")
        assert said[0] == (True, f"test helper (pid {first}) ended (killed by SIGKILL): "
                                 "nothing is helped until it is back; restarting it")
        assert said[1] == (False, f"test helper restarted: pid {h.proc.pid}")
        assert h.proc.pid != first and h.proc.poll() is None and h.starts == 2
        watch.remove(h)
        h.proc.kill()
        h.proc.wait()
        clock.t += 10
        watch.tick()
        assert len(said) == 2  # removed before an orderly stop: not restarted
    finally:
        h.stop()


def test_a_restart_that_fails_is_said_and_tried_again_after_the_back_off():
    said, clock, watch = _watch()
    h = Helper([UP, "error: port 5020 in use", UP])
    try:
        _started(h)
        watch.add(h)
        h.proc.terminate()
        h.proc.wait()
        _tick_until(watch, clock, lambda: len(said) >= 2, "the failed restart")
        assert said[0][1].startswith("test helper (pid ") and "ended (killed by SIGTERM)" in said[0][1]
        assert said[1] == (True, f"test helper did not restart: port 5020 in use; trying again in "
                                 f"{RESTART_BACKOFF_S[0]:g} s")
        assert h.proc is None and h.starts == 2
        t_failed = clock.t
        _tick_until(watch, clock, lambda: watch.restarts == 1, "the second restart")
        assert clock.t - t_failed >= RESTART_BACKOFF_S[0]  # not before the back-off
        assert said[2] == (False, f"test helper restarted: pid {h.proc.pid}") and h.starts == 3
    finally:
        h.stop()


def test_a_helper_that_says_nothing_is_given_up_after_its_window():
    said, clock, watch = _watch()
    h = Helper([UP, ""])  # the restarted one prints nothing
    try:
        _started(h)
        watch.add(h)
        h.proc.kill()
        h.proc.wait()
        clock.t += WATCH_EVERY_S
        watch.tick()  # said, spawned
        silent = h.proc
        assert said[-1][1].endswith("restarting it") and silent.poll() is None
        clock.t += WATCH_EVERY_S
        watch.tick()  # still within its window: waited for
        assert len(said) == 1
        clock.t += READY_WITHIN_S
        watch.tick()
        assert said[-1] == (True, f"test helper did not restart: no ready line within {READY_WITHIN_S:g} s; "
                                  f"trying again in {RESTART_BACKOFF_S[0]:g} s")
        assert silent.poll() is not None  # killed, not left behind
    finally:
        h.stop()


def test_half_a_line_is_kept_and_never_blocks():
    """A helper that prints part of its first line: first_line returns None within its
    time-out (the service's thread is never held), keeps the part, and gives the whole line
    once the rest arrives (3 s later: a test process held up that long could see both parts at once)."""
    p = spawn_helper([sys.executable, "-c", "import sys, time; sys.stdout.write('half'); sys.stdout.flush(); "
                                            "time.sleep(3); print(' a line', flush=True); time.sleep(60)"])
    try:
        end = time.monotonic() + 30.0
        while getattr(p, "_pfma_first_line", b"") != b"half":  # the part arrives
            # None, not the whole line a second later: a read to the newline would block
            assert first_line(p, 0.1) is None
            assert time.monotonic() < end, "the part never came"
        assert first_line(p, 30.0) == "half a line"
        assert p.stdout.closed
    finally:
        p.kill()
        p.wait()
