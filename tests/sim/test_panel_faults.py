"""The servo control chassis' front-panel switches as faults of the simulated rack
(``panel-off:28v``, ``panel-off:15v``, ``panel-off:pwm:JOINT``, ``panel-off:brake:JOINT``;
IRSS report 3.6): each switch's physical effect on the arm with a raised current limit and
a rate command, seen through the real drivers on the fake boards (DAC in, ADC out); its
undo; its independence from ``brake-held`` / ``amp-off``; its spec's errors; and the same
specs from a scenario step and from ``pfma fault``. Simulated time, deterministic."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.adc import Dvme611
from drivers.dac import Vmivme4100
from fakes.arm_params import AXES, N_JOINTS
from fakes.world import FakeWorld
from pfma.errors import ConfigError
from sim.faults import KINDS, FaultSet, kinds_help, parse_fault
from sim.rig import SimRig
from sim.scenario import ScenarioRunner, parse_scenario
from tools.cli import main

DT = 1.0 / 320.0
ADC_LSB = 20.0 / 4096
JOINTS = [a.joint for a in AXES]
SY, WR, GR = JOINTS.index("shoulder_yaw"), JOINTS.index("wrist_roll"), JOINTS.index("gripper")
#: the default rack names the gripper's ADC monitors "end_effector_*" (IRSS 3.4.2 wording)
ADC_STEM = {"gripper": "end_effector"}
#: the raised current limit on every axis (released brakes, 50 % of I_max) and the commands
LIMIT_V = 5.0
COMMAND_V = {SY: 5.0, GR: 2.0}  # 0.2 rad/s; 0.01 m/s (the jaw opens from half open)
MOVES = {SY: 0.05, GR: 0.002}  # at least this far in 0.5 s when the axis is driven, rad / m


class Rig:
    """The simulated rack (a FakeWorld, as FaultSet acts on) and the drivers a service uses."""

    def __init__(self) -> None:
        self.world = FakeWorld()
        self.sim = self.world.sim
        self.arm = self.sim.arm
        cfg, bus = self.world.rack_config, self.world.bus
        self.cfg = cfg
        self.dac = Vmivme4100(bus, cfg.board("dac").base, "dac")
        self.adc = Dvme611(bus, cfg.board("adc").base, "adc")
        self.faults = FaultSet(self.world)
        self.dac.enable_outputs()
        for a in AXES:
            self.write(f"{a.joint}_command", 0.0)
            self.write(f"{a.joint}_current_limit", LIMIT_V)
        self.run(0.1)

    def write(self, signal: str, volts: float) -> None:
        self.dac.write_volts(self.cfg.channel(signal).channel, volts)

    def adc_volts(self, axis: int, what: str) -> float:
        j = JOINTS[axis]
        return self.adc.read_volts(self.cfg.channel(f"{ADC_STEM.get(j, j)}_{what}").channel)

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT)):
            self.sim.advance(DT)

    def drive(self, axis: int, seconds: float = 0.5) -> float:
        """Command ``axis`` at its COMMAND_V for ``seconds``, then 0 V again until it is still;
        how far it moved while commanded."""
        q0 = self.arm.q[axis]
        self.write(f"{JOINTS[axis]}_command", COMMAND_V[axis])
        self.run(seconds)
        moved = float(self.arm.q[axis] - q0)
        self.state = self.sim.true_state()  # the state while commanded
        self.monitor_v = self.adc_volts(axis, "motor_current")
        self.tach_v = self.adc_volts(axis, "rate")
        self.write(f"{JOINTS[axis]}_command", 0.0)
        self.run(0.3)
        return moved


@pytest.fixture
def rig():
    return Rig()


def assert_moves_normally(rig: Rig, axis: int) -> None:
    assert rig.drive(axis) > MOVES[axis]
    assert rig.state.current_a[axis] != 0.0 and abs(rig.monitor_v) > 2 * ADC_LSB
    assert rig.tach_v == pytest.approx(rig.state.tach_volts[axis], abs=2 * ADC_LSB) and rig.tach_v > 0.5
    if axis < N_JOINTS:
        assert not rig.state.brake_engaged[axis]


# -- each switch's physical effect ----------------------------------------------------------------
@pytest.mark.parametrize("spec, axis", [
    ("panel-off:pwm:shoulder_yaw", SY), ("panel-off:pwm:gripper", GR),
    ("panel-off:28v", SY), ("panel-off:28v", GR), ("panel-off:15v", SY), ("panel-off:15v", GR),
])
def test_no_drive_no_motion_no_current_until_switched_back_on(rig, spec, axis):
    assert_moves_normally(rig, axis)
    rig.faults.inject(spec)
    rig.run(DT)  # a joint sagging under gravity on its rate loop stops within this step's first 1 ms
    q_all = rig.arm.q.copy()
    assert abs(rig.drive(axis)) < 1e-9  # commanded, the current limit raised: nothing
    st = rig.state
    assert st.current_a[axis] == 0.0
    assert rig.monitor_v == pytest.approx(0.0, abs=ADC_LSB)
    if spec.startswith("panel-off:pwm"):
        # the other axes are powered: their brakes released by the raised limit
        assert not st.brake_engaged[:N_JOINTS].any()
    else:
        # no +28 V or no +/-15 V: every axis without drive, every brake set, no joint moves,
        # every current monitor at 0 V
        assert np.array_equal(rig.arm.q, q_all)
        assert st.brake_engaged[:N_JOINTS].all() and not st.current_a.any()
        for i in range(len(AXES)):
            assert rig.adc_volts(i, "motor_current") == pytest.approx(0.0, abs=ADC_LSB), JOINTS[i]
    rig.faults.clear(spec)
    assert_moves_normally(rig, axis)


def test_brake_switch_off_the_amplifier_drives_at_its_limit_against_the_set_brake(rig):
    assert_moves_normally(rig, SY)
    rig.faults.inject("panel-off:brake:shoulder_yaw")
    assert rig.drive(SY) == 0.0
    st = rig.state
    assert st.brake_engaged[SY] and not st.brake_engaged[SY + 1:N_JOINTS].any()
    i_lim = AXES[SY].i_max_a * LIMIT_V / 10.0
    assert st.current_a[SY] == pytest.approx(i_lim)  # at its limit
    assert rig.monitor_v == pytest.approx(LIMIT_V, abs=2 * ADC_LSB)  # 10 I / I_max
    assert rig.tach_v == pytest.approx(0.0, abs=ADC_LSB)
    rig.faults.clear("panel-off:brake:shoulder_yaw")
    assert_moves_normally(rig, SY)


def test_15v_off_the_tach_filter_outputs_0v_while_the_joint_is_moved(rig):
    """An external load beyond the brake's slip torque turns the wrist roll with the +/-15 V
    off: the tach filter's RC still follows it (V_tf), its unpowered buffer outputs 0 V."""
    rig.write("wrist_roll_current_limit", 0.0)  # the brake set by the limit too: it slips
    slip = 1.5 * AXES[WR].torque_max
    rig.faults.inject(f"load:wrist_roll={slip + 3.4:.1f}")
    rig.faults.inject("panel-off:15v")
    q0 = rig.arm.q[WR]
    rig.run(0.3)
    st = rig.sim.true_state()
    assert st.qdot[WR] > 0.5 and rig.arm.q[WR] - q0 > 0.1  # moved, ~1.2 rad/s
    assert st.tach_volts[WR] > 2.5  # what the RC filter holds (K_w = 5 V per rad/s)
    assert rig.arm.tach_output_volts[WR] == 0.0
    assert rig.adc_volts(WR, "rate") == pytest.approx(0.0, abs=ADC_LSB)
    rig.faults.clear("panel-off:15v")
    rig.run(DT)  # the buffer outputs V_tf again; the anti-aliasing filter takes it to the A/D ...
    assert 0.0 < rig.adc_volts(WR, "rate") < 0.5 * st.tach_volts[WR]
    rig.run(0.1)  # ... within 100 ms
    st = rig.sim.true_state()
    assert st.qdot[WR] > 0.5
    assert rig.adc_volts(WR, "rate") == pytest.approx(st.tach_volts[WR], abs=2 * ADC_LSB)


