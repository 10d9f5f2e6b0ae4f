"""The data-acquisition service: the I/O chassis of the PFMA rack, in one process.

It owns the drivers of every board in the rack configuration and runs them on the
acquisition schedule (``ioservice.schedule``): DAC outputs every 3.125 ms minor
frame (320 Hz), resolvers and ADC every second frame (160 Hz), the F/T sensor and
the serial hand controller every fourth (80 Hz), the parallel ports every eighth.
Each frame's inputs carry the time they were sampled. Everything is published in
the Bit3 buffer's input area (one seqlocked copy per frame); commands are taken
from its command area; ``ioservice.safety.OutputGuard`` decides whether they may
reach the DAC.

The device work is done by one task object per device class (``ioservice.tasks``:
RtdTask, AdcTask, DacTask, FtTask, HandTask, PioTask), each wired once at start and run
in the frames the schedule gives it, and sees the service only through
``ioservice.host.TaskHost``; :meth:`IoService.frame` runs the command path
(``ioservice.command``, the service's base class: claim, limits, refusals, watchdog,
safety guard, freshness, envelope, then the DAC task's conversion and write) and then the
input tasks due. The drivers do every count <-> unit conversion; the tasks apply the
rack's scales and the calibration.

Serial lines are drained between frames by the ``TickingClock`` hook
(:meth:`IoService.serial_tick`), at the start and end of each frame and between its
tasks when the frame runs long: their FIFOs are 3 characters deep and fill in
1.56 ms at 19200 baud. Decoding happens only in the F/T and hand tasks.

The service knows schedules, the buffer and safety; it asks the rack
configuration for channels and the drivers for registers, and never uses a
register offset itself.
"""

from __future__ import annotations

import math
from typing import Any
import os
import resource
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bit3.layout import (  # noqa: F401 - the status bits are re-exported for older importers
    BOARD_FAULT, BOARD_INIT, BOARD_OK, CHANNEL_BUS_ERROR, CMD_ABSENT, CMD_FOREIGN, CMD_REFUSED, CMD_STALE,
    DAC_CLIPPED, DAC_FORCED_SAFE, LINK_FAULT, LINK_OPEN, LINK_STALE, LINK_SYNCED, RTD_NO_REFERENCE, ServiceState,
    Severity,
)
from bit3.layout import FIRST_TRIP_TEXT_BYTES, FaultCode, MessageCode
from bit3.layout import (  # noqa: F401 - inputs.fault_code values, re-exported for older importers
    FAULT_AMP_ENABLE, FAULT_COMMAND, FAULT_DAC, FAULT_DAC_UNREACHABLE, FAULT_FOREIGN, FAULT_INPUTS, FAULT_NONE,
    FAULT_OVERSPEED, FAULT_UNEXPECTED, FAULT_WATCHDOG,
)
from ioservice.chargepump import ChargePump
from ioservice.command import _AGE_RING_MASK, CommandPath
from ioservice.envelope import ServiceEnvelope
from ioservice.commandcheck import TWO_WRITER_HOLD_S, ClaimStreamCheck
from ioservice.direction import DirectionCheck
from ioservice.loop import FrameInfo, FrameLoop, LoopStats
from ioservice.safety import OutputGuard
from ioservice.schedule import (
    BUS_SHARE, BUS_TASKS, MINOR_FRAMES_PER_MAJOR, BusTooSlow, Schedule, busiest_frame, describe_rates, fits,
    slower_schedules,
)
from ioservice.tasks import (  # noqa: F401 - the F/T and brake constants are re-exported
    BRAKE_RELEASE_V, FT_START_ATTEMPTS, FT_STALE_S, AdcTask, DacTask, FtTask, HandTask, InputTask, PioTask, RtdTask,
)
from bit3.buffer import Bit3Buffer
from pfma.clock import Clock
from pfma.errors import BusError, ConfigError, PfmaError
from pfma.rack import BoardConfig, RackConfig
from drivers.rackio import RackIO

# the fault codes (inputs.fault_code: FAULT_NONE ... FAULT_OVERSPEED) and their names are
# bit3.layout's (imported above): the service writes them, the controller and tools read them
#: the command path's constants (the age ring, the stall blame) are ioservice/command.py's
#: consecutive failing samples of an input board before the outputs are made safe
INPUT_FAULT_FRAMES = 3
#: serial FIFO drains (``IoService.serial_tick``) closer together than this are skipped: at
#: 19200 baud the MVME400's 3-character Rx FIFO takes 1.56 ms to fill, so with a drain at
#: each task boundary a task may take up to about 1.1 ms (a 32-channel ADC scan on a busy
#: host) without losing characters
SERIAL_MIN_GAP_S = 0.0004
#: tick of the ``TickingClock`` a live service sleeps on (hooks: the serial drain, the
#: simulated rack): wake-up latency on a shared VM (p99 ~0.85 ms measured) plus this tick
#: must stay under the FIFO's 1.56 ms; at 0.7 ms one F/T record in ten was lost to
#: overruns on the simulated rack, at 0.4 ms one in fifty (``bench/bench_service.py``)
LIVE_TICK_S = 0.0004
#: an F/T slot that found no new record (characters lost, decoder re-syncing) is tried
#: again in this many following minor frames, so the record is published a frame or two
#: late instead of a whole F/T period (12.5 ms) late
FT_RETRY_FRAMES = 2
#: a gap this long with no frame and no hook tick of the service is a host stall (the
#: machine, or this process, did not run): recorded in ``inputs.host_stall_s`` and named
#: as the cause of a watchdog trip or stale command it explains. Assumed: 10 ms, well
#: above the wake-up jitter of a shared VM (p99 ~0.85 ms) and below the 15 ms watchdog
HOST_STALL_S = 0.010
#: a frame whose own run takes longer than HOST_STALL_S is posted as a "long frame" with its
#: measured length, at most once per this many seconds (the others counted in the next notice)
LONG_FRAME_NOTICE_S = 1.0
#: between frames the command heartbeat is checked at most this often (the hooks tick
#: every ``LIVE_TICK_S`` for the serial FIFOs; the watchdog is 15 ms, so a check every
#: 1 ms makes the reaction to a dead controller the watchdog plus at most 1 ms plus a
#: tick, and costs ~900 command reads a second instead of ~2200)
HEARTBEAT_CHECK_S = 0.001
#: attempts at a board's start-up transactions before it is marked FAULT (bus errors only;
#: an unreachable gateway is not tried again). Assumed: 3, enough for a time-out on a
#: loaded host, few enough that a missing board costs three bus time-outs
INIT_ATTEMPTS = 3
#: no register transaction has succeeded for this long (every board failing: a gateway that
#: stopped answering, a bus adapter gone): the bus is lost and the service stops, its outputs
#: already safe (the first failed DAC write tripped the guard). Assumed: 0.5 s, long enough
#: to ride through a gateway's reconnect, short enough that a dead bus ends a run promptly
BUS_LOST_S = 0.5
#: start-up measurement of the bus: each task's transactions are timed this many times, in
#: rounds, and the median is kept (a burst of host load in a few rounds does not condemn the
#: bus, nor a few fast rounds acquit it). Assumed: 11 (about 0.1 s over a loopback gateway)
BUS_PROBE_REPEATS = 11
#: message code of a rack-file or calibration value accepted outside the nominal band by
#: the rack file's ``[checks] allow_nonnominal`` (pfma/nominal.py), posted at start
NONNOMINAL_CODE = MessageCode.NONNOMINAL
#: the MVME400's receive FIFO: 3 characters, full 1.56 ms after the last drain at 19200
#: baud (10 bits a character). Over a register gateway every drain is a network round
#: trip, so the serial lines are not opened there (the F/T may come from a local port)
SERIAL_FIFO_FILL_S = 3 * 10 / 19200


