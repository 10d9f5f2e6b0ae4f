"""Requests to a RUNNING controller through its world model (tools.console.control): halt,
step [N], resume --rearm, route CAMERA MONITOR; the Global Commands power-up, power-down,
reset; the gripper. Each prints the controller's answer; a usage mistake is one line and
exit 2, a request that could not be made one line and exit 1."""

from __future__ import annotations

from tools.cli.controller.common import SYSTEM_REQUEST_TIMEOUT_S, no_wm, refuse
from tools.stacks.controller import PROG


def _frame_control_mistake(args) -> str | None:
    """What is wrong with ``halt|step|resume|route``'s arguments (None: nothing)."""
    from controller.runtime import MAX_STEP_FRAMES
    what = args.action
    if what == "route":
        if args.frames is None or args.monitor is None:
            return ("needs CAMERA MONITOR (e.g. `route 2 1`: camera 2 on monitor 1; camera 0 blanks the "
                    "monitor)")
    elif args.monitor is not None:
        return "takes no MONITOR (only route CAMERA MONITOR does)"
    if args.frames is not None and what not in ("step", "route"):
        return "takes no frame count (only step N does)"
    if getattr(args, "shoulder_roll", None) is not None:
        return ("takes no --shoulder-roll (a running controller's index: `pfma wm set joint.shoulder_roll_deg "
                "DEG` while it is powered down)")
    if args.rearm and what != "resume":
        return "--rearm belongs to resume"
    n = 1 if args.frames is None else args.frames
    if what == "step" and not 1 <= n <= MAX_STEP_FRAMES:
        return f"N must be 1..{MAX_STEP_FRAMES} (got {n}); longer is a resume"
    if no_wm(args):
        return "needs the running controller's world model (--wm NAME)"
    return None


def frame_control(args) -> int:
    """``pfma controller halt|step [N]|resume --rearm|route CAMERA MONITOR``: one request to
    the running controller through its world model; prints the answer (and a step's trace)."""
    from tools.console.control import ControlError, ControllerLink, Request
    prog = f"{PROG} {args.action}"
    mistake = _frame_control_mistake(args)
    if mistake is not None:
        return refuse(mistake, prog)
    n = 1 if args.frames is None else args.frames
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
        return refuse(str(err), prog, code=1)
    return 0 if a.ok else 1


def gripper_control(args) -> int:
    """``pfma controller gripper open|close|stop [--force N]`` (or ``gripper --force N``): one
    gripper request to the running controller's Servo Control through its world model; prints
    each answer and waits for the move to end (controller/gripper.py)."""
    from pfma.arm import GRIPPER
    from pfma.gripper import ACTIONS, MOVE_TIMEOUT_S, check_force
    from tools.console.control import ControlError, ControllerLink
    prog = f"{PROG} gripper"
    if args.monitor is not None or args.rearm or args.pose is not None or args.joints is not None or args.stop \
            or args.no_wait:
        return refuse("takes open|close|stop and --force N only", prog)
    if args.frames is None and args.force is None:
        return refuse("needs open, close or stop (and/or --force N)", prog)
    if args.force is not None:
        why = check_force(args.force, GRIPPER.force_max_n)
        if why:
            return refuse(f"--force: {why}", prog)
    if no_wm(args):
        return refuse("needs the running controller's world model (--wm NAME)", prog)
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
        return refuse(str(err), prog, code=1)
    return 0 if a.ok else 1


# --- the Global Commands from the shell: pfma controller power-up|power-down|reset ------------
def system_request(args) -> int:
    """``pfma controller power-up|power-down|reset``: the console's Global Commands (POWER
    UP, POWER DOWN, ERROR RESET) as one request to the running controller through its world
    model, as ``halt``, ``step`` and ``resume`` do; prints the answer. System Up/Down queues
    it: running, the final answer comes when the sequence ends (at most
    SYSTEM_REQUEST_TIMEOUT_S); halted, the request runs frame by frame with the steps
    (``pfma controller step``) and arming waits for ``resume --rearm``, so the command
    returns once the request is queued or in progress and says so."""
    from tools.console.control import ControlError, ControllerLink, Request, Response
    what = args.action
    prog = f"{PROG} {what}"
    if args.frames is not None or args.monitor is not None:
        return refuse("takes no frame count, camera or monitor", prog)
    if args.rearm:
        return refuse("--rearm belongs to resume", prog)
    if no_wm(args):
        return refuse("needs the running controller's world model (--wm NAME)", prog)
    kind = {"power-up": Request.POWER_UP, "power-down": Request.POWER_DOWN, "reset": Request.ERROR_RESET}[what]
    if args.shoulder_roll is not None and kind != Request.POWER_UP:
        return refuse("takes no --shoulder-roll (power-up's confirmation of the index)", prog)
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
        return refuse(str(err), prog, code=1)
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
        refuse(f"--shoulder-roll {given} but the controller's index is {t} (joint.shoulder_roll_deg): check the "
               f"joint's index pin, then set the index with `pfma wm set joint.shoulder_roll_deg {given}` (powered "
               f"down) or say {deg:g}; nothing sent", f"{PROG} power-up")
        return False
    how = (f"confirmed by --shoulder-roll {given}" if given is not None else
           "check the joint's index pin; --shoulder-roll DEG says it")
    print(f"POWER UP with the shoulder-roll index {t} (joint.shoulder_roll_deg; indexed by hand, no sensor: "
          f"{how})", flush=True)
    if "servo.brake_test" in link.wm.names() and int(link.wm.get("servo.brake_test")):
        print("the power-up tests every brake: each joint moves a little out and back (about a degree) "
              "before START UP COMPLETE (servo.brake_test); keep clear", flush=True)
    return True
