"""Attaching to a live service's Bit3 buffer, waiting for it, noticing its restart: one
helper for every tool.

Lab users' most common start-up complaint is tools that time out silently or hang
while a server is still starting (anchors.md 4.3 and 11, item 8). The rules here:

- :func:`service_status` attaches once and says why there is no live service (no
  buffer, no owner, its process gone, STOPPED); a layout mismatch is not "not up
  yet": it is raised at once.
- :func:`wait_for_service` retries it with a clear message while no service is up, a
  reminder every few seconds, until a service is there, a time-out or ``stop()``;
  :func:`attach_waiting` is the same wait that raises :class:`PfmaTimeoutError`;
  :func:`wait_for_frames` the same, silent, until the service has published N frames
  (for a program that has just started it).
- :class:`ServiceLink` notices a service that went away (its owner process is gone, it
  stopped, or the shared memory was re-created by a new service) and reattaches;
  :func:`buffer_replaced` tells a long-running reader (``pfma record``) the same.
- :func:`no_service` is the one-line refusal of a reader started with no live service
  (``pfma read``, ``stats``, ``watch``, ``monitor``), decided without attaching.
- A buffer named ``zenoh://HOST:PORT/NAME`` is read through a ``pfma bridge`` on that
  host (docs/bridge.md): :func:`attach_reader` and :class:`ServiceLink` return a
  :class:`tools.bridge.remote.RemoteBuffer` (the Client read API); :func:`no_service`
  leaves the decision to the attach, which asks the bridge.

Two families of tools word this differently, and each keeps its words (:class:`Words`):
the live views and the checkout speak of "the I/O service on buffer 'pfma'"
(:data:`SERVICE_WORDS`), the recorder, the scope and the replay of "service on
/dev/shm/pfma" (:data:`SHM_WORDS`).
"""

from __future__ import annotations

import os
import sys
import time
from typing import Callable, TextIO

from bit3.access import Bit3AccessError
from bit3.buffer import Bit3Error, LayoutMismatchError
from bit3.client import Client
from bit3.layout import Layout, ServiceState
from pfma.errors import PfmaTimeoutError
from tools.bridge.address import remote_target


class Words:
    """How one family of tools words waiting for a service, and the few rules that came
    with those words (which states count as live, which attach errors are waited out)."""

    #: a service still STARTING is live
    starting_is_live = False
    #: a buffer whose header is not written yet is waited for (else: LayoutMismatchError)
    waits_uninitialised = True
    #: other OSError/ValueError from attaching are waited out (else: raised)
    waits_os_errors = False
    #: a reason that changes is said at once (else: at the next notice)
    says_changes = False

    def reason(self, code: str, err: BaseException | None = None, owner=None) -> str:
        raise NotImplementedError

    def waiting(self, name: str, why: str, waited_s: float, limit_s: float | None) -> str:
        raise NotImplementedError

    def still(self, name: str, why: str, waited_s: float, limit_s: float | None) -> str:
        return self.waiting(name, why, waited_s, limit_s)

    def up(self, name: str, waited_s: float, said: bool, notice_s: float) -> str | None:
        raise NotImplementedError


class _ServiceWords(Words):
    """``pfma watch``, ``monitor``, ``checkout``: "the I/O service on buffer 'pfma'"."""

    def reason(self, code, err=None, owner=None) -> str:
        if code == "uninitialised":
            return "the buffer is not initialised yet"
        if code in ("no_buffer", "bit3", "missing"):
            return str(err)
        if code == "not_ready":  # a header read failed: the caller decides (see service_status)
            raise err
        if code == "unowned":
            return "no service owns the buffer (it stopped or has not started)"
        return f"its service {owner.name!r} (pid {owner.pid}) " + {
            "dead": "is not running", "stopped": "has stopped", "starting": "is starting"}[code]

    def waiting(self, name, why, waited_s, limit_s) -> str:
        limit = f", giving up after {limit_s:g} s" if limit_s else ""
        return f"waiting for the I/O service on buffer {name!r} ({why}; {waited_s:.0f} s so far{limit})"

    def up(self, name, waited_s, said, notice_s) -> str | None:
        return f"attached to the I/O service on buffer {name!r}" if waited_s > notice_s else None


