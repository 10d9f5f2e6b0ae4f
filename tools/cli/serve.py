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
import sys

from ioservice.schedule import Schedule
from pfma.log import add_argument as add_log_level
from pfma.log import for_process as process_logging
from tools.cli.fault import add_serve_fault_args, install_serve_faults
from tools.cli.args import add_sim_errors, float_in, positive_float, positive_int, shoulder_roll_degrees


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
    p.add_argument("--shoulder-roll", type=shoulder_roll_degrees, default=None, metavar="DEG",
                   help="the simulated rack (--rack fake) only: pin its arm's hand-indexed shoulder roll at "
                        "-90, -45, 0, 45 or 90 deg (default 0); the controller is told with its own "
                        "--shoulder-roll (docs/controller.md \"The shoulder-roll index\")")
    add_serve_fault_args(p)
    add_sim_errors(p)
    add_log_level(p)
    return p


def run(args) -> int:
    """Check the options (a usage mistake: one line, exit 2), then run the service process
    (tools/stacks/service.py) to its end."""
    # the gateway client's retries are not said: the service says which board failed, once
    with process_logging("pfma serve", args.log_level, hush=("pymodbus",)):
        return _serve(args)


def _serve(args) -> int:
    from tools.stacks.service import ServiceConfig, serve
    schedule = _schedule(args)
    why = _usage_mistake(args)
    if why:
        print(f"pfma serve: {why}", file=sys.stderr)
        return 2
    config = ServiceConfig(
        rack=args.rack, bus=args.bus, buffer=args.buffer, private_if_busy=args.private_if_busy,
        group=args.group, duration_s=args.duration, modbus=args.modbus, modbus_writes=args.modbus_writes,
        modbus_requests=args.modbus_requests, schedule=schedule, slow=args.schedule == "slow",
        ft=args.ft_port, hid=args.hid, watchdog_ms=args.watchdog_ms, max_input_age=args.max_input_age,
        live=args.live, quiet=args.quiet, demo=args.demo, realtime=args.realtime,
        calibration=getattr(args, "calibration", None), direction_state=_direction_state(args),
        shoulder_roll=args.shoulder_roll, sim_errors=args.sim_errors)

    def faults(svc, world) -> None:  # --fault, --scenario and the endpoint `pfma fault` reaches
        args.buffer = svc.buf.name  # a private buffer (--private-if-busy) has its own endpoint
        install_serve_faults(args, svc, world)
    return serve(config, before_run=faults)


def _schedule(args) -> Schedule:
    """``--schedule FILE.toml`` (its ``[schedule]`` table), or the ``--frame-rate`` one
    (``--schedule slow`` fits it to the bus at start)."""
    if args.schedule and args.schedule != "slow":
        import tomllib
        from pfma.errors import ConfigError
        try:
            with open(args.schedule, "rb") as f:
                return Schedule.from_config(tomllib.load(f).get("schedule", {}))
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise ConfigError(f"schedule file {args.schedule}: {err}") from err
    return Schedule() if args.frame_rate == 320.0 else Schedule.scaled(args.frame_rate)


def _usage_mistake(args) -> str:
    """What is wrong with the combination of options ("" when nothing)."""
    if (args.modbus_writes or args.modbus_requests) and not args.modbus:
        return (f"{'--modbus-requests' if args.modbus_requests else '--modbus-writes'} needs "
                f"--modbus HOST:PORT (the export it configures)")
    if args.rack != "fake" and args.bus is None:
        return (f"--rack {args.rack} needs --bus: the rack's register bus "
                f"(modbus://HOST:PORT, file:PATH), or --bus fake to run it on the simulated "
                f"rack's registers")
    if args.shoulder_roll is not None and not (args.rack == "fake" and args.bus in (None, "fake")):
        return ("--shoulder-roll pins the simulated arm (--rack fake); a real arm's shoulder roll is "
                "pinned by hand (tell the controller: pfma controller --shoulder-roll DEG)")
    if args.sim_errors and not (args.rack == "fake" and args.bus in (None, "fake")):
        return "--sim-errors gives the simulated rack (--rack fake) a real rack's imperfections; a real rack has its own"
    return ""


def _direction_state(args) -> str | None:
    """``--direction-state``, or ``<calibration>.direction.json`` beside ``--calibration``."""
    from ioservice.direction import default_path
    given = getattr(args, "direction_state", None)
    if given:
        return given
    p = default_path(getattr(args, "calibration", None))
    return str(p) if p is not None else None
