"""Tools reading a remote buffer, ``--buffer zenoh://HOST:PORT/NAME`` (issue 19 item 2,
read side) through tools.attach, against a bridge on a SimRig over tcp/127.0.0.1."""

from __future__ import annotations

import json
import threading
import time

import pytest

from sim.rig import SimRig
from tests.tools.bridge.test_bridge import free_port
from tools.attach import attach_reader, no_service, remote_target
from tools.bridge.bridge import Bridge
from tools.bridge.session import open_session
from tools.cli import main
from tools.cli.stats import collect

pytest.importorskip("zenoh")


@pytest.fixture
def served():
    """A SimRig stepped with its bridge in a thread (simulated frames, ~2 ms apart) until
    the test ends; yields (rig, url)."""
    port = free_port()
    rig = SimRig(prefix="pfma-test-remote-")
    session = open_session(listen=[f"tcp/127.0.0.1:{port}"])
    bridge = Bridge(session, rig.name, rig.reader)
    stop = threading.Event()

    def run() -> None:
        while not stop.is_set():
            rig.run_frames(1)
            bridge.poll()
            time.sleep(0.002)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield rig, f"zenoh://127.0.0.1:{port}/{rig.name}"
    finally:
        stop.set()
        t.join(timeout=10)
        bridge.close()
        session.close()
        rig.close()


def test_remote_names_parse_and_shared_memory_names_are_unchanged():
    assert remote_target("zenoh://10.0.0.5:7447/pfma") == ("tcp/10.0.0.5:7447", "pfma")
    assert remote_target("pfma") is None
    assert no_service("zenoh://127.0.0.1:1/pfma") is None  # decided by the attach
    assert "no I/O service runs" in no_service("pfma-no-such-remote-test")


@pytest.mark.realtime
def test_stats_and_read_through_the_bridge(served):
    rig, url = served
    with attach_reader(url) as remote:
        d = collect(remote)
        assert d["service_state"] in ("SAFE", "ARMED", "FAULT", "HALTED")
        assert d["frame_rate_hz"] >= 0 and set(d["devices"])
        hdr = remote.header()
        assert hdr.rack_name == rig.layout.rack_name and hdr.layout_hash == rig.layout.hash


@pytest.mark.realtime
def test_monitor_once_and_read_with_a_zenoh_buffer(served, capsys):
    rig, url = served
    assert main(["monitor", "--once", "--json", "--buffer", url]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["buffer"] == rig.name and d["rack"] == rig.layout.rack_name and d["frame"] > 0


@pytest.mark.parametrize("url, words", [
    ("zenoh://127.0.0.1/pfma", "zenoh://HOST:PORT/NAME"),
])
def test_a_bad_remote_name_is_one_message(url, words, capsys):
    assert main(["monitor", "--once", "--buffer", url]) == 1
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and err.count("\n") == 1


@pytest.mark.realtime
def test_pfma_read_and_stats_with_a_zenoh_buffer(served, capsys):
    rig, url = served
    assert main(["read", "--buffer", url, "elbow_pitch_angle", "--json"]) == 0
    out = capsys.readouterr().out
    assert "elbow_pitch_angle" in out
    assert main(["stats", "--buffer", url, "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["service_state"] in ("SAFE", "ARMED", "FAULT", "HALTED") and set(d["devices"])


@pytest.mark.realtime
def test_pfma_stats_with_no_bridge_is_one_message(capsys):
    from tests.tools.bridge.test_bridge import free_port as port
    assert main(["stats", "--buffer", f"zenoh://127.0.0.1:{port()}/pfma"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("pfma stats: ") and "Traceback" not in err
