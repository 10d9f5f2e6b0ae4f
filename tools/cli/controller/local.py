"""One controller process, run by ``pfma controller`` on a live service or with ``--sim``:
its settings, its frames (a budget, or single-stepped from the keyboard with ``--halt``), and
the summary at the end; the process itself is :class:`tools.stacks.controller.ControllerStack`."""

from __future__ import annotations

import signal
import sys

from tools.cli.controller.common import log, refuse, stack_options, status_line, summary
from tools.cli.controller.paths import finish_paths, setup_paths
from tools.cli.controller.setup import motion_settings, motion_summary, roll_summary, setup_motion, setup_roll
from tools.stacks.controller import ControllerStack, Driver

HELP = """single-step commands (IRSS halt / manual interrupt):
  Enter or s      one minor frame          s N   N minor frames
  c               continue to the end      q     quit
  p / d / r       request POWER UP / POWER DOWN / ERROR RESET
  m               the last 100 messages    t     the layers' statuses
  ?               this help"""




def print_tables(profile: str) -> int:
    """``pfma controller --tables``: the seven layers' decision tables (highest first) and
    the scheduling table."""
    from controller.decision import describe
    from controller.frames import FrameConfig
    from controller.tables import TABLES
    for table in TABLES.values():
        print(describe(table))
        print()
    print(FrameConfig.profile(profile).validate().describe())
    return 0



def _interactive(d: Driver, budget: int) -> None:
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


def _shared_command(d: Driver, cmd: str, applied: str) -> bool:
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
        print(status_line(d.rt))
    else:
        return False
    return True


def _interactive_live(d: Driver, budget: int) -> None:
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



def _sim_fault_mistake(args) -> int:
    """``--sim-fault`` or ``--sim-errors`` without ``--sim``, or a bad spec: a usage mistake, said before anything
    is built (2); 0 when there is none."""
    if getattr(args, "sim_errors", 0) and not args.sim:
        return refuse("--sim-errors needs --sim (a running service takes `pfma serve --sim-errors SEED`)")
    if not args.sim_fault:
        return 0
    if not args.sim:
        return refuse("--sim-fault needs --sim (a running service takes `pfma fault inject`)")
    from pfma.errors import ConfigError
    from sim.faults import parse_fault
    for spec in args.sim_fault:
        try:
            parse_fault(spec)
        except ConfigError as err:
            return refuse(f"--sim-fault {err}")
    return 0


def run(args) -> int:
    """``pfma controller [--sim]``: one controller process, its frames, its summary; the
    process is left safe and closed on every way out (tools.stacks.controller)."""
    code = _sim_fault_mistake(args)
    if code:
        return code
    try:
        stack = ControllerStack(stack_options(args)).open()
    except FileNotFoundError as err:
        return refuse(f"no service buffer {args.buffer!r} ({err}); start `pfma serve` or use --sim", code=1)
    with stack:
        d = stack.driver
        assert d is not None
        d.rt.on_frame.append(d.show)
        stack.stop_on_signals(between_frames=not args.halt)
        try:
            return _run_frames(d, args)
        except KeyboardInterrupt:
            print()
            if d.stop_signal:
                log.warning(f"{signal.Signals(d.stop_signal).name}: stopping (powering down in order)")
            summary(d, args)  # Ctrl-C and SIGTERM too: what happened, before the power-down
    return 0


def _budget(d: Driver, args) -> int:
    """How many minor frames the run lasts: --duration, 1 s with --sim, else until stopped;
    at most --step N."""
    if args.duration is not None:
        budget = int(round(args.duration / d.period_s))
    elif args.sim:
        budget = int(round(1.0 / d.period_s))
    else:
        budget = sys.maxsize
    if args.step is not None:
        budget = min(budget, args.step)
    return budget


def _run_frames(d: Driver, args) -> int:
    """The settings, the frames, the lines at the end (0; 2 for a refused power-up)."""
    from controller.layers import Request
    if setup_roll(d, args):
        return 2
    setup_motion(d, args)
    paths = setup_paths(d, args)
    if args.power_up:
        d.rt.request(Request.POWER_UP)
    budget = _budget(d, args)
    if args.halt and not args.sim:
        _interactive_live(d, budget)
    elif args.halt:
        _interactive(d, budget)
    else:
        for _ in range(budget):
            d.frame()
    finish_paths(d, args, paths)
    if motion_settings(args) or args.demo_stick or args.demo_wall is not None:
        print(motion_summary(d))
    if args.shoulder_roll is not None or (d.sim is None and args.power_up):
        print(roll_summary(d))
    summary(d, args)
    return 0
