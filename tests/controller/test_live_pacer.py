"""The live controller's pacer (tools.stacks.controller.LivePacer) returns once the service has
published the next frame: woken by the publish where futexes exist (bit3.futex), and still
within its bounded waits when the service does not wake it (an older service)."""

from __future__ import annotations

import contextlib
import threading
import time

import pytest

from bit3 import futex
from bit3.client import Client
from tools.stacks.controller import LivePacer

pytestmark = pytest.mark.realtime


def _publish(buf, w, frame: int, wake: bool) -> None:
    w.record["frame"] = frame
    w.publish()
    buf.set_frame(frame, frame / 320)
    if wake:
        buf.wake_frame_waiters()


@contextlib.contextmanager
def _after_frame_1(buf, shm_name, wake: bool = True):
    """A service that has published frame 1, and a client that has read it: (writer, client)."""
    buf.claim("service", "svc")
    w = buf.writer("inputs")
    _publish(buf, w, 1, wake)
    c = Client.attach(shm_name)
    try:
        c.read_inputs()
        yield w, c
    finally:
        c.close()


@pytest.mark.parametrize("wake", [True, False], ids=["service wakes", "service never wakes"])
def test_pacer_returns_on_the_next_published_frame(buf, shm_name, wake):
    with _after_frame_1(buf, shm_name, wake) as (w, c):  # the pacer now waits for frame 2
        pacer = LivePacer(c, 1 / 320)
        pacer.GIVE_UP_PERIODS = 10_000  # this test publishes when it likes: never give up
        done = threading.Event()
        t = threading.Thread(target=lambda: (pacer.wait(), done.set()))
        t.start()
        assert not done.wait(0.05)  # nothing new: still waiting
        _publish(buf, w, 2, wake)
        t.join(30.0)
        assert done.is_set() and pacer.gave_up == 0
        assert c.read_inputs().frame == 2


@pytest.mark.skipif(not futex.AVAILABLE, reason="no futex system call on this machine")
def test_pacer_sleeps_in_the_kernel_until_the_publish(buf, shm_name):
    """The pacer is asleep on the frame word (a wake finds it) rather than polling."""
    with _after_frame_1(buf, shm_name) as (w, c):
        pacer = LivePacer(c, 1 / 320)
        pacer.GIVE_UP_PERIODS = 10_000
        pacer.FUTEX_LATE_S = 60.0  # one long sleep: only a wake can end it
        t = threading.Thread(target=pacer.wait)
        t.start()
        woken = 0
        for _ in range(20000):  # until the pacer is asleep in the kernel (bounded)
            w.record["frame"] = 2
            woken = buf.wake_frame_waiters()  # a spurious wake: the pacer looks and sleeps again
            if woken:
                break
            threading.Event().wait(0.0005)
        assert woken == 1
        _publish(buf, w, 2, True)
        t.join(30.0)
        assert not t.is_alive() and pacer.gave_up == 0


def test_pacer_waits_a_whole_give_up_when_the_service_has_gone_quiet(buf, shm_name):
    """The service published its last frame long ago (it stopped): each wait still sleeps a
    whole give-up (the bound below which nothing can return early), instead of returning at
    once on a deadline in the past - the controller then spun through frames on the same
    inputs at ~50 % of a core."""
    with _after_frame_1(buf, shm_name) as (w, c):
        pacer = LivePacer(c, 1 / 320)
        pacer.stepped(time.monotonic() - 10.0)  # the last frame: 10 s ago
        for k in range(3):
            t0 = time.monotonic()
            pacer.wait()
            assert time.monotonic() - t0 >= pacer.GIVE_UP_PERIODS * pacer.period_s
            assert pacer.gave_up == k + 1
