"""The service process (``pfma serve``) assembled in one place: :class:`ServiceStack`.

In the order it is built (and torn down in the reverse order, on every exit path, by one
``contextlib.ExitStack``):

1. the device flags checked: the F/T URL (:func:`ft_url`), the USB 6-axis (:func:`open_hid`);
2. the rack and its layout, the clock (a :class:`ioservice.ticking.TickingClock` over the
   monotonic clock), the bus: the simulated rack (``fakes.world.FakeWorld``, its arm
   stepped by the clock's hooks) or a register bus (``drivers.bus.open_bus``);
3. the real-time set-up (SCHED_FIFO where permitted, said in one line);
4. the Bit3 buffer (a stale one of a dead service replaced; a live one refused);
5. the :class:`ioservice.service.IoService` on it, its devices wired and its start checks
   (the F/T, the HID, every board, the bus budget: a service that cannot run is stopped,
   its buffer removed, :class:`Refused`);
6. the frame ring beside the buffer;
7. then, while it serves: the output guardian (a hardware bus), the Modbus export, the
   helper watch (clock hook), the live view or the message sayer, the demo controller,
   the caller's ``before_run`` (``pfma serve``: the simulated faults and their endpoint),
   and the frame loop.

At the end: the demo stopped, the threads joined, the helpers stopped in order, the
figures printed (stdout), the buffer left stopped for its readers (a private one removed),
the ring removed, the devices and the bus closed.

Runtime messages go to ``logging`` (the process's root configures it once,
:func:`pfma.log.configure`); the operator's lines (the start line, the figures at the end)
go to ``out`` (stdout).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import subprocess
import sys
import threading
from dataclasses import dataclass
from typing import Any, Callable

from bit3.buffer import Bit3Buffer, Bit3Error
from bit3.layout import build_layout, default_layout
from tools.stacks import service_views as views

log = logging.getLogger(__name__)

#: message codes of the helper watch: a helper process ended or did not restart (ERROR),
#: a helper restarted (INFO); docs/reliability.md
HELPER_LOST_CODE, HELPER_BACK_CODE = 190, 191


class Refused(Exception):
    """The service cannot run: the message, and the exit status (2 for a usage mistake,
    1 when a device or the rack is missing). Raised once everything opened is closed."""

    def __init__(self, status: int, text: str) -> None:
        super().__init__(text)
        self.status = status


@dataclass
class ServiceConfig:
    """What ``pfma serve``'s options say (tools/cli/serve.py), checked there for usage."""

    rack: str = "fake"
    bus: str | None = None
    buffer: str = "pfma"
    private_if_busy: bool = False
    group: str | None = None
    duration_s: float | None = None
    modbus: str | None = None
    modbus_writes: bool = False
    modbus_requests: str | None = None
    #: the acquisition schedule (None: the default); ``slow``: run the best slower one that fits
    schedule: Any = None
    slow: bool = False
    ft: list[str] | None = None
    hid: str | None = None
    watchdog_ms: float = 15.0
    max_input_age: int | None = None
    live: bool = False
    quiet: bool = False
    demo: bool = False
    realtime: bool | None = None
    calibration: str | None = None
    direction_state: str | None = None
    shoulder_roll: int | None = None
    #: the simulated rack's imperfections (sim/errors.py), 0: none
    sim_errors: int = 0

    @property
    def simulated(self) -> bool:
        """The simulated rack (``--rack fake``, no bus): the fakes and the arm in this process."""
        return self.rack == "fake" and self.bus in (None, "fake")

    @property
    def fake_registers(self) -> bool:
        """A rack file on the simulated rack's registers (``--bus fake``)."""
        return self.bus is not None and self.bus.removeprefix("spy+") in ("fake", "fake://")


def _print(line: str) -> None:
    print(line, flush=True)


