"""The service's publish wakes readers sleeping on the header's frame word (bit3.futex).

Two mappings of one buffer in this process stand for two processes: the futex is shared
(keyed by the mapped file's page, not by the address), so a waiter on one mapping is woken
through the other. Waits are bounded by generous time-outs and the tests assert what the
kernel answered (woken, changed, timed out), never how long it took."""

from __future__ import annotations

import threading
import time

import pytest

from bit3 import futex
from bit3.buffer import Bit3Buffer

pytestmark = pytest.mark.skipif(not futex.AVAILABLE, reason="no futex system call on this machine")


def test_wait_returns_at_once_when_the_frame_moved_on(buf, shm_name):
    buf.claim("service", "svc")
    buf.set_frame(7, 0.02)
    reader = Bit3Buffer.attach(shm_name)
    try:
        assert reader.frame_word() == 7
        assert reader.wait_frame(6, 5.0) == futex.CHANGED  # frame 7 is already newer than 6
        assert reader.wait_frame(7, 0.001) == futex.TIMED_OUT  # nothing published, nobody woke it
    finally:
        reader.close()


@pytest.mark.realtime
def test_publish_wakes_a_waiter_on_another_mapping(buf, shm_name):
    buf.claim("service", "svc")
    buf.set_frame(41, 0.1)
    reader = Bit3Buffer.attach(shm_name)
    got: list[str] = []
    t = threading.Thread(target=lambda: got.append(reader.wait_frame(reader.frame_word(), 60.0)))
    try:
        t.start()
        woken = 0
        for _ in range(20000):  # wake until the waiter was asleep in the kernel (bounded)
            woken = buf.wake_frame_waiters()
            if woken:
                break
            time.sleep(0.0005)
        t.join(60.0)
        assert woken == 1 and got == [futex.WOKEN]  # found through the other mapping
        # the usual order: the word changes (set_frame), then the wake; a waiter that comes
        # after the change does not sleep at all
        buf.set_frame(42, 0.103)
        assert buf.wake_frame_waiters() == 0
        assert reader.wait_frame(41, 60.0) == futex.CHANGED
    finally:
        t.join(60.0)
        reader.close()


def test_the_frame_word_is_the_counters_low_32_bits(buf, shm_name):
    buf.claim("service", "svc")
    buf.set_frame(0x1_0000_0005, 1.0)
    assert buf.frame_word() == 5
    assert buf.wait_frame(4, 1.0) == futex.CHANGED
    buf.close()  # the futex address is taken without keeping an export: close works
