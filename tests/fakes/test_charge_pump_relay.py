"""The amplifier-enable charge-pump relay on the fake MVME410 (``drivers.pio.registers.
CHARGE_PUMP``, assumed): pulled in by edges less than ``drop_s`` apart, dropped ``drop_s``
after the last edge whatever level the pin is left at; and the arm model's amplifiers
without enable (no current, brakes set). Driven through the real MVME410 driver on a fake
rack, in simulated time."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.pio.mvme410 import Mvme410
from drivers.pio.registers import CHARGE_PUMP
from fakes.arm import ArmModel
from fakes.mvme410 import FakeMvme410
from fakes.rack import FakeRack
from pfma.clock import SimClock

DROP = CHARGE_PUMP["drop_s"]


@pytest.fixture
def board():
    clock = SimClock()
    rack = FakeRack(clock=clock)
    fake = rack.add(0x0020, FakeMvme410("pio_video", clock=clock))
    drv = Mvme410(rack, 0x0020, "pio_video")
    drv.configure(["out", "out", "in", "in"])
    return clock, fake, drv, fake.attach_charge_pump(1, 0)


def test_toggling_pulls_the_relay_in_and_a_held_level_drops_it(board):
    clock, fake, drv, relay = board
    assert not relay.energized()
    drv.write_port(1, 1)  # one edge: not enough
    assert relay.edges == 1 and not relay.energized()
    clock.advance(0.003125)
    drv.write_port(1, 0)
    assert relay.energized()
    for level in (1, 0, 1, 0, 1):  # a frame's edge at a time: held
        clock.advance(0.003125)
        drv.write_port(1, level)
        assert relay.energized()
    last = clock.now()
    drv.write_port(1, 1)  # the same level again: no edge
    assert relay.edges == 7 and relay.drops_at == pytest.approx(last + DROP)
    clock.advance(DROP - 1e-4)
    assert relay.energized()
    clock.advance(2e-4)
    assert not relay.energized()  # held high: dropped
    drv.write_port(1, 0)  # one edge after the drop does not pull it in again
    assert not relay.energized()
    clock.advance(0.003)
    drv.write_port(1, 1)
    assert relay.energized()


def test_only_its_own_bit_counts(board):
    clock, fake, drv, relay = board
    for v in (2, 0, 2, 0):  # bit 1 of the same port toggling
        drv.write_port(1, v)
        clock.advance(0.003)
    drv.write_port(0, 1)
    assert relay.edges == 0 and not relay.energized()


def test_slow_edges_never_pull_it_in(board):
    clock, fake, drv, relay = board
    for level in (1, 0, 1, 0):
        drv.write_port(1, level)
        clock.advance(DROP + 0.001)
    assert relay.edges == 4 and not relay.energized()


def test_amplifiers_without_enable_give_no_current_and_set_the_brakes():
    arm = ArmModel()
    v_cmd, v_ilim = np.full(7, 2.0), np.full(7, 5.0)
    arm.step(0.05, v_cmd, v_ilim)
    assert np.any(arm.state().current_a != 0.0) and not np.any(arm.state().brake_engaged)
    arm.amplifiers_enabled = False
    arm.step(0.05, v_cmd, v_ilim)
    st = arm.state()
    assert np.all(st.current_a == 0.0)
    assert np.array_equal(st.brake_engaged, arm.brake_fitted)
