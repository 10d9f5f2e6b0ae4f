"""Characterisation of :func:`bench.bench_soak.judge` (issue 31): the exact lines it gave,
before its split into one small function per criterion, on the hand-made reports of
test_soak_judge (each criterion broken alone, all together, an empty report)."""

import pytest

from bench import bench_soak
from tests.bench import test_soak_judge as T


def soak_cases():
    brks = sorted((n, getattr(T, n)) for n in dir(T) if n.startswith("_break_"))
    c = []
    for n, b in brks:
        r = T.soak_report()
        b(r)
        c.append((n, r))
    r = T.soak_report()
    for n, b in brks:
        if n not in ("_break_no_recording", "_break_process_missing"):
            b(r)
    c.append(("all", r))
    c.append(("empty", {}))
    r = T.soak_report()
    r["unexplained_trips"] = 2
    c.append(("count_only", r))
    r = T.soak_report()
    r["recorder"] = None
    r["operator"] = None
    c.append(("none_parts", r))
    return c


EXPECTED = {
    "_break_died": [
        "soak: FAILED every process alive to the end: recorder died: exited after 312 s (exit 1): "
        "pfma record: disk full"
    ],
    "_break_error": ["soak: FAILED the stack ran without a problem: console needed SIGKILL"],
    "_break_laps": ["soak: FAILED the stack ran (path laps > 0): 0 laps"],
    "_break_left": ["soak: FAILED nothing left behind: /dev/shm/pfma-soak-000000.ring"],
    "_break_lossless": [
        "soak: FAILED the recording lossless: not lossless (frames_recorded 192761, "
        "recorder_missed 0, window_service_frames 192617, window_recorded 192617, "
        "messages_missed 73)"
    ],
    "_break_no_recording": ["soak: FAILED the recording lossless: not lossless (no recording)"],
    "_break_process_missing": [
        "soak: FAILED RSS growth after the first minute measured in every process: none "
        "for bridge_reader (it needs two samples from 1 min on)"
    ],
    "_break_rss": ["soak: FAILED RSS growth after the first minute <= 5 MB: recorder +9.30 MB"],
    "_break_rss_unmeasured": [
        "soak: FAILED RSS growth after the first minute measured in every process: none "
        "for console (it needs two samples from 1 min on)"
    ],
    "_break_trip": ["soak: FAILED no unexplained trip: 1 of 2: 300.5 s outputs safe: ADC timeout"],
    "all": [
        "soak: FAILED RSS growth after the first minute <= 5 MB: recorder +9.30 MB",
        "soak: FAILED RSS growth after the first minute measured in every process: none for console (it "
        "needs two samples from 1 min on)",
        "soak: FAILED no unexplained trip: 1 of 2: 300.5 s outputs safe: ADC timeout",
        "soak: FAILED the recording lossless: not lossless (frames_recorded 192761, recorder_missed 0, "
        "window_service_frames 192617, window_recorded 192617, messages_missed 73)",
        "soak: FAILED the stack ran (path laps > 0): 0 laps",
        "soak: FAILED every process alive to the end: recorder died: exited after 312 s (exit 1): pfma "
        "record: disk full",
        "soak: FAILED the stack ran without a problem: console needed SIGKILL",
        "soak: FAILED nothing left behind: /dev/shm/pfma-soak-000000.ring",
    ],
    "count_only": ["soak: FAILED no unexplained trip: 2 of 1: "],
    "empty": [
        "soak: FAILED RSS growth after the first minute measured in every process: none for "
        "bridge_reader, console, bridge, recorder, controller, service (it needs two samples from 1 min "
        "on)",
        "soak: FAILED the recording lossless: not lossless (no summary)",
        "soak: FAILED the stack ran (path laps > 0): 0 laps",
    ],
    "none_parts": [
        "soak: FAILED the recording lossless: not lossless (no summary)",
        "soak: FAILED the stack ran (path laps > 0): 0 laps",
    ],
}


@pytest.mark.parametrize("name, rep", soak_cases(), ids=lambda v: v if isinstance(v, str) else "")
def test_soak_judge_gives_todays_lines(name, rep):
    assert bench_soak.judge(rep) == EXPECTED[name]


def test_a_good_soak_passes():
    assert bench_soak.judge(T.soak_report()) == []
