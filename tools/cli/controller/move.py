"""``pfma controller move``: a checked move-to request to a running controller (issue 30
item 5; docs/controller.md "Moves that mean what they say")."""

from __future__ import annotations

import math

from tools.cli.controller.common import max_turn_rad, no_wm, refuse
from tools.stacks.controller import PROG


PROG_MOVE = f"{PROG} move"


def move_control(args) -> int:
    """``pfma controller move --pose ... | --joints ... | --stop --wm NAME``: one move-to
    request to the running controller through its world model; waits for its end (the
    controller's words: a refusal names the point and the reason; FAILED the worst tracking
    error and where)."""
    from tools.console.control import ControlError, ControllerLink
    if args.frames is not None or args.monitor is not None:
        return refuse("takes no N/CAMERA/MONITOR (use --pose, --joints or --stop)", PROG_MOVE)
    if args.pose is None and args.joints is None and not args.stop:
        return refuse("what to? --pose X,Y,Z[,QW,QX,QY,QZ], --joints DEG x 6 or --stop", PROG_MOVE)
    if no_wm(args):
        return refuse("needs the running controller's world model (--wm NAME)", PROG_MOVE)
    try:
        if args.pose is not None:
            vals = _numbers(args.pose, (3, 7), "--pose")
        elif args.joints is not None:
            vals = [math.radians(x) for x in _numbers(args.joints, (6,), "--joints")]
        turn = max_turn_rad(args.max_turn) if args.max_turn is not None else None
    except ValueError as e:
        return refuse(str(e), PROG_MOVE)
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
        return refuse(str(e), PROG_MOVE, code=1)
    return 0 if a.ok else 1


def _numbers(text: str, counts: tuple[int, ...], what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"{what} {text!r}: not a comma-separated list of numbers") from None
    if len(vals) not in counts or not all(math.isfinite(x) for x in vals):
        raise ValueError(f"{what} {text!r}: needs {' or '.join(map(str, counts))} finite numbers")
    return vals