class ServiceStack:
    """The service process, built by :meth:`open`, run by :meth:`run`, torn down on leaving
    the ``with`` block (in the reverse order of building, whatever happened)::

        with ServiceStack(config) as stack:
            stack.open()          # raises Refused (everything closed again)
            status = stack.run(before_run=hook)

    :param out: where the operator's lines go (default: stdout, flushed)
    """

    def __init__(self, config: ServiceConfig, *, out: Callable[[str], None] = _print) -> None:
        self.config = config
        self.out = out
        self.rack: Any = None
        self.layout: Any = None
        self.clock: Any = None
        self.world: Any = None
        self.bus: Any = None
        self.buf: Bit3Buffer | None = None
        self.svc: Any = None
        self.private = False
        self.stop_event = threading.Event()
        self._hid: tuple | None = None
        self._ft_url: str | None = None
        self._serving = False
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> ServiceStack:
        return self

    def __exit__(self, *exc) -> bool:
        return bool(self._stack.__exit__(*exc))

    def close(self) -> None:
        """Tear down what was built (also done on leaving the ``with`` block)."""
        self._stack.close()

    # -- building -------------------------------------------------------------------

    def open(self) -> ServiceStack:
        """Build the service up to its first frame (steps 1-6 of the module docstring).

        :raises Refused: a device flag, the buffer's group, a device or the bus the service
            cannot run with (what was opened is closed when the stack is left)
        """
        from ioservice.loop import realtime_start
        cfg = self.config
        self._ft_url = ft_url(cfg.ft)
        self._hid = open_hid(cfg.hid)
        self._stack.callback(self._close_unwired_hid)
        self._open_rack()
        self._stack.callback(self._close_devices)  # before the bus they may talk over
        ncpu = os.cpu_count()
        cpu = ncpu - 1 if ncpu else None
        for i, line in enumerate(realtime_start("pfma serve", cfg.realtime, cpu, 50, watchdog_ms=cfg.watchdog_ms)):
            text = line.removeprefix("pfma serve: ")
            log.log(logging.WARNING if i or "not permitted" in text else logging.INFO, "%s", text)
        self._open_buffer()
        self._open_service()
        self._check_start()
        self._open_ring()
        for e in self.svc.init_errors:
            log.warning("%s", e)
        self.svc.install_signal_handlers()
        return self

    def _open_rack(self) -> None:
        """The rack, its layout, the clock and the bus (the simulated rack or a register bus)."""
        from ioservice.service import LIVE_TICK_S
        from ioservice.ticking import TickingClock
        from pfma.clock import MonotonicClock
        from pfma.rack import load_rack
        cfg = self.config
        self.rack = load_rack(cfg.rack)
        self.layout = default_layout() if cfg.rack in ("fake", "default") else build_layout(self.rack)
        base = MonotonicClock()
        self.clock = TickingClock(base, tick_s=LIVE_TICK_S)
        if cfg.simulated:
            from fakes.world import FakeWorld
            from sim.errors import seeded
            self.world = FakeWorld(self.rack, clock=base, shoulder_roll_rad=math.radians(cfg.shoulder_roll or 0),
                                   errors=seeded(cfg.sim_errors, self.rack))
            self.bus = self.world.bus
            self.clock.hooks.append(self.world.tick)
        else:
            from drivers.bus import open_bus
            from pfma.errors import PfmaError
            try:
                self.bus = open_bus(str(cfg.bus))
            except (PfmaError, OSError) as err:
                raise Refused(1, f"cannot open the bus {cfg.bus}: {err}") from None
        self._stack.callback(_close_bus, self.bus)

    def _open_buffer(self) -> None:
        """The Bit3 buffer: ``--private-if-busy`` names a private one while a live service has
        the name; a stale buffer of a dead service is replaced, a live one's refused."""
        cfg = self.config
        if cfg.private_if_busy:  # make run: the default name unless a live service has it (tools/runnames.py)
            from tools.runnames import claim
            names = claim(cfg.buffer, None)
            if names.private:
                cfg.buffer, self.private = names.buffer, True
                self.out(f"pfma serve: {names.note}")
        replace_stale(cfg.buffer)
        try:
            self.buf = Bit3Buffer.create(cfg.buffer, self.layout, group=cfg.group)
        except Bit3Error as err:  # an unknown group, or one this user is not in (nothing left behind)
            raise Refused(2, str(err)) from None
        self._stack.callback(self._close_buffer)

    def _open_service(self) -> None:
        from ioservice.service import IoService
        cfg = self.config
        assert self.buf is not None  # made by _open_buffer
        self.svc = IoService(self.rack, self.bus, self.buf, self.clock, schedule=cfg.schedule,
                             watchdog_s=cfg.watchdog_ms / 1e3, max_input_age_frames=cfg.max_input_age,
                             calibration=cfg.calibration, ft_port=self._ft_url,
                             bus_name=None if self.world is not None else cfg.bus,
                             direction_state=cfg.direction_state)

    def _check_start(self) -> None:
        """The F/T, the HID, the boards and the bus budget at start: a service that cannot
        run is refused; what it can run with is said."""
        svc, cfg = self.svc, self.config
        if svc.ft.open_error is not None:
            self._refuse("the F/T could not be opened", svc.ft.open_error)
        hid = self._hid
        if hid is not None and not svc.hand.wire_hid(*hid[:2], simulated=hid[2]):
            self._refuse("the HID could not be opened", f"--hid {cfg.hid}: {hid[0].last_error}")
        failed = failed_boards(svc, self.buf, self.layout)
        if failed and len(failed) == len(initialised_boards(svc, self.layout)):
            first = why_unreachable(self.bus, svc, self.layout) or failed[0]
            self._refuse("no board answered at start",
                         f"cannot reach the boards on {cfg.bus or 'the simulated rack'}: every "
                         f"board failed to initialise; first: {first}")
        for f in failed:
            log.warning("%s", f)
        for note in svc.notes:
            log.info("%s", note)
        self._fit_schedule()

    def _fit_schedule(self) -> None:
        from ioservice.schedule import BusTooSlow
        try:
            slower = self.svc.fit_schedule(slow=self.config.slow)
        except BusTooSlow as err:
            if self.world is None:
                self._refuse("the bus cannot keep the schedule", str(err))
            # the simulated rack is no bus: its "transfer time" is this host's CPU running the
            # fakes, which a loaded host lacks for a while (seen at load 9 on 2 cores). Said, not
            # refused: frames that overrun are counted and named like any other
            slower = None
            log.warning("warning: the simulated rack's register emulation is slow on this host "
                        "now (a loaded machine?); frames may overrun: %s", err)
        if slower is not None:
            self.out(f"pfma serve: {slower}")

    def _open_ring(self) -> None:
        from bit3.ring import FrameRing
        try:
            self.svc.ring = FrameRing.create(self.config.buffer, self.layout.area("inputs").body_size,
                                             self.layout.hash)
        except Bit3Error as err:  # no room in /dev/shm (bit3/space.py): nothing left behind
            self._refuse("no room for the frame ring", str(err))
        if self.world is not None:
            # the arm model steps once per frame, 0.4-0.8 ms before it (TickingClock
            # pre-deadline hooks; 1 ms integration substeps inside), so the frame reads the arm
            # at most ~0.8 ms old; the serial FIFOs are drained every tick and right after the
            # step (so a long step and a late wake-up do not add up to an overrun)
            self.clock.hooks[:] = [self.svc.serial_tick]
            self.clock.pre_deadline_hooks[:] = [self.world.tick]

    def _refuse(self, why: str, text: str) -> None:
        """A service built but unable to run: stopped (outputs safe); the stack then removes
        its buffer and closes what it opened."""
        self.svc.stop(why)
        raise Refused(1, text)

    # -- running --------------------------------------------------------------------

    def run(self, before_run: Callable[[Any, Any], None] | None = None) -> int:
        """Start the helpers beside the service and run its frame loop (``duration_s``, or
        until Ctrl-C / SIGTERM); returns the exit status: 1 when the bus stopped answering
        (``svc.bus_lost`` says why; :func:`serve` says it once the stack is torn down).

        :param before_run: called with (the service, the simulated world or None) just before
            the loop (``pfma serve``: its ``--fault``/``--scenario`` and fault endpoint)
        """
        cfg, svc = self.config, self.svc
        self._serving = True  # from here the buffer stays for its readers, the figures are said
        self._stack.callback(self._say_figures)
        with contextlib.ExitStack() as helpers:  # stopped before the figures are said
            self._start_helpers(helpers)
            self.out(f"pfma serve: {self.rack.name} on {self._where()}, buffer "
                     f"/dev/shm/{cfg.buffer}, {svc.schedule.frame_rate_hz:g} Hz frames; Ctrl-C stops "
                     f"(outputs go to 0 V)")
            self._start_watchers(helpers)
            helpers.callback(self.stop_event.set)
            if before_run is not None:
                before_run(svc, self.world)
            svc.run(duration_s=cfg.duration_s)
        return 0 if svc.bus_lost is None else 1

    def _start_helpers(self, helpers: contextlib.ExitStack) -> None:
        """The output guardian (a bus another process reaches) and the Modbus export, each
        stopped in the reverse order; the helper watch that restarts them."""
        guardian = self._start_guardian(helpers)
        export = self._start_export(helpers)
        watch = watch_helpers(self.svc, self.clock, guardian, export)
        if watch is not None:  # no restarts while the helpers are stopped in order
            helpers.callback(self.clock.hooks.remove, watch.tick)

    def _start_guardian(self, helpers: contextlib.ExitStack):
        cfg = self.config
        if self.world is not None or cfg.fake_registers:
            return None
        # the outputs outlive this process on a bus another process reaches: a guardian
        # writes the DAC to 0 V if the service dies or stays stopped (ioservice/guardian.py)
        from ioservice.guardian import GuardianProcess
        guardian = GuardianProcess(str(cfg.bus), cfg.rack, cfg.watchdog_ms / 1e3 + self.svc.schedule.period_s)
        why = guardian.start()
        if why:
            log.warning("warning: no output guardian (%s): if this process is killed "
                        "the DAC keeps its last outputs", why)
        else:
            helpers.callback(guardian.stop)  # after the service's own safe outputs: it leaves without writing
            self.out(f"pfma serve: output guardian pid {guardian.pid}: the DAC goes to 0 V if this "
                     f"service dies or stays stopped")
        self._say_amplifier_enable()
        return None if why else guardian

    def _say_amplifier_enable(self) -> None:
        """What stops the arm when the DAC board itself does not answer (docs/safety.md
        "Honest outputs"): said once at start, on a hardware bus."""
        if self.rack.amplifier_enable is not None:
            self.out(f"pfma serve: amplifier enable: charge pump {self.rack.amplifier_enable.describe()}, "
                     f"toggled every frame while ARMED and the DAC answers")
        else:
            log.warning("warning: rack %s has no amplifier-enable output ([amplifier_enable]): if "
                        "the DAC board stops answering, only the hardware E-stop stops the arm", self.rack.name)

    def _start_export(self, helpers: contextlib.ExitStack):
        cfg = self.config
        if not cfg.modbus:
            return None
        from tools.modbus_export import start_export_from_args
        export = start_export_from_args(cfg.buffer, cfg.modbus, cfg.modbus_writes,
                                        rack=None if cfg.rack == "fake" else cfg.rack,
                                        requests_wm=cfg.modbus_requests)
        helpers.callback(export.stop)
        mode = (f" (requests to the controller of {cfg.modbus_requests})" if cfg.modbus_requests
                else " (camera-route writes)" if cfg.modbus_writes else " (read-only)")
        self.out(f"pfma serve: Modbus TCP export on {export.address}{mode}")
        return export

    def _where(self) -> str:
        """What the service runs on, for its start line."""
        cfg = self.config
        if self.world is not None:
            roll = f" (its shoulder roll pinned at {cfg.shoulder_roll:+d} deg)" if cfg.shoulder_roll else ""
            return "the simulated rack" + roll
        return f"{cfg.bus} (simulated registers)" if cfg.fake_registers else str(cfg.bus)

    def _start_watchers(self, helpers: contextlib.ExitStack) -> None:
        """The live view (``live``) or the message sayer (unless ``quiet``), and the demo
        controller (``demo``), a separate process."""
        cfg, stop = self.config, self.stop_event
        thread = None
        if cfg.live:  # the live view prints every message
            thread = threading.Thread(target=views.live_view, args=(cfg.buffer, stop, self.rack), daemon=True)
            thread.start()
        elif not cfg.quiet:
            thread = views.start_saying(cfg.buffer, stop, self.clock.now())
        if thread is not None:
            helpers.callback(_join, thread, stop)
        if cfg.demo:
            demo = subprocess.Popen([sys.executable, "-m", "sim.demo", "--buffer", cfg.buffer,
                                     "--duration", str(cfg.duration_s or 3600)])
            helpers.callback(_end_process, demo)

    # -- tearing down ---------------------------------------------------------------

    def _say_figures(self) -> None:
        self.out(views.stopped_line(self.svc.publish_stats()))
        self.out(views.first_trip_line(self.svc))

    def _close_buffer(self) -> None:
        """The buffer: kept (stopped) for its readers once the service served, unless private;
        removed when it never did. The frame ring goes."""
        from bit3.ring import FrameRing
        buf, ring = self.buf, getattr(self.svc, "ring", None)
        assert buf is not None  # registered once the buffer is made
        if self._serving:
            buf.release()
        buf.close(unlink=self.private or not self._serving)
        if ring is not None:
            ring.close()
            FrameRing.unlink(self.config.buffer)

    def _close_devices(self) -> None:
        """The service's hand controllers and F/T."""
        if self.svc is not None:
            self.svc.hand.close()
            self.svc.ft.close()

    def _close_unwired_hid(self) -> None:
        """The USB 6-axis never handed to a service (it did not start)."""
        if self.svc is None and self._hid is not None:
            self._hid[0].close()


