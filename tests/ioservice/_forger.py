"""A forger of the command area: a second process (or object) running as the service's
user, mapping the segment writable and writing bodies that carry the claim holder's pid and
token, copied from the header's owner slot (issue 28 item 6's reproduction).

Modes of one forged write:

- ``"own"``: its own sequence counter (a seqlock writer from its own attachment, as
  ``Bit3Buffer.lock(...).write`` gives) and its own heartbeat, starting from the body it
  first copied: a forger writing at its own pace.
- ``"follow"``: continues the shared counters (sequence taken over, heartbeat = the
  body's + 1) before each write: a forger imitating the holder's stream.
- ``"inplace"``: rewrites the published body's bytes (the holder's heartbeat and all)
  without touching the sequence counter: what the service cannot tell from the holder.
"""

from __future__ import annotations

from bit3.buffer import Bit3Buffer


class Forger:
    def __init__(self, name: str, layout=None) -> None:
        self.buf = Bit3Buffer.attach(name, readonly=False, layout=layout)
        self.lock = self.buf.lock("commands")
        self.reader = self.buf.reader("commands")
        self._hb: int | None = None
        self.writes = 0

    def forge(self, mode: str, rate: float) -> None:
        pid, token = self.buf.owner_pid_token("commands")
        self.reader.read()
        body = self.reader.record.copy()
        body["joint_rate_rad_s"][0] = rate
        body["writer_pid"] = pid
        body["writer_token"] = token
        body["inputs_frame"] = self.buf.header().frame  # fresh, as the service wants it
        if mode == "inplace":
            self.lock._body[:] = memoryview(body.tobytes())
        elif mode == "follow":
            body["heartbeat"] = int(body["heartbeat"]) + 1
            self.lock.take_over()
            self.lock.write(memoryview(body.tobytes()))
        else:
            self._hb = int(body["heartbeat"]) + 1 if self._hb is None else self._hb + 1
            body["heartbeat"] = self._hb
            self.lock.write(memoryview(body.tobytes()))
        self.writes += 1

    def close(self) -> None:
        self.reader = None
        self.lock = None
        self.buf.close()


def forger_process(name: str, conn) -> None:
    """Child process body: attach, then one forged write per ("forge", mode, rate) request,
    answered ("ok", pid); ("bye",) ends it."""
    import os
    f = Forger(name)
    try:
        while conn.poll(30.0):  # bound: never outlive a test that forgot to say bye
            msg = conn.recv()
            if msg[0] != "forge":
                break
            f.forge(msg[1], msg[2])
            conn.send(("ok", os.getpid()))
    finally:
        f.close()
