"""`pfma checkout` on the simulated rack: passes when healthy, fails naming the channel
for each injected fault, writes well-formed JSON and HTML reports."""

import json
from dataclasses import replace
from html.parser import HTMLParser

import numpy as np
import pytest

from fakes.arm_params import AXES, SimErrors
from tools.checkout import FAIL, PASS, SKIP, Checkout, CheckoutConfig
from bit3.layout import ServiceState
from tools.cli import main


def run(target, cfg, **kw):
    lines = []
    rep = Checkout(target, cfg, say=lines.append, **kw).run()
    return rep, lines


def first_failure(rep):
    fails = rep.failures()
    assert fails, "expected a failure"
    return fails[0]


def outputs_safe(target):
    dac = target.world.bus["dac"]
    assert np.all(dac.output_volts_all() == 0.0)
    assert target.inputs().service_state != ServiceState.ARMED


class _Html(HTMLParser):
    VOID = {"meta", "br", "hr", "img", "link", "input"}

    def __init__(self):
        super().__init__()
        self.stack, self.errors, self.channels, self.tags = [], [], [], set()
        self._in_channel = False

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        a = dict(attrs)
        if tag == "td" and a.get("class") == "channel":
            self._in_channel = True
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unbalanced </{tag}> (open: {self.stack[-3:]})")
        else:
            self.stack.pop()
        if tag == "td":
            self._in_channel = False

    def handle_data(self, data):
        if self._in_channel:
            self.channels.append(data)


def test_healthy_rack_passes_with_json_and_html_reports(tmp_path, capsys):
    jp, hp = tmp_path / "r.json", tmp_path / "r.html"
    rc = main(["checkout", "--rack", "fake", "--non-interactive", "--json", str(jp), "--html", str(hp)])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "RESULT: PASS" in out
    d = json.loads(jp.read_text())
    assert d["passed"] is True and d["counts"]["fail"] == 0 and d["stopped_early"] == ""
    res = d["results"]
    checked = {r["channel"] for r in res if r["status"] == PASS}
    # every group left rows: resolvers, ADC, links, hand, PIO, matrix and each joint both ways
    for name in ("elbow_pitch_angle", "wrist_roll_motor_current", "adc_spare_31", "ft_sensor",
                 "crl_hand_controller", "cae_up_down", "cae_discrete_1", "user_if_box_inputs_hi.7",
                 "matrix_switcher_route"):
        assert name in checked, name
    for j in ("shoulder_yaw", "shoulder_pitch", "elbow_pitch", "wrist_pitch", "wrist_yaw", "wrist_roll"):
        rows = {(r["channel"], r["check"]) for r in res if r["status"] == PASS}
        for sign in "+-":
            assert (f"{j}_rate", f"open-loop rate {sign}") in rows
            assert (f"{j}_angle", f"open-loop travel {sign}") in rows
        assert (j, "disarm") in rows
        assert (f"{j}_motor_current", "motor current responds +") in rows
    # measured values, limits and units are in the report
    ft = next(r for r in res if r["channel"] == "ft_sensor" and r["check"] == "record rate")
    assert ft["measured"] >= 75 and ft["low"] == 75 and ft["units"] == "records/s"
    # the HTML: one self-contained page with a row per result
    text = hp.read_text()
    p = _Html()
    p.feed(text)
    p.close()
    assert not p.errors and not p.stack
    assert not p.tags & {"script", "link", "img", "iframe"} and "http" not in text and "src=" not in text
    assert "<style>" in text
    assert p.channels == [r["channel"] for r in res]
    assert text.count("<tr class=") == len(res)


