"""Child-process bodies for the cross-process Bit3 tests (spawned, so module-level)."""

from __future__ import annotations

import os
import time

import numpy as np

from bit3.client import Client
from bit3.buffer import Bit3Buffer


def flat_out_writer(name: str, started, stop, max_s: float, result) -> None:
    """Publish self-consistent inputs frames as fast as possible: every 8-byte word = frame."""
    buf = Bit3Buffer.attach(name, readonly=False)
    buf.claim("service", "fuzz-writer")
    w = buf.writer("inputs")
    words = np.frombuffer(w.raw, np.uint64)
    n = 0
    t_end = time.monotonic() + max_s  # bound: never outlive the test
    while not stop.is_set() and time.monotonic() < t_end:
        for _ in range(200):
            n += 1
            words[:] = n
            w.publish()
        if n == 200:
            started.set()
    result.put(n)
    buf.close()


def controller_round_trip(name: str, conn) -> None:
    """Read the service's inputs, write commands + a message, hold the claim until told."""
    with Client.attach(name) as reader:
        snap = reader.read_inputs()
        conn.send(("inputs", snap.frame, snap.shoulder_pitch_angle))
    ctl = Client.attach(name, writer="commands", owner="child-ctl")
    hb = ctl.write_commands(joint_rate_rad_s=[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], arm_request=1,
                            elbow_pitch_command=-0.25, gripper_current_limit=1.5)
    seq = ctl.post_message("hello from the controller", code=7)
    conn.send(("written", hb, seq, os.getpid()))
    if conn.poll(20.0):  # parent checks the claim, then says bye
        conn.recv()
    ctl.close()
    conn.send(("closed",))


def die_holding_claim(name: str, mid_write: bool) -> None:
    """Claim the controller role and exit without releasing (optionally mid-write)."""
    buf = Bit3Buffer.attach(name, readonly=False)
    buf.claim("commands", "doomed-ctl")
    w = buf.writer("commands")
    w.record["arm_request"] = 1
    w.publish()
    if mid_write:
        buf.lock("commands").begin()  # counter left odd, as if killed inside a write
    os._exit(0)


def hold_service_claim(name: str, layout_hash: bytes, conn) -> None:
    """Claim the service role of a buffer whose layout hash is ``layout_hash`` (another
    rack's), report the pid, hold the claim until told, then die without releasing."""
    from dataclasses import replace

    from bit3.layout import default_layout
    buf = Bit3Buffer.attach(name, readonly=False, layout=replace(default_layout(), hash=layout_hash))
    buf.claim("service", "other-rack-serve")
    conn.send(os.getpid())
    if conn.poll(60.0):
        conn.recv()
    os._exit(0)


def ring_reader_across_replacement(name: str, layout_hash: bytes, conn) -> None:
    """Map a frame ring, let the parent replace it, then touch every page of the old
    mapping (SIGBUS if the file was truncated under it), notice the replacement and
    attach the new ring."""
    from bit3.ring import FrameRing
    r = FrameRing.attach(name, layout_hash)
    conn.send(("attached", r.count(), r.replaced()))
    conn.recv()  # the parent has created a new ring at the same path
    whole = bytes(r._mm[:])
    last = r.read(r.count() - 1)
    replaced = r.replaced()
    new = FrameRing.attach(name, layout_hash)
    conn.send(("after", len(whole), r.count(), bytes(last), replaced, new.n_slots, new.count(),
               bytes(new.read(0)), new.replaced()))
    new.close()
    r.close()
