"""Child-process bodies for the cross-process Bit3 tests (spawned, so module-level)."""

from __future__ import annotations

import os
import time

import numpy as np

from ioservice.client import Client
from ioservice.shm import Bit3Buffer


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
