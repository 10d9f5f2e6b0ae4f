"""Bit3Buffer.owner_alive: is a buffer's service alive, whatever the buffer's layout?

Decided by the OFD byte lock a live service holds (Bit3Buffer.claim), not by the pid in
the owner record, which a dead service leaves behind and the system may give to another
process.
"""

import os
from dataclasses import replace

import pytest

from bit3.layout import default_layout
from bit3.buffer import Bit3Buffer, open_shm
from tests.bit3 import _workers


def test_missing_and_foreign_segments_are_not_alive(shm_name):
    alive, why = Bit3Buffer.owner_alive(shm_name)
    assert not alive and "no buffer" in why
    shm = open_shm(shm_name, create=True, size=4096)
    try:
        shm.buf[:8] = b"NOTBIT3!"
        alive, why = Bit3Buffer.owner_alive(shm_name)
        assert not alive and "not a Bit3 buffer" in why
    finally:
        shm.close()


def test_a_live_pid_without_the_lock_is_not_alive_and_the_lock_is(buf, shm_name):
    # a record naming a running process (ours) that holds no lock: a recycled pid
    buf._write_owner(buf.layout.area("inputs").index, os.getpid(), b"ghost", 0)
    alive, why = Bit3Buffer.owner_alive(shm_name)
    assert not alive and "'ghost'" in why and str(os.getpid()) in why
    buf._release_area("inputs")
    buf.claim("service", "svc")
    alive, why = Bit3Buffer.owner_alive(shm_name)
    assert alive and "'svc'" in why and f"pid {os.getpid()}" in why
    buf.release()
    alive, why = Bit3Buffer.owner_alive(shm_name)
    assert not alive


@pytest.mark.realtime
def test_a_live_owner_of_another_layout_is_alive_and_a_dead_one_is_not(shm_name, mp):
    other = replace(default_layout(), hash=b"otherrk!")
    b = Bit3Buffer.create(shm_name, other)
    parent, child_end = mp.Pipe()
    child = mp.Process(target=_workers.hold_service_claim, args=(shm_name, b"otherrk!", child_end))
    child.start()
    try:
        assert parent.poll(60.0), "child did not claim"
        pid = parent.recv()
        alive, why = Bit3Buffer.owner_alive(shm_name)
        assert alive and "'other-rack-serve'" in why and f"pid {pid}" in why
        parent.send("die")
        child.join(60.0)
        assert child.exitcode == 0
        alive, why = Bit3Buffer.owner_alive(shm_name)
        assert not alive and f"pid {pid}" in why
        assert bytes(b.header().layout_hash) == b"otherrk!"  # only looked at
    finally:
        if child.is_alive():
            child.kill()
        b.close()
