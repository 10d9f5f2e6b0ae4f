"""``pfma controller``: run the seven-layer controller against a running I/O service, or
the whole system in the simulator; halt, single-step, trace, messages.

Examples::

    pfma controller --sim --power-up --duration 0.5 --trace --changes
    pfma controller --sim --halt            # single-step: Enter = one minor frame, ? = help
    pfma controller --sim --power-up --step 40
    pfma controller --sim --shoulder-roll 45 --power-up      # the shoulder roll indexed at +45 deg
    pfma controller --buffer pfma --power-up --duration 10     # against ``pfma serve``
    pfma controller --tables                # the decision tables and the scheduling table
    pfma controller halt --wm pfma_wm       # a running controller: hold the outputs HALTED
    pfma controller step 5                  # ... run exactly 5 minor frames, print their trace
    pfma controller resume --rearm          # ... re-arm the outputs and go on
    pfma controller route 2 1               # ... camera 2 on monitor 1 (0 blanks it)
    pfma controller gripper close --force 60   # ... close the gripper, grip with 60 N
    pfma controller power-up                # ... the Global Commands: POWER UP (halted: it runs
    pfma controller power-down              #     with each step; resume --rearm arms), POWER DOWN,
    pfma controller reset                   #     ERROR RESET
    pfma controller move --pose 1.55,0,-0.33  # ... move the tool there, keeping its orientation
    pfma controller --distribute examples/distributed.toml --process rack       # one process of a
    pfma controller --distribute examples/distributed.toml --process planners --power-up   # distributed one
    pfma controller --sim --distribute examples/distributed.toml --power-up     # all of it, simulated

The trace has one line per minor frame: for every layer ``COMMAND>STATUS rN`` (the
command it receives, the status its decision table decided, the table row that
decided; ``*`` marks a change) and the Data Acquisition hardware-check bits.
"""

from __future__ import annotations

import argparse
import gc
import math
import signal
import sys
import time

from bit3 import futex
from tools.cli.args import (
    camera_number, monitor_number, nonneg_float, nonneg_int, positive_float, positive_int, shoulder_roll_degrees,
    whole_number,
)

HELP = """single-step commands (IRSS halt / manual interrupt):
  Enter or s      one minor frame          s N   N minor frames
  c               continue to the end      q     quit
  p / d / r       request POWER UP / POWER DOWN / ERROR RESET
  m               the last 100 messages    t     the layers' statuses
  ?               this help"""


#: ``pfma controller ACTION``: the Global Commands' requests (docs/console.md) to a running controller
SYSTEM_ACTIONS = ("power-up", "power-down", "reset")
#: how long ``pfma controller power-up|power-down|reset`` waits for the final answer (assumed:
#: the longest sequence, a power-up with its init, arm and brake-release time-outs of
#: controller/daq_layer.py and controller/servo.py, takes about 1.2 s; ten seconds is far
#: beyond it and still a prompt "no answer" for a controller that is not running frames)
SYSTEM_REQUEST_TIMEOUT_S = 10.0


def add_parser(sub):
    p = sub.add_parser("controller", help="run the IRSS-layered controller (live service or --sim)",
                       description=__doc__.split("\n\n")[0])
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
    p.add_argument("--no-ft", action="store_true", help="a stale F/T link is not a fault")
    p.add_argument("--tables", action="store_true", help="print the decision tables and the schedule")
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


def _setup_roll(d, args) -> int:
    """Set the index (``--shoulder-roll``) and, with ``--power-up``, show it and check it was
    confirmed; 0, or 2 after one line saying why the power-up is refused."""
    from controller.params import SHOULDER_ROLL_STEPS_TEXT, shoulder_roll_text
    wm = d.rt.wm
    if args.shoulder_roll is not None:
        d.rt.set_shoulder_roll(args.shoulder_roll)
        d.frame()  # applied at this frame's communications segment (still powered down)
    deg = float(wm.get("joint.shoulder_roll_deg"))
    if d.sim is not None and args.shoulder_roll is None:
        return 0  # the simulated arm and the controller both at 0: nothing to confirm or say
    if not args.power_up:
        if args.shoulder_roll is not None:
            print(f"shoulder-roll index {shoulder_roll_text(deg)} (joint.shoulder_roll_deg; the next power-up "
                  f"takes it)", flush=True)
        return 0
    if d.sim is not None:
        why = "the simulated arm is pinned there too"
    elif args.shoulder_roll is not None:
        why = f"confirmed by --shoulder-roll {args.shoulder_roll}"
    else:
        rack = _rack_kind(d.client)
        if rack != "simulated":
            print(f"pfma controller: the shoulder roll is indexed by hand and has no sensor: --power-up on "
                  f"{'an' if rack == 'unknown' else 'a'} {rack} rack needs --shoulder-roll DEG, the index the joint is pinned at ({SHOULDER_ROLL_STEPS_TEXT}); "
                  f"check the joint, then say it (the controller's is {shoulder_roll_text(deg)})", file=sys.stderr)
            return 2
        why = "not confirmed: the service's rack is simulated, its arm pinned where `pfma serve --shoulder-roll` put it"
    print(f"power-up with the shoulder-roll index {shoulder_roll_text(deg)} ({why})", flush=True)
    return 0


def _rack_kind(client) -> str:
    """"simulated", "real" or "unknown": what the service publishes of its rack (Bit3 header)."""
    try:
        return str(client.header().rack_kind)
    except Exception:  # noqa: BLE001 - what cannot be read is unknown (and needs the confirmation)
        return "unknown"


def _roll_summary(d) -> str:
    from controller.params import shoulder_roll_text
    v = d.rt.wm.get_task_inputs(("joint.shoulder_roll_deg", "joint.shoulder_roll_rad"))
    used = math.degrees(float(v["joint.shoulder_roll_rad"]))
    line = f"shoulder-roll index {shoulder_roll_text(float(v['joint.shoulder_roll_deg']))} (joint.shoulder_roll_deg)"
    if d.rt.wm.powered_up:
        line += f"; the kinematics use {shoulder_roll_text(round(used))}"
    if d.sim is not None:
        line += f"; the simulated arm is pinned at {shoulder_roll_text(round(math.degrees(d.sim.shoulder_roll_rad)))}"
    return line


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


def _motion_settings(args) -> dict:
    """World-model user variables the motion flags set (empty: none given)."""
    from controller.teleop import HC_SOURCES
    out: dict = {}
    if args.teleop is not None:
        out.update({"cart.mode": 1, "cart.hc_source": HC_SOURCES.index(args.teleop)})
    if args.teleop is not None or args.hc_frame != "world":
        out["cart.hc_frame"] = 1 if args.hc_frame == "tool" else 0
    if args.vernier:
        out["cart.vernier"] = True
    if args.impedance is not None:
        out["force.enable"] = args.impedance == "on"
    if args.delay is not None:
        out["delay.round_trip_s"] = args.delay
    if args.jitter is not None:
        out["delay.jitter"] = args.jitter
    return out


