"""``pfma controller``'s arguments: the verb's parser, its option groups (motion, paths,
moves, the shoulder-roll index) and the checks argparse makes of them."""

from __future__ import annotations

import argparse

from pfma.log import add_argument as add_log_level_argument
from tools.cli.args import (
    add_sim_errors, camera_number, monitor_number, nonneg_float, nonneg_int, positive_float, positive_int, shoulder_roll_degrees,
    whole_number,
)
from tools.cli.controller.common import GRIPPER_VERBS, SYSTEM_ACTIONS


def add_parser(sub, description: str):
    """The ``controller`` verb's parser on ``sub`` (argparse subparsers)."""
    p = sub.add_parser("controller", help="run the IRSS-layered controller (live service or --sim)",
                       description=description)
    p.add_argument("action", nargs="?", choices=("halt", "step", "resume", "route", "move", "gripper",
                                                 *SYSTEM_ACTIONS), default=None,
                   help="requests to a RUNNING controller (its --wm): halt (outputs held in the "
                        "service's HALTED state, 0 V, brakes set), step [N] (exactly N minor frames, "
                        "their trace printed), resume (needs --rearm), route CAMERA MONITOR (the "
                        "console's CAMERA ROUTE: that camera on that monitor, 0 blanks it), power-up, "
                        "power-down, reset (the Global Commands POWER UP, POWER DOWN, ERROR RESET; "
                        "halted, they run frame by frame with the steps), move (--pose, --joints or --stop: a checked "
                        "move-to request), gripper open|close|stop [--force N] (waits for the move to end)")
    p.add_argument("frames", nargs="?", default=None, metavar="N|CAMERA|open|close|stop", action=_CountOrCamera,
                   help="step: minor frames to run (default 1); route: the camera, 1..3 or 0 = blank; "
                        "gripper: open, close or stop")
    p.add_argument("monitor", nargs="?", type=monitor_number, default=None, metavar="MONITOR",
                   help="route: the monitor, 1..2")
    p.add_argument("--rearm", action="store_true", help="resume: re-arm the outputs (required)")
    p.add_argument("--force", type=positive_float, default=None, metavar="N",
                   help="gripper: the grip force in N (its current limit at 40 N/A; 10..200 N on the nominal "
                        "jaw); alone (`gripper --force N`) it only sets the force")
    p.add_argument("--key", default=None,
                   help="requests to a running controller: world-model access key (default $PFMA_WM_KEY or "
                        "the default key)")
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name of the service (default pfma)")
    p.add_argument("--sim", action="store_true", help="simulate the whole system (fake rack + service) "
                                                     "in simulated time instead")
    p.add_argument("--wm", "--name", dest="wm", default=None, metavar="NAME",
                   help="world-model shared-memory name for `pfma wm` (default pfma_wm; 'none' = "
                        "private); --name is an alias, as in `pfma wm`. With --distribute: the base name "
                        "(each process's world model is NAME.PROCESS; default the file's [distributed] wm)")
    p.add_argument("--profile", default="layers", help="rate profile: layers (default) or overview")
    p.add_argument("--power-up", action="store_true", help="request POWER UP at start")
    p.add_argument("--duration", type=positive_float, default=None,
                   help="seconds to run (simulated with --sim: default 1; live: until Ctrl-C)")
    p.add_argument("--halt", action="store_true", help="start halted; single-step from the keyboard")
    p.add_argument("--step", type=positive_int, default=None, metavar="N",
                   help="run N minor frames one at a time, printing each frame's trace, then stop")
    p.add_argument("--trace", action="store_true", help="print the per-frame trace")
    p.add_argument("--changes", action="store_true", help="trace only frames in which a status changed")
    p.add_argument("--messages", type=nonneg_int, default=30, metavar="N",
                   help="messages shown at the end (30), after the ERROR episode's first cause")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="do not print System Up/Down's state changes, WARNINGs and ERRORs as they happen "
                        "(the summary at the end stays)")
    p.add_argument("--sim-fault", action="append", default=[], metavar="SPEC",
                   help="with --sim: inject this fault into the simulated rack (any spec of `pfma fault "
                        "list`, e.g. resolver-los:shoulder_pitch_angle, tach-reversed:shoulder_yaw; "
                        "repeatable; docs/faults.md) at --sim-fault-at")
    p.add_argument("--sim-fault-at", type=nonneg_float, default=0.0, metavar="S",
                   help="simulated seconds from the start at which --sim-fault is injected (default 0)")
    add_sim_errors(p)
    p.add_argument("--no-ft", action="store_true", help="a stale F/T link is not a fault")
    p.add_argument("--tables", action="store_true", help="print the decision tables and the schedule")
    p.add_argument("--clock", choices=("locked", "own"), default="locked",
                   help="the minor frames' clock: locked (default: a frame after each service frame) or own "
                        "(the controller's own frame clock at the profile's rate, e.g. --profile overview's "
                        "268 Hz, while the service keeps 160/80/320 Hz; docs/controller.md \"Two clocks\")")
    p.add_argument("--max-missed-run", type=_missed_run, default=None, metavar="FRAMES",
                   help="service frames the controller may miss in a row before it is a servo fault (code 12; "
                        "default 2, fitting the service's default age limit of 4 frames). For a host too slow for "
                        "that: raise it with `pfma serve --max-input-age` raised by as much, and its --watchdog-ms to "
                        "cover that age (the service still refuses every rate command older than its own limit)")
    p.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=None,
                   help="SCHED_FIFO priority 49 pinned to CPU 0 (pfma serve takes the last CPU): taken by default "
                        "where this user may, said in one line; --no-realtime opts out (PFMA_REALTIME=off turns "
                        "the default off)")
    g = p.add_argument_group("distributed controller (docs/controller.md, \"Distributing the layers\")")
    g.add_argument("--distribute", metavar="FILE", default=None,
                   help="a TOML assigning the seven layers to processes (examples/distributed.toml)")
    g.add_argument("--process", metavar="NAME", default=None,
                   help="with --distribute: which process this is (it runs only that process's layers; "
                        "the one with daq writes the Bit3 command area, the others read the inputs)")
    _add_motion_arguments(p)
    _add_path_arguments(p)
    _add_move_arguments(p)
    _add_roll_arguments(p)
    add_log_level_argument(p)
    return p