def serve(config: ServiceConfig, before_run: Callable[[Any, Any], None] | None = None) -> int:
    """Run the service process to its end; its exit status. A refusal is said (logging)
    after everything opened was closed."""
    try:
        with ServiceStack(config) as stack:
            stack.open()
            status = stack.run(before_run)
    except Refused as err:
        log.error("%s", err)
        return err.status
    if stack.svc.bus_lost is not None:  # the last line: after the figures, the outputs' state
        log.error("%s", stack.svc.bus_lost)
    return status


def _join(thread: threading.Thread, stop: threading.Event) -> None:
    stop.set()
    thread.join(2)


def _end_process(proc: subprocess.Popen) -> None:
    proc.terminate()
    proc.wait(5)


def _close_bus(bus) -> None:
    close = getattr(bus, "close", None)
    if close is not None:
        close()


def watch_helpers(svc, clock, *helpers):
    """A :class:`pfma.process.HelperWatch` over the service's helper processes that run (the
    output guardian, the Modbus export), ticked between frames in the service's thread: one
    that ends while the service runs is said (logging and the service's message queue) and
    started again. None when there is no helper."""
    running = [h for h in helpers if h is not None]
    if not running:
        return None
    from bit3.layout import Severity
    from pfma.process import HelperWatch

    def say(error: bool, text: str) -> None:
        # logging never raises here (no terminal any more: the message queue has it)
        log.log(logging.ERROR if error else logging.INFO, "%s", text)
        svc.post(Severity.ERROR if error else Severity.INFO, HELPER_LOST_CODE if error else HELPER_BACK_CODE, text)
    watch = HelperWatch(say)
    for h in running:
        watch.add(h)
    clock.hooks.append(watch.tick)
    return watch


