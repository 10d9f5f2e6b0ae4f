"""``pfma bench soak --check`` / ``pfma bench flood --check``: the judgement of a report
(issue 20's criteria, ``judge`` in bench/bench_soak.py and bench/bench_flood.py) on
hand-made reports: a good one passes, each criterion broken alone fails alone, naming
itself and its figure; the CLI prints those lines and exits 1 (0 and one passed line)."""

from __future__ import annotations

import copy

import pytest

from bench import bench_flood, bench_soak
from tools.cli import main


def soak_report() -> dict:
    """A soak that met every criterion (figures of the shape ``bench_soak.measure`` returns)."""
    rss = {role: {"first": 50.0, "at_1min": 55.0, "last": 56.0, "max": 56.0, "growth_after_1min": 1.0,
                  "samples": 60, "slope_second_half_mb_per_h": 0.5} for role in bench_soak.ROLES}
    rss["controller"]["growth_after_1min"] = 4.99
    return {"minutes": 10, "buffer": "pfma-soak-000000", "realtime": True, "errors": [], "died": {},
            "run_s": 600.0, "rss_mb": rss,
            "trips": [{"at_s": 239.0, "text": "outputs safe: stale heartbeat 15.3>15 ms",
                       "explained": "controller late (its missed-frame events went up)"}],
            "unexplained_trips": 0, "operator": {"laps": 116, "recoveries": 1, "errors": []},
            "recorder": {"frames_recorded": "192761", "recorder_missed": "0", "window_service_frames": "192617",
                         "window_recorded": "192617", "messages_missed": "0", "lossless": "True"},
            "left_behind": [], "zenoh_files_removed": []}


def _break_rss(r):
    r["rss_mb"]["recorder"]["growth_after_1min"] = 9.3


def _break_rss_unmeasured(r):
    r["rss_mb"]["console"]["growth_after_1min"] = None


def _break_process_missing(r):
    del r["rss_mb"]["bridge_reader"]


def _break_trip(r):
    r["trips"].append({"at_s": 300.5, "text": "outputs safe: ADC timeout", "explained": None})
    r["unexplained_trips"] = 1


def _break_lossless(r):
    r["recorder"].update(messages_missed="73", lossless="False")


def _break_no_recording(r):
    r["recorder"] = {"error": "no recording"}


def _break_laps(r):
    r["operator"]["laps"] = 0


def _break_died(r):
    r["died"]["recorder"] = "exited after 312 s (exit 1): pfma record: disk full"


def _break_error(r):
    r["errors"].append("console needed SIGKILL")


def _break_left(r):
    r["left_behind"].append("/dev/shm/pfma-soak-000000.ring")


@pytest.mark.parametrize("brk, words", [
    (_break_rss, ["RSS growth after the first minute <= 5 MB", "recorder +9.30 MB"]),
    (_break_rss_unmeasured, ["measured in every process", "console"]),
    (_break_process_missing, ["measured in every process", "bridge_reader"]),
    (_break_trip, ["no unexplained trip", "1 of 2", "ADC timeout"]),
    (_break_lossless, ["the recording lossless", "messages_missed 73"]),
    (_break_no_recording, ["the recording lossless", "no recording"]),
    (_break_laps, ["laps > 0", "0 laps"]),
    (_break_died, ["every process alive to the end", "recorder died", "exited after 312 s"]),
    (_break_error, ["without a problem", "console needed SIGKILL"]),
    (_break_left, ["nothing left behind", "/dev/shm/pfma-soak-000000.ring"]),
])
def test_each_soak_criterion_fails_alone_naming_itself_and_its_figure(brk, words):
    good = soak_report()
    assert bench_soak.judge(good) == []
    bad = copy.deepcopy(good)
    brk(bad)
    lines = bench_soak.judge(bad)
    assert len(lines) == 1, lines
    assert lines[0].startswith("soak: FAILED ")
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_soak_failures_are_one_line_each():
    r = soak_report()
    for brk in (_break_rss, _break_trip, _break_lossless, _break_laps, _break_died):
        brk(r)
    lines = bench_soak.judge(r)
    assert len(lines) == 5 and all("\n" not in line for line in lines)


def test_soak_lossless_read_from_json_too():
    r = soak_report()
    r["recorder"]["lossless"] = True  # a report read back from --json
    assert bench_soak.judge(r) == []


