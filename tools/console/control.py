"""Requests to a running controller through its world model's request/response protocol
(``ui.request``, ``ui.request_arg``, ``ui.request_seq`` -> ``ui.response``,
``ui.response_text``, ``ui.response_seq``; System Up/Down answers, docs/console.md).

Used by ``pfma controller halt|step|resume`` and by the console. The link never blocks on
its own: :meth:`ControllerLink.answer` is polled (the CLI waits in real time, the console
at its refresh, a test in simulated frames).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from controller.layers import Request, Response
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
    what: str = "request"  #: the line's first word(s): "request", "gripper request"

    @property
    def done(self) -> bool:
        return self.code not in (Response.NONE, Response.IN_PROGRESS)

    @property
    def ok(self) -> bool:
        return self.code == Response.COMPLETE

    def line(self) -> str:
        return (f"{self.what} {self.seq}: {self.text or Request.NAMES.get(self.code, '?')} -> "
                f"{Response.NAMES.get(self.code, self.code)}")


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
        self._gseq = 0

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
        """Post request ``kind`` (``Request.*``) with ``arg``; returns its number."""
        try:
            self._seq = max(self._seq, int(self.wm.get("ui.request_seq"))) + 1
            self.wm.set_user("ui.request_arg", int(arg), self.key)
            self.wm.set_user("ui.request", int(kind), self.key)
            self.wm.set_user("ui.request_seq", self._seq, self.key)
        except WorldModelError as err:
            raise ControlError(str(err)) from None
        return self._seq

    def answer(self, seq: int) -> Answer | None:
        """The answer to request ``seq`` so far (None: not answered yet)."""
        v = self.wm.get_task_inputs(("ui.response_seq", "ui.response", "ui.response_text"))
        if int(v["ui.response_seq"]) != seq:
            return None
        return Answer(seq, int(v["ui.response"]), _text(v["ui.response_text"]))

    def wait(self, seq: int, timeout_s: float, poll_s: float = 0.005) -> Answer:
        """Poll (real time) until request ``seq`` is answered with more than IN PROGRESS.

        :raises ControlError: not answered within ``timeout_s``
        """
        end = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < end:
            a = self.answer(seq)
            if a is not None:
                last = a
                if a.done:
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
        """Ask the owner to set ``name`` to ``text`` (a ``pfma wm set`` VALUE: JSON, or numbers
        separated by commas/spaces) with this link's key; returns the request id. The rule,
        the key and the value are checked by ``WorldModel.set_user``, the call ``pfma wm set``
        makes, and again by the owner when it applies the request.

        :raises WorldModelError: why not (not user-settable, powered up, key, value, ring full)
        """
        from tools.cli.wm import parse_value  # VALUE as `pfma wm set` reads it
        return int(self.wm.set_user(name, parse_value(text), self.key))

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

    # --- the gripper (controller/gripper.py: requests to Servo Control) --------------------------
    def submit_gripper(self, kind: int, force_n: float = 0.0) -> int:
        """Post gripper request ``kind`` (``pfma.gripper.GripperRequest``: 1 OPEN 2 CLOSE 3 STOP
        4 FORCE; ``force_n`` > 0 sets the grip force); returns its number."""
        try:
            seq = self._gseq = max(self._gseq, int(self.wm.get("gripper.request_seq"))) + 1
            self.wm.set_user("gripper.request_force_n", float(force_n), self.key)
            self.wm.set_user("gripper.request", int(kind), self.key)
            self.wm.set_user("gripper.request_seq", seq, self.key)
        except WorldModelError as err:
            raise ControlError(str(err)) from None
        return seq

    def gripper_answer(self, seq: int) -> Answer | None:
        """Servo Control's answer to gripper request ``seq`` so far (None: not answered yet)."""
        v = self.wm.get_task_inputs(("gripper.response_seq", "gripper.response", "gripper.response_text"))
        if int(v["gripper.response_seq"]) != seq:
            return None
        return Answer(seq, int(v["gripper.response"]), _text(v["gripper.response_text"]), "gripper request")

    def wait_gripper(self, seq: int, timeout_s: float, poll_s: float = 0.005,
                     on_answer=None) -> Answer:
        """Poll (real time) until gripper request ``seq`` is answered with more than IN
        PROGRESS (``on_answer`` is called with each new answer, the IN PROGRESS one too).

        :raises ControlError: not answered within ``timeout_s``
        """
        end = time.monotonic() + timeout_s
        last = None
        while time.monotonic() < end:
            a = self.gripper_answer(seq)
            if a is not None and a != last:
                last = a
                if on_answer is not None:
                    on_answer(a)
                if a.done:
                    return a
            time.sleep(poll_s)
        info = self.wm.info()
        state = f"last answer: {last.line()}" if last else "no answer"
        alive = "" if info.owner_alive else f"; its controller (pid {info.owner_pid}) is not running"
        raise ControlError(f"gripper request {seq}: {state} within {timeout_s:g} s{alive}")

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