class _ShmWords(Words):
    """``pfma record``, ``scope``, ``replay``: "service on /dev/shm/pfma"."""

    starting_is_live = True
    # a restarting service's new buffer exists a moment before its header is written: a
    # recorder that met it ended its recording as "a different layout" (3 of 100 service
    # kills in the kill matrix); it waits now, saying so
    waits_uninitialised = True
    waits_os_errors = True
    says_changes = True

    def reason(self, code, err=None, owner=None) -> str:
        if code == "uninitialised":
            return "buffer not initialised yet"
        if code == "no_buffer":
            return "no buffer yet"
        if code == "bit3":
            return f"no buffer ({err})"
        if code in ("missing", "os"):
            return f"buffer not readable yet ({err})"
        if code == "not_ready":
            return f"buffer not ready ({err})"
        if code == "unowned":
            return "buffer exists but no service owns it (not started yet, or stopped)"
        if code == "dead":
            return f"buffer exists but its service (pid {owner.pid}) is not running"
        return f"service pid {owner.pid} has stopped"

    def waiting(self, name, why, waited_s, limit_s) -> str:
        return f"waiting for service on /dev/shm/{name} ... ({why}; Ctrl-C gives up)"

    def still(self, name, why, waited_s, limit_s) -> str:
        return f"still waiting for service on /dev/shm/{name} ({waited_s:.0f} s; {why})"

    def up(self, name, waited_s, said, notice_s) -> str | None:
        return f"service on /dev/shm/{name} is up (after {waited_s:.1f} s)" if said else None


#: "the I/O service on buffer 'pfma'" (live views, checkout)
SERVICE_WORDS: Words = _ServiceWords()
#: "service on /dev/shm/pfma" (recorder, scope, replay)
SHM_WORDS: Words = _ShmWords()


def _problem(client: Client, words: Words) -> str | None:
    """Why this attachment has no live service behind it (None: it has one)."""
    try:
        h = client.header()
        owner = next((o for o in h.owners if o.area == "inputs"), None)
        if owner is None or owner.pid <= 0:
            return words.reason("unowned")
        if not owner.alive:
            return words.reason("dead", owner=owner)
        if h.service_state == ServiceState.STOPPED:
            return words.reason("stopped", owner=owner)
        if h.service_state == ServiceState.STARTING and not words.starting_is_live:
            return words.reason("starting", owner=owner)
    except Exception as err:  # noqa: BLE001 - half-initialised buffer
        return words.reason("not_ready", err)
    return None


def service_problem(client: Client) -> str | None:
    """Why this attachment has no live service behind it (None: it has one)."""
    return _problem(client, SERVICE_WORDS)


def service_status(name: str, layout: Layout | None = None, *, rack: str | None = None,
                   words: Words = SHM_WORDS, require_live: bool = True) -> tuple[Client | None, str]:
    """``(client, "")`` when a live service publishes on buffer ``name``, else
    ``(None, why)``. Layout mismatches raise (they do not go away by waiting).

    A buffer this user may not open (:class:`bit3.access.Bit3AccessError`) raises too.
    Live means: the buffer exists, its layout matches, the inputs owner's process is
    running and the service state is not STOPPED (nor STARTING, in :data:`SERVICE_WORDS`).
    """
    try:
        c = Client.attach(name, rack=rack, layout=layout)
    except LayoutMismatchError as err:
        if not (words.waits_uninitialised and "not initialised" in str(err)):
            raise
        return None, words.reason("uninitialised", err)
    except Bit3AccessError:
        raise  # no permission does not go away by waiting: one message now (bit3/access.py)
    except Bit3Error as err:
        return None, words.reason("no_buffer" if "no Bit3 buffer" in str(err) else "bit3", err)
    except FileNotFoundError as err:
        return None, words.reason("missing", err)
    except (OSError, ValueError) as err:
        if not words.waits_os_errors:
            raise
        return None, words.reason("os", err)
    try:
        why = _problem(c, words) if require_live else None
    except (Bit3Error, FileNotFoundError) as err:  # as not up yet (SERVICE_WORDS re-raise it)
        why = str(err)
    except BaseException:
        c.close()
        raise
    if why is None:
        return c, ""
    c.close()
    return None, why


def _wait(name: str, *, layout: Layout | None, rack: str | None, words: Words, timeout_s: float | None,
          notice_s: float, poll_s: float, say: Callable[[str], None], stop: Callable[[], bool],
          sleep: Callable[[float], None], now: Callable[[], float],
          require_live: bool = True) -> tuple[Client | None, str, float]:
    """The waiting loop: ``(client, "", waited_s)``, or ``(None, why, waited_s)`` on time-out
    or when ``stop()`` turns true."""
    t0 = now()
    said: str | None = None  # the reason last said
    next_notice = t0
    while True:
        c, why = service_status(name, layout, rack=rack, words=words, require_live=require_live)
        if c is not None:
            text = words.up(name, now() - t0, said is not None, notice_s)
            if text:
                say(text)
            return c, "", now() - t0
        t = now()
        timed_out = timeout_s is not None and t - t0 >= timeout_s
        if timed_out and not words.says_changes:  # give up before saying more
            return None, why, t - t0
        if said is None or (why != said and words.says_changes):
            say(words.waiting(name, why, t - t0, timeout_s))
            said, next_notice = why, t + notice_s
        elif t >= next_notice:
            say(words.still(name, why, t - t0, timeout_s))
            next_notice = t + notice_s
        if stop() or timed_out:
            return None, why, t - t0
        sleep(poll_s)


