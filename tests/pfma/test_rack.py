"""Rack configuration: the default is the IRSS report's section 3.4.2 tables, channel for channel."""

import json

import pytest

from tools.cli import main
from pfma.errors import ConfigError
from pfma.rack import DEFAULT_RACK, load_rack, parse_rack

# The seed's tables, transcribed independently of pfma/rack_default.toml (IRSS report 3.4.2).
SEED_RTD = {
    0x0100: ["Elbow Pitch", "Wrist Yaw", "Wrist Pitch", "Wrist Roll"],
    0x0200: ["Shoulder Yaw", "Shoulder Pitch", "Not used", "Not used"],
}
SEED_DAC = ["Shoulder Pitch Command", "Shoulder Yaw Command", "Elbow Pitch Command",
            "Wrist Yaw Command", "Wrist Pitch Command", "Wrist Roll Command", "Gripper Command",
            "Shoulder Pitch Current Limit", "Shoulder Yaw Current Limit",
            "Elbow Pitch Current Limit", "Wrist Yaw Current Limit", "Wrist Pitch Current Limit",
            "Wrist Roll Current Limit", "Gripper Current Limit", "Spare", "Spare"]
SEED_ADC = (["Shoulder Yaw Motor Current", "Shoulder Pitch Motor Current",
             "Shoulder Roll Motor Current", "Elbow Pitch Motor Current",
             "Wrist Pitch Motor Current", "Wrist Yaw Motor Current", "Wrist Roll Motor Current",
             "End Effector Motor Current", "Shoulder Yaw Rate", "Shoulder Pitch Rate",
             "Shoulder Roll Rate", "Elbow Pitch Rate", "Wrist Pitch Rate", "Wrist Yaw Rate",
             "Wrist Roll Rate", "End Effector Rate", "CAE Up/Down", "CAE Forward/Backward",
             "CAE Right/Left", "CAE Yaw", "CAE Pitch", "CAE Roll", "CAE Discrete 1",
             "CAE Discrete 2", "CAE Discrete 3"] + ["Spare"] * 7)


