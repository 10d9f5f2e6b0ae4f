"""The Bit3 areas over Zenoh (issue 19 item 1): a bridge on a simulated service, remote
peers on tcp/127.0.0.1 with a free port. The service runs in simulated time; only the
link's delivery is waited for, bounded (``until``)."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from bit3.layout import ServiceState
from bit3.seqlock import OwnershipError
from sim.rig import SimRig
from tools.bridge.bridge import SAFE_START_FRAMES, Bridge
from tools.bridge.remote import RemoteBuffer, RemoteCommander
from tools.bridge.session import open_session

pytest.importorskip("zenoh")

pytestmark = pytest.mark.realtime

WAIT_S = 5.0  # bound of every wait for the link (a failure, not a timing assert)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def until(cond, what: str) -> None:
    end = time.monotonic() + WAIT_S
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"not within {WAIT_S} s: {what}")
        time.sleep(0.002)


@pytest.fixture
def link():
    """(rig, bridge, session_factory): a bridge with a command writer on a SimRig,
    listening on loopback; the factory opens remote peers connected to it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rig = SimRig(prefix="pfma-test-bridge-")
    here = open_session(listen=[endpoint])
    sessions = [here]
    bridge = Bridge(here, rig.name, rig.reader, commander=rig.controller("bridge"))

    def peer():
        s = open_session(connect=[endpoint])
        sessions.append(s)
        return s
    peer.endpoint = endpoint  # type: ignore[attr-defined]  (for a peer that must also listen)
    try:
        yield rig, bridge, peer
    finally:
        bridge.close()
        for s in reversed(sessions):
            s.close()
        rig.close()


def settle(rig, bridge, remote) -> None:
    """Frames until the remote subscriber's declaration has reached the bridge (bodies
    published before that are not delivered): bounded like every wait here."""
    until(lambda: (step(rig, bridge), remote.received("inputs") > 0)[1], "a first inputs body")


def step(rig, bridge, frames: int = 1) -> None:
    for _ in range(frames):
        rig.run_frames(1)
        bridge.poll()


def test_remote_read_equals_local_read(link):
    rig, bridge, peer = link
    remote = RemoteBuffer(peer(), rig.name)
    settle(rig, bridge, remote)
    for _ in range(5):
        step(rig, bridge)
        local = rig.reader.read_inputs()
        until(lambda: remote.read_inputs().frame == local.frame, "this frame's inputs body")
        snap = remote.read_inputs()
        assert bytes(snap.record.tobytes()) == bytes(local.record.tobytes())
        assert snap.elbow_pitch_angle == local.elbow_pitch_angle  # decoded by channel name
    assert remote.layout.hash_hex == rig.layout.hash_hex
    # a message queue arrives on change and decodes like a local read (a long text whole)
    n = remote.received("controller_messages")
    rig.ctl.post_message("hello from the rack " * 5)
    step(rig, bridge)
    until(lambda: remote.received("controller_messages") > n, "the message queue")
    assert remote.messages(queue="controller") == rig.reader.messages(queue="controller")
    assert "hello from the rack " * 5 in [m.text for m in remote.new_messages()]
    remote.close()


def _writer(link, name: str):
    """A remote writer on a new peer, its token seen by the bridge and the inputs flowing:
    (its session, its RemoteCommander)."""
    rig, bridge, peer = link
    s = peer()
    remote = RemoteBuffer(s, rig.name)
    cmd = RemoteCommander(remote, name)
    until(lambda: bridge.holder == name, "the bridge sees the writer's token")
    settle(rig, bridge, remote)
    return s, cmd


def _arm(cmd: RemoteCommander, rig, bridge) -> None:
    joints = len(rig.layout.joint_names)
    cmd.write_commands(joint_rate_rad_s=[0.0] * joints, current_limit_a=[1.0] * len(rig.layout.current_limit_names),
                       arm_request=1, rearm_counter=1)


def _deliver(rig, bridge, cmd_write, what: str) -> None:
    """One command write delivered to the bridge, then frames until it is written: one, or a
    new writer's first body SAFE_START_FRAMES more (the bridge's safe start comes first)."""
    before = bridge.applied
    cmd_write()
    until(lambda: bridge._pending is not None or bridge.applied > before, what)
    for _ in range(SAFE_START_FRAMES + 1):
        step(rig, bridge)
        if bridge.applied > before:
            break
    assert bridge.applied == before + 1, what