def wait_for_service(name: str, layout: Layout | None = None, *,
                     timeout_s: float | None = None, poll_s: float = 0.2,
                     say: Callable[[str], None] = print,
                     stop: Callable[[], bool] = lambda: False,
                     remind_every_s: float = 10.0, rack: str | None = None, words: Words = SHM_WORDS,
                     sleep: Callable[[float], None] = time.sleep,
                     now: Callable[[], float] = time.monotonic) -> Client | None:
    """Attach to a live service on ``/dev/shm/NAME``, waiting (with a clear message, then a
    reminder every ``remind_every_s``) while there is none. Returns None on time-out or
    when ``stop()`` turns true; raises LayoutMismatchError for a buffer of another layout."""
    return _wait(name, layout=layout, rack=rack, words=words, timeout_s=timeout_s, notice_s=remind_every_s,
                 poll_s=poll_s, say=say, stop=stop, sleep=sleep, now=now)[0]


def wait_for_frames(name: str, frames: int = 0, *, timeout_s: float, pid: int | None = None,
                    alive: Callable[[], bool] = lambda: True, poll_s: float = 0.1) -> Client | None:
    """A client of the live service on buffer ``name`` once it has published more than
    ``frames`` frames (and, with ``pid``, is that process): :func:`wait_for_service`, silent,
    then its frame counter. None on time-out or once ``alive()`` turns false (the service's
    process ended). For a program that has just started ``pfma serve`` (the benchmarks)."""
    end = time.monotonic() + timeout_s
    while True:
        c = wait_for_service(name, timeout_s=max(0.0, end - time.monotonic()), poll_s=poll_s,
                             say=lambda _text: None, stop=lambda: not alive())
        if c is None:
            return None
        try:
            if (pid is None or c.owners()["inputs"].pid == pid) and c.read_inputs().frame > frames:
                return c
        except Exception:  # noqa: BLE001 - a torn read, a buffer being replaced: not yet
            pass
        c.close()
        if time.monotonic() >= end or not alive():
            return None
        time.sleep(poll_s)


def _say_to(stream: TextIO | None) -> Callable[[str], None]:
    def say(text: str) -> None:
        print(text, file=stream or sys.stderr, flush=True)
    return say


def attach_waiting(name: str = "pfma", rack: str | None = None, *, wait_s: float = 30.0,
                   notice_s: float = 3.0, poll_s: float = 0.2, say: Callable[[str], None] | None = None,
                   sleep: Callable[[float], None] = time.sleep,
                   now: Callable[[], float] = time.monotonic, require_live: bool = True) -> Client:
    """A read-only :class:`Client` on buffer ``name`` once a live service publishes there
    (:func:`wait_for_service` in :data:`SERVICE_WORDS`, a notice every ``notice_s``).

    :param wait_s: give up after this long (0 = keep waiting, with a notice every ``notice_s``)
    :param require_live: also wait until the buffer's service process is running
    :raises PfmaTimeoutError: no service within ``wait_s``
    :raises LayoutMismatchError: the buffer belongs to a different rack or version
    """
    c, why, waited = _wait(name, layout=None, rack=rack, words=SERVICE_WORDS, timeout_s=wait_s or None,
                           notice_s=notice_s, poll_s=poll_s, say=say or _say_to(None), stop=lambda: False,
                           sleep=sleep, now=now, require_live=require_live)
    if c is None:
        raise PfmaTimeoutError(f"no I/O service on buffer {name!r} after {waited:.0f} s: {why}; "
                               f"start one with `pfma serve --buffer {name}`")
    return c


def shm_id(name: str) -> tuple[int, int] | None:
    """(inode, device) of ``/dev/shm/NAME``, or None: a segment replaced under the same name
    (a restarted service or controller) has another."""
    try:
        st = os.stat(f"/dev/shm/{name}")
    except OSError:
        return None
    return st.st_ino, st.st_dev


def buffer_replaced(client: Client) -> bool:
    """The name now refers to another segment than the one ``client`` maps (the service
    was restarted and created a new buffer), or the name is gone."""
    try:
        from bit3.buffer import Bit3Buffer
        b = Bit3Buffer.attach(client.buffer.name, readonly=True, layout=client.layout)
    except Exception:  # noqa: BLE001 - gone or different: either way not ours any more
        return True
    try:
        return b.header().created_ns != client.header().created_ns
    finally:
        b.close()