# -- kept apart from brake-held and amp-off ------------------------------------------------------
def test_clearing_a_panel_switch_leaves_a_held_brake_and_the_other_way_round(rig):
    fs = rig.faults
    fs.inject("brake-held:shoulder_yaw")
    fs.inject("panel-off:brake:shoulder_yaw")
    fs.inject("panel-off:28v")
    fs.clear("panel-off:brake:shoulder_yaw")
    fs.clear("panel-off:28v")
    e = rig.sim.errors
    assert e.brake_held[SY] and not e.panel_brake_off[SY] and not e.panel_28v_off
    assert rig.drive(SY) == 0.0 and rig.state.brake_engaged[SY]  # still held
    assert rig.state.current_a[SY] == pytest.approx(AXES[SY].i_max_a * LIMIT_V / 10.0)
    fs.inject("panel-off:brake:shoulder_yaw")
    fs.clear("brake-held:shoulder_yaw")
    assert rig.drive(SY) == 0.0  # the switch still holds it
    fs.clear("panel-off:brake:shoulder_yaw")
    assert_moves_normally(rig, SY)


def test_clearing_amp_off_leaves_the_pwm_switch_off_and_the_other_way_round(rig):
    fs = rig.faults
    fs.inject("amp-off:gripper")
    fs.inject("panel-off:pwm:gripper")
    fs.clear("amp-off:gripper")
    assert rig.drive(GR) == 0.0 and rig.state.current_a[GR] == 0.0
    fs.inject("amp-off:gripper")
    fs.clear("panel-off:pwm:gripper")
    assert rig.drive(GR) == 0.0 and rig.state.current_a[GR] == 0.0
    fs.clear("amp-off:gripper")
    assert_moves_normally(rig, GR)