def test_a_remote_commander_drives_the_service_and_its_loss_trips_the_watchdog(link):
    rig, bridge, peer = link
    s, cmd = _writer(link, "ops-laptop")
    _deliver(rig, bridge, lambda: _arm(cmd, rig, bridge), "the arm request")
    rate = [0.0] * len(rig.layout.joint_names)
    rate[2] = 0.2
    for _ in range(3):
        _deliver(rig, bridge, lambda: cmd.write_commands(joint_rate_rad_s=rate), "a rate command")
    s_in = rig.reader.read_inputs()
    assert ServiceState(s_in.service_state) is ServiceState.ARMED
    dac = np.abs(s_in.dac_value).max()
    assert dac > 0.01  # the DAC follows the rate command

    # the remote commander's link is cut: nothing new reaches the bridge, no heartbeat
    s.close()
    frames = int(np.ceil(rig.svc.guard.watchdog_s * rig.svc.schedule.frame_rate_hz)) + 1
    step(rig, bridge, frames)  # the watchdog + one frame
    s_in = rig.reader.read_inputs()
    assert ServiceState(s_in.service_state) is ServiceState.FAULT and s_in.watchdog_tripped
    assert np.abs(s_in.dac_value).max() == 0.0

    # a writer back on a new link with the same arm request: nothing jumps (needs a re-arm)
    until(lambda: bridge.holder is None, "the lost writer's token gone")
    remote2 = RemoteBuffer(peer(), rig.name)
    cmd2 = RemoteCommander(remote2, "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the writer's token back")
    cmd2.write_commands(joint_rate_rad_s=rate, current_limit_a=[1.0] * len(rig.layout.current_limit_names),
                        arm_request=1, rearm_counter=1)
    until(lambda: bridge._pending is not None, "the old command again")
    step(rig, bridge, 3)
    s_in = rig.reader.read_inputs()
    assert ServiceState(s_in.service_state) is ServiceState.FAULT
    assert np.abs(s_in.dac_value).max() == 0.0


def test_a_new_remote_writer_carries_on_from_the_command_area_and_can_re_arm(link):
    """A writer taking over (a controller restarted elsewhere) starts from the area's record:
    its re-arm counter goes on from the one the service has used, so a re-arm is taken."""
    rig, bridge, peer = link
    s, cmd = _writer(link, "ops-laptop")
    zero = [0.0] * len(rig.layout.joint_names)
    _deliver(rig, bridge, lambda: _arm(cmd, rig, bridge), "the arm request")
    for _ in range(3):
        _deliver(rig, bridge, lambda: cmd.write_commands(joint_rate_rad_s=zero), "a heartbeat")
    assert ServiceState(rig.reader.read_inputs().service_state) is ServiceState.ARMED
    s.close()  # the writer is lost: the watchdog trips
    step(rig, bridge, int(np.ceil(rig.svc.guard.watchdog_s * rig.svc.schedule.frame_rate_hz)) + 2)
    assert ServiceState(rig.reader.read_inputs().service_state) is ServiceState.FAULT
    until(lambda: bridge.holder is None, "the lost writer's token gone")

    remote2 = RemoteBuffer(peer(), rig.name)
    step(rig, bridge)
    cmd2 = RemoteCommander(remote2, "ops-laptop-2")
    assert int(cmd2.command["rearm_counter"]) == 1  # the area's, not zero
    until(lambda: bridge.holder == "ops-laptop-2", "the new writer's token")
    counter = int(cmd2.command["rearm_counter"]) + 1
    _deliver(rig, bridge, lambda: cmd2.write_commands(joint_rate_rad_s=zero, arm_request=1, rearm_counter=counter),
             "the re-arm")
    for _ in range(3):
        _deliver(rig, bridge, lambda: cmd2.write_commands(joint_rate_rad_s=zero), "a heartbeat")
    assert ServiceState(rig.reader.read_inputs().service_state) is ServiceState.ARMED


def test_a_second_remote_writer_is_refused_naming_the_first(link):
    rig, bridge, peer = link
    first = RemoteCommander(RemoteBuffer(peer(), rig.name), "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the first writer's token")
    with pytest.raises(OwnershipError, match="held by remote writer 'ops-laptop'"):
        RemoteCommander(RemoteBuffer(peer(), rig.name), "intruder")
    first.close()


def test_the_bridge_writes_only_the_holders_commands(link):
    """Two writers that both got past the check (a race): the bridge writes only the
    first token's bodies and says once whose it refused."""
    rig, bridge, peer = link
    a = RemoteCommander(RemoteBuffer(peer(), rig.name), "first")
    until(lambda: bridge.holder == "first", "the first writer's token")
    b_remote = RemoteBuffer(peer(), rig.name)
    b = RemoteCommander.__new__(RemoteCommander)  # skips the token check: the race
    b.remote, b.owner, b.ident, b._heartbeat = b_remote, "second", "second~0badcafe", 0
    b._token = b_remote.session.liveliness().declare_token(f"pfma/{rig.name}/writer/commands/{b.ident}")
    b._pub = b_remote.session.declare_publisher(f"pfma/{rig.name}/commands/set")
    b.raw = bytearray(a.raw)
    b.command = np.ndarray((), a.command.dtype, buffer=b.raw)
    until(lambda: len(bridge.writers) == 2, "both tokens")
    b.write_commands(arm_request=1, rearm_counter=5)
    until(lambda: bridge._pending is not None, "the second writer's body")
    step(rig, bridge)
    assert bridge.applied == 0 and bridge.refused == {"second": 1}
    texts = [m.text for m in rig.reader.messages(queue="controller")]
    assert any("commands from 'second' refused" in t and "'first'" in t for t in texts)
    a.close()
    b.close()


