"""A reader that knows only the published layout (``pfma layout --json``) and the
stdlib (bench/independent_reader.py) attaches to the service's buffer and sees the
documented refresh rates: resolvers and ADC 160 Hz, F/T 80 Hz, DAC 320 Hz, within 1 %."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.independent_reader import IndependentReader, LayoutMismatch, SAMPLE_TIMES, ServiceStalled, measure
from sim.rig import SimRig

READER = Path(__file__).resolve().parents[2] / "bench" / "independent_reader.py"


@pytest.fixture(scope="module")
def published_layout():
    out = subprocess.run([sys.executable, "-m", "tools.cli", "layout", "--json"], capture_output=True,
                         text=True, check=True).stdout
    return json.loads(out)


def test_reader_imports_only_the_standard_library():
    tree = ast.parse(READER.read_text())
    mods = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    mods |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert mods <= set(sys.stdlib_module_names) | {"__future__"}, mods


@pytest.mark.realtime
def test_independent_reader_sees_the_documented_rates(published_layout):
    rig = SimRig(prefix="pfma-test-")
    try:
        r = IndependentReader(published_layout, f"/dev/shm/{rig.name}")
        try:
            res = measure(r, lambda: rig.run_frames(1), seconds=3.0)
        finally:
            r.close()
    finally:
        rig.close()
    for name, want in SAMPLE_TIMES.items():
        assert res[name] == pytest.approx(want, rel=0.01), (name, res)
        assert res[f"stats.{name[2:-2]}"] == pytest.approx(want, rel=0.01), (name, res)


@pytest.mark.realtime
def test_a_different_layout_is_refused(published_layout):
    wrong = dict(published_layout, hash="0" * 16)
    rig = SimRig(prefix="pfma-test-")
    try:
        with pytest.raises(LayoutMismatch, match="layout hash"):
            IndependentReader(wrong, f"/dev/shm/{rig.name}")
    finally:
        rig.close()


@pytest.mark.realtime
def test_a_service_that_stops_mid_measurement_is_reported_not_waited_for(published_layout):
    """Frames stop after 1 s of a 3 s measurement: the reader says so once its inputs have
    stood still for ``stall_s`` of (here simulated) wall-clock time, instead of hanging."""
    rig = SimRig(prefix="pfma-test-")
    wall = [0.0]
    frames = [0]

    def step():
        wall[0] += 0.01
        if frames[0] < 320:  # 1 s of frames, then the service is gone
            rig.run_frames(1)
            frames[0] += 1

    try:
        r = IndependentReader(published_layout, f"/dev/shm/{rig.name}")
        try:
            with pytest.raises(ServiceStalled, match=r"not changed for 2 s .* after 1\.0 of 3 s"):
                measure(r, step, seconds=3.0, stall_s=2.0, wall=lambda: wall[0])
        finally:
            r.close()
    finally:
        rig.close()
    assert 2.0 < wall[0] - 3.2 < 2.1  # gave up 2 s (of its wall clock) after the last frame
