"""``pfma bench stack --minutes 0.05 --json``: the report's structure, and the three processes
were started and stopped (no timing is asserted: this is a benchmark)."""

import json
import subprocess
import sys

import pytest


@pytest.mark.realtime
@pytest.mark.parametrize("hog", [False, True])
def test_short_stack_bench_reports_and_stops_every_process(hog, capsys):
    out = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "stack", "--minutes", "0.05", "--json",
                          *(["--hog"] if hog else [])], capture_output=True, text=True, timeout=240)
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    rep = json.loads(out.stdout)
    names = ["hog"] * hog + ["service", "controller", "recorder"]
    assert rep["started"] == names and rep["hog"] == hog
    assert rep["held"] == (not rep["layers_in_error"] and not rep["errors"])
    for name in names:
        p = rep["processes"][name]
        assert p["pid"] > 0
        assert p["stopped"] in ("SIGINT", "had exited")
        assert p["returncode"] is not None  # it is gone
        assert p["cpu_percent"] is None or p["cpu_percent"] >= 0
    for key in ("service_stats", "controller_stats", "ft_link", "host_stalls", "recorder", "messages",
                "message_counts", "messages_lost", "trips", "layers_in_error", "errors", "run_s"):
        assert key in rep, key
    assert isinstance(rep["service_stats"], dict) and rep["service_stats"]["frames"] > 0
    cs = rep["controller_stats"]
    assert (isinstance(cs, str) and cs.startswith("n/a")) or "missed_frames" in cs
    assert set(rep["ft_link"]) >= {"records", "bad", "resyncs", "max_age_ms"}
    assert all({"queue", "severity", "text"} <= set(m) for m in rep["messages"])
    assert out.returncode == (1 if rep["errors"] else 0)
    # the text report of the same figures: readable lines, never a Python dict (issue 29 item 5)
    from bench.bench_stack import _print
    _print(rep)
    text = capsys.readouterr().out
    assert "  recorder: " in text and "  warnings/errors: service " in text
    assert not any(("{'" in ln or "': " in ln) for ln in text.splitlines() if not ln.startswith("    ")), text


def test_the_orderly_stop_notice_is_not_counted_as_a_trip():
    from bench.bench_stack import _trips
    from ioservice.safety import STOP_CODE
    stop = {"queue": "service", "code": STOP_CODE, "text": "outputs safe: service stopped"}
    trip = {"queue": "service", "code": 1, "text": "outputs safe: stale heartbeat (no new command for 16 ms)"}
    assert _trips([stop, trip]) == [trip]


def test_a_report_section_is_written_as_words_not_a_dict():
    from bench.bench_stack import _pairs_text
    assert _pairs_text({"frames_recorded": 1200, "lossless": True, "sessions": None}) == \
        "frames recorded 1200, lossless yes, sessions -"
    assert _pairs_text({"service": {"WARNING": 2}}) == "service WARNING 2" and _pairs_text("n/a") == "n/a"
