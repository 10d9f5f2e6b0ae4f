"""Calibration files that would invert or distort the loop are refused (issue 28 item 7):
each joint channel's scale and offset against the nominal arm as the rack file's are, and
the ``previous_hash`` chain verified at load."""

from __future__ import annotations

import json
import math
import shutil

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from calibration import files
from pfma import nominal
from pfma.errors import CalibrationError
from pfma.rack import DEFAULT_RACK, load_rack, parse_rack


@pytest.fixture
def rack():
    return load_rack()


def _data(rack, **scales) -> dict:
    d = files.nominal_calibration(rack, "ann", date="2026-01-01T00:00:00Z").data
    for sig, (scale, offset) in scales.items():
        d["channels"][sig]["scale"] = scale
        d["channels"][sig]["offset"] = offset
    return d


@pytest.mark.parametrize("signal,scale,offset,field,words", [
    ("elbow_pitch_command", 1e300, 0.0, "scale", "2e+301x the nominal scale; accepted 0.025..0.1 rad/s per V"),
    ("elbow_pitch_command", -0.05, 0.0, "scale", "sign inverted"),
    ("wrist_roll_rate", 0.002, 0.0, "scale", "0.01x the nominal scale; accepted 0.1..0.4 rad/s per V"),
    ("shoulder_pitch_current_limit", 1.0, -1.5, "offset",
     "1.5 V at scale 1; accepted |offset| <= 1 V x |scale| = 1 A"),
    ("wrist_roll_angle", -1.0, 0.0, "scale", "sign inverted"),
])
def test_a_value_that_distorts_the_loop_is_refused_naming_field_value_and_band(rack, signal, scale, offset, field,
                                                                               words):
    d = _data(rack, **{signal: (scale, offset)})
    with pytest.raises(CalibrationError) as exc:
        files.validate(d, rack=rack, source="cal.json")
    msg = str(exc.value)
    value = scale if field == "scale" else offset
    assert msg.startswith(f"calibration cal.json: channels.{signal}.{field}: {value:g}: "), msg
    assert words in msg and "previous calibration stays in force" in msg
    assert f'lists "{signal}.{field}" in the rack file\'s [checks] allow_nonnominal' in msg


@settings(max_examples=40, deadline=None)
@given(signal=st.sampled_from(["shoulder_yaw_command", "wrist_pitch_rate", "elbow_pitch_motor_current",
                               "gripper_current_limit", "shoulder_pitch_angle"]),
       sign=st.sampled_from([1.0, -1.0]), log_factor=st.floats(min_value=-4.0, max_value=4.0))
def test_a_perturbed_calibrated_scale_is_accepted_exactly_inside_the_band(signal, sign, log_factor):
    rack = load_rack()
    lo, hi = nominal.SCALE_BAND
    assume(min(abs(log_factor - math.log10(lo)), abs(log_factor - math.log10(hi))) > 1e-6)
    factor = sign * 10.0 ** log_factor
    c = rack.channel(signal)
    d = _data(rack, **{signal: (c.scale * factor, 0.0)})
    if sign > 0 and lo <= abs(factor) <= hi:
        assert files.validate(d, rack=rack).channel(signal)["scale"] == c.scale * factor
    else:
        with pytest.raises(CalibrationError, match=rf"channels\.{signal}\.scale: "):
            files.validate(d, rack=rack)


def test_without_a_rack_only_the_types_are_judged(rack):
    # the history's own files are read without a rack; the service always gives one
    d = _data(rack, elbow_pitch_command=(-0.05, 0.0))
    assert files.validate(d).channel("elbow_pitch_command")["scale"] == -0.05


def test_the_rack_files_override_accepts_a_calibration_and_says_so(rack):
    over = parse_rack(DEFAULT_RACK.read_text() + '\n[checks]\nallow_nonnominal = ["wrist_yaw_command.scale"]\n',
                      "lab.toml")
    d = _data(over, wrist_yaw_command=(-0.1, 0.0))
    cal = files.validate(d, rack=over, source="cal.json")
    [(key, said)] = cal.nonnominal
    assert key == "wrist_yaw_command.scale"
    assert said.startswith("calibration cal.json: wrist_yaw_command.scale = -0.1 accepted") and "lab.toml" in said
    with pytest.raises(CalibrationError, match="sign inverted"):  # the default rack has no override
        files.validate(d, rack=rack)