def _setup_motion(d, args) -> None:
    """Apply the motion flags (user writes, applied at the next frames) and the sim demos."""
    if (args.demo_stick or args.demo_wall is not None) and d.sim is None:
        raise SystemExit("pfma controller: --demo-stick and --demo-wall need --sim")
    settings = _motion_settings(args)
    if args.demo_stick and "cart.mode" not in settings:
        settings.update({"cart.mode": 1, "cart.hc_source": 0})
    wm = d.rt.wm
    for name, value in settings.items():
        wm.set_user(name, value, wm.access_key)
    if settings:
        d.frame()  # applied at this frame's communications segment
        print("motion settings: " + ", ".join(f"{k}={wm.spec(k).value_text(v) or v}" for k, v in settings.items()))
    if args.demo_wall is not None:
        from fakes.environment import Wall
        p, _ = d.sim.tool_pose()
        x = float(p[0]) + args.demo_wall
        d.sim.world.sim.environment.add(Wall(point_m=(x, 0.0, 0.0), normal=(-1.0, 0.0, 0.0)))
        print(f"virtual wall at x = {x:.3f} m (normal -x, 2e4 N/m)")
    if args.demo_stick:
        world, t0 = d.sim.world, [None]

        def stick(rec) -> None:
            from controller.decision import Status
            if d.rt.status("updown") != Status.START_UP_COMPLETE:
                return
            if t0[0] is None:
                t0[0] = rec.t_s
            t = rec.t_s - t0[0]
            if t < 1.0:  # CAE axis order: up/down, forward/backward, right/left, yaw, pitch, roll
                world.set_cae([0.0, 5.25, 0, 0, 0, 0], (True, False, False))
            elif t < 2.0:
                world.set_cae([5.25, 0.0, 0, 0, 0, 0], (True, False, False))
            else:
                world.set_cae([0.0] * 6, (False, False, False))
        d.rt.on_frame.append(stick)


def _motion_summary(d) -> str:
    v = d.rt.wm.get_task_inputs(("cart.pos_cmd_m", "cart.cmd_valid", "force.state", "force.wrench_n",
                                 "teleop.reflect_enabled"))
    p = v["cart.pos_cmd_m"]
    w = v["force.wrench_n"]
    line = (f"Cartesian command ({p[0]:+.4f}, {p[1]:+.4f}, {p[2]:+.4f}) m valid={bool(v['cart.cmd_valid'])}  "
            f"force {d.rt.wm.spec('force.state').value_text(v['force.state'])} "
            f"F ({w[0]:+.2f}, {w[1]:+.2f}, {w[2]:+.2f}) N  "
            f"reflection {'on' if v['teleop.reflect_enabled'] else 'off'}")
    if d.sim is not None:
        t, _ = d.sim.tool_pose()
        line += f"\ntool (true) ({t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}) m"
    return line


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


def _setup_paths(d, args) -> None:
    """Path store, path id, and a frame hook that starts recording/playback once powered up."""
    if args.record is None and args.play is None:
        return
    from controller.decision import Status
    from controller.paths import MspMode, PathStore
    store = PathStore(args.path_dir)
    msp = d.rt.by_key["msp"]
    msp.store = store
    wm, key = d.rt.wm, d.rt.wm.access_key
    if args.record is not None:
        path = store.load(args.record) if store.exists(args.record) else store.new(args.record,
                                                                                   note="pfma controller --record")
        settings = {"msp.path_id": path.id, "msp.capture": not args.no_capture,
                    "msp.record_source": 1 if args.record_command else 0}
        start = {"msp.mode": MspMode.RECORD}
        print(f"recording into path {path.name} (id {path.id}) in {store.dir}")
    else:
        path = store.load(args.play)
        settings = {"msp.path_id": path.id}
        if args.speed is not None:
            settings["msp.speed_scale"] = args.speed
        if args.max_turn is not None:
            settings["msp.max_turn_rad"] = _max_turn_rad(args.max_turn)
        start = {"cart.mode": 2, "msp.mode": MspMode.PLAY}
        print(f"playing path {path.name} (id {path.id}, {len(path.points)} points) from {store.dir}")
    for name, value in settings.items():
        wm.set_user(name, value, key)
    state = {"started": None, "teach_t": None}

    def hook(rec) -> None:
        if state["started"] is None:
            if d.rt.status("updown") == Status.START_UP_COMPLETE:
                for name, value in start.items():
                    wm.set_user(name, value, key)
                state["started"] = state["teach_t"] = rec.t_s
            return
        if args.record is not None and args.teach_every and rec.t_s - state["teach_t"] >= args.teach_every:
            state["teach_t"] = rec.t_s
            wm.set_user("msp.teach", int(wm.get("msp.teach")) + 1, key)
    d.rt.on_frame.append(hook)
    d.path_state = state


def _finish_paths(d, args) -> None:
    """End a recording (saved), report a playback."""
    if args.record is None and args.play is None:
        return
    from controller.paths import MspMode, MspResult
    wm = d.rt.wm
    if getattr(d, "path_state", {}).get("started") is None:
        print("path: never powered up (use --power-up); nothing recorded or played")
        return
    if args.record is not None:
        n = int(wm.get("msp.finished"))
        wm.set_user("msp.mode", MspMode.IDLE, wm.access_key)
        for _ in range(64):  # the planner runs at 20 Hz: a few of its periods
            d.frame()
            if int(wm.get("msp.finished")) > n:
                break
        d.rt.by_key["msp"].wait_saved()
        for _ in range(4):
            d.frame()
        saved = d.rt.by_key["msp"].last_saved
        res = MspResult.NAMES.get(int(wm.get("msp.result")), "?")
        if saved is not None:
            print(f"path {saved.name}: {len(saved.points)} points, {saved.length_m:.3f} m, revision {saved.revision} "
                  f"({res})")
        else:
            print(f"path {args.record}: not saved ({res})")
    else:
        v = wm.get_task_inputs(("msp.state", "msp.segment", "msp.segments", "msp.result", "msp.finished"))
        if int(v["msp.state"]) == MspMode.PLAY:
            print(f"path {args.play}: still playing, segment {int(v['msp.segment'])} of {int(v['msp.segments'])} "
                  f"(run longer: --duration)")
        else:
            print(f"path {args.play}: playback ended ({MspResult.NAMES.get(int(v['msp.result']), '?')}): "
                  f"{_text(wm.get('msp.result_text'))}")


def _text(words) -> str:
    return bytes(words).rstrip(b"\0").decode(errors="replace")


def _turn_degrees(text: str) -> float:
    """``--max-turn DEG``: the largest tool rotation, 0 < DEG <= 180 (argparse's usage error otherwise)."""
    try:
        deg = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of degrees") from None
    if not 0.0 < deg <= 180.0:
        raise argparse.ArgumentTypeError(f"{deg:g}: the largest tool rotation must be 0..180 degrees")
    return deg


def _max_turn_rad(deg: float) -> float:
    import math
    return math.radians(deg)


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


