"""The gripper: the seventh amplifier, driven by Servo Control (docs/controller.md "The gripper").

IRSS report section 1: "Joints on the PFMA are driven via 7 pulse width modulated amplifiers
(6 DOF + end effector)"; the rack's DAC channel 6 is the gripper command (a rate: 10 V =
full speed) and channel 13 its current limit. Servo Control writes the six joints' rate
commands and current limits; it owns the seventh amplifier the same way
(:class:`GripperDrive`, its periodic task ``gripper_control``, 40 Hz), and Data Acquisition
writes the gripper command beside the joints' (0 unless START UP COMPLETE).

Requests (report 2.2.8 request/response, "requests and responses coming to a layer"):

* the user's: ``gripper.request`` (1 OPEN 2 CLOSE 3 STOP 4 FORCE), ``gripper.request_force_n``
  (N; 0 keeps the grip force) and a new ``gripper.request_seq``; answered in
  ``gripper.response`` (1 IN PROGRESS 2 COMPLETE 3 REFUSED 4 FAILED), ``gripper.response_seq``
  and ``gripper.response_text``. An OPEN or CLOSE is IN PROGRESS until the move ends on a
  stall (COMPLETE) or fails. While the controller is halted a request is REFUSED at once.
* the Multi-Segment Path Planner's, replaying a path's gripper events:
  ``msp.gripper_request``/``msp.gripper_force_n``/``msp.gripper_seq``, answered in
  ``gripper.msp_done_seq``/``gripper.msp_done_code`` (the Response numbers).

The motion itself (stall detection, grip force, the jaw estimate) is
:class:`pfma.gripper.GripperMotion`. The largest grip force is the gripper's entry of the
protected ``servo.current_limit_a`` (default I_max: 200 N) times 40 N/A; the drive runs while
Servo Control is START UP COMPLETE with its loop closed and no fault, and is off otherwise
(its current limit goes to 0 with the joints' in the safe stop). Every accepted user request
is also counted in ``gripper.event_seq`` (``gripper.event``, ``gripper.event_force_n``):
what a path recording stores.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from controller.decision import Status
from controller.relays import at
from controller.messages import Level
from controller.worldmodel import VarSpec
from controller.variables import DAQ
from controller.worldmodel.var import Var, VarGroup, var
from pfma.arm import GRIPPER
from pfma.gripper import (
    ACTION_NAMES, COMPLETE, FAILED, IN_PROGRESS, NOTE, REFUSED, GripperMotion, GripperRequest, GripperState,
    Outcome,
)

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

#: bytes of ``gripper.response_text``
GRIPPER_TEXT_BYTES = 160
#: the gripper's index in the current-limit vector (the six joints, then the gripper)
GRIPPER_LIMIT_INDEX = 6
_RESPONSE_NAMES = {IN_PROGRESS: "IN PROGRESS", COMPLETE: "COMPLETE", REFUSED: "REFUSED", FAILED: "FAILED"}
#: the values of gripper.response and gripper.msp_done_code (0: nothing answered yet)
RESPONSE_ENUM = {0: "NONE", **_RESPONSE_NAMES}
#: the Servo Control brake phase in which the loop is closed (controller.servo)
_LOOP_CLOSED = 3


class GripperVars(VarGroup, prefix="gripper", writer="servo"):
    """The gripper's world-model variables (declared by Servo Control; writer ``servo``
    unless the row says): the user's requests, the answers, the gripper's state, its drive
    command and the events a path recording stores."""

    request: Var[int] = var(
        "command_input", "i2", (), 0, writer="user",
        doc="gripper request: 1 OPEN 2 CLOSE 3 STOP 4 FORCE (acted on when gripper.request_seq changes)",
        enum=GripperRequest)
    request_force_n: Var[float] = var("command_input", "f8", (), 0.0, "N", writer="user",
                                      doc="grip force for the request (0 keeps the present one; FORCE needs it)")
    request_seq: Var[int] = var("command_input", "i4", (), 0, writer="user",
                                doc="gripper request number: increment to make a new request")
    response: Var[int] = var(
        "response_output", "i2", (), 0,
        doc="answer to gripper request gripper.response_seq: 1 IN PROGRESS 2 COMPLETE 3 REFUSED 4 FAILED",
        enum=RESPONSE_ENUM)
    response_seq: Var[int] = var("response_output", "i4", (), 0,
                                 doc="the gripper request number gripper.response answers")
    response_text: Var[np.ndarray] = var("response_output", "u1", (GRIPPER_TEXT_BYTES,), [0] * GRIPPER_TEXT_BYTES,
                                         doc="the gripper's answer in words (UTF-8, zero-padded)")
    state: Var[int] = var("status_output", "i2", (), int(GripperState.OFF),
                          doc="gripper: 0 OFF 1 STOPPED 2 OPENING 3 CLOSING 4 OPEN 5 CLOSED 6 GRIPPING 7 STALLED",
                          enum=GripperState)
    force_n: Var[float] = var("status_output", "f8", (), 0.0, "N",
                              doc="the grip force in force (the gripper's current limit x 40 N/A)")
    motor_force_n: Var[float] = var(
        "task_status", "f8", (), 0.0, "N",
        doc="jaw force from the motor current monitor (40 N/A x |current|; not a force sensor)")
    jaw_m: Var[float] = var(
        "task_status", "f8", (), 0.0, "m",
        doc="estimated jaw opening (tach integrated from the open stop; valid when gripper.jaw_known)")
    jaw_known: Var[bool] = var("task_status", "b1", (), False,
                               doc="gripper.jaw_m is an estimate (an open reached the stop since the power-up)")
    rate_cmd_m_s: Var[float] = var(
        "task_io", "f8", (), 0.0, "m/s",
        doc="gripper drive command for Data Acquisition (opening positive; 0.05 m/s = 10 V)")
    msp_done_seq: Var[int] = var("task_io", "i4", (), 0,
                                 doc="the path planner's gripper request (msp.gripper_seq) answered last")
    msp_done_code: Var[int] = var("task_io", "i2", (), 0,
                                  doc="its answer: 2 COMPLETE 3 REFUSED 4 FAILED (1 while IN PROGRESS)",
                                  enum=RESPONSE_ENUM)
    event_seq: Var[int] = var("task_io", "i4", (), 0,
                              doc="counts the user's gripper requests accepted (a path recording stores each)")
    event: Var[int] = var("task_io", "i2", (), 0, doc="the last accepted request (1 OPEN 2 CLOSE 3 STOP 4 FORCE)",
                          enum=GripperRequest)
    event_force_n: Var[float] = var("task_io", "f8", (), 0.0, "N", doc="the grip force in force after it")


GRIP = GripperVars


def gripper_specs() -> list[VarSpec]:
    """The gripper's world-model variables (:class:`GripperVars`; declared by Servo Control)."""
    return GRIP.specs()


