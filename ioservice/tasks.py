"""The service's device tasks: one object per device class of the rack.

Each task is wired once at start (``wire``: its boards, drivers, buffer slots and
calibration looked up from the rack configuration and the Bit3 layout) and run by
the service's frame in the minor frames the schedule gives it
(``run(k)``, k = the frame index). A task reaches the service it belongs to only through
``ioservice.host.TaskHost`` (the input area's value views, the clock, the board and device
counters, messages, a trip); this module does not import the service.

- :class:`RtdTask`: the resolver boards (angles, status) at 160 Hz
- :class:`AdcTask`: the A/D boards (32-channel scans, engineering values) at 160 Hz
- :class:`DacTask`: the DAC board: its channels' roles, limits and conversion of the
  engineering commands to volts, and the write; the command path that decides what is
  written (freshness, refusals, watchdog, safety guard) is ``ioservice.command``
- :class:`FtTask`: the F/T sensor (serial line: start-up dialogue, decoding; or a CAN node)
  and its link status at 80 Hz
- :class:`HandTask`: the CRL (serial), CAE (A/D) and USB HID (SpaceMouse) hand
  controllers at 80 Hz
- :class:`PioTask`: the parallel ports (user inputs, matrix switcher route) at 40 Hz

Count <-> unit conversions are the drivers' (``drivers/<board>``); the tasks apply only
the rack's engineering scales and the calibration.

The tasks that touch the register bus (resolvers, A/D, DAC, parallel ports) also have a
``probe()``: the same transactions as a run, nothing published and no counter moved,
which the service times at start to learn what a frame costs on its bus. A failed
transaction in a probe is timed like any other (the time a failure takes is what a frame
pays for it).
"""

from __future__ import annotations

import math
import threading
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from bit3.layout import (
    CHANNEL_BUS_ERROR, DAC_CLIPPED, DAC_FORCED_SAFE, LINK_FAULT, LINK_OPEN, LINK_STALE, LINK_SYNCED, RTD_NO_REFERENCE,
    MessageCode, Severity,
)
from pfma.errors import PfmaError

if TYPE_CHECKING:
    from ioservice.host import TaskHost
    from pfma.ft_calibration import FtCalibration
    from drivers.crl.cae import CaeHandController
    from drivers.crl.crl import CrlHandController
    from drivers.crl.hid import HidSpaceMouse
    from drivers.serial_ft.can_ft import CanFtSensor
    from drivers.serial_ft.ftsensor import FtSensor

#: F/T record older than this is flagged stale: 8 F/T periods. Assumed: long enough to
#: ride through a development VM's 10-50 ms host stalls (each costs a burst of lost bytes
#: on the 3-deep FIFO), short enough that a dead sensor stops force control within 0.1 s.
FT_STALE_S = 0.1
#: attempts at the F/T start-up dialogue (mode, checksum, stream) before the link is
#: reported faulty: one lost character garbles a reply, and on a loaded host the 3-deep
#: MVME400 FIFO can overrun during the dialogue
FT_START_ATTEMPTS = 3
#: current-limit volts above which the amplifier releases the brake (pfma-model 8.4, assumed)
BRAKE_RELEASE_V = 0.5

_TWO_PI = 2.0 * math.pi


def _by_channel(channels):
    return sorted(channels, key=lambda c: c.channel)


class InputTask(Protocol):
    """What the frame loop needs of an input task: its schedule name, whether the serial
    FIFOs are drained right after it (a long scan), and the per-frame work."""

    name: str
    drain_after: bool

    def run(self, k: int = 0) -> None: ...