# -- the device flags ---------------------------------------------------------------

def ft_url(given: list[str] | None) -> str | None:
    """The one F/T URL of ``--ft``/``--ft-port`` (given twice, the same). A ``can://`` URL
    is checked here: its form (exit 2), python-can and the interface name (exit 1); the
    channel is opened by the service (``FtTask.wire_url``)."""
    urls = list(dict.fromkeys(given or ()))
    if len(urls) > 1:
        raise Refused(2, f"--ft/--ft-port given twice with different URLs ({', '.join(urls)}); give one")
    if not urls:
        return None
    url = urls[0]
    if not url.strip():
        raise Refused(2, "--ft: an empty URL (a serial port such as /dev/ttyUSB0, or can://INTERFACE/CHANNEL)")
    from drivers.serial_ft.can_ft import CanUrlError, is_can_url, parse_can_url
    if is_can_url(url):
        try:
            spec = parse_can_url(url)
        except CanUrlError as err:
            raise Refused(2, f"--ft: {err}") from None
        try:
            import can.interfaces
        except ImportError as err:
            raise Refused(1, f"--ft {url}: python-can is not installed ({err}); pip install python-can") from None
        from pfma.errors import did_you_mean
        known = can.interfaces.VALID_INTERFACES
        if spec.interface not in known:
            raise Refused(1, f"--ft {url}: python-can has no interface {spec.interface!r}"
                             f"{did_you_mean(spec.interface, known)} (known: {', '.join(sorted(known))})")
    return url


