"""What ``pfma wm`` shows of a running controller's world model, and its user writes: the
header line, the variable table, one variable in full, the request ring, and a keyed
``set`` waited for until its owner applies it. The verb (:mod:`tools.cli.wm`) parses the
options and prints; the value text itself is :mod:`tools.wmtext`."""

from __future__ import annotations

import fnmatch
import json
import os
import time
from dataclasses import dataclass

import numpy as np
from tools.wmtext import _py, parse_value, value_text

WAIT_POLL_S = 0.002


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


def _under_header(wm) -> list[str]:
    """Under the header: while the controller is in an ERROR episode, its root message; the
    gripper's state, grip force and jaw (controller/gripper.py), when the model has them."""
    lines = []
    cause = _first_cause(wm)
    if cause:
        lines.append(f"first cause of the ERROR: {cause}")
    line = gripper_line(wm)
    if line:
        lines.append(line)
    return lines


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


def list_text(wm, area: str | None, text: str | None, as_json: bool) -> list[str]:
    """``pfma wm list``: the variables of ``area`` matching ``text`` (all without them)."""
    specs = [s for s in wm.specs if (not area or s.area == area) and _matches(s, text)]
    values = wm.get_task_inputs([s.name for s in specs])
    info = wm.info()
    if as_json:
        return [json.dumps({"name": info.name, "owner": info.owner, "owner_pid": info.owner_pid,
                            "frame": info.frame, "powered_up": info.powered_up, "first_cause": _first_cause(wm),
                            "variables": [_describe(s, values[s.name]) for s in specs]}, indent=1)]
    lines = [_header(info, wm), *_under_header(wm)]
    if not specs:
        return lines + ["no variables match" + (f" area {area}" if area else "")
                        + (f" filter {text!r}" if text else "")]
    rows = [(s.name, s.area, s.type_text, s.units or "-", s.writer, s.user,
             value_text(s, values[s.name], 40), s.doc) for s in specs]
    heads = ("NAME", "AREA", "TYPE", "UNITS", "WRITER", "USER", "VALUE", "DOC")
    widths = [max(len(h), *(len(r[k]) for r in rows)) for k, h in enumerate(heads[:-1])]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths) + "  {}"
    lines.append(fmt.format(*heads))
    lines += [fmt.format(*r).rstrip() for r in rows]
    lines.append("USER = when `pfma wm set` may change it: always | powered_down (protected) | never (its writer "
                 "only). `pfma wm get NAME` shows one in full.")
    return lines


def get_text(wm, names: list[str], as_json: bool) -> list[str]:
    """``pfma wm get``: each variable in full, from one consistent copy.

    :raises controller.worldmodel.WorldModelError: an unknown name (before anything is read)
    """
    specs = [wm.spec(n) for n in names]  # unknown names fail before reading
    values = wm.get_task_inputs([s.name for s in specs])
    info = wm.info()
    if as_json:
        return [json.dumps({"name": info.name, "frame": info.frame, "powered_up": info.powered_up,
                            "first_cause": _first_cause(wm),
                            "variables": {s.name: _describe(s, values[s.name]) for s in specs}}, indent=1)]
    lines = [f"{_header(info, wm)} (values from one consistent copy)", *_under_header(wm)]
    for s in specs:
        lines += [f"\n{s.name}",
                  f"  area       {s.area}",
                  f"  type       {s.type_text}" + ("" if s.shape else " (scalar)"),
                  f"  units      {s.units or '-'}",
                  f"  writer     {s.writer}",
                  f"  user set   {_user_text(s)}",
                  f"  value      {value_text(s, values[s.name])}"]
        if s.enum:
            lines.append(f"  values     {s.enum_text()} (any other is refused)")
        elif s.flags:
            lines.append("  bits       " + ", ".join(f"{b} {n}" for b, n in s.flags))
        lines.append(f"  doc        {s.doc or '-'}")
    return lines


@dataclass(frozen=True)
class SetOutcome:
    """How a ``pfma wm set`` ended: exit code, the line, and whether it is an error (stderr)."""

    code: int
    text: str
    error: bool = False


def set_user(wm, name: str, text: str, key: str | None, wait_s: float) -> SetOutcome:
    """``pfma wm set``: check and queue the user write (``key`` default ``$PFMA_WM_KEY``),
    then wait up to ``wait_s`` for its owner to apply or reject it (0: just queue).

    :raises controller.worldmodel.WorldModelError: a variable users may not set, no key, a bad value
    """
    from controller.worldmodel import ACCESS_KEY_ENV, WorldModelError

    spec = wm.check_user_settable(name)  # who may set it: refused with or without a key
    key = key if key is not None else os.environ.get(ACCESS_KEY_ENV)
    if not key:
        raise WorldModelError(f"setting {spec.name!r} needs the world model's access key "
                              f"(--key KEY or ${ACCESS_KEY_ENV})")
    value = parse_value(text, spec)
    rid = wm.set_user(spec.name, value, key)
    if wait_s <= 0:
        return SetOutcome(0, f"{spec.name}: request #{rid} queued; the owner applies it at its next "
                             f"communications segment (`pfma wm requests` shows the outcome)")
    deadline = time.monotonic() + wait_s
    while True:
        r = wm.request(rid)
        if r is None:
            return SetOutcome(1, f"{spec.name}: request #{rid} was overwritten before its outcome was read")
        if r.state == "applied":
            return SetOutcome(0, f"{spec.name} = {value_text(spec, wm.get(spec.name))} {spec.units}".rstrip()
                              + f"  (request #{rid}, {r.result})")
        if r.state == "rejected":
            return SetOutcome(1, f"{spec.name}: request #{rid} rejected by the owner: {r.result}", error=True)
        if time.monotonic() > deadline:
            return SetOutcome(1, f"{spec.name}: request #{rid} still pending after {wait_s:g} s; is the "
                                 f"controller running communications segments? (`pfma wm requests`)", error=True)
        time.sleep(WAIT_POLL_S)  # a CLI waiting for another process, not a test


def requests_text(wm, as_json: bool) -> list[str]:
    """``pfma wm requests``: the user-request ring and each outcome."""
    reqs = wm.requests()
    if as_json:
        return [json.dumps([r.__dict__ for r in reqs], indent=1)]
    lines = [_header(wm.info(), wm)]
    if not reqs:
        return lines + ["no user requests"]
    lines.append(f"{'ID':>5}  {'STATE':<8}  {'VARIABLE':<28}  {'USER':<12}  {'FRAME':>8}  RESULT")
    lines += [f"{r.req_id:>5}  {r.state:<8}  {r.variable:<28}  {r.user:<12}  "
              f"{r.applied_frame or '-':>8}  {r.result}" for r in reqs]
    return lines