class _CountOrCamera(argparse.Action):
    """The second positional, checked as what its action takes: ``route``'s CAMERA
    (:func:`tools.cli.args.camera_number`), else ``step``'s whole number N (its range is
    checked with the request); a bad one is argparse's usage error naming it, exit 2."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        if values is None:
            setattr(namespace, self.dest, None)
            return
        if getattr(namespace, "action", None) == "gripper":
            if values not in GRIPPER_VERBS:
                raise argparse.ArgumentError(None, f"argument open|close|stop: gripper takes open, close or stop, "
                                                   f"not {values!r}")
            setattr(namespace, self.dest, values)
            return
        route = getattr(namespace, "action", None) == "route"
        try:
            value = camera_number(values) if route else whole_number(values)
        except argparse.ArgumentTypeError as err:
            raise argparse.ArgumentError(None, f"argument {'CAMERA' if route else 'N'}: {err}") from None
        setattr(namespace, self.dest, value)



# --- the shoulder-roll index (issue 30 item 2; docs/controller.md "The shoulder-roll index") ----
def _add_roll_arguments(p) -> None:
    g = p.add_argument_group("the shoulder-roll index (indexed by hand, no sensor)")
    g.add_argument("--shoulder-roll", type=shoulder_roll_degrees, default=None, metavar="DEG",
                   help="where the shoulder roll is pinned: -90, -45, 0, 45 or 90 (deg). Sets "
                        "joint.shoulder_roll_deg before anything powers up, and is the operator's "
                        "confirmation of it: a --power-up on a rack the service does not report as "
                        "simulated needs it. With --sim the simulated arm is pinned there too")



# --- motion: teleoperation, force control, time delay (Cartesian engine, issue 6) -------------
def _add_motion_arguments(p) -> None:
    g = p.add_argument_group("teleoperation, force control, time delay (Cartesian engine)")
    g.add_argument("--teleop", choices=("cae", "crl", "hid"), default=None,
                   help="teleoperate from this hand controller (cart.mode 1; deadman required)")
    g.add_argument("--hc-frame", choices=("world", "tool"), default="world",
                   help="hand-controller rates in the world (default) or the tool frame")
    g.add_argument("--vernier", action="store_true", help="vernier rates (0.03 m/s, 0.05 rad/s)")
    g.add_argument("--impedance", choices=("on", "off"), default=None,
                   help="impedance control on (zeroes the F/T sensor first) or off")
    g.add_argument("--delay", type=nonneg_float, default=None, metavar="S",
                   help="synthetic round-trip delay in seconds, split equally up/down (0..8)")
    g.add_argument("--jitter", type=nonneg_float, default=None, metavar="F",
                   help="synthetic delay jitter fraction per packet (e.g. 0.1; order preserved)")
    g.add_argument("--demo-stick", action="store_true",
                   help="--sim only: move the simulated CAE stick (deadman, +x 1 s, +z 1 s, release)")
    g.add_argument("--demo-wall", type=float, default=None, metavar="M",
                   help="--sim only: a stiff virtual wall M metres in front of the tool (+x, world)")



# --- paths: record and play back (Multi-Segment Path Planner, issue 6) -------------------------
def _add_path_arguments(p) -> None:
    g = p.add_argument_group("path record and playback (Multi-Segment Path Planner; files: pfma path)")
    x = g.add_mutually_exclusive_group()
    x.add_argument("--record", metavar="NAME", default=None,
                   help="record path NAME once powered up, until the end of the run (teach points with "
                        "--teach-every or `pfma wm set msp.teach`; continuous capture unless --no-capture)")
    x.add_argument("--play", metavar="NAME", default=None,
                   help="play path NAME back once powered up (cart.mode 2)")
    g.add_argument("--path-dir", default=None, metavar="DIR",
                   help="path directory (default $PFMA_PATH_DIR or ~/.local/share/pfma/paths)")
    g.add_argument("--teach-every", type=positive_float, default=None, metavar="S",
                   help="while recording, store a teach point every S seconds")
    g.add_argument("--no-capture", action="store_true", help="record teach points only")
    g.add_argument("--record-command", action="store_true",
                   help="record the Cartesian command instead of the measured tool pose (playback then "
                        "repeats the recorded motion, servo errors included)")
    g.add_argument("--speed", type=positive_float, default=None, metavar="F", help="playback speed factor (msp.speed_scale)")
    g.add_argument("--max-turn", type=_turn_degrees, default=None, metavar="DEG",
                   help="allow the playback (or `move`) to turn the tool up to DEG degrees from its starting "
                        "orientation (msp.max_turn_rad, default 30: more is refused before it starts)")



def _missed_run(text: str) -> int:
    from controller.frames import MINOR_FRAMES_PER_MAJOR
    v = whole_number(text)
    if not 0 <= v <= MINOR_FRAMES_PER_MAJOR:
        raise argparse.ArgumentTypeError(f"{text} must be 0..{MINOR_FRAMES_PER_MAJOR} (frames of one major frame)")
    return v


def _turn_degrees(text: str) -> float:
    """``--max-turn DEG``: the largest tool rotation, 0 < DEG <= 180 (argparse's usage error otherwise)."""
    try:
        deg = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of degrees") from None
    if not 0.0 < deg <= 180.0:
        raise argparse.ArgumentTypeError(f"{deg:g}: the largest tool rotation must be 0..180 degrees")
    return deg



# --- move-to requests (issue 30 item 5; docs/controller.md "Moves that mean what they say") ------
def _add_move_arguments(p) -> None:
    g = p.add_argument_group("move (`pfma controller move ... --wm NAME`: a checked move-to request to a running "
                             "controller)")
    x = g.add_mutually_exclusive_group()
    x.add_argument("--pose", metavar="X,Y,Z[,QW,QX,QY,QZ]", default=None,
                   help="move the tool point to X,Y,Z (m, world) in a straight line; without a quaternion the tool "
                        "keeps its orientation (sets cart.mode 2 TRAJECTORY if it is not)")
    x.add_argument("--joints", metavar="DEG,DEG,DEG,DEG,DEG,DEG", default=None,
                   help="move the joints to these angles (degrees, command order: shoulder pitch, shoulder yaw, "
                        "elbow pitch, wrist yaw, wrist pitch, wrist roll) in a straight line in joint space")
    x.add_argument("--stop", action="store_true", help="stop the running move or playback (decelerates to rest)")
    g.add_argument("--no-wait", action="store_true", help="return once the request is sent (default: wait for "
                                                           "its end and print how it ended)")
    g.add_argument("--timeout", type=positive_float, default=300.0, metavar="S",
                   help="seconds to wait for the move's end (default 300; the move goes on after it)")