def test_reversed_tach_fails_naming_the_tach_and_leaves_outputs_safe(sim, cfg):
    err = [0.0] * len(AXES)
    err[[a.joint for a in AXES].index("wrist_yaw")] = -2.0  # tach volts = -K_w qdot
    sim.world.sim.set_errors(SimErrors(tach_scale_error=tuple(err)))
    rep, lines = run(sim, cfg)
    f = first_failure(rep)
    assert f.channel == "wrist_yaw_rate" and f.group == "joints"
    assert "REVERSED" in f.detail and f.measured < 0
    assert not rep.passed and "wrist_yaw_rate" in rep.stopped_early
    # the joints before it passed, the run stopped at the first failure: after it only the
    # joint's drive-and-brake diagnosis (the drive answered: the joint moved)
    k = rep.results.index(f)
    assert all(r.status != FAIL for r in rep.results[:k])
    assert [(r.channel, r.check, r.measured) for r in rep.results[k + 1:]] == \
        [("wrist_yaw", "drive and brake (diagnosis)", "moved")]
    assert any(r.channel == "wrist_pitch" and r.check == "disarm" for r in rep.results) is False
    outputs_safe(sim)


def test_dead_adc_channel_fails_naming_the_channel(sim, cfg):
    e = sim.world.sim.errors
    sim.world.sim.set_errors(replace(e, adc_gain_error={"elbow_pitch_motor_current": -1.0},
                                     adc_offset_v={"elbow_pitch_motor_current": 3.0}))
    rep, _ = run(sim, cfg)
    f = first_failure(rep)
    assert (f.group, f.channel) == ("adc", "elbow_pitch_motor_current")
    assert f.measured == pytest.approx(3.0, abs=0.01) and (f.low, f.high) == (-0.25, 0.25)
    assert f.units == "A"


def test_dead_tach_at_zero_volts_passes_idle_but_fails_the_open_loop_test(sim, cfg):
    sim.world.sim.set_errors(replace(sim.world.sim.errors, adc_gain_error={"wrist_pitch_rate": -1.0}))
    rep, _ = run(sim, cfg)
    idle = next(r for r in rep.results if r.channel == "wrist_pitch_rate" and r.group == "adc")
    assert idle.status == PASS
    f = first_failure(rep)
    assert (f.group, f.channel, f.check) == ("joints", "wrist_pitch_rate", "open-loop rate +")
    assert f.measured == 0
    assert "TACH NOT RESPONDING" in f.detail and "REVERSED" not in f.detail
    outputs_safe(sim)


def test_dead_motor_current_at_zero_volts_passes_idle_but_fails_when_driven(sim, cfg):
    sim.world.sim.set_errors(replace(sim.world.sim.errors, adc_gain_error={"elbow_pitch_motor_current": -1.0}))
    rep, _ = run(sim, cfg)
    idle = next(r for r in rep.results if r.channel == "elbow_pitch_motor_current" and r.group == "adc")
    assert idle.status == PASS
    f = first_failure(rep)
    assert (f.group, f.channel, f.check) == ("joints", "elbow_pitch_motor_current", "motor current responds +")
    assert f.measured == 0 and f.low > 0 and f.units == "A"
    assert "MOTOR CURRENT NOT RESPONDING" in f.detail
    # the joints driven before it showed their currents responding
    ok = {r.channel for r in rep.results if r.check.startswith("motor current responds") and r.status == PASS}
    assert "shoulder_yaw_motor_current" in ok
    outputs_safe(sim)


def test_spare_adc_held_at_fixed_volts_fails_by_cli(capsys):
    rc = main(["checkout", "--non-interactive", "-q", "--only", "adc", "--sim-fault", "adc-dead:adc_spare_27=2.0"])
    out = capsys.readouterr().out
    assert rc == 1
    assert "FAILED: adc_spare_27 (adc, idle: spare)" in out and "RESULT: FAIL" in out


