"""Attaching to a service that may not be up yet, and reattaching when it restarts.

Lab users' most common start-up complaint is tools that time out silently or hang
while a server is still starting (anchors.md 4.3 and 11, item 8: ophyd connection
timeouts raised to 10-15 s). The rules here:

- :func:`attach_waiting` retries the attach while no service is up, prints one clear
  line every ``notice_s`` seconds ("waiting for the I/O service on buffer 'pfma' ..."),
  and gives up with :class:`PfmaTimeoutError` after ``wait_s`` (0 = never gives up, but
  still says so every few seconds). A layout mismatch is not "not up yet": it is
  raised at once.
- :class:`ServiceLink` notices a service that went away (its owner process is gone,
  it stopped, or the shared memory was re-created by a new service) and reattaches.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Callable, TextIO

from bit3.client import Client
from bit3.layout import ServiceState
from bit3.buffer import Bit3Error, LayoutMismatchError
from pfma.errors import PfmaTimeoutError


def _say_to(stream: TextIO | None) -> Callable[[str], None]:
    def say(text: str) -> None:
        print(text, file=stream or sys.stderr, flush=True)
    return say


def _shm_id(name: str) -> tuple[int, int] | None:
    try:
        st = os.stat(f"/dev/shm/{name}")
    except OSError:
        return None
    return st.st_ino, st.st_dev


def service_problem(client: Client) -> str | None:
    """Why this attachment has no live service behind it (None: it has one)."""
    h = client.header()
    owner = next((o for o in h.owners if o.area == "inputs"), None)
    if owner is None or owner.pid <= 0:
        return "no service owns the buffer (it stopped or has not started)"
    if not owner.alive:
        return f"its service {owner.name!r} (pid {owner.pid}) is not running"
    if h.service_state == ServiceState.STOPPED:
        return f"its service {owner.name!r} (pid {owner.pid}) has stopped"
    if h.service_state == ServiceState.STARTING:
        return f"its service {owner.name!r} (pid {owner.pid}) is starting"
    return None


def attach_waiting(name: str = "pfma", rack: str | None = None, *, wait_s: float = 30.0,
                   notice_s: float = 3.0, poll_s: float = 0.2, say: Callable[[str], None] | None = None,
                   sleep: Callable[[float], None] = time.sleep,
                   now: Callable[[], float] = time.monotonic, require_live: bool = True) -> Client:
    """A read-only :class:`Client` on buffer ``name`` once a live service publishes there.

    :param wait_s: give up after this long (0 = keep waiting, with a notice every ``notice_s``)
    :param require_live: also wait until the buffer's service process is running
    :raises PfmaTimeoutError: no service within ``wait_s``
    :raises LayoutMismatchError: the buffer belongs to a different rack or version
    """
    say = say or _say_to(None)
    t0 = now()
    next_notice = t0
    while True:
        client = None
        try:
            client = Client.attach(name, rack=rack)
            why = service_problem(client) if require_live else None
        except LayoutMismatchError as err:
            if "not initialised" not in str(err):
                raise
            why = "the buffer is not initialised yet"
        except (Bit3Error, FileNotFoundError) as err:
            why = str(err)
        if why is None:
            if now() - t0 > notice_s:
                say(f"attached to the I/O service on buffer {name!r}")
            return client
        if client is not None:
            client.close()
        t = now()
        if wait_s and t - t0 >= wait_s:
            raise PfmaTimeoutError(f"no I/O service on buffer {name!r} after {t - t0:.0f} s: {why}; "
                                   f"start one with `pfma serve --buffer {name}`")
        if t >= next_notice:
            limit = f", giving up after {wait_s:g} s" if wait_s else ""
            say(f"waiting for the I/O service on buffer {name!r} ({why}; {t - t0:.0f} s so far{limit})")
            next_notice = t + notice_s
        sleep(poll_s)


class ServiceLink:
    """A read-only attachment that reattaches when the service goes away and comes back.

    Call :meth:`client` before each read: it returns the current client, or waits
    (with notices, bounded by ``wait_s``) for a new service and returns a new client.
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
        self._client = attach_waiting(self.name, self.rack, wait_s=self.wait_s, notice_s=self.notice_s,
                                      say=self.say, sleep=self.sleep)
        self._shm = _shm_id(self.name)
        return self._client

    def client(self) -> Client:
        """The live client (attaching or reattaching first when needed)."""
        if self._client is None:
            return self._attach()
        why = None
        sid = _shm_id(self.name)
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
