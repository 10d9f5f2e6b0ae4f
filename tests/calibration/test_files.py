"""Calibration files: versions, history, hash, validation naming the field, consumers."""

import json

import numpy as np
import pytest

from calibration import files
from calibration.plot import Panel, Series, figure, plot_fit, read_png_size, residual_panel
from pfma.errors import CalibrationError
from pfma.ft_calibration import ft_calibration
from pfma.rack import load_rack


@pytest.fixture
def rack():
    return load_rack()


def test_save_keeps_history_and_versions(tmp_path, rack):
    p = tmp_path / "cal.json"
    v0 = files.save_calibration(files.nominal_calibration(rack, "ann"), p, rack=rack)
    assert v0.version == 0 and v0.data["previous_hash"] is None
    v1 = files.save_calibration(v0.updated(channels={"adc_spare_25": {"scale": 1.01, "offset": 0.002}}), p, rack=rack)
    assert v1.version == 1 and v1.data["previous_hash"] == v0.hash().hex()
    kept = tmp_path / "cal.json.history" / "cal.v0000.json"
    assert kept.exists() and files.load_calibration(kept).hash() == v0.hash()
    assert [c.version for c in files.history(p)] == [0, 1]
    assert files.load_calibration(p, rack).channel("adc_spare_25")["scale"] == 1.01
    rows = files.diff(v0, v1)
    assert {r["entry"] for r in rows} == {"channels.adc_spare_25.scale", "channels.adc_spare_25.offset"}
    assert not list(tmp_path.glob(".cal.json.tmp*"))  # atomic write left no temporary
    assert len(files.calibration_hash(v1)) == 8 and files.calibration_hash(v1) != files.calibration_hash(v0)


def _good(tmp_path, rack):
    p = tmp_path / "cal.json"
    files.save_calibration(files.nominal_calibration(rack, "ann"), p, rack=rack)
    return p, json.loads(p.read_text())


def test_truncated_file_is_refused_naming_the_problem(tmp_path, rack):
    p, _ = _good(tmp_path, rack)
    text = p.read_text()
    p.write_text(text[: len(text) // 2])
    with pytest.raises(CalibrationError, match=r"not valid JSON \(truncated or corrupt\?\).*previous calibration stays"):
        files.load_calibration(p, rack)
    p.write_text("")
    with pytest.raises(CalibrationError, match="empty file"):
        files.load_calibration(p, rack)


@pytest.mark.parametrize("mutate, field, what", [
    (lambda d: d["channels"]["shoulder_yaw_rate"].__setitem__("scale", "0.04"),
     "channels.shoulder_yaw_rate.scale", "expected a number, got string"),
    (lambda d: d["channels"]["elbow_pitch_angle"].__setitem__("offset", None),
     "channels.elbow_pitch_angle.offset", "expected a number, got null"),
    (lambda d: d["channels"]["adc_spare_25"].__setitem__("scale", 0),
     "channels.adc_spare_25.scale", "must not be 0"),
    (lambda d: d["channels"].pop("wrist_roll_command"),
     "channels.wrist_roll_command", "missing: the rack's dac channel 5 on board dac"),
    (lambda d: d["channels"].__setitem__("no_such", dict(d["channels"]["adc_spare_25"])),
     "channels.no_such", "not an analog channel"),
    (lambda d: d["channels"]["cae_yaw"]["provenance"].pop("operator"),
     "channels.cae_yaw.provenance.operator", "missing"),
    (lambda d: d.__setitem__("version", "3"), "version", "expected an integer"),
    (lambda d: d.pop("channels"), "channels", "missing (truncated or partial file?)"),
    (lambda d: d.__setitem__("rack", "other"), "rack", "calibration is for rack 'other'"),
    (lambda d: d.__setitem__("ft", {"bias_counts": [0] * 5}), "ft.matrix", "missing"),
    (lambda d: d.__setitem__("cae", {"x": {}}), "cae.x.centre_v", "missing"),
])
def test_bad_content_is_refused_naming_the_field(tmp_path, rack, mutate, field, what):
    p, data = _good(tmp_path, rack)
    mutate(data)
    p.write_text(json.dumps(data))
    with pytest.raises(CalibrationError) as e:
        files.load_calibration(p, rack)
    assert f"{field}: " in str(e.value) and what in str(e.value)


def test_consumers_apply_to_rack_cae_ft(tmp_path, rack):
    cal = files.nominal_calibration(rack)
    cal = cal.updated(channels={"shoulder_yaw_rate": {"scale": 0.041, "offset": 0.001},
                                "wrist_roll_angle": {"offset": -0.1}},
                      ft=files.nominal_ft(), rack=rack)
    r2 = files.apply_to_rack(rack, cal)
    assert r2.channel("shoulder_yaw_rate").scale == 0.041 and r2.channel("shoulder_yaw_rate").offset == 0.001
    assert r2.channel("wrist_roll_angle").offset == -0.1
    assert rack.channel("shoulder_yaw_rate").scale == 0.04  # the input is untouched
    assert files.cae_calibration(cal) is None
    ft = ft_calibration(cal)
    assert np.allclose(ft.wrench([16, 0, 0, 200, 0, 0]), [1, 0, 0, 1, 0, 0])


def test_png_plot_is_a_valid_png_with_titles_labels_units_and_legend(tmp_path):
    x = np.linspace(-1, 1, 9)
    panels = [Panel([Series(x, 2 * x, "points", "blue", "wrist_roll"), Series(x, 2 * x, "line", "red")],
                    "tach vs velocity", "velocity (rad/s)", "tach (V)"),
              residual_panel([Series(x, 0.01 * x, "points", "blue", "wrist_roll")], "fit", "V", "velocity (rad/s)")]
    p = plot_fit(tmp_path / "p.png", panels, title="Tachometer scale")
    assert read_png_size(p) == (640, 480)
    fig = figure(panels, "Tachometer scale")
    top, bottom = fig.axes
    assert fig.get_suptitle() == "Tachometer scale"
    assert (top.get_title(), top.get_xlabel(), top.get_ylabel()) == ("tach vs velocity", "velocity (rad/s)", "tach (V)")
    assert [t.get_text() for t in top.get_legend().get_texts()] == ["wrist_roll"]  # unlabelled fit line: no entry
    # the residual panel states its scale and units, and draws its zero line
    assert bottom.get_title() == "fit residuals (largest 0.01 V)"
    assert bottom.get_ylabel() == "residual (V)"
    assert any(list(line.get_ydata()) == [0.0, 0.0] for line in bottom.get_lines())