class RtdTask:
    """Resolver boards: per board (config, driver, input-area slots, board slot), and the
    calibration per board that has one ((scale, offset) lists per channel)."""

    name = "rtd"
    drain_after = True  # a slow input scan must not overrun the serial FIFOs

    def __init__(self, svc: TaskHost) -> None:
        self.svc = svc
        self.boards: list[tuple] = []
        self.cal: dict[str, tuple[list[float], list[float]]] = {}

    def wire(self) -> None:
        svc = self.svc
        self.boards = []
        for cfg in svc.rack.boards_of("rtd"):
            drv = svc.io.driver(cfg)
            slots = svc.span("rtd", cfg.channels)
            self.boards.append((cfg, drv, slots, svc.board_slot(cfg.name)))
            svc.init_board(cfg, drv.status)

    def probe(self) -> None:
        """The run's transactions (counts and status of each board), nothing published."""
        for _cfg, drv, _slots, _bslot in self.boards:
            try:
                drv.read_counts_status()
            except PfmaError:
                pass

    def calibrate(self, rack) -> None:
        """Calibration: angle = (scale * raw + offset) mod 2 pi, per channel, for the boards
        whose channels are not nominal."""
        self.cal = {}
        for cfg, _drv, _slots, _b in self.boards:
            chans = _by_channel(rack.board(cfg.name).channels)
            scale = np.array([c.scale for c in chans])
            offset = np.array([c.offset for c in chans])
            if np.any(scale != 1.0) or np.any(offset != 0.0):
                self.cal[cfg.name] = (scale.tolist(), offset.tolist())

    def run(self, k: int = 0) -> None:
        svc = self.svc
        v = svc.values
        t_ok = None
        for cfg, drv, slots, bslot in self.boards:
            t = svc.clock.now()
            try:
                counts, status = drv.read_counts_status()  # one bus transaction per board
            except PfmaError as err:
                svc.input_failed(cfg.name, "rtd", err)
                v["rtd_status"][slots] |= CHANNEL_BUS_ERROR
                continue
            v["rtd_counts"][slots] = counts
            angles = drv.angles_from_counts(counts)  # four values: plain Python lists
            cal = self.cal.get(cfg.name)
            if cal is None:
                v["rtd_angle_rad"][slots] = angles
            else:  # calibration: (scale * raw + offset) mod 2 pi
                v["rtd_angle_rad"][slots] = [(a * k_ + off) % _TWO_PI
                                             for a, k_, off in zip(angles, *cal, strict=True)]
            ref = 0 if status.reference_present else RTD_NO_REFERENCE
            v["rtd_status"][slots] = [int(f) | ref for f in status.faults]
            svc.input_ok(cfg.name, bslot)
            v["t_rtd_s"][...] = t
            t_ok = t
        if t_ok is not None:
            svc.sampled("rtd", t_ok)


class AdcTask:
    """A/D boards: per board (config, driver, slots, engineering scale and offset arrays,
    the counts and volts arrays a scan fills in place, board slot)."""

    name = "adc"
    drain_after = True

    def __init__(self, svc: TaskHost) -> None:
        self.svc = svc
        self.boards: list[tuple] = []
        self._started: dict[str, float] = {}  # boards whose scan start() began this frame: when

    def wire(self) -> None:
        svc = self.svc
        self.boards = []
        for cfg in svc.rack.boards_of("adc"):
            drv = svc.io.driver(cfg)
            chans = _by_channel(cfg.channels)
            slots = svc.span("adc", chans)
            scale = np.array([c.scale for c in chans])
            offset = np.array([c.offset for c in chans])
            counts = np.zeros(len(chans), dtype=np.int64)
            volts = np.zeros(len(chans))
            self.boards.append((cfg, drv, slots, scale, offset, counts, volts, svc.board_slot(cfg.name)))
            svc.init_board(cfg, lambda d=drv: d.read_counts(0))

    def probe(self) -> None:
        """The run's transactions (one scan of each board into a scratch array)."""
        for _cfg, drv, _slots, _scale, _offset, counts, *_ in self.boards:
            try:
                drv.scan(counts.copy())
            except PfmaError:
                pass

    def calibrate(self, rack) -> None:
        """New engineering scales and offsets (in place: the arrays are the task's)."""
        for cfg, _drv, _slots, scale, offset, *_ in self.boards:
            chans = _by_channel(rack.board(cfg.name).channels)
            scale[:] = [c.scale for c in chans]
            offset[:] = [c.offset for c in chans]

    def volts_of(self, board: str) -> np.ndarray | None:
        """The volts array the scans of ``board`` fill (None for no such A/D board)."""
        return next((b[6] for b in self.boards if b[0].name == board), None)

    def start(self) -> None:
        """At the start of a frame the ADC runs in: start each scan-mode board's scan, so its
        128 us of conversions overlap the DAC and resolver work before :meth:`run` collects it
        (instead of a busy wait on EOC inside the task). A board whose start fails, or one
        that uses the per-channel sequence, does its whole scan in :meth:`run`."""
        started, now = self._started, self.svc.clock.now
        started.clear()
        for b in self.boards:
            drv = b[1]
            if drv.scan_mode:
                t = now()
                try:
                    drv.start_scan()
                except PfmaError:
                    continue  # run() tries the whole scan and reports its failure
                started[b[0].name] = t  # the inputs are sampled from here on

    def run(self, k: int = 0) -> None:
        svc = self.svc
        v = svc.values
        started = self._started
        for cfg, drv, slots, scale, offset, counts, volts, bslot in self.boards:
            t = started.pop(cfg.name, None)
            try:
                if t is not None:
                    counts[:] = drv.read_scan()
                else:
                    t = svc.clock.now()
                    drv.scan(counts)
            except PfmaError as err:
                svc.input_failed(cfg.name, "adc", err)
                v["adc_status"][slots] |= CHANNEL_BUS_ERROR
                continue
            drv.volts_from_counts(counts, out=volts)
            v["adc_counts"][slots] = counts
            v["adc_volts"][slots] = volts
            v["adc_value"][slots] = volts * scale + offset
            v["adc_status"][slots] = 0
            svc.input_ok(cfg.name, bslot)
            v["t_adc_s"][...] = t
            svc.sampled("adc", t)


