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

__all__ = ["Answer", "ControllerLink", "ControlError", "MoveAnswer", "Request", "Response", "WriteOutcome",
           "access_key", "parse_move"]


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
        """A final answer (not QUEUED or IN PROGRESS)."""
        return self.code in Response.FINAL

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
        self._move_seq = 0

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
        from tools.wmtext import parse_value  # VALUE as `pfma wm set` reads it
        return int(self.wm.set_user(name, parse_value(text, self.wm.spec(name)), self.key))

    def outcome(self, rid: int) -> "WriteOutcome | None":
        """The owner's verdict on write ``rid`` once it has one (None while pending)."""
        r = self.wm.request(rid)
        if r is None:
            return WriteOutcome(rid, "?", False, "its slot was reused before the outcome was read")
        if r.state not in ("applied", "rejected"):
            return None
        return WriteOutcome(rid, r.variable, r.state == "applied", r.result)

    # --- move-to requests (msp.move_request; docs/controller.md "Moves that mean what they say") ---
    def move_pose(self, pos_m, quat=None, max_turn_rad: float | None = None) -> int:
        """Ask the controller to move the tool to ``pos_m`` (x, y, z m, world) with ``quat``
        (qw, qx, qy, qz; None: keep the tool's orientation) on a straight line, checked
        first (tool rotation up to ``max_turn_rad``, default ``msp.max_turn_rad``; soft
        limits; singular sets). It needs cart.mode 2 TRAJECTORY: :meth:`trajectory_mode`.
        Returns the request number (:meth:`move_answer`, :meth:`wait_move`).

        :raises ControlError: a bad pose (one line), or the write refused
        """
        from controller.paths import MoveRequest, PathError
        try:
            return self._move(lambda seq: MoveRequest.pose(seq, pos_m, quat, max_turn_rad))
        except PathError as err:
            raise ControlError(f"move: {err}") from None

    def move_joints(self, joints_rad, max_turn_rad: float | None = None) -> int:
        """Ask the controller to move the joints to ``joints_rad`` (rad, command-area order)
        on a straight line in joint space, checked first. Returns the request number."""
        from controller.paths import MoveRequest, PathError
        try:
            return self._move(lambda seq: MoveRequest.joints(seq, joints_rad, max_turn_rad))
        except PathError as err:
            raise ControlError(f"move: {err}") from None

    def stop_move(self) -> int:
        """Stop the running move or playback (it decelerates to rest). Returns the request number."""
        from controller.paths import MoveRequest
        return self._move(MoveRequest.stop)

    def _move(self, make) -> int:
        """Write one move request. Refused while the controller is halted: no frame runs then,
        and the move would start on the resume, unexpected."""
        if self.halted():
            raise ControlError("the controller is halted: a move would start only on the resume (pfma controller "
                               "resume --rearm first)")
        try:
            seq = max(int(self.wm.get("msp.move_request")[0]), int(self.wm.get("msp.move_done_seq")),
                      self._move_seq) + 1
            req = make(seq)
            self.wm.set_user("msp.move_request", req.to_array(), self.key)
        except WorldModelError as err:
            raise ControlError(str(err)) from None
        self._move_seq = seq
        return seq

    def trajectory_mode(self) -> str:
        """Set cart.mode 2 TRAJECTORY (the Cartesian Engine follows the Trajectory Planner, as a
        pose move or playback needs) unless it is; "" if it was, else the change in words."""
        from controller.cartesian import MODE_NAMES, MODE_TRAJECTORY
        try:
            mode = int(self.wm.get("cart.mode"))
            if mode == MODE_TRAJECTORY:
                return ""
            self.wm.set_user("cart.mode", MODE_TRAJECTORY, self.key)
        except WorldModelError as err:
            raise ControlError(str(err)) from None
        return f"cart.mode {MODE_NAMES.get(mode, mode)} -> TRAJECTORY"

    def move_answer(self, seq: int) -> "MoveAnswer | None":
        """How move request ``seq`` ended (None: not yet)."""
        from controller.paths import MspResult
        v = self.wm.get_task_inputs(("msp.move_done_seq", "msp.result", "msp.result_text"))
        done = int(v["msp.move_done_seq"])
        if done < seq:
            return None
        code = int(v["msp.result"])
        text = _text(v["msp.result_text"])
        if done > seq:
            return MoveAnswer(seq, code, f"move {seq} ended; a later request's answer is shown: {text}", False,
                              MspResult.NAMES.get(code, "?"))
        return MoveAnswer(seq, code, text, code == MspResult.OK, MspResult.NAMES.get(code, "?"))

    def wait_move(self, seq: int, timeout_s: float, poll_s: float = 0.02) -> "MoveAnswer":
        """Poll (real time) until move request ``seq`` is answered.

        :raises ControlError: not answered within ``timeout_s`` (the move goes on)
        """
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            a = self.move_answer(seq)
            if a is not None:
                return a
            time.sleep(poll_s)
        info = self.wm.info()
        alive = "" if info.owner_alive else f"; its controller (pid {info.owner_pid}) is not running"
        raise ControlError(f"move {seq}: not ended within {timeout_s:g} s (it goes on; `pfma controller move --stop` "
                           f"stops it){alive}")

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
class MoveAnswer:
    """How a move request ended: ``code`` is ``msp.result`` (``MspResult``), ``text`` the
    controller's words (``msp.result_text``: the point and the reason of a refusal, the worst
    tracking error of a FAILED)."""

    seq: int
    code: int
    text: str
    ok: bool
    result: str  #: the result's name: OK, REFUSED, FAILED, CANCELLED ...

    def line(self) -> str:
        return self.text or f"move {self.seq} -> {self.result}"