def test_resolver_loss_of_signal_fails_naming_the_resolver(sim, cfg):
    ch = sim.rack.channel("wrist_yaw_angle")
    sim.world.bus[ch.board].inject("loss_of_signal", channel=ch.channel)
    rep, _ = run(sim, cfg)
    f = first_failure(rep)
    assert (f.group, f.channel, f.check) == ("resolvers", "wrist_yaw_angle", "valid (status bits)")
    assert "loss of signal" in f.detail and f.measured == 1
    # the resolvers checked before it passed
    assert [r.channel for r in rep.results if r.group == "resolvers" and r.status == PASS][:2] == \
        ["elbow_pitch_angle", "elbow_pitch_angle"]


@pytest.mark.parametrize("fault", ["noise", "drops"])
def test_noisy_ft_line_fails_naming_the_link(sim, cfg, fault):
    for k in range(300):  # a burst every ~300 bytes for the whole run
        if fault == "noise":
            sim.world.ft.inject_noise(b"\x55\xaa\x13", after_bytes=300 * k)
        else:
            sim.world.ft.drop_next(3, after_bytes=300 * k)
    rep, _ = run(sim, cfg)
    f = first_failure(rep)
    assert (f.group, f.channel, f.check) == ("links", "ft_sensor", "bad records")
    assert f.measured > 0 and f.high == 0


def test_keep_going_reports_every_failure(sim, cfg):
    sim.inject_fault("resolver-los:wrist_yaw_angle")
    sim.inject_fault("resolver-los:shoulder_pitch_angle")
    rep, _ = run(sim, cfg, keep_going=True, only=["resolvers", "adc"])
    assert {r.channel for r in rep.failures()} == {"wrist_yaw_angle", "shoulder_pitch_angle"}
    assert rep.stopped_early == "" and not rep.passed
    assert any(r.group == "adc" and r.status == PASS for r in rep.results)


def test_operator_steps_time_out_without_stimulus_or_skip_when_non_interactive(sim, cfg):
    data = cfg.as_dict()
    data["checkout"]["operator_timeout_s"] = 0.2
    short = CheckoutConfig(data, "test")
    sim.stimulus = None  # a rack nobody operates
    rep, lines = run(sim, short, only=["hand"], interactive=True)
    f = first_failure(rep)
    assert (f.channel, f.check) == ("cae_up_down", "deflect +")
    assert any(line.startswith(">>> OPERATOR: Deflect the CAE stick UP") for line in lines)
    rep, _ = run(sim, short, only=["hand", "pio"], interactive=False)
    skipped = [r for r in rep.results if r.group in ("hand", "pio") and r.status == SKIP]
    assert len(skipped) == 6 + 3 + 16 and rep.count(FAIL) == 0


def test_unknown_fault_spec_and_group_are_refused(sim, cfg):
    from pfma.errors import ConfigError, PfmaError
    with pytest.raises(ConfigError, match="tach-reversed"):
        sim.inject_fault("tach-sideways:wrist_yaw")
    with pytest.raises(ConfigError, match="no joint"):
        sim.inject_fault("tach-reversed:knee")
    with pytest.raises(PfmaError, match="unknown checkout group"):
        Checkout(sim, cfg, only=["teleport"])


def test_limits_read_as_words_with_units_never_as_infinities():
    from tools.checkout.report import Result
    assert Result("g", "c", "k", "PASS", 1.0, None, 0.01, "V").limits_text() == "<= 0.01 V"
    assert Result("g", "c", "k", "PASS", 1.0, float("-inf"), 0.0, "V").limits_text() == "<= 0 V"
    assert Result("g", "c", "k", "PASS", 1.0, 3.0, None, "rad/s").limits_text() == ">= 3 rad/s"
    assert Result("g", "c", "k", "PASS", 1.0, 0.5, 2.0, "A").limits_text() == "0.5 .. 2 A"
    assert Result("g", "c", "k", "PASS", 1, 0x40, 0x40, "1").limits_text() == "= 64"
    line = Result("resolvers", "elbow_pitch_angle", "noise", "PASS", 1.0, None, 2.0, "counts").line()
    assert "inf" not in line and "<= 2 counts" in line