@dataclass
class _DeviceCounter:
    samples: int = 0
    errors: int = 0
    t_last: float = math.nan
    window_samples: int = 0
    window_t0: float = math.nan
    rate_hz: float = 0.0


#: statistics asked for by a frame are published between frames; if no sleep long enough
#: for the clock's hooks comes within this many frames, the frame publishes them itself
STATS_MAX_DEFER_FRAMES = 16


class IoService(CommandPath):
    """The I/O service over any RegisterBus.

    :param rack: rack configuration (boards, channels, scales)
    :param bus: RegisterBus (fake rack, Modbus gateway, device-file window)
    :param buffer: the Bit3 buffer; the service claims its ``service`` role
    :param clock: the loop's clock (a ``TickingClock`` so serial lines are drained)
    :param schedule: acquisition schedule (default: the report's rates at 320 Hz)
    :param watchdog_s: command heartbeat time-out (15 ms: the MVME 104's watchdog)
    :param owner: name written into the buffer's owner slot
    :param serial: open the F/T and CRL lines of the MVME400 (off for racks without them)
    :param calibration: calibration file path or loaded ``calibration.files.Calibration``,
        applied before the drivers are wired (see the "calibration" section at the end)
    :param max_input_age_frames: rate channels are driven only from commands computed from
        inputs at most this many frames old (default: the rack file's ``[commands]``, 4);
        refused with a ConfigError if it exceeds the watchdog
    :param bus_name: how messages name the bus (``modbus://HOST:PORT``); default: the bus's
        own ``describe()``, or its type
    :param direction_state: the direction-check state file (``ioservice.direction``): the
        scale signs a direction check last confirmed; when the running signs differ, arms
        are direction-check arms until each changed joint has moved as commanded. None
        (default): no direction check
    :param simulated: whether the rack is simulated (the register-level fakes), published as
        ``OWNER_FLAG_SIMULATED`` in the service's owner slots of the Bit3 header so every
        tool can say so; default (None): :func:`bus_is_simulated`
    """

    def __init__(self, rack: RackConfig, bus, buffer: Bit3Buffer, clock: Clock, *,
                 schedule: Schedule | None = None, watchdog_s: float = 0.015,
                 owner: str = "pfma-ioservice", serial: bool = True, calibration=None,
                 ft_port: str | None = None, max_input_age_frames: int | None = None,
                 bus_name: str | None = None, simulated: bool | None = None,
                 direction_state: str | Path | None = None) -> None:
        self.calibration = None  # calibration: the loaded calibration in force (None = nominal)
        if calibration is not None:
            rack, self.calibration = _calibrated_rack(rack, calibration)
        self.rack = rack
        self.bus = bus
        self.buf = buffer
        self.clock = clock
        self.schedule = schedule or Schedule()
        self.watchdog_s = watchdog_s
        self.bus_name = bus_name or _bus_name(bus)
        #: a register gateway's ``HOST:PORT`` (a bus with a ``gateway`` attribute, as
        #: ``drivers.bus.modbus.ModbusTcpBus``), None for a local bus
        gateway = getattr(bus, "gateway", None)
        self.gateway: str | None = gateway if isinstance(gateway, str) else None
        self.layout = buffer.layout
        self.policy = _command_policy(rack, self.schedule, watchdog_s, max_input_age_frames)
        #: the rack is simulated (published in the header's owner slots: HeaderInfo.rack_kind)
        self.simulated = bus_is_simulated(bus) if simulated is None else bool(simulated)
        self._init_areas(owner)
        self._init_command_state()
        self.loop_stats = LoopStats()
        self.loop = FrameLoop(clock, self.schedule.period_s, self.frame, self.loop_stats)
        self.io = RackIO(bus, rack, clock)
        self.state = ServiceState.STARTING
        self._set_fault(FaultCode.NONE)
        self._init_counters()
        self._init_tasks(serial, ft_port)
        self._cpu0 = self._cpu_s()
        self._wall0 = clock.now()
        self.stats_every = max(1, int(round(self.schedule.frame_rate_hz / 2)))  # twice a second
        self._stats_between_frames = False  # True while run() has idle_tick on the clock
        self._stats_due_k: int | None = None  # frame that asked for statistics not yet published
        self._last_hb_check = -math.inf  # clock time of idle_tick's last heartbeat check
        self.set_state(ServiceState.SAFE)
        self.post(Severity.INFO, MessageCode.STARTED, f"service started: {rack.name}, "
                  f"{self.schedule.frame_rate_hz:g} Hz frames, watchdog {watchdog_s * 1e3:g} ms")
        for diff in self.schedule.check_documented_rates():
            self.post(Severity.WARNING, MessageCode.SCHEDULE_DIFFERS,
                      f"schedule differs from the report and the rack file's rate_hz: {diff}")
        self._say_overrides(self.calibration)
        self._direction_path = direction_state
        self.direction: DirectionCheck | None = None  #: the direction check (None: not kept)
        self._start_direction_check()

    # ------------------------------------------------------------------ set-up
    def _init_areas(self, owner: str) -> None:
        """Claim the service's role in the Bit3 buffer; its writers, the command reader, the
        message queue, and the field views of the records they fill in place."""
        buffer = self.buf
        buffer.claim("service", owner, simulated=self.simulated)
        self.inputs = buffer.writer("inputs")
        #: optional ``bit3.ring.FrameRing``: every published inputs body is also
        #: appended there (``pfma serve`` creates it for recorders)
        self.ring = None
        self.stats_writer = buffer.writer("stats")
        self.commands = buffer.reader("commands")
        #: the command area's record (the reader's, refreshed in place by each good read)
        self.command = self.commands.record
        #: views of the command record's fields
        self._cv = {name: self.commands.record[name] for name in self.commands.record.dtype.names or ()}
        self.queue = buffer.queue("service_messages")
        self._rec = self.inputs.record
        #: the input area's field views (``TaskHost.values``: the tasks fill them in place)
        self.values = self._v = {name: self.inputs.record[name] for name in self.inputs.record.dtype.names or ()}
        self._stats_rec = self.stats_writer.record

    def _init_command_state(self) -> None:
        """The output guard and what the command path keeps from frame to frame
        (``ioservice.command``)."""
        self.guard = OutputGuard(self.clock, self.watchdog_s, post=self._post_guard)
        self._hb_ok: int | None = None  # heartbeat of the last command written by the claim holder
        self._hb_seen: int | None = None  # heartbeat in the command record at the last good read
        #: two writers on one claim (a forger copying the holder's pid and token): issue 28 item 6
        self._claim_check = ClaimStreamCheck(self.commands.raw,
                                             int(round(TWO_WRITER_HOLD_S * self.schedule.frame_rate_hz)))
        self._refusals_seen = 0
        self._cmd_episode = 0  # command_status bits already announced by a message
        self._last_alive: float | None = None  # clock time the service last ran (frame or hook tick)
        self._stall_s = 0.0  # the latest host stall and when it ended
        self._stall_end = -math.inf
        self._long_frames = 0  # long frames since the last notice, and the longest (s)
        self._long_frame_max_s = 0.0
        self._long_frame_said = -math.inf
        self._guard_state = self.guard.state
        self._first_trip: tuple[int, str, float] | None = None  # what inputs.first_trip_* hold
        self._dropped_total = 0  #: frames the loop dropped since start (it did not run them)
        self._dropped_at = [0] * (_AGE_RING_MASK + 1)  # _dropped_total as it was at frame k (k & mask)
        #: while the DAC board does not answer: the message that said so (the outputs may hold
        #: their last values; issue 28 item 5); None while its last write succeeded
        self.dac_unreachable: str | None = None

    def _init_counters(self) -> None:
        """Device and board counters, start-up notes, the bus's health."""
        self._devices = {g: _DeviceCounter() for g in ("rtd", "adc", "dac", "ft", "pio", "crl", "hid")}
        #: boards whose last transaction failed (BOARD_FAULT set); one that answers again is
        #: back to OK (``board_answered``, ``input_ok``)
        self.faulted_boards: set[str] = set()
        self._board_fail_run: dict[str, int] = {}
        self.init_errors: list[str] = []  #: full texts of start-up problems (messages keep MESSAGE_MAX_BYTES)
        self.notes: list[str] = []  #: full texts of start-up decisions the user should know of
        self._bus_ok_t = self.clock.now()  # the last register transaction that succeeded
        self._bus_failed = False  # a register transaction failed in the current frame
        self._last_bus_error: Exception | None = None
        self.bus_lost: str | None = None  #: the bus stopped answering: why the run ended, or how it ended
        self.shed_tasks = 0  #: input tasks skipped by frames already late on a failing bus

    def _init_tasks(self, serial: bool, ft_port: str | None) -> None:
        """The device tasks, the envelope and the charge pump, wired to the boards; the DAC's
        outputs start disconnected at 0 V; the serial lines, the CAE, the calibration."""
        rack, lay = self.rack, self.layout
        self.rtd = RtdTask(self)
        self.adc = AdcTask(self)
        self.dac = DacTask(self)
        #: the motion envelope (issue 28 item 4): slew, braking distance, overspeed
        self.envelope = ServiceEnvelope(
            rack.envelope, [(j, lay.joint_entry("dac", j, "rate_command").channel, lay.joint_slot("rtd", j, "angle"),
                             lay.joint_slot("adc", j, "rate")) for j in lay.joint_names
                            if rack.find(j, "angle") is not None and rack.find(j, "rate") is not None],
            self.post)
        self._env_status = [0] * max((len(b.channels) for b in rack.boards_of("dac")), default=0)
        self._env_k = 0  # the frame the envelope last ran in
        self.ft = FtTask(self)
        self.hand = HandTask(self, self.ft)
        self.pio = PioTask(self)
        self.pump = ChargePump(self)  #: the amplifier-enable charge pump (inactive without one)
        self._build_tasks()
        self.rtd.wire()
        self.adc.wire()
        self.dac.wire()
        # Outputs start disconnected and at 0 V: write the zeros, keep P3 off.
        self.init_board(self.dac.cfg, self.dac.drv.disable_outputs)
        self.pio.wire()
        self.pump.wire()
        self._mvme400: tuple[BoardConfig, Any] | None = None  # (board, driver) of the serial board
        self._last_drain = -math.inf  # clock time of the last serial FIFO drain
        self._ft_url = ft_port
        if serial and self.gateway is not None and self.rack.boards_of("serial"):
            self._serial_over_gateway(ft_port)
        elif serial:
            self._wire_serial()
        if ft_port is not None:
            self.ft.wire_url(ft_port)
        self.hand.wire_cae(self.adc)
        self._apply_calibration_extras()  # calibration: resolver offsets, CAE, F/T, header hash

    # ------------------------------------------------------------------ set-up
    def _build_tasks(self) -> None:
        """The input tasks in run order, each with its schedule bit: a frame runs those whose
        bit is in its mask (its own schedule entry, those of frames just dropped, the F/T
        retry)."""
        table = self.schedule.frame_table()
        tasks: tuple[InputTask, ...] = (self.rtd, self.adc, self.ft, self.hand, self.pio)  # inputs, in run order
        names = tuple(t.name for t in tasks)
        self._input_tasks = tuple((1 << i, t) for i, t in enumerate(tasks))
        self._adc_bit = 1 << tasks.index(self.adc)
        self._frame_tasks = tuple(tuple(n for n in names if n in frame) for frame in table)
        self._frame_masks = tuple(sum(1 << i for i, n in enumerate(names) if n in frame)
                                  for frame in table)
        self._task_names = names

    def board_slot(self, board: str) -> int:
        return self.layout.slot("board", board)

    def _slots(self, kind: str, channels) -> np.ndarray:
        return np.array([self.layout.slot(kind, c.signal) for c in channels], dtype=np.intp)

    def span(self, kind: str, channels) -> np.ndarray | slice:
        """Like :meth:`_slots`, as a slice when the slots are consecutive (the default
        layout's): the per-frame copies into the input area then avoid fancy indexing."""
        slots = self._slots(kind, channels)
        if len(slots) and np.array_equal(slots, np.arange(slots[0], slots[0] + len(slots))):
            return slice(int(slots[0]), int(slots[0]) + len(slots))
        return slots

    def init_board(self, cfg, action) -> bool:
        """Run a board's start-up ``action``; a bus error is tried again up to
        ``INIT_ATTEMPTS`` times in all (a gateway's one-frame time-out on a loaded host failed
        whole boards at start that then worked), except an unreachable gateway; a board that
        needed more than one attempt is named in :attr:`notes`."""
        slot = self.board_slot(cfg.name)
        first: BusError | None = None
        for attempt in range(1, INIT_ATTEMPTS + 1):
            try:
                action()
            except BusError as err:
                if attempt < INIT_ATTEMPTS and "unreachable" not in err.reason:
                    first = first or err
                    continue
                return self._init_failed(cfg.name, slot, err)
            except PfmaError as err:
                return self._init_failed(cfg.name, slot, err)
            if attempt > 1:
                self.notes.append(f"{cfg.name}: answered its start-up on attempt {attempt} of "
                                  f"{INIT_ATTEMPTS} (first: {first})")
            self._v["board_status"][slot] = BOARD_OK | BOARD_INIT
            return True
        return False  # not reached: the last attempt returns

    def _init_failed(self, board: str, slot: int, err: PfmaError) -> bool:
        self._v["board_status"][slot] = BOARD_FAULT
        self.board_error(board, err)
        self.post(Severity.ERROR, MessageCode.BOARD_INIT_FAILED, f"{board}: init failed: {err}")
        return False

    def _wire_serial(self) -> None:
        """The MVME400: both ports at their rack baud rates; the F/T sensor (the rack's
        force_torque channel, unless on a URL) and the CRL hand controller on their ports.
        Its FIFOs are drained by :meth:`serial_tick`."""
        boards = self.rack.boards_of("serial")
        if not boards:
            return
        cfg = boards[0]
        ch = {c.signal: c for c in cfg.channels}
        ft_ch = next((c for c in cfg.channels if c.quantity == "force_torque"), None)
        drv = self.io.driver(cfg)
        bauds = [int(ch_.baud or 19200) for ch_ in sorted(cfg.channels, key=lambda c: c.channel)]
        if not self.init_board(cfg, lambda: drv.init(baud_a=bauds[0], baud_b=bauds[1])):
            return
        self._mvme400 = (cfg, drv)
        if ft_ch is not None and self._ft_url is None:
            port = drv.port(ft_ch.channel, timeout=0.05)
            self.ft.start(port, bauds[ft_ch.channel], f"{cfg.name} port {ft_ch.channel}")
        if "crl_hand_controller" in ch:  # no rack quantity for the CRL line: by its signal
            self.hand.attach_crl(drv.port(ch["crl_hand_controller"].channel, timeout=0, write_queue=True))

    def _serial_over_gateway(self, ft_port: str | None) -> None:
        """Say once that the MVME400's lines are not opened over a register gateway, and where
        the F/T comes from instead."""
        ft = (f"F/T sensor from {ft_port}" if ft_port is not None
              else "no F/T sensor (give it a local port: pfma serve --ft-port URL)")
        text = (f"serial lines cannot cross the register gateway {self.gateway}: the MVME400's "
                f"3-character FIFO fills in {SERIAL_FIFO_FILL_S * 1e3:.2f} ms at 19200 baud and "
                f"each drain would be a network round trip; running with {ft} and without the "
                f"CRL hand controller")
        self.notes.append(text)
        self.post(Severity.WARNING, MessageCode.SERIAL_NOT_OVER_GATEWAY, "serial not over gateway: " + ("F/T on local port" if ft_port
                                                                         else "no F/T, no CRL"))

    # -- private names older code and tests reach (the state is the tasks')
    @property
    def _ft(self):
        return self.ft.ft

    @_ft.setter
    def _ft(self, ft) -> None:
        self.ft.ft = ft

    @property
    def _ft_in_tick(self) -> bool:
        return self.ft.in_tick

    @_ft_in_tick.setter
    def _ft_in_tick(self, on: bool) -> None:
        self.ft.in_tick = on

    @property
    def _dac_n(self) -> int:
        return self.dac.n

    @property
    def _dac_sat_v(self) -> list[float]:
        return self.dac.sat_v

    @property
    def _dac_is_limit(self) -> list[bool]:
        return self.dac.is_limit

    # ------------------------------------------------------------------ messages and state
    def _say_overrides(self, cal) -> None:
        """Name every ``[checks] allow_nonnominal`` entry of the rack file (``pfma.nominal``):
        each value it lets through outside the nominal band (rack file and calibration),
        and each entry that lets nothing through. Posted (code 103, WARNING) and kept in
        :attr:`notes` (``pfma serve`` prints them)."""
        found = list(self.rack.nonnominal) + list(getattr(cal, "nonnominal", ()))
        used = {key for key, _text in found}
        texts = [text for _key, text in found]
        texts += [f"[checks] allow_nonnominal lists {o} ({self.rack.source}): its value is within the nominal "
                  f"band (the override is not needed)" for o in self.rack.overrides if o not in used]
        for t in texts:
            self.post(Severity.WARNING, NONNOMINAL_CODE, f"override: {t}")
            self.notes.append(f"override: {t}")

    def _start_direction_check(self) -> None:
        """(Re)compare the running scale signs with the direction-check record and say
        which joints are pending (code 104, also in :attr:`notes`)."""
        if self._direction_path is None:
            return
        self.direction = DirectionCheck(self.rack, self.layout, self._direction_path, self.dac.limit)
        text = self.direction.start_text()
        if text:
            self.post(Severity.WARNING, MessageCode.DIRECTION_PENDING, text)
            self.notes.append(text)

    def post(self, severity: int, code: int, text: str) -> None:
        self.queue.post(text, severity=severity, code=code, t_s=self.clock.now())

    def fault(self, code: FaultCode, reason: str, trip_code: int | None = None) -> None:
        """FAULT (``TaskHost.fault``): ``code`` published as ``inputs.fault_code``, the guard
        tripped with ``reason`` (posted with ``trip_code``, default ``code``); the outputs go
        safe in this frame."""
        self._set_fault(code)
        self.guard.trip(reason, code=code if trip_code is None else trip_code)

    def armed(self) -> bool:
        """The guard lets the commands drive the arm (``TaskHost.armed``)."""
        return self.guard.state == ServiceState.ARMED

    def device_error(self, group: str) -> int:
        """Count an error of a device group (``TaskHost.device_error``); returns the count."""
        d = self._devices[group]
        d.errors += 1
        return d.errors

    def _post_guard(self, severity: int, code: int, text: str) -> None:
        self.post((Severity.INFO, Severity.WARNING, Severity.ERROR)[min(severity, 2)], code, text)

    def set_state(self, state: ServiceState) -> None:
        self.state = state
        self.buf.set_service_state(state)
        self._v["service_state"][...] = int(state)

    def board_error(self, board: str, err: Exception) -> None:
        self._bus_failed = True
        self._last_bus_error = err
        slot = self.board_slot(board)
        self._v["board_errors"][slot] += 1
        self._v["board_status"][slot] |= BOARD_FAULT
        self._v["board_last_error_addr"][slot] = getattr(err, "addr", 0) or 0
        self._v["board_last_error_t_s"][slot] = self.clock.now()
        self.faulted_boards.add(board)

    def board_answered(self, board: str) -> None:
        """A board in :attr:`faulted_boards` answered a whole transaction again (a DAC
        write-all, a serial drain, a matrix route): an initialised board's status goes back
        to OK (its error count and last error stay). Callers test ``faulted_boards`` first,
        so a healthy frame pays one set test."""
        if board in self.faulted_boards:
            self.faulted_boards.discard(board)
            slot = self.board_slot(board)
            if self._v["board_status"][slot] & BOARD_INIT:
                self._v["board_status"][slot] = BOARD_OK | BOARD_INIT

    def input_failed(self, board: str, group: str, err: Exception) -> None:
        self.board_error(board, err)
        self._devices[group].errors += 1
        run = self._board_fail_run.get(board, 0) + 1
        self._board_fail_run[board] = run
        if run == 1:
            self.post(Severity.ERROR, MessageCode.INPUT_FAILED, f"{board}: {err}")
        if run == INPUT_FAULT_FRAMES:
            self.fault(FaultCode.INPUTS, f"{board} failed {run} samples in a row: {err}")

    def input_ok(self, board: str, slot: int) -> None:
        self._bus_ok_t = self.clock.now()
        if self._board_fail_run.get(board):
            self._board_fail_run[board] = 0
            self._v["board_status"][slot] = BOARD_OK | BOARD_INIT
            self.faulted_boards.discard(board)

    def sampled(self, group: str, t: float) -> None:
        d = self._devices[group]
        d.samples += 1
        d.t_last = t

    # ------------------------------------------------------------------ the frame
    def frame(self, info: FrameInfo) -> None:
        """One minor frame: the DAC first (commands and the watchdog checked at a fixed,
        short time after the wake-up, before the variable input work), then the input tasks
        due in this frame (and in frames just dropped), then one consistent publish of the
        input area."""
        k = info.index
        self.serial_tick()  # the 3-deep serial FIFOs: drain on both sides of the work
        mask = self._frame_masks[k % MINOR_FRAMES_PER_MAJOR]
        for j in range(1, min(info.missed, MINOR_FRAMES_PER_MAJOR) + 1):
            mask |= self._frame_masks[(k - j) % MINOR_FRAMES_PER_MAJOR]
        ft = self.ft
        if mask & 4:
            ft.retry = FT_RETRY_FRAMES
        elif ft.retry:  # the last F/T slot found nothing new: look again
            ft.retry -= 1
            mask |= 4
        self._note_alive(info.t_wake)
        self._bus_failed = False
        late = info.t_wake + self.schedule.period_s  # a frame's work past this overruns
        try:
            if mask & self._adc_bit:
                self.adc.start()  # the scan converts while the DAC and resolvers run
            # frames the loop dropped (the service did not run: a host stall) are noted so that
            # they do not age a command (issue 29 item 1): see _task_dac
            missed = info.missed
            if missed:
                total = self._dropped_total = self._dropped_total + missed
                # a dropped frame j counts itself: a command stamped with it (it was never
                # published; a writer's arithmetic) is then as old as one from the frame before k
                for j in range(1, min(missed, _AGE_RING_MASK) + 1):
                    self._dropped_at[(k - j) & _AGE_RING_MASK] = total - j + 1
            self._dropped_at[k & _AGE_RING_MASK] = self._dropped_total
            self._task_dac(k)
            for bit, task in self._input_tasks:
                if mask & bit:
                    if self._bus_failed and self.clock.now() > late:
                        # the bus is failing (each access may wait out its timeout) and the
                        # frame is already over its period: no more bus work in this frame
                        self.shed_tasks += 1
                        continue
                    task.run(k)
                    if task.drain_after:
                        self._drain_if_due()  # a slow input scan must not overrun the FIFOs
        except Exception as err:  # noqa: BLE001 - a fault we cannot explain: outputs safe
            self.fault(FaultCode.UNEXPECTED, f"unexpected {type(err).__name__} in frame {k}: {err}")
            self._apply_safe()
        if self._bus_failed and self.bus_lost is None:
            self._check_bus_lost()
        self._publish(info)
        self.serial_tick()
        end = self._last_alive = self.clock.now()  # a long frame is the service's own work, not a stall
        if end - info.t_wake > HOST_STALL_S:  # measured and named (rare: nothing per frame otherwise)
            self._long_frame(k, end - info.t_wake, end)
        if k % self.stats_every == 0:
            if self._stats_between_frames:
                self._stats_due_k = k  # computed in the sleep after this frame (idle_tick)
            else:
                self.publish_stats()
        elif self._stats_due_k is not None and k - self._stats_due_k >= STATS_MAX_DEFER_FRAMES:
            self.publish_stats()  # no idle time for a while (overloaded): do it here

    def _check_bus_lost(self) -> None:
        """After a frame with a failed transaction: if none has succeeded for BUS_LOST_S, the
        bus is lost: the guard trips (if the failed DAC writes have not tripped it already),
        one message names the bus, and the loop ends after this frame."""
        silent = self.clock.now() - self._bus_ok_t
        if silent <= BUS_LOST_S:
            return
        self.bus_lost = self._bus_silence(silent) + (
            "; outputs made safe, service stopping" if self.dac_unreachable is None else
            "; outputs NOT known safe (the DAC did not answer: they may hold their last values; "
            "press the hardware E-stop), service stopping")
        self.post(Severity.ERROR, MessageCode.BUS_LOST, f"bus lost: {self.bus_name}")
        if self.fault_code == FaultCode.NONE:
            self._set_fault(FaultCode.DAC)
        # outputs: the DAC write of this frame has already failed (and tripped the guard);
        # stop() disables them once more on the way out; no third attempt in this frame
        self.guard.trip(f"bus {self.bus_name} lost", code=FaultCode.DAC)
        self.loop.stop()

    def _bus_silence(self, silent: float) -> str:
        return (f"the bus {self.bus_name} stopped answering: no register transaction succeeded "
                f"for {silent:.2f} s (last error: {self._last_bus_error})")

    def _check_bus_at_end(self) -> None:
        """A run that ends (its duration, Ctrl-C) while the bus has not answered for longer
        than the command watchdog, before BUS_LOST_S, is reported all the same."""
        silent = self.clock.now() - self._bus_ok_t
        if self.bus_lost is None and self._bus_failed and silent > self.watchdog_s:
            self.bus_lost = self._bus_silence(silent) + (
                " when the run ended; outputs made safe" if self.dac_unreachable is None else
                " when the run ended; outputs NOT known safe (the DAC did not answer: they may hold "
                "their last values; press the hardware E-stop)")
            self.post(Severity.ERROR, MessageCode.BUS_LOST, f"bus lost: {self.bus_name}")

    # ------------------------------------------------------------------ what the bus can keep
    def measure_bus(self, repeats: int = BUS_PROBE_REPEATS) -> tuple[dict[str, float], float]:
        """Time one run of each bus task's transactions (the tasks' ``probe``: the same reads
        and writes as a frame, nothing published), ``repeats`` times on the service's clock.
        Returns (task -> median seconds, seconds of serial drains in every frame).

        The DAC probe writes the shadow's codes (0 V while the outputs are disconnected, as
        they are until the first arm)."""
        tasks: dict[str, Any] = {"dac": self.dac, "rtd": self.rtd, "adc": self.adc, "pio": self.pio}
        probes = {name: tasks[name].probe for name in BUS_TASKS}
        probes["dac"] = self._probe_dac
        now = self.clock.now
        serial = self._mvme400[1] if self._mvme400 is not None else None
        times: dict[str, list[float]] = {name: [] for name in (*BUS_TASKS, "serial")}
        for _ in range(repeats):  # round by round: a burst of host load hits every task alike
            for name in BUS_TASKS:
                t0 = now()
                probes[name]()
                times[name].append(now() - t0)
            if serial is not None:  # the drains at the start and end of every frame
                t0 = now()
                try:
                    serial.poll()
                except PfmaError:
                    pass
                times["serial"].append(now() - t0)
        out = {name: float(np.median(times[name])) for name in BUS_TASKS}
        every = 2 * float(np.median(times["serial"])) if serial is not None else 0.0
        return out, every

    def _probe_dac(self) -> None:
        """The DAC's probe, and the charge pump's: its write follows the DAC's in every ARMED frame."""
        self.dac.probe()
        self.pump.probe()

    def fit_schedule(self, slow: bool = False, repeats: int = BUS_PROBE_REPEATS) -> str | None:
        """Measure the bus (:meth:`measure_bus`) and check that every frame of the schedule
        gets its bus work done within BUS_SHARE of the period.

        :param slow: when the schedule cannot be kept, run the best slower one that can
            (``ioservice.schedule.slower_schedules``) instead of refusing
        :returns: None when the schedule stands; the message naming the slower schedule
            when ``slow`` chose one
        :raises BusTooSlow: the schedule cannot be kept (and ``slow`` is off, or no slower
            schedule fits either); the message gives the figures per task and per frame
        """
        cost, every = self.measure_bus(repeats)
        sched = self.schedule
        if fits(sched, cost, every):
            return None
        options = slower_schedules(sched, self.watchdog_s)
        better = next((s for s in options if fits(s, cost, every)), None)
        frame_s, names = busiest_frame(sched, cost, every)
        figures = ("per task " + ", ".join(f"{t} {cost[t] * 1e3:.2f} ms" for t in BUS_TASKS if t in cost)
                   + (f", serial drains {every * 1e3:.2f} ms" if every else "")
                   + f"; the busiest frame ({'+'.join(names) or 'nothing'}) needs {frame_s * 1e3:.2f} ms "
                   f"of the bus, {BUS_SHARE:.0%} of a {sched.period_s * 1e3:.3f} ms frame is "
                   f"{BUS_SHARE * sched.period_s * 1e3:.2f} ms")
        if not slow or better is None:
            if better is not None:
                hint = f"; --schedule slow would run {describe_rates(better)}"
            else:
                hint = (f"; no slower schedule fits either (frames are at most the "
                        f"{self.watchdog_s * 1e3:g} ms command watchdog, --watchdog-ms)")
            raise BusTooSlow(f"the bus {self.bus_name} cannot keep the schedule of "
                             f"{describe_rates(sched)}: {figures}{hint}")
        self.reschedule(better)
        b_s, b_names = busiest_frame(better, cost, every)
        text = (f"running {describe_rates(better)} over {self.bus_name}: the bus costs "
                f"{b_s * 1e3:.2f} ms in the busiest frame ({'+'.join(b_names)}) of "
                f"{better.period_s * 1e3:.3f} ms (it could not keep {describe_rates(sched)}: "
                f"{frame_s * 1e3:.2f} ms)")
        self.post(Severity.WARNING, MessageCode.SLOW_BUS, f"slow bus: rtd {better.rate_hz('rtd'):g} Hz, "
                                         f"dac {better.rate_hz('dac'):g} Hz")
        return text

    def reschedule(self, schedule: Schedule) -> None:
        """Run ``schedule`` instead (before :meth:`run`): the frame period, the task table, the
        statistics interval; the command age limit is lowered to what fits the watchdog.

        :raises ConfigError: a frame period longer than the command watchdog
        """
        fit = int(self.watchdog_s / schedule.period_s + 1e-9)
        if fit < 1:
            raise ConfigError(f"a {schedule.frame_rate_hz:g} Hz schedule has frames longer than "
                              f"the {self.watchdog_s * 1e3:g} ms command watchdog")
        if self.policy.max_input_age_frames > fit:
            from dataclasses import replace
            self.policy = replace(self.policy, max_input_age_frames=fit)
        self.schedule = schedule
        self.loop.period_s = schedule.period_s
        self._build_tasks()
        self.stats_every = max(1, int(round(schedule.frame_rate_hz / 2)))
        self._claim_check.hold_frames = int(round(TWO_WRITER_HOLD_S * schedule.frame_rate_hz))
        for diff in schedule.check_documented_rates():
            self.post(Severity.WARNING, MessageCode.SCHEDULE_DIFFERS,
                      f"schedule differs from the report and the rack file's rate_hz: {diff}")

    # one input task on its own, outside the frame (``bench/bench_service.py`` times them)
    def _task_rtd(self) -> None:
        self.rtd.run(self.loop.k)

    def _task_adc(self) -> None:
        self.adc.run(self.loop.k)

    def _task_ft(self) -> None:
        self.ft.run(self.loop.k)

    def _task_hand(self) -> None:
        self.hand.run(self.loop.k)

    def _task_pio(self) -> None:
        self.pio.run(self.loop.k)


    def _note_alive(self, now: float) -> None:
        """Called at every frame start and hook tick: a gap longer than HOST_STALL_S since the
        service last ran (a tick, or the end of a frame's work) is a host stall, recorded and
        announced (the service could not run). A stall inside a frame's work shows as an
        overrun instead."""
        last = self._last_alive
        self._last_alive = now
        # without the between-frames ticks (run() installs them) a whole period may pass
        limit = HOST_STALL_S if self._stats_between_frames else HOST_STALL_S + self.schedule.period_s
        if last is not None and now - last > limit:
            self._stall_s, self._stall_end = now - last, now
            v = self._v
            v["host_stall_s"][...] = self._stall_s
            v["host_stall_t_s"][...] = now
            self.post(Severity.WARNING, MessageCode.HOST_STALL, f"host stall: service did not run for {self._stall_s * 1e3:.0f} ms")

    def _long_frame(self, k: int, took_s: float, now: float) -> None:
        """A frame whose own run took longer than HOST_STALL_S (its work, or the host taking
        the CPU inside it: the service cannot tell which) is not a host stall, but its length
        is measured and posted: at most one notice per LONG_FRAME_NOTICE_S, counting the others."""
        self._long_frames += 1
        self._long_frame_max_s = max(self._long_frame_max_s, took_s)
        if now - self._long_frame_said < LONG_FRAME_NOTICE_S:
            return
        n, longest = self._long_frames, self._long_frame_max_s
        self._long_frame_said, self._long_frames, self._long_frame_max_s = now, 0, 0.0
        more = f" ({n} such frames, longest {longest * 1e3:.0f} ms)" if n > 1 else ""
        self.post(Severity.WARNING, MessageCode.LONG_FRAME, f"long frame: frame {k} ran {took_s * 1e3:.0f} ms{more}")

    def _publish(self, info: FrameInfo) -> None:
        v = self._v
        v["frame"][...] = info.index
        v["t_s"][...] = info.t_wake
        v["service_state"][...] = int(self.state)
        v["fault_code"][...] = self.fault_code
        if self.guard.first_trip is not self._first_trip:  # changes once a trip episode
            self._put_first_trip()
        self.inputs.publish()
        if self.ring is not None:  # the history a stalled recorder catches up from
            self.ring.write(self.inputs.raw)
        self.buf.set_frame(info.index, info.t_wake)
        self.buf.wake_frame_waiters()  # a live controller sleeps on the frame word (bit3.futex)

    def _put_first_trip(self) -> None:
        """The guard's first trip or refusal since the last arm into ``inputs.first_trip_*``
        (written when it changes, not every frame)."""
        self._first_trip = ft = self.guard.first_trip
        v = self._v
        code, text, t = ft if ft is not None else (0, "", 0.0)
        raw = text.encode()[:FIRST_TRIP_TEXT_BYTES]
        v["first_trip_code"][...] = code
        v["first_trip_t_s"][...] = t
        v["first_trip_text"][...] = 0
        v["first_trip_text"][:len(raw)] = np.frombuffer(raw, dtype=np.uint8)

    # ------------------------------------------------------------------ between frames
    def serial_tick(self, now: float | None = None) -> None:
        """Drain the serial boards' receive FIFOs into the drivers' buffers (TickingClock
        hook between frames, and around the work inside a frame). The MVME400 F/T line is
        decoded here as soon as its buffer can complete a record (``FtSensor.record_due``);
        the hand controller in its task. A drain within ``SERIAL_MIN_GAP_S`` of the previous
        one is skipped: the FIFO cannot have filled, and every drain costs register accesses."""
        m = self._mvme400
        if m is None:
            return
        t = self.clock.now()
        if t - self._last_drain < SERIAL_MIN_GAP_S:
            return
        self._last_drain = t
        try:
            m[1].poll()
        except PfmaError as err:
            self.board_error(m[0].name, err)
        else:
            if self.faulted_boards:
                self.board_answered(m[0].name)
        fts = self.ft
        ft = fts.ft
        if ft is not None and fts.in_tick:
            try:
                due = ft.record_due()  # a length check on the software buffer: no bus access
            except PfmaError:
                due = True  # let the decode count the failure
            if due:
                self.decode_serial(hand=False)

    def _drain_if_due(self) -> None:
        """Inside a frame, at a task boundary: drain the serial FIFOs if ``SERIAL_MIN_GAP_S``
        has passed since the last drain (a slow scan, or a host that preempted the frame)."""
        self.serial_tick()

    def decode_serial(self, hand: bool = True) -> None:
        try:
            self.ft.decode()
            if hand:
                self.hand.decode()
        except PfmaError as err:
            if self._mvme400 is not None:
                self.board_error(self._mvme400[0].name, err)
            self._devices["ft"].errors += 1

    # ------------------------------------------------------------------ statistics
    @staticmethod
    def _cpu_s() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    def idle_tick(self, now: float | None = None) -> None:
        """Between frames (a TickingClock hook that :meth:`run` installs, every 0.4 ms of
        sleep when live):

        - while ARMED, the command heartbeat is checked (at most every
          ``HEARTBEAT_CHECK_S``), and a stale one drives the DAC to 0 V at once rather than
          at the next frame (the reaction to a dead controller is then the watchdog plus at
          most 1 ms and a tick, not plus one frame and a late wake-up);
        - the statistics a frame asked for are published (percentiles over the 4096-frame
          window cost about 1 ms, a periodic work spike inside a frame).
        """
        now = self.clock.now()
        self._note_alive(now)
        if self.guard.state == ServiceState.ARMED and self.state == ServiceState.ARMED \
                and now - self._last_hb_check >= HEARTBEAT_CHECK_S:
            self._last_hb_check = now
            self._fetch_command()  # only a good command's heartbeat counts (_hb_ok)
            hb = self._hb_ok if self._hb_ok is not None else -1
            if self.guard.check_between_frames(hb, stall_note=self._stall_note()):
                self._set_fault(FaultCode.WATCHDOG)
                self._v["watchdog_tripped"][...] = 1
                self._apply_safe()
        if self._stats_due_k is not None:
            self.publish_stats()

    def publish_stats(self) -> dict:
        """Compute loop and device statistics, publish them in the stats area, return them."""
        self._stats_due_k = None
        now = self.clock.now()
        s = self.loop_stats.summary()
        rec = self._stats_rec
        rec["frame"] = self.loop.k
        rec["t_s"] = now
        rec["frames"] = s["frames"]
        rec["dropped_frames"] = s["dropped"]
        rec["overruns"] = s["overruns"]
        rec["stall_events"] = s["stalls"]
        rec["window_frames"] = min(self.loop_stats.n, self.loop_stats.window)
        rec["period_s"] = self.schedule.period_s
        r = s["rate_hz"]  # frames run over the time they took: a dropped frame lowers it
        rec["rate_hz"] = 0.0 if math.isnan(r) else r
        for n in ("p50", "p99", "p999", "max"):
            rec[f"wake_latency_{n}_us"] = s["wake_latency_s"][n] * 1e6
        for n in ("p50", "p99", "max"):
            rec[f"work_{n}_us"] = s["work_s"][n] * 1e6
        wall = now - self._wall0
        rec["cpu_percent"] = 100.0 * (self._cpu_s() - self._cpu0) / wall if wall > 0 and \
            not getattr(self.clock, "simulated", False) else 0.0
        rec["gc_gen2"] = s["gc_gen2_in_loop"]
        out = {"loop": s, "devices": {}}
        for name, d in self._devices.items():
            if not math.isnan(d.window_t0) and d.t_last > d.window_t0:
                d.rate_hz = (d.samples - d.window_samples) / (d.t_last - d.window_t0)
            d.window_samples, d.window_t0 = d.samples, d.t_last
            slot = self.layout.slot("device", name)
            rec["device_rate_hz"][slot] = d.rate_hz
            rec["device_t_s"][slot] = d.t_last if not math.isnan(d.t_last) else 0.0
            rec["device_samples"][slot] = d.samples
            rec["device_errors"][slot] = d.errors
            out["devices"][name] = {"rate_hz": d.rate_hz, "samples": d.samples, "errors": d.errors}
        self.stats_writer.publish()
        return out

    # ------------------------------------------------------------------ running
    def run(self, duration_s: float | None = None, frames: int | None = None) -> LoopStats:
        """Run the frame loop; outputs are made safe and disconnected however it ends."""
        hook = getattr(self.clock, "hooks", None)
        if hook is not None and self.serial_tick not in hook:
            hook.append(self.serial_tick)
        if hook is not None and self.idle_tick not in hook:
            hook.append(self.idle_tick)
            self._stats_between_frames = True
        try:
            return self.loop.run(frames=frames, duration_s=duration_s)
        finally:
            self._check_bus_at_end()
            if hook is not None and self.idle_tick in hook:
                hook.remove(self.idle_tick)
            self._stats_between_frames = False
            self.stop()

    def install_signal_handlers(self) -> None:
        """SIGINT/SIGTERM end the loop after the current frame; outputs then go safe."""
        def handler(signum, _frame):
            self.loop.stop()
        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)

    def stop(self, reason: str = "service stopped") -> None:
        """Outputs to 0 V and disconnected, state STOPPED, message posted (idempotent)."""
        if self.state == ServiceState.STOPPED:
            return
        try:
            self.dac.drv.disable_outputs()
        except PfmaError as err:
            self.guard.outputs_known_safe = False  # the stop's notice must not call them safe
            self._set_fault(FaultCode.DAC_UNREACHABLE)
            self.post(Severity.ERROR, MessageCode.DAC_NOT_DISABLED, f"could not disable DAC outputs: {err}")
        else:
            self.guard.outputs_known_safe = True
            self.dac_unreachable = None
            if self.fault_code == FaultCode.DAC_UNREACHABLE:  # written 0 V and disconnected after all
                self._set_fault(FaultCode.DAC)
        self._v["fault_code"][...] = self.fault_code
        self.guard.stop(reason if self.guard.outputs_known_safe else
                        f"{reason}; the DAC did not answer: its outputs may hold their last values "
                        f"({self.dac.last_values_text()}); {self.pump.stopped_text()}; press the hardware E-stop")
        self.dac.publish_stopped()  # the outputs disconnected: no outputs, no brakes
        self.set_state(ServiceState.STOPPED)
        self.publish_stats()
        if self.guard.first_trip is not self._first_trip:
            self._put_first_trip()
        self.inputs.publish()
        if self.ring is not None:
            self.ring.write(self.inputs.raw)
        self.buf.wake_frame_waiters()  # a reader waiting for the next frame sees STOPPED now
        self.ft.stop()
        self.post(Severity.INFO, MessageCode.STOPPED, f"{reason} (pid {os.getpid()})")

    # ------------------------------------------------------------------ calibration
    # (calibration issue) Scales and offsets come from the rack configuration with the
    # calibration applied (calibration.files.apply_to_rack); resolver offsets, the CAE
    # and F/T sections and the header hash are applied here.
    def _apply_calibration_extras(self) -> None:
        from calibration.files import cae_calibration, calibration_hash
        from pfma.ft_calibration import ft_calibration
        self.rtd.calibrate(self.rack)
        cal = self.calibration
        self.ft.cal = ft_calibration(cal) if cal is not None else None
        if self.hand.cae is not None:
            from drivers.crl.cae import CaeCalibration
            cae = cae_calibration(cal) if cal is not None else None
            self.hand.cae.calibration = cae if cae is not None else CaeCalibration()
        self.buf.set_calibration_hash(calibration_hash(cal) if cal is not None else bytes(8))

    def reload_calibration(self, calibration) -> None:
        """Load a calibration (path or loaded object) and re-wire every conversion.

        :raises PfmaError: while the arm is ARMED (nothing changes)
        :raises CalibrationError: for a bad file (naming the field); the calibration in
            force stays
        """
        if self.state == ServiceState.ARMED or self.guard.state == ServiceState.ARMED:
            raise PfmaError("calibration reload refused: the arm is ARMED; disarm first "
                            "(the calibration in force is unchanged)")
        rack, cal = _calibrated_rack(self.rack, calibration)
        self.rack, self.calibration = rack, cal
        self.adc.calibrate(rack)
        self.dac.calibrate(rack)
        self._apply_calibration_extras()
        self.post(Severity.INFO, MessageCode.CALIBRATION_LOADED, f"calibration v{cal.version} loaded ({cal.hash().hex()})")
        self._start_direction_check()  # the calibration may have changed a sign
        self._say_overrides(cal)