def _move_control(args) -> int:
    """``pfma controller move --pose ... | --joints ... | --stop --wm NAME``: one move-to
    request to the running controller through its world model; waits for its end (the
    controller's words: a refusal names the point and the reason; FAILED the worst tracking
    error and where)."""
    import math
    from tools.console.control import ControlError, ControllerLink
    err = sys.stderr
    if args.frames is not None or args.monitor is not None:
        print("pfma controller move: takes no N/CAMERA/MONITOR (use --pose, --joints or --stop)", file=err)
        return 2
    if args.pose is None and args.joints is None and not args.stop:
        print("pfma controller move: what to? --pose X,Y,Z[,QW,QX,QY,QZ], --joints DEG x 6 or --stop", file=err)
        return 2
    if args.wm in ("none", ""):
        print("pfma controller move: needs the running controller's world model (--wm NAME)", file=err)
        return 2
    try:
        if args.pose is not None:
            vals = _numbers(args.pose, (3, 7), "--pose")
        elif args.joints is not None:
            vals = [math.radians(x) for x in _numbers(args.joints, (6,), "--joints")]
        turn = _max_turn_rad(args.max_turn) if args.max_turn is not None else None
    except ValueError as e:
        print(f"pfma controller move: {e}", file=err)
        return 2
    try:
        link = ControllerLink.attach(args.wm, args.key)
        try:
            if args.stop:
                seq = link.stop_move()
            elif args.pose is not None:
                change = link.trajectory_mode()
                if change:
                    print(f"{change} (a pose move follows the Trajectory Planner)")
                seq = link.move_pose(vals[:3], vals[3:] if len(vals) == 7 else None, turn)
            else:
                seq = link.move_joints(vals, turn)
            print(f"move {seq} sent", flush=True)
            if args.no_wait:
                return 0
            a = link.wait_move(seq, args.timeout)
            print(a.line())
        finally:
            link.close()
    except ControlError as e:
        print(f"pfma controller move: {e}", file=err)
        return 1
    return 0 if a.ok else 1


def _numbers(text: str, counts: tuple[int, ...], what: str) -> list[float]:
    import math
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"{what} {text!r}: not a comma-separated list of numbers") from None
    if len(vals) not in counts or not all(math.isfinite(x) for x in vals):
        raise ValueError(f"{what} {text!r}: needs {' or '.join(map(str, counts))} finite numbers")
    return vals


def _print_tables(profile: str) -> int:
    from controller.decision import BOTTOM_TABLE, LAYER_TABLE, describe
    from controller.frames import FrameConfig
    print(describe(LAYER_TABLE))
    print()
    print(describe(BOTTOM_TABLE))
    print()
    print(FrameConfig.profile(profile).validate().describe())
    return 0


def _status_line(rt) -> str:
    from controller.decision import status_text
    return "  ".join(f"{l.short.strip()}={status_text(s)}" for l, s in zip(rt.layers, rt.statuses().values()))


class LivePacer:
    """Paces a live controller to the service's frames, by the service's hot-loop rules.

    Where the machine has futexes (``bit3.futex``: Linux on the usual architectures) the
    pacer sleeps on the header's frame word and the service's publish wakes it: one wake-up
    a frame, at the publish. Elsewhere it polls, as follows.
    Absolute deadlines: the service publishes frame k + 1 at about ``t_s(k) + period``
    (``inputs.t_s`` is the service's frame time on the same CLOCK_MONOTONIC host clock), so
    the pacer sleeps to :data:`LEAD_S` before that, then polls ``client.changed("inputs")``
    every :data:`POLL_S` until the frame is there (at most :data:`GIVE_UP_PERIODS` periods
    past it: the runtime's stale-service check then reports a service that stopped). A
    controller that woke late steps at once on the newest frame; the runtime counts the
    frames in between as missed and catches their tasks up. Nothing is allocated per frame
    here (floats only). After start-up :meth:`freeze_gc` moves everything allocated so far
    out of the collector's reach and turns automatic collection off; young generations are
    collected in the slack before a frame (:data:`GC_EVERY_FRAMES`), never a full one.
    """

    #: wake this long before the service's next frame time, then poll (assumed: more than
    #: the host's usual sleep overshoot, less than the service's publish delay)
    LEAD_S = 0.3e-3
    POLL_S = 50e-6
    #: futex waits: how long past the expected publish one wait may last before the pacer
    #: looks again (assumed: longer than the service's usual publish delay, ~0.3 ms here)
    FUTEX_LATE_S = 1e-3
    GIVE_UP_PERIODS = 4
    GC_EVERY_FRAMES = 64
    GC_MIN_SLACK_S = 1.5e-3

    def __init__(self, client, period_s: float) -> None:
        self.client = client
        self.period_s = period_s
        self.t_next = -1.0  # expected time of the next service frame (-1: not known yet)
        self.frames = 0
        self.gave_up = 0  #: waits that ended without a new frame
        self.gc_frozen = False

    def wait(self) -> None:
        c, mono = self.client, time.monotonic
        if c.changed("inputs"):
            return  # already published (we are late): step on the newest frame now
        now = mono()
        t_next = self.t_next if self.t_next > 0 else now
        if now > t_next + self.GIVE_UP_PERIODS * self.period_s:
            # nothing published for longer than a give-up (the service stopped or stalls):
            # wait a whole give-up from now. Without this the deadline stays in the past and
            # the controller spun through frames on the same inputs (~50 % of a core, seen
            # after its service stopped)
            t_next = now
        slack = t_next - self.LEAD_S - now
        if self.gc_frozen and slack > self.GC_MIN_SLACK_S and self.frames % self.GC_EVERY_FRAMES == 0:
            gc.collect(1)  # young generations only, in the slack before the frame
            now = mono()
            slack = t_next - self.LEAD_S - now
        give_up = t_next + self.GIVE_UP_PERIODS * self.period_s
        if futex.AVAILABLE:
            # one wake-up at the service's publish (bit3.futex): no lead sleep, no polling. The
            # first sleep lasts to FUTEX_LATE_S past the frame's expected time, later ones
            # FUTEX_LATE_S each: a service that never wakes (an older version) is still looked
            # at every millisecond
            buf = c.buffer
            until = t_next + self.FUTEX_LATE_S
            while True:
                seen = buf.frame_word()
                if c.changed("inputs"):
                    return
                now = mono()
                if now >= give_up:
                    self.gave_up += 1
                    return
                if until <= now:
                    until = now + self.FUTEX_LATE_S
                buf.wait_frame(seen, min(until, give_up) - now)
        if slack > 0:
            time.sleep(slack)
        while not c.changed("inputs"):
            if mono() > give_up:
                self.gave_up += 1
                break
            time.sleep(self.POLL_S)

    def stepped(self, t_frame_s: float) -> None:
        """The controller ran on the service frame of time ``t_frame_s``: the next is due a
        period later (absolute, so no drift accumulates)."""
        self.t_next = t_frame_s + self.period_s
        self.frames += 1

    def freeze_gc(self) -> None:
        gc.collect()
        gc.freeze()
        gc.disable()
        self.gc_frozen = True

    def release_gc(self) -> None:
        if self.gc_frozen:
            gc.enable()
            gc.unfreeze()
            self.gc_frozen = False