@dataclass(frozen=True)
class WriteOutcome:
    """What the owner did with a user write: applied (at frame N) or rejected (why)."""

    rid: int
    variable: str
    applied: bool
    result: str


def parse_move(text: str) -> tuple[str, list[float], float | None]:
    """The console's move-to text: ``pose X,Y,Z[,QW,QX,QY,QZ]``, ``joints D,D,D,D,D,D``
    (degrees) or ``stop``, optionally followed by ``turn DEG``; returns (kind, numbers -
    metres/quaternion or radians -, largest tool rotation in rad or None).

    :raises ControlError: one line saying what is wrong
    """
    import math
    words = text.replace(";", " ").split()
    turn = None
    if len(words) >= 2 and words[-2] == "turn":
        try:
            deg = float(words[-1])
        except ValueError:
            raise ControlError(f"turn {words[-1]!r}: not a number of degrees") from None
        if not 0.0 < deg <= 180.0:
            raise ControlError(f"turn {deg:g}: the largest tool rotation must be 0..180 degrees")
        turn = math.radians(deg)
        words = words[:-2]
    if words == ["stop"]:
        return "stop", [], None
    if len(words) < 2 or words[0] not in ("pose", "joints"):
        raise ControlError("type pose X,Y,Z[,QW,QX,QY,QZ], joints D,D,D,D,D,D or stop (then optionally turn DEG)")
    try:
        nums = [float(x) for x in ",".join(words[1:]).split(",") if x.strip()]
    except ValueError:
        raise ControlError(f"{words[0]}: {' '.join(words[1:])!r} is not a list of numbers") from None
    if not all(math.isfinite(x) for x in nums):
        raise ControlError(f"{words[0]}: numbers must be finite")
    if words[0] == "pose" and len(nums) not in (3, 7):
        raise ControlError(f"pose: 3 numbers (x, y, z m) or 7 (and qw, qx, qy, qz) needed, {len(nums)} given")
    if words[0] == "joints":
        if len(nums) != 6:
            raise ControlError(f"joints: 6 angles (degrees) needed, {len(nums)} given")
        nums = [math.radians(x) for x in nums]
    return words[0], nums, turn


def _text(words) -> str:
    return bytes(words).rstrip(b"\0").decode(errors="replace")
