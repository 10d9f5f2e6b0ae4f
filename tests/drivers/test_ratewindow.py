"""drivers.ratewindow.RateWindow: the link-rate figure of the F/T and hand-controller drivers."""

import pytest

from drivers.ratewindow import RateWindow


def test_rate_over_the_window_and_events_leaving_it():
    r = RateWindow(window_s=1.0)
    assert r.rate_hz(0.0) == 0.0
    for i in range(101):  # 100 Hz for 1 s
        r.mark(i * 0.01)
    assert r.rate_hz(1.0) == pytest.approx(100.0)
    for i in range(1, 26):  # then 25 Hz
        r.mark(1.0 + i * 0.04)
    assert r.rate_hz(2.0) == pytest.approx(25.0)  # the 100 Hz events have left the window
    assert r.rate_hz(3.5) == 0.0  # silence: nothing left
    r.mark(4.0)
    assert r.rate_hz(4.0) == 0.0  # one event is no rate
    r.clear()
    assert r.rate_hz(4.0) == 0.0
