"""Editing the recorded path files from the command line: the logic of ``pfma path``
(:mod:`tools.cli.path`): the option texts (points, point numbers, gripper events) read into
numbers, the edits of ``pfma path edit`` applied in their order, the points of ``pfma path
new`` and the playback plan's line of ``pfma path show --plan``. The files and the edits
themselves are :mod:`controller.paths`."""

from __future__ import annotations


def gripper_event(text: str, what: str = "--gripper") -> tuple[str, float | None]:
    """``ACTION[:N]`` -> (action, grip force or None); a PathError names what is wrong."""
    from controller.paths import PathError
    from controller.paths.model import PATH_GRIPPER_ACTIONS
    action, _, force = text.partition(":")
    if action not in PATH_GRIPPER_ACTIONS:
        raise PathError(f"{what}: {text!r}: the action is one of {', '.join(PATH_GRIPPER_ACTIONS)} "
                        f"(then :N for a grip force in N)")
    if not force:
        return action, None
    try:
        return action, float(force)
    except ValueError:
        raise PathError(f"{what}: {text!r}: the grip force {force!r} is not a number (N)") from None


def floats(text: str, n: tuple[int, ...], what: str) -> list[float]:
    from controller.paths import PathError
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise PathError(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if len(vals) not in n:
        raise PathError(f"{what}: {text!r} needs {' or '.join(map(str, n))} numbers")
    return vals


def ints(text: str, what: str) -> list[int]:
    from controller.paths import PathError
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise PathError(f"{what}: {text!r} is not a comma-separated list of point numbers") from None


def apply_edits(p, args):
    """``pfma path edit``'s changes to path ``p`` in the order delete, insert, move, speed,
    limits, gripper, note: the edited path (equal to ``p`` when nothing changes). ``args`` has
    the edit's options (``delete``, ``insert``, ``move``, ``pos``, ``offset``, ``quat``,
    ``speed``, ``v_lin``, ``v_rot``, ``clear``, ``limits``, ``gripper``, ``note``).

    :raises controller.paths.PathError: a bad option value, named
    """
    p = _edit_points(p, args)
    p = _edit_speeds(p, args)
    p = _edit_grippers(p, args)
    if args.note is not None:
        from dataclasses import replace
        p = replace(p, note=args.note)
    return p


def _edit_points(p, args):
    """``--delete``, ``--insert`` and ``--move`` (with ``--pos``, ``--offset``, ``--quat``)."""
    from controller.paths import PathError, delete_points, insert_point, move_point
    keep = args.quat == "keep"
    quat = floats(args.quat, (4,), "--quat") if args.quat and not keep else None
    if args.delete:
        p = delete_points(p, ints(args.delete, "--delete"))
    if args.insert is not None:
        if not args.pos:
            raise PathError("--insert needs --pos")
        p = insert_point(p, args.insert, floats(args.pos, (3,), "--pos"), quat)
    if args.move is not None:
        if not (args.pos or args.offset or args.quat):
            raise PathError("--move needs --pos, --offset or --quat")
        p = move_point(p, args.move, floats(args.pos, (3,), "--pos") if args.pos else None, quat,
                       floats(args.offset, (3,), "--offset") if args.offset else None, keep_orientation=keep)
    return p


def _edit_speeds(p, args):
    """``--speed`` (with ``--v-lin``, ``--v-rot`` or ``--clear``) and ``--limits``."""
    from controller.paths import PathError, set_limits, set_speed
    from controller.trajectory import Limits
    if args.speed:
        idx = None if args.speed == "all" else ints(args.speed, "--speed")
        if not args.clear and args.v_lin is None and args.v_rot is None:
            raise PathError("--speed needs --v-lin and/or --v-rot (or --clear)")
        p = set_speed(p, idx, args.v_lin, args.v_rot, clear=args.clear)
    if args.limits:
        p = set_limits(p, **dict(zip(Limits._fields, floats(args.limits, (4,), "--limits"))))
    return p


def _edit_grippers(p, args):
    """Each ``--gripper I ACTION[:N]``, in the order given."""
    from controller.paths import PathError, insert_gripper
    for index, text in args.gripper:
        try:
            i = int(index)
        except ValueError:
            raise PathError(f"--gripper: {index!r} is not a point number") from None
        p = insert_gripper(p, i, *gripper_event(text))
    return p


def plan_line(p) -> str:
    """The playback plan of path ``p`` (with points) in one line: segments, key points, time."""
    from controller.paths import plan_duration_s, plan_path
    plan = plan_path(p)
    keep = " with the orientation of the first point that has one" if any(
        x.quat is None for x in p.points) else ""
    return (f"  playback plan: {len(plan)} segments to key points "
            f"{', '.join(str(s.index) for s in plan)}; {plan_duration_s(p):.2f} s at the limits "
            f"(from point 0{keep}, without the approach)")


def new_points(points: list[str], grippers: list[tuple[int, str]]) -> list:
    """The points of ``pfma path new``: each ``--point`` text, and each ``--gripper`` event
    ``(points given before it, ACTION[:N])`` at its place among them with the pose of the
    point before it.

    :raises controller.paths.PathError: a bad point or event, named by its option
    """
    from controller.paths import PathError, make_point
    pts = []
    for i, text in enumerate(points):
        v = floats(text, (3, 7), f"--point {i}")
        pts.append(make_point(v[:3], v[3:] if len(v) == 7 else None, "teach", where=f"--point {i}"))
    for k, (after, text) in enumerate(grippers):  # in the order given; k events inserted before
        if not pts:
            raise PathError("--gripper: a gripper event needs a --point to take its pose from")
        action, force = gripper_event(text)
        at = after + k
        ref = pts[at - 1] if at > 0 else pts[0]  # the point before it (the first, for an event before any)
        pts.insert(at, make_point(ref.pos_m, ref.quat, "gripper", where=f"--gripper {text}",
                                  gripper=action, force_n=force))
    return pts
