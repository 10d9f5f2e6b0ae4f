"""Fail-safe output policy: when the DAC may drive the arm, and when it must not.

Rules (issue "data-acquisition service", item 3; MVME 104 watchdog 15 ms, IRSS 3.4.2):

- Outputs start **SAFE**: DAC outputs disconnected from the field (P3 off) and every
  channel at 0 V. The arm is enabled only by an explicit command.
- **Arming** needs all of: the command area's ``arm_request`` set (``arm_enable``
  below), a *new* request number (the controller increments ``rearm_counter``,
  ``arm_request`` below; a number already used never arms again), a fresh command
  heartbeat, and every joint rate command at zero. So
  nothing jumps to a stale setpoint on (re-)arm.
- **Tripping**: in ARMED, a command heartbeat that has not changed for longer than
  the watchdog time, or a fault the service cannot explain, latches **FAULT**: every
  joint command and every current limit goes to 0 V (a current limit below 0.3 V
  sets the brakes), the event is posted to the message queue, and outputs stay
  safe until an explicit re-arm. ``arm_request`` cleared by the controller disarms
  to SAFE (an orderly stop, not a fault).
- **Refusing**: a command that is NaN, infinite or beyond its configured limit, or that
  was written by a process that does not hold the command area's claim, is refused
  (:meth:`OutputGuard.refuse`): ARMED -> SAFE (0 V, brakes set) with a message naming
  the field, the value and the limit (or the writer), never clipped and obeyed. An arm
  request with such a command is refused the same way. Re-arming needs a new request.
- **Halting** (IRSS halt / single step, docs/console.md): a halted controller keeps writing
  (a fresh heartbeat) 0 rates, 0 current limits and no arm request, with
  ``commands.mode`` = :data:`bit3.layout.MODE_HALTED`. The guard then holds **HALTED**
  (outputs 0 V, brakes set, named in the header and ``pfma stats``): not a fault and not a
  trip. Leaving HALTED needs an arm request with a new number (the re-arm), or the mode
  cleared (-> SAFE). A heartbeat that goes stale while HALTED is a watchdog FAULT like any
  other: the controller that was holding the halt is gone.
- **Honesty** (issue 28 item 5, docs/safety.md "Honest outputs"): every safe action goes
  through the DAC board. While the service's last DAC write failed
  (:attr:`OutputGuard.outputs_known_safe` False, set by the service) no trip or stop says
  "outputs safe": they say "outputs NOT known safe" instead.
- The heartbeat is judged on the **service's** clock: the service notes when it
  last saw the heartbeat counter change, so the two processes' clocks never need to
  agree.
"""

from __future__ import annotations

from bit3.layout import FaultCode, MessageCode, ServiceState  # the states as the Bit3 header publishes them
from pfma.clock import Clock

__all__ = ["OutputGuard", "ServiceState", "STOP_CODE", "HALT_CODE", "TRIP_PREFIXES"]

#: message code of the orderly stop's notice ("outputs safe: service stopped"): not a trip
STOP_CODE = MessageCode.STOP
#: how every trip and stop message of the service begins: "outputs safe" while the DAC
#: answers, "outputs NOT known safe" while its last write failed (docs/safety.md "Honest
#: outputs"); tools that count trips look for either
TRIP_PREFIXES = ("outputs safe", "outputs NOT known safe")
#: message code of the halt's notices (halted by the controller, halt released): not a trip
HALT_CODE = MessageCode.HALT