def _arm_at(rig, bridge, cmd: RemoteCommander, frame: int, counter: int) -> None:
    """``cmd`` arms the service (0 rates, 1 A limits) at ``controller_frame`` ``frame``, then
    one heartbeat at ``frame + 1``; ARMED after."""
    zero = [0.0] * len(rig.layout.joint_names)
    limits = [1.0] * len(rig.layout.current_limit_names)
    _deliver(rig, bridge, lambda: cmd.write_commands(joint_rate_rad_s=zero, current_limit_a=limits, arm_request=1,
                                                     rearm_counter=counter, controller_frame=frame), "the arm request")
    _deliver(rig, bridge, lambda: cmd.write_commands(controller_frame=frame + 1), "a heartbeat")
    assert ServiceState(rig.reader.read_inputs().service_state) is ServiceState.ARMED


def _rearms_as_one_writer(rig, bridge, cmd: RemoteCommander, frame: int) -> None:
    """A new writer ``cmd`` re-arms from ``frame`` (its next rearm counter) and beats three
    times: ARMED, and the service never said "two writers"."""
    _arm_at(rig, bridge, cmd, frame, int(cmd.command["rearm_counter"]) + 1)
    for f in (frame + 2, frame + 3):
        _deliver(rig, bridge, lambda: cmd.write_commands(controller_frame=f), "a heartbeat")
    said = [m.text for m in rig.reader.messages(queue="service")]
    assert not [t for t in said if "two writers" in t], said
    assert ServiceState(rig.reader.read_inputs().service_state) is ServiceState.ARMED


@pytest.mark.parametrize("second", ["ops-laptop", "ops-laptop-2"])
def test_a_new_remote_writer_whose_first_bodies_were_lost_is_not_a_second_writer(link, second):
    """The service's claim check (ioservice/commandcheck.py) takes a step back of
    ``controller_frame`` to a smaller non-zero value for a second writer; a step back to 0 is a
    Data Acquisition layer started again. A remote controller's first bodies can be lost before
    its token reaches the bridge (its frame 0 among them), so its first body applied says frame
    5 after the last writer's 300: the bridge writes the safe start (0 rates, no arm request,
    ``controller_frame`` 0) when a new writer's first body comes, and the new writer arms
    (the kill matrix's bridge trial once failed on "command foreign writer" here). A writer
    started again under the same name (the bench's far end) is a new writer too, and the last
    body of the writer before it, still at the bridge when its token went, is never written
    for it (the bench once saw "controller_frame 1 after 507" so)."""
    rig, bridge, peer = link
    s, cmd = _writer(link, "ops-laptop")
    _arm_at(rig, bridge, cmd, 299, 1)
    cmd.write_commands(controller_frame=301)  # its last word, at the bridge, not written yet
    until(lambda: bridge._pending is not None, "the lost writer's last body at the bridge")
    s.close()
    until(lambda: bridge.holder is None, "the lost writer's token gone")
    step(rig, bridge, int(np.ceil(rig.svc.guard.watchdog_s * rig.svc.schedule.frame_rate_hz)) + 2)

    cmd2 = RemoteCommander(RemoteBuffer(peer(), rig.name), second)
    until(lambda: bridge.holder == second, "the new writer's token")
    applied = bridge.applied
    step(rig, bridge, SAFE_START_FRAMES + 2)
    assert bridge.applied == applied and bridge._pending is None  # the lost writer's body: never written
    _rearms_as_one_writer(rig, bridge, cmd2, 5)


def test_a_body_that_comes_after_its_writers_token_went_is_never_the_next_writers(link):
    """Zenoh may deliver a writer's token withdrawal before its last body. The kill matrix's
    far end, stopped and started again under the same name, met it: the late body came under
    the new writer's token and was written for it, and the service saw "two writers on the
    claim: controller_frame 4 after 1046" and refused the new writer's arming. Each writer's
    token and bodies carry a nonce of its own (``RemoteCommander.ident``), so the late body
    is never written: the new writer arms, and nobody is taken for a second writer."""
    rig, bridge, peer = link
    _s, cmd = _writer(link, "ops-laptop")
    _arm_at(rig, bridge, cmd, 1045, 1)
    cmd._token.undeclare()  # the token goes first ...
    until(lambda: bridge.holder is None, "the writer's token gone")
    step(rig, bridge, int(np.ceil(rig.svc.guard.watchdog_s * rig.svc.schedule.frame_rate_hz)) + 2)
    cmd2 = RemoteCommander(RemoteBuffer(peer(), rig.name), "ops-laptop")
    until(lambda: bridge.holder == "ops-laptop", "the new writer's token")
    assert cmd2.ident != cmd.ident
    applied = bridge.applied
    cmd.write_commands(controller_frame=1047)  # ... and its last body after, under the new token
    until(lambda: bridge._pending is not None, "the late body at the bridge")
    step(rig, bridge, SAFE_START_FRAMES + 2)
    assert bridge.applied == applied and bridge._pending is None  # never written
    _rearms_as_one_writer(rig, bridge, cmd2, 4)
    assert bridge.refusals.total == {"command bodies under the holder's name from another writer (an earlier "
                                     "writer's last word after its token went, or a forger)": 1}