class DacTask:
    """The DAC board: config, driver, slots; per channel (plain lists: 16 values are cheaper
    in Python than in numpy) the engineering scale and offset, the command-area role (rate
    command, current limit, gripper), the limit a command is refused beyond and the
    saturation volts; the all-zero and all-forced-safe rows written while safe."""

    name = "dac"

    def __init__(self, svc: TaskHost) -> None:
        self.svc = svc
        self.v = svc.values  # the input area's views, published by the service
        self.sampled = svc.sampled
        self.enabled = False  #: the outputs are connected (P3 on): since the first ARMED frame

    def wire(self) -> None:
        svc = self.svc
        dacs = svc.rack.boards_of("dac")
        if len(dacs) != 1:
            raise PfmaError(f"rack {svc.rack.name}: the service drives exactly one DAC board, "
                            f"found {len(dacs)}")
        cfg = dacs[0]
        self.cfg = cfg
        self.drv = svc.io.driver(cfg)
        n = len(cfg.channels)
        chans = _by_channel(cfg.channels)
        self.slots = svc.span("dac", chans)
        self.n = n
        self.scale_l = [c.scale for c in chans]  # volts = (engineering - offset) / scale
        self.offset_l = [c.offset for c in chans]
        self.zeros = [0.0] * n
        self.forced_safe = [DAC_FORCED_SAFE] * n
        # command-area order (layout.joint_names; the rack's current_limit channels in rack
        # order, as the layout's current_limit_names) -> DAC channel, by the rack's channel
        # roles (quantity rate_command / current_limit / gripper_command)
        self.rate_list = [svc.layout.joint_entry("dac", j, "rate_command").channel
                          for j in svc.layout.joint_names]
        self.limit_list = [c.channel for c in cfg.channels if not c.spare and c.quantity == "current_limit"]
        self.is_limit = [ch in self.limit_list for ch in range(n)]
        self.is_rate = [ch in self.rate_list for ch in range(n)]
        grip = [c.channel for c in chans if c.quantity == "gripper_command"]
        self.gripper_ch = grip[0] if grip else None
        if self.gripper_ch is not None:
            self.is_rate[self.gripper_ch] = True  # a motor command too: 0 V when stale
        self.set_limits(chans)
        self.board_slot = svc.board_slot(cfg.name)

    def set_limits(self, chans) -> None:
        """Per DAC channel: the engineering limit a command is refused beyond (``limit``
        in the rack file, default the DAC's full range), the saturation volts within it,
        and the names the refusal message uses."""
        r = self.drv.range_volts
        m = 1.0 + self.svc.rack.commands.limit_margin
        self.limit = []  # engineering limit per channel (rates: |x|, current limits: 0..x)
        self.refuse = []  # limit x (1 + margin)
        self.sat_v = []  # saturation volts: the DAC range or the limit, whichever is lower
        for c in chans:
            full = r * abs(c.scale)
            lim = c.limit if c.limit is not None else full
            self.limit.append(lim)
            self.refuse.append(lim * m)
            self.sat_v.append(min(r, lim / abs(c.scale)) if c.scale else 0.0)
        self.names = [c.signal for c in chans]
        self.units = [c.units for c in chans]

    def probe(self) -> None:
        """The run's transaction: all 16 channels written, with the codes they hold (0 V
        while the outputs are disconnected, as at start), and the charge pump's port with
        the level it holds (no edge)."""
        drv = self.drv
        try:
            drv.write_volts_all(list(drv.shadow_volts), clamp=True)
        except PfmaError:
            pass

    def calibrate(self, rack) -> None:
        chans = _by_channel(rack.board(self.cfg.name).channels)
        self.scale_l = [c.scale for c in chans]
        self.offset_l = [c.offset for c in chans]
        self.set_limits(chans)

    def volts(self, eng: list[float], stale: bool) -> tuple[list[float], list[int]]:
        """(volts, dac_status) per channel for engineering commands ``eng``: the rack's
        scale and offset, saturated at the channel's limit (DAC_CLIPPED); a current limit
        below 0 is 0 V (brakes set); while ``stale`` the motor commands are 0 V
        (DAC_FORCED_SAFE, and their ``eng`` entry set to 0)."""
        r = self.drv.range_volts
        scale_l, offset_l, sat_v, is_limit, is_rate = self.scale_l, self.offset_l, self.sat_v, \
            self.is_limit, self.is_rate
        volts, st_out = [], []
        for ch, e in enumerate(eng):
            k_ = scale_l[ch]
            if stale and is_rate[ch]:
                volts.append(0.0)
                st_out.append(DAC_FORCED_SAFE)
                eng[ch] = 0.0
                continue
            x = (e - offset_l[ch]) / k_ if k_ else 0.0
            st = 0
            sat = sat_v[ch] if sat_v[ch] > 0 else r
            if is_limit[ch] and x < 0.0:
                st, x = DAC_CLIPPED, 0.0  # a current limit within the margin below 0: brakes set
            elif x > sat or x < -sat:  # within the refusal margin: saturate, say so
                st, x = DAC_CLIPPED, (sat if x > sat else -sat)
            volts.append(x)
            st_out.append(st)
        return volts, st_out

    def write(self, volts: list[float], status: list[int], eng: list[float], t: float,
              armed: bool) -> Exception | None:
        """Write the volts (the driver converts to codes) and publish codes, volts, values,
        status, the outputs and brakes flags, the sample time ``t`` (taken before the write).
        Returns None when the write succeeded, else its error: nothing is published then
        (the service makes the board's failure known: ``IoService._dac_not_answering``)."""
        drv = self.drv
        try:
            drv.write_volts_all(volts, clamp=True)
        except PfmaError as err:
            return err
        v = self.v
        slots = self.slots
        v["dac_counts"][slots] = drv.shadow_counts
        v["dac_volts"][slots] = drv.shadow_volts
        v["dac_value"][slots] = eng
        v["dac_status"][slots] = status
        enabled = self.enabled
        v["outputs_enabled"][...] = enabled and armed
        v["brakes_released"][...] = enabled and \
            any(volts[ch] > BRAKE_RELEASE_V for ch in self.limit_list)
        v["t_dac_s"][...] = t
        self.sampled("dac", t)
        return None

    def enable(self) -> None:
        """Connect the outputs (P3 on); the shadow holds the zeros written while safe."""
        self.drv.enable_outputs()
        self.enabled = True

    def last_values_text(self) -> str:
        """What the DAC holds as far as the service knows: the codes of the last writes that
        reached it (the driver's shadow: a failed block write keeps a channel's old code),
        the non-zero channels named."""
        if not self.enabled:
            return "last written 0 V with the outputs disconnected (P3 off)"
        held = [(v, name) for v, name in zip(self.drv.shadow_volts.tolist(), self.names) if abs(v) >= 0.005]
        if not held:
            return "last written 0 V on every channel"
        return "last written " + ", ".join(f"{v:+.2f} V on {name}" for v, name in held)

    def publish_stopped(self) -> None:
        """After the outputs were disabled: the shadow (0 V) and no outputs, no brakes."""
        self.enabled = False
        v = self.v
        slots = self.slots
        v["dac_counts"][slots] = self.drv.shadow_counts
        v["dac_volts"][slots] = self.drv.shadow_volts
        v["dac_value"][slots] = 0.0
        v["outputs_enabled"][...] = 0
        v["brakes_released"][...] = 0


