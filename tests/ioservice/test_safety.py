"""The output guard in simulated time."""

import pytest

from ioservice.safety import OutputGuard, ServiceState
from pfma.clock import SimClock

P = 1 / 320


def make():
    clock = SimClock()
    posted = []
    g = OutputGuard(clock, watchdog_s=0.015, post=lambda s, c, t: posted.append((s, c, t)))
    return clock, g, posted


def run(clock, g, frames, hb_start, arm_enable=True, arm_request=1, rates_zero=True, beat=True):
    live = []
    hb = hb_start
    for _ in range(frames):
        clock.advance(P)
        if beat:
            hb += 1
        live.append(g.update(hb, arm_enable, arm_request, rates_zero))
    return live, hb


def test_starts_safe_and_arms_only_on_explicit_fresh_request_with_zero_rates():
    clock, g, posted = make()
    assert g.state == ServiceState.SAFE
    live, hb = run(clock, g, 5, 0, arm_enable=False)
    assert not any(live)
    live, hb = run(clock, g, 3, hb, rates_zero=False)  # nonzero rates: refused, once
    assert not any(live) and any("rate commands must be 0" in t for _, _, t in posted)
    live, hb = run(clock, g, 3, hb, arm_request=1)  # the same request never arms again
    assert not any(live)
    live, hb = run(clock, g, 3, hb, arm_request=2)
    assert all(live) and g.state == ServiceState.ARMED


def test_stale_heartbeat_trips_within_watchdog_plus_one_frame_and_latches():
    clock, g, posted = make()
    live, hb = run(clock, g, 2, 0, arm_request=1)
    assert live == [False, True]  # the first frame cannot judge the heartbeat fresh
    assert g.state == ServiceState.ARMED
    t_last_beat = clock.now()
    tripped_at = None
    for _ in range(20):  # the controller dies: heartbeat stops
        clock.advance(P)
        if not g.update(hb, True, 1, True):
            tripped_at = clock.now()
            break
    assert tripped_at is not None
    assert tripped_at - t_last_beat <= 0.015 + P
    assert g.state == ServiceState.FAULT and "stale" in g.reason
    assert posted[-1][0] == 2 and "outputs safe" in posted[-1][2]
    live, hb = run(clock, g, 10, hb, arm_request=1)  # heartbeat back, same request: stays safe
    assert not any(live) and g.state == ServiceState.FAULT
    live, hb = run(clock, g, 2, hb, arm_request=2)  # explicit re-arm
    assert all(live) and g.state == ServiceState.ARMED and g.trips == 1


def test_disarm_by_command_is_not_a_fault():
    clock, g, _ = make()
    _, hb = run(clock, g, 2, 0, arm_request=1)
    live, hb = run(clock, g, 1, hb, arm_enable=False)
    assert live == [False] and g.state == ServiceState.SAFE and g.trips == 0


def test_unexplained_fault_trips_and_watchdog_must_be_positive():
    clock, g, _ = make()
    run(clock, g, 2, 0, arm_request=1)
    g.trip("frame raised ZeroDivisionError")
    assert g.state == ServiceState.FAULT
    with pytest.raises(ValueError):
        OutputGuard(clock, watchdog_s=0)
