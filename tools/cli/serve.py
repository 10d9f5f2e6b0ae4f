"""``pfma serve``: run the data-acquisition service (the main job).

On the simulated rack (``--rack fake``, the default) the register-level fakes,
the arm model, the F/T sensor and the CRL hand controller run in this process in
real time; on hardware, ``--rack FILE.toml --bus URL`` names the rack and the bus.
The Bit3 buffer is POSIX shared memory ``/dev/shm/NAME``.

At start the service times one frame's bus work on its bus (the resolver, A/D, DAC and
parallel-port transactions); a schedule the bus cannot keep is refused with the figures,
unless ``--schedule slow`` lets it run the best slower schedule that fits, which it names.
Over a Modbus gateway (``--bus modbus://HOST:PORT``, e.g. ``pfma gateway``) the serial
lines are not opened: the F/T comes from ``--ft URL`` or is absent. A bus that stops
answering ends the run with exit status 1; the DAC then did not take its 0 V either, so the
outputs are NOT known safe and the message says so (they may hold their last values: the
hardware E-stop, or the rack's amplifier-enable charge pump, docs/safety.md, must stop the arm).

Devices beside the rack (docs/devices.md):
  --ft URL       the F/T sensor on a pyserial URL (/dev/ttyUSB0, socket://host:port) or
                 on CAN, can://INTERFACE/CHANNEL[?node=N&bitrate=BPS] with python-can's
                 interface names (can://socketcan/can0, can://virtual/ft); --ft-port is
                 the same option. An F/T URL that cannot be opened: exit 1.
  --hid SOURCE   the USB 6-axis (SpaceMouse, hidapi) in the hand-controller slot "hid":
                 auto (the first one hidapi lists; exit 1 when none), fake (a SIMULATED
                 device, said so at start and in the messages) or /dev/hidrawN.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import threading
import time

from bit3.layout import ServiceState, build_layout, default_layout
from ioservice.schedule import Schedule
from bit3.buffer import Bit3Buffer, Bit3Error
from ioservice.ticking import TickingClock
from pfma.clock import MonotonicClock
from pfma.rack import load_rack
from tools.cli.fault import add_serve_fault_args, install_serve_faults
from tools.cli.args import float_in, positive_float, positive_int


def add_parser(sub):
    p = sub.add_parser("serve", help="run the data-acquisition service",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rack", default="fake", help="fake (simulated rack, default) or a rack TOML")
    p.add_argument("--bus", default=None, help="register bus for a real rack (modbus://H:P, file:PATH)")
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--private-if-busy", action="store_true",
                   help="while a live service owns --buffer, run on a private buffer (pfma-sim-...), named in "
                        "one line, instead of refusing (make run)")
    p.add_argument("--group", default=None, metavar="GROUP",
                   help="make the buffer and its frame ring mode 0640 with this group, so its members "
                        "(operators' accounts) can read them (default: 0600, this user only; "
                        "docs/reliability.md, the pfma group model)")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds to run (default: until Ctrl-C)")
    p.add_argument("--modbus", default=None, metavar="HOST:PORT", help="export the buffer over Modbus TCP")
    p.add_argument("--modbus-writes", action="store_true",
                   help="with no controller: let Modbus clients set the camera route (claims the command area; "
                        "never arms or moves the arm: docs/modbus-map.md)")
    p.add_argument("--modbus-requests", default=None, metavar="WM",
                   help="let Modbus clients post HALT and CAMERA ROUTE requests to the controller of world "
                        "model WM, which answers them (never arms or moves the arm: docs/modbus-map.md)")
    p.add_argument("--frame-rate", type=float_in(1.0, 5000.0, "Hz"), default=320.0, help="minor-frame rate (320 default; 1000 fast)")
    p.add_argument("--schedule", default=None, metavar="FILE.toml|slow",
                   help="acquisition schedule: a [schedule] table (frame_rate_hz, tasks.NAME = {divider, "
                        "phase}); or slow: if the bus cannot keep the schedule, run the best slower one "
                        "it can (named at start) instead of refusing to start")
    p.add_argument("--ft", "--ft-port", dest="ft_port", action="append", default=None, metavar="URL",
                   help="F/T sensor on a pyserial URL (/dev/ttyUSB0, socket://host:port) or on CAN "
                        "(can://INTERFACE/CHANNEL[?node=N], python-can names: can://socketcan/can0) "
                        "instead of MVME400 port A")
    p.add_argument("--hid", default=None, metavar="auto|fake|/dev/hidrawN",
                   help="USB 6-axis hand controller (SpaceMouse) in the buffer's hid slot: the first "
                        "found, a simulated one, or that hidraw node")
    p.add_argument("--watchdog-ms", type=positive_float, default=15.0, help="command heartbeat time-out (15 ms)")
    p.add_argument("--max-input-age", type=positive_int, default=None, metavar="FRAMES",
                   help="drive rate channels only from commands computed from inputs at most FRAMES "
                        "minor frames old (default: the rack file's [commands] max_input_age_frames, 4); "
                        "must fit the watchdog")
    p.add_argument("--live", action="store_true", help="print a live channel view twice a second")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="do not print trips, refusals, stalls (every WARNING and ERROR) as they happen")
    p.add_argument("--demo", action="store_true",
                   help="also start the demo controller (a separate process) that arms and swings the arm")
    p.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=None,
                   help="SCHED_FIFO priority 50 pinned to the last CPU: taken by default where this user may "
                        "(root, CAP_SYS_NICE or an RLIMIT_RTPRIO), said in one line; --no-realtime opts out "
                        "(PFMA_REALTIME=off turns the default off)")
    p.add_argument("--calibration", default=None, metavar="FILE",
                   help="calibration file (pfma calibrate ...) applied at start; default: nominal scales")
    p.add_argument("--direction-state", default=None, metavar="FILE",
                   help="the scale signs the last direction check confirmed (docs/safety.md \"Files\"); when "
                        "they changed, arms are direction-check arms until each joint moved as commanded; "
                        "default: FILE.direction.json beside --calibration, none without it")
    add_serve_fault_args(p)
    return p


#: short labels of the command-area joints in the live view (layout.joint_names order)
JOINT_ABBREV = {"shoulder_pitch": "SP", "shoulder_yaw": "SY", "elbow_pitch": "EP",
                "wrist_yaw": "WY", "wrist_pitch": "WP", "wrist_roll": "WR"}
#: the live view's leading columns: time since start, frame, service state
_LIVE_LEAD = "{:>8} {:>7} {:<8}"


def _wrap_pi(a: float) -> float:
    """An angle (rad) wrapped to (-pi, pi]: the resolvers read 0..2 pi, so a joint near 0
    would jump between ~0 and ~2 pi."""
    from pfma.show import wrap_angle  # the one way an angle is shown
    return wrap_angle(a)


def _joint_label(name: str) -> str:
    return JOINT_ABBREV.get(name) or "".join(w[0] for w in name.split("_")).upper()[:3]


def _live_header(joints) -> list[str]:
    """The column names, printed once above the live view's two-line updates."""
    return ["live view: t = s since the service started; joint angles in deg, (-180, 180]",
            _LIVE_LEAD.format("t[s]", "frame", "state") + " "
            + " ".join(f"{_joint_label(j):>7}" for j in joints) + "  deg",
            "  F/T force Fx Fy Fz [N]; device rates [Hz]; frame work time p50 [us]"]


