"""Two writers on one claim: a command stream that goes backwards or repeats with new content.

The claim check (``IoService._fetch_command``) compares the pid and token stamped in a
command body with the header's owner slot. Anyone who can map the segment writable can
copy both (they are in the header and in every body), so it alone cannot tell the claim
holder from a forger running as the same user (issue 28 item 6). This check looks at the
stream of bodies that pass it. One writer through ``bit3.client.Client`` (the controller,
the bridge, checkout, calibration, the Modbus export, the demo) keeps three things
consistent; a second writer whose counters do not line up with the holder's breaks at least
one of them as soon as the service has read a body of each:

- **sequence and heartbeat move together.** Every publish bumps the area's sequence counter
  by 2 (``bit3.seqlock``; each writer keeps its *own* copy of the counter) and the body's
  ``heartbeat`` by 1 (``Client.publish_commands``, keep-alives included). Between two
  bodies the service reads, ``heartbeat`` must have moved by exactly half the sequence
  step: a sequence number that goes backwards, a heartbeat that goes backwards or repeats
  in a new publish, or a heartbeat that jumps further than the publishes in between, is a
  second writer.
- **the same sequence number means the same body.** A body whose bytes changed while the
  sequence number did not (two writers' counters met, or bytes written around the lock) is
  a second writer.
- **controller_frame never goes backwards.** A writer that stamps its own frame counter
  (the controller's Data Acquisition layer) counts up; one that never passes it (open-loop
  tools) leaves it at 0. A step back to a smaller non-zero value is a second writer.
  Assumption (named once here and in docs/safety.md): a step back to **0** is allowed (a
  Data Acquisition layer started again on the same claim writes ``controller_frame=0``
  first, its safe command); the two checks above still see such a writer.

A new pid or token (a new claim: the controller restarted) starts the tracking afresh.

What happens then (``IoService._task_dac``): the frame that sees it refuses the command
through the guard (ARMED -> SAFE, 0 V, one message "two writers on the claim of pid P:
heartbeat 1203 after 1207 (seq +2)", ``foreign_writes`` + 1, ``fault_code`` FOREIGN), and
for :data:`TWO_WRITER_HOLD_S` after the last sign of a second writer an arm request is
refused with the same words (so a forger still writing cannot be re-armed past). After that
an explicit re-arm (a new ``rearm_counter``, rates at zero) arms again.

What it cannot see: a second writer whose bodies the service reads only ever in place of the
holder's, continuing the holder's sequence and heartbeat: one that overwrites every holder
body before the service reads it (in place, or through the lock with the next numbers), or
one that writes while the holder writes nothing (stopped with SIGSTOP by the same user, or
between a dead holder and its lock's release). One stream, one writer as far as the bytes
tell; the boundary is the service's user (docs/safety.md, "Trust boundary").

Cost: a few integer comparisons per good read and a ~200-byte compare and copy; no numpy.
"""

from __future__ import annotations

__all__ = ["ClaimStreamCheck", "TWO_WRITER_HOLD_S"]

#: after the last sign of two writers on the claim, arm requests are refused this long
#: (assumption: long enough that a forger still writing at any rate above 1 Hz is seen again
#: before the holder can re-arm; short enough not to annoy an operator who stopped it)
TWO_WRITER_HOLD_S = 1.0


class ClaimStreamCheck:
    """Watches the command bodies that passed the claim check for a second writer.

    :param raw: the reader's body bytes (``AreaReader.raw``; refreshed in place by each read)
    :param hold_frames: frames an arm request stays refused after the last detection
    """

    def __init__(self, raw: bytearray, hold_frames: int) -> None:
        self._raw = raw
        self._prev = bytearray(len(raw))
        self.hold_frames = hold_frames
        self._pid = 0
        self._token = 0
        self._seq = -1  # sequence number of the last body noted (-1: none since the claim)
        self._hb = 0
        self._cf = 0
        self.detections = 0  #: signs of a second writer seen (each inconsistent step)
        self.reason = ""  #: the last detection's words
        self._new = False  # a detection the next frame has not consumed yet
        self._until = -1  # frame index up to which the refusal holds

    def note(self, pid: int, token: int, seq: int, hb: int, cf: int) -> bool:
        """A good read of a body carrying the owner's ``pid`` and ``token`` at sequence ``seq``
        with ``heartbeat`` ``hb`` and ``controller_frame`` ``cf``. Returns True when it shows
        a second writer (recorded for :meth:`frame`)."""
        if seq == self._seq and pid == self._pid and token == self._token:
            if self._raw == self._prev:
                return False  # the same publish read again (a frame with no new write)
            why = f"body changed at the same seq {seq}"
        elif pid != self._pid or token != self._token or self._seq < 0:
            self._pid, self._token = pid, token  # a new claim: a new stream
            self._remember(seq, hb, cf)
            return False
        else:
            dseq = seq - self._seq
            dhb = hb - self._hb
            if dseq < 0:
                why = f"seq {seq} after {self._seq}"
            elif dhb * 2 != dseq:
                if dhb <= 0:
                    why = f"heartbeat {hb} after {self._hb} (seq +{dseq})"
                else:
                    why = f"heartbeat +{dhb} in {dseq // 2} publishes"
            elif cf < self._cf and cf != 0:
                why = f"controller_frame {cf} after {self._cf}"
            else:
                self._remember(seq, hb, cf)
                return False
        self._remember(seq, hb, cf)
        self.detections += 1
        self.reason = f"two writers on the claim of pid {pid}: {why}"
        self._new = True
        return True

    def _remember(self, seq: int, hb: int, cf: int) -> None:
        self._seq, self._hb, self._cf = seq, hb, cf
        self._prev[:] = self._raw

    def frame(self, k: int) -> tuple[bool, str | None]:
        """Once per service frame ``k``: (a detection since the last frame, the refusal text
        while the hold lasts or None)."""
        new = self._new
        if new:
            self._new = False
            self._until = k + self.hold_frames
        if k <= self._until:
            return new, self.reason
        return False, None