class OutputGuard:
    """Decides, frame by frame, whether commands reach the DAC.

    :param clock: the service's clock
    :param watchdog_s: command heartbeat time-out (15 ms, the MVME 104's, by default)
    :param post: callable(severity, code, text) posting to the message queue
    """

    def __init__(self, clock: Clock, watchdog_s: float = 0.015, post=None) -> None:
        if watchdog_s <= 0:
            raise ValueError("watchdog_s must be positive")
        self.clock = clock
        self.watchdog_s = watchdog_s
        self.post = post or (lambda severity, code, text: None)
        self.state = ServiceState.SAFE
        self.trips = 0
        self.refusals = 0  #: commands refused while they would have driven the arm
        self.reason = ""
        #: the first trip or refusal since the outputs were last armed (code, reason, clock
        #: time): the root of the episode, not the notices after it; None once armed again
        self.first_trip: tuple[int, str, float] | None = None
        self._hb: int | None = None  # last heartbeat counter seen
        self._hb_t = -1e300  # when it last changed (service clock)
        self._arm_request_used: int | None = None  # arm_request value that armed or was refused last
        self._ever_seen = False
        self._pending_notice: int | None = None
        #: False while the service's last DAC write failed (the DAC board not answering):
        #: the outputs may hold their last values, and no message calls them safe
        self.outputs_known_safe = True

    def outputs_word(self) -> str:
        """How trips and stops name the outputs: "outputs safe" only while the DAC answers."""
        return "outputs safe" if self.outputs_known_safe else "outputs NOT known safe"

    def heartbeat_age_s(self) -> float:
        return self.clock.now() - self._hb_t

    def update(self, heartbeat: int, arm_enable: bool, arm_request: int, rates_zero: bool,
               refusal: str | None = None, stall_note: str = "", halted: bool = False) -> bool:
        """Feed this frame's command-area values; return True when commands may drive the DAC.

        :param refusal: why this frame's command must not drive the arm (a field beyond its
            limit, a foreign writer), or None; refused while ARMED -> SAFE, at arming ->
            the arm request is refused
        :param stall_note: appended to a heartbeat trip's reason when the service itself
            was stalled during the heartbeat's age (names the host stall as the cause)
        :param halted: the command area says the controller is halted (``mode`` =
            ``MODE_HALTED``): ARMED or SAFE -> HALTED while the heartbeat is fresh
        """
        now = self.clock.now()
        if heartbeat != self._hb:
            self._hb = heartbeat
            self._hb_t = now
        fresh = self._ever_seen and (now - self._hb_t) <= self.watchdog_s
        self._ever_seen = True
        if self.state == ServiceState.ARMED:
            if not fresh:
                self.trip(self._stale_text(now - self._hb_t, stall_note), code=FaultCode.WATCHDOG)
            elif refusal is not None:
                self.refuse(refusal)
            elif not arm_enable:
                if halted:
                    self._halt()
                else:
                    self.state = ServiceState.SAFE
                    self.post(0, MessageCode.DISARMED, "disarmed by command")
            return self.state == ServiceState.ARMED
        if self.state == ServiceState.HALTED and not fresh:
            self.trip(self._stale_text(now - self._hb_t, stall_note) + " (halted)", code=FaultCode.WATCHDOG)
            return False
        if arm_enable and arm_request != self._arm_request_used and self.state in (
                ServiceState.SAFE, ServiceState.FAULT, ServiceState.HALTED) and not halted:
            if not fresh:
                # keep the request pending: a controller that is starting up may arm as
                # soon as its heartbeat is seen to move; say so once
                if self._pending_notice != arm_request:
                    self._pending_notice = arm_request
                    self.post(1, MessageCode.ARM_PENDING, "arm pending: command heartbeat not fresh")
                return False
            self._arm_request_used = arm_request
            if refusal is not None:
                self.refusals += 1
                self.post(2, MessageCode.ARM_REFUSED, f"arm refused: {refusal}")
            elif not rates_zero:
                self.post(1, MessageCode.ARM_RATES_NOT_ZERO, "arm refused: joint rate commands must be 0 when arming")
            else:
                self.state = ServiceState.ARMED
                self.reason = ""
                self.first_trip = None  # a new episode begins with the next trip
                self.post(0, MessageCode.ARMED, "armed")
                return True
        if halted and fresh and self.state == ServiceState.SAFE:
            self._halt()
        elif not halted and self.state == ServiceState.HALTED:
            self.state = ServiceState.SAFE
            self.post(0, HALT_CODE, "halt released: outputs stay safe until an arm request")
        return False

    def _halt(self) -> None:
        """ARMED or SAFE -> HALTED: outputs 0 V, brakes set; not a fault."""
        self.state = ServiceState.HALTED
        self.reason = "controller halted"
        self.post(0, HALT_CODE, "halted by the controller: outputs 0 V, brakes set")

    def check_between_frames(self, heartbeat: int, stall_note: str = "") -> bool:
        """Between frames: note ``heartbeat``; trip when ARMED and it is older than the
        watchdog. Returns True when this call tripped. Lets the service act on a stale
        heartbeat within a hook tick instead of at the next frame."""
        now = self.clock.now()
        if heartbeat != self._hb:
            self._hb = heartbeat
            self._hb_t = now
        if self.state == ServiceState.ARMED and now - self._hb_t > self.watchdog_s:
            self.trip(self._stale_text(now - self._hb_t, stall_note) + ("" if stall_note else " between frames"),
                      code=FaultCode.WATCHDOG)
            return True
        return False

    def _stale_text(self, age_s: float, stall_note: str) -> str:
        """The trip reason, short enough for one 56-byte queue entry with its prefix."""
        if stall_note:
            return f"stale heartbeat {age_s * 1e3:.0f}>{self.watchdog_s * 1e3:.0f} ms{stall_note}"
        return f"stale heartbeat {age_s * 1e3:.1f}>{self.watchdog_s * 1e3:.0f} ms"

    def refuse(self, reason: str, code: int = MessageCode.REFUSED) -> None:
        """A command that must not drive the arm: ARMED -> SAFE (outputs 0 V) and the reason
        posted as an error. Not a latched FAULT: the controller re-arms with a new request
        once its commands are valid again."""
        if self.state != ServiceState.ARMED:
            return
        self.state = ServiceState.SAFE
        self.refusals += 1
        self.reason = reason
        if self.first_trip is None:
            self.first_trip = (code, reason, self.clock.now())
        self.post(2, code, reason)

    def trip(self, reason: str, code: int = MessageCode.TRIPPED) -> None:
        """Latch FAULT (outputs to 0 V) and post the reason; idempotent while faulted."""
        if self.state in (ServiceState.FAULT, ServiceState.STOPPED):
            return
        self.state = ServiceState.FAULT
        self.trips += 1
        self.reason = reason
        if self.first_trip is None:
            self.first_trip = (code, reason, self.clock.now())
        self.post(2, code, f"{self.outputs_word()}: {reason}")

    def stop(self, reason: str = "service stopped") -> None:
        self.state = ServiceState.STOPPED
        self.reason = reason
        self.post(1 if self.outputs_known_safe else 2, STOP_CODE, f"{self.outputs_word()}: {reason}")