def _json_channels(capsys):
    assert main(["channels", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_channels_json_matches_seed_tables(capsys):
    chans = _json_channels(capsys)
    by = lambda dev, addr: sorted((c for c in chans if c["device"] == dev and c["address"] == addr),
                                  key=lambda c: c["channel"])
    for addr, labels in SEED_RTD.items():
        got = by("rtd", addr)
        assert [c["label"] for c in got] == labels
        assert all(c["rate_hz"] == 160 and c["direction"] == "in" for c in got)
        assert [c["spare"] for c in got] == [lab == "Not used" for lab in labels]
    dac = by("dac", 0xD000)
    assert [c["label"] for c in dac] == SEED_DAC
    assert all(c["rate_hz"] == 320 and c["direction"] == "out" for c in dac)
    adc = by("adc", 0xC000)
    assert [c["label"] for c in adc] == SEED_ADC
    assert all(c["rate_hz"] == 160 for c in adc)
    serial = by("serial", 0x0000)
    assert [c["signal"] for c in serial] == ["ft_sensor", "crl_hand_controller"]
    assert serial[0]["rate_hz"] == 80 and serial[0]["baud"] == 19200
    assert {c["address"] for c in chans if c["device"] == "pio"} == {0x0020, 0x0040}
    assert [c["direction"] for c in by("pio", 0x0040)][:2] == ["in", "in"]
    assert by("pio", 0x0020)[0]["direction"] == "out"


def test_signal_names_examples_and_uniqueness(capsys):
    chans = _json_channels(capsys)
    names = [c["signal"] for c in chans]
    assert len(names) == len(set(names))
    for expected in ("elbow_pitch_angle", "shoulder_yaw_motor_current", "wrist_roll_current_limit"):
        assert expected in names
    required = {"device", "address", "channel", "signal", "label", "units", "direction", "rate_hz"}
    assert all(required <= set(c) for c in chans)


def test_channels_table_prints(capsys):
    assert main(["channels"]) == 0
    out = capsys.readouterr().out
    assert "0xD000" in out and "wrist_roll_current_limit" in out


def _text_with(old: str, new: str) -> str:
    text = DEFAULT_RACK.read_text()
    assert old in text
    return text.replace(old, new, 1)


def _line_of(text: str, needle: str, nth: int = 1) -> int:
    hits = [i for i, line in enumerate(text.splitlines(), 1) if needle in line]
    return hits[nth - 1]


def test_overlapping_boards_refused_naming_line():
    text = _text_with("base = 0x0200", "base = 0x0110")
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    msg = str(exc.value)
    assert "overlaps" in msg and "rtd1" in msg
    assert f"rack.toml:{_line_of(text, 'base = 0x0110')}:" in msg  # the offending key's line


def test_channel_listed_twice_refused_naming_line():
    text = _text_with('{ ch = 3, signal = "wrist_roll_angle"', '{ ch = 2, signal = "wrist_roll_angle"')
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    assert "channel 2 listed twice" in str(exc.value)
    assert f"rack.toml:{_line_of(text, 'wrist_roll_angle')}:" in str(exc.value)


def test_unknown_device_refused_naming_line():
    text = _text_with('kind = "dvme611"', 'kind = "dvme999"')
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    assert "unknown device kind 'dvme999'" in str(exc.value)
    line = _line_of(text, 'kind = "dvme999"')
    assert f"rack.toml:{line}:" in str(exc.value)


def test_device_not_matching_kind_names_its_line():
    text = _text_with('device = "adc"', 'device = "scope"')
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    assert "not 'scope'" in str(exc.value)
    line = _line_of(text, 'device = "scope"')
    assert f"rack.toml:{line}:" in str(exc.value)


def test_duplicate_channel_line_with_keys_in_any_order():
    # an entry whose first key is not ``ch`` must not shift the line of later entries
    text = _text_with('{ ch = 0, signal = "elbow_pitch_angle",', '{ signal = "elbow_pitch_angle", ch = 0,')
    text = text.replace('{ ch = 3, signal = "wrist_roll_angle"', '{ ch = 2, signal = "wrist_roll_angle"', 1)
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    assert "channel 2 listed twice" in str(exc.value)
    assert f"rack.toml:{_line_of(text, 'wrist_roll_angle')}:" in str(exc.value)


def test_duplicate_channel_line_with_two_entries_on_one_line():
    text = _text_with('quantity = "angle" },\n  { ch = 1, signal = "wrist_yaw_angle"',
                      'quantity = "angle" }, { ch = 1, signal = "wrist_yaw_angle"')
    text = text.replace('{ ch = 3, signal = "wrist_roll_angle"', '{ ch = 1, signal = "wrist_roll_angle"', 1)
    with pytest.raises(ConfigError) as exc:
        parse_rack(text, "rack.toml")
    assert "channel 1 listed twice" in str(exc.value)
    assert f"rack.toml:{_line_of(text, 'wrist_roll_angle')}:" in str(exc.value)


def test_duplicate_channel_line_in_array_of_tables_form():
    text = """[[board]]
name = "rtd1"
kind = "vmivme4940"
base = 0x0100
rate_hz = 160

[[board.channels]]
ch = 0
signal = "a_angle"
label = "A"
units = "rad"

[[board.channels]]
signal = "b_angle"
ch = 0
label = "B"
units = "rad"
"""
    with pytest.raises(ConfigError, match=r"^rack.toml:13: board rtd1: channel 0 listed twice"):
        parse_rack(text, "rack.toml")


@pytest.mark.parametrize("old,new,words", [
    ('signal = "elbow_pitch_angle"', 'signal = "Elbow Pitch"', "snake_case"),
    ('{ ch = 31, signal = "adc_spare_31"', '{ ch = 32, signal = "adc_spare_31"', "out of range"),
    ('signal = "wrist_yaw_angle"', 'signal = "elbow_pitch_angle"', "used twice"),
    ('rate_hz = 320', 'rate_hz = 0', "rate_hz must be positive"),
    ('name = "adc"', 'name = "adc"\nbogus = 1', "unknown key"),
])
def test_other_invalid_configs_refused(old, new, words):
    with pytest.raises(ConfigError, match=words):
        parse_rack(_text_with(old, new), "rack.toml")


def test_missing_channel_refused_and_default_loads():
    text = _text_with('  { ch = 15, signal = "dac_spare_15",                 label = "Spare",                        units = "V", spare = true },\n', "")
    with pytest.raises(ConfigError, match=r"channel\(s\) 15 not listed"):
        parse_rack(text, "rack.toml")
    rack = load_rack()
    assert len(rack.channels()) == 4 + 4 + 16 + 32 + 2 + 4 + 4
    assert rack.channel("gripper_current_limit").channel == 13


def test_toml_syntax_error_is_config_error(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[[board]\nname = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_rack(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_rack(tmp_path / "missing.toml")


def _first_match(text: str, pattern: str) -> str:
    import re
    m = re.search(pattern, text, re.M)
    assert m, pattern
    return m.group(0)


@pytest.mark.parametrize("pattern,new,words,needle", [
    (r"rate_hz = 320", 'rate_hz = "fast"', "rate_hz must be a number", 'rate_hz = "fast"'),
    (r"base = 0x0200", "base = 0x0201", "base 0x0201 is odd", "base = 0x0201"),
    (r"base = 0x0200", 'base = "0x0200"', "not an A16 address", 'base = "0x0200"'),
    (r"base = 0x0200", "base = true", "not an A16 address", "base = true"),
    (r"scale = [-0-9.e]+", 'scale = "x"', "scale must be a number", 'scale = "x"'),
    (r"scale = 0.04", "scale = 0.04, offset = [1]", "offset must be a number", "offset = [1]"),
    (r"baud = 19200", "baud = 19201", "baud 19201 is not a rate", "baud = 19201"),
    (r"baud = 19200", 'baud = "fast"', "baud 'fast' is not a rate", 'baud = "fast"'),
    (r"^size = 32768", "size = 4096", r"\[bit3\] size must be 32768", "size = 4096"),
    (r"^io_window = .*", "io_window = [0x800000]", r"\[bit3\] io_window must be a \[lo, hi\]",
     "io_window = [0x800000]"),
    (r"^io_window = .*", "io_window = [0x800000, 0x80FFFF]", "spans 65536 bytes",
     "io_window = [0x800000, 0x80FFFF]"),
    (r"^size = 32768", "size = 32768\nbogus = 1", r"\[bit3\]: unknown key", "bogus = 1"),
])
def test_wrong_types_and_values_refused_naming_line_and_field(pattern, new, words, needle):
    base = DEFAULT_RACK.read_text()
    text = base.replace(_first_match(base, pattern), new, 1)
    with pytest.raises(ConfigError, match=words) as exc:
        parse_rack(text, "rack.toml")
    assert str(exc.value).startswith(f"rack.toml:{_line_of(text, needle)}: "), str(exc.value)


def test_non_utf8_rack_file_names_file_and_line(tmp_path):
    p = tmp_path / "latin1.toml"
    p.write_bytes(DEFAULT_RACK.read_bytes() + b"# caf\xe9\n")
    n = DEFAULT_RACK.read_text().count("\n") + 1
    with pytest.raises(ConfigError, match=rf"^{p}:{n}: not UTF-8 text \(byte 0xE9"):
        load_rack(p)


def test_default_rack_bit3_section_is_read():
    assert load_rack().bit3 == {"size": 32768, "computational_window": (0x01ED0000, 0x01ED7FFF),
                                "io_window": (0x800000, 0x807FFF)}


# -- channel roles: which joint a channel belongs to and what it carries ----------------

def test_every_servoed_joint_has_its_channels_by_role_matching_the_seed_wording():
    rack = load_rack()
    assert rack.joints == ("shoulder_yaw", "shoulder_pitch", "elbow_pitch", "wrist_pitch", "wrist_yaw",
                           "wrist_roll")
    for j in rack.joints:
        words = j.replace("_", " ").title()  # the seed's label wording, e.g. "Elbow Pitch"
        assert rack.joint_channel(j, "angle").label == words
        assert rack.joint_channel(j, "rate").label == f"{words} Rate"
        assert rack.joint_channel(j, "motor_current").label == f"{words} Motor Current"
        assert rack.joint_channel(j, "rate_command").label == f"{words} Command"
        assert rack.joint_channel(j, "current_limit").label == f"{words} Current Limit"
    # the gripper's ADC monitors carry the seed's "End Effector" wording
    assert rack.joint_channel("gripper", "rate").label == "End Effector Rate"
    assert rack.joint_channel("gripper", "gripper_command").label == "Gripper Command"
    assert [c.label for c in rack.with_quantity("hand_controller")] == SEED_ADC[16:25]
    assert rack.find("shoulder_roll", "angle") is None  # indexed by hand: no resolver


def test_layout_joint_order_comes_from_the_rate_command_roles_not_the_signal_names():
    from bit3.layout import build_layout
    text = _text_with('signal = "wrist_roll_command",', 'signal = "wr_cmd",')
    lay = build_layout(parse_rack(text, "rack.toml"))
    assert lay.joint_names[-1] == "wrist_roll"
    assert lay.joint_entry("dac", "wrist_roll", "rate_command").name == "wr_cmd"


@pytest.mark.parametrize("old,new,words", [
    ('quantity = "angle" },\n  { ch = 1, signal = "wrist_yaw_angle"',
     'quantity = "volts" },\n  { ch = 1, signal = "wrist_yaw_angle"', "quantity 'volts' is not one of"),
    ('joint = "elbow_pitch", quantity = "angle"', 'joint = "elbow_pitch", quantity = "rate"',
     "a rtd channel cannot carry 'rate'"),
    ('joint = "wrist_yaw", quantity = "angle"', 'joint = "elbow_pitch", quantity = "angle"',
     "joint 'elbow_pitch' has two angle channels"),
    ('joint = "wrist_yaw", quantity = "angle"', 'quantity = "angle"', "needs the joint it belongs to"),
    ('joint = "wrist_yaw", quantity = "angle"', 'joint = "wrist_yaw"', "names joint 'wrist_yaw' but no quantity"),
    ('"wrist_roll"]', '"wrist_roll", "gripper"]', "joint 'gripper' has no angle, rate_command channel"),
    ('joints = ["shoulder_yaw",', 'joints = ["shoulder_yaw", "shoulder_yaw",', "lists a joint twice"),
])
def test_bad_channel_roles_are_refused_naming_the_line(old, new, words):
    with pytest.raises(ConfigError, match=words) as exc:
        parse_rack(_text_with(old, new), "rack.toml")
    assert "rack.toml:" in str(exc.value)