class _Driver:
    """Steps either a SystemSimulator or a runtime paced by a live service."""

    def __init__(self, args) -> None:
        from controller.frames import FrameConfig
        self.args = args
        frames = FrameConfig.profile(args.profile)
        wm_name = None if args.wm in ("none", "") else args.wm
        self.sim = None
        self.client = None
        if args.sim:
            from sim.system import SystemSimulator
            self.sim = SystemSimulator(frames=frames, wm_name=wm_name, require_ft=not args.no_ft,
                                       shoulder_roll_deg=getattr(args, "shoulder_roll", None) or 0)
            self.rt = self.sim.rt
            self.sim.step(10)  # the service's first frames (links open)
        else:
            from controller.runtime import ControllerRuntime
            from bit3.client import Client
            from pfma.clock import MonotonicClock
            self.client = Client.attach(args.buffer, writer="commands", owner="pfma-controller")
            self.rt = ControllerRuntime(self.client, frames=frames, wm_name=wm_name, clock=MonotonicClock(),
                                        require_ft=not args.no_ft)
            self.pacer = LivePacer(self.client, frames.period_s)
            _realtime(args)
            gc.collect()  # what start-up allocated is not collected inside the first frames
            gc.freeze()
        self.printed_header = False
        #: says System Up/Down's state changes, WARNINGs and ERRORs as they happen (after the
        #: frame, rate-limited; None with -q): controller.messages.LivePrinter
        self.say = None
        if not getattr(args, "quiet", False):
            from controller.messages import LivePrinter
            clock = self.sim.clock.now if self.sim is not None else time.monotonic  # sim: simulated seconds
            self.say = LivePrinter(lambda line: print(line, flush=True), clock)
            self.rt.messages.listeners.append(self.say)
        self.faults = None
        if self.sim is not None and getattr(args, "sim_fault", None):
            from sim.faults import FaultSet
            self.faults = FaultSet(self.sim.world)
            self._fault_frame = self.sim.service_frames + int(round(args.sim_fault_at / self.period_s))
        self.stop_signal = 0  #: the SIGTERM or SIGINT that asked for a stop (0: none)
        self.closing = False  #: in close(): the power-down's frames run whatever the signals
        self._silent_since: float | None = None  # the first give-up of the pacer in a row
        self._silent_frame = -1
        self._silent_said = False

    @property
    def period_s(self) -> float:
        return self.rt.frames.period_s

    def frame(self) -> None:
        if self.stop_signal and not self.closing:
            raise KeyboardInterrupt  # SIGTERM/SIGINT, acted on between frames (see stop_on_signals)
        if self.sim is not None:
            if self.faults is not None and self.sim.service_frames >= self._fault_frame:
                for spec in self.args.sim_fault:
                    f = self.faults.inject(spec)
                    print(f"pfma controller: simulated fault injected: {f.spec}", flush=True)
                self.faults = None
            self.sim.step(1)
            if self.say is not None:
                self.say.flush()
            return
        pacer = self.pacer
        gave_up = pacer.gave_up
        pacer.wait()  # locked to the service: its next frame, on absolute deadlines
        self.rt.tick()  # a minor frame, or the halted hold (pfma controller halt|step|resume)
        snap = self.rt.daq.snapshot
        pacer.stepped(float(snap.t_s))
        if self.say is not None:
            self.say.flush()  # after the frame's work: at most LIVE_PER_FLUSH lines
        if pacer.gave_up != gave_up or self._silent_since is not None:
            self._say_silence(pacer.gave_up != gave_up, int(snap.frame))
        if not self.pacer.gc_frozen and self.pacer.frames == self.FREEZE_AFTER_FRAMES:
            self.pacer.freeze_gc()  # start-up allocations done: no collector pauses in frames

    #: live frames run before the garbage collector is frozen (imports, first allocations)
    FREEZE_AFTER_FRAMES = 32
    #: the terminal is told the service went silent after this long without a frame, s
    #: (its layers report it at once, in the controller's message queue: this line is for
    #: whoever watches the terminal)
    SILENT_SAY_S = 0.5

    def _say_silence(self, gave_up: bool, frame: int) -> None:
        """One line when the service has published nothing for SILENT_SAY_S, one when its
        frames come again."""
        now = time.monotonic()
        if gave_up:
            if self._silent_since is None:
                self._silent_since, self._silent_frame, self._silent_said = now, frame, False
            elif not self._silent_said and now - self._silent_since >= self.SILENT_SAY_S:
                self._silent_said = True
                print(f"pfma controller: no frame from the service for over {self.SILENT_SAY_S:g} s "
                      f"(last: frame {frame}; stopped or stalled?): the layers report it and the commands "
                      f"are 0; waiting for frames", file=sys.stderr, flush=True)
        elif frame != self._silent_frame:
            if self._silent_said:
                print(f"pfma controller: frames from the service again (frame {frame})", file=sys.stderr, flush=True)
            self._silent_since = None

    def show(self, rec) -> None:
        if not self.args.trace and self.args.step is None and not self.args.halt:
            return
        if self.args.changes and not any(l.changed for l in rec.layers):
            return
        if not self.printed_header:
            print(self.rt.header())
            self.printed_header = True
        print(self.rt.format_frame(rec), flush=True)

    def stop_on_signals(self, between_frames: bool = True) -> dict:
        """SIGTERM and SIGINT stop the controller as Ctrl-C always did (the orderly power-down
        of :meth:`close`), acted on between two frames, never inside one; a second signal
        stops at once. Also where the shell started it with SIGINT ignored (a background job)
        and under a process manager's SIGTERM (before, SIGTERM ended it with no power-down and
        left its world model behind). ``between_frames`` False (the keyboard loops, which
        wait in ``input()``): the signal interrupts at once, as Ctrl-C does there. Returns the
        old handlers."""
        def on_signal(signum, _frame) -> None:
            if self.stop_signal or not between_frames:
                raise KeyboardInterrupt
            self.stop_signal = signum
        return {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}

    def close(self) -> None:
        from controller.decision import Status
        self.closing = True
        rt = self.rt
        if rt.halted:  # outputs already held safe: let the service go SAFE (no re-arm, no power down)
            rt.release_halt()
            print("pfma controller: was halted; outputs left safe (0 V, brakes set)", file=sys.stderr)
        elif self.sim is None and rt.status("updown") not in (Status.SHUT_DOWN, Status.ERROR):
            from controller.layers import Request
            try:  # leave the arm safe: power down in order before letting go of the buffer
                rt.request(Request.POWER_DOWN)
                t_end = time.monotonic() + 2.0
                while time.monotonic() < t_end and not rt.all_status(Status.SHUT_DOWN):
                    self.frame()
            except Exception as err:  # noqa: BLE001
                print(f"pfma controller: power down on exit: {err}", file=sys.stderr)
        if self.sim is not None:
            self.sim.close()
        else:
            self.pacer.release_gc()
            rt.close()
            self.client.close()


def _interactive(d: _Driver, budget: int) -> None:
    print(HELP)
    run = 0
    while run < budget:
        try:
            line = input(f"[frame {d.rt.frame}] > ").strip()
        except EOFError:
            return
        cmd, _, arg = line.partition(" ")
        if cmd in ("", "s"):
            n = int(arg) if arg.strip().isdigit() else 1
            for _ in range(min(n, budget - run)):
                d.frame()
                run += 1
        elif cmd == "c":
            while run < budget:
                d.frame()
                run += 1
        elif cmd == "q":
            return
        elif not _shared_command(d, cmd, "the next frame"):
            print(HELP)


