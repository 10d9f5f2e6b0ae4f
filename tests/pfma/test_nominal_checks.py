"""Rack files that would invert or distort the loop are refused at parse (issue 28 item 7):
scales checked against the nominal arm (sign, band), offsets bounded, limits within the DAC
range and the joint's full scale; ``[checks] allow_nonnominal`` lets a lab accept a value
outside the band; ``rate_hz`` is the schedule's or refused."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from pfma import nominal
from pfma.arm import JOINTS, joint
from pfma.errors import ConfigError
from pfma.rack import DEFAULT_RACK, SCHEDULED_RATES_HZ, load_rack, parse_rack
from tools.cli import main

TEXT = DEFAULT_RACK.read_text()


def _line_of_signal(text: str, signal: str) -> int:
    hits = [n for n, line in enumerate(text.splitlines(), 1) if f'signal = "{signal}"' in line]
    assert len(hits) == 1, signal
    return hits[0]


def _with_fields(signal: str, text: str = TEXT, **fields) -> str:
    """The default rack text with ``signal``'s channel entry given ``fields`` (None: removed)."""
    lines = text.splitlines(keepends=True)
    n = _line_of_signal(text, signal) - 1
    line = lines[n]
    for key, value in fields.items():
        pat = re.compile(rf"\b{key} = [^,}}]+, ")
        if value is None:
            line = pat.sub("", line)
        elif pat.search(line):
            line = pat.sub(f"{key} = {value!r}, ", line)
        else:
            line = line.replace(f'signal = "{signal}", ', f'signal = "{signal}", {key} = {value!r}, ')
    lines[n] = line
    return "".join(lines)


def _refusal(text: str) -> str:
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    return str(exc.value)


def test_the_default_rack_is_within_every_band_and_needs_no_override():
    rack = load_rack()
    assert rack.overrides == () and rack.nonnominal == ()
    checked = [c for c in rack.channels() if nominal.nominal(c.device, c.joint, c.quantity)]
    # every servoed joint's rate command, current limit, tach, current monitor and resolver
    assert len(checked) == 6 * 5 + 3  # + the gripper's command, current limit and monitor
    for c in checked:
        assert nominal.check(c.device, c.joint, c.quantity, c.units, c.scale, c.offset, c.limit) == []


# the issue's files, one refusal each: (signal, fields, field named, words of the band)
ISSUE_CASES = [
    # a negative DAC scale: a runaway
    ("elbow_pitch_command", {"scale": -0.05}, "scale = -0.05", "sign inverted", "0.025..0.1 rad/s per V"),
    # a scale 100x too small: a +-10 V limit cycle (the limit shrunk with it, so only the scale is wrong)
    ("elbow_pitch_command", {"scale": 0.0005, "limit": 0.005}, "scale = 0.0005", "0.01x the nominal scale",
     "0.025..0.1 rad/s per V"),
    # a limit beyond the DAC range
    ("wrist_roll_command", {"limit": 3.0}, "limit = 3", "beyond what the DAC can express", "limit <= 2 rad/s"),
    # a limit within the DAC range (scale 2x nominal) but beyond the joint's full scale
    ("shoulder_yaw_command", {"scale": 0.08, "limit": 0.8}, "limit = 0.8", "beyond the joint's full scale",
     "limit <= 0.4 rad/s"),
    # an offset of 2 V
    ("wrist_yaw_current_limit", {"offset": 1.0}, "offset = 1", "2 V at scale 0.5", "|offset| <= 1 V x |scale| = 0.5 A"),
    # the tach and the current monitor and the resolver are judged too
    ("shoulder_pitch_rate", {"scale": -0.04}, "scale = -0.04", "sign inverted", "0.02..0.08 rad/s per V"),
    ("wrist_roll_motor_current", {"scale": 5.0}, "scale = 5", "10x the nominal", "0.25..1 A per V"),
    ("elbow_pitch_angle", {"scale": 57.29577951308232}, "scale = 57.2958", "57.3x the nominal", "0.5..2 rad per V"),
    ("elbow_pitch_angle", {"offset": 7.0}, "offset = 7", "more than one turn", "|offset| <= 6.28319 rad"),
    ("gripper_current_limit", {"scale": 1e300}, "scale = 1e+300", "the nominal scale", "0.25..1 A per V"),
]


@pytest.mark.parametrize("signal,fields,named,why,band", ISSUE_CASES)
def test_a_file_that_distorts_the_loop_is_one_message_naming_file_line_field_value_and_band(
        signal, fields, named, why, band):
    text = _with_fields(signal, **fields)
    msg = _refusal(text)
    assert msg.startswith(f"rack.toml:{_line_of_signal(text, signal)}: "), msg
    assert f"({signal}) {named}:" in msg and why in msg and band in msg, msg
    assert msg.count("\n") == 0


def test_the_dac_range_is_a_fact_of_the_board_no_override_lets_it_through():
    text = _with_fields("wrist_roll_command", limit=3.0) + \
        '\n[checks]\nallow_nonnominal = ["wrist_roll_command.limit"]\n'
    msg = _refusal(text)
    assert "beyond what the DAC can express" in msg and "not overridable" in msg
    assert "allow_nonnominal" not in msg  # no hint at an override that would not help


def test_the_dac_range_constant_is_the_boards():
    from drivers.dac.vmivme4100 import Vmivme4100
    assert Vmivme4100(None, 0xD000).range_volts == nominal.DAC_FULL_SCALE_V


