"""Characterisation of ``bench.bench_stack._print`` (issue 31): the exact text report it
printed, before its split into one small function per section, for a full report (a hog,
a died process, 42 messages: the 40 shown and the rest counted), a bare one and a held one."""

from __future__ import annotations

import pytest

from bench.bench_stack import _print


def stack_reports() -> dict:
    """Reports of the shape ``bench_stack.measure`` returns: a full one, a bare one."""
    full = {
        "buffer": "pfma-stack-abc123",
        "run_s": 30.0,
        "service_start_s": 1.25,
        "hog": True,
        "held": False,
        "processes": {
            "hog": {"pid": 11, "cpu_percent": 99.0, "stopped": "SIGINT", "returncode": -2, "died": None},
            "service": {
                "pid": 12,
                "cpu_percent": 8.5,
                "stopped": "had exited",
                "returncode": 1,
                "died": {"at_s": 12.5, "returncode": 1},
            },
        },
        "errors": ["service died", "recorder needed SIGKILL"],
        "service_stats": {
            "frames": 9600,
            "dropped_frames": 2,
            "overruns": 1,
            "stall_events": 3,
            "wake_latency_p99_us": 812.4,
            "wake_latency_max_us": 20012.6,
            "work_p99_us": 143.5,
        },
        "controller_stats": {
            "frames": 9590,
            "missed_frames": 4,
            "missed_events": 2,
            "longest_missed_run": 3,
            "missed_task_slots": 1,
            "overruns": 0,
        },
        "ft_link": {
            "records": 30000,
            "bad": 0,
            "resyncs": 1,
            "rate_hz": 1000.0,
            "max_age_ms": 4.2,
            "stale_fraction": 0.0123,
        },
        "host_stalls": {"named": 2, "longest_ms": 64.0, "over_20ms": 2, "over_60ms": 1, "over_100ms": 0},
        "recorder": {"frames_recorded": 9500, "lossless": False, "sessions": None},
        "trips": [{"at_s": 12.25, "severity": "ERROR", "text": "outputs safe: stale heartbeat"}],
        "layers_in_error": [{"layer": "servo", "at_s": 12.3, "count": 2, "why": "fault 12"}],
        "message_counts": {"service": {"WARNING": 2, "ERROR": 1}, "controller": {}},
        "messages_lost": {},
        "messages": [
            {"at_s": 0.01 * i, "queue": "service", "severity": "WARNING", "code": 7, "text": f"m{i}"} for i in range(42)
        ],
    }
    bare = {
        "buffer": "pfma-stack-000000",
        "errors": [],
        "controller_stats": "n/a (no controller)",
        "ft_link": None,
        "host_stalls": {},
        "recorder": None,
    }
    held = dict(
        bare,
        held=True,
        run_s=1.5,
        service_start_s=0.5,
        trips=[],
        layers_in_error=[],
        message_counts={"service": {}},
        messages_lost={"service": 3},
        messages=[],
        ft_link={"records": 1, "bad": 0, "resyncs": 0, "rate_hz": 1.0, "max_age_ms": 1.0, "stale_fraction": None},
    )
    return {"full": full, "bare": bare, "held": held}


EXPECTED = {
    "bare": [
        "stack on buffer pfma-stack-000000: 0 s measured (service up in None s)",
        "  controller: no statistics (n/a (no controller))",
    ],
    "full": [
        "stack on buffer pfma-stack-abc123: 30 s measured (service up in 1.25 s), beside a CPU hog",
        "  NOT HELD: see the problems and layers below",
        "  hog        pid 11      CPU 99.0 % of a core, stopped by SIGINT (exit -2)",
        "  service    pid 12      CPU 8.5 % of a core, stopped by had exited (exit 1), DIED at 12.5 s (exit 1)",
        "  PROBLEM: service died",
        "  PROBLEM: recorder needed SIGKILL",
        "  service: frames 9600, dropped 2, overruns 1, stall events 3, wake p99/max 812/20013 us, work p99 144 us",
        "  controller: frames 9590, missed 4 in 2 events (longest run 3), missed task slots 1, overruns 0",
        "  F/T link: records 30000, bad 0, resyncs 1, rate 1000.0 Hz, max age 4.2 ms (read every 20 ms), "
        "stale in 1.23 % of reads",
        "  host stalls named by the service: 2 (longest 64.0 ms; >20 ms 2, >60 ms 1, >100 ms 0)",
        "  recorder: frames recorded 9500, lossless no, sessions -",
        "  trips (service): 1",
        "       12.25 s ERROR   outputs safe: stale heartbeat",
        "  layers that went to ERROR: 1",
        "    servo at 12.3 s (2x): fault 12",
        "  warnings/errors: service WARNING 2, ERROR 1; controller none (lost unread: none)",
        "        0.00 s service    WARNING    7 m0",
        "        0.01 s service    WARNING    7 m1",
        "        0.02 s service    WARNING    7 m2",
        "        0.03 s service    WARNING    7 m3",
        "        0.04 s service    WARNING    7 m4",
        "        0.05 s service    WARNING    7 m5",
        "        0.06 s service    WARNING    7 m6",
        "        0.07 s service    WARNING    7 m7",
        "        0.08 s service    WARNING    7 m8",
        "        0.09 s service    WARNING    7 m9",
        "        0.10 s service    WARNING    7 m10",
        "        0.11 s service    WARNING    7 m11",
        "        0.12 s service    WARNING    7 m12",
        "        0.13 s service    WARNING    7 m13",
        "        0.14 s service    WARNING    7 m14",
        "        0.15 s service    WARNING    7 m15",
        "        0.16 s service    WARNING    7 m16",
        "        0.17 s service    WARNING    7 m17",
        "        0.18 s service    WARNING    7 m18",
        "        0.19 s service    WARNING    7 m19",
        "        0.20 s service    WARNING    7 m20",
        "        0.21 s service    WARNING    7 m21",
        "        0.22 s service    WARNING    7 m22",
        "        0.23 s service    WARNING    7 m23",
        "        0.24 s service    WARNING    7 m24",
        "        0.25 s service    WARNING    7 m25",
        "        0.26 s service    WARNING    7 m26",
        "        0.27 s service    WARNING    7 m27",
        "        0.28 s service    WARNING    7 m28",
        "        0.29 s service    WARNING    7 m29",
        "        0.30 s service    WARNING    7 m30",
        "        0.31 s service    WARNING    7 m31",
        "        0.32 s service    WARNING    7 m32",
        "        0.33 s service    WARNING    7 m33",
        "        0.34 s service    WARNING    7 m34",
        "        0.35 s service    WARNING    7 m35",
        "        0.36 s service    WARNING    7 m36",
        "        0.37 s service    WARNING    7 m37",
        "        0.38 s service    WARNING    7 m38",
        "        0.39 s service    WARNING    7 m39",
        "    ... 2 more (--json has them all)",
    ],
    "held": [
        "stack on buffer pfma-stack-000000: 1.5 s measured (service up in 0.5 s)",
        "  HELD: no layer went to ERROR",
        "  controller: no statistics (n/a (no controller))",
        "  F/T link: records 1, bad 0, resyncs 0, rate 1.0 Hz, max age 1.0 ms (read every 20 ms), stale in "
        "0.00 % of reads",
        "  trips (service): 0",
        "  layers that went to ERROR: 0",
        "  warnings/errors: service none (lost unread: service 3)",
    ],
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_stack_print_gives_todays_text(name, capsys):
    _print(stack_reports()[name])
    assert capsys.readouterr().out.splitlines() == EXPECTED[name]
