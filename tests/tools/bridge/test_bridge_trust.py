"""Zenoh peers and the trust boundary (issue 28 item 6).

- A hostile peer reaching a reader publishes right-sized inputs bodies (the issue: 479 of
  1,180 reads taken as real, sequence numbers jumping to 10^12): the reader takes none of
  them, counts them and names each kind once.
- Zenoh's own authentication (usrpwd) and access control on the bridge's session: a peer
  without the credentials is not connected at all; an authenticated viewer cannot put on
  the command key nor on an area's key; an operator's commands reach the service.

The service runs in simulated time (SimRig); only the loopback link's delivery is waited
for, bounded (``until``).
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from bit3.layout import ServiceState
from tools.bridge.bridge import Bridge
from tools.bridge.consistency import RESYNC_BODIES, BodyCheck
from tools.bridge.remote import RemoteBuffer, RemoteCommander
from tools.bridge.session import ZenohAuth, open_session
from sim.rig import SimRig
from tests.tools.bridge.test_bridge import free_port, link, settle, step, until  # noqa: F401

zenoh = pytest.importorskip("zenoh")

ROGUE_FRAME = 999_999


def _rogue_body(rig) -> bytes:
    snap = rig.reader.read_inputs()
    rec = snap.record.copy()
    rec["frame"] = ROGUE_FRAME
    rec["service_state"] = int(ServiceState.ARMED)  # what a reader would take for the rack's state
    return rec.tobytes()


def _frames(reader) -> list[int]:
    out = []
    while reader.changed("inputs"):
        out.append(int(reader.read_inputs().frame))
    return out


@pytest.mark.realtime
@pytest.mark.parametrize("copy_id", [False, True])
def test_a_rogue_publisher_on_the_inputs_key_is_never_read_as_the_service(link, copy_id):
    rig, bridge, peer = link
    reader_ep = f"tcp/127.0.0.1:{free_port()}"
    reader_session = open_session(listen=[reader_ep], connect=[peer.endpoint])
    hostile = open_session(connect=[reader_ep])
    try:
        reader = RemoteBuffer(reader_session, rig.name, queue_inputs=True)
        settle(rig, bridge, reader)
        until(lambda: reader.check.publishers == [bridge.writer_id], "the bridge's publisher token")
        pub = hostile.declare_publisher(f"pfma/{rig.name}/inputs", congestion_control=zenoh.CongestionControl.BLOCK)
        body = _rogue_body(rig)
        ident = bridge.writer_id.encode() if copy_id else b""
        rejected = lambda: sum(reader.check.rejected.values())  # noqa: E731
        until(lambda: (pub.put(body, attachment=struct.pack("<Q", 10 ** 12) + ident), rejected() > 0)[1],
              "the hostile route")
        sent = 0
        for k in range(40):  # the jump to 10^12, and bodies just behind the bridge's
            seq = 10 ** 12 + 2 * k if k % 2 else 2
            pub.put(body, attachment=struct.pack("<Q", seq) + ident)
            sent += 1
            step(rig, bridge)
        until(lambda: rejected() >= sent, f"{sent} rogue bodies rejected")
        frames = _frames(reader)
        assert frames and ROGUE_FRAME not in frames
        assert frames == sorted(frames) and len(frames) == len(set(frames))
        kinds = {k for _a, k in reader.check.rejected}
        assert kinds == ({"jump", "backwards"} if copy_id else {"writer"}), reader.check.rejected
        # one line per kind of episode, naming key and numbers or ids
        assert len(reader.check.notes) == len(kinds), reader.check.notes
        if copy_id:
            assert any("seq 1000000000000 after" in n for n in reader.check.notes), reader.check.notes
        else:
            assert any(f"not the bridge's liveliness token {bridge.writer_id}" in n for n in reader.check.notes)
        # the genuine frames go on being read
        step(rig, bridge, 3)
        local = int(rig.reader.read_inputs().frame)
        got: list[int] = []
        until(lambda: (got.extend(_frames(reader)), bool(got) and got[-1] == local)[1], "genuine frames")
        reader.close()
    finally:
        hostile.close()
        reader_session.close()


def test_the_body_check_restarts_a_stream_only_after_a_run_nobody_else_fed():
    t = [0.0]
    chk = BodyCheck("pfma", now=lambda: t[0])
    chk.token("bridge-id", True)
    assert chk.take("inputs", 1000, "bridge-id", b"a")
    t[0] += 1 / 320
    assert not chk.take("inputs", 1002, "other", b"b")  # another writer
    assert not chk.take("inputs", 1002, None, b"b")  # no writer identity
    assert chk.take("inputs", 1002, "bridge-id", b"b")
    assert chk.take("inputs", 1002, "bridge-id", b"b")  # the same body again (query reply)
    assert not chk.take("inputs", 1002, "bridge-id", b"c")  # the same number, other bytes
    assert not chk.take("inputs", 10 ** 12, "bridge-id", b"d")  # 10^12 in 3 ms
    # the service restarted: its numbers start again; after RESYNC_BODIES rejected in a row
    for i in range(RESYNC_BODIES - 3):  # (a "backwards" and a "jump" above are in the run already)
        t[0] += 1 / 320
        assert not chk.take("inputs", 2 + 2 * i, "bridge-id", bytes([i]))
    t[0] += 1 / 320
    assert chk.take("inputs", 500, "bridge-id", b"e")
    assert any("sequence restarted at 500" in n for n in chk.notes), chk.notes
    chk.token("bridge-id", False)  # the bridge is gone: nobody's bodies are taken
    assert not chk.take("inputs", 502, "bridge-id", b"f")
    assert chk.rejected[("inputs", "writer")] == 3


# --- Zenoh's authentication and access control ---------------------------------------------

@pytest.fixture
def secured(tmp_path):
    """A bridge with commands on a SimRig whose session requires user/password
    authentication (``bridge-users`` file) and whose access control lets every user read and
    only the operator ``ops`` put commands."""
    users = tmp_path / "bridge-users"
    users.write_text("bridge:bridge-pw\nops:ops-pw\nviewer:viewer-pw\n")
    users.chmod(0o600)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rig = SimRig(prefix="pfma-test-trust-")
    here = open_session(listen=[endpoint], auth=ZenohAuth("bridge", "bridge-pw", users),
                        buffer=rig.name, operators=["ops"])
    sessions = [here]
    bridge = Bridge(here, rig.name, rig.reader, commander=rig.controller("bridge"))

    def peer(user: str | None, password: str | None):
        s = open_session(connect=[endpoint], auth=ZenohAuth(user, password) if user else None)
        sessions.append(s)
        return s
    try:
        yield rig, bridge, here, peer
    finally:
        bridge.close()
        for s in reversed(sessions):
            s.close()
        rig.close()


@pytest.mark.realtime
@pytest.mark.parametrize("who", ["nobody", "wrong-password"])
def test_a_peer_without_the_credentials_is_not_connected(secured, who):
    rig, bridge, here, peer = secured
    s = peer(*({"nobody": (None, None), "wrong-password": ("ops", "guess")}[who]))
    got = []
    sub = s.declare_subscriber(f"pfma/{rig.name}/inputs", lambda smp: got.append(1))
    ok = peer("viewer", "viewer-pw")  # a peer with credentials, connected meanwhile
    until(lambda: len(list(here.info.peers_zid())) >= 1, "the viewer's session")
    step(rig, bridge, 20)
    assert str(s.zid()) not in {str(z) for z in here.info.peers_zid()}
    assert str(ok.zid()) in {str(z) for z in here.info.peers_zid()}
    assert got == []  # nothing of the rack reaches it
    sub.undeclare()


@pytest.mark.realtime
def test_a_viewer_reads_but_its_commands_and_area_bodies_are_denied(secured):
    rig, bridge, here, peer = secured
    reader = RemoteBuffer(peer("viewer", "viewer-pw"), rig.name)
    settle(rig, bridge, reader)
    assert reader.received("inputs") > 0 and reader.read_inputs().seq > 0  # reading is allowed
    viewer = peer("viewer", "viewer-pw")
    got = []
    here_sub = here.declare_subscriber(f"pfma/{rig.name}/inputs", lambda smp: got.append(smp.payload.to_bytes()))
    body = _rogue_body(rig)
    for _ in range(20):
        viewer.put(f"pfma/{rig.name}/inputs", body)
        viewer.put(f"pfma/{rig.name}/commands/set", b"\x00" * rig.layout.area("commands").body_size,
                   attachment=b"viewer")
        step(rig, bridge)
    # an operator's put, sent after the viewer's, arrives: the viewer's were denied, not slow
    ops = RemoteCommander(RemoteBuffer(peer("ops", "ops-pw"), rig.name), "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the operator's token")
    before = bridge.applied
    until(lambda: (ops.write_commands(arm_request=0), step(rig, bridge), bridge.applied > before)[2],
          "the operator's command")
    assert not any(b == body for b in got)  # the bridge's session never received the viewer's body
    assert not any(k[1] == "writer" for k in reader.check.rejected)
    assert all("viewer" not in s for s in bridge.refused)  # not even refused: denied before the bridge
    assert rig.reader.read_inputs().service_state == ServiceState.SAFE
    assert np.all(np.asarray(rig.world.bus["dac"].output_volts_all()) == 0.0)
    here_sub.undeclare()
    reader.close()


@pytest.mark.realtime
def test_a_reader_with_a_wrong_password_gets_one_line_naming_the_credentials(secured):
    from bit3.buffer import Bit3Error
    rig, bridge, here, peer = secured
    with pytest.raises(Bit3Error) as err:
        RemoteBuffer(peer("viewer", "not-the-password"), rig.name, timeout_s=0.5)
    text = str(err.value)
    assert "no bridge publishes buffer" in text and "$PFMA_ZENOH_CREDENTIALS" in text and "\n" not in text


def test_a_credentials_file_that_is_not_user_password_is_one_message(tmp_path, monkeypatch):
    from pfma.errors import PfmaError
    bad = tmp_path / "creds"
    bad.write_text("just-a-password\n")
    monkeypatch.setenv("PFMA_ZENOH_CREDENTIALS", str(bad))
    with pytest.raises(PfmaError, match="line 1 is not user:password"):
        open_session(connect=["tcp/127.0.0.1:1"])
