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
import fnmatch
import json
import os
import sys
import time

import numpy as np
from tools.cli.args import nonneg_float
from tools.wmtext import _py, parse_value, value_text

WAIT_POLL_S = 0.002


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
# formatting


def _layers_in_error(wm) -> tuple[int, int]:
    """(layers in ERROR, layers): the ``<layer>.status`` variables whose value is named ERROR."""
    specs = [s for s in wm.specs if s.name.endswith(".status") and "ERROR" in s.enum_names.values()]
    if not specs:
        return 0, 0
    values = wm.get_task_inputs([s.name for s in specs])
    return sum(1 for s in specs if s.enum_names.get(int(values[s.name])) == "ERROR"), len(specs)


def _header(info, wm=None) -> str:
    owner = (f"{info.owner} (pid {info.owner_pid}, {'running' if info.owner_alive else 'NOT running'})"
             if info.owner_pid > 0 else f"{info.owner} (closed)")
    up = "yes" if info.powered_up else "no"
    n_err, n = _layers_in_error(wm) if wm is not None else (0, 0)
    if n_err:
        up += f" (but {n_err} of {n} layers in ERROR)" if info.powered_up else f" ({n_err} of {n} layers in ERROR)"
    return (f"world model {info.name!r}: owner {owner}, frame {info.frame}, "
            f"powered up: {up}, {info.n_variables} variables")


def _print_first_cause(wm) -> None:
    """Under the header, while the controller is in an ERROR episode: its root message."""
    cause = _first_cause(wm)
    if cause:
        print(f"first cause of the ERROR: {cause}")


def _print_gripper(wm) -> None:
    """Under the header: the gripper's state, grip force and jaw (controller/gripper.py), when
    the model has them."""
    line = gripper_line(wm)
    if line:
        print(line)


GRIPPER_VARS = ("gripper.state", "gripper.force_n", "gripper.motor_force_n", "gripper.jaw_m", "gripper.jaw_known")


def gripper_line(wm) -> str:
    """The gripper in one line ("" for a model without the gripper's variables)."""
    if wm is None or not all(n in wm.names() for n in GRIPPER_VARS):
        return ""
    from pfma.gripper import describe
    v = wm.get_task_inputs(GRIPPER_VARS)
    return describe(int(v["gripper.state"]), float(v["gripper.force_n"]), float(v["gripper.motor_force_n"]),
                    float(v["gripper.jaw_m"]) if bool(v["gripper.jaw_known"]) else None)


def _first_cause(wm) -> str:
    """The controller's current ERROR episode's root message (runtime.first_cause), or ""."""
    if wm is None:
        return ""
    from controller.runtime import first_cause_text
    return first_cause_text(wm)


def _matches(spec, text: str | None) -> bool:
    if not text:
        return True
    hay = [spec.name, spec.doc, spec.units, spec.writer]
    if any(c in text for c in "*?["):
        return any(fnmatch.fnmatch(h.lower(), text.lower()) for h in hay)
    t = text.lower()
    return any(t in h.lower() for h in hay)


def _user_text(spec) -> str:
    if spec.user == "always":
        return "yes, any time (with the access key)"
    if spec.user == "powered_down":
        return "only while powered down (protected; with the access key)"
    return f"never (posted by {spec.writer})"


def _describe(spec, value) -> dict:
    out = {"name": spec.name, "area": spec.area, "type": spec.type_text, "dtype": spec.dtype,
           "shape": list(spec.shape), "units": spec.units, "writer": spec.writer,
           "protected": spec.protected, "user": spec.user, "value": _py(value), "doc": spec.doc}
    if spec.enum or spec.flags:  # the number stays in "value"; the name beside it
        names = spec.enum_names or spec.flag_names
        v = int(np.asarray(value).item())
        out["value_name"] = (names.get(v) if spec.enum else
                             [n for b, n in names.items() if v & b])
        out["enum" if spec.enum else "flags"] = {str(k): n for k, n in names.items()}
    return out


# ----------------------------------------------------------------------------------------
# commands


