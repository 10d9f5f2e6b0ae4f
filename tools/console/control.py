"""Requests to a running controller through its world model's request/response protocol
(one keyed write of ``ui.request`` = (kind, argument) per request, numbered by the write's
request id; System Up/Down queues them and answers each in its answer log ``ui.answer_*``,
docs/controller.md "User requests", docs/console.md).

Used by ``pfma controller halt|step|resume|power-up|power-down|reset`` and by the console.
The link never blocks on its own: :meth:`ControllerLink.answer` is polled (the CLI waits in
real time, the console at its refresh, a test in simulated frames).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from controller.layers import Request, Response, find_answer
from controller.worldmodel import WorldModel, WorldModelError
from controller.worldmodel.model import ACCESS_KEY_ENV, DEFAULT_ACCESS_KEY

__all__ = ["Answer", "ControllerLink", "ControlError", "Request", "Response", "WriteOutcome", "access_key"]


class ControlError(Exception):
    """A request that could not be made or was not answered (one clear message)."""


@dataclass(frozen=True)
class Answer:
    seq: int
    code: int  #: Response.*
    text: str

    @property
    def done(self) -> bool:
        """A final answer (not QUEUED or IN PROGRESS)."""
        return self.code in Response.FINAL

    @property
    def ok(self) -> bool:
        return self.code == Response.COMPLETE

    def line(self) -> str:
        return f"request {self.seq}: {self.text or Request.NAMES.get(self.code, '?')} -> {Response.NAMES[self.code]}"


def access_key(key: str | None) -> str:
    """The key user requests carry: ``--key``, else ``$PFMA_WM_KEY``, else the default key
    the controller itself uses when it was started without one (assumed: an operator at the
    console of a controller started without a key need not type one; docs/console.md)."""
    return key or os.environ.get(ACCESS_KEY_ENV) or DEFAULT_ACCESS_KEY


class ControllerLink:
    """Requests to the controller owning ``wm`` (attached read-only, or the owner itself in
    a simulator)."""

    def __init__(self, wm: WorldModel, key: str | None = None) -> None:
        self.wm = wm
        self.key = access_key(key)
        self._seq = 0

    @classmethod
    def attach(cls, name: str, key: str | None = None) -> "ControllerLink":
        """Attach to world model ``name``; one clear :class:`ControlError` when there is no
        controller (no segment, or its owner is not running)."""
        try:
            wm = WorldModel.attach(name)
        except WorldModelError as err:
            raise ControlError(str(err)) from None
        info = wm.info()
        if not info.owner_alive:
            wm.close()
            raise ControlError(f"world model {name!r}: its controller {info.owner!r} (pid {info.owner_pid}) "
                               f"is not running")
        return cls(wm, key)

    def submit(self, kind: int, arg: int = 0) -> int:
        """Post request ``kind`` (``Request.*``) with ``arg``: one keyed write of
        ``ui.request``; returns its number (the write's request id)."""
        try:
            return int(self.wm.set_user("ui.request", [int(kind), int(arg)], self.key))
        except WorldModelError as err:
            raise ControlError(str(err)) from None

    def answer(self, seq: int) -> Answer | None:
        """The newest answer to request ``seq`` so far (None: not answered yet). A request
        the world model itself rejected (never reached System Up/Down) reads as REFUSED
        with the world model's reason."""
        a = find_answer(self.wm, seq)
        if a is not None:
            return Answer(seq, a[0], a[1])
        r = self.wm.request(seq)
        if r is not None and r.state == "rejected":
            return Answer(seq, Response.REFUSED, f"not taken by the world model: {r.result}")
        return None

    def wait(self, seq: int, timeout_s: float, poll_s: float = 0.005, halted_ok: bool = False) -> Answer:
        """Poll (real time) until request ``seq`` has a final answer (``Answer.done``).
        ``halted_ok``: also return once it is QUEUED or IN PROGRESS while the controller is
        halted (it then runs frame by frame, with the steps).

        :raises ControlError: not answered within ``timeout_s``
        """
        end = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < end:
            a = self.answer(seq)
            if a is not None:
                last = a
                if a.done or (halted_ok and self.halted()):
                    return a
            time.sleep(poll_s)
        info = self.wm.info()
        state = f"last answer: {last.line()}" if last else "no answer"
        alive = "" if info.owner_alive else f"; its controller (pid {info.owner_pid}) is not running"
        raise ControlError(f"request {seq}: {state} within {timeout_s:g} s{alive}")

    # --- keyed user writes (the debug window; the code path of `pfma wm set`) ------------------
    def may_set(self, name: str):
        """The variable's spec if a user may set it now; else :class:`WorldModelError` with
        the ownership rule's reason (``WorldModel.check_user_settable``, as ``pfma wm set``)."""
        return self.wm.check_user_settable(name)

    def write(self, name: str, text: str) -> int:
        """Ask the owner to set ``name`` to ``text`` (a ``pfma wm set`` VALUE: JSON, numbers
        separated by commas/spaces, or a name of an enumerated variable's values) with this link's key; returns the request id. The rule,
        the key and the value are checked by ``WorldModel.set_user``, the call ``pfma wm set``
        makes, and again by the owner when it applies the request.

        :raises WorldModelError: why not (not user-settable, powered up, key, value, ring full)
        """
        from tools.cli.wm import parse_value  # VALUE as `pfma wm set` reads it
        return int(self.wm.set_user(name, parse_value(text, self.wm.spec(name)), self.key))

    def outcome(self, rid: int) -> "WriteOutcome | None":
        """The owner's verdict on write ``rid`` once it has one (None while pending)."""
        r = self.wm.request(rid)
        if r is None:
            return WriteOutcome(rid, "?", False, "its slot was reused before the outcome was read")
        if r.state not in ("applied", "rejected"):
            return None
        return WriteOutcome(rid, r.variable, r.state == "applied", r.result)

    def halted(self) -> bool:
        return bool(self.wm.get("runtime.halted"))

    def step_trace(self) -> str:
        """The trace of the last single-step run (header and one line per frame)."""
        return _text(self.wm.get("runtime.step_trace"))

    def close(self) -> None:
        if self.wm.readonly:
            self.wm.close()


@dataclass(frozen=True)
class WriteOutcome:
    """What the owner did with a user write: applied (at frame N) or rejected (why)."""

    rid: int
    variable: str
    applied: bool
    result: str


def _text(words) -> str:
    return bytes(words).rstrip(b"\0").decode(errors="replace")
