"""``pfma wm``: browse a running controller's world model, and ask it for user writes.

    pfma wm list [--area A] [--filter TEXT] [--wm WM] [--json]
    pfma wm get NAME... [--json] [--wm WM]
    pfma wm set NAME VALUE [--key KEY] [--wait S] [--wm WM]
    pfma wm requests [--wm WM]

Everything is decoded from the variable table stored (as JSON) in the shared-memory
segment, so this needs no controller code. ``set`` checks the request here: unknown
variable; a variable users may not set (a task output, layer command, status or report, or
a control-law parameter while powered up: ``VarSpec.user``, the USER column of ``list``);
wrong key; bad value (an enumerated variable takes only the values of its enumeration).
It then puts it into the segment's user-request ring; the owning
process applies it at its next communications segment (docs/world-model.md). VALUE is JSON: ``1.5``, ``-3``, ``true``, ``[0.1, 0.2, 0.3]``
(or numbers separated by commas/spaces); an enumerated variable also takes a name (``PLAY``).

States, statuses, modes and error codes are shown by name with the number beside them
(``ERROR (7)``; pfma/show.py); ``--json`` keeps the number in ``value`` and puts the name
in ``value_name``.
"""

from __future__ import annotations

import argparse
import os
import sys

from tools.cli.args import nonneg_float
from tools.wmview import get_text, list_text, requests_text, set_user


def add_parser(sub):
    from controller.worldmodel import AREAS, DEFAULT_NAME, ACCESS_KEY_ENV

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--wm", "--name", dest="name", metavar="NAME", default=os.environ.get("PFMA_WM", DEFAULT_NAME),
                        help=f"world-model shared-memory name (default $PFMA_WM or {DEFAULT_NAME}); "
                             f"--name is an alias, as in `pfma controller`")
    p = sub.add_parser("wm", help="browse the controller's world model; user writes with a key",
                       description="Browse a running controller's world model (read from its "
                                   "shared memory), and ask its owner for keyed user writes.")
    wsub = p.add_subparsers(dest="wm_cmd", metavar="COMMAND")
    ls = wsub.add_parser("list", parents=[common],
                         help="variables with area, type, units, writer, who may set them, value")
    ls.add_argument("--area", choices=AREAS, help="only this area")
    ls.add_argument("--filter", metavar="TEXT",
                    help="only variables whose name, doc, units or writer contain TEXT (or match a *glob*)")
    ls.add_argument("--json", action="store_true", help="one JSON object")
    g = wsub.add_parser("get", parents=[common], help="variables in full (one consistent copy)")
    g.add_argument("names", nargs="+", metavar="NAME")
    g.add_argument("--json", action="store_true", help="one JSON object")
    s = wsub.add_parser("set", parents=[common], help="user write, applied at the next communications segment")
    s.add_argument("var", metavar="NAME")
    s.add_argument("value", metavar="VALUE", help="JSON value: 1.5, 3, true, [1, 2, 3]")
    s.add_argument("--key", default=None, help=f"access key (default ${ACCESS_KEY_ENV})")
    s.add_argument("--wait", type=nonneg_float, default=2.0, metavar="S",
                   help="wait up to S seconds for the owner to apply it (0: just queue; default 2)")
    r = wsub.add_parser("requests", parents=[common], help="the user-request ring and each outcome")
    r.add_argument("--json", action="store_true", help="one JSON object")
    p.set_defaults(_wm_parser=p)
    return p


# ----------------------------------------------------------------------------------------
# commands


def _print(lines: list[str]) -> int:
    for line in lines:
        print(line)
    return 0


def cmd_list(wm, args) -> int:
    return _print(list_text(wm, args.area, args.filter, args.json))


def cmd_get(wm, args) -> int:
    return _print(get_text(wm, args.names, args.json))


def cmd_set(wm, args) -> int:
    done = set_user(wm, args.var, args.value, args.key, args.wait)
    if done.error:
        print(f"pfma wm: {done.text}", file=sys.stderr)
    else:
        print(done.text)
    return done.code


def cmd_requests(wm, args) -> int:
    return _print(requests_text(wm, args.json))


COMMANDS = {"list": cmd_list, "get": cmd_get, "set": cmd_set, "requests": cmd_requests}


def run(args) -> int:
    from controller.worldmodel import WorldModel

    if not getattr(args, "wm_cmd", None):
        args._wm_parser.print_help()
        return 2
    wm = WorldModel.attach(args.name)  # WorldModelError (a PfmaError) -> "pfma wm: ..." exit 1
    try:
        return COMMANDS[args.wm_cmd](wm, args)
    finally:
        wm.close()
