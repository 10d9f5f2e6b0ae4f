"""The service with a calibration: applied at start, reloaded when not armed, a bad file
refused with the previous calibration kept in force; the CLI's file commands."""

import io
import json
import uuid

import pytest

from calibration import files
from bit3.buffer import Bit3Buffer
from tools.cli import build_parser
from pfma.errors import CalibrationError
from sim.calibration import CalibrationRig as Rig


def _cal(tmp_path, rack, scale=2.0):
    p = tmp_path / "cal.json"
    cal = files.nominal_calibration(rack, "test").updated(
        channels={"adc_spare_25": {"scale": scale, "offset": 0.5}}, rack=rack)
    return files.save_calibration(cal, p, rack=rack), p


def test_applied_at_start_and_bad_reload_keeps_previous(tmp_path):
    from pfma.rack import load_rack
    saved, p = _cal(tmp_path, load_rack())
    rig = Rig(name="pfma-caltest-" + uuid.uuid4().hex[:8], calibration=p)
    try:
        rig.world.sim.hold_adc_volts("adc_spare_25", 1.0)
        rig.run(0.05)
        s = rig.reader.read_inputs()
        assert s.value("adc_spare_25") == pytest.approx(2.5, abs=0.02)
        assert bytes(rig.reader.header().calibration_hash) == saved.hash()
        good = p.read_text()
        bad_cases = [good[:200], good.replace('"scale": 2.0', '"scale": "2.0"'),
                     json.dumps({k: v for k, v in json.loads(good).items() if k != "channels"})]
        data = json.loads(good)
        del data["channels"]["adc_spare_31"]
        bad_cases.append(json.dumps(data))
        for text in bad_cases:
            p.write_text(text)
            with pytest.raises(CalibrationError, match="previous calibration stays in force"):
                rig.svc.reload_calibration(p)
            rig.run(0.02)
            assert rig.reader.read_inputs().value("adc_spare_25") == pytest.approx(2.5, abs=0.02)
            assert bytes(rig.reader.header().calibration_hash) == saved.hash()
        new, p2 = _cal(tmp_path / "b", rig.world.rack_config, scale=3.0)
        rig.svc.reload_calibration(p2)
        rig.run(0.02)
        assert rig.reader.read_inputs().value("adc_spare_25") == pytest.approx(3.5, abs=0.02)
        assert bytes(rig.reader.header().calibration_hash) == new.hash()
        assert any("calibration v" in m.text for m in rig.reader.messages())
    finally:
        rig.close()


def test_service_refuses_a_bad_file_at_start(tmp_path):
    p = tmp_path / "cal.json"
    p.write_text('{"format": "pfma-calibration", "format_version": 1')
    name = "pfma-caltest-" + uuid.uuid4().hex[:8]
    try:
        with pytest.raises(CalibrationError, match="truncated"):
            Rig(name=name, calibration=p)
    finally:
        Bit3Buffer.unlink(name)  # the rig made the buffer before the service refused the file


def _cli(*argv) -> tuple[int, str]:
    args = build_parser().parse_args(["calibrate", *argv])
    out = io.StringIO()
    from tools.cli import calibrate
    return calibrate.run(args, out=out), out.getvalue()


def test_cli_init_procedure_show_history_diff(tmp_path):
    f = str(tmp_path / "c.json")
    assert _cli("init", "--file", f)[0] == 0
    rc, text = _cli("current-offsets", "--file", f, "--operator", "bob")
    assert rc == 0 and "PASSED" in text and "saved" in text and "simulated operator" in text
    rc, text = _cli("show", "--file", f)
    assert rc == 0 and "current offset, amplifiers disabled / " in text and "/ bob" in text
    rc, text = _cli("history", "--file", f)
    assert rc == 0 and text.count("\nv") + text.startswith("v") == 2
    rc, text = _cli("diff", "--file", f)
    assert rc == 0 and text.startswith("diff v0 -> v1")
    rc, text = _cli("diff", "--file", f, "--from", "0", "--to", "1")
    assert rc == 0 and text.startswith("diff v0 -> v1")
    with pytest.raises(CalibrationError, match="no version 7"):
        _cli("diff", "--file", f, "--from", "7")
