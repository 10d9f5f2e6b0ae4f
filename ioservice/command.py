"""The command path: what the service makes of the command area in every frame, before the
DAC task converts and writes it (docs/safety.md).

In order, first in every frame (:meth:`CommandPath._task_dac`):

- **claim**: one bounded read of the command area and the claim check (the body's pid and
  token must be the owner slot's; a second writer on one claim is caught by its stream,
  ``ioservice.commandcheck``); an absent copy, a foreign write, two writers;
- **limits**: every engineering value finite and within its limit x (1 + margin), the
  direction check's restriction while joints are pending;
- **guard**: the output guard (``ioservice.safety.OutputGuard``) decides from the heartbeat,
  the arm request and the refusal whether the commands may drive the arm;
- **freshness**: the age of the inputs the command was computed from, in frames the service
  ran (dropped frames do not age it); beyond ``max_input_age_frames`` the rate channels are
  driven at 0 V;
- the motion envelope (slew, braking distance, overspeed), then the DAC task's conversion
  and write, or the safe zeros.

:class:`CommandPath` is a part of ``ioservice.service.IoService`` (its base class): the path
works on the service's own attributes, so the frame pays no extra lookup for it. A DAC that
stops answering is made known here too (:meth:`CommandPath._dac_not_answering`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from bit3.layout import (
    CMD_ABSENT, CMD_FOREIGN, CMD_REFUSED, CMD_STALE, MODE_HALTED, FaultCode, MessageCode, ServiceState, Severity,
)
from ioservice.envelope import CODE_OVERSPEED

if TYPE_CHECKING:
    from bit3.buffer import Bit3Buffer
    from ioservice.commandcheck import ClaimStreamCheck
    from ioservice.direction import DirectionCheck
    from ioservice.envelope import ServiceEnvelope
    from ioservice.safety import OutputGuard
    from ioservice.schedule import Schedule
    from ioservice.chargepump import ChargePump
    from ioservice.tasks import DacTask
    from pfma.clock import Clock
    from pfma.rack import CommandPolicy

#: a command's age is counted in frames the service ran over the last this-many-plus-one
#: frames (a ring of the dropped-frame count; an older command is stale whatever the count)
_AGE_RING_MASK = 63
#: internal: nobody holds the command area's claim (no controller yet); not published
_NO_WRITER = 0x100
#: _fetch_command: the body carries the claim's pid and token but its stream shows a second
#: writer (ioservice/commandcheck.py); not published (CMD_FOREIGN is, for the hold)
_TWO_WRITERS = 0x200
#: a stall is named in trips and stale-command messages for this long after it ended (the
#: time a controller needs to see new inputs and answer: two watchdog periods, assumed)
STALL_BLAME_S = 0.030


class CommandPath:
    """The command path of the I/O service (its base class; see the module's docstring).

    The attributes below are the service's, set up by ``IoService.__init__``."""

    clock: Clock
    buf: Bit3Buffer
    schedule: Schedule
    policy: CommandPolicy
    guard: OutputGuard
    dac: DacTask
    pump: ChargePump
    envelope: ServiceEnvelope
    direction: DirectionCheck | None
    state: ServiceState
    fault_code: int
    dac_unreachable: str | None
    faulted_boards: set[str]
    _v: dict
    _cv: dict
    _claim_check: ClaimStreamCheck
    _hb_ok: int | None
    _hb_seen: int | None
    _refusals_seen: int
    _cmd_episode: int
    _guard_state: ServiceState
    _stall_s: float
    _stall_end: float
    _env_status: list[int]
    _env_k: int
    _dropped_total: int
    _dropped_at: list[int]
    _bus_ok_t: float

    commands: Any  # the command area's reader (bit3.buffer)

    if TYPE_CHECKING:  # provided by the service
        def post(self, severity: int, code: int, text: str) -> None: ...

        def set_state(self, state: ServiceState) -> None: ...

        def board_error(self, board: str, err: Exception) -> None: ...

        def board_answered(self, board: str) -> None: ...

        def device_error(self, group: str) -> int: ...

    def _set_fault(self, code: FaultCode) -> None:
        """``fault_code`` (published every frame) as a plain int: numpy takes an int faster
        than the enum."""
        self.fault_code = int(code)

    # ------------------------------------------------------------------ claim
    def _fetch_command(self) -> int:
        """One bounded read of the command area (a writer killed mid-write leaves its
        counter odd: the frame goes on and the command counts as absent, the record keeps
        the last good copy) and the claim check (pid and token in the body must be the
        owner slot's). Returns 0 for a good command, CMD_ABSENT, CMD_FOREIGN, or
        _NO_WRITER (nobody holds the claim). Only a good command's heartbeat is noted in
        ``_hb_ok``: a foreign write never feeds the watchdog."""
        if not self.commands.try_read():
            return CMD_ABSENT
        c = self._cv
        pid, token = self.buf.owner_pid_token("commands")
        body_pid = int(c["writer_pid"])
        if pid <= 0 or body_pid == 0:  # nobody holds the claim, or the holder has not written yet
            return _NO_WRITER
        if body_pid != pid or int(c["writer_token"]) != token:
            return CMD_FOREIGN
        hb = int(c["heartbeat"])
        if self._claim_check.note(pid, token, self.commands.last_seq, hb, int(c["controller_frame"])):
            return _TWO_WRITERS  # the claim's stamps, but not one writer's stream: no heartbeat
        self._hb_ok = hb
        return 0

    def _foreign_write(self, new_write: bool) -> str:
        """The body is not the claim holder's: never obeyed; a new such write is counted.
        Returns the refusal."""
        pid, _tok = self.buf.owner_pid_token("commands")
        if new_write:
            self._v["foreign_writes"] += 1
        return f"refused write by pid {int(self._cv['writer_pid'])}: owner pid {pid}"

    def _two_writers(self, new_two: bool, two: str, refusal: str | None) -> str:
        """Two writers on the claim, now or within the hold: a new episode is counted and
        said (while ARMED the guard's refusal says it). Returns the frame's refusal: the one
        found before, else ``two``."""
        if new_two:
            self._v["foreign_writes"] += 1
            if self.guard.state != ServiceState.ARMED:
                self._announce(CMD_FOREIGN, two)
            self._cmd_episode |= CMD_FOREIGN
        return two if refusal is None else refusal

    # ------------------------------------------------------------------ limits
    def _check_limits(self, eng: list[float]) -> str | None:
        """The first command value that is not finite or beyond its limit (x (1 + margin)),
        as a message giving field, value and limit; then, while joints are pending, the
        direction check's refusal (:meth:`_direction`); None when the command is acceptable."""
        isfinite = math.isfinite
        dac = self.dac
        neg_margin = -self.policy.limit_margin
        for ch, (e, lim, is_lim) in enumerate(zip(eng, dac.refuse, dac.is_limit)):
            if not isfinite(e):
                bad = True
            elif is_lim:
                bad = e > lim or e < neg_margin * dac.limit[ch]
            else:
                bad = e > lim or e < -lim
            if bad:
                lo = "0.." if is_lim else "+-"
                return (f"refused {dac.names[ch]}={e:.4g} {dac.units[ch]}, "
                        f"limit {lo}{dac.limit[ch]:g}")
        c = self._cv
        for f in ("crl_reflect_force_n", "crl_reflect_torque_nm"):
            if not all(map(isfinite, c[f].tolist())):
                return f"refused {f} not finite"
        d = self.direction
        if d is not None and d.pending:
            return self._direction(eng)
        return None

    def _direction(self, eng: list[float]) -> str | None:
        """This frame's direction-check refusal (a pending joint moved the wrong way, or the
        command is not a direction-check move), None when there is none; posts what the
        check found (a joint confirmed, the record written)."""
        d = self.direction
        assert d is not None
        v = self._v
        why = d.observe(eng, v["rtd_angle_rad"], v["adc_value"], self.guard.state == ServiceState.ARMED)
        for sev, code, text in d.events:
            self.post((Severity.INFO, Severity.WARNING, Severity.ERROR)[sev], code, text)
        d.events.clear()
        return why or d.restriction(eng)

    # ------------------------------------------------------------------ messages, stalls
    def _announce(self, bits: int, text: str, severity: int = Severity.ERROR) -> None:
        """Post ``text`` when a command-status condition starts (not every frame it lasts)."""
        if not self._cmd_episode & bits:
            self._cmd_episode |= bits
            self.post(severity, MessageCode.COMMAND_STATUS, text)

    def _stall_note(self) -> str:
        """" (stall N ms)" while a recent host stall explains a late command, else "" (the
        stall itself was announced as "host stall: ..." when it ended)."""
        if self.clock.now() - self._stall_end <= STALL_BLAME_S:
            return f" (stall {self._stall_s * 1e3:.0f} ms)"
        return ""

    # ------------------------------------------------------------------ guard
    def _refused(self, status: int) -> None:
        """The guard refused a command: one refusal, one message (the guard's)."""
        self._refusals_seen = self.guard.refusals
        self._v["refused_commands"] += 1
        self._set_fault(FaultCode.FOREIGN if status & CMD_FOREIGN else FaultCode.COMMAND)

    def _guard_moved(self, gs: ServiceState) -> None:
        """The guard's state changed this frame, or it is FAULT: a trip not yet named gets
        the watchdog's code; a successful (re-)arm ends what made the outputs safe before."""
        v = self._v
        if gs == ServiceState.FAULT and self.state != ServiceState.FAULT:
            if self.fault_code == FaultCode.NONE:
                self._set_fault(FaultCode.WATCHDOG)
            v["watchdog_tripped"][...] = self.fault_code == FaultCode.WATCHDOG
        if gs == ServiceState.ARMED and self._guard_state != ServiceState.ARMED:
            self._set_fault(FaultCode.NONE)
            v["watchdog_tripped"][...] = 0
            self._cmd_episode = 0
        self._guard_state = gs

    # ------------------------------------------------------------------ the frame's command
    def _task_dac(self, k: int = 0) -> None:
        """The command path, first in every frame: fetch and check the command, update the
        safety guard, and have the DAC task convert and write it (or the safe zeros)."""
        v = self._v
        dac = self.dac
        status = self._fetch_command()
        c = self._cv
        refusal = None
        hb_now = int(c["heartbeat"])
        if status & CMD_ABSENT:
            v["absent_commands"] += 1
            self._announce(CMD_ABSENT, "command area: no stable copy (writer died mid-write?)",
                           Severity.WARNING)
        else:
            new_write = self._hb_seen is not None and hb_now != self._hb_seen
            self._hb_seen = hb_now
            if status & CMD_FOREIGN:
                refusal = self._foreign_write(new_write)
        new_two, two = self._claim_check.frame(k)
        if two is not None:  # two writers on the claim, now or within the hold
            status |= CMD_FOREIGN
            refusal = self._two_writers(new_two, two, refusal)
        status &= CMD_ABSENT | CMD_FOREIGN  # _NO_WRITER, _TWO_WRITERS are not published
        # engineering command per DAC channel, in plain Python (16 values)
        eng = [0.0] * dac.n
        rates = c["joint_rate_rad_s"].tolist()
        for ch, x in zip(dac.rate_list, rates):
            eng[ch] = x
        for ch, x in zip(dac.limit_list, c["current_limit_a"].tolist()):
            eng[ch] = x
        if dac.gripper_ch is not None:
            eng[dac.gripper_ch] = float(c["gripper"])
        if refusal is None:
            refusal = self._check_limits(eng)  # and the direction check's restriction
            if refusal is not None:
                status |= CMD_REFUSED
        guard = self.guard
        hb = self._hb_ok if self._hb_ok is not None else -1
        live = guard.update(hb, bool(c["arm_request"]), int(c["rearm_counter"]),
                            not any(rates), refusal=refusal, stall_note=self._stall_note(),
                            halted=int(c["mode"]) == MODE_HALTED)  # HALTED (issue 18): a halted controller
        if guard.refusals != self._refusals_seen:
            self._refused(status)
        v["command_heartbeat"][...] = hb if hb >= 0 else 0
        v["command_age_s"][...] = guard.heartbeat_age_s()
        gs = guard.state
        if gs != self._guard_state or gs == ServiceState.FAULT:
            self._guard_moved(gs)
        # freshness: how old are the inputs these commands were computed from?
        f_in = int(c["inputs_frame"])
        age = k - f_in
        if 0 < age <= _AGE_RING_MASK:
            # counted in frames the service ran: frames it dropped (it did not run, so no newer
            # inputs existed for the controller to answer) do not age the command
            age -= self._dropped_total - self._dropped_at[f_in & _AGE_RING_MASK]
        v["command_inputs_frame"][...] = f_in
        v["command_input_age_frames"][...] = age if 0 <= age < 0xFFFFFFFF else 0xFFFFFFFF
        # the envelope's judgement, then the DAC: the command converted and written while
        # live (the rate channels at 0 V when the inputs it answers are too old), else the zeros
        env = self.envelope
        over = env.sample(v["rtd_angle_rad"], v["adc_value"], float(v["t_rtd_s"]))
        if over is not None and live:  # the envelope's overspeed: every channel 0 V, brakes set
            self._set_fault(FaultCode.OVERSPEED)
            self.guard.trip(over, code=CODE_OVERSPEED)
            live = False
        if not live:
            v["command_status"][...] = status
            # a condition that ended may be announced again; refusals stay announced until re-armed
            self._cmd_episode &= status | CMD_REFUSED | CMD_FOREIGN
            env.reset()
            self._apply_safe()
            return
        if not dac.enabled:
            dac.enable()  # the shadow holds the zeros written while safe
        stale = age < 0 or age > self.policy.max_input_age_frames
        if stale:
            status |= CMD_STALE
            v["stale_commands"] += 1
            self._announce(CMD_STALE, f"rates 0V: cmd inputs {age} fr old > "
                                      f"{self.policy.max_input_age_frames}{self._stall_note()}")
        self._cmd_episode &= status | CMD_REFUSED | CMD_FOREIGN
        v["command_status"][...] = status
        est = self._env_status
        if not stale:
            for ch in dac.rate_list:
                est[ch] = 0
            env.apply(eng, self.schedule.period_s * max(1, k - self._env_k), est)
        else:
            env.reset()
        self._env_k = k
        volts, st_out = dac.volts(eng, stale)
        if not stale:
            for ch in dac.rate_list:
                st_out[ch] |= est[ch]
        self._write_dac(volts, st_out, eng)

    def _apply_safe(self) -> None:
        if self.state == ServiceState.ARMED or self.guard.state == ServiceState.FAULT:
            self.set_state(self.guard.state)
        self._write_dac(self.dac.zeros, self.dac.forced_safe, self.dac.zeros)

    # ------------------------------------------------------------------ the DAC write
    def _write_dac(self, volts: list[float], status: list[int], eng: list[float]) -> None:
        """The DAC task's write; the bus and the board's health, the service's state, and
        the amplifier-enable charge pump (one edge per frame while ARMED and the DAC answers)."""
        dac = self.dac
        t = self.clock.now()
        err = dac.write(volts, status, eng, t, self.guard.state == ServiceState.ARMED)
        if err is None:
            self._bus_ok_t = t
            if self.faulted_boards:
                self.board_answered(dac.cfg.name)
            if self.dac_unreachable is not None:
                self._dac_answering_again(volts)
            if self.guard.state != self.state and self.state != ServiceState.STOPPED:
                self.set_state(self.guard.state)
        else:
            self._dac_not_answering(err)
        self.pump.frame(err is None and self.guard.state == ServiceState.ARMED)

    def _dac_not_answering(self, err: Exception) -> None:
        """A DAC write failed: every safe action of the service, its stop and the output
        guardian go through this board, so nothing in software can make the outputs safe
        now. FAULT with FaultCode.DAC_UNREACHABLE and one message saying so, naming what the
        outputs may hold and what to do (the guard trips, or says it when already FAULT);
        later failures of the same episode are counted, not said again, unless a re-arm made
        the service ARMED meanwhile: that is a new trip, said by the guard."""
        self.board_error(self.dac.cfg.name, err)
        self.device_error("dac")
        self._set_fault(FaultCode.DAC_UNREACHABLE)
        guard = self.guard
        guard.outputs_known_safe = False
        text = self.dac_unreachable
        first = text is None
        if text is None:
            text = self.dac_unreachable = (
                f"DAC not answering ({err}): its outputs may hold their last values "
                f"({self.dac.last_values_text()}); {self.pump.stopped_text()}; press the hardware "
                f"E-stop if the arm moves; the service keeps writing 0 V every frame")
        was = guard.state
        # a re-arm while the board is still silent trips again (and says so once more)
        guard.trip(text, code=FaultCode.DAC_UNREACHABLE)
        if first and was in (ServiceState.FAULT, ServiceState.STOPPED):  # the guard said nothing
            self.post(Severity.ERROR, FaultCode.DAC_UNREACHABLE, f"{guard.outputs_word()}: {text}")

    def _dac_answering_again(self, volts: list[float]) -> None:
        """The first write that succeeded after :meth:`_dac_not_answering`: the outputs are
        known again (0 V: the guard is FAULT, so the zeros were written); FAULT stays until a
        re-arm."""
        self.dac_unreachable = None
        self.guard.outputs_known_safe = True
        if self.fault_code == FaultCode.DAC_UNREACHABLE:
            self._set_fault(FaultCode.DAC)
        zero = not any(volts)
        self.post(Severity.WARNING, FaultCode.DAC,
                  "DAC answering again: outputs " + ("0 V" if zero else "written")
                  + f"; the service stays {self.guard.state.name} until re-armed")