def _shared_command(d: _Driver, cmd: str, applied: str) -> bool:
    """The single-step commands both keyboard loops take alike (p/d/r requests, m, t);
    False for any other command."""
    from controller.layers import Request
    if cmd in ("p", "d", "r"):
        kind = {"p": Request.POWER_UP, "d": Request.POWER_DOWN, "r": Request.ERROR_RESET}[cmd]
        if cmd == "p":
            from controller.params import shoulder_roll_text
            print(f"shoulder-roll index {shoulder_roll_text(float(d.rt.wm.get('joint.shoulder_roll_deg')))} "
                  f"(no sensor: joint.shoulder_roll_deg, as set)")
        print(f"request {d.rt.request(kind)}: {Request.NAMES[kind]} (applied at {applied})")
    elif cmd == "m":
        print(d.rt.messages.format())
    elif cmd == "t":
        print(_status_line(d.rt))
    else:
        return False
    return True


def _interactive_live(d: _Driver, budget: int) -> None:
    """``--halt`` on a live service: the controller halts at its first frame (the service
    holds HALTED: 0 V, brakes set, no watchdog trip) and goes on ticking with the service
    while a thread reads the keyboard; each command is acted on between service frames
    through the same requests as ``pfma controller halt|step|resume`` (``c`` resumes with a
    re-arm)."""
    import queue
    import threading
    from controller.layers import Request
    lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()

    def read_keyboard() -> None:
        while True:
            try:
                lines.put(input())
            except (EOFError, OSError):
                lines.put(None)
                return
    threading.Thread(target=read_keyboard, name="pfma-controller-keyboard", daemon=True).start()
    print(HELP)
    d.rt.request(Request.HALT)
    prompt = True
    for _ in range(budget):
        d.frame()  # halted: the hold writes the halted command; a STEP request runs its frames
        if prompt and d.rt.halted and not d.rt.steps_left:
            print(f"[frame {d.rt.frame}] > ", end="", flush=True)
            prompt = False
        try:
            line = lines.get_nowait()
        except queue.Empty:
            continue
        if line is None:
            return
        prompt = True
        cmd, _, arg = line.strip().partition(" ")
        if cmd in ("", "s"):
            n = int(arg) if arg.strip().isdigit() else 1
            print(f"request {d.rt.request(Request.STEP, n)}: SINGLE STEP {n}")
        elif cmd == "c":
            print(f"request {d.rt.request(Request.RESUME, 1)}: RESUME with re-arm (runs on)")
            prompt = False
        elif cmd == "q":
            return
        elif not _shared_command(d, cmd, "the next step"):
            print(HELP)


def _frame_control(args) -> int:
    """``pfma controller halt|step [N]|resume --rearm|route CAMERA MONITOR``: one request to
    the running controller through its world model; prints the answer (and a step's trace)."""
    from controller.runtime import MAX_STEP_FRAMES
    from tools.console.control import ControlError, ControllerLink, Request
    if args.action == "route":
        if args.frames is None or args.monitor is None:
            print("pfma controller route: needs CAMERA MONITOR (e.g. `route 2 1`: camera 2 on monitor 1; "
                  "camera 0 blanks the monitor)", file=sys.stderr)
            return 2
    elif args.monitor is not None:
        print(f"pfma controller {args.action}: takes no MONITOR (only route CAMERA MONITOR does)", file=sys.stderr)
        return 2
    if args.frames is not None and args.action not in ("step", "route"):
        print(f"pfma controller {args.action}: takes no frame count (only step N does)", file=sys.stderr)
        return 2
    if getattr(args, "shoulder_roll", None) is not None:
        print(f"pfma controller {args.action}: takes no --shoulder-roll (a running controller's index: `pfma wm "
              f"set joint.shoulder_roll_deg DEG` while it is powered down)", file=sys.stderr)
        return 2
    if args.rearm and args.action != "resume":
        print(f"pfma controller {args.action}: --rearm belongs to resume", file=sys.stderr)
        return 2
    n = 1 if args.frames is None else args.frames
    if args.action == "step" and not 1 <= n <= MAX_STEP_FRAMES:
        print(f"pfma controller step: N must be 1..{MAX_STEP_FRAMES} (got {n}); longer is a resume",
              file=sys.stderr)
        return 2
    if args.wm in ("none", ""):
        print(f"pfma controller {args.action}: needs the running controller's world model (--wm NAME)",
              file=sys.stderr)
        return 2
    kind = {"halt": Request.HALT, "step": Request.STEP, "resume": Request.RESUME, "route": Request.ROUTE}[args.action]
    if args.action == "route":
        from controller.routes import route_request_arg
        arg = route_request_arg(args.monitor, args.frames)  # monitor * 16 + camera (docs/cameras.md)
    else:
        arg = n if args.action == "step" else int(args.rearm)
    try:
        link = ControllerLink.attach(args.wm, args.key)
        try:
            seq = link.submit(kind, arg)
            # a step waits its frames (at most 1 kHz) on top of a second for the answer
            a = link.wait(seq, timeout_s=2.0 + (n / 300.0 if args.action == "step" else 0.0))
            print(a.line())
            if args.action == "step" and a.ok:
                print(link.step_trace())
        finally:
            link.close()
    except ControlError as err:
        print(f"pfma controller {args.action}: {err}", file=sys.stderr)
        return 1
    return 0 if a.ok else 1


#: the words of ``pfma controller gripper`` (pfma.gripper.ACTIONS; the force alone is --force)
GRIPPER_VERBS = ("open", "close", "stop")


def _gripper_control(args) -> int:
    """``pfma controller gripper open|close|stop [--force N]`` (or ``gripper --force N``): one
    gripper request to the running controller's Servo Control through its world model; prints
    each answer and waits for the move to end (controller/gripper.py)."""
    from pfma.arm import GRIPPER
    from pfma.gripper import ACTIONS, MOVE_TIMEOUT_S, check_force
    from tools.console.control import ControlError, ControllerLink
    if args.monitor is not None or args.rearm or args.pose is not None or args.joints is not None or args.stop \
            or args.no_wait:
        print("pfma controller gripper: takes open|close|stop and --force N only", file=sys.stderr)
        return 2
    if args.frames is None and args.force is None:
        print("pfma controller gripper: needs open, close or stop (and/or --force N)", file=sys.stderr)
        return 2
    if args.force is not None:
        why = check_force(args.force, GRIPPER.force_max_n)
        if why:
            print(f"pfma controller gripper: --force: {why}", file=sys.stderr)
            return 2
    if args.wm in ("none", ""):
        print("pfma controller gripper: needs the running controller's world model (--wm NAME)", file=sys.stderr)
        return 2
    kind = ACTIONS[args.frames or "force"]
    try:
        link = ControllerLink.attach(args.wm, args.key)
        try:
            seq = link.submit_gripper(kind, args.force or 0.0)
            # a move ends on a stall, or fails after MOVE_TIMEOUT_S; a second for the answer on top
            a = link.wait_gripper(seq, timeout_s=MOVE_TIMEOUT_S + 2.0, on_answer=lambda x: print(x.line(), flush=True))
        finally:
            link.close()
    except ControlError as err:
        print(f"pfma controller gripper: {err}", file=sys.stderr)
        return 1
    return 0 if a.ok else 1


