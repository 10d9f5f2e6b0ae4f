"""SimulatedRack: the arm wired to the fake boards, observed through the real drivers.

Channels are looked up by signal name in the default rack configuration, never by number.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.adc import Dvme611
from drivers.dac import Vmivme4100
from drivers.rtd import Vmivme4940
from fakes.arm_params import AXES, N_AXES, SimErrors
from fakes.environment import Environment, Wall
from fakes.ft_sensor import FakeFtController
from fakes.sim_rack import CAE_AXIS_SIGNALS, CAE_DISCRETE_SIGNALS, SimulatedRack
from pfma.clock import SimClock

DT = 1.0 / 320.0
ADC_LSB = 20.0 / 4096
RTD_LSB = 2 * math.pi / (1 << 14)
SY, SP, EP, WP, WY, WR, GR = range(7)

#: the default rack names the gripper's ADC monitors "end_effector_*" (IRSS 3.4.2 wording); the
#: simulator finds them by role, this test by name
ADC_STEM = {"gripper": "end_effector"}


class Rig:
    """A simulated rack plus the drivers a service would use on it."""

    def __init__(self, **kw) -> None:
        self.sim = SimulatedRack(clock=SimClock(), **kw)
        cfg, bus = self.sim.config, self.sim.fake_rack
        self.cfg = cfg
        self.dac = Vmivme4100(bus, cfg.board("dac").base, "dac")
        self.adc = Dvme611(bus, cfg.board("adc").base, "adc")
        self.rtd = {b.name: Vmivme4940(bus, b.base, b.name) for b in cfg.boards_of("rtd")}

    def write(self, signal: str, volts: float) -> None:
        c = self.cfg.channel(signal)
        assert c.board == "dac"
        self.dac.write_volts(c.channel, volts)

    def adc_volts(self, signal: str) -> float:
        c = self.cfg.channel(signal)
        return self.adc.read_volts(c.channel)

    def angle(self, signal: str) -> float:
        c = self.cfg.channel(signal)
        return self.rtd[c.board].read_angle_rad(c.channel)

    def power_up(self, limit_v: float = 10.0) -> None:
        self.dac.enable_outputs()
        for a in AXES:
            self.write(f"{a.joint}_command", 0.0)
            self.write(f"{a.joint}_current_limit", limit_v)

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            self.sim.advance(DT)


def test_outputs_disconnected_nothing_moves_and_the_brakes_hold():
    rig = Rig(errors=SimErrors(payload_kg=5.0))
    q0 = rig.sim.true_state().q
    for a in AXES:  # written but not connected: the field sees 0 V
        rig.write(f"{a.joint}_command", 5.0)
        rig.write(f"{a.joint}_current_limit", 10.0)
    rig.run(1.0)
    st = rig.sim.true_state()
    assert np.array_equal(st.q, q0)
    assert st.brake_engaged[:6].all()
    assert rig.sim.clock.now() >= 1.0


def test_rate_command_through_the_dac_moves_the_joint_and_shows_on_the_adc():
    rig = Rig()
    rig.power_up()
    rig.run(0.1)
    assert not rig.sim.true_state().brake_engaged.any()
    rig.write("shoulder_yaw_command", 5.0)
    rig.run(0.8)
    st = rig.sim.true_state()
    assert st.qdot[SY] == pytest.approx(5.0 / 25.0, rel=0.05)
    assert rig.adc_volts("shoulder_yaw_rate") == pytest.approx(st.tach_volts[SY], abs=ADC_LSB)
    assert rig.adc_volts("shoulder_yaw_motor_current") == pytest.approx(st.current_monitor_volts[SY], abs=ADC_LSB)
    assert rig.adc_volts("shoulder_yaw_rate") == pytest.approx(5.0, rel=0.05)
    assert rig.adc_volts("shoulder_roll_rate") == pytest.approx(0.0, abs=ADC_LSB)
    assert rig.angle("shoulder_yaw_angle") == pytest.approx(st.q[SY] % (2 * math.pi), abs=RTD_LSB)
    for axis in (WY, WR):
        assert st.qdot[axis] == 0.0


def test_every_axis_reports_on_its_own_channels():
    rig = Rig()
    rig.power_up()
    q = (0.3, 0.2, -0.7, 0.5, -0.4, 2.5, 0.03)
    rig.sim.arm.set_state(q=q, qdot=(0.01, 0.02, -0.03, 0.04, -0.05, 0.06, 0.007))
    rig.sim.settle_filters()  # publish without moving, the anti-aliasing filters at rest on it
    st = rig.sim.true_state()
    for i, a in enumerate(AXES):
        assert rig.adc_volts(f"{ADC_STEM.get(a.joint, a.joint)}_rate") == pytest.approx(st.tach_volts[i], abs=ADC_LSB), a.name
        assert rig.adc_volts(f"{ADC_STEM.get(a.joint, a.joint)}_motor_current") == pytest.approx(
            st.current_monitor_volts[i], abs=ADC_LSB), a.name
        if a.has_angle:
            assert rig.angle(f"{a.joint}_angle") == pytest.approx(q[i] % (2 * math.pi), abs=RTD_LSB), a.name
    # distinct values, so a swapped channel would fail above
    assert len({round(v, 3) for v in st.tach_volts}) == N_AXES
    # the elbow is negative: wrapped into 0..2 pi
    assert rig.angle("elbow_pitch_angle") > math.pi


def test_current_limit_shows_on_the_current_monitor():
    rig = Rig()
    rig.power_up(limit_v=10.0)
    # a held brake keeps the joint still, so the current stays at its limit
    rig.sim.set_errors(SimErrors(brake_held=tuple(a.name == "WR" for a in AXES)))
    rig.write("wrist_roll_current_limit", 4.0)  # 5 A * 0.4 = 2 A -> monitor 4 V
    rig.write("wrist_roll_command", 10.0)
    rig.sim.advance(DT)
    rig.sim.advance(DT)
    assert rig.sim.true_state().current_monitor_volts[5] == pytest.approx(4.0, abs=ADC_LSB)
    # the monitor's anti-aliasing filter (10 ms lag) has not caught up after 6 ms ...
    assert rig.adc_volts("wrist_roll_motor_current") < 2.0
    for _ in range(32):  # ... and has 100 ms later
        rig.sim.advance(DT)
    assert rig.sim.true_state().current_monitor_volts[5] == pytest.approx(4.0, abs=ADC_LSB)
    assert rig.adc_volts("wrist_roll_motor_current") == pytest.approx(4.0, abs=2 * ADC_LSB)


def test_cae_volts_appear_on_the_cae_channels():
    rig = Rig()
    axes = (1.0, -2.0, 3.0, -4.0, 5.0, -6.0)
    rig.sim.set_cae(axes, (True, False, 2.5))
    for sig in CAE_AXIS_SIGNALS:  # the axes reach the A/D through the anti-aliasing filters ...
        assert rig.adc_volts(sig) == pytest.approx(0.0, abs=ADC_LSB)
    for sig, v in zip(CAE_DISCRETE_SIGNALS, (5.0, 0.0, 2.5)):  # ... the discretes directly
        assert rig.adc_volts(sig) == pytest.approx(v, abs=ADC_LSB)
    rig.run(0.1)  # settled after 100 ms (the Butterworth's 11 % overshoot rung out), and stays set
    for sig, v in zip(CAE_AXIS_SIGNALS, axes):
        assert rig.adc_volts(sig) == pytest.approx(v, abs=ADC_LSB)
    assert rig.adc_volts("cae_roll") == pytest.approx(-6.0, abs=ADC_LSB)
    with pytest.raises(ValueError, match="6 axis voltages"):
        rig.sim.set_cae((0.0,) * 5)


def test_truth_errors_show_where_calibration_will_look_for_them():
    errors = SimErrors(resolver_offset_rad=(0.0, 0.01, 0.0, 0.0, -0.02, 0.0),
                       adc_gain_error={"shoulder_yaw_rate": 0.05}, adc_offset_v={"cae_yaw": 0.2},
                       dac_offset_v={"wrist_yaw_command": 0.5})
    rig = Rig(errors=errors)
    q = rig.sim.true_state().q
    assert rig.angle("shoulder_pitch_angle") == pytest.approx(q[SP] + 0.01, abs=RTD_LSB)
    assert rig.angle("wrist_yaw_angle") == pytest.approx((q[WY] - 0.02) % (2 * math.pi), abs=RTD_LSB)
    assert rig.adc_volts("cae_yaw") == pytest.approx(0.2, abs=ADC_LSB)
    assert rig.sim.amplifier_inputs()[0][WY] == 0.0  # DAC disconnected: no offset reaches the amplifier
    rig.power_up()
    rig.write("shoulder_yaw_command", 4.0)
    rig.run(0.6)  # the 0.5 V DAC offset on wrist yaw moves it with a zero command
    st = rig.sim.true_state()
    assert st.qdot[WY] > 0.0
    assert rig.adc_volts("shoulder_yaw_rate") == pytest.approx(1.05 * st.tach_volts[SY], abs=ADC_LSB)
    with pytest.raises(KeyError, match="no_such_signal"):
        rig.sim.set_errors(SimErrors(adc_offset_v={"no_such_signal": 1.0}))
    with pytest.raises(ValueError, match="shoulder_yaw_command.*dac board dac channel 1"):
        rig.sim.set_errors(SimErrors(adc_gain_error={"shoulder_yaw_command": 0.1}))
    rig.sim.set_errors(SimErrors(adc_offset_v={"adc_spare_31": -1.0}))  # a channel the arm never drives
    rig.sim.hold_adc_volts("adc_spare_31", 3.0)
    rig.sim.step(DT)
    assert rig.adc_volts("adc_spare_31") == pytest.approx(2.0, abs=ADC_LSB)
    with pytest.raises(ValueError, match="driven by the simulator"):
        rig.sim.hold_adc_volts("cae_yaw", 1.0)


def test_ft_fake_gets_the_arm_load():
    rig = Rig(environment=Environment([Wall((0.0, 0.05, 0.0), (0.0, -1.0, 0.0))]))
    ft = FakeFtController()
    rig.sim.attach_ft(ft)
    force, torque = ft.load_fn(0.0)
    assert np.allclose(force, (0.0, -1.5 * 9.81, 0.0), atol=1e-9)  # tool gravity at rest
    rig.power_up(limit_v=0.0)
    rig.write("shoulder_yaw_current_limit", 3.0)
    rig.write("shoulder_yaw_command", 2.5)
    rig.run(3.0)
    force, torque = ft.load_fn(rig.sim.clock.now())
    assert abs(force[0]) > 30.0  # pushing the wall
    assert np.allclose(force, rig.sim.ft_load()[0])

    class PushOnly:
        def __init__(self):
            self.loads = []

        def set_load(self, force_n, torque_nm):
            self.loads.append((force_n, torque_nm))

    push = PushOnly()
    rig.sim.attach_ft(push)
    rig.sim.advance(DT)
    assert len(push.loads) == 2 and np.allclose(push.loads[-1][0], rig.sim.ft_load()[0])
    with pytest.raises(TypeError):
        rig.sim.attach_ft(object())


def test_simulated_rack_is_deterministic():
    def trajectory():
        rig = Rig()
        rig.power_up()
        out = []
        for k in range(300):
            if k % 50 == 0:
                rig.write("wrist_pitch_command", 3.0 * math.sin(k))
                rig.write("shoulder_pitch_command", 2.0 * math.cos(k))
            rig.sim.advance(DT)
            out.append(np.concatenate([rig.sim.true_state().q, rig.adc.scan_volts().copy()]))
        return np.array(out)

    assert np.array_equal(trajectory(), trajectory())
