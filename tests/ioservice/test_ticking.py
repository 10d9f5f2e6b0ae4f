"""TickingClock: hooks between ticks, and the once-per-sleep pre-deadline hooks (simulated time)."""

from __future__ import annotations

import pytest

from ioservice.ticking import TickingClock
from pfma.clock import SimClock


def test_hooks_run_at_each_intermediate_tick_and_not_at_the_deadline():
    clock = TickingClock(SimClock(), tick_s=0.001)
    seen: list[float] = []
    clock.hooks.append(seen.append)
    clock.sleep_until(0.0035)
    assert seen == pytest.approx([0.001, 0.002, 0.003])
    assert clock.now() == pytest.approx(0.0035)


def test_pre_deadline_hooks_run_once_per_sleep_within_their_lead():
    clock = TickingClock(SimClock(), tick_s=0.0004, pre_deadline_s=0.0008)
    pre: list[float] = []
    ticks: list[float] = []
    clock.pre_deadline_hooks.append(pre.append)
    clock.hooks.append(ticks.append)
    clock.sleep_until(0.003125)
    assert len(pre) == 1
    assert 0.003125 - 0.0008 <= pre[0] < 0.003125  # within the lead, before the deadline
    assert len(ticks) >= 6  # the ordinary ticks still run every 0.4 ms
    assert pre[0] in ticks  # and once right after the pre-deadline hooks (a serial drain)
    clock.sleep_until(0.00625)  # the next frame's sleep runs them again, once
    assert len(pre) == 2 and 0.00625 - 0.0008 <= pre[1] < 0.00625


def test_pre_deadline_hooks_run_at_once_when_the_sleep_is_shorter_than_the_lead():
    clock = TickingClock(SimClock(), tick_s=0.0004)
    pre: list[float] = []
    ticks: list[float] = []
    clock.pre_deadline_hooks.append(pre.append)
    clock.hooks.append(ticks.append)
    clock.sleep_until(0.0005)  # a frame that overran leaves 0.5 ms: less than the 0.8 ms lead
    assert pre == [0.0]
    assert ticks == pytest.approx([0.0, 0.0004])  # right after them, then every tick as before
    assert clock.now() == pytest.approx(0.0005)


def test_default_lead_is_two_ticks():
    assert TickingClock(SimClock(), tick_s=0.0004).pre_deadline_s == pytest.approx(0.0008)