def test_soak_passed_line_names_the_figures():
    line = bench_soak.passed_line(soak_report())
    assert line.startswith("soak: passed (600 s --realtime")
    for w in ("<= 5 MB in all 6 processes", "controller +4.99 MB", "0 unexplained trips of 1", "192761 frames",
              "116 laps"):
        assert w in line, w


def flood_report() -> dict:
    """A flood that met its goal (figures of the shape ``bench_flood.figures`` returns)."""
    def run(dropped, flood):
        r = {"window_s": 10.0, "frames": 3200, "overruns": 0, "dropped_frames": dropped,
             "dropped_per_10s": float(dropped)}
        if flood:
            r.update(flood_rate=2000.0, connections=4, answered_per_s=1900.0, refused=0, failed=0)
        return r
    return {"seconds": 10.0, "rounds": 2, "realtime": True, "quiet": [run(1, False), run(2, False)],
            "flooded": [run(4, True), run(5, True)], "quiet_dropped_per_10s": 1.5,
            "flooded_dropped_per_10s": 4.5, "extra_dropped_per_10s": 3.0}


def _flood_dropped(r):
    r["flooded_dropped_per_10s"], r["extra_dropped_per_10s"] = 7.0, 5.5


def _flood_slow(r):
    r["flooded"][1]["answered_per_s"] = 900.0


def _flood_refused(r):
    r["flooded"][0]["refused"] = 3


def _flood_failed(r):
    r["flooded"][1]["failed"] = 1


def _flood_error(r):
    r.clear()
    r["error"] = "flooded run: the Modbus export on 127.0.0.1:5020 did not answer"


@pytest.mark.parametrize("brk, words", [
    (_flood_dropped, ["at most 5 extra dropped frames per 10 s", "+5.5", "quiet 1.5, flooded 7"]),
    (_flood_slow, ["the export answering", "run 2: 900 of 2000 requests/s"]),
    (_flood_refused, ["the export answering", "run 1", "3 refused"]),
    (_flood_failed, ["the export answering", "run 2", "1 timed out or cut"]),
    (_flood_error, ["the runs ran", "did not answer"]),
])
def test_each_flood_criterion_fails_alone_naming_itself_and_its_figure(brk, words):
    good = flood_report()
    assert bench_flood.judge(good) == []
    assert bench_flood.passed_line(good).startswith("flood: passed (2 round(s) of 10 s, --realtime: +3 dropped")
    bad = copy.deepcopy(good)
    brk(bad)
    lines = bench_flood.judge(bad)
    assert len(lines) == 1 and lines[0].startswith("flood: FAILED "), lines
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_flood_at_the_goal_passes():
    r = flood_report()
    r["extra_dropped_per_10s"] = 5.0
    assert bench_flood.judge(r) == []


@pytest.mark.parametrize("brk, rc", [(None, 0), (_break_lossless, 1)])
def test_soak_check_prints_the_verdict_and_exits_by_it(brk, rc, monkeypatch, capsys):
    rep = soak_report()
    if brk:
        brk(rep)
    seen = {}

    def fake_run(**kw):
        seen.update(kw)
        return rep
    monkeypatch.setattr(bench_soak, "run", fake_run)
    assert main(["bench", "soak", "--minutes", "10", "--check", "--realtime"]) == rc
    assert seen == {"minutes": 10.0, "as_json": False, "realtime": True}
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1].startswith("soak: passed (" if rc == 0 else "soak: FAILED the recording lossless")


def test_soak_check_with_json_keeps_stdout_json(monkeypatch, capsys):
    rep = soak_report()
    _break_laps(rep)
    monkeypatch.setattr(bench_soak, "run", lambda **kw: rep)
    assert main(["bench", "soak", "--json", "--check"]) == 1
    cap = capsys.readouterr()
    assert "FAILED" not in cap.out and cap.err.startswith("soak: FAILED the stack ran (path laps > 0)")


@pytest.mark.parametrize("brk, rc", [(None, 0), (_flood_dropped, 1)])
def test_flood_check_prints_the_verdict_and_exits_by_it(brk, rc, monkeypatch, capsys):
    rep = flood_report()
    if brk:
        brk(rep)
    seen = {}

    def fake_run(**kw):
        seen.update(kw)
        return rep
    monkeypatch.setattr(bench_flood, "run", fake_run)
    assert main(["bench", "flood", "--rounds", "2", "--check"]) == rc
    assert seen == {"seconds": bench_flood.DEFAULT_SECONDS, "rounds": 2, "realtime": False}
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1].startswith("flood: passed (" if rc == 0 else "flood: FAILED at most 5 extra")