class FtTask:
    """The F/T sensor: its ``FtSensor`` (None without one), whether the line is decoded in
    the serial drain (``in_tick``: an MVME400 port), the latest record, the calibration
    (``calibration.files.FtCalibration`` or None), and the frames left in which a missed
    F/T slot is tried again (``retry``, counted down by the service's frame)."""

    name = "ft"
    drain_after = False

    def __init__(self, svc: TaskHost) -> None:
        self.svc = svc
        self.ft: FtSensor | CanFtSensor | None = None
        self.in_tick = False
        self.latest: Any = None  #: the newest decoded F/T record
        self.cal: FtCalibration | None = None
        self.retry = 0
        #: why the F/T URL given to :meth:`wire_url` could not be opened (None: opened, or none given)
        self.open_error: str | None = None
        self.can: CanFtSensor | None = None  #: the F/T when it is a CAN node (``self.ft`` too)
        self._can_errors = 0  # CAN link errors already seen
        self._can_quiet = False  # a CAN trouble message is out; no other until a record arrives

    def stop(self) -> None:
        """End the stream (the service is stopping; outputs are already safe). The stop
        dialogue reads with waits again: an MVME400 port polls its FIFO in its reads and
        waits on the board's clock (on a simulated clock that moves the model on), any port
        gets a read time-out, instead of the frames' non-blocking reads, which on the
        simulated rack never saw the prompt and spun on the wall clock for the whole reply
        time-out (0.5 s at every stop)."""
        ft = self.ft
        if ft is None:
            return
        port = getattr(ft, "port", None)
        if port is not None:
            if hasattr(port, "autopoll"):
                port.autopoll = True
            if getattr(port, "timeout", None) == 0:
                port.timeout = 0.05
        try:
            ft.stop_stream()
        except PfmaError:
            pass

    def start(self, port, baud: int, where: str) -> None:
        """Binary records with checksum, streamed (QS); then only non-blocking reads."""
        from drivers.serial_ft.ftsensor import FtSensor
        svc = self.svc
        ft = FtSensor(port, clock=svc.clock, baud=baud)
        err = None
        for attempt in range(1, FT_START_ATTEMPTS + 1):
            try:
                ft.set_mode("binary")
                ft.set_checksum(True)
                ft.start_stream(rate_hz=svc.schedule.rate_hz("ft"))
                port.timeout = 0  # from now on only non-blocking reads, between frames
                # an MVME400 port: the service's serial tick drains it, and decodes as soon as a record is
                # complete (its time stamp is then its arrival, and after lost characters
                # the link is synced again at the first whole record, not at the next F/T slot)
                self.in_tick = hasattr(port, "autopoll")
                if self.in_tick:
                    port.autopoll = False
                self.ft = ft
                if attempt > 1:
                    svc.post(Severity.WARNING, MessageCode.FT_RETRIED, f"F/T sensor on {where}: streaming after "
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
        svc.init_errors.append(str(err))
        svc.post(Severity.ERROR, MessageCode.FT_NOT_STREAMING, f"F/T sensor on {where}: not streaming: {err}")
        svc.values["link_status"][svc.layout.slot("link", "ft_sensor")] = LINK_FAULT

    def wire_url(self, url: str) -> None:
        """The F/T sensor on a URL instead of the MVME400: ``can://INTERFACE/CHANNEL``
        (python-can, :func:`drivers.serial_ft.can_ft.open_can_url`: the CAN node) or else a
        pyserial URL (USB-serial adapter, terminal server: the kernel's or the server's
        buffer holds the bytes between frames). A URL that cannot be opened is posted and
        kept in :attr:`open_error` (``pfma serve`` then refuses to run)."""
        from drivers.serial_ft.can_ft import is_can_url
        if is_can_url(url):
            self._wire_can(url)
            return
        import serial
        try:
            port = serial.serial_for_url(url, baudrate=19200, timeout=0.05)
        except (serial.SerialException, ValueError) as err:
            self._open_failed(url, str(err))
            return
        self.start(port, 19200, url)

    def _open_failed(self, url: str, why: str) -> None:
        svc = self.svc
        self.open_error = f"F/T {why}" if why.startswith(url) else f"F/T port {url}: {why}"
        svc.init_errors.append(self.open_error)
        svc.post(Severity.ERROR, MessageCode.FT_PORT_FAILED, self.open_error)
        svc.values["link_status"][svc.layout.slot("link", "ft_sensor")] = LINK_FAULT

    def _wire_can(self, url: str) -> None:
        """The F/T node on a CAN bus: request/response, so nothing to start; each F/T slot
        collects the answer to the previous slot's request and sends the next
        (``CanFtSensor.read_records``: never waits), decoded in the slot, not in the serial
        tick. The record's time is when the slot took it: one F/T period (12.5 ms) after
        the request, well inside FT_STALE_S."""
        from drivers.serial_ft.can_ft import open_can_url
        svc = self.svc
        try:
            ft = open_can_url(url, clock=svc.clock)
        except PfmaError as err:
            self._open_failed(url, str(err))
            return
        self.ft = ft
        self.in_tick = False
        self.can = ft
        svc.post(Severity.INFO, MessageCode.FT_CAN, f"F/T on CAN node {ft.node_id}")

    def _can_trouble(self, ft: CanFtSensor) -> None:
        """A CAN request unanswered, an answer that did not pair, a send or receive that
        failed: posted once per episode (until a record arrives again)."""
        self._can_errors = ft.errors
        if not self._can_quiet:
            self._can_quiet = True
            self.svc.post(Severity.WARNING, MessageCode.FT_CAN_TROUBLE, f"F/T CAN node {ft.node_id}: {ft.last_error}")

    def close(self) -> None:
        """Release what :meth:`wire_url` opened on a CAN bus (the serial ports are closed
        with their boards or by their owners)."""
        from drivers.serial_ft.can_ft import CanFtSensor
        if isinstance(self.ft, CanFtSensor):
            self.ft.close()

    def decode(self) -> None:
        """Decode what the line's buffer holds; keep the newest record (PfmaError passes)."""
        if self.ft is not None:
            recs = self.ft.read_records()
            if recs:
                self.latest = recs[-1]

    def run(self, k: int = 0) -> None:
        svc = self.svc
        svc.decode_serial()
        ft = self.ft
        if ft is None:
            return
        v = svc.values
        slot = svc.layout.slot("link", "ft_sensor")
        r = self.latest
        st = ft.stats()
        v["link_records"][slot] = st.records
        v["link_bad"][slot] = st.bad_records
        v["link_resyncs"][slot] = st.resyncs
        v["link_rate_hz"][slot] = st.rate_hz
        v["link_age_s"][slot] = -1.0 if st.age_s is None else st.age_s
        stale = st.age_s is None or st.age_s > FT_STALE_S
        v["link_status"][slot] = LINK_OPEN | (LINK_STALE if stale else LINK_SYNCED)
        can = self.can
        if can is not None and can.errors != self._can_errors:
            v["link_errors"][slot] = can.errors
            self._can_trouble(can)
        if r is not None and r.t_s != v["ft_t_s"][()]:
            self.retry = 0  # this F/T period has its record
            self._can_quiet = False
            v["ft_counts"][:] = r.counts
            v["ft_force_n"][:] = r.force_n
            v["ft_torque_nm"][:] = r.torque_nm
            if self.cal is not None:  # calibration: wrench = matrix @ (counts - bias)
                w = self.cal.wrench(r.counts)
                v["ft_force_n"][:] = w[:3]
                v["ft_torque_nm"][:] = w[3:]
            v["ft_status"][...] = r.status
            v["ft_t_s"][...] = r.t_s
            v["t_ft_s"][...] = r.t_s
            svc.sampled("ft", r.t_s)


class HandTask:
    """The hand controllers: the CRL on the MVME400 (its ``CrlHandController``, the latest
    state, the force-reflection half-rate toggle), the CAE on the A/D board (its
    ``CaeHandController``, the volts array of its A/D board and the indices of its nine
    channels in it, found by the rack's ``hand_controller`` quantity) and the USB HID
    SpaceMouse (its ``HidSpaceMouse``, wired by :meth:`wire_hid`; a thread re-opens it
    after an unplug, so the frame never waits on hidapi's enumerate or open)."""

    name = "hand"
    drain_after = False

    def __init__(self, svc: TaskHost, ft: FtTask) -> None:
        self.svc = svc
        self.ft_task = ft  # the CRL's line is decoded here when no F/T task decodes the serial lines
        self.crl: CrlHandController | None = None
        self.crl_latest: Any = None  #: the newest CRL state
        self.crl_tx = 0
        self.cae: CaeHandController | None = None
        self.cae_volts: np.ndarray | None = None
        self.cae_idx: np.ndarray | None = None
        self.hid: HidSpaceMouse | None = None
        self.hid_label = "HID hand controller"  #: how messages name it ("simulated ..." for a fake)
        self.hid_up = False  #: the HID was connected at the last run (messages on a change)
        self._hid_inline = True  # reconnect inside update() (no thread: simulated time)
        self._hid_stop = threading.Event()
        self._hid_thread: threading.Thread | None = None
        #: set by the reconnect thread each time it re-opens the device
        self.hid_reconnected = threading.Event()

    def wire_hid(self, sm: HidSpaceMouse, where: str, *, simulated: bool = False,
                 thread: bool = True) -> bool:
        """The USB HID hand controller in the ``hid`` slot and the ``hid_hand_controller``
        link: opened once here (not in a frame), then read without waiting in each hand
        slot (``update(connect=False)``). After an unplug the slot is invalid, faulted, the
        deadman released (a controller cannot take a stale command) and a message posted;
        ``thread`` re-opens the device from a thread every ``sm.retry_s`` seconds (False:
        ``update`` re-opens it inline: a fake on a simulated clock, where that costs
        nothing and stays deterministic).

        :param where: the device's name in messages (path, or "fake SpaceMouse")
        :param simulated: a fake: messages say "simulated"
        :returns: the device opened now (else the slot says why, and the thread keeps trying)
        """
        svc = self.svc
        self.hid = sm
        self.hid_label = "simulated HID hand controller" if simulated else "HID hand controller"
        self._hid_inline = not thread
        up = sm.connected or sm.connect()
        self.hid_up = up
        kind = "SIMULATED: a fake device, no hardware" if simulated else sm.product or "SpaceMouse"
        if up:
            svc.notes.append(f"{self.hid_label}: {where} ({kind})")
            svc.post(Severity.INFO, MessageCode.HID_OPEN, f"{self.hid_label}: {where}"[:56])
        else:
            svc.init_errors.append(f"{self.hid_label} {where}: {sm.last_error}")
            svc.post(Severity.ERROR, MessageCode.HID_NOT_OPEN, f"{self.hid_label}: not open: {sm.last_error}")
        if thread:
            self._hid_stop.clear()
            self._hid_thread = threading.Thread(target=self._hid_reconnect_loop, name="pfma-hid-reconnect",
                                                daemon=True)
            self._hid_thread.start()
        return up

    def _hid_reconnect_loop(self) -> None:
        """The reconnect thread: while the HID is unplugged, one enumerate/open attempt every
        ``retry_s`` seconds (hidapi's calls wait on udev and the kernel, not the frame)."""
        sm = self.hid
        while sm is not None and not self._hid_stop.wait(sm.retry_s):
            if not sm.connected and sm.connect():
                self.hid_reconnected.set()

    def close(self) -> None:
        """Stop the HID reconnect thread and close the device (idempotent)."""
        self._hid_stop.set()
        if self._hid_thread is not None:
            self._hid_thread.join(5.0)
            self._hid_thread = None
        if self.hid is not None:
            self.hid.close()

    def attach_crl(self, port) -> None:
        from drivers.crl.crl import CrlHandController
        port.autopoll = False  # the service's serial tick drains the FIFO; decoding reads the buffer
        self.crl = CrlHandController(port, self.svc.clock)
        self.crl_tx = 0

    def decode(self) -> None:
        if self.crl is not None:
            self.crl_latest = self.crl.update()

    def wire_cae(self, adc: AdcTask) -> None:
        from drivers.crl.cae import CaeHandController
        svc = self.svc
        try:
            self.cae = CaeHandController(rack=svc.rack, clock=svc.clock)
        except (PfmaError, KeyError) as err:
            svc.post(Severity.WARNING, MessageCode.CAE_UNAVAILABLE, f"CAE hand controller not available: {err}")
            return
        # where the CAE channels sit among the ADC board's scanned volts (the rack's
        # hand_controller channels, in channel order: up/down, forward/backward,
        # right/left, yaw, pitch, roll, discretes 1-3)
        chans = _by_channel(svc.rack.with_quantity("hand_controller"))
        if not chans:
            return
        self.cae_volts = adc.volts_of(chans[0].board)
        self.cae_idx = np.array([c.channel for c in chans], dtype=np.intp)

    def _put(self, name: str, s) -> None:
        svc = self.svc
        v = svc.values
        i = svc.layout.slot("hc", name)
        v["hc_axes"][i] = s.axes
        v["hc_deadman"][i] = s.deadman
        v["hc_valid"][i] = s.valid
        v["hc_fault"][i] = s.fault
        v["hc_buttons"][i] = s.buttons
        v["hc_t_s"][i] = s.t_s

    def run(self, k: int = 0) -> None:
        svc = self.svc
        if self.crl is not None and self.ft_task.ft is None:
            svc.decode_serial()
        if self.cae is not None and self.cae_volts is not None:
            self._put("cae", self.cae.from_volts(self.cae_volts[self.cae_idx].tolist(),
                                                 t_s=float(svc.values["t_adc_s"][()])))
        if self.crl is not None:
            self.send_force()
        if self.crl_latest is not None and self.crl is not None:
            self._put("crl", self.crl_latest)
            stats = self.crl.link_stats()
            slot = svc.layout.slot("link", "crl_hand_controller")
            v = svc.values
            v["link_records"][slot] = stats["frames_ok"]
            v["link_bad"][slot] = stats["frames_bad"]
            v["link_resyncs"][slot] = stats["resyncs"]
            v["link_status"][slot] = LINK_OPEN | (LINK_FAULT if stats["tripped"] else LINK_SYNCED)
            v["link_rate_hz"][slot] = stats["rate_hz"]
            v["link_age_s"][slot] = stats["age_s"]
            svc.sampled("crl", self.crl_latest.t_s)
        if self.hid is not None:
            self.run_hid()

    def run_hid(self) -> None:
        """Every pending report of the HID (non-blocking reads), into the ``hid`` slot; its
        link: records = reports, errors = disconnects, resyncs = re-opens, age = since the
        last report (a puck at rest reports nothing: a growing age is not staleness while
        the device is open), status open+synced, or fault+stale while unplugged."""
        svc = self.svc
        sm = self.hid
        if sm is None:
            return
        s = sm.update(connect=self._hid_inline)
        self._put("hid", s)
        v = svc.values
        slot = svc.layout.slot("link", "hid_hand_controller")
        now = s.t_s
        v["link_records"][slot] = sm.reports
        v["link_errors"][slot] = sm.disconnects
        v["link_resyncs"][slot] = max(0, sm.connects - 1)
        v["link_rate_hz"][slot] = sm.rate_hz(now)
        v["link_age_s"][slot] = now - sm.t_last_report_s
        up = sm.connected
        v["link_status"][slot] = LINK_OPEN | LINK_SYNCED if up else LINK_FAULT | LINK_STALE
        if up:
            svc.sampled("hid", now)
        if up != self.hid_up:
            self.hid_up = up
            if up:
                svc.post(Severity.INFO, MessageCode.HID_RECONNECTED, f"{self.hid_label} reconnected")
            else:
                svc.device_error("hid")
                svc.post(Severity.ERROR, MessageCode.HID_LOST, f"{self.hid_label} lost: slot invalid")

    def send_force(self) -> None:
        """Force reflection to the CRL at half the hand-controller rate (40 Hz; its
        placeholder protocol's watchdog is 60 ms): the command area's force while armed and
        enabled, zero and disabled otherwise. Queued: the bytes leave between frames."""
        self.crl_tx ^= 1
        if not self.crl_tx or self.crl is None:
            return
        svc = self.svc
        c = svc.command
        live = svc.armed() and bool(c["crl_reflect_enable"])
        f = tuple(float(x) for x in c["crl_reflect_force_n"]) if live else (0.0, 0.0, 0.0)
        t = tuple(float(x) for x in c["crl_reflect_torque_nm"]) if live else (0.0, 0.0, 0.0)
        try:
            self.crl.send_force(f, t, enable=live)
        except (PfmaError, ValueError) as err:
            if svc.device_error("crl") == 1:
                svc.post(Severity.ERROR, MessageCode.CRL_FORCE_FAILED, f"CRL force reflection: {err}")


class PioTask:
    """The parallel ports: the boards with user inputs (config, driver, slots per port),
    the board with the matrix switcher output, and the route last applied. The PIO
    channels carry no rack quantity: they are found by their signal names."""

    name = "pio"
    drain_after = False

    def __init__(self, svc: TaskHost) -> None:
        self.svc = svc
        self.inputs: list[tuple] = []
        self.out: tuple[Any, Any, dict] | None = None  #: (board, driver, slots) of the matrix switcher
        self.matrix_applied = -1

    def wire(self) -> None:
        svc = self.svc
        self.inputs = []
        self.out = None
        self.matrix_applied = -1
        for cfg in svc.rack.boards_of("pio"):
            drv = svc.io.driver(cfg)
            dirs = ["in"] * 4
            for c in cfg.channels:
                dirs[c.channel] = c.direction
            slots = {c.channel: svc.layout.slot("pio", c.signal) for c in cfg.channels}
            if svc.init_board(cfg, lambda d=drv, dd=dirs: d.configure(dd)):
                if any(c.signal == "matrix_switcher_route" for c in cfg.channels):
                    self.out = (cfg, drv, slots)
                if any(c.signal.startswith("user_if_box_inputs") for c in cfg.channels):
                    self.inputs.append((cfg, drv, slots, svc.board_slot(cfg.name)))

    def probe(self) -> None:
        """The run's transactions: the user inputs of each input board (the matrix route is
        written only when it changes: not every run)."""
        for _cfg, drv, _slots, _bslot in self.inputs:
            try:
                drv.read_user_inputs()
            except PfmaError:
                pass

    def run(self, k: int = 0) -> None:
        svc = self.svc
        v = svc.values
        t = svc.clock.now()
        for cfg, drv, slots, bslot in self.inputs:
            try:
                word = drv.read_user_inputs()
            except PfmaError as err:
                svc.input_failed(cfg.name, "pio", err)
                continue
            v["pio_user_inputs"][...] = word
            v["pio_port_bits"][slots[0]] = word & 0xFF
            v["pio_port_bits"][slots[1]] = word >> 8
            svc.input_ok(cfg.name, bslot)
            v["t_pio_s"][...] = t
            svc.sampled("pio", t)
        if self.out is not None:
            route = int(svc.command["matrix_route"])
            if route != self.matrix_applied:
                cfg, drv, slots = self.out
                try:
                    drv.write_matrix_route(route)
                    self.matrix_applied = route
                    if svc.faulted_boards:
                        svc.board_answered(cfg.name)
                    v["matrix_route"][...] = route
                    v["pio_port_bits"][slots[0]] = route & 0xFF
                    svc.post(Severity.INFO, MessageCode.MATRIX_ROUTE, f"matrix switcher route 0x{route:02X}")
                except (PfmaError, ValueError) as err:
                    svc.board_error(cfg.name, err)
                    self.matrix_applied = route  # do not retry every frame; posted once
                    svc.post(Severity.ERROR, MessageCode.MATRIX_ROUTE_FAILED, f"{cfg.name}: matrix route 0x{route:02X} failed: {err}")