def open_hid(source: str | None):
    """``--hid``: None, or (HidSpaceMouse, where, simulated), not yet opened (the service's
    hand task opens it). ``auto`` needs hidapi and a SpaceMouse that hidapi lists now;
    ``fake`` is ``fakes.hid.FakeHidDevice`` (its puck at rest, no button pressed: it
    never commands motion); a path must exist."""
    if source is None:
        return None
    from drivers.crl import hid as hidmod
    if source == "fake":
        from fakes.hid import FakeHidDevice
        return hidmod.HidSpaceMouse(opener=FakeHidDevice()), "fake SpaceMouse", True
    if source != "auto" and not source.startswith("/"):
        raise Refused(2, f"--hid {source}: expected auto (the first SpaceMouse hidapi finds), "
                         f"fake (a simulated one) or a device path such as /dev/hidraw0")
    try:
        opener = hidmod.default_opener()
    except ImportError as err:
        raise Refused(1, f"--hid {source}: hidapi is not installed ({err}); pip install hidapi, "
                         f"or run with --hid fake") from None
    if source != "auto":
        if not os.path.exists(source):
            raise Refused(1, f"--hid {source}: no such device (is the SpaceMouse plugged in? "
                             f"ls /dev/hidraw*)")
        return hidmod.HidSpaceMouse(path=source, opener=opener), source, False
    sm = hidmod.HidSpaceMouse(opener=opener)
    try:
        found = sm.enumerate()
    except (OSError, ValueError) as err:
        raise Refused(1, f"--hid auto: hidapi could not list the USB HID devices: {err}") from None
    if not found:
        vids = "/".join(f"0x{v:04X}" for v in sm.vendor_ids)
        raise Refused(1, f"--hid auto: no SpaceMouse found (hidapi lists no device of vendor {vids}); "
                         f"plug one in (and allow /dev/hidraw* in a udev rule), give its "
                         f"/dev/hidrawN, or run with --hid fake")
    path = found[0].get("path")
    where = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
    return sm, where, False


