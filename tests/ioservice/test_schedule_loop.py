"""Acquisition schedule and frame loop, in simulated time."""

import pytest

from ioservice.loop import FrameLoop
from ioservice.schedule import MINOR_FRAMES_PER_MAJOR, Schedule
from pfma.clock import SimClock
from pfma.errors import ConfigError


def test_default_schedule_keeps_documented_rates():
    s = Schedule()
    assert s.period_s == pytest.approx(1 / 320)
    assert s.rate_hz("dac") == 320 and s.rate_hz("rtd") == 160 and s.rate_hz("adc") == 160
    assert s.rate_hz("ft") == 80 and s.rate_hz("hand") == 80
    assert s.check_documented_rates() == []
    table = s.frame_table()
    assert len(table) == MINOR_FRAMES_PER_MAJOR
    count = lambda t: sum(t in frame for frame in table)
    assert (count("dac"), count("rtd"), count("adc"), count("ft"), count("pio")) == (16, 8, 8, 4, 2)


@pytest.mark.parametrize("cfg,words", [
    ({"tasks": {"rtd": {"divider": 3}}}, "must divide"),
    ({"tasks": {"ft": {"divider": 4, "phase": 4}}}, "phase 4"),
    ({"tasks": {"bogus": {"divider": 1}}}, "unknown task"),
    ({"tasks": {"dac": {"divider": 2}}}, "must run every frame"),
    ({"frame_rate_hz": 0}, "outside"),
    ({"rate": 320}, "unknown key"),
])
def test_invalid_schedule_refused(cfg, words):
    with pytest.raises(ConfigError, match=words):
        Schedule.from_config(cfg)


def test_slower_schedule_reports_rate_difference():
    s = Schedule.from_config({"tasks": {"rtd": {"divider": 4, "phase": 1}}})
    assert s.check_documented_rates() == ["rtd: 80 Hz (documented 160 Hz)"]


def test_1khz_profile_keeps_rates_at_or_above_documented():
    s = Schedule.scaled(1000.0)
    assert s.rate_hz("dac") == 1000
    assert s.rate_hz("rtd") >= 160 and s.rate_hz("ft") >= 80


def test_loop_runs_on_absolute_grid_in_simulated_time():
    clock = SimClock(100.0)
    seen = []

    def body(info):
        seen.append((info.index, info.t_wake))
        clock.advance(50e-6)  # 50 us of work

    loop = FrameLoop(clock, 1 / 320, body)
    stats = loop.run(frames=320, freeze_gc=False)
    assert [k for k, _ in seen] == list(range(320))
    assert seen[-1][1] == pytest.approx(100.0 + 319 / 320)
    assert stats.dropped == 0 and stats.overruns == 0
    assert stats.summary()["work_s"]["p50"] == pytest.approx(50e-6)


def test_late_frame_is_dropped_not_burst():
    clock = SimClock(0.0)
    P = 1 / 320
    wakes = []

    def body(info):
        wakes.append((info.index, info.t_wake, info.missed))
        if info.index == 10:
            clock.advance(3.5 * P)  # a stall inside frame 10

    stats = FrameLoop(clock, P, body).run(frames=20, freeze_gc=False)
    idx = [k for k, _, _ in wakes]
    # frame 10 ends at 13.5 P: deadlines 11 P and 12 P have passed, so frames 11 and 12
    # are dropped and counted; frame 13 runs once, at 13.5 P, told it follows 2 dropped frames
    assert 11 not in idx and 12 not in idx and 13 in idx
    k13 = [w for w in wakes if w[0] == 13][0]
    assert k13[1] == pytest.approx(13.5 * P) and k13[2] == 2
    assert stats.dropped == 2
    assert stats.overruns == 1 and stats.longest_overrun_run == 1
    times = [t for _, t, _ in wakes]
    assert all(b > a for a, b in zip(times, times[1:]))
    # no two frames ran at the same instant (no catch-up burst)
    assert len(set(round(t, 9) for t in times)) == len(times)


def test_the_rate_counts_frames_actually_run_so_dropped_frames_lower_it():
    """Issue 29 item 8: `pfma stats` showed 319.96 Hz while ~65 % of frames were dropped
    (a median period hides them). The rate is frames run over the time they span."""
    clock = SimClock(0.0)
    P = 1 / 320
    wakes = []

    def body(info):
        wakes.append(info.t_wake)
        if info.index % 3 == 0:
            clock.advance(2.2 * P)  # every third frame overruns: the next one is dropped

    stats = FrameLoop(clock, P, body).run(frames=300, freeze_gc=False)
    s = stats.summary()
    assert stats.dropped == 100  # one of every three frames
    run = len(wakes)
    assert s["rate_hz"] == pytest.approx((run - 1) / (wakes[-1] - wakes[0]))
    assert s["rate_hz"] == pytest.approx(2 / 3 * 320, rel=0.01)  # 200 frames run in 300 periods
    assert s["rate_window_s"] == pytest.approx(wakes[-1] - wakes[0])


def test_the_rate_is_the_frame_rate_when_nothing_is_dropped():
    clock = SimClock(0.0)
    stats = FrameLoop(clock, 1 / 320, lambda info: clock.advance(1e-4)).run(frames=100, freeze_gc=False)
    assert stats.summary()["rate_hz"] == pytest.approx(320.0)