class PathGripperVars(VarGroup, prefix="msp", writer="msp"):
    """The path planner's gripper request: posted by the Multi-Segment Path Planner (writer
    ``msp``), read by Servo Control's gripper drive (declared here, where it is read)."""

    gripper_request: Var[int] = var("task_io", "i2", (), 0,
                                    doc="path playback's gripper request: 1 OPEN 2 CLOSE 3 STOP 4 FORCE",
                                    enum=GripperRequest)
    gripper_force_n: Var[float] = var("task_io", "f8", (), 0.0, "N", doc="its grip force (0 keeps the present one)")
    gripper_seq: Var[int] = var(
        "task_io", "i4", (), 0,
        doc="path playback's gripper request number (Servo Control answers in gripper.msp_done_*)")


MSP_GRIP = PathGripperVars
#: a path's gripper step as Servo Control reads it: the Joint Planner's copy (controller/relays.py)
_MG = {n: at("servo", n) for n in MSP_GRIP.all()}


def path_request_specs() -> list[VarSpec]:
    """The path planner's gripper request (declared by the Multi-Segment Path Planner)."""
    return MSP_GRIP.specs()


def text_words(text: str, n: int = GRIPPER_TEXT_BYTES) -> np.ndarray:
    raw = text.encode()[:n]
    words = np.zeros(n, dtype=np.uint8)
    words[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)
    return words


