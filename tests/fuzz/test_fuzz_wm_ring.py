"""The world model's user-request ring under arbitrary writes (issue 20 item 3).

The ring is shared memory any process that maps ``/dev/shm/NAME`` can write. Here a
hostile process writes forged requests with arbitrary fields (variable index, byte
count, value bytes, key hash, state word, request id) and plain random bytes anywhere in
the ring's slots, between the owner's communications segments. The owner never raises;
a variable users may not set is never changed; a user-settable variable only ever holds
a value its declaration accepts; every pending request is answered (applied, or rejected
with a message saying why); the listing of the ring never raises; and a good request made
after all that is applied (the ring is still usable).

Not repeated here: tests/controller/test_wm_ownership.py forges well-formed requests for
variables a user may not set; this test writes malformed ones and raw bytes.
"""

from __future__ import annotations

import hashlib
import mmap
import os
import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.worldmodel import (
    APPLIED, HEADER_FIELDS, PENDING, REJECTED, REQUEST_SLOTS, SLOT_FIELDS, SLOT_HEADER, WorldModel,
)
from controller.worldmodel.spec import WorldModelError, coerce
from tests.controller import _wm_support as sup
from tests.fuzz._mutate import FUZZ

KEY = "fuzz-key"
SPECS = sup.sample_specs()
USER_SETTABLE = [s for s in SPECS if s.user_refusal(powered_up=False) is None]

_forge = st.tuples(
    st.just("forge"),
    st.integers(0, REQUEST_SLOTS - 1),                       # slot
    st.sampled_from([PENDING, PENDING, PENDING, 0, 1, 3, 4, 7, 0xFFFFFFFF]),  # state word
    st.one_of(st.integers(0, len(SPECS) - 1), st.integers(0, 2**32 - 1)),  # variable index
    st.one_of(st.just(None), st.integers(0, 2**32 - 1)),      # byte count (None: the value's)
    st.binary(max_size=140),                                  # value bytes
    st.booleans(),                                            # the right key hash
)
_bytes = st.tuples(st.just("bytes"), st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=64))
_segment = st.tuples(st.just("segment"))
_op = st.one_of(_forge, _forge, _bytes, _segment)


def _values(wm: WorldModel) -> dict[str, bytes]:
    return {s.name: np.asarray(wm.get(s.name)).tobytes() for s in SPECS}


@settings(FUZZ, max_examples=150)
@given(st.lists(_op, min_size=1, max_size=12))
def test_forged_and_random_ring_entries_never_set_what_a_user_may_not_and_the_ring_stays_usable(ops):
    name = sup.unique_name()
    wm = WorldModel.create(SPECS, name=name, owner="fuzz-owner", access_key=KEY)
    fd = os.open(f"/dev/shm/{name}", os.O_RDWR)
    mm = mmap.mmap(fd, 0)
    os.close(fd)
    try:
        def hget(fld):
            off, fmt = HEADER_FIELDS[fld]
            return struct.unpack_from("<" + fmt, mm, off)[0]
        ring0, slot_size = hget("req_offset"), hget("req_slot_size")
        ring_len = REQUEST_SLOTS * slot_size
        good_hash = hashlib.sha256(hget("key_salt") + KEY.encode()).digest()
        before = _values(wm)

        def slot(k: int, fld: str):
            off, fmt = SLOT_FIELDS[fld]
            return struct.unpack_from("<" + fmt, mm, ring0 + k * slot_size + off)[0]

        def segment() -> None:
            """The owner's segment: every request pending before it is answered by it."""
            pending = [k for k in range(REQUEST_SLOTS) if slot(k, "state") == PENDING]
            wm.communications_segment()
            for k in pending:
                assert slot(k, "state") in (APPLIED, REJECTED), (k, slot(k, "state"))
                assert slot(k, "result").rstrip(b"\0"), f"slot {k} answered without a message"

        for op in ops:
            if op[0] == "forge":
                _, k, state, var, nbytes, raw, right_key = op
                base = ring0 + k * slot_size
                raw = raw[:slot_size - SLOT_HEADER]
                for fld, v in (("var_index", var), ("req_id", hget("req_next_id") + 1 + k),
                               ("pid", 4242), ("nbytes", len(raw) if nbytes is None else nbytes),
                               ("key_hash", good_hash if right_key else bytes(32)),
                               ("user", b"fuzzer"), ("result", b"")):
                    off, fmt = SLOT_FIELDS[fld]
                    struct.pack_into("<" + fmt, mm, base + off, v)
                mm[base + SLOT_HEADER:base + SLOT_HEADER + len(raw)] = raw
                struct.pack_into("<I", mm, base + SLOT_FIELDS["state"][0], state)
            elif op[0] == "bytes":
                _, at, junk = op
                i = ring0 + int(at * ring_len)
                junk = junk[:ring0 + ring_len - i]
                mm[i:i + len(junk)] = junk
            else:
                segment()
            wm.requests()  # the listing never raises, whatever the slots hold
        segment()
        assert wm.user_requests_pending() == 0
        after = _values(wm)
        for s in SPECS:
            if s not in USER_SETTABLE:
                assert after[s.name] == before[s.name], f"{s.name} changed by a forged request"
            else:
                coerce(s, wm.get(s.name))  # a value its declaration accepts
        # the ring still works for a good request
        spec = USER_SETTABLE[-1]
        value = not bool(wm.get(spec.name)) if spec.dtype == "b1" else np.full(spec.shape, 3.5)
        try:
            rid = wm.set_user(spec.name, value, KEY)
        except WorldModelError as err:
            raise AssertionError(f"a good request refused after the fuzzing: {err}") from None
        wm.communications_segment()
        r = wm.request(rid)
        assert r is not None and r.state == "applied", r
        assert np.array_equal(np.asarray(wm.get(spec.name)), np.asarray(value))
    finally:
        mm.close()
        wm.close()
        WorldModel.remove_segment(name)
