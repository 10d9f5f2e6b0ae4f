"""`pfma stats`'s frame rate is the frames the service actually ran (issue 29 item 8)."""

import pytest


def test_a_long_frame_and_its_dropped_frames_lower_the_published_rate(rig):
    wakes = []
    stalled = []

    def frame(info):
        wakes.append(info.t_wake)
        if len(wakes) == 320 and not stalled:  # one frame of 175 ms, as seen beside 50 watchers
            stalled.append(info.index)
            rig.clock.advance(0.175)

    rig.on_frame.append(frame)
    rig.run(2.0)
    rig.svc.publish_stats()
    st = rig.reader.read_stats()
    assert st.dropped_frames >= 55  # 175 ms / 3.125 ms
    run = len(wakes)
    assert st.rate_hz == pytest.approx((run - 1) / (wakes[-1] - wakes[0]), rel=1e-9)
    assert st.rate_hz < 0.95 * 320  # not 319.96
