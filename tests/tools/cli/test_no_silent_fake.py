"""Issue 17, item 1: never a silent fake. Tools that read a service's buffer fail with one
line and exit 1 when no live service publishes it; the fake rack is read only with an
explicit ``--bus fake`` and says so; ``pfma serve`` refuses a rack file without ``--bus``
and exits 1 naming the bus when it cannot reach its boards."""

from __future__ import annotations

import multiprocessing
import os
import uuid

import pytest

from drivers.bus import open_bus
from bit3.layout import default_layout
from bit3.buffer import Bit3Buffer
from tools.cli import main
from pfma.errors import PfmaError
from tests.bit3 import _workers

READERS = [
    ["read", "elbow_pitch_angle"],
    ["stats"],
    ["watch", "elbow_pitch_angle", "--count", "1"],
    ["monitor", "--once"],
]


@pytest.fixture
def name():
    n = "pfma-nsf-" + uuid.uuid4().hex[:8]
    yield n
    Bit3Buffer.unlink(n)


def _one_line_error(capsys, verb: str) -> str:
    cap = capsys.readouterr()
    assert cap.out == ""  # nothing that looks like data
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1, cap.err
    assert lines[0].startswith(f"pfma {verb}: ") and "Traceback" not in cap.err
    return lines[0]


@pytest.mark.parametrize("argv", READERS, ids=lambda a: a[0])
def test_missing_buffer_is_one_clear_error(argv, name, capsys):
    assert main([*argv, "--buffer", name]) == 1
    line = _one_line_error(capsys, argv[0])
    assert f"/dev/shm/{name}" in line and "pfma serve" in line and "--buffer" in line
    assert not os.path.exists(f"/dev/shm/{name}")


def _dead_service_buffer(name: str) -> int:
    """A buffer whose service claimed it in a child process that then died (pid returned)."""
    buf = Bit3Buffer.create(name)
    buf.close()
    ctx = multiprocessing.get_context("spawn")
    parent, child_end = ctx.Pipe()
    child = ctx.Process(target=_workers.hold_service_claim, args=(name, default_layout().hash, child_end))
    child.start()
    assert parent.poll(60.0)
    pid = parent.recv()
    parent.send("die")
    child.join(30.0)
    assert child.exitcode == 0
    return pid


@pytest.mark.realtime
@pytest.mark.parametrize("argv", READERS, ids=lambda a: a[0])
def test_dead_service_is_one_clear_error(argv, name, capsys):
    pid = _dead_service_buffer(name)
    assert Bit3Buffer.owner_alive(name)[0] is False
    assert main([*argv, "--buffer", name]) == 1
    line = _one_line_error(capsys, argv[0])
    assert f"service on /dev/shm/{name} is not running" in line
    assert "last frame 0" in line and str(pid) in line


@pytest.mark.parametrize("argv", READERS[:3], ids=lambda a: a[0])
def test_buffer_nobody_ever_claimed_is_not_a_service(argv, name, capsys):
    Bit3Buffer.create(name).close()
    assert main([*argv, "--buffer", name]) == 1
    assert f"service on /dev/shm/{name} is not running" in _one_line_error(capsys, argv[0])


@pytest.mark.realtime
def test_read_from_a_live_service_still_works(name, capsys):
    buf = Bit3Buffer.create(name)
    buf.close()
    ctx = multiprocessing.get_context("spawn")
    parent, child_end = ctx.Pipe()
    child = ctx.Process(target=_workers.hold_service_claim, args=(name, default_layout().hash, child_end))
    child.start()
    try:
        assert parent.poll(60.0)
        parent.recv()
        assert main(["read", "elbow_pitch_angle", "--buffer", name]) == 0
        out = capsys.readouterr().out
        assert "from the service" in out and "simulated" not in out
        assert main(["stats", "--buffer", name]) == 0  # a live service's statistics, as before
        out = capsys.readouterr().out
        assert out.startswith("state ") and "controller: no controller attached" in out
    finally:
        parent.send("die")
        child.join(30.0)


def test_read_fake_rack_needs_bus_fake_and_says_simulated(capsys):
    assert main(["read", "--bus", "fake", "elbow_pitch_angle", "shoulder_yaw_motor_current"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and all("(simulated rack)" in ln for ln in lines)


def test_read_fake_rack_json_says_simulated(capsys):
    import json
    assert main(["read", "--bus", "fake", "elbow_pitch_angle", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["source"] == "simulated rack"


def test_serve_rack_file_without_bus_is_refused(name, capsys):
    rack = os.path.join(os.path.dirname(__file__), "..", "..", "..", "pfma", "rack_default.toml")
    assert main(["serve", "--rack", rack, "--duration", "0.1", "--buffer", name]) == 2
    err = capsys.readouterr().err
    assert "needs --bus" in err and "--bus fake" in err
    assert not os.path.exists(f"/dev/shm/{name}")


@pytest.mark.parametrize("bus, why", [
    ("modbus://127.0.0.1:1", "every board failed to initialise"),  # nothing listens on port 1
    ("bogus://x", "unknown bus scheme"),
    ("modbus://127.0.0.1", "needs a host and a port"),
])
def test_serve_that_cannot_reach_its_boards_exits_1(bus, why, name, capsys):
    assert main(["serve", "--bus", bus, "--duration", "0.2", "--buffer", name]) == 1
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err and "stopped after" not in cap.out
    (line,) = cap.err.strip().splitlines()
    assert line.startswith("pfma serve: ") and bus in line and why in line
    assert not os.path.exists(f"/dev/shm/{name}")
    assert not os.path.exists(f"/dev/shm/{name}.ring")


@pytest.mark.parametrize("url", ["bogus://x", "modbus://host", "nothing"])
def test_open_bus_url_errors_are_pfma_errors(url):
    with pytest.raises(PfmaError, match=repr(url).strip("'")):
        open_bus(url)
    with pytest.raises(ValueError):  # as before
        open_bus(url)