def test_28v_and_15v_are_two_switches(rig):
    fs = rig.faults
    fs.inject("panel-off:28v")
    fs.inject("panel-off:15v")
    fs.clear("panel-off:28v")
    assert not rig.arm.analog_powered and rig.drive(SY) == 0.0
    fs.clear("panel-off:15v")
    assert rig.arm.analog_powered
    assert_moves_normally(rig, SY)


# -- the specs ------------------------------------------------------------------------------------------
def test_each_switch_has_its_row_in_the_fault_list():
    rows = {k: s for k, (s, _) in KINDS.items() if k.startswith("panel-off")}
    assert rows == {"panel-off:28v": "panel-off:28v", "panel-off:15v": "panel-off:15v",
                    "panel-off:pwm": "panel-off:pwm:JOINT", "panel-off:brake": "panel-off:brake:JOINT"}
    lines = [ln for ln in kinds_help() if ln.startswith("panel-off")]
    assert len(lines) == 4 and all(len(ln.split("  ", 1)[1].strip()) > 10 for ln in lines)


@pytest.mark.parametrize("spec, kind, says", [
    ("panel-off:28v", "panel-off:28v", "+28 VDC off"),
    ("panel-off:15v", "panel-off:15v", "+/-15 V converter off"),
    ("panel-off:pwm:gripper", "panel-off:pwm", "PWM stage switch of gripper off"),
    ("panel-off:brake:wrist_roll", "panel-off:brake", "brake release switch of wrist_roll off"),
])
def test_good_specs_name_their_switch(spec, kind, says):
    f = parse_fault(spec)
    assert f.kind == kind and says in f.description and "\n" not in f.description


