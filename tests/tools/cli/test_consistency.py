"""One face for every verb (issue 17 item 4): ``--json`` on every verb that reads prints
JSON a parser reads (one document, or JSON lines for a stream), the flag aliases work,
``monitor --once`` with no service fails at once, and the monitor fits 80x24.

Verbs run in-process through :func:`tools.cli.main` against the simulated-time rig
(``sim.rig``) or the fake bus; nothing waits on a wall clock.
"""

from __future__ import annotations

import io
import json
import math
import uuid
from dataclasses import dataclass

import pytest

from pfma.show import wrap_angle
from tools.cli import build_parser, main

OFFSET_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A running simulated-time service, a 0.3 s recording of it, a scope capture and a
    calibration file with two versions."""
    from sim.rig import SimRig
    from tools.recording.writer import Recorder
    from tools.scope import Capture, save

    d = tmp_path_factory.mktemp("consistency")
    rig = SimRig(name="pfma-cons-" + uuid.uuid4().hex[:8])
    rec = Recorder(rig.reader, d / "rec.mcap", rack=rig.world.rack_config, epoch_offset_ns=OFFSET_NS)
    hook = lambda info: rec.poll()  # noqa: E731
    rig.on_frame.append(hook)
    rig.run(0.3)
    rig.on_frame.remove(hook)
    rec.close()
    rig.svc.publish_stats()
    cap = Capture(["adc_spare_25"], ["V"], t_s=[0.0, 0.003125, 0.00625], frames=[1, 2, 3],
                  values=[[0.0], [2.5], [float("nan")]], trigger="adc_spare_25>1.0", trigger_t_s=0.003125,
                  trigger_frame=2, pre_s=0.003, post_s=0.003)
    save(cap, d / "cap.mcap", epoch_offset_ns=OFFSET_NS)
    cal = d / "cal.json"
    assert main(["calibrate", "init", "--file", str(cal)]) == 0
    assert main(["calibrate", "current-offsets", "--file", str(cal), "--non-interactive"]) == 0
    yield {"rig": rig, "buffer": rig.name, "rec": d / "rec.mcap", "cap": d / "cap.mcap", "cal": cal}
    rig.close()


@dataclass
class Verb:
    id: str
    argv: tuple[str, ...]
    lines: bool = False   # a stream: JSON lines
    check: str = ""       # a key the document (or every line) has


def _fill(argv, w) -> list[str]:
    return [a.format(**{k: str(v) for k, v in w.items() if k != "rig"}) for a in argv]


#: every verb that reads, with --json
VERBS = [
    Verb("channels", ("channels", "--json")),
    Verb("stats", ("stats", "--buffer", "{buffer}", "--json"), check="service_state"),
    Verb("read-buffer", ("read", "elbow_pitch_angle", "--buffer", "{buffer}", "--json")),
    Verb("read-bus", ("read", "elbow_pitch_angle", "--bus", "fake", "--json")),
    Verb("reg-read", ("reg", "read", "0x0100", "--json"), check="value"),
    Verb("reg-dump", ("reg", "dump", "rtd1", "--json"), check="registers"),
    Verb("watch", ("watch", "elbow_pitch_angle", "ft_force_n", "--buffer", "{buffer}", "--count", "3",
                   "--rate", "1000", "--json"), lines=True, check="values"),
    Verb("monitor", ("monitor", "--once", "--buffer", "{buffer}", "--json"), check="channels"),
    Verb("record-info", ("record", "info", "{rec}", "--json"), check="topics"),
    Verb("scope-open", ("scope", "--open", "{cap}", "--json"), check="values"),
    Verb("calibrate-show", ("calibrate", "show", "--file", "{cal}", "--json"), check="calibration"),
    Verb("calibrate-history", ("calibrate", "history", "--file", "{cal}", "--json")),
    Verb("calibrate-diff", ("calibrate", "diff", "--file", "{cal}", "--json"), check="changes"),
    Verb("checkout", ("checkout", "--non-interactive", "--only", "adc", "--json"), check="results"),
    Verb("ft", ("ft", "--port", "fake", "--count", "2", "--interval", "0.01", "--json"), lines=True,
         check="type"),
    Verb("hand", ("hand", "--source", "hid", "--bus", "fake", "--count", "2", "--rate-hz", "100", "--json"),
         lines=True),
]
# `pfma wm list/get/requests --json` need a running controller: tests/controller/test_wm_cli.py


@pytest.mark.parametrize("verb", VERBS, ids=[v.id for v in VERBS])
def test_json_output_parses(verb: Verb, world, capsys):
    world["rig"].run(0.05)
    world["rig"].svc.publish_stats()
    code = main(_fill(verb.argv, world))
    out = capsys.readouterr().out
    assert code == 0, out
    if verb.lines:
        docs = [json.loads(line) for line in out.splitlines()]
        assert len(docs) >= 2
    else:
        docs = [json.loads(out)]  # exactly one document: a second one would not parse
    for d in docs:
        if verb.check:
            assert verb.check in d, d


def test_json_documents_carry_the_values(world, capsys):
    """Not only parseable: the monitor's JSON agrees with the buffer, NaN is null."""
    rig = world["rig"]
    assert main(["monitor", "--once", "--buffer", world["buffer"], "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    row = next(r for r in d["channels"] if r["name"] == "elbow_pitch_angle")
    # the resolver's 0..2 pi is shown in (-pi, pi] (pfma/show.py); the status by name beside its bits
    assert row["value"] == pytest.approx(wrap_angle(rig.reader.read_inputs().value("elbow_pitch_angle")))
    assert -math.pi < row["value"] <= math.pi and row["status"] == "ok" and row["status_bits"] == 0
    assert row["units"] == "rad" and d["state"] == "SAFE" and d["fault_code"] == 0 and d["fault_name"] == "none"
    assert main(["scope", "--open", str(world["cap"]), "--json"]) == 0
    cap = json.loads(capsys.readouterr().out)
    assert cap["values"]["adc_spare_25"] == [0.0, 2.5, None] and cap["trigger_frame"] == 2


def test_json_with_a_verb_that_does_not_read_is_a_usage_error(world, capsys):
    assert main(["monitor", "--buffer", world["buffer"], "--json"]) == 2  # --json needs --once
    assert main(["scope", "adc_spare_25", "--json"]) == 2                 # --json needs --open
    assert main(["calibrate", "init", "--file", str(world["cal"]), "--json"]) == 2
    err = capsys.readouterr().err
    assert err.count("--json") == 3 and "Traceback" not in err


def test_hand_port_is_a_deprecated_alias_of_bus(capsys):
    assert main(["hand", "--source", "hid", "--port", "fake", "--count", "1", "--json"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out.splitlines()[0])
    assert cap.err.count("--port is deprecated; use --bus") == 1
    assert main(["hand", "--source", "hid", "--bus", "fake", "--count", "1", "--json"]) == 0
    assert "deprecated" not in capsys.readouterr().err
    assert main(["hand", "--source", "hid", "--bus", "fake", "--port", "/dev/hidraw9", "--count", "1"]) == 2
    assert "disagree" in capsys.readouterr().err


@pytest.mark.parametrize("argv, dest", [
    (["controller", "--wm", "seg1"], "wm"), (["controller", "--name", "seg1"], "wm"),
    (["wm", "list", "--wm", "seg1"], "name"), (["wm", "list", "--name", "seg1"], "name"),
    (["wm", "get", "x", "--wm", "seg1"], "name"), (["wm", "requests", "--name", "seg1"], "name"),
])
def test_world_model_segment_is_wm_or_name_on_both_verbs(argv, dest):
    assert getattr(build_parser().parse_args(argv), dest) == "seg1"


def test_wm_alias_reaches_the_segment(capsys):
    missing = "pfma-nowm-" + uuid.uuid4().hex[:6]
    assert main(["wm", "list", "--wm", missing]) == 1
    a = capsys.readouterr().err
    assert main(["wm", "list", "--name", missing]) == 1
    assert capsys.readouterr().err == a and missing in a


def _options(verb_argv: list[str]) -> set[str]:
    """Every option string of a verb's (sub)parser."""
    p = build_parser()
    for word in verb_argv:
        sub = next(a for a in p._actions if a.__class__.__name__ == "_SubParsersAction")
        p = sub.choices[word]  # type: ignore[attr-defined]
    return {o for a in p._actions for o in a.option_strings}


@pytest.mark.parametrize("verb", [["monitor"], ["watch"], ["stats"], ["read"], ["record"], ["scope"],
                                  ["replay"], ["calibrate"], ["checkout"], ["controller"]])
def test_buffer_is_spelled_buffer(verb):
    opts = _options(verb)
    assert "--buffer" in opts and not {"--buf", "--shm", "--segment"} & opts


@pytest.mark.parametrize("verb", [["channels"], ["monitor"], ["watch"], ["read"], ["record"], ["scope"],
                                  ["replay"], ["calibrate"], ["checkout"], ["hand"], ["reg", "read"],
                                  ["reg", "dump"]])
def test_rack_is_spelled_rack(verb):
    assert "--rack" in _options(verb)


@pytest.mark.parametrize("verb", [["reg", "read"], ["reg", "write"], ["reg", "dump"], ["read"], ["hand"]])
def test_register_bus_is_spelled_bus(verb):
    assert "--bus" in _options(verb)


def test_monitor_once_without_a_service_fails_at_once(monkeypatch, capsys):
    """Exit 1 with one line, and no wait: nothing sleeps and no link to the service is made
    (the 30 s reattach wait lives in that link)."""
    import time

    import tools.attach as attach
    sleeps = []
    monkeypatch.setattr(time, "sleep", lambda dt: sleeps.append(dt))
    links = []
    real = attach.ServiceLink
    monkeypatch.setattr(attach, "ServiceLink", lambda *a, **k: links.append(a) or real(*a, **k))
    name = "pfma-nobody-" + uuid.uuid4().hex[:6]
    for argv in (["monitor", "--once", "--buffer", name], ["monitor", "--once", "--json", "--buffer", name],
                 ["stats", "--buffer", name]):
        assert main(argv) == 1
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and name in err[0] and "Traceback" not in err[0]
    assert sleeps == [] and links == []


def test_monitor_once_rows_fit_80_columns(world, capsys):
    assert main(["monitor", "--once", "--buffer", world["buffer"]]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) > 80 and max(len(line) for line in lines) <= 80


def test_monitor_screen_fits_80x24_keeps_its_header_and_pages_through_every_row(world):
    from bit3.client import Client
    from tools.checkout.view import monitor_data, monitor_screen
    c = Client.attach(world["buffer"])
    try:
        d = monitor_data(c)
    finally:
        c.close()
    first, pages = monitor_screen(d, 0, height=24, width=80)
    assert pages >= 4  # 79 rows do not fit one screen
    seen = []
    for page in range(pages):
        lines, _ = monitor_screen(d, page, height=24, width=80)
        assert len(lines) <= 24 and max(map(len, lines)) <= 80
        assert lines[0].startswith("pfma monitor") and lines[0] == first[0]  # the header stays
        assert f"page {page + 1}/{pages}" in lines[-1]
        seen += [ln.split()[0] for ln in lines if ln.split() and ln.split()[0] in
                 {r["name"] for r in d["channels"]}]
    assert sorted(seen) == sorted(r["name"] for r in d["channels"])  # every row, once
    assert monitor_screen(d, pages, height=24)[0] == first  # the page number wraps


def test_every_verb_that_reads_has_json():
    """The table above is complete: a verb that reads and has no --json is found here."""
    reading = [["channels"], ["stats"], ["read"], ["reg", "read"], ["reg", "dump"], ["watch"], ["monitor"],
               ["record"], ["scope"], ["calibrate"], ["ft"], ["hand"], ["layout"], ["wm", "list"],
               ["wm", "get"], ["wm", "requests"], ["path", "show"]]
    missing = [" ".join(v) for v in reading if "--json" not in _options(v)]
    assert not missing, missing



class _Terminal(io.StringIO):
    """A captured stream that says it is a terminal (rich then draws bars and colours)."""

    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("terminal", [False, True])
def test_calibration_progress_is_a_bar_on_a_terminal_and_plain_lines_on_a_pipe(tmp_path, terminal):
    from tools.cli import calibrate
    args = build_parser().parse_args(["calibrate", "current-offsets", "--file", str(tmp_path / "c.json"),
                                      "--non-interactive"])
    out = _Terminal() if terminal else io.StringIO()
    assert calibrate.run(args, out=out) == 0
    text = out.getvalue()
    assert "PASSED" in text and "saved" in text  # the procedure's own lines either way
    if terminal:
        assert "\u2501" in text and "[####" not in text  # rich's bar, not the plain one
    else:
        assert "[####################] " in text and "\x1b[" not in text  # plain and uncoloured


def test_tables_on_a_pipe_are_plain_one_row_per_line(capsys):
    assert main(["channels"]) == 0
    lines = capsys.readouterr().out.splitlines()
    from pfma.rack import load_rack
    chans = load_rack("fake").channels()
    assert len(lines) == 1 + len(chans)  # a header and one line per channel: nothing wraps
    assert lines[0].split()[:4] == ["device", "addr", "ch", "signal"]
    assert all(line == line.rstrip() and "\x1b[" not in line for line in lines)
    for line, c in zip(lines[1:], chans):
        assert line.split()[3] == c.signal


@pytest.mark.parametrize("argv, typo, meant, code", [
    (("read", "--bus", "fake", "elbow_pitch_angel"), "elbow_pitch_angel", "elbow_pitch_angle", 1),
    (("watch", "elbow_pitch_angel", "--buffer", "{buffer}", "--count", "1"), "elbow_pitch_angel",
     "elbow_pitch_angle", 1),
    (("scope", "wrist_roll_rat"), "wrist_roll_rat", "wrist_roll_rate", 1),
    (("calibrate", "adc", "--signals", "cae_up_dwn", "--file", "{tmp}/c.json"), "cae_up_dwn", "cae_up_down", 1),
    (("calibrate", "tach", "--joints", "elbow_pich", "--file", "{tmp}/c.json"), "elbow_pich", "elbow_pitch", 1),
    (("reg", "dump", "rtd3"), "rtd3", "rtd1", 2),
])
def test_every_name_a_user_types_gets_did_you_mean(argv, typo, meant, code, world, tmp_path, capsys):
    w = dict(world, tmp=tmp_path)
    assert main(_fill(argv, w)) == code
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert typo in lines[0] and "did you mean" in lines[0] and meant in lines[0]
    assert not (tmp_path / "c.json").exists()  # refused before anything was written
