"""``pfma wm`` against a world model created in the test (unique shm names, removed after)."""

import json
import threading
import time

import numpy as np
import pytest

from controller.worldmodel import DEFAULT_ACCESS_KEY, WorldModel
from tools.cli import main
from tests.controller import _wm_support as sup


@pytest.fixture
def wm(monkeypatch):
    monkeypatch.delenv("PFMA_WM_KEY", raising=False)
    monkeypatch.delenv("PFMA_WM", raising=False)
    name = sup.unique_name()
    m = WorldModel.create(sup.sample_specs(), name=name, owner="test-controller")
    m.post_task_outputs("servo", {"servo.q_rad": [0.25] * 6, "servo.error_code": -7})
    m.communications_segment()
    yield m
    m.close()
    WorldModel.remove_segment(name)


def pfma(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_list_shows_every_variable_readably(wm, capsys):
    rc, out, err = pfma(capsys, "wm", "list", "--name", wm.name)
    assert rc == 0 and err == ""
    lines = out.splitlines()
    assert lines[0].startswith(f"world model '{wm.name}': owner test-controller")
    assert "frame 1" in lines[0] and "powered up: no" in lines[0] and "10 variables" in lines[0]
    assert lines[1].split() == ["NAME", "AREA", "TYPE", "UNITS", "WRITER", "USER", "VALUE", "DOC"]
    row = next(ln for ln in lines if ln.startswith("servo.kp_1_s "))
    for part in ("control_flags", "f8[6]", "1/s", " user ", " powered_down ", "[10, 10, 10, 10, 10, 10]",
                 "position-loop gains"):
        assert part in row, part
    # who may set what, for every variable: from the area and the writer unless declared
    user_col = {ln.split()[0]: ln.split()[5] for ln in lines[2:-1]}
    assert user_col == {"servo.q_cmd_rad": "never", "servo.q_rad": "never", "tool.T_base": "never",
                        "servo.integrator": "never", "updown.command": "always", "updown.status": "never",
                        "servo.kp_1_s": "powered_down", "hc.enable": "always", "servo.frames": "never",
                        "servo.error_code": "never"}
    assert lines[-1].startswith("USER = when `pfma wm set` may change it")
    row = next(ln for ln in lines if ln.startswith("servo.q_rad "))
    assert "[0.25, 0.25, 0.25, 0.25, 0.25, 0.25]" in row and "rad" in row
    assert "tool.T_base" in out and "f4[4,4]" in out and "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1..." in out
    assert len([ln for ln in lines if ln.split() and ln.split()[0] in wm.names()]) == 10


def test_list_filters_by_area_and_text(wm, capsys):
    rc, out, _ = pfma(capsys, "wm", "list", "--area", "control_flags", "--name", wm.name)
    names = [ln.split()[0] for ln in out.splitlines()[2:-1]]
    assert rc == 0 and names == ["servo.kp_1_s", "hc.enable"]
    rc, out, _ = pfma(capsys, "wm", "list", "--filter", "LAYER", "--name", wm.name)  # doc text, any case
    names = [ln.split()[0] for ln in out.splitlines()[2:-1]]
    assert names == ["servo.q_cmd_rad", "updown.command", "updown.status"]
    rc, out, _ = pfma(capsys, "wm", "list", "--filter", "updown.*", "--name", wm.name)  # glob
    assert [ln.split()[0] for ln in out.splitlines()[2:-1]] == ["updown.command", "updown.status"]
    rc, out, _ = pfma(capsys, "wm", "list", "--filter", "zzz", "--name", wm.name)
    assert rc == 0 and "no variables match filter 'zzz'" in out


def test_list_json(wm, capsys):
    rc, out, _ = pfma(capsys, "wm", "list", "--json", "--name", wm.name)
    d = json.loads(out)
    assert rc == 0 and d["frame"] == 1 and d["owner"] == "test-controller"
    v = {x["name"]: x for x in d["variables"]}
    assert v["servo.error_code"]["value"] == -7 and v["servo.error_code"]["area"] == "error_reports"
    assert v["servo.kp_1_s"]["protected"] is True and v["servo.kp_1_s"]["shape"] == [6]
    assert v["servo.kp_1_s"]["user"] == "powered_down" and v["servo.q_cmd_rad"]["user"] == "never"
    assert v["hc.enable"]["user"] == "always"
    assert v["tool.T_base"]["value"][2][2] == 1.0


def test_get_prints_each_variable_in_full(wm, capsys):
    rc, out, err = pfma(capsys, "wm", "get", "servo.q_rad", "updown.status", "--name", wm.name)
    assert rc == 0 and err == ""
    assert "(values from one consistent copy)" in out.splitlines()[0]
    block = out.split("\nservo.q_rad\n")[1].split("\n\n")[0]
    assert "area       task_io" in block and "type       f8[6]" in block
    assert "units      rad" in block and "writer     servo" in block
    assert "user set   never (posted by servo)" in block and "value      [0.25, 0.25, 0.25, 0.25, 0.25, 0.25]" in block
    assert "doc        measured joint angles" in block
    assert "type       i2 (scalar)" in out and "units      -" in out
    rc, out, _ = pfma(capsys, "wm", "get", "servo.q_rad", "hc.enable", "--json", "--name", wm.name)
    d = json.loads(out)
    assert d["variables"]["servo.q_rad"]["value"] == [0.25] * 6
    assert d["variables"]["hc.enable"]["value"] is False and d["frame"] == 1


def test_get_unknown_variable_and_missing_model(wm, capsys):
    rc, out, err = pfma(capsys, "wm", "get", "servo.q_rda", "--name", wm.name)
    assert rc == 1 and out == ""
    assert "pfma wm: no variable 'servo.q_rda'" in err and "did you mean servo.q_rad" in err
    rc, _, err = pfma(capsys, "wm", "list", "--name", wm.name + "_nothere")
    assert rc == 1 and "no world model" in err and "is the controller running?" in err


def test_set_queues_a_request_the_owner_applies_at_its_next_segment(wm, capsys):
    rc, out, err = pfma(capsys, "wm", "set", "servo.kp_1_s", "[5, 5, 5, 5, 5, 6.5]",
                        "--key", DEFAULT_ACCESS_KEY, "--wait", "0", "--name", wm.name)
    assert rc == 0 and err == "" and "request #1 queued" in out
    assert wm.get("servo.kp_1_s")[5] == 10.0  # not yet
    assert wm.communications_segment() == 1
    np.testing.assert_array_equal(wm.get("servo.kp_1_s"), [5, 5, 5, 5, 5, 6.5])
    rc, out, _ = pfma(capsys, "wm", "requests", "--name", wm.name)
    row = out.splitlines()[-1].split()
    assert rc == 0 and row[:3] == ["1", "applied", "servo.kp_1_s"] and "applied at frame 2" in out
    # comma-separated numbers are accepted too
    rc, out, _ = pfma(capsys, "wm", "set", "servo.kp_1_s", "0.1,0.2,0.3,0.4,0.5,0.6",
                      "--key", DEFAULT_ACCESS_KEY, "--wait", "0", "--name", wm.name)
    assert rc == 0
    wm.communications_segment()
    assert wm.get("servo.kp_1_s")[2] == 0.3


def test_set_waits_for_the_owner_and_reports_the_new_value(wm, capsys):
    result = {}
    t = threading.Thread(target=lambda: result.update(rc=main(
        ["wm", "set", "updown.command", "2", "--key", DEFAULT_ACCESS_KEY, "--wait", "20",
         "--name", wm.name])))
    t.start()
    deadline = time.monotonic() + 20.0
    while not wm.user_requests_pending():  # wait for the request itself, not for time
        assert time.monotonic() < deadline, "the CLI never queued its request"
    wm.communications_segment()
    t.join(20.0)
    assert not t.is_alive() and result["rc"] == 0
    out = capsys.readouterr().out
    assert "updown.command = 2" in out and "applied at frame 2" in out


@pytest.mark.parametrize("args, text", [
    (["servo.kp", "1", "--key", DEFAULT_ACCESS_KEY], "no variable 'servo.kp'"),
    (["hc.enable", "true", "--key", "wrong"], "wrong or missing access key"),
    (["hc.enable", "true"], "needs the world model's access key (--key KEY or $PFMA_WM_KEY)"),
    (["servo.kp_1_s", "[1, 2]", "--key", DEFAULT_ACCESS_KEY], r"shape (2,) given, shape (6,) expected"),
    (["servo.kp_1_s", "1,2,3,4,5,nan", "--key", DEFAULT_ACCESS_KEY], "not finite"),
    (["updown.command", "abc", "--key", DEFAULT_ACCESS_KEY], "is not JSON"),
    (["updown.command", "1.5", "--key", DEFAULT_ACCESS_KEY], "float given for an integer"),
    (["servo.q_rad", "[1, 2, 3, 4, 5, 6]", "--key", DEFAULT_ACCESS_KEY],
     "servo.q_rad is an output of task servo; users may not set it"),
    (["servo.error_code", "12", "--key", DEFAULT_ACCESS_KEY],
     "servo.error_code is an error report posted by servo; users may not set it"),
])
def test_set_refusals_are_clear(wm, capsys, args, text):
    rc, out, err = pfma(capsys, "wm", "set", *args, "--wait", "0", "--name", wm.name)
    assert rc == 1 and out == "" and text in err and err.startswith("pfma wm: ")
    assert wm.user_requests_pending() == 0


def test_set_protected_while_powered_up_is_refused(wm, capsys):
    wm.powered_up = True
    rc, _, err = pfma(capsys, "wm", "set", "servo.kp_1_s", "[1,1,1,1,1,1]", "--key", DEFAULT_ACCESS_KEY,
                      "--wait", "0", "--name", wm.name)
    assert rc == 1 and err == ("pfma wm: servo.kp_1_s is protected: it may be set only while powered "
                               "down (the system is powered up)\n")
    rc, out, _ = pfma(capsys, "wm", "list", "--name", wm.name)
    assert "powered up: yes" in out.splitlines()[0]


def test_set_takes_the_key_from_the_environment(wm, capsys, monkeypatch):
    monkeypatch.setenv("PFMA_WM_KEY", DEFAULT_ACCESS_KEY)
    rc, out, _ = pfma(capsys, "wm", "set", "hc.enable", "true", "--wait", "0", "--name", wm.name)
    assert rc == 0 and "queued" in out
    wm.communications_segment()
    assert wm.get("hc.enable")


def test_set_when_the_owner_has_gone(wm, capsys):
    wm.close()  # owner gone, segment still there
    rc, _, err = pfma(capsys, "wm", "set", "hc.enable", "true", "--key", DEFAULT_ACCESS_KEY,
                      "--wait", "0", "--name", wm.name)
    assert rc == 1 and "is not running; nobody would apply the write" in err
    rc, out, _ = pfma(capsys, "wm", "list", "--name", wm.name)
    assert rc == 0 and "(closed)" in out.splitlines()[0]


def test_wm_without_a_command_prints_help(capsys):
    rc, out, _ = pfma(capsys, "wm")
    assert rc == 2 and "list" in out and "requests" in out


@pytest.mark.parametrize("var, value, owner_text", [
    ("servo.q_cmd_rad", "[6, 0, 0, 0, 0, 0]", "servo.q_cmd_rad is an output of task trajectory"),
    ("updown.status", "5", "updown.status is a status posted by updown"),
    ("servo.frames", "1", "servo.frames is a response posted by servo"),
])
@pytest.mark.parametrize("key", [DEFAULT_ACCESS_KEY, "wrong", None])
def test_set_of_a_variable_a_task_posts_is_refused_in_one_line_with_or_without_the_key(
        wm, capsys, var, value, owner_text, key):
    for powered in (False, True):
        wm.powered_up = powered
        argv = ["wm", "set", var, value, "--wait", "0", "--name", wm.name] + (["--key", key] if key else [])
        rc, out, err = pfma(capsys, *argv)
        assert rc == 1 and out == ""
        assert err == f"pfma wm: {owner_text}; users may not set it\n"  # one line, no traceback
    assert wm.user_requests_pending() == 0