def cmd_list(wm, args) -> int:
    specs = [s for s in wm.specs if (not args.area or s.area == args.area) and _matches(s, args.filter)]
    values = wm.get_task_inputs([s.name for s in specs])
    info = wm.info()
    if args.json:
        print(json.dumps({"name": info.name, "owner": info.owner, "owner_pid": info.owner_pid,
                          "frame": info.frame, "powered_up": info.powered_up, "first_cause": _first_cause(wm),
                          "variables": [_describe(s, values[s.name]) for s in specs]}, indent=1))
        return 0
    print(_header(info, wm))
    _print_first_cause(wm)
    _print_gripper(wm)
    if not specs:
        print("no variables match" + (f" area {args.area}" if args.area else "")
              + (f" filter {args.filter!r}" if args.filter else ""))
        return 0
    rows = [(s.name, s.area, s.type_text, s.units or "-", s.writer, s.user,
             value_text(s, values[s.name], 40), s.doc) for s in specs]
    heads = ("NAME", "AREA", "TYPE", "UNITS", "WRITER", "USER", "VALUE", "DOC")
    widths = [max(len(h), *(len(r[k]) for r in rows)) for k, h in enumerate(heads[:-1])]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths) + "  {}"
    print(fmt.format(*heads))
    for r in rows:
        print(fmt.format(*r).rstrip())
    print("USER = when `pfma wm set` may change it: always | powered_down (protected) | never (its writer "
          "only). `pfma wm get NAME` shows one in full.")
    return 0


def cmd_get(wm, args) -> int:
    specs = [wm.spec(n) for n in args.names]  # unknown names fail before reading
    values = wm.get_task_inputs([s.name for s in specs])
    info = wm.info()
    if args.json:
        print(json.dumps({"name": info.name, "frame": info.frame, "powered_up": info.powered_up,
                          "first_cause": _first_cause(wm),
                          "variables": {s.name: _describe(s, values[s.name]) for s in specs}}, indent=1))
        return 0
    print(f"{_header(info, wm)} (values from one consistent copy)")
    _print_first_cause(wm)
    _print_gripper(wm)
    for s in specs:
        print(f"\n{s.name}")
        print(f"  area       {s.area}")
        print(f"  type       {s.type_text}" + ("" if s.shape else " (scalar)"))
        print(f"  units      {s.units or '-'}")
        print(f"  writer     {s.writer}")
        print(f"  user set   {_user_text(s)}")
        print(f"  value      {value_text(s, values[s.name])}")
        if s.enum:
            print(f"  values     {s.enum_text()} (any other is refused)")
        elif s.flags:
            print("  bits       " + ", ".join(f"{b} {n}" for b, n in s.flags))
        print(f"  doc        {s.doc or '-'}")
    return 0


def cmd_set(wm, args) -> int:
    from controller.worldmodel import ACCESS_KEY_ENV, WorldModelError

    spec = wm.check_user_settable(args.var)  # who may set it: refused with or without a key
    key = args.key if args.key is not None else os.environ.get(ACCESS_KEY_ENV)
    if not key:
        raise WorldModelError(f"setting {spec.name!r} needs the world model's access key "
                              f"(--key KEY or ${ACCESS_KEY_ENV})")
    value = parse_value(args.value, spec)
    rid = wm.set_user(spec.name, value, key)
    if args.wait <= 0:
        print(f"{spec.name}: request #{rid} queued; the owner applies it at its next "
              f"communications segment (`pfma wm requests` shows the outcome)")
        return 0
    deadline = time.monotonic() + args.wait
    while True:
        r = wm.request(rid)
        if r is None:
            print(f"{spec.name}: request #{rid} was overwritten before its outcome was read")
            return 1
        if r.state == "applied":
            print(f"{spec.name} = {value_text(spec, wm.get(spec.name))} {spec.units}".rstrip()
                  + f"  (request #{rid}, {r.result})")
            return 0
        if r.state == "rejected":
            print(f"pfma wm: {spec.name}: request #{rid} rejected by the owner: {r.result}",
                  file=sys.stderr)
            return 1
        if time.monotonic() > deadline:
            print(f"pfma wm: {spec.name}: request #{rid} still pending after {args.wait:g} s; is the "
                  f"controller running communications segments? (`pfma wm requests`)", file=sys.stderr)
            return 1
        time.sleep(WAIT_POLL_S)  # a CLI waiting for another process, not a test


def cmd_requests(wm, args) -> int:
    reqs = wm.requests()
    if args.json:
        print(json.dumps([r.__dict__ for r in reqs], indent=1))
        return 0
    print(_header(wm.info(), wm))
    if not reqs:
        print("no user requests")
        return 0
    print(f"{'ID':>5}  {'STATE':<8}  {'VARIABLE':<28}  {'USER':<12}  {'FRAME':>8}  RESULT")
    for r in reqs:
        print(f"{r.req_id:>5}  {r.state:<8}  {r.variable:<28}  {r.user:<12}  "
              f"{r.applied_frame or '-':>8}  {r.result}")
    return 0


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
