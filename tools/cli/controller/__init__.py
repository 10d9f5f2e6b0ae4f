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

from pfma import log as pfma_log
from tools.cli.controller import arguments, distributed, local, move, requests
from tools.cli.controller.common import SYSTEM_ACTIONS, refuse
from tools.stacks.controller import PROG


def add_parser(sub):
    return arguments.add_parser(sub, __doc__.split("\n\n")[0])


def run(args) -> int:
    """The process's log set up once (``--log-level``: ``pfma controller: ...`` on stderr),
    then the action. Its handler is taken off again when the verb returns: ``main()`` called
    in-process (the tests) leaves no handler on a stderr that is gone by then."""
    with pfma_log.for_process(PROG, args.log_level):
        return _act(args)


def _act(args) -> int:
    """One call per action."""
    if args.distribute is not None or args.process is not None:
        if args.clock != "locked":
            return refuse("--clock own is for a controller in one process; a distributed one steps on "
                          "the service's frames (docs/controller.md, \"Two clocks\")")
        return distributed.run(args)
    if args.wm is None:
        args.wm = "pfma_wm"
    if args.action == "gripper":
        return requests.gripper_control(args)
    if args.force is not None:
        return refuse("--force belongs to `pfma controller gripper`")
    if args.action in SYSTEM_ACTIONS:
        return requests.system_request(args)
    if args.action == "move":
        return move.move_control(args)
    if args.pose is not None or args.joints is not None or args.stop or args.no_wait:
        return refuse("--pose, --joints, --stop and --no-wait belong to `pfma controller move`")
    if args.action is not None:
        return requests.frame_control(args)
    if args.frames is not None or args.monitor is not None:
        return refuse("a frame count belongs to `pfma controller step N`, a camera and a monitor to "
                      "`pfma controller route CAMERA MONITOR`")
    if args.tables:
        return local.print_tables(args.profile)
    return local.run(args)
