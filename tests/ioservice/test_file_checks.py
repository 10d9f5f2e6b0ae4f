"""The service's side of the file checks (issue 28 item 7): the rack file's ``rate_hz`` is
what the schedule runs, and every ``[checks] allow_nonnominal`` override is named in the
start-up messages."""

from __future__ import annotations

import uuid

import pytest

from bit3.buffer import Bit3Buffer
from calibration import files
from ioservice.schedule import Schedule
from ioservice.service import NONNOMINAL_CODE
from pfma.rack import DEFAULT_RACK, SCHEDULED_RATES_HZ, load_rack, parse_rack
from sim.rig import SimRig
from tools.cli import main

#: the schedule's tasks that serve each device's boards
TASKS_OF = {"dac": ("dac",), "rtd": ("rtd",), "adc": ("adc",), "serial": ("ft", "hand"), "pio": ("pio",)}


def test_the_rack_files_rates_are_the_rates_the_default_schedule_runs():
    s = Schedule()
    assert set(SCHEDULED_RATES_HZ) == set(TASKS_OF)
    for device, tasks in TASKS_OF.items():
        assert [s.rate_hz(t) for t in tasks] == [SCHEDULED_RATES_HZ[device]] * len(tasks), device
    # and so every board of the default rack file says what runs
    for b in load_rack().boards:
        assert all(s.rate_hz(t) == b.rate_hz for t in TASKS_OF[b.device]), b.name


def _override_rack():
    text = DEFAULT_RACK.read_text().replace(
        'signal = "shoulder_yaw_rate",            label = "Shoulder Yaw Rate",            units = "rad/s", scale = 0.04,',
        'signal = "shoulder_yaw_rate",            label = "Shoulder Yaw Rate",            units = "rad/s", scale = 0.1,', 1)
    text += '\n[checks]\nallow_nonnominal = ["shoulder_yaw_rate.scale", "wrist_roll_command.offset"]\n'
    return parse_rack(text, "lab.toml")


def test_every_override_is_named_at_start():
    rack = _override_rack()
    assert rack.channel("shoulder_yaw_rate").scale == 0.1
    r = SimRig(rack, prefix="pfma-override-")
    try:
        said = [m.text for m in r.reader.messages() if m.code == NONNOMINAL_CODE]
        assert len(said) == 2, said
        assert said[0].startswith("override: shoulder_yaw_rate.scale = 0.1 accepted outside the nominal band")
        assert said[1].startswith("override: [checks] allow_nonnominal lists wrist_roll_command.offset")
        assert "not needed" in r.svc.notes[-1] and "lab.toml" in r.svc.notes[-1]  # pfma serve prints the notes
    finally:
        r.close()


def test_the_default_rack_says_no_override():
    r = SimRig(prefix="pfma-override-")
    try:
        assert not [m for m in r.reader.messages() if m.code == NONNOMINAL_CODE]
    finally:
        r.close()


def test_a_calibration_accepted_by_an_override_is_named_when_it_is_loaded(tmp_path):
    rack = _override_rack()
    d = files.nominal_calibration(rack, "ann").data
    d["channels"]["wrist_roll_command"]["offset"] = 0.5  # 2.5 V at 0.2 rad/s per V
    p = tmp_path / "cal.json"
    files.save_calibration(files.validate(d, rack=rack), p, rack=rack)
    r = SimRig(rack, prefix="pfma-override-", service_kw={"calibration": p})
    try:
        said = [m.text for m in r.reader.messages() if m.code == NONNOMINAL_CODE]
        assert any(t.startswith(f"override: calibration {p}: wrist_roll_command.offset = 0.5 accepted") for t in said)
        assert not any("not needed" in t for t in said)  # both overrides are in use
    finally:
        r.close()


@pytest.mark.realtime
def test_pfma_serve_prints_every_override_and_the_pending_direction_check(tmp_path, capsys):
    rack_file = tmp_path / "lab.toml"
    rack_file.write_text(DEFAULT_RACK.read_text().replace("scale = 0.05, limit = 0.5", "scale = -0.05, limit = 0.5", 1)
                         + '\n[checks]\nallow_nonnominal = ["elbow_pitch_command.scale"]\n')
    state = tmp_path / "d.json"
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    try:
        assert main(["serve", "--rack", str(rack_file), "--bus", "fake", "--duration", "0.3", "--buffer", name,
                     "--direction-state", str(state)]) == 0
        err = capsys.readouterr().err.splitlines()
        assert any(ln.startswith(f"pfma serve: override: elbow_pitch_command.scale = -0.05 accepted outside the "
                                 f"nominal band by [checks] allow_nonnominal ({rack_file})") for ln in err), err
        assert any(ln.startswith("pfma serve: direction check required before normal arming") for ln in err), err
        assert not state.exists()  # nothing was confirmed
    finally:
        Bit3Buffer.unlink(name)
