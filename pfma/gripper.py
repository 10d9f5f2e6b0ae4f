"""The gripper's motion logic: open, close, stop and grip force, with a stall detection that
ends a move on contact. Pure Python, no I/O: the controller's Servo Control layer
(:mod:`controller.gripper`) and the script handle (:class:`bit3.handle.Rack`) each drive it
from what they read, and write what it commands.

Each :meth:`GripperMotion.update` takes the time, the jaw rate from the tach (m/s, opening
positive) and the motor current monitor (A); the motion holds the rate command
(:attr:`GripperMotion.rate_cmd_m_s`, m/s: the writer puts ``rate x k_w`` volts on DAC channel 6)
and the current limit (:attr:`GripperMotion.current_limit_a`, DAC channel 13).

* **OPEN / CLOSE** drive at :data:`GRIP_SPEED_M_S` with the current limit the grip force sets
  (``force / force_per_amp``). A move ends when the jaw **stalls**: its rate stays below
  :data:`STALL_SPEED_FRACTION` of the move's speed for :data:`STALL_TIME_S` (counted from
  :data:`START_GRACE_S` after the start). Then the motor current says why:

  - it draws at least :data:`DRIVE_CURRENT_FRACTION` of the limit: contact. Opening, the jaw
    is at its open stop: **OPEN** (rate 0; the jaw estimate is referenced to the full
    travel). Closing, the jaws press on an object or on each other: the command goes to full
    scale closing, so the amplifier saturates at the current limit and the jaws hold with the
    set grip force: **GRIPPING**, or **CLOSED** when the jaw estimate says nothing is between
    them (within :data:`JAW_EMPTY_M` of closed);
  - it draws less: the drive does not answer (PWM stage off, amplifier not enabled):
    **STALLED**, the move FAILED, rate 0.

  A move that has not stalled after :data:`MOVE_TIMEOUT_S` (the whole travel at the move
  speed, plus margin) is stopped and FAILED: the jaw kept moving, its tach is not believable.
* **STOP**: rate 0 (a grip is released: the jaws no longer press).
* **FORCE**: a new grip force, in force at once (a hold presses with it from the next update).
  Refused outside :data:`GRIP_FORCE_MIN_N` .. the cap (``force_max_n`` of the facts, lowered by
  the controller's current-limit parameter), naming the range.
* **Holding** (GRIPPING, CLOSED): when the jaw closes again for :data:`STALL_TIME_S` (the
  object slipped out or was taken away) the close resumes at the move speed and ends on the
  next stall (a NOTE says so).
* **Jaw opening**: not sensed (no position sensor). Estimated by integrating the tach from
  the open stop (the first OPEN that stalls there references it), and set to 0 when a close
  ends CLOSED; unknown before the first reference and after a power-down (no brake: the jaw
  may be moved by hand).

The figures are this project's assumptions (the IRSS report gives none), named once here and
in docs/simulated-arm.md "The gripper"; the jaw's own are :data:`pfma.arm.GRIPPER`.
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import NamedTuple

from pfma.arm import GRIPPER, GripperFacts

#: the speed of an open or close (assumed: 40 % of full scale, the whole travel in 5 s)
GRIP_SPEED_M_S = 0.02
#: the grip force until one is asked for (assumed: a light grip, 1 A)
GRIP_FORCE_N = 40.0
#: the smallest grip force (assumed: five times the jaw's Coulomb friction, so an open or a
#: close at that current limit still accelerates the jaw within START_GRACE_S)
GRIP_FORCE_MIN_N = 10.0
#: stall detection (assumed): the rate below this fraction of the move's speed ...
STALL_SPEED_FRACTION = 0.25
#: ... for this long ends a move
STALL_TIME_S = 0.1
#: stall detection starts this long after a move starts (the jaw accelerates from rest)
START_GRACE_S = 0.25
#: at a stall, a motor current below this fraction of the current limit means the drive does
#: not answer (no contact: nothing pushes back on a motor that draws no current)
DRIVE_CURRENT_FRACTION = 0.2
#: a close that stalls with the jaw estimate within this of closed has nothing between the jaws
JAW_EMPTY_M = 0.003
#: a move that has not stalled after this is stopped and FAILED: the whole travel at the move
#: speed plus 2 s
MOVE_TIMEOUT_S = GRIPPER.travel_m / GRIP_SPEED_M_S + 2.0


class GripperState(IntEnum):
    """``gripper.state``: what the jaw is doing."""

    OFF = 0  #: not powered (the controller is not START UP COMPLETE; current limit 0)
    STOPPED = 1  #: powered, rate 0 (after power-up, a STOP, a failed move)
    OPENING = 2
    CLOSING = 3
    OPEN = 4  #: an open ended at the open stop
    CLOSED = 5  #: a close ended with nothing between the jaws (jaw estimate at 0); holding
    GRIPPING = 6  #: a close ended on contact: the jaws press with the grip force
    STALLED = 7  #: a move stopped and the motor drew no current: the drive does not answer


class GripperRequest(IntEnum):
    """``gripper.request``: what a user (or a path) asks."""

    NONE = 0
    OPEN = 1
    CLOSE = 2
    STOP = 3
    FORCE = 4  #: set the grip force only (``force_n``)


#: the request words of the command line and of path files
ACTIONS = {"open": GripperRequest.OPEN, "close": GripperRequest.CLOSE, "stop": GripperRequest.STOP,
           "force": GripperRequest.FORCE}
ACTION_NAMES = {v: k for k, v in ACTIONS.items()}

#: outcome codes (the same numbers as the controller's request responses, controller.layers.Response)
IN_PROGRESS, COMPLETE, REFUSED, FAILED = 1, 2, 3, 4
#: an outcome that answers no request: something the jaw did by itself (a slip), a message only
NOTE = 5


class Outcome(NamedTuple):
    """The answer to a request, or the end of a move (``code``: IN_PROGRESS, COMPLETE, REFUSED,
    FAILED, NOTE)."""

    code: int
    text: str


def state_name(v: int) -> str:
    """``GripperState`` by name (``"GRIPPING"``), or the number."""
    try:
        return GripperState(int(v)).name
    except ValueError:
        return str(v)


def describe(state: int, force_n: float, motor_force_n: float, jaw_m: float | None) -> str:
    """The gripper in one line of at most 76 columns (the console's World Status and ``pfma
    wm``): its state, the grip force set and the motor's (from its current monitor), the jaw
    opening estimated from the tach, or "not known" (it is not sensed)."""
    jaw = f"jaw ~{jaw_m * 1e3:.0f} mm (tach estimate)" if jaw_m is not None else "jaw not known (not sensed)"
    return f"gripper {state_name(state)}  grip {force_n:.0f} N set, motor {motor_force_n:.0f} N  {jaw}"


def check_force(force_n: float, cap_n: float, facts: GripperFacts = GRIPPER) -> str:
    """Why ``force_n`` is not a grip force to use ("" when it is)."""
    top = min(cap_n, facts.force_max_n)
    if not (isinstance(force_n, (int, float)) and math.isfinite(force_n)):
        return f"grip force {force_n!r} is not a number"
    if top < GRIP_FORCE_MIN_N:
        return (f"the gripper's current limit allows {top:.0f} N, below the smallest grip force "
                f"{GRIP_FORCE_MIN_N:.0f} N: the gripper is disabled")
    if not GRIP_FORCE_MIN_N <= force_n <= top:
        return (f"grip force {force_n:g} N is outside {GRIP_FORCE_MIN_N:g}..{top:g} N "
                f"(current limit {GRIP_FORCE_MIN_N / facts.force_per_amp:g}..{top / facts.force_per_amp:g} A "
                f"at {facts.force_per_amp:g} N/A)")
    return ""


class GripperMotion:
    """The jaw's state machine (see the module doc).

    :param facts: the jaw (default :data:`pfma.arm.GRIPPER`)
    :param force_n: the grip force to start with
    :param force_cap_n: the largest grip force allowed (default the jaw's at I_max)
    """

    def __init__(self, facts: GripperFacts = GRIPPER, *, force_n: float = GRIP_FORCE_N,
                 force_cap_n: float | None = None) -> None:
        self.facts = facts
        self.speed_m_s = GRIP_SPEED_M_S
        self.force_cap_n = facts.force_max_n if force_cap_n is None else float(force_cap_n)
        self.force_n = min(float(force_n), self.force_cap_n)
        self.state = GripperState.OFF
        self.jaw_m: float | None = None  #: estimated opening (None: not known)
        self.rate_cmd_m_s = 0.0  #: the drive's rate command (m/s, opening positive)
        self.current_limit_a = 0.0  #: the drive's current limit (A)
        self.motor_force_n = 0.0  #: force_per_amp x |motor current| at the last update
        self._t0 = 0.0  # the move's start
        self._slow_since: float | None = None  # first slow sample of the present run
        self._last_t: float | None = None

    # --- what the owner asks ------------------------------------------------------------
    @property
    def moving(self) -> bool:
        return self.state in (GripperState.OPENING, GripperState.CLOSING)

    @property
    def powered(self) -> bool:
        return self.state != GripperState.OFF

    def power(self, on: bool, t_s: float) -> Outcome | None:
        """The drive may run (``on``: the controller is START UP COMPLETE, the script's outputs
        are armed) or not. Returns the end of a move cut short by a power-down."""
        if on:
            if self.state == GripperState.OFF:
                self.state = GripperState.STOPPED
                self.rate_cmd_m_s = 0.0
                self.current_limit_a = self.force_n / self.facts.force_per_amp
                self._last_t = t_s
            return None
        if self.state == GripperState.OFF:
            return None
        was = self.state
        self.state = GripperState.OFF
        self.rate_cmd_m_s = self.current_limit_a = 0.0
        self.jaw_m = None  # no brake: the jaw may be moved while the drive is off
        self._last_t = None
        if was in (GripperState.OPENING, GripperState.CLOSING):
            return Outcome(FAILED, f"{was.name} stopped: the gripper drive was switched off")
        return None

    def request(self, kind: int, force_n: float = 0.0, t_s: float = 0.0) -> Outcome:
        """Act on a request (``GripperRequest``; ``force_n`` > 0 also sets the grip force, 0
        keeps it). The answer: IN_PROGRESS (a move started; its end comes from
        :meth:`update`), COMPLETE, or REFUSED with the reason (nothing changed)."""
        try:
            kind = GripperRequest(int(kind))
        except ValueError:
            return Outcome(REFUSED, f"unknown gripper request {kind} (1 OPEN 2 CLOSE 3 STOP 4 FORCE)")
        if kind == GripperRequest.NONE:
            return Outcome(REFUSED, "no gripper request (1 OPEN 2 CLOSE 3 STOP 4 FORCE)")
        if force_n or kind == GripperRequest.FORCE:
            why = check_force(force_n, self.force_cap_n, self.facts)
            if why:
                return Outcome(REFUSED, why)
        if kind in (GripperRequest.OPEN, GripperRequest.CLOSE) and self.state == GripperState.OFF:
            return Outcome(REFUSED, "the gripper drive is off (power up first)")
        if force_n:
            self.force_n = float(force_n)
            if self.powered:
                self.current_limit_a = self.force_n / self.facts.force_per_amp
        set_text = f" at {self.force_n:.0f} N" if force_n else ""
        if kind == GripperRequest.FORCE:
            when = "" if self.powered else " (in force from the next power-up)"
            return Outcome(COMPLETE, f"grip force {self.force_n:.0f} N, current limit "
                                     f"{self.force_n / self.facts.force_per_amp:.3g} A{when}")
        if kind == GripperRequest.STOP:
            if self.state in (GripperState.OFF, GripperState.STOPPED, GripperState.OPEN, GripperState.STALLED):
                return Outcome(COMPLETE, f"not moving ({self.state.name}){set_text}")
            was = self.state
            self._stop(GripperState.STOPPED)
            return Outcome(COMPLETE, f"stopped ({was.name} ended){set_text}{self._jaw_text()}")
        if kind == GripperRequest.OPEN:
            if self.state == GripperState.OPEN:
                return Outcome(COMPLETE, f"already OPEN{set_text}")
            self._start(GripperState.OPENING, t_s)
            return Outcome(IN_PROGRESS, f"OPENING at {self.speed_m_s * 1e3:.0f} mm/s, {self.force_n:.0f} N")
        if self.state in (GripperState.GRIPPING, GripperState.CLOSED):
            return Outcome(COMPLETE, f"already {self.state.name} at {self.force_n:.0f} N")
        self._start(GripperState.CLOSING, t_s)
        return Outcome(IN_PROGRESS, f"CLOSING at {self.speed_m_s * 1e3:.0f} mm/s, {self.force_n:.0f} N")

    def set_force_cap(self, cap_n: float) -> None:
        """The largest grip force (the controller's current-limit parameter, latched at power-up);
        the grip force is lowered to it if need be."""
        self.force_cap_n = float(cap_n)
        if self.force_n > self.force_cap_n:
            self.force_n = max(self.force_cap_n, 0.0)

    # --- the periodic update ------------------------------------------------------------
    def update(self, t_s: float, rate_m_s: float, current_a: float) -> Outcome | None:
        """One sample of the jaw. Returns the end of a move (COMPLETE or FAILED) or a NOTE
        (a grip lost) when there is one."""
        if self.state == GripperState.OFF:
            return None
        dt = t_s - self._last_t if self._last_t is not None else 0.0
        self._last_t = t_s
        if self.jaw_m is not None and dt > 0:
            self.jaw_m = min(max(self.jaw_m + rate_m_s * dt, 0.0), self.facts.travel_m)
        self.motor_force_n = self.facts.force_per_amp * abs(current_a)
        if self.moving:
            slow = abs(rate_m_s) < STALL_SPEED_FRACTION * self.speed_m_s
            if slow and t_s - self._t0 >= START_GRACE_S:
                if self._slow_since is None:
                    self._slow_since = t_s
            else:
                self._slow_since = None
            if self._slow_since is not None and t_s - self._slow_since >= STALL_TIME_S - 1e-9:
                return self._stalled(t_s, current_a)
            if t_s - self._t0 > MOVE_TIMEOUT_S:
                was = self.state
                self._stop(GripperState.STOPPED)
                self.jaw_m = None
                return Outcome(FAILED, f"{was.name} did not end within {MOVE_TIMEOUT_S:g} s (no stall: "
                                       f"the jaw travels {self.facts.travel_m * 1e3:.0f} mm at "
                                       f"{self.speed_m_s * 1e3:.0f} mm/s); stopped: check its tach")
        elif self.state in (GripperState.GRIPPING, GripperState.CLOSED):
            if rate_m_s < -STALL_SPEED_FRACTION * self.speed_m_s:
                if self._slow_since is None:  # here: the first sample of a closing run
                    self._slow_since = t_s
                if t_s - self._slow_since >= STALL_TIME_S - 1e-9:
                    was = self.state
                    self._start(GripperState.CLOSING, t_s)
                    return Outcome(NOTE, f"grip lost while {was.name} (the jaw is closing: the object "
                                         f"slipped or was taken away); closing again")
            else:
                self._slow_since = None
        return None

    # --- internals ----------------------------------------------------------------------
    def _start(self, state: GripperState, t_s: float) -> None:
        self.state = state
        self._t0 = t_s
        self._slow_since = None
        self.rate_cmd_m_s = self.speed_m_s if state == GripperState.OPENING else -self.speed_m_s
        self.current_limit_a = self.force_n / self.facts.force_per_amp

    def _stop(self, state: GripperState) -> None:
        self.state = state
        self._slow_since = None
        self.rate_cmd_m_s = 0.0

    def _jaw_text(self) -> str:
        return f", jaw ~{self.jaw_m * 1e3:.0f} mm" if self.jaw_m is not None else ""

    def _stalled(self, t_s: float, current_a: float) -> Outcome:
        took = t_s - self._t0
        if abs(current_a) < DRIVE_CURRENT_FRACTION * self.current_limit_a:
            was = self.state
            self._stop(GripperState.STALLED)
            return Outcome(FAILED, f"{was.name}: the jaw did not move and its motor drew {abs(current_a):.2f} A "
                                   f"of the {self.current_limit_a:.2f} A limit: the drive does not answer "
                                   f"(PWM stage off? amplifier not enabled?)")
        if self.state == GripperState.OPENING:
            self._stop(GripperState.OPEN)
            self.jaw_m = self.facts.travel_m
            return Outcome(COMPLETE, f"OPEN: at the open stop after {took:.2f} s")
        self._slow_since = None
        self.rate_cmd_m_s = -self.facts.omega_fs_m_s  # full scale: the amplifier saturates at the limit
        if self.jaw_m is not None and self.jaw_m <= JAW_EMPTY_M:
            self.state = GripperState.CLOSED
            self.jaw_m = 0.0
            return Outcome(COMPLETE, f"CLOSED after {took:.2f} s: nothing between the jaws; holding at "
                                     f"{self.force_n:.0f} N")
        self.state = GripperState.GRIPPING
        jaw = (f"jaw ~{self.jaw_m * 1e3:.0f} mm" if self.jaw_m is not None
               else "jaw position not known (no open to the stop yet)")
        return Outcome(COMPLETE, f"GRIPPING after {took:.2f} s: contact, holding at {self.force_n:.0f} N; {jaw}")