# -- the start checks ---------------------------------------------------------------

def _boards(layout) -> list:
    return [c for c in layout.channels if c.kind == "board"]


def initialised_boards(svc, layout) -> list:
    """The boards the service tried to initialise (over a gateway the serial board is not)."""
    from bit3.layout import BOARD_FAULT, BOARD_INIT
    status = svc.inputs.record["board_status"]
    return [c for c in _boards(layout) if int(status[c.slot]) & (BOARD_FAULT | BOARD_INIT)]


def failed_boards(svc, buf, layout) -> list[str]:
    """One line per board whose initialisation failed (its ``board_status`` FAULT bit),
    with the service's message about it when there is one."""
    from bit3.layout import BOARD_FAULT
    status = svc.inputs.record["board_status"]
    texts = [m.text for m in buf.queue("service_messages").read(0)]
    out = []
    for c in _boards(layout):
        if int(status[c.slot]) & BOARD_FAULT:
            said = next((t for t in texts if t.startswith(f"{c.name}:")), None)
            out.append(said or f"{c.name}: init failed")
    return out


def why_unreachable(bus, svc, layout) -> str | None:
    """The full text of the first board's failure (the message queue keeps 56 bytes): one
    read of the word it failed at, made only when no board answered at all."""
    from pfma.errors import PfmaError
    board = _boards(layout)[0]
    addr = int(svc.inputs.record["board_last_error_addr"][board.slot]) & 0xFFFE
    if not addr:
        return None
    try:
        bus.read16(addr)
    except PfmaError as err:
        return f"{board.name}: {err}"
    return None


def replace_stale(name: str) -> None:
    """Remove buffer ``name`` when its service is provably gone (its claim lock is free),
    whatever the buffer's layout; refuse, touching nothing, while that service lives.

    :raises Bit3Error: the buffer's service is alive (or the buffer cannot be inspected)
    """
    alive, who = Bit3Buffer.owner_alive(name)
    if alive:
        raise Bit3Error(f"Bit3 buffer /dev/shm/{name} is in use: {who}. This service leaves it "
                        f"alone; stop that service first, or run this one on another buffer "
                        f"with --buffer OTHER")
    Bit3Buffer.unlink(name)