def _live_lines(t_since_start_s: float, frame: int, state: str, angles_rad, force_n,
                rates_hz, work_p50_us: float) -> list[str]:
    """One live-view update (two lines, each <= 80 columns); ``angles_rad`` in the
    command-area joint order of :func:`_live_header`."""
    q = " ".join(f"{math.degrees(_wrap_pi(a)):+7.1f}" for a in angles_rad)
    work = f"{work_p50_us:.0f} us" if math.isfinite(work_p50_us) else "--"
    r = "/".join(f"{x:.0f}" for x in rates_hz[:4])
    return [_LIVE_LEAD.format(f"{t_since_start_s:.2f}", frame, state) + " " + q,
            f"  F[N] {force_n[0]:+6.1f} {force_n[1]:+6.1f} {force_n[2]:+6.1f}  "
            f"rtd/adc/dac/ft {r} Hz  work p50 {work}"]


def _live_message(m, t_start_s: float) -> str:
    """A service or controller message, its time since start, its text whole (a long text
    takes several Bit3 queue entries, joined by the reader)."""
    return (f"  > {m.t_s - t_start_s:9.2f} {m.queue.removesuffix('_messages')} "
            f"{m.severity.name} src={m.source} code={m.code}: {m.text}")


#: message codes of the helper watch: a helper process ended or did not restart (ERROR),
#: a helper restarted (INFO); docs/reliability.md
HELPER_LOST_CODE, HELPER_BACK_CODE = 190, 191


