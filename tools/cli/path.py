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

from tools.paths import apply_edits, new_points, plan_line


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


def _edit(store, args) -> int:
    """``pfma path edit``: the changes (:func:`tools.paths.apply_edits`) saved as one new
    revision; then the rename."""
    orig = store.load(args.name)
    p = apply_edits(orig, args)
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
    p = store.load(args.name)
    if args.json:
        print(json.dumps(p.to_json(), indent=1))
        return 0
    print(p.describe())
    if args.plan and p.points:
        print(plan_line(p))
    return 0


def _new(store, args) -> int:
    """``pfma path new``: a new path from points."""
    p = store.new(args.name, new_points(args.point, args.gripper), note=args.note)
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