# --- the Global Commands from the shell: pfma controller power-up|power-down|reset ------------
def _system_request(args) -> int:
    """``pfma controller power-up|power-down|reset``: the console's Global Commands (POWER
    UP, POWER DOWN, ERROR RESET) as one request to the running controller through its world
    model, as ``halt``, ``step`` and ``resume`` do; prints the answer. System Up/Down queues
    it: running, the final answer comes when the sequence ends (at most
    SYSTEM_REQUEST_TIMEOUT_S); halted, the request runs frame by frame with the steps
    (``pfma controller step``) and arming waits for ``resume --rearm``, so the command
    returns once the request is queued or in progress and says so."""
    from tools.console.control import ControlError, ControllerLink, Request, Response
    what = args.action
    if args.frames is not None or args.monitor is not None:
        print(f"pfma controller {what}: takes no frame count, camera or monitor", file=sys.stderr)
        return 2
    if args.rearm:
        print(f"pfma controller {what}: --rearm belongs to resume", file=sys.stderr)
        return 2
    if args.wm in ("none", ""):
        print(f"pfma controller {what}: needs the running controller's world model (--wm NAME)", file=sys.stderr)
        return 2
    kind = {"power-up": Request.POWER_UP, "power-down": Request.POWER_DOWN, "reset": Request.ERROR_RESET}[what]
    if args.shoulder_roll is not None and kind != Request.POWER_UP:
        print(f"pfma controller {what}: takes no --shoulder-roll (power-up's confirmation of the index)",
              file=sys.stderr)
        return 2
    try:
        link = ControllerLink.attach(args.wm, args.key)
        try:
            if kind == Request.POWER_UP and not _shell_roll_confirmed(link, args.shoulder_roll):
                return 2
            seq = link.submit(kind)
            a = link.wait(seq, timeout_s=SYSTEM_REQUEST_TIMEOUT_S, halted_ok=True)
            print(a.line())
            waiting = a.code in (Response.QUEUED, Response.IN_PROGRESS)
            if waiting:
                arming = " and `pfma controller resume --rearm` arms the outputs" if kind == Request.POWER_UP else ""
                print(f"the controller is halted: `pfma controller step [N]` runs the {Request.NAMES[kind]} frame by "
                      f"frame{arming}; the outputs stay safe (0 V, brakes set) until then")
        finally:
            link.close()
    except ControlError as err:
        print(f"pfma controller {what}: {err}", file=sys.stderr)
        return 1
    return 0 if a.ok or waiting else 1


def _shell_roll_confirmed(link, given: int | None) -> bool:
    """``pfma controller power-up``: show the shoulder-roll index the power-up will take, as
    the console's question does (indexed by hand, no sensor); ``--shoulder-roll DEG`` is the
    operator's confirmation and must be the controller's index. False after one line on
    stderr when it is not."""
    from controller.params import shoulder_roll_text
    if "joint.shoulder_roll_deg" not in link.wm.names():
        return True  # a controller without the index (older world model): nothing to show
    deg = float(link.wm.get("joint.shoulder_roll_deg"))
    t = shoulder_roll_text(deg)
    if given is not None and float(given) != deg:
        print(f"pfma controller power-up: --shoulder-roll {given} but the controller's index is {t} "
              f"(joint.shoulder_roll_deg): check the joint's index pin, then set the index with `pfma wm set "
              f"joint.shoulder_roll_deg {given}` (powered down) or say {deg:g}; nothing sent", file=sys.stderr)
        return False
    how = (f"confirmed by --shoulder-roll {given}" if given is not None else
           "check the joint's index pin; --shoulder-roll DEG says it")
    print(f"POWER UP with the shoulder-roll index {t} (joint.shoulder_roll_deg; indexed by hand, no sensor: "
          f"{how})", flush=True)
    if "servo.brake_test" in link.wm.names() and int(link.wm.get("servo.brake_test")):
        print("the power-up tests every brake: each joint moves a little out and back (about a degree) "
              "before START UP COMPLETE (servo.brake_test); keep clear", flush=True)
    return True


def run(args) -> int:
    if args.distribute is not None or args.process is not None:
        return _run_distributed(args)
    if args.wm is None:
        args.wm = "pfma_wm"
    if args.action == "gripper":
        return _gripper_control(args)
    if args.force is not None:
        print("pfma controller: --force belongs to `pfma controller gripper`", file=sys.stderr)
        return 2
    if args.action in SYSTEM_ACTIONS:
        return _system_request(args)
    if args.action == "move":
        return _move_control(args)
    if args.pose is not None or args.joints is not None or args.stop or args.no_wait:
        print("pfma controller: --pose, --joints, --stop and --no-wait belong to `pfma controller move`",
              file=sys.stderr)
        return 2
    if args.action is not None:
        return _frame_control(args)
    if args.frames is not None or args.monitor is not None:
        print("pfma controller: a frame count belongs to `pfma controller step N`, a camera and a monitor to "
              "`pfma controller route CAMERA MONITOR`", file=sys.stderr)
        return 2
    if args.tables:
        return _print_tables(args.profile)
    from controller.layers import Request
    if args.sim_fault:
        if not args.sim:
            print("pfma controller: --sim-fault needs --sim (a running service takes `pfma fault inject`)",
                  file=sys.stderr)
            return 2
        from pfma.errors import ConfigError
        from sim.faults import parse_fault
        for spec in args.sim_fault:  # a bad spec is a usage mistake: exit 2 before anything is built
            try:
                parse_fault(spec)
            except ConfigError as err:
                print(f"pfma controller: --sim-fault {err}", file=sys.stderr)
                return 2
    try:
        d = _Driver(args)
    except FileNotFoundError as err:
        print(f"pfma controller: no service buffer {args.buffer!r} ({err}); start `pfma serve` or use --sim",
              file=sys.stderr)
        return 1
    d.rt.on_frame.append(d.show)
    old_handlers = d.stop_on_signals(between_frames=not args.halt)
    try:
        if _setup_roll(d, args):
            return 2
        _setup_motion(d, args)
        _setup_paths(d, args)
        if args.power_up:
            d.rt.request(Request.POWER_UP)
        if args.duration is not None:
            budget = int(round(args.duration / d.period_s))
        elif args.sim:
            budget = int(round(1.0 / d.period_s))
        else:
            budget = sys.maxsize
        if args.step is not None:
            budget = min(budget, args.step)
        if args.halt and not args.sim:
            _interactive_live(d, budget)
        elif args.halt:
            _interactive(d, budget)
        else:
            for _ in range(budget):
                d.frame()
        _finish_paths(d, args)
        if _motion_settings(args) or args.demo_stick or args.demo_wall is not None:
            print(_motion_summary(d))
        if args.shoulder_roll is not None or (d.sim is None and args.power_up):
            print(_roll_summary(d))
        _summary(d, args)
    except KeyboardInterrupt:
        print()
        if d.stop_signal:
            print(f"pfma controller: {signal.Signals(d.stop_signal).name}: stopping (powering down in order)",
                  file=sys.stderr, flush=True)
        _summary(d, args)  # Ctrl-C and SIGTERM too: what happened, before the power-down
    finally:
        try:
            d.close()
        finally:
            for sig, h in old_handlers.items():
                signal.signal(sig, h)
    return 0


