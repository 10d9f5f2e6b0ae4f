"""The data-acquisition service: the I/O chassis of the PFMA rack, in one process.

It owns the drivers of every board in the rack configuration and runs them on the
acquisition schedule (``ioservice.schedule``): DAC outputs every 3.125 ms minor
frame (320 Hz), resolvers and ADC every second frame (160 Hz), the F/T sensor and
the serial hand controller every fourth (80 Hz), the parallel ports every eighth.
Each frame's inputs carry the time they were sampled. Everything is published in
the Bit3 buffer's input area (one seqlocked copy per frame); commands are taken
from its command area; ``ioservice.safety.OutputGuard`` decides whether they may
reach the DAC.

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
import os
import resource
import signal
from dataclasses import dataclass

import numpy as np

from bit3.layout import (  # noqa: F401 - the status bits are re-exported for older importers
    BOARD_FAULT, BOARD_INIT, BOARD_OK, CHANNEL_BUS_ERROR, CMD_ABSENT, CMD_FOREIGN, CMD_REFUSED, CMD_STALE,
    DAC_CLIPPED, DAC_FORCED_SAFE, LINK_FAULT, LINK_OPEN, LINK_STALE, LINK_SYNCED, RTD_NO_REFERENCE, ServiceState,
    Severity,
)
from ioservice.loop import FrameInfo, FrameLoop, LoopStats
from ioservice.safety import OutputGuard
from ioservice.schedule import MINOR_FRAMES_PER_MAJOR, Schedule
from bit3.buffer import Bit3Buffer
from pfma.clock import Clock
from pfma.errors import ConfigError, PfmaError
from pfma.rack import RackConfig
from drivers.rackio import RackIO

#: fault codes (inputs.fault_code)
FAULT_NONE, FAULT_WATCHDOG, FAULT_DAC, FAULT_INPUTS, FAULT_UNEXPECTED = 0, 1, 2, 3, 4
#: inputs.fault_code when the outputs went safe because a command was refused (the service
#: is then SAFE, not FAULT): a field beyond its limit / NaN, or a writer without the claim
FAULT_COMMAND, FAULT_FOREIGN = 5, 6
#: internal: nobody holds the command area's claim (no controller yet); not published
_NO_WRITER = 0x100
#: consecutive failing samples of an input board before the outputs are made safe
INPUT_FAULT_FRAMES = 3
#: F/T record older than this is flagged stale: 8 F/T periods. Assumed: long enough to
#: ride through a development VM's 10-50 ms host stalls (each costs a burst of lost bytes
#: on the 3-deep FIFO), short enough that a dead sensor stops force control within 0.1 s.
FT_STALE_S = 0.1
#: attempts at the F/T start-up dialogue (mode, checksum, stream) before the link is
#: reported faulty: one lost character garbles a reply, and on a loaded host the 3-deep
#: MVME400 FIFO can overrun during the dialogue
FT_START_ATTEMPTS = 3
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
#: current-limit volts above which the amplifier releases the brake (pfma-model 8.4, assumed)
BRAKE_RELEASE_V = 0.5
#: a gap this long with no frame and no hook tick of the service is a host stall (the
#: machine, or this process, did not run): recorded in ``inputs.host_stall_s`` and named
#: as the cause of a watchdog trip or stale command it explains. Assumed: 10 ms, well
#: above the wake-up jitter of a shared VM (p99 ~0.85 ms) and below the 15 ms watchdog
HOST_STALL_S = 0.010
#: a stall is named in trips and stale-command messages for this long after it ended (the
#: time a controller needs to see new inputs and answer: two watchdog periods, assumed)
STALL_BLAME_S = 0.030


@dataclass
class _DeviceCounter:
    samples: int = 0
    errors: int = 0
    t_last: float = math.nan
    window_samples: int = 0
    window_t0: float = math.nan
    rate_hz: float = 0.0


_TWO_PI = 2.0 * math.pi
#: statistics asked for by a frame are published between frames; if no sleep long enough
#: for the clock's hooks comes within this many frames, the frame publishes them itself
STATS_MAX_DEFER_FRAMES = 16


class IoService:
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
    """

    def __init__(self, rack: RackConfig, bus, buffer: Bit3Buffer, clock: Clock, *,
                 schedule: Schedule | None = None, watchdog_s: float = 0.015,
                 owner: str = "pfma-ioservice", serial: bool = True, calibration=None,
                 ft_port: str | None = None, max_input_age_frames: int | None = None) -> None:
        self.calibration = None  # calibration: the loaded calibration in force (None = nominal)
        if calibration is not None:
            rack, self.calibration = _calibrated_rack(rack, calibration)
        self.rack = rack
        self.bus = bus
        self.buf = buffer
        self.clock = clock
        self.schedule = schedule or Schedule()
        self.layout = buffer.layout
        self.policy = rack.commands
        if max_input_age_frames is not None:  # overrides the rack file's [commands] value
            if isinstance(max_input_age_frames, bool) or int(max_input_age_frames) != max_input_age_frames \
                    or max_input_age_frames < 1:
                raise ConfigError(f"max_input_age_frames must be a whole number of frames >= 1, "
                                  f"not {max_input_age_frames!r}")
            from dataclasses import replace
            self.policy = replace(self.policy, max_input_age_frames=int(max_input_age_frames))
        age_s = self.policy.max_input_age_frames * self.schedule.period_s
        if age_s > watchdog_s + 1e-9:
            raise ConfigError(f"rack {rack.name}: [commands] max_input_age_frames = "
                              f"{self.policy.max_input_age_frames} ({age_s * 1e3:.2f} ms at "
                              f"{self.schedule.frame_rate_hz:g} Hz) exceeds the {watchdog_s * 1e3:g} ms "
                              f"command watchdog; lower it or raise the watchdog")
        buffer.claim("service", owner)
        self.inputs = buffer.writer("inputs")
        #: optional ``bit3.ring.FrameRing``: every published inputs body is also
        #: appended there (``pfma serve`` creates it for recorders)
        self.ring = None
        self.stats_writer = buffer.writer("stats")
        self.commands = buffer.reader("commands")
        self.queue = buffer.queue("service_messages")
        self.guard = OutputGuard(clock, watchdog_s, post=self._post_guard)
        self._hb_ok = None  # heartbeat of the last command written by the claim holder
        self._hb_seen = None  # heartbeat in the command record at the last good read
        self._refusals_seen = 0
        self._cmd_episode = 0  # command_status bits already announced by a message
        self._last_alive = None  # clock time the service last ran (frame or hook tick)
        self._stall_s = 0.0  # the latest host stall and when it ended
        self._stall_end = -math.inf
        self._guard_state = self.guard.state
        self.loop_stats = LoopStats()
        self.loop = FrameLoop(clock, self.schedule.period_s, self.frame, self.loop_stats)
        self.io = RackIO(bus, rack, clock)
        self.state = ServiceState.STARTING
        self.fault_code = FAULT_NONE
        self._rec = self.inputs.record
        self._v = {name: self.inputs.record[name] for name in self.inputs.record.dtype.names}
        self._stats_rec = self.stats_writer.record
        self._devices = {g: _DeviceCounter() for g in ("rtd", "adc", "dac", "ft", "pio", "crl", "hid")}
        self._board_fail_run: dict[str, int] = {}
        self.init_errors: list[str] = []  #: full texts of start-up problems (messages are cut to 56 bytes)
        self._build_tasks()
        self._wire_rtd()
        self._wire_adc()
        self._wire_dac()
        self._wire_pio()
        self._ft = self._crl = self._cae = None
        self._ft_latest = None
        self._ft_retry = 0  # frames left in which a missed F/T slot is tried again
        self._crl_latest = None
        self._mvme400 = None
        self._last_drain = -math.inf  # clock time of the last serial FIFO drain
        self._ft_url = ft_port
        if serial:
            self._wire_serial()
        if ft_port is not None:
            self._wire_ft_url()
        self._wire_cae()
        self._apply_calibration_extras()  # calibration: resolver offsets, CAE, F/T, header hash
        self._cpu0 = self._cpu_s()
        self._wall0 = clock.now()
        self.stats_every = max(1, int(round(self.schedule.frame_rate_hz / 2)))  # twice a second
        self._stats_between_frames = False  # True while run() has idle_tick on the clock
        self._stats_due_k = None  # frame that asked for statistics not yet published
        self.set_state(ServiceState.SAFE)
        self.post(Severity.INFO, 100, f"service started: {rack.name}, "
                  f"{self.schedule.frame_rate_hz:g} Hz frames, watchdog {watchdog_s * 1e3:g} ms")
        for diff in self.schedule.check_documented_rates():
            self.post(Severity.WARNING, 101, f"schedule differs from the report: {diff}")

    # ------------------------------------------------------------------ set-up
    def _build_tasks(self) -> None:
        table = self.schedule.frame_table()
        names = ("rtd", "adc", "ft", "hand", "pio")  # inputs, in run order
        self._frame_tasks = tuple(tuple(n for n in names if n in frame) for frame in table)
        self._frame_masks = tuple(sum(1 << i for i, n in enumerate(names) if n in frame)
                                  for frame in table)
        self._task_names = names

    def _board_slot(self, board: str) -> int:
        return self.layout.slot("board", board)

    def _slots(self, kind: str, channels) -> np.ndarray:
        return np.array([self.layout.slot(kind, c.signal) for c in channels], dtype=np.intp)

    def _span(self, kind: str, channels) -> np.ndarray | slice:
        """Like :meth:`_slots`, as a slice when the slots are consecutive (the default
        layout's): the per-frame copies into the input area then avoid fancy indexing."""
        slots = self._slots(kind, channels)
        if len(slots) and np.array_equal(slots, np.arange(slots[0], slots[0] + len(slots))):
            return slice(int(slots[0]), int(slots[0]) + len(slots))
        return slots

    def _init_board(self, cfg, action) -> bool:
        slot = self._board_slot(cfg.name)
        try:
            action()
        except PfmaError as err:
            self._v["board_status"][slot] = BOARD_FAULT
            self._count_board_error(cfg.name, err)
            self.post(Severity.ERROR, 110, f"{cfg.name}: init failed: {err}")
            return False
        self._v["board_status"][slot] = BOARD_OK | BOARD_INIT
        return True

    def _wire_rtd(self) -> None:
        self._rtd = []
        for cfg in self.rack.boards_of("rtd"):
            drv = self.io.driver(cfg)
            slots = self._span("rtd", cfg.channels)
            self._rtd.append((cfg, drv, slots, self._board_slot(cfg.name)))
            self._init_board(cfg, drv.status)

    def _wire_adc(self) -> None:
        self._adc = []
        for cfg in self.rack.boards_of("adc"):
            drv = self.io.driver(cfg)
            chans = sorted(cfg.channels, key=lambda c: c.channel)
            slots = self._span("adc", chans)
            scale = np.array([c.scale for c in chans])
            offset = np.array([c.offset for c in chans])
            counts = np.zeros(len(chans), dtype=np.int64)
            volts = np.zeros(len(chans))
            self._adc.append((cfg, drv, slots, scale, offset, counts, volts, self._board_slot(cfg.name)))
            self._init_board(cfg, lambda d=drv: d.read_counts(0))

    def _wire_dac(self) -> None:
        dacs = self.rack.boards_of("dac")
        if len(dacs) != 1:
            raise PfmaError(f"rack {self.rack.name}: the service drives exactly one DAC board, "
                            f"found {len(dacs)}")
        cfg = dacs[0]
        self._dac_cfg = cfg
        self._dac = self.io.driver(cfg)
        n = len(cfg.channels)
        chans = sorted(cfg.channels, key=lambda c: c.channel)
        self._dac_slots = self._span("dac", chans)
        self._dac_n = n
        self._dac_scale_l = [c.scale for c in chans]  # volts = (engineering - offset) / scale
        self._dac_offset_l = [c.offset for c in chans]
        self._dac_zeros = [0.0] * n
        self._dac_forced_safe = [DAC_FORCED_SAFE] * n
        sig = {c.signal: c.channel for c in chans}
        # command-area order (layout.joint_names / current_limit_names) -> DAC channel, by the
        # rack's channel roles (quantity rate_command / current_limit / gripper_command)
        self._cmd_rate_list = [self.layout.joint_entry("dac", j, "rate_command").channel
                               for j in self.layout.joint_names]
        self._cmd_limit_list = [sig[s] for s in self.layout.current_limit_names]
        self._dac_is_limit = [ch in self._cmd_limit_list for ch in range(n)]
        self._dac_is_rate = [ch in self._cmd_rate_list for ch in range(n)]
        grip = [c.channel for c in chans if c.quantity == "gripper_command"]
        self._cmd_gripper_ch = grip[0] if grip else None
        if self._cmd_gripper_ch is not None:
            self._dac_is_rate[self._cmd_gripper_ch] = True  # a motor command too: 0 V when stale
        self._set_dac_limits(chans)
        self._dac_board_slot = self._board_slot(cfg.name)
        self._outputs_enabled = False
        # Outputs start disconnected and at 0 V: write the zeros, keep P3 off.
        self._init_board(cfg, self._dac.disable_outputs)

    def _set_dac_limits(self, chans) -> None:
        """Per DAC channel: the engineering limit a command is refused beyond (``limit``
        in the rack file, default the DAC's full range), the saturation volts within it,
        and the names the refusal message uses."""
        r = self._dac.range_volts
        m = 1.0 + self.policy.limit_margin
        self._dac_limit = []  # engineering limit per channel (rates: |x|, current limits: 0..x)
        self._dac_refuse = []  # limit x (1 + margin)
        self._dac_sat_v = []  # saturation volts: the DAC range or the limit, whichever is lower
        for c in chans:
            full = r * abs(c.scale)
            lim = c.limit if c.limit is not None else full
            self._dac_limit.append(lim)
            self._dac_refuse.append(lim * m)
            self._dac_sat_v.append(min(r, lim / abs(c.scale)) if c.scale else 0.0)
        self._dac_names = [c.signal for c in chans]
        self._dac_units = [c.units for c in chans]

    def _wire_pio(self) -> None:
        self._pio_in = []
        self._pio_out = None
        self._matrix_applied = -1
        for cfg in self.rack.boards_of("pio"):
            drv = self.io.driver(cfg)
            dirs = ["in"] * 4
            for c in cfg.channels:
                dirs[c.channel] = c.direction
            slots = {c.channel: self.layout.slot("pio", c.signal) for c in cfg.channels}
            if self._init_board(cfg, lambda d=drv, dd=dirs: d.configure(dd)):
                if any(c.signal == "matrix_switcher_route" for c in cfg.channels):
                    self._pio_out = (cfg, drv, slots)
                if any(c.signal.startswith("user_if_box_inputs") for c in cfg.channels):
                    self._pio_in.append((cfg, drv, slots))

    def _start_ft(self, port, baud: int, where: str) -> None:
        """Binary records with checksum, streamed (QS); then only non-blocking reads."""
        from drivers.serial_ft.ftsensor import FtSensor
        ft = FtSensor(port, clock=self.clock, baud=baud)
        err = None
        for attempt in range(1, FT_START_ATTEMPTS + 1):
            try:
                ft.set_mode("binary")
                ft.set_checksum(True)
                ft.start_stream(rate_hz=self.schedule.rate_hz("ft"))
                port.timeout = 0  # from now on only non-blocking reads, between frames
                # an MVME400 port: serial_tick drains it, and decodes as soon as a record is
                # complete (its time stamp is then its arrival, and after lost characters
                # the link is synced again at the first whole record, not at the next F/T slot)
                self._ft_in_tick = hasattr(port, "autopoll")
                if self._ft_in_tick:
                    port.autopoll = False
                self._ft = ft
                if attempt > 1:
                    self.post(Severity.WARNING, 122, f"F/T sensor on {where}: streaming after "
                              f"{attempt} attempts ({str(err)[:40]})")
                return
            except PfmaError as e:
                # A reply garbled by characters lost on a 3-deep FIFO (a host that did not
                # poll the line in time) is transient: ask again, the sensor answers anew.
                err = e
                try:  # the sensor may be streaming already (a garbled QS echo): CR stops it
                    ft.streaming = True
                    ft.stop_stream()
                except PfmaError:
                    pass
        self.init_errors.append(str(err))
        self.post(Severity.ERROR, 120, f"F/T sensor on {where}: not streaming: {err}")
        self._v["link_status"][self.layout.slot("link", "ft_sensor")] = LINK_FAULT

    def _wire_ft_url(self) -> None:
        """The F/T sensor on a pyserial URL (USB-serial adapter, terminal server) instead of
        the MVME400: the kernel's or the server's buffer holds the bytes between frames."""
        import serial
        try:
            port = serial.serial_for_url(self._ft_url, baudrate=19200, timeout=0.05)
        except (serial.SerialException, ValueError) as err:
            self.init_errors.append(f"F/T port {self._ft_url}: {err}")
            self.post(Severity.ERROR, 121, f"F/T port {self._ft_url}: {err}")
            return
        self._start_ft(port, 19200, self._ft_url)

    def _wire_serial(self) -> None:
        from drivers.crl.crl import CrlHandController
        boards = self.rack.boards_of("serial")
        if not boards:
            return
        cfg = boards[0]
        ch = {c.signal: c for c in cfg.channels}
        drv = self.io.driver(cfg)
        bauds = [int(ch_.baud or 19200) for ch_ in sorted(cfg.channels, key=lambda c: c.channel)]
        if not self._init_board(cfg, lambda: drv.init(baud_a=bauds[0], baud_b=bauds[1])):
            return
        self._mvme400 = (cfg, drv)
        if "ft_sensor" in ch and self._ft_url is None:
            port = drv.port(ch["ft_sensor"].channel, timeout=0.05)
            self._start_ft(port, bauds[ch["ft_sensor"].channel], f"{cfg.name} port {ch['ft_sensor'].channel}")
        if "crl_hand_controller" in ch:
            port = drv.port(ch["crl_hand_controller"].channel, timeout=0, write_queue=True)
            port.autopoll = False  # serial_tick drains the FIFO; decoding reads the buffer
            self._crl = CrlHandController(port, self.clock)
            self._crl_tx = 0

    def _wire_cae(self) -> None:
        from drivers.crl.cae import CaeHandController
        try:
            self._cae = CaeHandController(rack=self.rack, clock=self.clock)
        except (PfmaError, KeyError) as err:
            self.post(Severity.WARNING, 130, f"CAE hand controller not available: {err}")
            return
        # where the CAE channels sit among the ADC board's scanned volts
        sigs = ("cae_up_down", "cae_forward_backward", "cae_right_left", "cae_yaw", "cae_pitch",
                "cae_roll", "cae_discrete_1", "cae_discrete_2", "cae_discrete_3")
        chans = [self.rack.channel(s) for s in sigs]
        board = chans[0].board
        self._cae_adc = next(i for i, a in enumerate(self._adc) if a[0].name == board)
        self._cae_idx = np.array([c.channel for c in chans], dtype=np.intp)

    # ------------------------------------------------------------------ messages and state
    def post(self, severity: int, code: int, text: str) -> None:
        self.queue.post(text, severity=severity, code=code, t_s=self.clock.now())

    def _post_guard(self, severity: int, code: int, text: str) -> None:
        self.post((Severity.INFO, Severity.WARNING, Severity.ERROR)[min(severity, 2)], code, text)

    def set_state(self, state: ServiceState) -> None:
        self.state = state
        self.buf.set_service_state(state)
        self._v["service_state"][...] = int(state)

    def _count_board_error(self, board: str, err: Exception) -> None:
        slot = self._board_slot(board)
        self._v["board_errors"][slot] += 1
        self._v["board_status"][slot] |= BOARD_FAULT
        self._v["board_last_error_addr"][slot] = getattr(err, "addr", 0) or 0
        self._v["board_last_error_t_s"][slot] = self.clock.now()

    def _input_failed(self, board: str, group: str, err: Exception) -> None:
        self._count_board_error(board, err)
        self._devices[group].errors += 1
        run = self._board_fail_run.get(board, 0) + 1
        self._board_fail_run[board] = run
        if run == 1:
            self.post(Severity.ERROR, 111, f"{board}: {err}")
        if run == INPUT_FAULT_FRAMES:
            self.fault_code = FAULT_INPUTS
            self.guard.trip(f"{board} failed {run} samples in a row: {err}", code=FAULT_INPUTS)

    def _input_ok(self, board: str, slot: int) -> None:
        if self._board_fail_run.get(board):
            self._board_fail_run[board] = 0
            self._v["board_status"][slot] = BOARD_OK | BOARD_INIT

    def _sampled(self, group: str, t: float) -> None:
        d = self._devices[group]
        d.samples += 1
        d.t_last = t

    # ------------------------------------------------------------------ the frame
    def frame(self, info: FrameInfo) -> None:
        """One minor frame: the DAC first (commands and the watchdog checked at a fixed,
        short time after the wake-up, before the variable input work), then the inputs due
        in this frame (and in frames just dropped), then one consistent publish of the
        input area."""
        k = info.index
        self.serial_tick()  # the 3-deep serial FIFOs: drain on both sides of the work
        mask = self._frame_masks[k % MINOR_FRAMES_PER_MAJOR]
        for j in range(1, min(info.missed, MINOR_FRAMES_PER_MAJOR) + 1):
            mask |= self._frame_masks[(k - j) % MINOR_FRAMES_PER_MAJOR]
        if mask & 4:
            self._ft_retry = FT_RETRY_FRAMES
        elif self._ft_retry:  # the last F/T slot found nothing new: look again
            self._ft_retry -= 1
            mask |= 4
        self._note_alive(info.t_wake)
        try:
            self._task_dac(k)
            if mask & 1:
                self._task_rtd()
                self._drain_if_due()  # a slow input scan must not overrun the FIFOs
            if mask & 2:
                self._task_adc()
                self._drain_if_due()
            if mask & 4:
                self._task_ft()
            if mask & 8:
                self._task_hand()
            if mask & 16:
                self._task_pio()
        except Exception as err:  # noqa: BLE001 - a fault we cannot explain: outputs safe
            self.fault_code = FAULT_UNEXPECTED
            self.guard.trip(f"unexpected {type(err).__name__} in frame {k}: {err}", code=FAULT_UNEXPECTED)
            self._apply_safe()
        self._publish(info)
        self.serial_tick()
        self._last_alive = self.clock.now()  # a long frame is the service's own work, not a stall
        if k % self.stats_every == 0:
            if self._stats_between_frames:
                self._stats_due_k = k  # computed in the sleep after this frame (idle_tick)
            else:
                self.publish_stats()
        elif self._stats_due_k is not None and k - self._stats_due_k >= STATS_MAX_DEFER_FRAMES:
            self.publish_stats()  # no idle time for a while (overloaded): do it here

    def _task_rtd(self) -> None:
        v = self._v
        t_ok = None
        for cfg, drv, slots, bslot in self._rtd:
            t = self.clock.now()
            try:
                counts = drv.read_counts()
                status = drv.status()
            except PfmaError as err:
                self._input_failed(cfg.name, "rtd", err)
                v["rtd_status"][slots] |= CHANNEL_BUS_ERROR
                continue
            # four values: plain Python beats numpy's per-call cost
            v["rtd_counts"][slots] = counts
            lsb = drv.lsb_rad
            cal = self._rtd_cal.get(cfg.name)
            if cal is None:
                v["rtd_angle_rad"][slots] = [c * lsb for c in counts]
            else:  # calibration: (scale * raw + offset) mod 2 pi
                v["rtd_angle_rad"][slots] = [(c * lsb * k + off) % _TWO_PI
                                             for c, k, off in zip(counts, *cal, strict=True)]
            ref = 0 if status.reference_present else RTD_NO_REFERENCE
            v["rtd_status"][slots] = [int(f) | ref for f in status.faults]
            self._input_ok(cfg.name, bslot)
            v["t_rtd_s"][...] = t
            t_ok = t
        if t_ok is not None:
            self._sampled("rtd", t_ok)

    def _task_adc(self) -> None:
        v = self._v
        for cfg, drv, slots, scale, offset, counts, volts, bslot in self._adc:
            t = self.clock.now()
            try:
                drv.scan(counts)
            except PfmaError as err:
                self._input_failed(cfg.name, "adc", err)
                v["adc_status"][slots] |= CHANNEL_BUS_ERROR
                continue
            np.multiply(np.subtract(counts, drv.zero_code, out=volts, casting="unsafe"), drv.lsb_volts, out=volts)
            v["adc_counts"][slots] = counts
            v["adc_volts"][slots] = volts
            v["adc_value"][slots] = volts * scale + offset
            v["adc_status"][slots] = 0
            self._input_ok(cfg.name, bslot)
            v["t_adc_s"][...] = t
            self._sampled("adc", t)

    def _task_ft(self) -> None:
        self._decode_serial()
        ft = self._ft
        if ft is None:
            return
        v = self._v
        slot = self.layout.slot("link", "ft_sensor")
        r = self._ft_latest
        st = ft.stats()
        v["link_records"][slot] = st.records
        v["link_bad"][slot] = st.bad_records
        v["link_resyncs"][slot] = st.resyncs
        v["link_rate_hz"][slot] = st.rate_hz
        v["link_age_s"][slot] = -1.0 if st.age_s is None else st.age_s
        stale = st.age_s is None or st.age_s > FT_STALE_S
        v["link_status"][slot] = LINK_OPEN | (LINK_STALE if stale else LINK_SYNCED)
        if r is not None and r.t_s != v["ft_t_s"][()]:
            self._ft_retry = 0  # this F/T period has its record
            v["ft_counts"][:] = r.counts
            v["ft_force_n"][:] = r.force_n
            v["ft_torque_nm"][:] = r.torque_nm
            if self._ft_cal is not None:  # calibration: wrench = matrix @ (counts - bias)
                w = self._ft_cal.wrench(r.counts)
                v["ft_force_n"][:] = w[:3]
                v["ft_torque_nm"][:] = w[3:]
            v["ft_status"][...] = r.status
            v["ft_t_s"][...] = r.t_s
            v["t_ft_s"][...] = r.t_s
            self._sampled("ft", r.t_s)

    def _put_hand(self, name: str, s) -> None:
        v = self._v
        i = self.layout.slot("hc", name)
        v["hc_axes"][i] = s.axes
        v["hc_deadman"][i] = s.deadman
        v["hc_valid"][i] = s.valid
        v["hc_fault"][i] = s.fault
        v["hc_buttons"][i] = s.buttons
        v["hc_t_s"][i] = s.t_s

    def _task_hand(self) -> None:
        if self._crl is not None and self._ft is None:
            self._decode_serial()
        if self._cae is not None and self._adc:
            volts = self._adc[self._cae_adc][6]
            self._put_hand("cae", self._cae.from_volts(volts[self._cae_idx].tolist(),
                                                        t_s=float(self._v["t_adc_s"][()])))
        if self._crl is not None:
            self._send_crl_force()
        if self._crl_latest is not None:
            self._put_hand("crl", self._crl_latest)
            stats = self._crl.link_stats()
            slot = self.layout.slot("link", "crl_hand_controller")
            v = self._v
            v["link_records"][slot] = stats["frames_ok"]
            v["link_bad"][slot] = stats["frames_bad"]
            v["link_resyncs"][slot] = stats["resyncs"]
            v["link_status"][slot] = LINK_OPEN | (LINK_FAULT if stats["tripped"] else LINK_SYNCED)
            v["link_rate_hz"][slot] = stats["rate_hz"]
            v["link_age_s"][slot] = stats["age_s"]
            self._sampled("crl", self._crl_latest.t_s)

    def _send_crl_force(self) -> None:
        """Force reflection to the CRL at half the hand-controller rate (40 Hz; its
        placeholder protocol's watchdog is 60 ms): the command area's force while armed and
        enabled, zero and disabled otherwise. Queued: the bytes leave between frames."""
        self._crl_tx ^= 1
        if not self._crl_tx:
            return
        c = self.commands.record
        live = self.guard.state == ServiceState.ARMED and bool(c["crl_reflect_enable"])
        f = tuple(float(x) for x in c["crl_reflect_force_n"]) if live else (0.0, 0.0, 0.0)
        t = tuple(float(x) for x in c["crl_reflect_torque_nm"]) if live else (0.0, 0.0, 0.0)
        try:
            self._crl.send_force(f, t, enable=live)
        except (PfmaError, ValueError) as err:
            self._devices["crl"].errors += 1
            if self._devices["crl"].errors == 1:
                self.post(Severity.ERROR, 142, f"CRL force reflection: {err}")

    def _task_pio(self) -> None:
        v = self._v
        t = self.clock.now()
        for cfg, drv, slots in self._pio_in:
            try:
                word = drv.read_user_inputs()
            except PfmaError as err:
                self._input_failed(cfg.name, "pio", err)
                continue
            v["pio_user_inputs"][...] = word
            v["pio_port_bits"][slots[0]] = word & 0xFF
            v["pio_port_bits"][slots[1]] = word >> 8
            self._input_ok(cfg.name, self._board_slot(cfg.name))
            v["t_pio_s"][...] = t
            self._sampled("pio", t)
        if self._pio_out is not None:
            route = int(self.commands.record["matrix_route"])
            if route != self._matrix_applied:
                cfg, drv, slots = self._pio_out
                try:
                    drv.write_matrix_route(route)
                    self._matrix_applied = route
                    v["matrix_route"][...] = route
                    v["pio_port_bits"][slots[0]] = route & 0xFF
                    self.post(Severity.INFO, 140, f"matrix switcher route 0x{route:02X}")
                except (PfmaError, ValueError) as err:
                    self._count_board_error(cfg.name, err)
                    self._matrix_applied = route  # do not retry every frame; posted once
                    self.post(Severity.ERROR, 141, f"{cfg.name}: matrix route 0x{route:02X} failed: {err}")

    # ------------------------------------------------------------------ the command path
    def _fetch_command(self) -> int:
        """One bounded read of the command area (a writer killed mid-write leaves its
        counter odd: the frame goes on and the command counts as absent, the record keeps
        the last good copy) and the claim check (pid and token in the body must be the
        owner slot's). Returns 0 for a good command, CMD_ABSENT, CMD_FOREIGN, or
        _NO_WRITER (nobody holds the claim). Only a good command's heartbeat is noted in
        ``_hb_ok``: a foreign write never feeds the watchdog."""
        if not self.commands.try_read():
            return CMD_ABSENT
        c = self.commands.record
        pid, token = self.buf.owner_pid_token("commands")
        body_pid = int(c["writer_pid"])
        if pid <= 0 or body_pid == 0:  # nobody holds the claim, or the holder has not written yet
            return _NO_WRITER
        if body_pid != pid or int(c["writer_token"]) != token:
            return CMD_FOREIGN
        self._hb_ok = int(c["heartbeat"])
        return 0

    def _stall_note(self) -> str:
        """" (stall N ms)" while a recent host stall explains a late command, else "" (the
        stall itself was announced as "host stall: ..." when it ended)."""
        if self.clock.now() - self._stall_end <= STALL_BLAME_S:
            return f" (stall {self._stall_s * 1e3:.0f} ms)"
        return ""

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
            self.post(Severity.WARNING, 170, f"host stall: service did not run for {self._stall_s * 1e3:.0f} ms")

    def _check_limits(self, eng: list[float]) -> str | None:
        """The first command value that is not finite or beyond its limit (x (1 + margin)),
        as a message giving field, value and limit; None when every value is acceptable."""
        isfinite = math.isfinite
        for ch, e in enumerate(eng):
            lim = self._dac_refuse[ch]
            if not isfinite(e):
                bad = True
            elif self._dac_is_limit[ch]:
                bad = e > lim or e < -self.policy.limit_margin * self._dac_limit[ch]
            else:
                bad = e > lim or e < -lim
            if bad:
                lo = "0.." if self._dac_is_limit[ch] else "+-"
                return (f"refused {self._dac_names[ch]}={e:.4g} {self._dac_units[ch]}, "
                        f"limit {lo}{self._dac_limit[ch]:g}")
        c = self.commands.record
        for f in ("crl_reflect_force_n", "crl_reflect_torque_nm"):
            if not all(isfinite(x) for x in c[f].tolist()):
                return f"refused {f} not finite"
        return None

    def _announce(self, bits: int, text: str, severity: int = Severity.ERROR) -> None:
        """Post ``text`` when a command-status condition starts (not every frame it lasts)."""
        if not self._cmd_episode & bits:
            self._cmd_episode |= bits
            self.post(severity, 171, text)

    def _task_dac(self, k: int = 0) -> None:
        v = self._v
        status = self._fetch_command()
        c = self.commands.record
        refusal = None
        hb_now = int(c["heartbeat"])
        new_write = self._hb_seen is not None and hb_now != self._hb_seen
        if not status & CMD_ABSENT:
            self._hb_seen = hb_now
        if status & CMD_ABSENT:
            v["absent_commands"] += 1
            self._announce(CMD_ABSENT, "command area: no stable copy (writer died mid-write?)",
                           Severity.WARNING)
        elif status & CMD_FOREIGN:
            # the body is not the claim holder's: never obeyed; a new such write is counted
            pid, _tok = self.buf.owner_pid_token("commands")
            if new_write:
                v["foreign_writes"] += 1
            refusal = f"refused write by pid {int(c['writer_pid'])}: owner pid {pid}"
        status &= CMD_ABSENT | CMD_FOREIGN  # _NO_WRITER is not published: no command yet
        # engineering command per DAC channel, in plain Python (16 values)
        eng = [0.0] * self._dac_n
        rates = c["joint_rate_rad_s"].tolist()
        for ch, x in zip(self._cmd_rate_list, rates):
            eng[ch] = x
        for ch, x in zip(self._cmd_limit_list, c["current_limit_a"].tolist()):
            eng[ch] = x
        if self._cmd_gripper_ch is not None:
            eng[self._cmd_gripper_ch] = float(c["gripper"])
        if refusal is None:
            refusal = self._check_limits(eng)
            if refusal is not None:
                status |= CMD_REFUSED
        hb = self._hb_ok if self._hb_ok is not None else -1
        live = self.guard.update(hb, bool(c["arm_request"]), int(c["rearm_counter"]),
                                 not any(rates), refusal=refusal, stall_note=self._stall_note())
        if self.guard.refusals != self._refusals_seen:  # one refusal, one message (the guard's)
            self._refusals_seen = self.guard.refusals
            v["refused_commands"] += 1
            self.fault_code = FAULT_FOREIGN if status & CMD_FOREIGN else FAULT_COMMAND
        v["command_heartbeat"][...] = hb if hb >= 0 else 0
        v["command_age_s"][...] = self.guard.heartbeat_age_s()
        if self.guard.state == ServiceState.FAULT and self.state != ServiceState.FAULT:
            if self.fault_code == FAULT_NONE:
                self.fault_code = FAULT_WATCHDOG
            v["watchdog_tripped"][...] = self.fault_code == FAULT_WATCHDOG
        if self.guard.state == ServiceState.ARMED and self._guard_state != ServiceState.ARMED:
            # a successful (re-)arm: what made the outputs safe before is over
            self.fault_code = FAULT_NONE
            v["watchdog_tripped"][...] = 0
            self._cmd_episode = 0
        self._guard_state = self.guard.state
        # freshness: how old are the inputs these commands were computed from?
        f_in = int(c["inputs_frame"])
        age = k - f_in
        v["command_inputs_frame"][...] = f_in
        v["command_input_age_frames"][...] = age if 0 <= age < 0xFFFFFFFF else 0xFFFFFFFF
        if not live:
            v["command_status"][...] = status
            # a condition that ended may be announced again; refusals stay announced until re-armed
            self._cmd_episode &= status | CMD_REFUSED | CMD_FOREIGN
            self._apply_safe()
            return
        if not self._outputs_enabled:
            self._dac.enable_outputs()  # the shadow holds the zeros written while safe
            self._outputs_enabled = True
        stale = age < 0 or age > self.policy.max_input_age_frames
        if stale:
            status |= CMD_STALE
            v["stale_commands"] += 1
            self._announce(CMD_STALE, f"rates 0V: cmd inputs {age} fr old > "
                                      f"{self.policy.max_input_age_frames}{self._stall_note()}")
        self._cmd_episode &= status | CMD_REFUSED | CMD_FOREIGN
        v["command_status"][...] = status
        r = self._dac.range_volts
        volts, st_out = [], []
        for ch, e in enumerate(eng):
            k_ = self._dac_scale_l[ch]
            if stale and self._dac_is_rate[ch]:
                volts.append(0.0)
                st_out.append(DAC_FORCED_SAFE)
                eng[ch] = 0.0
                continue
            x = (e - self._dac_offset_l[ch]) / k_ if k_ else 0.0
            st = 0
            sat = self._dac_sat_v[ch] if self._dac_sat_v[ch] > 0 else r
            if self._dac_is_limit[ch] and x < 0.0:
                st, x = DAC_CLIPPED, 0.0  # a current limit within the margin below 0: brakes set
            elif x > sat or x < -sat:  # within the refusal margin: saturate, say so
                st, x = DAC_CLIPPED, (sat if x > sat else -sat)
            volts.append(x)
            st_out.append(st)
        self._write_dac(volts, st_out, eng)

    def _apply_safe(self) -> None:
        if self.state == ServiceState.ARMED or self.guard.state == ServiceState.FAULT:
            self.set_state(self.guard.state)
        self._write_dac(self._dac_zeros, self._dac_forced_safe, self._dac_zeros)

    def _write_dac(self, volts: list[float], status: list[int], eng: list[float]) -> None:
        v = self._v
        t = self.clock.now()
        try:
            self._dac.write_volts_all(volts, clamp=True)
        except PfmaError as err:
            self._count_board_error(self._dac_cfg.name, err)
            self._devices["dac"].errors += 1
            self.fault_code = FAULT_DAC
            self.guard.trip(f"DAC write failed: {err}", code=FAULT_DAC)
            return
        slots = self._dac_slots
        v["dac_counts"][slots] = self._dac.shadow_counts
        v["dac_volts"][slots] = self._dac.shadow_volts
        v["dac_value"][slots] = eng
        v["dac_status"][slots] = status
        v["outputs_enabled"][...] = self._outputs_enabled and self.guard.state == ServiceState.ARMED
        v["brakes_released"][...] = self._outputs_enabled and \
            any(volts[ch] > BRAKE_RELEASE_V for ch in self._cmd_limit_list)
        v["t_dac_s"][...] = t
        self._sampled("dac", t)
        if self.guard.state != self.state and self.state not in (ServiceState.STOPPED,):
            self.set_state(self.guard.state)

    def _publish(self, info: FrameInfo) -> None:
        v = self._v
        v["frame"][...] = info.index
        v["t_s"][...] = info.t_wake
        v["service_state"][...] = int(self.state)
        v["fault_code"][...] = self.fault_code
        self.inputs.publish()
        if self.ring is not None:  # the history a stalled recorder catches up from
            self.ring.write(self.inputs.raw)
        self.buf.set_frame(info.index, info.t_wake)

    # ------------------------------------------------------------------ between frames
    def serial_tick(self, now: float | None = None) -> None:
        """Drain the serial boards' receive FIFOs into the drivers' buffers (TickingClock
        hook between frames, and around the work inside a frame). The MVME400 F/T line is
        decoded here as soon as its buffer can complete a record (``FtSensor.record_due``);
        the hand controller in its task. A drain within ``SERIAL_MIN_GAP_S`` of the previous
        one is skipped: the FIFO cannot have filled, and every drain costs register accesses."""
        if self._mvme400 is None:
            return
        t = self.clock.now()
        if t - self._last_drain < SERIAL_MIN_GAP_S:
            return
        self._last_drain = t
        cfg, drv = self._mvme400
        try:
            drv.poll()
        except PfmaError as err:
            self._count_board_error(cfg.name, err)
        ft = self._ft
        if ft is not None and self._ft_in_tick:
            try:
                due = ft.record_due()  # a length check on the software buffer: no bus access
            except PfmaError:
                due = True  # let the decode count the failure
            if due:
                self._decode_serial(hand=False)

    def _drain_if_due(self) -> None:
        """Inside a frame, at a task boundary: drain the serial FIFOs if ``SERIAL_MIN_GAP_S``
        has passed since the last drain (a slow scan, or a host that preempted the frame)."""
        self.serial_tick()

    def _decode_serial(self, hand: bool = True) -> None:
        try:
            if self._ft is not None:
                recs = self._ft.read_records()
                if recs:
                    self._ft_latest = recs[-1]
            if hand and self._crl is not None:
                self._crl_latest = self._crl.update()
        except PfmaError as err:
            if self._mvme400 is not None:
                self._count_board_error(self._mvme400[0].name, err)
            self._devices["ft"].errors += 1

    # ------------------------------------------------------------------ statistics
    @staticmethod
    def _cpu_s() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    def idle_tick(self, now: float | None = None) -> None:
        """Between frames (a TickingClock hook that :meth:`run` installs, every 0.4 ms of
        sleep when live):

        - while ARMED, the command heartbeat is checked, and a stale one drives the DAC to
          0 V at once rather than at the next frame (the reaction to a dead controller is
          then the watchdog plus one tick, not plus one frame and a late wake-up);
        - the statistics a frame asked for are published (percentiles over the 4096-frame
          window cost about 1 ms, a periodic work spike inside a frame).
        """
        self._note_alive(self.clock.now())
        if self.guard.state == ServiceState.ARMED and self.state == ServiceState.ARMED:
            self._fetch_command()  # only a good command's heartbeat counts (_hb_ok)
            hb = self._hb_ok if self._hb_ok is not None else -1
            if self.guard.check_between_frames(hb, stall_note=self._stall_note()):
                self.fault_code = FAULT_WATCHDOG
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
        p = s["period_s"]["p50"]
        rec["rate_hz"] = 1.0 / p if p and p > 0 and not math.isnan(p) else 0.0
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
        self.guard.stop(reason)
        try:
            self._dac.disable_outputs()
        except PfmaError as err:
            self.post(Severity.ERROR, 150, f"could not disable DAC outputs: {err}")
        self._outputs_enabled = False
        slots = self._dac_slots
        self._v["dac_counts"][slots] = self._dac.shadow_counts
        self._v["dac_volts"][slots] = self._dac.shadow_volts
        self._v["dac_value"][slots] = 0.0
        self._v["outputs_enabled"][...] = 0
        self._v["brakes_released"][...] = 0
        self.set_state(ServiceState.STOPPED)
        self.publish_stats()
        self.inputs.publish()
        if self.ring is not None:
            self.ring.write(self.inputs.raw)
        if self._ft is not None:
            try:
                self._ft.stop_stream()
            except PfmaError:
                pass
        self.post(Severity.INFO, 151, f"{reason} (pid {os.getpid()})")

    # ------------------------------------------------------------------ calibration
    # (calibration issue) Scales and offsets come from the rack configuration with the
    # calibration applied (calibration.files.apply_to_rack); resolver offsets, the CAE
    # and F/T sections and the header hash are applied here.
    def _apply_calibration_extras(self) -> None:
        from calibration.files import cae_calibration, calibration_hash, ft_calibration
        self._rtd_cal = {}
        for cfg, _drv, _slots, _b in self._rtd:
            chans = sorted(self.rack.board(cfg.name).channels, key=lambda c: c.channel)
            scale = np.array([c.scale for c in chans])
            offset = np.array([c.offset for c in chans])
            if np.any(scale != 1.0) or np.any(offset != 0.0):
                self._rtd_cal[cfg.name] = (scale.tolist(), offset.tolist())  # per channel
        cal = self.calibration
        self._ft_cal = ft_calibration(cal) if cal is not None else None
        if self._cae is not None:
            from drivers.crl.cae import CaeCalibration
            cae = cae_calibration(cal) if cal is not None else None
            self._cae.calibration = cae if cae is not None else CaeCalibration()
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
        for cfg, _drv, _slots, scale, offset, *_ in self._adc:
            chans = sorted(rack.board(cfg.name).channels, key=lambda c: c.channel)
            scale[:] = [c.scale for c in chans]
            offset[:] = [c.offset for c in chans]
        chans = sorted(rack.board(self._dac_cfg.name).channels, key=lambda c: c.channel)
        self._dac_scale_l = [c.scale for c in chans]
        self._dac_offset_l = [c.offset for c in chans]
        self._set_dac_limits(chans)
        self._apply_calibration_extras()
        self.post(Severity.INFO, 160, f"calibration v{cal.version} loaded ({cal.hash().hex()})")


def _calibrated_rack(rack: RackConfig, calibration):
    """(rack with calibrated scales, validated calibration) from a path or object."""
    from calibration.files import apply_to_rack, resolve
    cal = resolve(calibration, rack)
    return apply_to_rack(rack, cal), cal
