"""``pfma path``: list, show, create, edit and delete the recorded path files.

Examples::

    pfma path list
    pfma path show demo
    pfma path new square --point 1.5,0,-0.3 --point 1.6,0,-0.3 --point 1.6,0.1,-0.3
    pfma path edit demo --delete 3,4 --insert 2 --pos 1.55,0.02,-0.3
    pfma path edit demo --move 5 --offset 0,0,0.01 --speed 5 --v-lin 0.02
    pfma path edit demo --limits 0.05,0.1,0.15,0.2 --rename demo2
    pfma path new pick --point 1.5,0,-0.3 --gripper open --point 1.5,0,-0.35 --gripper close:60
    pfma path edit pick --gripper 2 open       # a gripper event before point 2
    pfma path delete demo2

Files live in ``--dir`` (default ``$PFMA_PATH_DIR``, else ``~/.local/share/pfma/paths``);
``pfma controller --record NAME`` / ``--play NAME`` record and play them. Points are
numbered from 0 (negative numbers count from the end). A point given without an
orientation keeps the tool's: the orientation of the point before it, or, at the first
point, the tool's orientation when the playback starts (``--quat keep`` makes a point so).
"""

from __future__ import annotations

import argparse
import json
import sys


def add_parser(sub):
    p = sub.add_parser("path", help="list, show, edit and delete recorded paths",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--dir", default=None, help="path directory (default $PFMA_PATH_DIR or ~/.local/share/pfma/paths)")
    ps = p.add_subparsers(dest="path_cmd", metavar="CMD")
    ps.add_parser("list", help="the paths (name, id, points, length, revision)")
    s = ps.add_parser("show", help="one path, point by point")
    s.add_argument("name")
    s.add_argument("--json", action="store_true", help="the file's JSON")
    s.add_argument("--plan", action="store_true", help="also the playback plan (key points, limits, time)")
    n = ps.add_parser("new", help="a new path from points")
    n.add_argument("name")
    n.add_argument("--point", action="append", default=[], metavar="X,Y,Z[,QW,QX,QY,QZ]",
                   help="a teach point (metres, world frame); without a quaternion it keeps the tool's orientation "
                        "(the point before's, or the tool's when the playback starts); repeat")
    n.add_argument("--gripper", action=_GripperAfterPoints, default=[], metavar="ACTION[:N]",
                   help="a gripper event (open, close or stop; :N a grip force in N) after the points given so "
                        "far, at the pose of the point before it; replayed in order with the motion; repeat")
    n.add_argument("--note", default="")
    e = ps.add_parser("edit", help="change points, speeds, limits or the name (saved as a new revision)")
    e.add_argument("name")
    e.add_argument("--delete", metavar="I[,J...]", help="delete these points")
    e.add_argument("--insert", type=int, metavar="I", help="insert a point before I (with --pos [--quat])")
    e.add_argument("--move", type=int, metavar="I", help="move point I (with --pos, --offset and/or --quat)")
    e.add_argument("--pos", metavar="X,Y,Z", help="position for --insert/--move (m)")
    e.add_argument("--offset", metavar="DX,DY,DZ", help="shift for --move (m)")
    e.add_argument("--quat", metavar="QW,QX,QY,QZ|keep",
                   help="orientation for --insert/--move ('keep': none of its own, it keeps the tool's; --insert "
                        "without --quat keeps it too)")
    e.add_argument("--speed", metavar="I[,J...]|all", help="speed override of the segments ending at these points "
                                                            "(with --v-lin/--v-rot, or --clear)")
    e.add_argument("--v-lin", type=float, help="translation speed m/s for --speed")
    e.add_argument("--v-rot", type=float, help="rotation speed rad/s for --speed")
    e.add_argument("--clear", action="store_true", help="remove the --speed overrides")
    e.add_argument("--limits", metavar="VLIN,ALIN,VROT,AROT", help="path limits (m/s, m/s^2, rad/s, rad/s^2)")
    e.add_argument("--gripper", nargs=2, action="append", default=[], metavar=("I", "ACTION[:N]"),
                   help="insert a gripper event (open, close or stop; :N a grip force in N) before point I, at "
                        "the pose of the point before it; repeat")
    e.add_argument("--note", default=None)
    e.add_argument("--rename", metavar="NEW")
    d = ps.add_parser("delete", help="delete a path file")
    d.add_argument("name")
    return p


class _GripperAfterPoints(argparse.Action):
    """``--gripper`` of ``pfma path new``: kept with the number of ``--point`` given before it
    (argparse reads the options in order), so the events keep their place among the points."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        events = list(getattr(namespace, self.dest) or [])
        events.append((len(getattr(namespace, "point", None) or []), values))
        setattr(namespace, self.dest, events)


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


def _floats(text: str, n: tuple[int, ...], what: str) -> list[float]:
    from controller.paths import PathError
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise PathError(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if len(vals) not in n:
        raise PathError(f"{what}: {text!r} needs {' or '.join(map(str, n))} numbers")
    return vals


def _ints(text: str, what: str) -> list[int]:
    from controller.paths import PathError
    try:
        return [int(x) for x in text.split(",")]
    except ValueError:
        raise PathError(f"{what}: {text!r} is not a comma-separated list of point numbers") from None


def _edit(store, args) -> int:
    """``pfma path edit``: the changes in the order delete, insert, move, speed, limits,
    gripper, note, saved as one new revision; then the rename."""
    orig = store.load(args.name)
    p = _edit_points(orig, args)
    p = _edit_speeds(p, args)
    p = _edit_grippers(p, args)
    if args.note is not None:
        from dataclasses import replace
        p = replace(p, note=args.note)
    if p == orig and not args.rename:
        print("nothing to change (see pfma path edit --help)", file=sys.stderr)
        return 2
    if p != orig:
        p = store.save(p)
        print(f"path {p.name}: revision {p.revision}, {len(p.points)} points")
    if args.rename:
        p = store.rename(p.name, args.rename)
        print(f"path {args.name} renamed {p.name} (id {p.id}, revision {p.revision})")
    return 0


def _edit_points(p, args):
    """``--delete``, ``--insert`` and ``--move`` (with ``--pos``, ``--offset``, ``--quat``)."""
    from controller.paths import PathError, delete_points, insert_point, move_point
    keep = args.quat == "keep"
    quat = _floats(args.quat, (4,), "--quat") if args.quat and not keep else None
    if args.delete:
        p = delete_points(p, _ints(args.delete, "--delete"))
    if args.insert is not None:
        if not args.pos:
            raise PathError("--insert needs --pos")
        p = insert_point(p, args.insert, _floats(args.pos, (3,), "--pos"), quat)
    if args.move is not None:
        if not (args.pos or args.offset or args.quat):
            raise PathError("--move needs --pos, --offset or --quat")
        p = move_point(p, args.move, _floats(args.pos, (3,), "--pos") if args.pos else None, quat,
                       _floats(args.offset, (3,), "--offset") if args.offset else None, keep_orientation=keep)
    return p


def _edit_speeds(p, args):
    """``--speed`` (with ``--v-lin``, ``--v-rot`` or ``--clear``) and ``--limits``."""
    from controller.paths import PathError, set_limits, set_speed
    from controller.trajectory import Limits
    if args.speed:
        idx = None if args.speed == "all" else _ints(args.speed, "--speed")
        if not args.clear and args.v_lin is None and args.v_rot is None:
            raise PathError("--speed needs --v-lin and/or --v-rot (or --clear)")
        p = set_speed(p, idx, args.v_lin, args.v_rot, clear=args.clear)
    if args.limits:
        p = set_limits(p, **dict(zip(Limits._fields, _floats(args.limits, (4,), "--limits"))))
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


def _list(store, args) -> int:
    """``pfma path list``: name, id, points, length, revision; unreadable files on stderr."""
    infos = store.list()
    if not infos:
        print(f"no paths in {store.dir}")
    else:
        print(f"{'name':<24} {'id':>5} {'points':>7} {'length m':>9} {'rev':>4}  modified")
        for i in infos:
            print(f"{i.name:<24} {i.id:>5} {i.points:>7} {i.length_m:>9.3f} {i.revision:>4}  {i.modified}")
    for prob in store.problems():
        print(f"unreadable: {prob}", file=sys.stderr)
    return 0


def _show(store, args) -> int:
    """``pfma path show``: point by point (``--plan``: and the playback plan), or ``--json``."""
    from controller.paths import plan_duration_s, plan_path
    p = store.load(args.name)
    if args.json:
        print(json.dumps(p.to_json(), indent=1))
        return 0
    print(p.describe())
    if args.plan and p.points:
        plan = plan_path(p)
        keep = " with the orientation of the first point that has one" if any(
            x.quat is None for x in p.points) else ""
        print(f"  playback plan: {len(plan)} segments to key points "
              f"{', '.join(str(s.index) for s in plan)}; {plan_duration_s(p):.2f} s at the limits "
              f"(from point 0{keep}, without the approach)")
    return 0


def _new_points(args) -> list:
    """The points of ``pfma path new``: each ``--point``, and each ``--gripper`` event at its
    place among them with the pose of the point before it."""
    from controller.paths import PathError, make_point
    pts = []
    for i, text in enumerate(args.point):
        v = _floats(text, (3, 7), f"--point {i}")
        pts.append(make_point(v[:3], v[3:] if len(v) == 7 else None, "teach", where=f"--point {i}"))
    for k, (after, text) in enumerate(args.gripper):  # in the order given; k events inserted before
        if not pts:
            raise PathError("--gripper: a gripper event needs a --point to take its pose from")
        action, force = gripper_event(text)
        at = after + k
        ref = pts[at - 1] if at > 0 else pts[0]  # the point before it (the first, for an event before any)
        pts.insert(at, make_point(ref.pos_m, ref.quat, "gripper", where=f"--gripper {text}",
                                  gripper=action, force_n=force))
    return pts


def _new(store, args) -> int:
    """``pfma path new``: a new path from points."""
    p = store.new(args.name, _new_points(args), note=args.note)
    print(f"path {p.name}: id {p.id}, {len(p.points)} points, {store.file(p.name)}")
    return 0


def _delete(store, args) -> int:
    """``pfma path delete``."""
    store.delete(args.name)
    print(f"path {args.name} deleted")
    return 0


#: ``pfma path CMD`` -> what runs it
_COMMANDS = {"list": _list, "show": _show, "new": _new, "edit": _edit, "delete": _delete}


def run(args) -> int:
    from controller.paths import PathStore
    store = PathStore(args.dir)
    command = _COMMANDS.get(args.path_cmd or "list")
    return 2 if command is None else command(store, args)
