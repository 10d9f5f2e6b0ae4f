"""The world model's user-request ring: asynchronous, keyed user-interface writes.

A user write (:meth:`WorldModel.set_user`, ``pfma wm set``) is checked at once, then goes
through a small ring of request slots in the segment (any attachment may submit; an OFD
byte lock orders submitting processes). The owner applies pending requests, after
checking all of it again, at its next communications segment, and writes each one's
result into its slot (``pfma wm requests``).
"""

from __future__ import annotations

import hmac
import os
import struct
import time
from dataclasses import dataclass
from typing import Any

from bit3.buffer import lock_byte
from controller.worldmodel.segment import (
    APPLIED, FREE, HEADER_FIELDS, PENDING, REQUEST_SLOTS, SLOT_FIELDS, SLOT_HEADER, STATE_NAMES, WRITING,
)
from controller.worldmodel.spec import VarSpec, WorldModelError, WorldModelValueError, coerce


@dataclass(frozen=True)
class UserRequest:
    """One entry of the user-request ring (``pfma wm requests``)."""

    req_id: int
    state: str
    variable: str
    user: str
    pid: int
    submit_ns: int
    applied_frame: int
    result: str


class UserRequestRing:
    """The request-ring half of :class:`~controller.worldmodel.model.WorldModel` (a mixin:
    it uses the model's segment views, variable table, key and power state)."""

    def _slot(self, k: int) -> memoryview:
        n = self._lay.req_slot_size
        return self._req[k * n:(k + 1) * n]

    def _slot_get(self, k: int, fld: str):
        off, fmt = SLOT_FIELDS[fld]
        return struct.unpack_from("<" + fmt, self._req, k * self._lay.req_slot_size + off)[0]

    def _slot_state(self, k: int) -> memoryview:
        off = k * self._lay.req_slot_size
        return self._req[off:off + 4].cast("I")  # one aligned 4-byte store/load

    def set_user(self, name: str, value: Any, key: str | None, *, user: str | None = None) -> int:
        """Asynchronous user-interface write (``pfma wm set``): checked now, applied by the
        owner at its next communications segment. Returns the request id.

        :raises WorldModelError: unknown variable, not user-settable (a task's output, a layer
            command, a status ...: names the owner), protected while powered up, wrong key,
            request ring full, owner not running
        :raises WorldModelValueError: the value does not fit the variable
        """
        s = self.check_user_settable(name)
        if not self.check_key(key):
            raise WorldModelError(f"world-model variable {name!r}: wrong or missing access key; "
                                  f"user writes need the model's access key")
        raw = coerce(s, value).tobytes()
        if self.readonly:
            info = self.info()
            if not info.owner_alive:
                raise WorldModelError(f"world model {self.name!r}: its owner {info.owner!r} (pid "
                                      f"{info.owner_pid}) is not running; nobody would apply the write")
        return self._submit(self._index[name], raw, self._key_hash(key), user)

    def check_user_settable(self, name: str) -> VarSpec:
        """The variable's spec if a user may set it now (its ``user`` declaration and the
        power state; the key is not checked). Refusals hold with or without the key.

        :raises WorldModelError: unknown variable, or why not (names the owner)
        """
        s = self.spec(name)
        why = s.user_refusal(self.powered_up) or self._section_refusal(self._index[name])
        if why is not None:
            raise WorldModelError(why)
        return s

    def _submit(self, i: int, raw: bytes, key_hash: bytes, user: str | None) -> int:
        with self._req_tlock:
            self._lock_ring(True)
            try:
                nxt = self._words["req_next_id"]
                rid = nxt[0] + 1
                k = (rid - 1) % REQUEST_SLOTS
                st = self._slot_state(k)
                try:
                    # a WRITING slot seen while holding the lock was abandoned by a
                    # submitter that died mid-write (writers hold the lock): reuse it
                    if st[0] == PENDING:
                        raise WorldModelError(
                            f"world model {self.name or 'private'}: user request queue full "
                            f"({REQUEST_SLOTS} pending); the owner applies them at each "
                            f"communications segment - is it running?")
                    st[0] = WRITING
                    base = k * self._lay.req_slot_size
                    for fld, v in (("var_index", i), ("req_id", rid), ("submit_ns", time.time_ns()),
                                   ("pid", os.getpid()), ("nbytes", len(raw)), ("applied_frame", 0),
                                   ("key_hash", key_hash),
                                   ("user", (user or _login()).encode()[:24]),
                                   ("result", b"")):
                        off, fmt = SLOT_FIELDS[fld]
                        struct.pack_into("<" + fmt, self._req, base + off, v)
                    self._req[base + SLOT_HEADER:base + SLOT_HEADER + len(raw)] = raw
                    st[0] = PENDING  # last: the owner takes only complete entries
                finally:
                    st.release()
                nxt[0] = rid
                return rid
            finally:
                self._lock_ring(False)

    def _lock_ring(self, lock: bool) -> None:
        """Exclusive access to the ring among submitting processes (OFD byte lock)."""
        if self._fd < 0:
            return
        idx = HEADER_FIELDS["lock_byte"][0]
        if not lock:
            lock_byte(self._fd, idx, False)
            return
        deadline = time.monotonic() + 1.0
        while True:
            try:
                lock_byte(self._fd, idx, True)
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise WorldModelError(f"world model {self.name!r}: user request queue is "
                                          f"locked by another process for over 1 s") from None
                os.sched_yield()

    def _pending_requests(self) -> list[tuple[int, int, int, bytes]]:
        """(request id, slot, variable index, value bytes) of every pending request, oldest first."""
        out = []
        words, step = self._req_words, self._req_step  # each slot's state word, one view
        for k in range(REQUEST_SLOTS):
            if words[k * step] != PENDING:
                continue
            i = self._slot_get(k, "var_index")
            n = self._slot_get(k, "nbytes")
            base = k * self._lay.req_slot_size + SLOT_HEADER
            out.append((self._slot_get(k, "req_id"), k, i, bytes(self._req[base:base + n])))
        out.sort()  # oldest first
        return out

    def _check_request(self, k: int, i: int, raw: bytes) -> tuple[bool, str]:
        """Re-check a request at apply time: the ring is shared memory any process can write
        (so who may set the variable is checked again), and the power state or key may have
        changed since it was queued."""
        if not 0 <= i < len(self._specs):
            return False, f"unknown variable index {i}"
        s = self._specs[i]
        why = s.user_refusal(self.powered_up) or self._section_refusal(i)
        if why is not None:
            return False, why
        if len(raw) != s.nbytes:
            return False, f"{s.name}: {len(raw)} bytes given, {s.nbytes} expected"
        o = HEADER_FIELDS["key_hash"][0]
        if not hmac.compare_digest(self._slot_get(k, "key_hash"), bytes(self._root[o:o + 32])):
            return False, f"{s.name}: wrong access key"
        try:
            coerce(s, self._decode_value(i, raw))
        except WorldModelValueError as err:
            return False, str(err)
        return True, ""

    def _finish_request(self, k: int, state: int, frame: int, msg: str) -> None:
        base = k * self._lay.req_slot_size
        off, _ = SLOT_FIELDS["applied_frame"]
        struct.pack_into("<Q", self._req, base + off, frame)
        off, _ = SLOT_FIELDS["result"]
        struct.pack_into("<96s", self._req, base + off, msg.encode()[:96])
        st = self._slot_state(k)
        st[0] = state
        st.release()
        w = self._words["user_applied" if state == APPLIED else "user_rejected"]
        w[0] = w[0] + 1
        self._stats["user_applied" if state == APPLIED else "user_rejected"] += 1

    def request(self, req_id: int) -> UserRequest | None:
        """The ring entry of request ``req_id`` (None once its slot was reused)."""
        for r in self.requests():
            if r.req_id == req_id:
                return r
        return None

    def requests(self) -> list[UserRequest]:
        """Every used slot of the request ring, oldest first."""
        out = []
        for k in range(REQUEST_SLOTS):
            st = self._slot_get(k, "state")
            rid = self._slot_get(k, "req_id")
            if st == FREE or rid == 0:
                continue
            i = self._slot_get(k, "var_index")
            var = self._specs[i].name if 0 <= i < len(self._specs) else f"#{i}"
            out.append(UserRequest(
                rid, STATE_NAMES.get(st, str(st)), var,
                self._slot_get(k, "user").rstrip(b"\0").decode(errors="replace"),
                self._slot_get(k, "pid"), self._slot_get(k, "submit_ns"),
                self._slot_get(k, "applied_frame"),
                self._slot_get(k, "result").rstrip(b"\0").decode(errors="replace")))
        return sorted(out, key=lambda r: r.req_id)

    def user_requests_pending(self) -> int:
        return sum(1 for k in range(REQUEST_SLOTS) if self._slot_get(k, "state") == PENDING)


def _login() -> str:
    try:
        import getpass
        return getpass.getuser()
    except Exception:  # no USER and no passwd entry (containers)
        return f"uid{os.getuid()}"