def attach_reader(name: str, rack: str | None = None, *, every_frame: bool = False,
                  timeout_s: float | None = None):
    """A read-only reader of buffer ``name``: a :class:`Client` on shared memory (refused
    with :func:`no_service`'s line when no live service is there), or a RemoteBuffer for
    ``zenoh://HOST:PORT/NAME``.

    :param every_frame: a remote reader keeps every inputs body in order and
        ``changed``/``read_inputs`` step through them (the scope, the recorder), as a
        local reader polling fast enough sees every publish
    :param timeout_s: how long a remote reader waits for its bridge (default: RemoteBuffer's)
    :raises PfmaError: no live service, no bridge answering, or another layout
    """
    target = remote_target(name)
    if target is not None:
        from tools.bridge.remote import DEFAULT_TIMEOUT_S, RemoteBuffer
        return RemoteBuffer.connect(*target, rack=rack, queue_inputs=every_frame,
                                    timeout_s=DEFAULT_TIMEOUT_S if timeout_s is None else timeout_s)
    from pfma.errors import PfmaError
    why = no_service(name)
    if why is not None:
        raise PfmaError(why)
    return Client.attach(name, rack=rack)


class ServiceLink:
    """A read-only attachment that reattaches when the service goes away and comes back.

    Call :meth:`client` before each read: it returns the current client, or waits
    (with notices, bounded by ``wait_s``) for a new service and returns a new client.
    A re-created buffer is noticed from its ``/dev/shm`` inode (one ``stat`` per call).
    """

    def __init__(self, name: str = "pfma", rack: str | None = None, *, wait_s: float = 30.0,
                 notice_s: float = 3.0, say: Callable[[str], None] | None = None,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.name = name
        self.rack = rack
        self.wait_s = wait_s
        self.notice_s = notice_s
        self.say = say or _say_to(None)
        self.sleep = sleep
        self.reattachments = 0
        self._client: Client | None = None
        self._shm: tuple[int, int] | None = None

    def _attach(self) -> Client:
        if remote_target(self.name) is not None:  # through a bridge: its own waits and errors
            self._client = attach_reader(self.name, self.rack)
            return self._client
        self._client = attach_waiting(self.name, self.rack, wait_s=self.wait_s, notice_s=self.notice_s,
                                      say=self.say, sleep=self.sleep)
        self._shm = shm_id(self.name)
        return self._client

    def client(self) -> Client:
        """The live client (attaching or reattaching first when needed)."""
        if self._client is None:
            return self._attach()
        if remote_target(self.name) is not None:
            return self._client
        why = None
        sid = shm_id(self.name)
        if sid != self._shm:
            why = "its shared memory was removed or re-created"
        else:
            why = service_problem(self._client)
        if why is None:
            return self._client
        self.say(f"lost the I/O service on buffer {self.name!r} ({why}); waiting to reattach")
        self._client.close()
        self._client = None
        self._attach()
        self.reattachments += 1
        self.say(f"reattached to the I/O service on buffer {self.name!r}")
        return self._client

    def invalidate(self, why: str) -> None:
        """Drop the attachment after a failed read; the next :meth:`client` reattaches."""
        if self._client is not None:
            self.say(f"lost the I/O service on buffer {self.name!r} ({why}); waiting to reattach")
            self._client.close()
            self._client = None
            self.reattachments += 1

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


def no_service(name: str) -> str | None:
    """Why no live service publishes Bit3 buffer ``name`` (None: one does).

    Decided from the service's claim lock (:meth:`Bit3Buffer.owner_alive`), so for a
    buffer of any layout; the message is one line a tool prints before exiting 1.
    """
    from bit3.buffer import Bit3Buffer
    if remote_target(name) is not None:
        return None  # a remote buffer: the attach asks its bridge (attach_reader)
    path = f"/dev/shm/{name}"
    alive, who = Bit3Buffer.owner_alive(name)
    if alive:
        return None
    if who.startswith("no buffer"):
        return (f"no service buffer {path}: no I/O service runs on buffer {name!r}; start one "
                f"with `pfma serve --buffer {name}` (in another terminal), or check --buffer")
    return f"service on {path} is not running ({_last_frame(name)}{who})"


def _last_frame(name: str) -> str:
    """``"last frame N at t=T s; "`` from the buffer's header, or "" when it cannot be read."""
    import struct

    from bit3.layout import MAGIC
    from bit3.buffer import _header_offsets
    try:
        with open(f"/dev/shm/{name}", "rb") as f:
            head = f.read(1024)
        if head[:8] != MAGIC:
            return ""
        h = _header_offsets()
        frame = struct.unpack_from("<Q", head, h["frame"])[0]
        t_s = struct.unpack_from("<d", head, h["frame_t_s"])[0]
        state = struct.unpack_from("<I", head, h["service_state"])[0]
    except (OSError, KeyError, struct.error):
        return ""
    how = "it stopped; " if state == ServiceState.STOPPED else ""
    return f"{how}last frame {frame} at t={t_s:.3f} s; "