#: a bus whose class comes from this package is the simulated rack (see bus_is_simulated)
FAKES_PACKAGE = "fakes"


def bus_is_simulated(bus) -> bool:
    """Whether a register bus is the simulated rack, for the header's SIMULATED flag.

    ASSUMED (named once here; docs/console.md "Simulated or real"): a bus that says so with a
    boolean class attribute ``simulated`` is believed; otherwise a bus whose class lives in
    the ``fakes`` package (``fakes.rack.FakeRack`` and the simulated racks built on it: what
    ``pfma serve --rack fake``, ``--bus fake`` and every simulation rig use) is simulated,
    and so is a wrapper (``drivers.bus.spy.SpyBus``, its ``bus`` attribute) around one. Any
    other bus is a hardware bus (device file, VME bridge, Modbus gateway): not simulated,
    even if a simulator answers at its far side (``pfma gateway``), which the service cannot
    see. The service does not import the fakes (docs/architecture.md); it only reads the
    class's module name.
    """
    b = bus
    for _ in range(4):  # a spy on a spy ...
        said = getattr(type(b), "simulated", None)
        if isinstance(said, bool):
            return said
        if type(b).__module__.partition(".")[0] == FAKES_PACKAGE:
            return True
        inner = vars(b).get("bus") if hasattr(b, "__dict__") else None
        if inner is None or inner is b:
            return False
        b = inner
    return False