def test_nominal_scales_are_the_joint_tables():
    for j in JOINTS:
        assert nominal.nominal("dac", j.name, "rate_command").scale == pytest.approx(j.omega_fs_rad_s / 10)
        assert nominal.nominal("adc", j.name, "rate").scale == pytest.approx(1 / j.k_w_v_per_rad_s)
        assert nominal.nominal("dac", j.name, "current_limit").full_scale == j.i_max_a
    assert nominal.nominal("adc", "shoulder_roll", "rate") is None  # indexed by hand: no model figure
    assert nominal.nominal("adc", "", "hand_controller") is None


# scale factors and the channels they are applied to; DAC channels lose their limit (the
# DAC's full range is then the limit) so that only the scale is judged
PERTURBED = ["elbow_pitch_command", "wrist_roll_current_limit", "shoulder_yaw_rate", "wrist_pitch_motor_current",
             "wrist_yaw_angle"]


@settings(max_examples=60, deadline=None)
@given(signal=st.sampled_from(PERTURBED), sign=st.sampled_from([1.0, -1.0]),
       log_factor=st.floats(min_value=-3.0, max_value=3.0))
def test_a_perturbed_scale_is_accepted_exactly_inside_the_band(signal, sign, log_factor):
    factor = sign * 10.0 ** log_factor
    lo, hi = nominal.SCALE_BAND
    # not within rounding of an edge of the band (either answer would be right there)
    assume(min(abs(log_factor - math.log10(lo)), abs(log_factor - math.log10(hi))) > 1e-6)
    c = load_rack().channel(signal)
    fields: dict = {"scale": c.scale * factor}
    if c.device == "dac":
        fields["limit"] = None
    text = _with_fields(signal, **fields)
    inside = sign > 0 and lo <= abs(factor) <= hi
    if inside:
        assert parse_rack(text, "rack.toml").channel(signal).scale == pytest.approx(c.scale * factor)
    else:
        msg = _refusal(text)
        assert f"({signal}) scale = " in msg
        assert ("sign inverted" in msg) == (sign < 0), msg


def test_an_override_accepts_the_value_and_says_so():
    text = _with_fields("elbow_pitch_command", scale=-0.05) + \
        '\n[checks]\nallow_nonnominal = ["elbow_pitch_command.scale", "wrist_yaw_rate.scale"]\n'
    rack = parse_rack(text, "rack.toml")
    assert rack.channel("elbow_pitch_command").scale == -0.05
    assert rack.overrides == ("elbow_pitch_command.scale", "wrist_yaw_rate.scale")
    [(key, said)] = rack.nonnominal  # the unused override accepts nothing
    assert key == "elbow_pitch_command.scale"
    assert "elbow_pitch_command.scale = -0.05" in said and "rack.toml" in said and "sign inverted" in said


@pytest.mark.parametrize("entry,words", [
    ('["elbow_pitch_comand.scale"]', "did you mean elbow_pitch_command"),
    ('["elbow_pitch_command.sign"]', "field one of scale, offset, limit"),
    ('["cae_roll.scale"]', "'cae_roll' is not a channel the nominal checks judge"),
    ('["shoulder_yaw_rate.limit"]', "only DAC channels have a limit"),
    ('"elbow_pitch_command.scale"', "must be a list"),
    ('["elbow_pitch_command.scale", "elbow_pitch_command.scale"]', "names an entry twice"),
])
def test_a_bad_override_entry_is_refused_naming_its_line(entry, words):
    text = TEXT + f"\n[checks]\nallow_nonnominal = {entry}\n"
    msg = _refusal(text)
    assert msg.startswith(f"rack.toml:{len(text.splitlines())}: ") and words in msg, msg


def test_rate_hz_is_the_schedules_or_refused_naming_the_supported_rates():
    text = TEXT.replace("rate_hz = 320", "rate_hz = 1000", 1)
    msg = _refusal(text)
    line = [n for n, ln in enumerate(text.splitlines(), 1) if ln.startswith("rate_hz = 1000")][0]
    assert msg.startswith(f"rack.toml:{line}: board dac: rate_hz = 1000"), msg
    assert "runs dac boards at 320 Hz" in msg and "rtd 160 Hz" in msg and "pio 40 Hz" in msg
    # left out: the schedule's rate
    rack = parse_rack(re.sub(r"^rate_hz = .*\n", "", TEXT, flags=re.M), "rack.toml")
    assert {b.device: b.rate_hz for b in rack.boards} == SCHEDULED_RATES_HZ


def test_channels_and_serve_on_a_bad_rack_file_exit_1_with_one_line(tmp_path, capsys):
    path = tmp_path / "inverted.toml"
    path.write_text(_with_fields("wrist_pitch_command", scale=-0.1))
    for argv in (["channels", "--rack", str(path)], ["serve", "--rack", str(path), "--bus", "fake"]):
        assert main(argv) == 1
        out = capsys.readouterr()
        lines = [ln for ln in out.err.splitlines() if ln.strip()]
        assert len(lines) == 1, out.err
        assert lines[0].startswith(f"pfma {argv[0]}: {path}:{_line_of_signal(path.read_text(), 'wrist_pitch_command')}:")
        assert "(wrist_pitch_command) scale = -0.1: sign inverted" in lines[0]
        assert "Traceback" not in out.out + out.err


def test_the_gripper_i_max_is_one_figure():
    from controller import params
    assert params.GRIPPER_I_MAX_A is nominal.GRIPPER_I_MAX_A
    assert load_rack().channel("gripper_current_limit").scale * 10 == nominal.GRIPPER_I_MAX_A
    assert joint("wrist_roll").i_max_a == load_rack().channel("wrist_roll_current_limit").limit
