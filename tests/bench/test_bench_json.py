"""``pfma bench --json``: one JSON object with the figures of the service, the controller,
the whole stack, the service over a loopback Modbus gateway, the Zenoh bridge and the host's
costs of a periodic loop. Tiny
durations; the keys are checked and that the figures are finite and positive, never how
fast anything is."""

import json
import math
import subprocess
import sys

import pytest

from bench.bench_host import ROUNDS

pytestmark = pytest.mark.realtime

HEADLINE = {
    "service": ("own_work_p50_us", "own_work_p99_us", "own_cpu_percent", "process_cpu_percent", "ticks_per_s"),
    "controller": ("frame_p50_us", "frame_p99_us"),
    "stack": ("minutes", "run_s"),
    "host": ("wakes_per_s", "cpu_per_wake_us", "cold_factor"),
}


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def test_bench_json_prints_one_object_with_every_benchmark():
    out = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--json", "--seconds", "0.3",
                          "--minutes", "0.05"], capture_output=True, text=True, timeout=300)
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    rep = json.loads(out.stdout)  # the whole output is one object
    assert set(rep) >= {"service", "controller", "stack", "modbus", "host"}
    for section, keys in HEADLINE.items():
        for k in keys:
            assert _positive(rep[section][k]), (section, k, rep[section].get(k))
    assert rep["stack"]["minutes"] == 0.05  # it names its duration
    assert isinstance(rep["service"]["serial_overruns"], int) and rep["service"]["serial_overruns"] >= 0
    host = rep["host"]  # per task, after a sleep and after a busy-wait; the sums per round
    assert set(host["own_after_sleep_us"]) == set(host["own_after_spin_us"]) and "publish" in host["own_after_sleep_us"]
    assert len(host["tasks_after_sleep_us"]) == len(host["tasks_after_spin_us"]) == ROUNDS
    assert isinstance(rep["stack"]["errors"], list)
    mb = rep["modbus"]
    if "skipped" in mb:
        assert isinstance(mb["skipped"], str) and mb["skipped"]
    else:
        assert "error" not in mb, mb
        assert _positive(mb["frame_rate_hz"]) and _positive(mb["work_p50_us"]) and _positive(mb["work_p99_us"])
        assert set(mb["rates_hz"]) == {"rtd", "adc", "dac"}
        assert all(_positive(v) for v in mb["rates_hz"].values())
        # the independent (stdlib-only) reader saw the inputs refresh (no speed asserted)
        assert set(mb["independent_reader_hz"]) == {"rtd", "adc", "dac"}
        assert all(_positive(v) for v in mb["independent_reader_hz"].values())
        assert mb["url"].startswith("modbus://127.0.0.1:")  # loopback only
    br = rep["bridge"]  # the Zenoh bridge on loopback beside shared memory (tools/bridge/latency.py)
    if "skipped" in br:
        assert isinstance(br["skipped"], str) and br["skipped"]
    else:
        assert "error" not in br, br
        for path in ("shm", "bridge"):
            assert _positive(br[path]["p50_us"]) and br[path]["p99_us"] >= br[path]["p50_us"]
        assert 0 < br["delivered_percent"] <= 100 and br["bridge_cpu_percent"] >= 0
    assert out.returncode == (1 if rep["stack"]["errors"] else 0)


def test_bench_json_refuses_a_benchmark_it_does_not_measure():
    out = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "--json", "buffer"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert out.stdout == ""
    assert out.stderr.strip() == "pfma bench: --json measures service, controller, stack, modbus, bridge, host; not buffer"


def test_bench_unknown_name_is_one_message():
    out = subprocess.run([sys.executable, "-m", "tools.cli", "bench", "nosuch"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.startswith("pfma bench: unknown benchmark(s): nosuch; known: ")