class GripperDrive:
    """Servo Control's seventh amplifier: requests, the motion, the outputs (module doc).

    :param layer: the Servo Control layer (its decided status, fault, brake phase, latched
        parameters and the current-limit vector it posts)
    """

    _IN = (GRIP.request, GRIP.request_force_n, GRIP.request_seq, DAQ.gripper_rate_m_s,
           DAQ.gripper_current_a)
    _MSP = tuple(_MG.values())

    def __init__(self, layer) -> None:
        self.layer = layer
        self.motion = GripperMotion()
        self._seen_user = 0
        self._seen_msp = 0
        self._has_msp: bool | None = None
        self._active: tuple[str, int] | None = None  # ("user" | "msp", seq) of the move in progress
        self._posted_limit: float | None = None  # the gripper current limit last posted (None: off)
        self._posted: dict = {}  # status values last posted
        self._events = 0
        self.answers: list[tuple[str, int, int, str]] = []  #: (channel, seq, code, text), the last 32

    # --- the periodic task ---------------------------------------------------------------
    def task(self, rt: "LayerContext") -> None:
        """``gripper_control``: power, requests, one motion update, the outputs."""
        wm = rt.wm
        if self._has_msp is None:
            self._has_msp = all(n in set(wm.names()) for n in self._MSP)
        v = wm.get_task_inputs(self._IN + self._MSP if self._has_msp else self._IN)
        layer = self.layer
        t = rt.now
        on = (layer.decided == Status.START_UP_COMPLETE and not layer.fault and layer.sup is not None
              and layer.brake_phase == _LOOP_CLOSED)
        if on and not self.motion.powered:
            cap = float(layer.params["current_limit_a"][GRIPPER_LIMIT_INDEX]) * GRIPPER.force_per_amp
            self.motion.set_force_cap(cap)
        ended = self.motion.power(on, t)
        if ended is not None:
            self._ended(rt, ended)
        if not on:
            self._posted_limit = None  # the safe stop zeroed every limit: post it again at the next power-up
        seq = int(v[GRIP.request_seq])
        if seq != self._seen_user:
            self._seen_user = seq
            self._request(rt, "user", seq, int(v[GRIP.request]), float(v[GRIP.request_force_n]))
        if self._has_msp:
            mseq = int(v[_MG[MSP_GRIP.gripper_seq]])
            if mseq != self._seen_msp:
                self._seen_msp = mseq
                if mseq:
                    self._request(rt, "msp", mseq, int(v[_MG[MSP_GRIP.gripper_request]]), float(v[_MG[MSP_GRIP.gripper_force_n]]))
        ended = self.motion.update(t, float(v[DAQ.gripper_rate_m_s]), float(v[DAQ.gripper_current_a]))
        if ended is not None:
            self._ended(rt, ended)
        self._publish(rt, on)

    def halted(self, rt: "LayerContext") -> None:
        """Between frames while halted (no task runs): a new user request is REFUSED at once
        (it is not kept to run after the resume)."""
        seq = int(rt.wm.get(GRIP.request_seq))
        if seq != self._seen_user:
            self._seen_user = seq
            self._answer(rt, "user", seq, REFUSED, "the controller is HALTED: outputs held safe, the gripper "
                                                   "drive off; send it again after the resume")

    # --- requests and answers -------------------------------------------------------------
    def _request(self, rt: "LayerContext", channel: str, seq: int, kind: int, force_n: float) -> None:
        name = ACTION_NAMES.get(kind, str(kind)).upper()
        if kind in (GripperRequest.OPEN, GripperRequest.CLOSE) and not self.motion.powered:
            st = Status(int(self.layer.decided)).name.replace("_", " ") if 0 <= self.layer.decided <= 9 else "?"
            why = "in ERROR" if self.layer.fault else f"{st}"
            self._answer(rt, channel, seq, REFUSED, f"{name}: Servo Control is {why}: the gripper drive is off "
                                                    f"(power up first)")
            return
        was_moving = self.motion.moving
        out = self.motion.request(kind, force_n, rt.now)
        if out.code == REFUSED:
            self._answer(rt, channel, seq, REFUSED, f"{name}: {out.text}")
            return
        if self._active is not None and kind != GripperRequest.FORCE and was_moving:
            old = self._active
            self._active = None
            self._answer(rt, old[0], old[1], FAILED, f"superseded by {channel} request {seq} ({name})")
        if out.code == IN_PROGRESS:
            self._active = (channel, seq)
        self._answer(rt, channel, seq, out.code, f"{name}: {out.text}")
        if channel == "user":
            self._events += 1
            rt.wm.post_task_outputs("servo", {GRIP.event_seq: self._events, GRIP.event: int(kind),
                                              GRIP.event_force_n: self.motion.force_n})

    def _ended(self, rt: "LayerContext", out: Outcome) -> None:
        if out.code == NOTE or self._active is None:
            rt.post("servo", Level.WARNING if out.code in (NOTE, FAILED) else Level.INFO, f"gripper: {out.text}")
            return
        channel, seq = self._active
        self._active = None
        self._answer(rt, channel, seq, out.code, out.text)

    def _answer(self, rt: "LayerContext", channel: str, seq: int, code: int, text: str) -> None:
        lvl = Level.WARNING if code in (REFUSED, FAILED) else Level.INFO
        rt.post("servo", lvl, f"gripper {'request' if channel == 'user' else 'path request'} {seq}: {text} "
                              f"-> {_RESPONSE_NAMES.get(code, code)}")
        self.answers = (self.answers + [(channel, seq, code, text)])[-32:]
        if channel == "user":
            rt.wm.post_task_outputs("servo", {GRIP.response: code, GRIP.response_seq: seq,
                                              GRIP.response_text: text_words(text)})
        else:
            rt.wm.post_task_outputs("servo", {GRIP.msp_done_seq: seq, GRIP.msp_done_code: code})

    # --- outputs ------------------------------------------------------------------------
    def _publish(self, rt: "LayerContext", on: bool) -> None:
        m = self.motion
        out: dict = {}
        jaw = m.jaw_m
        now = {GRIP.state: int(m.state), GRIP.force_n: m.force_n, GRIP.motor_force_n: m.motor_force_n,
               GRIP.jaw_m: jaw if jaw is not None else 0.0, GRIP.jaw_known: jaw is not None,
               GRIP.rate_cmd_m_s: m.rate_cmd_m_s}
        for k, val in now.items():
            if self._posted.get(k) != val:
                self._posted[k] = val
                out[k] = val
        if on and m.current_limit_a != self._posted_limit:
            self._posted_limit = m.current_limit_a
            out["servo.current_limit_cmd_a"] = self.layer.limits_cmd(m.current_limit_a)
        if out:
            rt.wm.post_task_outputs("servo", out)