def first_cause_line(rt) -> str:
    """The current ERROR episode's first cause in one line ("none" without an episode)."""
    fc = rt.first_cause
    if fc is None:
        return "first cause: none (no ERROR episode)"
    return f"first cause of the ERROR: {fc.format()}"


def _summary(d, args) -> None:
    """At exit (--duration ended, Ctrl-C, SIGTERM): what is still to be said, the layers'
    statuses, the ERROR episode's first cause (kept however many messages followed it) and
    the last messages."""
    if d.say is not None:
        d.say.drain()
    print(_status_line(d.rt))
    print(first_cause_line(d.rt))
    if args.messages:
        print(f"--- last {args.messages} messages ---")
        print(d.rt.messages.format(args.messages), flush=True)


# --- a distributed controller (issue 19 item 3; docs/controller.md "Distributing the layers") ----
#: live seconds a process with --power-up waits for every other process's section before it
#: gives up (assumed: long enough to start the processes by hand one after the other)
DISTRIBUTED_WAIT_S = 10.0
#: live seconds a process stopping waits for the layers to reach SHUT DOWN (as one process's does)
DISTRIBUTED_STOP_S = 2.0


def _distributed_unsupported(args) -> list[str]:
    """Flags a distributed controller does not take (halt and single step stay with one
    process; the motion and path flags set world-model variables: pfma wm set --name BASE.PROCESS)."""
    flags = [("--halt", args.halt), ("--step", args.step is not None), ("--record", args.record is not None),
             ("--play", args.play is not None), ("--teleop", args.teleop is not None),
             ("--impedance", args.impedance is not None), ("--delay", args.delay is not None),
             ("--jitter", args.jitter is not None), ("--vernier", args.vernier), ("--demo-stick", args.demo_stick),
             ("--demo-wall", args.demo_wall is not None), ("--tables", args.tables),
             ("--hc-frame", args.hc_frame != "world"), ("--shoulder-roll", args.shoulder_roll is not None)]
    return [f for f, on in flags if on]


def _run_distributed(args) -> int:
    """``pfma controller --distribute FILE --process NAME``: one process of a distributed
    controller (or, with --sim, all of them in the distributed simulator)."""
    from controller.distributed import DistributedConfigError, load_config
    err = sys.stderr
    if args.action is not None:
        print(f"pfma controller {args.action}: not for a distributed controller (halt, step, resume and route "
              f"need one process's controller)", file=err)
        return 2
    if args.distribute is None:
        print("pfma controller: --process needs --distribute FILE (the file that assigns the layers to processes)",
              file=err)
        return 2
    try:
        config = load_config(args.distribute)
    except DistributedConfigError as e:
        for problem in e.problems:
            print(f"pfma controller: {e.source}: {problem}", file=err)
        return 2
    bad = _distributed_unsupported(args)
    if bad:
        print(f"pfma controller --distribute: {', '.join(bad)} not with a distributed controller (set world-model "
              f"variables with `pfma wm set --name BASE.PROCESS`; halt and single step need one process)", file=err)
        return 2
    if args.sim:  # --wm none: private memory (no `pfma wm` view)
        return _run_distributed_sim(args, config, None if args.wm in ("none", "") else
                                    args.wm or config.wm or "pfma_wm")
    if args.wm in ("none", ""):
        print("pfma controller --distribute: the processes find each other's world models by name: give --wm BASE "
              "(not none)", file=err)
        return 2
    base = args.wm or config.wm or "pfma_wm"
    if args.process is None:
        print(f"pfma controller --distribute: which process is this? --process NAME (processes in "
              f"{config.source}: {', '.join(config.names)}); --sim runs all of them simulated", file=err)
        return 2
    try:
        spec = config.process(args.process)
    except DistributedConfigError as e:
        print(f"pfma controller: {e.problems[0]}", file=err)
        return 2
    if args.power_up and "updown" not in spec.layers:
        print(f"pfma controller: --power-up goes to the process that runs updown (System Up/Down): "
              f"{config.process_of('updown')}, not {spec.name}", file=err)
        return 2
    from tools.attach import remote_target
    if "daq" in spec.layers and remote_target(args.buffer) is not None:
        print(f"pfma controller: process {spec.name} runs daq, the one writer of the Bit3 command area: it needs "
              f"the service's shared memory (--buffer NAME on the rack's host), not {args.buffer}", file=err)
        return 2
    try:
        d = _DistributedDriver(args, config, spec.name, base)
    except FileNotFoundError as e:
        print(f"pfma controller: no service buffer {args.buffer!r} ({e}); start `pfma serve`", file=err)
        return 1
    except Exception as e:  # noqa: BLE001 - a PfmaError (no service, no bridge, world model in use): one line
        from pfma.errors import PfmaError
        if not isinstance(e, PfmaError):
            raise
        print(f"pfma controller: {e}", file=err)
        return 1
    return d.run()


def _run_distributed_sim(args, config, base: str | None) -> int:
    """``--sim --distribute FILE``: every process in the distributed simulator."""
    from controller.decision import Status
    from controller.frames import FrameConfig
    from controller.layers import Request
    from controller.worldmodel import WorldModelError
    from sim.distributed import DistributedSimulator
    if args.process is not None:
        try:
            config.process(args.process)
        except Exception as e:  # noqa: BLE001 - DistributedConfigError
            print(f"pfma controller: {e.problems[0]}", file=sys.stderr)  # type: ignore[attr-defined]
            return 2
    shown = args.process or config.process_of("updown")
    try:
        sim = DistributedSimulator(config, frames=FrameConfig.profile(args.profile), wm_base=base,
                                   require_ft=not args.no_ft)
    except WorldModelError as e:
        print(f"pfma controller: {e}", file=sys.stderr)
        return 1
    with sim:
        rt = sim.rt(shown)
        printed = [False]

        def show(rec) -> None:
            if not args.trace or (args.changes and not any(lt.changed for lt in rec.layers)):
                return
            if not printed[0]:
                print(f"process {shown} (layers {' '.join(config.process(shown).layers)}; the others as its "
                      f"world model sees them)")
                print(rt.header())
                printed[0] = True
            print(rt.format_frame(rec), flush=True)
        rt.on_frame.append(show)
        sim.step(10)  # the service's first frames (links open)
        if args.power_up:
            sim.top.request(Request.POWER_UP)
        budget = int(round((args.duration if args.duration is not None else 1.0) / sim.period_s))
        up_at = None
        for n in range(budget):
            sim.step(1)
            if up_at is None and sim.all_status(Status.START_UP_COMPLETE):
                up_at = n + 1
        for p in config.processes:
            line = "  ".join(f"{k}={Status(s).name}" for k, s in sim.statuses().items() if k in p.layers)
            print(f"process {p.name}: {line}")
        if args.power_up:
            print(f"power-up: {'every layer START UP COMPLETE after ' + str(up_at) + ' frames' if up_at else 'not complete'}")
        print(f"process {shown}: {first_cause_line(rt)}")
        if args.messages:
            print(f"--- last {args.messages} messages of process {shown} ---")
            print(rt.messages.format(args.messages))
    return 0


