"""Zenoh traffic the bridge and its remote readers did not ask for (issue 20 item 2): a
hostile or broken peer on the same Zenoh network publishes truncated, oversized and
foreign bodies on the areas' keys, garbage on the layout and writer keys, command bodies
of the wrong size, under other writers' names and with values beyond every limit, floods
of liveliness tokens and messages bigger than a session takes. Nothing crashes, nothing
reaches the arm, every refusal is counted and said in a bounded number of messages.

The service runs in simulated time (SimRig); only the loopback link's delivery is waited
for, bounded (``until``)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from bit3.buffer import Bit3Error
from bit3.layout import ServiceState
from tools.bridge.bridge import MAX_NAMED_SENDERS, MAX_WRITERS, OTHER_SENDERS
from tools.bridge.remote import RemoteBuffer, RemoteCommander
from tools.bridge.session import MAX_MESSAGE_BYTES, open_session
from tests.tools.bridge.test_bridge import _arm, _deliver, free_port, link, settle, step, until  # noqa: F401

zenoh = pytest.importorskip("zenoh")

pytestmark = pytest.mark.realtime


def _bridge_lines(rig) -> list[str]:
    return [m.text for m in rig.reader.messages(queue="controller") if m.text.startswith("bridge")]


def test_foreign_bodies_on_the_area_keys_are_never_decoded(link):
    """Truncated, empty, oversized and foreign-layout bodies published on the inputs and
    stats keys by another peer that reaches the reader (here: connected to the reader's
    own session, as on a mesh or through a router): the reader counts and drops every one,
    and what it reads is still the service's, frame for frame."""
    rig, bridge, peer = link
    reader_ep = f"tcp/127.0.0.1:{free_port()}"
    reader_session = open_session(listen=[reader_ep], connect=[peer.endpoint])
    hostile = open_session(connect=[reader_ep])
    try:
        reader = RemoteBuffer(reader_session, rig.name, queue_inputs=True)
        settle(rig, bridge, reader)
        size = rig.layout.area("inputs").body_size
        bad = [b"", b"\x00", bytes(size - 1), bytes(size + 1), bytes(3 * size), b"\xff" * 100]
        # BLOCK: a put under CPU load is not dropped at the sender (zenoh's default for data
        # is DROP), so every body sent is one the reader must count
        pubs = {a: hostile.declare_publisher(f"pfma/{rig.name}/{a}",
                                             congestion_control=zenoh.CongestionControl.BLOCK)
                for a in ("inputs", "stats")}
        # the hostile peer's route to the reader's subscriber is in place once one body arrives
        sent = 0

        def probe() -> bool:
            nonlocal sent
            pubs["inputs"].put(b"x")
            sent += 1
            return sum(reader.rejected.values()) > 0
        until(probe, "the hostile route")
        base, sent = sent, 0  # probes in flight are counted too (a put before the route is lost)
        for k in range(30):
            for body in bad:
                pubs["inputs" if k % 2 else "stats"].put(body, attachment=struct.pack("<Q", 2 ** 63 + k))
                sent += 1
            step(rig, bridge)
        until(lambda: sum(reader.rejected.values()) >= sent, f"{sent} foreign bodies counted")
        assert sent <= sum(reader.rejected.values()) <= base + sent
        assert set(reader.rejected) == {"inputs", "stats"}
        frames = []
        while reader.changed("inputs"):
            frames.append(int(reader.read_inputs().frame))
        local = int(rig.reader.read_inputs().frame)
        assert frames and frames == sorted(frames) and frames[-1] <= local
        assert len(frames) == len(set(frames))  # no foreign body read as a frame
        step(rig, bridge, 3)  # genuine frames after the flood: the reader gets them all
        local = int(rig.reader.read_inputs().frame)
        got: list[int] = []

        def caught_up() -> bool:
            while reader.changed("inputs"):
                got.append(int(reader.read_inputs().frame))
            return bool(got) and got[-1] == local
        until(caught_up, "the genuine frames after the flood")
        assert got == list(range(got[0], local + 1))
        reader.close()
    finally:
        hostile.close()
        reader_session.close()