# ------------------------------------------------------------------ the hash chain
def _three_versions(tmp_path, rack):
    p = tmp_path / "cal.json"
    cal = files.save_calibration(files.nominal_calibration(rack, "ann"), p, rack=rack)
    for k in (1, 2):
        cal = files.save_calibration(cal.updated(channels={"adc_spare_25": {"scale": 1 + k / 100}}), p, rack=rack)
    return p


def test_an_intact_chain_loads_and_is_walked_to_its_first_version(tmp_path, rack):
    p = _three_versions(tmp_path, rack)
    cal = files.load_calibration(p, rack)
    chain = files.verify_chain_of(cal, p)
    assert [c.version for c in chain] == [2, 1, 0]
    assert chain[0].data["previous_hash"] == chain[1].hash().hex()
    assert chain[-1].data["previous_hash"] is None


def test_an_altered_kept_version_breaks_the_chain(tmp_path, rack):
    p = _three_versions(tmp_path, rack)
    kept = tmp_path / "cal.json.history" / "cal.v0001.json"
    d = json.loads(kept.read_text())
    want = files.load_calibration(p).data["previous_hash"]
    d["channels"]["elbow_pitch_command"]["provenance"]["operator"] = "mallory"  # valid, but not what was kept
    kept.write_text(json.dumps(d))
    with pytest.raises(CalibrationError) as exc:
        files.load_calibration(p, rack)
    msg = str(exc.value)
    assert msg.startswith(f"calibration {p}: previous_hash: broken hash chain: the file (version 2) names "
                          f"previous_hash {want}, which matches no version kept in {p}.history;"), msg
    # what happened is still on show (pfma calibrate history)
    assert [c.version for c in files.history(p)] == [0, 1, 2]


def test_an_altered_older_version_is_named_by_the_version_that_points_at_it(tmp_path, rack):
    p = _three_versions(tmp_path, rack)
    kept = tmp_path / "cal.json.history" / "cal.v0000.json"
    d = json.loads(kept.read_text())
    d["comment"] = "edited"
    kept.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match=r"broken hash chain: kept version 1 \(.*cal\.v0001\.json\) "
                                               r"names previous_hash [0-9a-f]{16}, which matches no version"):
        files.load_calibration(p, rack)


def test_a_lost_history_or_an_edited_hash_breaks_the_chain(tmp_path, rack):
    p = _three_versions(tmp_path, rack)
    d = json.loads(p.read_text())
    d["previous_hash"] = "0" * 16
    p.with_name("edited.json").write_text(json.dumps(d))
    shutil.copytree(p.with_name("cal.json.history"), p.with_name("edited.json.history"))
    for name in ("cal.v0000.json", "cal.v0001.json"):  # the kept files carry the copy's stem
        p.with_name("edited.json.history").joinpath(name).rename(
            p.with_name("edited.json.history") / name.replace("cal.", "edited."))
    with pytest.raises(CalibrationError, match=f"names previous_hash {'0' * 16}, which matches no version"):
        files.load_calibration(p.with_name("edited.json"), rack)
    shutil.rmtree(p.with_name("cal.json.history"))
    with pytest.raises(CalibrationError, match=r"matches no version kept in .*cal\.json\.history \(no such directory\)"):
        files.load_calibration(p, rack)


def test_the_service_refuses_a_broken_chain_and_keeps_the_calibration_in_force(tmp_path, rack):
    from sim.rig import SimRig
    p = _three_versions(tmp_path, rack)
    good = files.load_calibration(p, rack)
    r = SimRig(prefix="pfma-chain-", service_kw={"calibration": p})
    try:
        assert r.svc.calibration.hash() == good.hash()
        shutil.rmtree(p.with_name("cal.json.history"))
        with pytest.raises(CalibrationError, match="broken hash chain"):
            r.svc.reload_calibration(p)
        assert r.svc.calibration.hash() == good.hash()
    finally:
        r.close()
