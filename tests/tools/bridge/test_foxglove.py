"""``pfma foxglove`` (issue 19 item 4): the live channels over the foxglove-sdk WebSocket
server on 127.0.0.1, under the names and schemas of an MCAP recording; a WebSocket client
(tests/tools/bridge/_ws.py) sees them advertised and an inputs message that decodes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from sim.rig import SimRig
from tests.tools.bridge._ws import BINARY, WsClient, message_data
from tests.tools.bridge.test_bridge import free_port
from tools.cli import main
from tools.recording import RAW_TOPIC, Recorder
from tools.recording.schema import decode_raw, raw_dtype

foxglove = pytest.importorskip("foxglove")

WAIT_S = 10.0
ROOT = Path(__file__).resolve().parents[3]


def recording_schemas(rig, path) -> dict[str, tuple[str, str, str, str]]:
    """topic -> (message encoding, schema name, schema encoding, schema text) of an MCAP
    recording of ``rig``, as the recorder registers them."""
    from mcap.reader import make_reader
    Recorder(rig.reader, path).close()
    with open(path, "rb") as f:
        s = make_reader(f).get_summary()
    return {ch.topic: (ch.message_encoding, s.schemas[ch.schema_id].name, s.schemas[ch.schema_id].encoding,
                       s.schemas[ch.schema_id].data.decode()) for ch in s.channels.values()}


def advertised(ws: WsClient) -> dict[str, dict]:
    info = ws.recv_json()
    assert info["op"] == "serverInfo"
    adv = ws.recv_json()
    assert adv["op"] == "advertise"
    return {ch["topic"]: ch for ch in adv["channels"]}


def check_channels(chans: dict[str, dict], rig, tmp_path) -> None:
    """The recording's channels, same encodings and schemas (its recorder counters aside)."""
    rec = recording_schemas(rig, tmp_path / "schemas.mcap")
    assert set(chans) == set(rec) - {"/pfma/recorder"}
    for topic, ch in chans.items():
        assert (ch["encoding"], ch["schemaName"], ch["schemaEncoding"], ch["schema"]) == rec[topic], topic


def first_messages(ws: WsClient, subs: dict[int, str], step, want: set[str]) -> dict[str, tuple[int, bytes]]:
    """Step (``step()``) until one message of each topic in ``want`` arrived (bounded)."""
    got: dict[str, tuple[int, bytes]] = {}
    end = time.monotonic() + WAIT_S
    while not want <= set(got):
        if time.monotonic() > end:
            raise AssertionError(f"not within {WAIT_S} s: messages of {sorted(want - set(got))}")
        step()
        while ws.ready(0.005):
            op, data = ws.recv()
            if op == BINARY:
                sub, t_ns, msg = message_data(data)
                got.setdefault(subs[sub], (t_ns, msg))
    return got


def test_live_channels_are_the_recordings_and_an_inputs_message_decodes(tmp_path):
    """In process, simulated frames: the server on a free loopback port, a WebSocket client
    subscribes to the raw inputs and the joints; each tick sends the newest frame."""
    from tools.foxglove import LiveChannels
    with SimRig(prefix="pfma-test-fox-") as rig:
        rig.run_frames(5)
        ctx = foxglove.Context()
        live = LiveChannels(rig.reader, context=ctx)
        server = foxglove.start_server(host="127.0.0.1", port=0, context=ctx)
        ws = WsClient(server.port)
        try:
            assert "foxglove" in ws.head.lower()  # a foxglove subprotocol negotiated
            chans = advertised(ws)
            check_channels(chans, rig, tmp_path)
            subs = {1: RAW_TOPIC, 2: "/pfma/joints", 3: "/pfma/status"}
            ws.send_json({"op": "subscribe", "subscriptions": [{"id": i, "channelId": chans[t]["id"]}
                                                               for i, t in subs.items()]})
            got = first_messages(ws, subs, lambda: (rig.run_frames(1), live.tick()), set(subs.values()))
            schema = json.loads(chans[RAW_TOPIC]["schema"])
            t_ns, body = got[RAW_TOPIC]
            r = decode_raw(schema, body, raw_dtype(schema))
            frame = int(r["frame"])
            assert 5 <= frame <= int(rig.reader.read_inputs().frame)  # a frame run after the start
            assert t_ns == live.offset_ns + round(float(r["t_s"]) * 1e9)  # the recording's log time
            joints = json.loads(got["/pfma/joints"][1])
            assert "elbow_pitch" in json.dumps(joints) and joints["frame"] >= 5
            assert json.loads(got["/pfma/status"][1])["state"] == "SAFE"
        finally:
            ws.close()
            server.stop()
            live.close()


@pytest.mark.realtime
def test_pfma_foxglove_serves_a_simulated_service(tmp_path):
    """``pfma foxglove`` in its own process against a simulated service (stepped here, ~2 ms
    a frame); a WebSocket client on its loopback port gets the channels and inputs."""
    port = free_port()
    with SimRig(prefix="pfma-test-foxcli-") as rig:
        stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                rig.run_frames(1)
                time.sleep(0.002)
        t = threading.Thread(target=run, daemon=True)
        t.start()
        proc = subprocess.Popen([sys.executable, "-m", "tools.cli", "foxglove", "--buffer", rig.name, "--port",
                                 str(port), "--rate", "50", "--duration", "20"], cwd=ROOT,
                                env=dict(os.environ, PYTHONPATH=str(ROOT)), stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stderr is not None
            line = proc.stderr.readline()  # said once the server listens
            assert f"ws://127.0.0.1:{port}" in line, line
            ws = WsClient(port)
            chans = advertised(ws)
            assert RAW_TOPIC in chans and "/pfma/joints" in chans
            ws.send_json({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": chans[RAW_TOPIC]["id"]}]})
            got = first_messages(ws, {7: RAW_TOPIC}, lambda: None, {RAW_TOPIC})
            schema = json.loads(chans[RAW_TOPIC]["schema"])
            r = decode_raw(schema, got[RAW_TOPIC][1], raw_dtype(schema))
            assert 0 < int(r["frame"]) <= int(rig.reader.read_inputs().frame)
            ws.close()
        finally:
            proc.send_signal(2)
            _, err = proc.communicate(timeout=20)
            stop.set()
            t.join(timeout=10)
        assert proc.returncode == 0 and "Traceback" not in err and "stopped after" in err, err


@pytest.mark.parametrize("argv, code, words", [
    (["foxglove", "--rate", "100"], 2, "outside 20..60 Hz"),
    (["foxglove", "--port", "70000"], 2, "outside 0..65535"),
    (["foxglove", "--buffer", "pfma-no-such-foxglove-buffer"], 1, "no I/O service runs on buffer"),
])
def test_bad_foxglove_input_is_one_message(argv, code, words, capsys):
    if code == 2:
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2
    else:
        assert main(argv) == code
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err


def test_a_port_in_use_is_one_message(capsys):
    import socket
    with SimRig(prefix="pfma-test-foxport-") as rig, socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        assert main(["foxglove", "--buffer", rig.name, "--port", str(s.getsockname()[1]), "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert "cannot serve on 127.0.0.1:" in err and "Traceback" not in err and err.count("\n") == 1