def test_garbage_on_the_layout_key_is_one_clear_error():
    """A peer that answers the layout query with something else: a one-line Bit3Error, not
    a JSON traceback; the same for the writer key a commander asks."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    here = open_session(listen=[endpoint])
    there = open_session(connect=[endpoint])
    try:
        answers = {"pfma/junk/layout": b"\x00not json", "pfma/list/layout": b"[1, 2, 3]"}
        qs = [here.declare_queryable(k, lambda q, body=b: q.reply(q.key_expr, body)) for k, b in answers.items()]
        with pytest.raises(Bit3Error, match="not a layout document .*not JSON"):
            RemoteBuffer(there, "junk", timeout_s=3.0)
        with pytest.raises(Bit3Error, match="not a layout document .*no layout hash"):
            RemoteBuffer(there, "list", timeout_s=3.0)
        for q in qs:
            q.undeclare()
    finally:
        there.close()
        here.close()


def test_a_holder_sending_bodies_of_the_wrong_size_is_counted_not_obeyed(link):
    """The token holder publishes 120 command bodies of wrong sizes (arming attempts among
    them): none is written, the service never arms, and the bridge says so in ONE message
    (the rest summed into the next one, a minute later), not one per body."""
    rig, bridge, peer = link
    remote = RemoteBuffer(peer(), rig.name)
    cmd = RemoteCommander(remote, "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the holder's token")
    settle(rig, bridge, remote)
    size = rig.layout.area("commands").body_size
    for k in range(120):
        body = bytes(cmd.raw) + b"\x01" * (1 + k % 7) if k % 2 else bytes(cmd.raw)[: size - 1 - k]
        cmd._pub.put(body, attachment=cmd.ident.encode())
        until(lambda: bridge._pending is not None, "a body at the bridge")
        step(rig, bridge)
    assert bridge.applied == 0 and bridge.refused == {"ops-laptop": 120}
    total = bridge.refusals.total
    assert total == {f"command bodies shorter than the layout's {size} bytes": 60,
                     f"command bodies longer than the layout's {size} bytes": 60}
    lines = _bridge_lines(rig)
    refusal_lines = [t for t in lines if "refused in the last" in t]
    assert len(refusal_lines) == 1, lines  # the first at once; the rest wait for the interval
    s_in = rig.reader.read_inputs()
    assert ServiceState(s_in.service_state) is not ServiceState.ARMED
    assert np.abs(s_in.dac_value).max() == 0.0
    bridge.close()  # the stop says what was left
    assert len([t for t in _bridge_lines(rig) if "refused in the last" in t]) == 2


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e9])
def test_a_holder_commanding_beyond_every_limit_is_refused_by_the_service(link, value):
    """A right-size body whose joint rate is NaN, infinite or 1e9 rad/s, from the holder,
    while ARMED: the bridge passes it on (the service is the one judge of limits), the
    service refuses it naming the field, and every output goes to 0 V."""
    rig, bridge, peer = link
    remote = RemoteBuffer(peer(), rig.name)
    cmd = RemoteCommander(remote, "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the holder's token")
    settle(rig, bridge, remote)
    _deliver(rig, bridge, lambda: _arm(cmd, rig, bridge), "the arm request")
    zero = [0.0] * len(rig.layout.joint_names)
    for _ in range(3):
        _deliver(rig, bridge, lambda: cmd.write_commands(joint_rate_rad_s=zero), "a heartbeat")
    assert ServiceState(rig.reader.read_inputs().service_state) is ServiceState.ARMED
    # the client refuses non-finite values itself; a hostile peer writes the bytes directly
    rec = np.ndarray((), cmd.command.dtype, buffer=bytearray(cmd.raw))
    rec["joint_rate_rad_s"][2] = value
    rec["heartbeat"] = int(rec["heartbeat"]) + 1
    before = bridge.applied
    cmd._pub.put(bytes(rec.tobytes()), attachment=cmd.ident.encode())
    until(lambda: bridge._pending is not None, "the hostile body at the bridge")
    step(rig, bridge, 2)
    assert bridge.applied == before + 1
    s_in = rig.reader.read_inputs()
    assert ServiceState(s_in.service_state) is not ServiceState.ARMED
    assert np.abs(s_in.dac_value).max() == 0.0
    texts = [m.text for m in rig.reader.messages(queue="service")]
    assert any("refused" in t and "elbow_pitch" in t for t in texts), texts


def test_senders_under_new_names_cannot_flood_the_messages_or_the_counts(link):
    """60 bodies, each under a new sender name that holds no token: at most
    MAX_NAMED_SENDERS messages name a sender, the counts keep MAX_NAMED_SENDERS names plus
    one bucket, and nothing is written."""
    rig, bridge, peer = link
    remote = RemoteBuffer(peer(), rig.name)
    cmd = RemoteCommander(remote, "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the holder's token")
    settle(rig, bridge, remote)
    hostile = peer().declare_publisher(f"pfma/{rig.name}/commands/set")
    for k in range(60):
        hostile.put(bytes(cmd.raw), attachment=f"spoof-{k}-".encode() + b"x" * 500)
        until(lambda: bridge._pending is not None, "a spoofed body at the bridge")
        step(rig, bridge)
    assert bridge.applied == 0
    assert len(bridge.refused) == MAX_NAMED_SENDERS + 1
    assert sum(bridge.refused.values()) == 60 and bridge.refused[OTHER_SENDERS] == 60 - MAX_NAMED_SENDERS
    assert all(len(name) <= 64 for name in bridge.refused)
    named = [t for t in _bridge_lines(rig) if "refused: the command area is held" in t]
    assert len(named) == MAX_NAMED_SENDERS


def test_a_peer_that_copies_the_holders_name_but_not_its_nonce_is_never_written(link):
    """A hostile peer puts arming bodies under the holder's name alone (no nonce, as a peer
    that read the name in a message would): none is written, the service never arms, and
    they are counted, not named in a refused-sender message (the name is the holder's).
    The nonce is no secret: this is what it does, not a trust boundary (docs/bridge.md)."""
    rig, bridge, peer = link
    remote = RemoteBuffer(peer(), rig.name)
    cmd = RemoteCommander(remote, "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the holder's token")
    settle(rig, bridge, remote)
    rec = np.ndarray((), cmd.command.dtype, buffer=bytearray(cmd.raw))
    rec["arm_request"], rec["rearm_counter"] = 1, int(rec["rearm_counter"]) + 1
    hostile = peer().declare_publisher(f"pfma/{rig.name}/commands/set")
    for _ in range(5):
        hostile.put(bytes(rec.tobytes()), attachment=b"ops-laptop")
        until(lambda: bridge._pending is not None, "the copied-name body at the bridge")
        step(rig, bridge, 2)
    assert bridge.applied == 0 and bridge.refused == {}
    assert ServiceState(rig.reader.read_inputs().service_state) is not ServiceState.ARMED
    assert bridge.refusals.total == {"command bodies under the holder's name from another writer (an earlier "
                                     "writer's last word after its token went, or a forger)": 5}
    cmd.close()


def test_a_flood_of_writer_tokens_is_bounded(link):
    """40 liveliness tokens from one peer: the bridge keeps MAX_WRITERS, the first stays
    the holder, the rest are counted and said once."""
    rig, bridge, peer = link
    s = peer()
    tokens = [s.liveliness().declare_token(f"pfma/{rig.name}/writer/commands/w{k:02d}") for k in range(40)]
    until(lambda: len(bridge.writers) == MAX_WRITERS
          and bridge._tokens_over >= 40 - MAX_WRITERS, "the tokens at the bridge")
    step(rig, bridge)
    assert len(bridge.writers) == MAX_WRITERS
    assert bridge.refusals.total == {f"writer tokens over the limit of {MAX_WRITERS} (ignored)": 40 - MAX_WRITERS}
    assert bridge.holder is not None and bridge.holder.startswith("w")
    for t in tokens:
        t.undeclare()
    until(lambda: not bridge.writers, "the tokens withdrawn")


def test_a_message_over_the_size_limit_drops_its_link_and_the_bridge_goes_on(link):
    """One 5 MiB put on the command key (over MAX_MESSAGE_BYTES): the bridge's session does
    not take it (the link that carried it is closed), the bridge writes nothing, and a
    reader on another link keeps receiving frames."""
    rig, bridge, peer = link
    reader = RemoteBuffer(peer(), rig.name)
    settle(rig, bridge, reader)
    hostile = peer()
    hostile.put(f"pfma/{rig.name}/commands/set", bytes(MAX_MESSAGE_BYTES + 1024 * 1024), attachment=b"x")
    for _ in range(50):
        step(rig, bridge)
    assert bridge._pending is None and bridge.applied == 0
    n = reader.received("inputs")
    until(lambda: (step(rig, bridge), reader.received("inputs") > n + 5)[1], "frames to the other reader")
    assert int(reader.read_inputs().frame) <= int(rig.reader.read_inputs().frame)


def test_a_bridge_without_commands_is_said_after_a_bounded_wait():
    """A remote writer asks a read-only bridge for its writer key: no answer within
    WRITER_QUERY_WAIT_S (a just-started bridge answers within milliseconds) -> one clear
    Bit3Error, not a wait of the whole time-out."""
    import time

    from sim.rig import SimRig
    from tools.bridge.bridge import Bridge
    from tools.bridge.remote import WRITER_QUERY_WAIT_S
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rig = SimRig(prefix="pfma-test-bridge-ro-")
    here = open_session(listen=[endpoint])
    there = open_session(connect=[endpoint])
    bridge = Bridge(here, rig.name, rig.reader)  # read-only: no command writer
    try:
        remote = RemoteBuffer(there, rig.name, timeout_s=30.0)
        t0 = time.monotonic()
        with pytest.raises(Bit3Error, match="takes no commands"):
            RemoteCommander(remote, "ops-laptop")
        assert time.monotonic() - t0 < 30.0  # bounded by WRITER_QUERY_WAIT_S, not the 30 s time-out
        assert WRITER_QUERY_WAIT_S < 30.0
    finally:
        bridge.close()
        there.close()
        here.close()
        rig.close()