@pytest.mark.parametrize("spec, says", [
    ("panel-off", "needs a switch: panel-off:28v|15v|pwm:JOINT|brake:JOINT"),
    ("panel-off:24v", "unknown switch '24v'; did you mean 28v?"),
    ("panel-off:pmw:elbow_pitch", "unknown switch 'pmw'; did you mean pwm?"),
    ("panel-off:fan", "unknown switch 'fan'; switches: panel-off:28v|15v|pwm:JOINT|brake:JOINT"),
    ("panel-off:28v:shoulder_yaw", "takes no joint"),
    ("panel-off:pwm", "needs a joint: panel-off:pwm:JOINT"),
    ("panel-off:pwm:knee", "no joint 'knee'"),
    ("panel-off:pwm:elbow_pich", "did you mean elbow_pitch"),
    ("panel-off:brake:gripper", "the gripper has no brake"),
    ("panel-off:brake:wrist_rol", "did you mean wrist_roll"),
    ("panel-off:brake:knee", "joints with a brake: shoulder_yaw, shoulder_pitch, elbow_pitch, wrist_pitch, "
                             "wrist_yaw, wrist_roll"),
    ("panel-of:28v", "unknown kind 'panel-of'; did you mean panel-off?"),
])
def test_bad_panel_specs_are_one_clear_error(spec, says):
    with pytest.raises(ConfigError) as e:
        parse_fault(spec)
    text = str(e.value)
    assert text.startswith(f"fault {spec!r}: ") and says in text and "\n" not in text


# -- from a scenario step and from pfma fault ---------------------------------------------------------
def test_panel_switches_from_scenario_steps():
    sc = parse_scenario('name = "panel"\n'
                        '[[step]]\nat_s = 0.25\ninject = "panel-off:28v"\n'
                        '[[step]]\nat_s = 0.25\ninject = "panel-off:brake:elbow_pitch"\n'
                        '[[step]]\nat_s = 0.5\nclear = "panel-off:28v"\n'
                        '[[step]]\nat_s = 0.75\nclear = "all"\n')
    with SimRig(prefix="pfma-panel-") as r:
        fs = FaultSet(r.world)
        events = []
        runner = ScenarioRunner(sc, fs, r.svc.schedule.frame_rate_hz,
                                say=lambda st, done, err: events.append((st.spec, err)))
        r.on_frame.append(lambda info: runner.on_frame(info.index))
        seen = []
        for t in (0.2, 0.4, 0.6, 0.9):
            r.run(t - r.svc.loop.k / r.svc.schedule.frame_rate_hz)
            e = r.world.sim.errors
            seen.append((e.panel_28v_off, e.panel_brake_off[JOINTS.index("elbow_pitch")], r.world.sim.arm.analog_powered))
        assert seen == [(False, False, True), (True, True, False), (False, True, True), (False, False, True)]
        assert runner.finished and fs.active == [] and all(err is None for _, err in events)


def test_panel_switches_through_the_fault_control_and_pfma_fault(capsys):
    from tools.faultctl import MSG_FAULT_ON, FaultController
    with SimRig(prefix="pfma-panel-") as r:
        ctl = FaultController(r.svc, r.world, say=None)
        reply = ctl.handle({"op": "inject", "spec": "panel-off:pwm:gripper"})
        assert reply["ok"] and reply["faults"][0]["kind"] == "panel-off:pwm"
        assert r.world.sim.errors.panel_pwm_off[GR]
        reply = ctl.handle({"op": "inject", "spec": "panel-off:brake:gripper"})
        assert reply == {"ok": False, "exit": 2, "error": reply["error"]} and "no brake" in reply["error"]
        assert ctl.handle({"op": "clear", "spec": "panel-off:pwm:gripper"})["ok"]
        assert not r.world.sim.errors.panel_pwm_off[GR] and ctl.faults.active == []
        r.run(0.05)
        assert (MSG_FAULT_ON, "simulated fault on: panel-off:pwm:gripper") in [
            (m.code, m.text) for m in r.reader.messages()]
    assert main(["fault", "list"]) == 0
    out = capsys.readouterr().out
    assert all(s in out for s in ("panel-off:28v", "panel-off:15v", "panel-off:pwm:JOINT", "panel-off:brake:JOINT"))
    assert main(["fault", "list", "--json"]) == 0
    kinds = [k["kind"] for k in json.loads(capsys.readouterr().out)]
    assert [k for k in kinds if k.startswith("panel-off")] == ["panel-off:28v", "panel-off:15v", "panel-off:pwm",
                                                                 "panel-off:brake"]
    # a bad spec is refused before any service is asked: one line, exit 2
    assert main(["fault", "inject", "panel-off:brake:gripper", "--buffer", "pfma-panel-none"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the gripper has no brake" in err
