"""The capture thread: every inputs publish (or every frame of the service's frame ring)
copied into a queue the recorder's writing thread empties."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from bit3.client import Client, Snapshot

if TYPE_CHECKING:
    from tools.recording.writer import Recorder

#: idle polls of the capture thread between two looks whether its frame ring was replaced
#: (one ``stat``; about every 10 ms while no frame comes without a ring, every 0.5 s with one)
RING_CHECK_POLLS = 50
#: sleep between polls without a frame ring: the single inputs area keeps only the newest
#: frame, so every publish must be caught (a 1 kHz frame is 1 ms)
AREA_POLL_S = 0.0002
#: sleep between polls of the frame ring: the ring keeps n_slots - 1 frames (255: 0.8 s at
#: 320 Hz), so a poll every 10 ms loses nothing and wakes the process ~100 times a second
#: instead of ~5000 (measured: the recorder's CPU is mostly its wake-ups; docs/deployment.md)
RING_POLL_S = 0.01
#: the message queues' bodies are copied at most this often (only when their head moved):
#: the service's queue keeps its last 50 entries and the controller's 127, and a power-up
#: posts ~130 controller entries in half a second, a trip ~40 in one frame (measured in
#: simulated time, ``bit3.layout.CONTROLLER_QUEUE_LEN``), so the recorder's writing
#: thread, which may spend tens of ms on a backlog of frames, must not be the one to read them
MESSAGES_POLL_S = 0.005
#: the queues, by the names the recorder writes (``/pfma/messages`` ``queue``)
MESSAGE_QUEUES = ("service", "controller")
#: SCHED_FIFO priority of the capture thread where real-time is permitted: below the
#: service (50) and the controller (49), above every time-shared process (the console, the
#: bridge). The soak showed why (stop 36): a time-shared recorder beside a busy console
#: was descheduled long enough for a trip's and recovery's ~100 entries to wrap a queue.
CAPTURE_FIFO_PRIORITY = 10


@dataclass(frozen=True)
class RingSwitch:
    """Queued by :class:`InputsCapture` between the last frame of a replaced ring and the
    first of the new one; :meth:`InputsCapture.drain` stops there and sets ``replaced_note``."""

    note: str


@dataclass(frozen=True)
class MessagesCopy:
    """Queued by :class:`InputsCapture` (``messages=True``) when a message queue's head
    moved: a consistent copy of its body, decoded by the writing thread
    (``Recorder.feed_messages``) in order with the frames around it."""

    queue: str  #: "service" or "controller"
    body: np.ndarray


class InputsCapture:
    """Copies every inputs publish into a queue from its own thread, so the recorder's
    slow moments (closing and compressing a chunk, flushing the file, encoding JSON; 2-4
    ms measured) no longer make it miss a 3.125 ms frame. With the service's frame ring
    (``bit3.ring``) it reads the ring instead and may itself be descheduled for up
    to n_slots - 1 frames without a loss. The writing thread empties the
    queue with :meth:`drain`. Run the process with a short GIL switch interval
    (``sys.setswitchinterval(0.0005)``) so this thread gets in while the other one works.

    :param client: the recorder's read-only client (this thread is the only one that
        reads its inputs area)
    :param poll_s: sleep between polls when nothing new was published (default
        :data:`RING_POLL_S` with a ring, :data:`AREA_POLL_S` without)
    :param max_queue: snapshots held at most (about 2.6 s at 320 Hz); beyond it the newest
        are not queued, and the recorder counts them as missed

    A restarted service replaces the ring file (``bit3.ring``): the thread notices it
    (:meth:`check_ring`), takes what the old ring still holds, attaches the new ring and
    reads it from its first frame. The switch is a :class:`RingSwitch` in the queue:
    :meth:`drain` stops there and sets :attr:`replaced_note`, so the recorder can start
    the new session (``Recorder.attach`` with the new service's client) before the new
    ring's frames.

    With ``messages=True`` the thread also copies the two message queues when their head
    moved (:class:`MessagesCopy`, at most every :data:`MESSAGES_POLL_S`): the bounded
    queues are then read as promptly as the frames, not after the writing thread has
    worked off a backlog. After a ring switch it copies none until :meth:`messages_from`
    names the new service's client.
    """

    def __init__(self, client: Client, poll_s: float | None = None, max_queue: int = 8192,
                 ring=None, messages: bool = False, realtime: bool | None = False) -> None:
        self.client = client
        self.poll_s = poll_s if poll_s is not None else (AREA_POLL_S if ring is None else RING_POLL_S)
        self.max_queue = max_queue
        #: an attached ``bit3.ring.FrameRing`` of the same layout: frames are taken
        #: from it (up to n_slots - 1 behind) instead of from the single inputs area;
        #: the capture owns it (``stop`` closes it)
        self.ring = ring
        self._inputs_dtype = client.layout.area("inputs").body_dtype
        self.ring_lost = 0  #: frames overwritten in the ring before this thread read them
        self._ring_k: int | None = None  # next ring frame to take
        self.ring_reattached = 0  #: replaced rings this capture moved on from
        #: set by :meth:`drain` when it reached a ring switch (the caller clears it)
        self.replaced_note: str | None = None
        self.queue: deque = deque()
        #: copy the message queues (None: not now; see :meth:`messages_from`)
        self._msg_client: Client | None = client if messages else None
        self._msg_heads: dict[str, int] = {}
        self._msg_next = 0.0  # monotonic time of the next look at the message queues
        #: the thread's real-time set-up (``ioservice.loop.realtime_start``'s flag: None is
        #: "where permitted", False none) and what it said (:meth:`start` waits for it)
        self.realtime = realtime
        self.realtime_lines: list[str] = []
        self._set_up = threading.Event()
        self.error: BaseException | None = None  #: what stopped the thread (e.g. SeqLockTimeout)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pfma-record-capture", daemon=True)

    def start(self) -> "InputsCapture":
        self._thread.start()
        self._set_up.wait(2.0)
        return self

    def _run(self) -> None:
        c, q, sleep, stop = self.client, self.queue, time.sleep, self._stop
        try:
            if self.realtime is not False:  # this thread only (Linux: policy is per thread)
                from ioservice.loop import realtime_start
                self.realtime_lines = realtime_start("pfma record: capture thread", self.realtime, None,
                                                     CAPTURE_FIFO_PRIORITY)
            self._set_up.set()
            if self.ring is not None:
                self._run_ring()
                return
            while not stop.is_set():
                self.take_messages()
                if c.changed("inputs"):
                    snap = c.read_inputs()
                    if snap.seq and len(q) < self.max_queue:
                        q.append(snap.copy())
                else:
                    sleep(self.poll_s)
        except BaseException as err:  # noqa: BLE001 - handed to the writing thread
            self.error = err
            self._set_up.set()

    def _run_ring(self) -> None:
        self._ring_k = self.ring.count()  # frames already in the ring are history
        idle = 0
        while not self._stop.is_set():
            self.take_messages()
            if self.take_from_ring():
                idle = 0
                continue
            idle += 1
            if idle % RING_CHECK_POLLS == 0 and self.check_ring():
                continue
            time.sleep(self.poll_s)

    def check_ring(self) -> bool:
        """If the ring's file was replaced (the service restarted), take what the old ring
        still holds, attach the new ring, queue a :class:`RingSwitch` and read the new ring
        from its first frame; returns True when it switched. A ring that was removed, or
        whose replacement is not there yet or has another layout, is kept: the recorder's
        own checks on the buffer decide what happens then."""
        from bit3.ring import FrameRing, RingError
        old = self.ring
        if old is None or not old.replaced():
            return False
        try:
            new = FrameRing.attach(old.buffer_name, old.layout_hash)
        except RingError:
            return False
        self.take_from_ring()  # the old ring's memory stays valid: finish it
        try:  # and the old buffer's messages (its client is open; a killed service may
            self.take_messages(force=True)  # have left a queue mid-post: then they are lost)
        except Exception:  # noqa: BLE001 - the new ring must be taken regardless
            pass
        self._msg_client = None  # the old client is closed soon: none until messages_from
        self.queue.append(RingSwitch(
            f"frame ring {old.path} was replaced (service restarted?): the old ring ended after "
            f"{old.count()} frames; reading the new ring from its first frame"))
        self.ring, self._ring_k = new, 0
        self.ring_reattached += 1
        old.close()
        return True

    def take_from_ring(self) -> int:
        """Queue every whole frame the ring holds beyond the last one taken; returns how
        many were queued (the thread calls it; tests call it in simulated time)."""
        ring, q = self.ring, self.queue
        if self._ring_k is None:
            self._ring_k = ring.count()
        layout, dtype = self.client.layout, self._inputs_dtype
        k, n, taken = self._ring_k, ring.count(), 0
        if n - k >= ring.n_slots:  # fell a whole ring behind: those frames are gone
            self.ring_lost += n - k - (ring.n_slots - 1)
            k = n - (ring.n_slots - 1)
        while k < n:
            data = ring.read(k)
            k += 1
            if data is None or len(q) >= self.max_queue:
                self.ring_lost += 1  # the gap in the sequence numbers counts it as missed
                continue
            # seq: even and +2 per frame, as the buffer's own counter
            q.append(Snapshot(np.ndarray((), dtype, buffer=data), "inputs", layout, 2 * k))
            taken += 1
        self._ring_k = k
        return taken

    def take_messages(self, force: bool = False) -> int:
        """Queue a :class:`MessagesCopy` of each message queue whose head moved, at most
        every :data:`MESSAGES_POLL_S` (``force``: now); returns how many were queued."""
        c = self._msg_client
        now = time.monotonic()
        if c is None or (now < self._msg_next and not force):
            return 0
        self._msg_next = now + MESSAGES_POLL_S
        n = 0
        for q in MESSAGE_QUEUES:
            body = c.buffer.queue(q + "_messages").copy()
            head = int(body["head_seq"])
            if head != self._msg_heads.get(q):
                self._msg_heads[q] = head
                self.queue.append(MessagesCopy(q, body))
                n += 1
        return n

    def messages_from(self, client: Client) -> None:
        """Copy the message queues of ``client`` from now on (after a ring switch: the new
        service's; the recorder's cursors start at their heads, ``Recorder.attach``)."""
        self._msg_heads = {}
        self._msg_client = client

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        """End the thread and close the ring (queued snapshots stay for :meth:`drain`)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        if self.ring is not None and not self._thread.is_alive():
            self.ring.close()

    def drain(self, rec: "Recorder") -> int:
        """Write every queued snapshot up to a ring switch (then :attr:`replaced_note` is
        set and the rest stays queued for the next call); returns frames written."""
        n = 0
        q = self.queue
        while q:
            snap = q.popleft()
            kind = type(snap)
            if kind is RingSwitch:  # the frames after it are the new service's
                self.replaced_note = snap.note
                return n
            if kind is MessagesCopy:
                rec.feed_messages(snap.queue, snap.body)
                continue
            n += rec.feed_inputs(snap)
        return n
