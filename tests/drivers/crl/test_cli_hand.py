"""``pfma hand`` on the fakes (short real-time runs)."""

from __future__ import annotations

import json

import pytest

from tools.cli import main


@pytest.mark.realtime
def test_cae_on_the_fake_rack(capsys):
    assert main(["hand", "--source", "cae", "--count", "3", "--rate-hz", "50"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("# CAE on a fake rack")
    assert len(out) == 4 and all(" cae " in line and "VALID" in line for line in out[1:])


@pytest.mark.realtime
def test_crl_on_a_fake_master_behind_a_pty_json(capsys):
    assert main(["hand", "--source", "crl", "--count", "8", "--rate-hz", "20", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(rows) == 8 and {r["source"] for r in rows} == {"crl"}
    assert any(r["valid"] for r in rows)  # frames arrive well within 350 ms


@pytest.mark.realtime
def test_hid_falls_back_to_a_fake_and_says_so(capsys, monkeypatch):
    from drivers.crl.hid import HidSpaceMouse

    monkeypatch.setattr(HidSpaceMouse, "enumerate", lambda self: [])
    assert main(["hand", "--source", "hid", "--count", "2", "--rate-hz", "50"]) == 0
    cap = capsys.readouterr()
    assert "using a FAKE device" in cap.err
    assert "FAKE" in cap.out.splitlines()[0] and len(cap.out.splitlines()) == 3


@pytest.mark.realtime
def test_hid_fake_port_and_duration(capsys):
    assert main(["hand", "--source", "hid", "--port", "fake", "--duration", "0.05"]) == 0
    assert " hid " in capsys.readouterr().out


def test_bad_source_is_a_usage_error():
    with pytest.raises(SystemExit):
        main(["hand", "--source", "joystick"])


@pytest.mark.realtime
def test_hand_times_are_seconds_since_the_command_started(capsys):
    """t= (and the JSON t_s) count from the start of the command, not the host's uptime."""
    import json

    from tools.cli import main
    assert main(["hand", "--source", "cae", "--count", "3", "--rate-hz", "50", "--json"]) == 0
    ts = [json.loads(line)["t_s"] for line in capsys.readouterr().out.splitlines()]
    assert len(ts) == 3
    assert 0.0 <= ts[0] < 1.0 and ts == sorted(ts)