def _bus_name(bus) -> str:
    describe = getattr(bus, "describe", None)
    if callable(describe):
        try:
            return str(describe())
        except Exception:  # noqa: BLE001 - a name for messages only
            pass
    return type(bus).__name__


def _command_policy(rack: RackConfig, schedule: Schedule, watchdog_s: float,
                    max_input_age_frames: int | None):
    """The rack file's ``[commands]``, its ``max_input_age_frames`` overridden when given;
    refused (ConfigError) when the age exceeds the command watchdog."""
    policy = rack.commands
    if max_input_age_frames is not None:  # overrides the rack file's [commands] value
        if isinstance(max_input_age_frames, bool) or int(max_input_age_frames) != max_input_age_frames \
                or max_input_age_frames < 1:
            raise ConfigError(f"max_input_age_frames must be a whole number of frames >= 1, "
                              f"not {max_input_age_frames!r}")
        from dataclasses import replace
        policy = replace(policy, max_input_age_frames=int(max_input_age_frames))
    age_s = policy.max_input_age_frames * schedule.period_s
    if age_s > watchdog_s + 1e-9:
        raise ConfigError(f"rack {rack.name}: [commands] max_input_age_frames = "
                          f"{policy.max_input_age_frames} ({age_s * 1e3:.2f} ms at "
                          f"{schedule.frame_rate_hz:g} Hz) exceeds the {watchdog_s * 1e3:g} ms "
                          f"command watchdog; lower it or raise the watchdog")
    return policy


def _calibrated_rack(rack: RackConfig, calibration):
    """(rack with calibrated scales, validated calibration) from a path or object."""
    from calibration.files import apply_to_rack, resolve
    cal = resolve(calibration, rack)
    return apply_to_rack(rack, cal), cal