class _PollPacer(LivePacer):
    """Paces a process whose inputs come over a bridge (``zenoh://``): no futex, and the
    service's frame times are another host's clock, so it polls for a new inputs body (the
    collector handling is the live pacer's)."""

    POLL_S = 100e-6
    GIVE_UP_S = 0.05  #: one wait at most (16 frames): the runtime's stale checks see the rest

    def __init__(self, client) -> None:
        super().__init__(client, period_s=self.GIVE_UP_S)

    def wait(self) -> None:
        end = time.monotonic() + self.GIVE_UP_S
        while not self.client.changed("inputs"):
            if time.monotonic() > end:
                self.gave_up += 1
                return
            time.sleep(self.POLL_S)

    def stepped(self, t_frame_s: float) -> None:
        self.frames += 1


class _DistributedDriver:
    """One live process of a distributed controller: its runtime paced by the service."""

    def __init__(self, args, config, process: str, base: str) -> None:
        from bit3.client import Client
        from controller.distributed import DistributedProcess
        from controller.frames import FrameConfig
        from pfma.clock import MonotonicClock
        from tools.attach import attach_reader
        self.args, self.config, self.process, self.base = args, config, process, base
        frames = FrameConfig.profile(args.profile)
        self.spec = config.process(process)
        self.link = None
        self.dp = None
        if "daq" in self.spec.layers:
            self.client = Client.attach(args.buffer, writer="commands", owner=f"pfma-controller-{process}")
        else:
            self.client = attach_reader(args.buffer)
        try:
            sources = None
            if config.transport == "zenoh":
                from tools.wm_sections import ZenohLink
                listen, connect = config.endpoints(process)
                self.link = ZenohLink(config, process, base, listen=listen, connect=connect)
                sources = self.link.sources
            self.dp = DistributedProcess(config, process, self.client, wm_base=base, sources=sources, frames=frames,
                                         clock=MonotonicClock(), require_ft=not args.no_ft)
            if self.link is not None:
                self.dp.rt.on_frame.append(self.link.publish)
        except BaseException:
            self.close()
            raise
        self.rt = self.dp.rt
        self.pacer = LivePacer(self.client, frames.period_s) if isinstance(self.client, Client) \
            else _PollPacer(self.client)
        _realtime(args)
        gc.collect()
        gc.freeze()
        self.printed_header = False
        #: says System Up/Down's state changes, WARNINGs and ERRORs as they happen (after the
        #: frame, rate-limited; None with -q): controller.messages.LivePrinter
        self.say = None
        if not getattr(args, "quiet", False):
            from controller.messages import LivePrinter
            self.say = LivePrinter(lambda line: print(line, flush=True), time.monotonic)
            self.rt.messages.listeners.append(self.say)
        self.stop_signal = 0  #: the SIGTERM or SIGINT that asked for a stop (0: none)
        self.closing = False  #: in close(): the power-down's frames run whatever the signals
        self._silent_since: float | None = None  # the first give-up of the pacer in a row
        self._silent_frame = -1
        self._silent_said = False

    @property
    def period_s(self) -> float:
        return self.rt.frames.period_s

    def frame(self) -> None:
        self.pacer.wait()
        self.rt.tick()
        self.pacer.stepped(float(self.rt.daq.snapshot.t_s))
        if self.say is not None:
            self.say.flush()  # after the frame's work: at most LIVE_PER_FLUSH lines
        if not self.pacer.gc_frozen and self.pacer.frames == _Driver.FREEZE_AFTER_FRAMES:
            self.pacer.freeze_gc()

    def show(self, rec) -> None:
        if not self.args.trace or (self.args.changes and not any(lt.changed for lt in rec.layers)):
            return
        if not self.printed_header:
            print(self.rt.header())
            self.printed_header = True
        print(self.rt.format_frame(rec), flush=True)

    def run(self) -> int:
        from controller.layers import Request
        args, imp = self.args, self.dp.importer
        others = [p for p in self.config.names if p != self.process]
        print(f"pfma controller: process {self.process} of {self.config.source}: layers "
              f"{' '.join(self.spec.layers)}; world model {self.dp.wm_name}; the others' sections by "
              f"{'Zenoh' if self.link is not None else 'shared memory'} from {', '.join(others)}", flush=True)
        self.rt.on_frame.append(self.show)
        budget = int(round(args.duration / self.period_s)) if args.duration is not None else sys.maxsize
        code = 0
        try:
            powered = not args.power_up
            wait_end = None
            for _ in range(budget):
                self.frame()
                if not powered:
                    # every other section seen, and this process past its first frames (imports,
                    # first allocations, the collector frozen): then the request
                    if imp.seen_all and self.pacer.frames > _Driver.FREEZE_AFTER_FRAMES:
                        self.rt.request(Request.POWER_UP)
                        powered = True
                    elif not imp.seen_all:
                        if wait_end is None:
                            print(f"pfma controller: waiting for the sections of {', '.join(imp.missing())} "
                                  f"before POWER UP", flush=True)
                            wait_end = time.monotonic() + DISTRIBUTED_WAIT_S
                        elif time.monotonic() > wait_end:
                            names = ", ".join(self.config.wm_name(self.base, p) for p in imp.missing())
                            print(f"pfma controller: no world-model section from {', '.join(imp.missing())} within "
                                  f"{DISTRIBUTED_WAIT_S:g} s ({names}): start those processes first; no POWER UP",
                                  file=sys.stderr)
                            code = 1
                            break
            _summary(self, args)
        except KeyboardInterrupt:
            print()
            _summary(self, args)  # Ctrl-C too: what happened, before the power-down
        finally:
            self.stop()
            self.close()
        return code

    def stop(self) -> None:
        """Leave the arm safe before letting go. The process with System Up/Down powers the
        whole system down in order (the others still running); another process, while the
        system is up, stops its own layers (its layers next to another process's fault,
        DistributedProcess.leave) and, with Data Acquisition, waits for the safe stop."""
        from controller.decision import Status
        from controller.layers import Request
        rt = self.rt
        t_end = time.monotonic() + DISTRIBUTED_STOP_S
        try:
            if "updown" in rt.local_keys:
                if rt.status("updown") in (Status.SHUT_DOWN, Status.ERROR):
                    return
                rt.request(Request.POWER_DOWN)
                while time.monotonic() < t_end and not rt.all_status(Status.SHUT_DOWN):
                    self.frame()
                return
            if self.dp.leave():
                while time.monotonic() < t_end and not self.dp.stopped():
                    self.frame()
        except Exception as e:  # noqa: BLE001
            print(f"pfma controller: power down on exit: {e}", file=sys.stderr)

    def close(self) -> None:
        if getattr(self, "pacer", None) is not None:
            self.pacer.release_gc()
        if self.dp is not None:
            self.dp.close()
        if self.link is not None:
            self.link.close()
        self.client.close()


def _realtime(args) -> None:
    """The live controller's real-time set-up (by default where permitted; ioservice.loop.
    realtime_start): the service pins itself to the last CPU (pfma serve), the controller
    takes the first, one priority below it."""
    from ioservice.loop import realtime_start
    for line in realtime_start("pfma controller", args.realtime, 0, 49):
        print(line, file=sys.stderr)
