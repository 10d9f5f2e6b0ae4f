"""`pfma checkout` and the servo chassis' front panel (IRSS 3.6): the panel state is asked of
the operator (or stated with --panel-off, or assumed) before the joints move and recorded as
a statement; each joint's open-loop test ends with a diagnosis naming the drive or the brake
from what the sensors showed. Simulated rack, simulated time; faults `brake-held:JOINT` and
`amp-off:JOINT` (sim.faults)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from bit3.layout import ServiceState
from pfma.errors import ConfigError
from tools.checkout import FAIL, PASS, SKIP, Checkout, PanelState, parse_panel_off
from tools.checkout.panel import COMMAND_LINE
from tools.cli import main

DIAG = "drive and brake (diagnosis)"
JOINTS = ("shoulder_yaw", "shoulder_pitch", "elbow_pitch", "wrist_pitch", "wrist_yaw", "wrist_roll")


def run(target, cfg, **kw):
    lines: list[str] = []
    rep = Checkout(target, cfg, say=lines.append, only=["joints"], **kw).run()
    return rep, lines


def diagnosis(rep, joint):
    rows = [r for r in rep.results if r.channel == joint and r.check == DIAG]
    assert len(rows) == 1, [r.line() for r in rep.results if r.channel == joint]
    return rows[0]


def panel_rows(results):
    return {r.channel: r for r in results if r.group == "panel"}


def outputs_safe(target):
    assert np.all(target.world.bus["dac"].output_volts_all() == 0.0)
    assert target.inputs().service_state != ServiceState.ARMED


def test_a_held_brake_is_named_in_the_joints_diagnosis_and_fails(sim, cfg):
    sim.inject_fault("brake-held:elbow_pitch")
    rep, _ = run(sim, cfg)
    assert not rep.passed
    d = diagnosis(rep, "elbow_pitch")
    assert d.status == FAIL and d.measured == "brake held"
    assert d.detail.startswith("brake not released (or a jam): check the joint's brake-release switch and brake")
    # from the sensors: no travel, the motor current at the test's limit (2 A on the elbow;
    # its step read through the anti-aliasing filter peaks up to its 10.8 % overshoot above)
    assert "resolver +0.0000 rad" in d.detail
    peak = re.search(r"peak \|current\| ([0-9.]+) A of 2\.00 A", d.detail)
    assert peak is not None and 2.0 <= float(peak.group(1)) <= 2.25, d.detail
    # the joints tested before it were diagnosed healthy
    assert diagnosis(rep, "shoulder_yaw").status == PASS
    outputs_safe(sim)


def test_a_pwm_stage_off_is_named_no_motor_current(sim, cfg):
    sim.inject_fault("amp-off:wrist_roll")
    rep, _ = run(sim, cfg)
    assert not rep.passed
    d = diagnosis(rep, "wrist_roll")
    assert d.status == FAIL and d.measured == "no current"
    assert d.detail.startswith("no motor current: check its PWM stage switch, +28 V and +/-15 V (the servo chassis panel), and the amplifier")
    assert "brake" not in d.detail.split(".")[0]
    outputs_safe(sim)


def test_keep_going_diagnoses_every_joint_from_both_moves(sim, cfg):
    sim.inject_fault("brake-held:wrist_pitch")  # the wrist stalls below its limit (K_a x V_cmd)
    sim.inject_fault("amp-off:elbow_pitch")
    rep, _ = run(sim, cfg, keep_going=True)
    got = {j: diagnosis(rep, j).measured for j in JOINTS}
    assert got == {"shoulder_yaw": "moved", "shoulder_pitch": "moved", "elbow_pitch": "no current",
                   "wrist_pitch": "brake held", "wrist_yaw": "moved", "wrist_roll": "moved"}
    assert "- move:" in diagnosis(rep, "wrist_pitch").detail


def test_a_clean_rack_passes_every_diagnosis_with_the_panel_assumed(sim, cfg):
    rep, lines = run(sim, cfg)
    assert rep.passed, [r.line() for r in rep.failures()]
    for j in JOINTS:
        d = diagnosis(rep, j)
        assert d.status == PASS and d.measured == "moved"
        assert d.detail.startswith("drive answers, brake released")
    # no operator on the simulated rack and nothing stated: assumed, and said so
    rows = panel_rows(rep.results)
    assert list(rows) == ["servo_chassis_28v", "servo_chassis_15v", "pwm_stage_switches",
                          "brake_release_switches"]
    assert all(r.status == SKIP and r.detail.startswith("assumed (no operator asked and no --panel-off given), "
                                                        "not checked by a person") for r in rows.values())
    assert [r.measured for r in rows.values()] == ["on", "on", "all on", "all on"]
    assert rep.panel.startswith("all switches on; assumed")
    assert not any(line.startswith(">>> OPERATOR") for line in lines)


def test_no_panel_rows_when_the_joints_do_not_run(sim, cfg):
    rep = Checkout(sim, cfg, say=lambda _line: None, only=["matrix"]).run()
    assert not panel_rows(rep.results) and rep.panel == ""


def test_non_interactive_run_records_the_panel_as_stated_and_skips_those_joints(tmp_path, capsys):
    jp = tmp_path / "r.json"
    rc = main(["checkout", "--non-interactive", "-q", "--only", "joints", "--json", str(jp),
               "--panel-off", "pwm:wrist_roll,brake:elbow_pitch", "--panel-off", "pwm:gripper"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "servo chassis panel: off: PWM output stage of wrist_roll, gripper; brake-release of elbow_pitch" in out
    d = json.loads(jp.read_text())
    assert "stated on the command line" in d["panel"]
    res = d["results"]
    panel = {r["channel"]: r for r in res if r["group"] == "panel"}
    assert panel["servo_chassis_28v"]["measured"] == "on"
    assert panel["pwm_stage_switches"]["measured"] == "off: wrist_roll, gripper"
    assert panel["brake_release_switches"]["measured"] == "off: elbow_pitch"
    assert all(r["status"] == SKIP and r["detail"].startswith("stated on the command line (--panel-off), "
                                                              "not checked by a person")
               for r in panel.values())
    skipped = {r["channel"]: r["detail"] for r in res if r["check"] == "open-loop test"}
    assert set(skipped) == {"elbow_pitch", "wrist_roll", "gripper"}
    assert skipped["elbow_pitch"].startswith("not run: the command line (--panel-off) states its brake-release")
    assert "PWM output stage switch is off" in skipped["wrist_roll"]
    assert "PWM output stage switch is off" in skipped["gripper"]
    assert all("pfma checkout --only joints" in t for t in skipped.values())
    ran = {r["channel"] for r in res if r["check"] == DIAG and r["status"] == PASS}
    assert ran == set(JOINTS) - {"elbow_pitch", "wrist_roll"}


def test_panel_off_28v_skips_the_joints_group_with_the_reason(tmp_path, capsys):
    jp = tmp_path / "r.json"
    rc = main(["checkout", "--non-interactive", "-q", "--only", "joints", "--panel-off", "28v",
               "--json", str(jp)])
    assert rc == 0, capsys.readouterr().out
    res = json.loads(jp.read_text())["results"]
    joints = [r for r in res if r["group"] == "joints"]
    assert len(joints) == 1 and joints[0]["status"] == SKIP and joints[0]["channel"] == "joints"
    why = joints[0]["detail"]
    assert "+28 VDC is off: nothing can move" in why
    assert "Turn +28 VDC and +/-15 V on, then run `pfma checkout --only joints`" in why
    assert next(r for r in res if r["channel"] == "servo_chassis_28v")["measured"] == "off"


def test_interactive_run_asks_the_panel_through_the_runners_ask(sim, cfg):
    sim.stimulus = None  # a rack with an operator at it
    answers = iter(["y", "yes",
                    "n", "wrist_roll",          # PWM stages: not all on; which: wrist_roll
                    "maybe", "elbow_pitch"])   # brakes: not understood, asked again; named directly
    prompts: list[str] = []

    def ask(prompt: str) -> str:
        prompts.append(prompt)
        return next(answers)
    rep, lines = run(sim, cfg, interactive=True, ask=ask)
    assert len(prompts) == 6 and all(p.startswith(">>> OPERATOR: ") for p in prompts)
    assert "+28 VDC switch (centre) on? [y/n]" in prompts[0]
    assert "+/-15 V DC-DC converter switch (centre) on? [y/n]" in prompts[1]
    assert "PWM output stage switches (left) on, all 7?" in prompts[2]
    assert prompts[3].startswith(">>> OPERATOR: Which PWM stages are off?")
    assert "brake-release switches (right) on, all 6?" in prompts[4]
    assert prompts[5] == prompts[4]  # asked again after an answer not understood
    assert any("not understood: 'maybe'" in line for line in lines)
    rows = panel_rows(rep.results)
    assert rows["pwm_stage_switches"].measured == "off: wrist_roll"
    assert rows["brake_release_switches"].measured == "off: elbow_pitch"
    assert all("the operator's answer, not measured by the checkout" in r.detail for r in rows.values())
    skipped = {r.channel: r.detail for r in rep.results if r.check == "open-loop test"}
    assert set(skipped) == {"elbow_pitch", "wrist_roll"}
    assert all(t.startswith("not run: the operator says its") for t in skipped.values())
    assert rep.passed


def test_interactive_operator_saying_15v_off_skips_the_joints(sim, cfg):
    sim.stimulus = None
    answers = iter(["y", "n", "y", "y"])
    rep, _ = run(sim, cfg, interactive=True, ask=lambda _p: next(answers))
    joints = [r for r in rep.results if r.group == "joints"]
    assert len(joints) == 1 and joints[0].status == SKIP
    assert joints[0].detail.startswith("not run: the operator says the servo chassis +/-15 V DC-DC converter "
                                       "is off: nothing can move")
    outputs_safe(sim)


def test_a_closed_input_stops_the_run_with_one_clear_row(sim, cfg):
    sim.stimulus = None

    def ask(_prompt: str) -> str:
        raise EOFError
    rep, _ = run(sim, cfg, interactive=True, ask=ask)
    f = rep.failures()
    assert len(f) == 1 and "input closed" in f[0].detail and "--panel-off" in f[0].detail
    assert not any(r.check == DIAG for r in rep.results)


def test_stated_panel_given_to_the_runner_is_not_asked(sim, cfg):
    sim.stimulus = None

    def ask(_prompt: str) -> str:
        raise AssertionError("asked although the panel was stated")
    rep, _ = run(sim, cfg, interactive=True, ask=ask, panel=PanelState(frozenset({"15v"}), COMMAND_LINE))
    assert next(r for r in rep.results if r.channel == "servo_chassis_15v").measured == "off"


def test_panel_off_grammar():
    assert parse_panel_off(["28v, pwm:gripper", "brake:wrist_roll"], JOINTS) == \
        {"28v", "pwm:gripper", "brake:wrist_roll"}
    assert parse_panel_off(["none"], JOINTS) == frozenset()
    assert parse_panel_off(["brake:all"], JOINTS) == {f"brake:{j}" for j in JOINTS}
    assert len(parse_panel_off(["pwm:all"], JOINTS)) == 7
    for bad, needle in (("pwm:knee", "no joint 'knee'"), ("brake:gripper", "the gripper has no brake"),
                        ("28v:elbow_pitch", "takes no joint"), ("brake", "needs a joint"),
                        ("29v", "did you mean 28v"), ("none,28v", "'none'"), ("28v,,15v", "empty item")):
        with pytest.raises(ConfigError, match="^--panel-off: ") as e:
            parse_panel_off([bad], JOINTS)
        assert needle in str(e.value), (bad, str(e.value))


def test_a_bad_panel_off_value_is_one_message_and_exit_2(capsys):
    rc = main(["checkout", "--non-interactive", "--panel-off", "pwm:wrist_rol"])
    out = capsys.readouterr()
    assert rc == 2 and "Traceback" not in out.out + out.err
    lines = out.err.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("pfma checkout: --panel-off: no joint 'wrist_rol' for pwm; did you mean wrist_roll")
    assert lines[0].endswith("joints: shoulder_yaw, shoulder_pitch, elbow_pitch, wrist_pitch, wrist_yaw, "
                             "wrist_roll, gripper")
    assert out.out == ""