def _watch_helpers(svc, clock, *helpers):
    """A :class:`pfma.process.HelperWatch` over the service's helper processes that run (the
    output guardian, the Modbus export), ticked between frames in the service's thread: one
    that ends while the service runs is said (stderr and the service's message queue) and
    started again. None when there is no helper."""
    running = [h for h in helpers if h is not None]
    if not running:
        return None
    from bit3.layout import Severity
    from pfma.process import HelperWatch

    def say(error: bool, text: str) -> None:
        try:
            print(f"pfma serve: {text}", file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass  # no terminal any more (this runs in the frame loop): the message queue has it
        svc.post(Severity.ERROR if error else Severity.INFO, HELPER_LOST_CODE if error else HELPER_BACK_CODE, text)
    watch = HelperWatch(say)
    for h in running:
        watch.add(h)
    clock.hooks.append(watch.tick)
    return watch


#: how often `pfma serve` looks for its own new messages to say (a thread beside the frame
#: loop, never in it): s
SAY_POLL_S = 0.1


def _say_line(m, t_start_s: float) -> str:
    """One service message as `pfma serve` says it when it happens."""
    text = m.text.replace("\n", " | ")
    return f"pfma serve: {m.t_s - t_start_s:9.2f} s  {m.severity.name:<7} {m.code}: {text}"


def _start_saying(buffer_name: str, stop: threading.Event, t_start_s: float) -> threading.Thread | None:
    """Say the service's trips, refusals, stalls (every WARNING and ERROR of its own message
    queue) as they happen: a thread reading the Bit3 queue every SAY_POLL_S, rate-limited
    by :class:`controller.messages.LivePrinter` (at most LIVE_PER_SECOND lines a second,
    then one "... K more" line). Nothing of this runs in the frame loop; the attach and the
    imports are done here, before the loop starts, not in the thread beside it."""
    from bit3.client import Client
    from bit3.layout import Severity
    from controller.messages import LivePrinter
    try:
        c = Client.attach(buffer_name)
    except Bit3Error as err:
        print(f"pfma serve: cannot say its messages: {err}", file=sys.stderr)
        return None
    say = LivePrinter(lambda line: print(line, flush=True), time.monotonic,
                      wanted=lambda m: m.queue == "service_messages" and m.severity >= Severity.WARNING,
                      fmt=lambda m: _say_line(m, t_start_s), always=lambda m: False)
    c.new_messages()  # the start-up messages: said by the start lines

    def run() -> None:
        try:
            while True:
                stopping = stop.wait(SAY_POLL_S)
                for m in c.new_messages():
                    say(m)
                if stopping:
                    say.drain()
                    return
                say.flush()
        except (OSError, ValueError):
            pass  # no terminal any more
        finally:
            c.close()
    t = threading.Thread(target=run, name="pfma-serve-say", daemon=True)
    t.start()
    return t


def first_trip_line(svc) -> str:
    """The service's first trip or refusal since the last arm, one line (at exit)."""
    ft = svc.guard.first_trip
    if ft is None:
        return "pfma serve: first trip since the last arm: none"
    code, reason, _t = ft
    return f"pfma serve: first trip since the last arm: {reason} (code {code})"


def _live_view(buffer_name: str, stop: threading.Event, rack) -> None:
    from bit3.client import Client
    try:
        c = Client.attach(buffer_name, rack=None if rack.source.endswith("rack_default.toml") else rack.source)
    except Bit3Error as err:
        print(f"live view: {err}", file=sys.stderr)
        return
    angles = {ch.joint: ch.name for ch in c.layout.channels if ch.kind == "rtd" and ch.quantity == "angle"}
    joints = [j for j in c.layout.joint_names if j in angles]
    t_start = None
    try:
        print("\n".join(_live_header(joints)), flush=True)
        while not stop.wait(0.5):
            s = c.read_inputs()
            st = c.read_stats()
            if s.t_s == 0.0 and s.frame == 0:
                continue  # no frame published yet
            if t_start is None:  # the service's start: its frame 0 (if the viewer came late)
                t_start = s.t_s - s.frame * (st.period_s if st.period_s > 0 else 1 / 320)
            lines = _live_lines(s.t_s - t_start, s.frame, ServiceState(s.service_state).name,
                                [s.value(angles[j]) for j in joints], s.ft_force_n,
                                st.device_rate_hz, st.work_p50_us)
            print("\n".join(lines), flush=True)
            for m in c.new_messages():
                print(_live_message(m, t_start), flush=True)
    finally:
        c.close()


def run(args) -> int:
    from ioservice.service import LIVE_TICK_S, IoService
    from ioservice.loop import realtime_start
    slow = args.schedule == "slow"
    if args.schedule and not slow:
        import tomllib
        from pfma.errors import ConfigError
        try:
            with open(args.schedule, "rb") as f:
                schedule = Schedule.from_config(tomllib.load(f).get("schedule", {}))
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise ConfigError(f"schedule file {args.schedule}: {err}") from err
    else:
        schedule = Schedule() if args.frame_rate == 320.0 else Schedule.scaled(args.frame_rate)
    if (args.modbus_writes or args.modbus_requests) and not args.modbus:
        print(f"pfma serve: {'--modbus-requests' if args.modbus_requests else '--modbus-writes'} needs "
              f"--modbus HOST:PORT (the export it configures)", file=sys.stderr)
        return 2
    if args.rack != "fake" and args.bus is None:
        print(f"pfma serve: --rack {args.rack} needs --bus: the rack's register bus "
              f"(modbus://HOST:PORT, file:PATH), or --bus fake to run it on the simulated "
              f"rack's registers", file=sys.stderr)
        return 2
    try:
        ft_url = _ft_url(args.ft_port)
        hid = _open_hid(args.hid)
    except _Refused as err:
        print(f"pfma serve: {err}", file=sys.stderr)
        return err.status
    rack = load_rack(args.rack)
    layout = default_layout() if args.rack in ("fake", "default") else build_layout(rack)
    base = MonotonicClock()
    clock = TickingClock(base, tick_s=LIVE_TICK_S)
    world = None
    if args.rack == "fake" and args.bus in (None, "fake"):
        from fakes.world import FakeWorld
        world = FakeWorld(rack, clock=base)
        bus = world.bus
        clock.hooks.append(world.tick)
    else:
        from drivers.bus import open_bus
        from pfma.errors import PfmaError
        try:
            bus = open_bus(args.bus)
        except (PfmaError, OSError) as err:
            print(f"pfma serve: cannot open the bus {args.bus}: {err}", file=sys.stderr)
            return 1
    for line in realtime_start("pfma serve", args.realtime, os.cpu_count() - 1 if os.cpu_count() else None, 50,
                               watchdog_ms=args.watchdog_ms):
        print(line, file=sys.stderr)
    private = False
    if args.private_if_busy:  # make run: the default name unless a live service has it (tools/runnames.py)
        from tools.runnames import claim
        names = claim(args.buffer, None)
        if names.private:
            args.buffer, private = names.buffer, True
            print(f"pfma serve: {names.note}", flush=True)
    _replace_stale(args.buffer)
    try:
        buf = Bit3Buffer.create(args.buffer, layout, group=args.group)
    except Bit3Error as err:  # an unknown group, or one this user is not in (nothing left behind)
        _close_bus(bus)
        if hid is not None:
            hid[0].close()
        print(f"pfma serve: {err}", file=sys.stderr)
        return 2
    try:
        svc = IoService(rack, bus, buf, clock, schedule=schedule, watchdog_s=args.watchdog_ms / 1e3,
                        max_input_age_frames=args.max_input_age,
                        calibration=getattr(args, "calibration", None), ft_port=ft_url,
                        bus_name=None if world is not None else args.bus,
                        direction_state=_direction_state(args))
    except BaseException:
        buf.close(unlink=True)  # a service that could not start leaves no buffer behind
        if hid is not None:
            hid[0].close()
        raise
    if svc.ft.open_error is not None:
        return _refuse(svc, buf, bus, "the F/T could not be opened", svc.ft.open_error)
    if hid is not None and not svc.hand.wire_hid(*hid[:2], simulated=hid[2]):
        return _refuse(svc, buf, bus, "the HID could not be opened", f"--hid {args.hid}: {hid[0].last_error}")
    failed = _failed_boards(svc, buf, layout)
    if failed and len(failed) == len(_initialised_boards(svc, layout)):
        first = _why_unreachable(bus, svc, layout) or failed[0]
        return _refuse(svc, buf, bus, "no board answered at start",
                       f"cannot reach the boards on {args.bus or 'the simulated rack'}: every "
                       f"board failed to initialise; first: {first}")
    for f in failed:
        print(f"pfma serve: {f}", file=sys.stderr)
    for note in svc.notes:
        print(f"pfma serve: {note}", file=sys.stderr)
    from ioservice.schedule import BusTooSlow
    try:
        slower = svc.fit_schedule(slow=slow)
    except BusTooSlow as err:
        if world is None:
            return _refuse(svc, buf, bus, "the bus cannot keep the schedule", str(err))
        # the simulated rack is no bus: its "transfer time" is this host's CPU running the
        # fakes, which a loaded host lacks for a while (seen at load 9 on 2 cores). Said, not
        # refused: frames that overrun are counted and named like any other
        slower = None
        print(f"pfma serve: warning: the simulated rack's register emulation is slow on this host "
              f"now (a loaded machine?); frames may overrun: {err}", file=sys.stderr, flush=True)
    if slower is not None:
        print(f"pfma serve: {slower}", flush=True)
    schedule = svc.schedule
    from bit3.ring import FrameRing
    try:
        svc.ring = FrameRing.create(args.buffer, layout.area("inputs").body_size, layout.hash)
    except Bit3Error as err:  # no room in /dev/shm (bit3/space.py): nothing left behind
        return _refuse(svc, buf, bus, "no room for the frame ring", str(err))
    if world is not None:
        # the arm model steps once per frame, 0.4-0.8 ms before it (TickingClock
        # pre-deadline hooks; 1 ms integration substeps inside), so the frame reads the arm
        # at most ~0.8 ms old; the serial FIFOs are drained every tick and right after the
        # step (so a long step and a late wake-up do not add up to an overrun)
        clock.hooks[:] = [svc.serial_tick]
        clock.pre_deadline_hooks[:] = [world.tick]
    for e in svc.init_errors:
        print(f"pfma serve: {e}", file=sys.stderr)
    svc.install_signal_handlers()
    export = guardian = watch = sayer = None
    stop = threading.Event()
    viewer = demo = None
    try:
        if world is None and args.bus.removeprefix("spy+") not in ("fake", "fake://"):
            # the outputs outlive this process on a bus another process reaches: a guardian
            # writes the DAC to 0 V if the service dies or stays stopped (ioservice/guardian.py)
            from ioservice.guardian import GuardianProcess
            guardian = GuardianProcess(args.bus, args.rack, args.watchdog_ms / 1e3 + schedule.period_s)
            why = guardian.start()
            if why:
                guardian = None
                print(f"pfma serve: warning: no output guardian ({why}): if this process is killed "
                      f"the DAC keeps its last outputs", file=sys.stderr, flush=True)
            else:
                print(f"pfma serve: output guardian pid {guardian.pid}: the DAC goes to 0 V if this "
                      f"service dies or stays stopped", flush=True)
            # what stops the arm when the DAC board itself does not answer (docs/safety.md
            # "Honest outputs"): said once at start, on a hardware bus
            if rack.amplifier_enable is not None:
                print(f"pfma serve: amplifier enable: charge pump {rack.amplifier_enable.describe()}, "
                      f"toggled every frame while ARMED and the DAC answers", flush=True)
            else:
                print(f"pfma serve: warning: rack {rack.name} has no amplifier-enable output "
                      f"([amplifier_enable]): if the DAC board stops answering, only the hardware "
                      f"E-stop stops the arm", file=sys.stderr, flush=True)
        if args.modbus:  # inside the try: an export that cannot start leaves no buffer or ring behind
            from tools.modbus_export import start_export_from_args
            export = start_export_from_args(args.buffer, args.modbus, args.modbus_writes,
                                            rack=None if args.rack == "fake" else args.rack,
                                            requests_wm=args.modbus_requests)
            mode = (f" (requests to the controller of {args.modbus_requests})" if args.modbus_requests
                    else " (camera-route writes)" if args.modbus_writes else " (read-only)")
            print(f"pfma serve: Modbus TCP export on {export.address}{mode}")
        on = "the simulated rack" if world else (
            f"{args.bus} (simulated registers)" if args.bus.removeprefix("spy+") in ("fake", "fake://")
            else args.bus)
        print(f"pfma serve: {rack.name} on {on}, buffer "
              f"/dev/shm/{args.buffer}, {schedule.frame_rate_hz:g} Hz frames; Ctrl-C stops "
              f"(outputs go to 0 V)", flush=True)
        watch = _watch_helpers(svc, clock, guardian, export)
        if args.live:  # the live view prints every message
            viewer = threading.Thread(target=_live_view, args=(args.buffer, stop, rack), daemon=True)
            viewer.start()
        elif not args.quiet:
            sayer = _start_saying(args.buffer, stop, clock.now())
        if args.demo:
            demo = subprocess.Popen([sys.executable, "-m", "sim.demo", "--buffer", args.buffer,
                                     "--duration", str(args.duration or 3600)])
        install_serve_faults(args, svc, world)
        svc.run(duration_s=args.duration)
    finally:
        stop.set()
        if demo is not None:
            demo.terminate()
            demo.wait(5)
        if viewer is not None:
            viewer.join(2)
        if sayer is not None:
            sayer.join(2)
        if watch is not None:
            clock.hooks.remove(watch.tick)  # no restarts while the helpers are stopped in order
        if export is not None:
            export.stop()
        if guardian is not None:
            guardian.stop()  # after the service's own safe outputs: it leaves without writing
        s = svc.publish_stats()
        loop = s["loop"]
        print(f"pfma serve: stopped after {loop['frames']} frames, {loop['dropped']} dropped, "
              f"{loop['overruns']} overruns; work p50 {loop['work_s']['p50'] * 1e6:.0f} us, "
              f"p99 {loop['work_s']['p99'] * 1e6:.0f} us; wake latency p50 "
              f"{loop['wake_latency_s']['p50'] * 1e6:.0f} us; device rates "
              + ", ".join(f"{k} {v['rate_hz']:.1f} Hz" for k, v in s["devices"].items() if v["samples"]))
        print(first_trip_line(svc), flush=True)
        buf.release()
        buf.close(unlink=private)  # a private name nobody will ask for again goes; the default stays for readers
        svc.ring.close()
        FrameRing.unlink(args.buffer)
        svc.hand.close()
        svc.ft.close()
        _close_bus(bus)
    if svc.bus_lost is not None:
        print(f"pfma serve: {svc.bus_lost}", file=sys.stderr)
        return 1
    return 0


class _Refused(Exception):
    """A device flag the service cannot run with: the message, and the exit status (2 for
    a usage mistake, 1 when the device is missing)."""

    def __init__(self, status: int, text: str) -> None:
        super().__init__(text)
        self.status = status


def _direction_state(args) -> str | None:
    """``--direction-state``, or ``<calibration>.direction.json`` beside ``--calibration``."""
    from ioservice.direction import default_path
    given = getattr(args, "direction_state", None)
    if given:
        return given
    p = default_path(getattr(args, "calibration", None))
    return str(p) if p is not None else None


def _ft_url(given: list[str] | None) -> str | None:
    """The one F/T URL of ``--ft``/``--ft-port`` (given twice, the same). A ``can://`` URL
    is checked here: its form (exit 2), python-can and the interface name (exit 1); the
    channel is opened by the service (``FtTask.wire_url``)."""
    urls = list(dict.fromkeys(given or ()))
    if len(urls) > 1:
        raise _Refused(2, f"--ft/--ft-port given twice with different URLs ({', '.join(urls)}); give one")
    if not urls:
        return None
    url = urls[0]
    if not url.strip():
        raise _Refused(2, "--ft: an empty URL (a serial port such as /dev/ttyUSB0, or can://INTERFACE/CHANNEL)")
    from drivers.serial_ft.can_ft import CanUrlError, is_can_url, parse_can_url
    if is_can_url(url):
        try:
            spec = parse_can_url(url)
        except CanUrlError as err:
            raise _Refused(2, f"--ft: {err}") from None
        try:
            import can.interfaces
        except ImportError as err:
            raise _Refused(1, f"--ft {url}: python-can is not installed ({err}); pip install python-can") from None
        from pfma.errors import did_you_mean
        known = can.interfaces.VALID_INTERFACES
        if spec.interface not in known:
            raise _Refused(1, f"--ft {url}: python-can has no interface {spec.interface!r}"
                              f"{did_you_mean(spec.interface, known)} (known: {', '.join(sorted(known))})")
    return url


def _open_hid(source: str | None):
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
        raise _Refused(2, f"--hid {source}: expected auto (the first SpaceMouse hidapi finds), "
                          f"fake (a simulated one) or a device path such as /dev/hidraw0")
    try:
        opener = hidmod.default_opener()
    except ImportError as err:
        raise _Refused(1, f"--hid {source}: hidapi is not installed ({err}); pip install hidapi, "
                          f"or run with --hid fake") from None
    if source != "auto":
        if not os.path.exists(source):
            raise _Refused(1, f"--hid {source}: no such device (is the SpaceMouse plugged in? "
                              f"ls /dev/hidraw*)")
        return hidmod.HidSpaceMouse(path=source, opener=opener), source, False
    sm = hidmod.HidSpaceMouse(opener=opener)
    try:
        found = sm.enumerate()
    except (OSError, ValueError) as err:
        raise _Refused(1, f"--hid auto: hidapi could not list the USB HID devices: {err}") from None
    if not found:
        vids = "/".join(f"0x{v:04X}" for v in sm.vendor_ids)
        raise _Refused(1, f"--hid auto: no SpaceMouse found (hidapi lists no device of vendor {vids}); "
                          f"plug one in (and allow /dev/hidraw* in a udev rule), give its "
                          f"/dev/hidrawN, or run with --hid fake")
    path = found[0].get("path")
    where = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
    return sm, where, False


def _refuse(svc, buf, bus, why: str, text: str) -> int:
    """A service built but unable to run: stopped (outputs safe), its buffer removed, what it
    opened closed; ``text`` on stderr; exit status 1."""
    try:
        svc.stop(why)
    finally:
        buf.close(unlink=True)
        svc.hand.close()
        svc.ft.close()
        _close_bus(bus)
    print(f"pfma serve: {text}", file=sys.stderr)
    return 1


def _close_bus(bus) -> None:
    close = getattr(bus, "close", None)
    if close is not None:
        close()


def _boards(layout) -> list:
    return [c for c in layout.channels if c.kind == "board"]


def _initialised_boards(svc, layout) -> list:
    """The boards the service tried to initialise (over a gateway the serial board is not)."""
    from bit3.layout import BOARD_FAULT, BOARD_INIT
    status = svc.inputs.record["board_status"]
    return [c for c in _boards(layout) if int(status[c.slot]) & (BOARD_FAULT | BOARD_INIT)]


def _failed_boards(svc, buf, layout) -> list[str]:
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


def _why_unreachable(bus, svc, layout) -> str | None:
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


def _replace_stale(name: str) -> None:
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
