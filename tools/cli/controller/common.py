"""What the ``pfma controller`` verb modules share: the one-line refusal, the names of the
actions, the summary said at the end of a run."""

from __future__ import annotations

import logging
import math

from tools.stacks.controller import PROG, ControllerOptions, Distribution

log = logging.getLogger("tools.cli.controller")

#: ``pfma controller ACTION``: the Global Commands' requests (docs/console.md) to a running controller
SYSTEM_ACTIONS = ("power-up", "power-down", "reset")
#: how long ``pfma controller power-up|power-down|reset`` waits for the final answer (assumed:
#: the longest sequence, a power-up with its init, arm and brake-release time-outs of
#: controller/daq_layer.py and controller/servo.py, takes about 1.2 s; ten seconds is far
#: beyond it and still a prompt "no answer" for a controller that is not running frames)
SYSTEM_REQUEST_TIMEOUT_S = 10.0
#: the words of ``pfma controller gripper`` (pfma.gripper.ACTIONS; the force alone is --force)
GRIPPER_VERBS = ("open", "close", "stop")


def refuse(text: str, prog: str = PROG, code: int = 2) -> int:
    """Say ``PROG: text`` on stderr (the process's log, at error) and return ``code``: a
    usage mistake is 2, a request that could not be made 1."""
    log.error(text, extra={"prog": prog})
    return code


def no_wm(args) -> bool:
    """``--wm none`` (or empty): a private world model, which no other process can reach."""
    return args.wm in ("none", "")


def stack_options(args, distributed: Distribution | None = None) -> ControllerOptions:
    """The controller process ``pfma controller``'s arguments ask for."""
    return ControllerOptions(
        profile=args.profile, wm=None if no_wm(args) else args.wm, sim=args.sim, buffer=args.buffer,
        require_ft=not args.no_ft, shoulder_roll_deg=getattr(args, "shoulder_roll", None) or 0,
        quiet=getattr(args, "quiet", False), sim_faults=tuple(getattr(args, "sim_fault", None) or ()),
        sim_fault_at_s=args.sim_fault_at, sim_errors=getattr(args, "sim_errors", 0), realtime=args.realtime, changes=args.changes,
        trace=args.trace or (distributed is None and (args.step is not None or args.halt)),
        distributed=distributed, max_missed_run=getattr(args, "max_missed_run", None),
        clock=getattr(args, "clock", "locked"))


def text(words) -> str:
    """A world model's text variable (words of bytes, NUL-padded)."""
    return bytes(words).rstrip(b"\0").decode(errors="replace")


def max_turn_rad(deg: float) -> float:
    return math.radians(deg)


def status_line(rt) -> str:
    from controller.decision import status_text
    return "  ".join(f"{l.short.strip()}={status_text(s)}" for l, s in zip(rt.layers, rt.statuses().values()))


def first_cause_line(rt) -> str:
    """The current ERROR episode's first cause in one line ("none" without an episode)."""
    fc = rt.first_cause
    if fc is None:
        return "first cause: none (no ERROR episode)"
    return f"first cause of the ERROR: {fc.format()}"


def summary(d, args) -> None:
    """At exit (--duration ended, Ctrl-C, SIGTERM): what is still to be said, the layers'
    statuses, the ERROR episode's first cause (kept however many messages followed it) and
    the last messages."""
    if d.say is not None:
        d.say.drain()
    print(status_line(d.rt))
    print(first_cause_line(d.rt))
    if args.messages:
        print(f"--- last {args.messages} messages ---")
        print(d.rt.messages.format(args.messages), flush=True)
