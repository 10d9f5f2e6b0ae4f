"""Issue 33 item 6: the plant's filters in the simulator, flown by the servo (simulated
time): the anti-aliasing board delays what the A/D reads of the tach by its group delay and
changes nothing the servo flies; each position of a rate servo card's gain switch still
meets the compensator's predicted overshoot; the figures docs/simulated-arm.md shows read
at a glance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.plot import figure
from controller.params import DEFAULT_KP_PER_S, GAIN_SWITCH_POSITIONS, joint
from controller.servo import predict_step
from drivers.rtd.registers import VMIVME4940
from pfma.arm import anti_alias_delay_s
from sim.step_response import anti_alias_panels, fly_step, gain_switch_panels
from tests.calibration.test_plot_legibility import legibility_faults


def _crossing_s(t: np.ndarray, w: np.ndarray, level: float) -> float:
    """When ``w`` first rises through ``level`` (linear between samples)."""
    k = int(np.argmax(w >= level))
    return float(t[k - 1] + (level - w[k - 1]) / (w[k] - w[k - 1]) * (t[k] - t[k - 1]))


def _lag_s(t: np.ndarray, lead: np.ndarray, lagging: np.ndarray) -> float:
    """How much later ``lagging`` rises than ``lead``: the mean over the levels 20..80 % of
    the rise, each crossing interpolated between samples."""
    top = float(lead.max())
    return float(np.mean([_crossing_s(t, lagging, f * top) - _crossing_s(t, lead, f * top)
                          for f in np.linspace(0.2, 0.8, 13)]))


def test_the_anti_aliasing_board_delays_the_tach_reading_and_not_the_joint():
    before = fly_step("shoulder_yaw", 0.1, anti_alias_hz=None, seconds=0.4)
    after = fly_step("shoulder_yaw", 0.1, seconds=0.4)
    # the servo flies the resolver: the same step (the runs start a few ms apart: power-up
    # waits on the tach, which the board slows)
    start = _lag_s(before.t_s, before.true_rad_s, after.true_rad_s)
    assert abs(start) < 0.01
    assert np.interp(before.t_s, after.t_s - start, after.q_rad) == pytest.approx(before.q_rad, abs=1e-3)
    # the tach behind the joint's true rate: the card's 10 Hz filter and the A/D's sampling
    # before; the board's group delay (10.4 ms) more after, within 1.5 ms
    extra = _lag_s(after.t_s, after.true_rad_s, after.tach_rad_s) - \
        _lag_s(before.t_s, before.true_rad_s, before.tach_rad_s)
    assert abs(extra - anti_alias_delay_s()) <= 1.5e-3, (extra, anti_alias_delay_s())


@pytest.mark.parametrize("position", list(GAIN_SWITCH_POSITIONS))
def test_every_gain_switch_position_overshoots_no_more_than_predicted(position):
    g = GAIN_SWITCH_POSITIONS[position]
    run = fly_step("wrist_roll", 0.2, gain_switch=g, seconds=1.5)
    pred = predict_step(dataclasses.replace(joint("wrist_roll"), gain_switch=g), 0.2)
    tol = 0.75 * VMIVME4940.constants["lsb_rad"]  # resolver quantisation, as tests/controller/test_rt_servo.py
    assert max(0.0, float(run.q_rad.max()) - 0.2) <= pred.overshoot_rad + tol
    # and it got there but for the Coulomb dead band F_c / (lambda' J K)
    jf = dataclasses.replace(joint("wrist_roll"), gain_switch=g)
    dead = jf.coulomb_nm / (jf.rate_loop_lambda * jf.inertia_kg_m2 * DEFAULT_KP_PER_S)
    assert 0.2 - dead - 0.01 <= run.q_rad[-1] <= 0.2 + tol


def test_the_step_response_figures_read_at_a_glance():
    for panels, title in ((anti_alias_panels(), "anti-aliasing"), (gain_switch_panels(), "gain switch")):
        assert legibility_faults(figure(panels, title)) == []
