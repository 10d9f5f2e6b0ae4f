"""Synthetic time delay (pfma-model 6, 8.10): FIFOs, split, jitter with order preserved,
and in the loop: a 2 s round trip changes when hand-controller commands arrive, not what
they do."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.delay import MAX_ROUND_TRIP_S, DelayLine, SyntheticDelay
from controller.teleop import REFLECT_MAX_ROUND_TRIP_S, reflect
from pfma.errors import ConfigError

FRAME_S = 1.0 / 320.0


def test_delay_line_releases_at_send_time_plus_delay_in_order():
    line = DelayLine()
    released = []
    for k in range(400):  # 320 Hz polls for 1.25 s, a packet every 8 frames (40 Hz)
        t = k * FRAME_S
        if k % 8 == 0:
            line.push(t, (k, t), 0.5)
        for k0, t0 in line.poll(t):
            released.append((t0, t))
    assert len(released) == 30  # packets sent up to 0.725 s (frame 232) are out by 1.247 s
    for t0, t in released:
        assert t - t0 == pytest.approx(0.5, abs=1e-9)  # 0.5 s is 160 frames exactly
    assert [r[0] for r in released] == sorted(r[0] for r in released)


def test_zero_delay_is_immediate():
    d = SyntheticDelay(0.0)
    assert d.send_up(1.0, "a") == "a"
    assert d.send_down(1.0, "b") == "b"


def test_round_trip_split_equally_and_checked():
    d = SyntheticDelay(2.0)
    assert (d.up_s, d.down_s) == (1.0, 1.0)
    assert d.send_up(0.0, "x") is None  # nothing has arrived yet
    assert d.send_up(0.999, "y") is None
    assert d.send_up(1.0, "z") == "x"
    for bad in (-0.1, math.nan, MAX_ROUND_TRIP_S + 1):
        with pytest.raises(ConfigError, match="round trip"):
            d.set_round_trip(bad)
    assert d.round_trip_s == 2.0


def test_jitter_bounded_and_order_preserved():
    a, b = DelayLine(jitter=0.1, seed=7), DelayLine(jitter=0.1, seed=7)
    rel = [a.push(k * 0.025, k, 1.0) for k in range(400)]
    assert rel == [b.push(k * 0.025, k, 1.0) for k in range(400)]  # deterministic
    delays = np.array(rel) - np.arange(400) * 0.025
    assert delays.min() >= 0.9 - 1e-12 and delays.max() <= 1.1 + 1e-12
    assert delays.std() > 0.02  # it does jitter
    assert all(x <= y for x, y in zip(rel, rel[1:]))  # never reordered
    out = a.poll(100.0)
    assert out == list(range(400))


def test_force_reflection_gated_by_round_trip():
    f, t, on = reflect([100.0, 0.0, 0.0], [0.0, 0.0, 4.0], 0.0, True)
    assert on and f == pytest.approx([25.0, 0.0, 0.0]) and t == pytest.approx([0.0, 0.0, 1.0])
    f, t, on = reflect([400.0, 0.0, 0.0], [0.0, 0.0, 40.0], 0.5, True)  # saturated at 40 N, 2 N*m
    assert on and f == pytest.approx([40.0, 0.0, 0.0]) and t == pytest.approx([0.0, 0.0, 2.0])
    f, t, on = reflect([100.0, 0.0, 0.0], [0.0, 0.0, 4.0], REFLECT_MAX_ROUND_TRIP_S + 0.01, True)
    assert not on and not f.any() and not t.any()
    assert not reflect([100.0, 0.0, 0.0], [0.0] * 3, 0.0, False)[2]


def _stick_run(round_trip_s: float) -> tuple[np.ndarray, list]:
    """Stick +x for 0.5 s then released, from the same simulated instant; the true tool
    path for 2.5 s from then. Returns (path, messages of the cartesian layer)."""
    from tests.controller._cart_support import powered_sim, record, stick
    with powered_sim(cart__mode=1, delay__round_trip_s=round_trip_s) as sim:
        sim.step(316)  # settle; same frame phase in both runs
        stick(sim, "x")
        path = list(record(sim, 160))
        stick(sim, None, deadman=False)
        path += list(record(sim, 640))
        msgs = [m.text for m in sim.rt.messages.recent() if m.source == "cartesian"]
    return np.array(path), msgs


def test_two_second_delay_shifts_commands_by_the_one_way_delay():
    """Measured: the delayed tool path equals the undelayed one shifted by 1.0 s (the
    uplink half of 2 s) to within 0.2 mm over the whole motion; it does not move at all
    during the first second."""
    fast, _ = _stick_run(0.0)
    slow, msgs = _stick_run(2.0)
    shift = 320  # 1.0 s of 320 Hz frames
    assert np.linalg.norm(slow[:shift] - slow[0], axis=1).max() < 2e-4  # nothing arrived yet
    moved = fast[-1][0] - fast[0][0]
    assert moved > 0.014  # 0.5 s at 0.0375 m/s less the ramps (measured 14.7 mm: the stick reaches the A/D
    # through the anti-aliasing filter, 10 ms later than the deadman, which does not)
    err = np.linalg.norm(slow[shift:] - fast[:len(slow) - shift], axis=1)
    assert err.max() < 2e-4
    assert any("round trip 0 s -> 2 s" in m for m in msgs)
