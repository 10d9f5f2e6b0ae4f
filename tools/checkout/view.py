"""Text views of the buffer for ``pfma monitor`` (every channel) and ``pfma watch`` (a few).

Pure functions of a :class:`bit3.client.Client`; the CLI modules only loop, pace
and redraw. Values are shown the one way of pfma/show.py: angles (rad) in (-pi, pi],
states and codes by name, each channel's status word by name (``bit3.layout.status_text``:
``ok``, ``LOS``, ``BUSERR``, ``STALE``, ``FAULT``).
"""

from __future__ import annotations

import fnmatch
import math
import re
from typing import Any, Callable, NamedTuple

import numpy as np

from bit3.layout import (
    CMD_STATUS_NAMES, DEVICE_GROUPS, FAULT_CODE_NAMES, FAULT_DAC_UNREACHABLE, ServiceState, status_text,
)
from pfma.errors import PfmaError, did_you_mean
from pfma.show import flag_names, name_of, named, wrap_angle

#: which device group's measured rate applies to a channel kind
KIND_DEVICE = {"rtd": "rtd", "adc": "adc", "dac": "dac", "pio": "pio"}
HC_DEVICE = {"cae": "adc", "crl": "crl", "hid": "hid"}
#: input-area fields that hold an enumeration or a bit set, by their names (``pfma watch``)
FIELD_NAMES: dict[str, tuple[str, dict[int, str]]] = {
    "service_state": ("enum", {int(s): s.name for s in ServiceState}),
    "fault_code": ("enum", FAULT_CODE_NAMES),
    "command_status": ("flags", CMD_STATUS_NAMES),
}


def hc_status(valid: bool, deadman: bool, fault: bool) -> str:
    """A hand controller's status: FAULT, NO DATA (axes not valid), DEADMAN (held) or ok."""
    return "FAULT" if fault else "NO DATA" if not valid else "DEADMAN" if deadman else "ok"


def entry_status(s, c) -> str | None:
    """The status of one input entry (rack channel, board, link, hand controller) of
    snapshot ``s`` by name (``ok``, ``LOS``, ...), or None when it has no status word."""
    if c.kind == "hc":
        i = c.slot
        return hc_status(bool(s.hc_valid[i]), bool(s.hc_deadman[i]), bool(s.hc_fault[i]))
    for f, i, _ in c.fields:
        if f.endswith("_status") and c.kind != "pio":
            return status_text(c.kind, int(s.record[f][i]))
    return None


#: what a board's or a link's value is (its status word is shown as its status, by name)
ENTRY_VALUE = {"board": ("board_errors", "err"), "link": ("link_records", "recs")}


def entry_value(s, c) -> Any:
    """The value of one input entry of snapshot ``s`` as the tools show it: a resolver angle
    in (-pi, pi]; a board's error count, a link's good records (:data:`ENTRY_VALUE`); else
    the channel's engineering value (``Snapshot.value``)."""
    if c.kind in ENTRY_VALUE:
        return int(s.record[ENTRY_VALUE[c.kind][0]][c.slot])
    v = s.value(c.name)
    return wrap_angle(v) if c.kind == "rtd" else v


def entry_units(c) -> str:
    """The units of :func:`entry_value`."""
    return ENTRY_VALUE[c.kind][1] if c.kind in ENTRY_VALUE else c.units


def field_text(name: str, v: Any) -> str | None:
    """An enumerated input field's value by name (``ARMED (2)``), None for any other field."""
    how = FIELD_NAMES.get(name)
    if how is None:
        return None
    kind, names = how
    if kind == "enum":
        return named(int(v), names)
    return f"{flag_names(int(v), names)} ({int(v)})"


def fmt(v: Any) -> str:
    """A compact number (or array) for a fixed-width column."""
    if isinstance(v, np.ndarray):
        return "[" + " ".join(fmt(x) for x in v.tolist()) + "]"
    if isinstance(v, (list, tuple)):
        return "[" + " ".join(fmt(x) for x in v) + "]"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    if not math.isfinite(v):
        return str(v)
    return f"{v:+.4f}" if abs(v) < 1e4 else f"{v:+.4e}"


def matches(filter_text: str | None, *names: str) -> bool:
    """Case-insensitive: a shell pattern (``*``, ``?``, ``[``) on the name, else a substring of
    any of ``names`` (name, label, kind, board)."""
    if not filter_text:
        return True
    f = filter_text.lower()
    if any(ch in f for ch in "*?["):
        return fnmatch.fnmatchcase(names[0].lower(), f)
    return any(f in n.lower() for n in names if n)


#: the terminal the monitor is drawn for: every line of its view fits this width
MONITOR_WIDTH = 80
#: the row layout (name, value, units, rate, then status and detail in what is left)
ROW_HEADER = f"{'name':28} {'value':>9} {'units':5} {'rate':>5} status / detail"


def clip(text: str, width: int) -> str:
    """``text`` cut to ``width`` columns, the cut marked with ``~``."""
    return text if len(text) <= width else text[:width - 1] + "~"


class _Reading(NamedTuple):
    """One input channel as the monitor shows it; ``rate``/``where`` None: the kind's default."""

    value: Any
    raw: str
    code: int = 0  # the status word as published (--json: "status_bits")
    rate: float | None = None
    where: str | None = None


def _read_rtd(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    value = wrap_angle(float(s.rtd_angle_rad[i]))  # the resolver's 0..2 pi shown in (-pi, pi]
    return _Reading(value, f"{int(s.rtd_counts[i])} cnt {math.degrees(value):+.1f} deg", int(s.rtd_status[i]))


def _read_adc(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    return _Reading(float(s.adc_value[i]), f"{s.adc_volts[i]:+.3f} V {int(s.adc_counts[i])} cnt",
                    int(s.adc_status[i]))


def _read_dac(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    return _Reading(float(s.dac_value[i]), f"{s.dac_volts[i]:+.3f} V {int(s.dac_counts[i])} cnt",
                    int(s.dac_status[i]))


def _read_pio(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    b = int(s.pio_port_bits[i])
    return _Reading(b, f"{b:08b}")


def _read_board(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    addr = int(s.board_last_error_addr[i])
    return _Reading(int(s.board_errors[i]), f"last error at A16 0x{addr:04X}" if addr else "",
                    int(s.board_status[i]), float("nan"), c.board)


def _read_link(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    raw = (f"bad {int(s.link_bad[i])} resyncs {int(s.link_resyncs[i])} "
           f"age {s.link_age_s[i] * 1e3:.0f} ms")
    return _Reading(int(s.link_records[i]), raw, int(s.link_status[i]), float(s.link_rate_hz[i]))


def _read_hc(s, c, i: int, dev_rate: dict[str, float]) -> _Reading:
    return _Reading([round(float(x), 3) for x in s.hc_axes[i]], f"btn 0x{int(s.hc_buttons[i]):X}",
                    rate=dev_rate.get(HC_DEVICE.get(c.name, ""), float("nan")))


#: how the monitor reads each kind of input entry (other kinds are not shown)
_READERS: dict[str, Callable[[Any, Any, int, dict[str, float]], _Reading]] = {
    "rtd": _read_rtd, "adc": _read_adc, "dac": _read_dac, "pio": _read_pio,
    "board": _read_board, "link": _read_link, "hc": _read_hc,
}


def _monitor_service(client, s, st, dev_rate: dict[str, float]) -> dict[str, Any]:
    """The service header of :func:`monitor_data`."""
    lay = client.layout
    hdr = client.header()
    return {
        "buffer": client.buffer.name, "rack": hdr.rack_name, "state": name_of(s.service_state, ServiceState),
        "frame": int(s.frame), "t_s": float(s.t_s), "fault_code": int(s.fault_code),
        "fault_name": name_of(s.fault_code, FAULT_CODE_NAMES),  # the number stays in fault_code
        "outputs_enabled": bool(s.outputs_enabled), "brakes_released": bool(s.brakes_released),
        "watchdog_tripped": bool(s.watchdog_tripped), "command_heartbeat": int(s.command_heartbeat),
        "command_age_s": float(s.command_age_s), "frame_rate_hz": float(st.rate_hz),
        "dropped_frames": int(st.dropped_frames), "overruns": int(st.overruns),
        "devices": {g: {"rate_hz": dev_rate[g], "errors": int(st.device_errors[lay.slot("device", g)])}
                    for g in DEVICE_GROUPS if int(st.device_samples[lay.slot("device", g)])},
    }


def _monitor_row(s, c, dev_rate: dict[str, float]) -> dict[str, Any] | None:
    """One input entry of :func:`monitor_data` (None: a kind the monitor does not show)."""
    read = _READERS.get(c.kind)
    if read is None:
        return None
    r = read(s, c, c.slot, dev_rate)
    where = f"{c.board}/{c.channel}" if c.channel >= 0 else c.board
    rate = dev_rate.get(KIND_DEVICE.get(c.kind, ""), float("nan"))
    return {"name": c.name, "kind": c.kind, "value": r.value, "units": entry_units(c), "raw": r.raw,
            "status": entry_status(s, c) or "-", "status_bits": r.code,
            "rate_hz": rate if r.rate is None else r.rate, "where": where if r.where is None else r.where,
            "spare": bool(c.spare)}


def _monitor_ft_rows(s, filter_text: str | None, dev_rate: dict[str, float]) -> list[dict[str, Any]]:
    """The F/T sensor's force and torque rows of :func:`monitor_data`."""
    return [{"name": name, "kind": "ft", "value": [round(float(x), 3) for x in s[name]],
             "units": units, "raw": f"status 0x{int(s.ft_status):X} t {s.ft_t_s:.3f} s",
             "status": status_text("ft", int(s.ft_status)), "status_bits": int(s.ft_status),
             "rate_hz": dev_rate["ft"], "where": "sio", "spare": False}
            for name, units in (("ft_force_n", "N"), ("ft_torque_nm", "N*m"))
            if matches(filter_text, name, "ft force torque")]


def monitor_data(client, filter_text: str | None = None, messages: int = 5) -> dict[str, Any]:
    """The monitor's snapshot as data: the service header, one dict per input channel
    (name, kind, value, units, raw, status, rate_hz, where, spare) and the last messages.
    ``pfma monitor --once --json`` prints it; :func:`monitor_lines` draws it."""
    s = client.read_inputs()
    st = client.read_stats()
    lay = client.layout
    dev_rate = {g: float(st.device_rate_hz[lay.slot("device", g)]) for g in DEVICE_GROUPS}
    out = _monitor_service(client, s, st, dev_rate)
    rows = [_monitor_row(s, c, dev_rate) for c in lay.channels
            if c.area == "inputs" and matches(filter_text, c.name, c.label, c.kind, c.board)]
    out["channels"] = [r for r in rows if r is not None] + _monitor_ft_rows(s, filter_text, dev_rate)
    out["messages"] = [{"t_s": float(m.t_s), "queue": m.queue, "seq": int(m.seq), "severity": m.severity.name,
                        "source": m.source, "code": int(m.code), "text": m.text}
                       for m in (client.messages()[-messages:] if messages else [])]
    return out


def monitor_header(d: dict[str, Any], width: int = MONITOR_WIDTH) -> list[str]:
    """The service's state in lines of at most ``width`` columns."""
    import textwrap
    rates = "  ".join(f"{g} {v['rate_hz']:.0f}/{v['errors']}" for g, v in d["devices"].items())
    unknown = d["fault_code"] == FAULT_DAC_UNREACHABLE  # the DAC does not answer (docs/safety.md)
    lines = [
        f"pfma monitor  buffer {d['buffer']}  rack {d['rack']}  state {d['state']}",
        *(["OUTPUTS NOT KNOWN SAFE: the DAC does not answer; press the hardware E-stop"]
          if unknown else []),
        f"frame {d['frame']}  t {d['t_s']:.3f} s  fault "
        + (f"{d['fault_name']} ({d['fault_code']})" if d["fault_code"] else "none"),
        f"outputs {'UNKNOWN' if unknown else 'ENABLED' if d['outputs_enabled'] else 'off'}  "
        f"brakes {'released' if d['brakes_released'] else 'set'}  "
        f"watchdog {'TRIPPED' if d['watchdog_tripped'] else 'ok'}",
        f"heartbeat {d['command_heartbeat']} (age {d['command_age_s'] * 1e3:.1f} ms)  "
        f"frames {d['frame_rate_hz']:.1f} Hz  dropped {d['dropped_frames']}  overruns {d['overruns']}",
    ]
    lines += textwrap.wrap("device Hz/errors: " + rates, width) if rates else []
    return [clip(x, width) for x in lines]


def monitor_row(r: dict[str, Any], width: int = MONITOR_WIDTH) -> str:
    """One channel in ``width`` columns: name, value, units, rate, status, detail."""
    v = r["value"]
    if isinstance(v, list):  # a vector (hand-controller axes, F/T): the detail column shows it
        vec = "[" + " ".join(f"{x:+.2f}" for x in v) + "]"
        val, detail = "", (f"{vec} {r['raw']}" if r["kind"] == "ft" else f"{r['raw']} {vec}")
    elif r["kind"] == "pio":
        val, detail = f"0x{v:02X}", r["raw"]
    else:
        val, detail = fmt(v), r["raw"]
    if r["kind"] not in ("board", "link", "ft", "hc"):
        detail = f"{r['where']} {detail}"
    rate = "" if math.isnan(r["rate_hz"]) else f"{r['rate_hz']:.1f}"
    name = r["name"] + (" (spare)" if r["spare"] else "")
    return clip(f"{name:28} {val:>9} {r['units']:5} {rate:>5} {r['status']} {detail}".rstrip(), width)


def monitor_lines(client, filter_text: str | None = None, messages: int = 5,
                  width: int = MONITOR_WIDTH) -> list[str]:
    """Every channel of the input area, one line each of at most ``width`` columns, with a
    header, the column names and the last messages (``pfma monitor --once``)."""
    d = monitor_data(client, filter_text, messages)
    rows = [monitor_row(r, width) for r in d["channels"]] or [f"(no channel matches {filter_text!r})"]
    out = monitor_header(d, width) + ["", clip(ROW_HEADER, width)] + rows
    if d["messages"]:
        out += ["", "messages:"] + [clip("  " + message_text(m), width) for m in d["messages"]]
    return out


def message_text(m: dict[str, Any]) -> str:
    """``12.345 INFO service: armed``: a message with its queue's name (the number in its
    ``source`` field says nothing: every writer posts 0)."""
    return f"{m['t_s']:.3f} {m['severity']} {m['queue'].removesuffix('_messages')}: {m['text']}"


def monitor_screen(d: dict[str, Any], page: int, height: int, width: int = MONITOR_WIDTH,
                   messages: int = 3) -> tuple[list[str], int]:
    """The live monitor's screen: at most ``height`` lines of at most ``width`` columns.

    The header and the column names stay at the top, the last ``messages`` messages and a
    footer at the bottom; the channel rows between them are shown one page at a time.
    Returns the lines and the number of pages (``page`` is taken modulo it).
    """
    head = monitor_header(d, width) + [clip(ROW_HEADER, width)]
    msgs = [clip("  " + message_text(m), width) for m in d["messages"][-messages:]] if messages else []
    rows = [monitor_row(r, width) for r in d["channels"]] or ["(no channel matches the filter)"]
    room = max(1, height - len(head) - len(msgs) - 1)
    pages = max(1, math.ceil(len(rows) / room))
    page %= pages
    body = rows[page * room:(page + 1) * room]
    footer = clip(f"-- page {page + 1}/{pages}, rows {page * room + 1}-{page * room + len(body)} of "
                  f"{len(rows)}  space/n next  p previous  q quit --", width)
    return head + body + [""] * (room - len(body)) + msgs + [footer], pages


# ---------------------------------------------------------------------------------- watch
Getter = Callable[[Any], Any]
_INDEXED = re.compile(r"^(\w+)\[(\d+)\]$")


class Signal(NamedTuple):
    """One signal ``pfma watch`` follows: ``get(snapshot)`` its value (an angle already in
    (-pi, pi]), ``status(snapshot)`` its status by name (None: it has none), ``name(value)``
    an enumerated field's value by name (None: a number)."""

    label: str
    get: Getter
    units: str
    status: Callable[[Any], str] | None = None
    name: Callable[[Any], str | None] | None = None


def _angle(get: Getter) -> Getter:
    def wrapped(s):
        v = get(s)
        return np.array([wrap_angle(x) for x in np.ravel(v)]).reshape(np.shape(v)) if np.ndim(v) else wrap_angle(v)
    return wrapped


def resolve_signals(layout, names: list[str]) -> list[Signal]:
    """A :class:`Signal` for each name: a rack channel / board / link / hand controller, an
    input-area field (``ft_force_n``) or one element (``ft_force_n[2]``).

    :raises PfmaError: for an unknown name, with the closest known ones
    """
    fields = {f.name: f for f in layout.fields if f.area == "inputs"}
    channels = {c.name: c for c in layout.channels if c.area == "inputs"}
    out = []
    for name in names:
        if name in channels:
            c = channels[name]
            status = None if c.kind == "pio" else (lambda s, e=c: entry_status(s, e) or "-")
            out.append(Signal(name, lambda s, e=c: entry_value(s, e), entry_units(c), status))
            continue
        m = _INDEXED.match(name)
        base, idx = (m.group(1), int(m.group(2))) if m else (name, None)
        if base in fields:
            f = fields[base]
            if idx is not None:
                n_el = int(np.prod(f.shape)) if f.shape else 1
                if not f.shape or idx >= f.shape[0]:
                    raise PfmaError(f"watch: {name}: field {base} has {n_el} element(s)")
                get = lambda s, b=base, i=idx: s[b][i]  # noqa: E731
            else:
                get = lambda s, b=base: s[b]  # noqa: E731
            if f.units == "rad":
                get = _angle(get)
            enum_name = (lambda v, b=base: field_text(b, v)) if base in FIELD_NAMES else None
            out.append(Signal(name, get, "" if enum_name else f.units, None, enum_name))
            continue
        raise PfmaError(f"watch: no channel or input field {name!r}"
                        + (did_you_mean(name, list(channels) + list(fields), n=4, cutoff=0.5)
                           or "; `pfma channels` lists the rack's channels"))
    return out


def watch_line(snapshot, signals: list[Signal]) -> str:
    """``t=12.3456 s  elbow_pitch_angle=-1.5708 rad [ok]  service_state=ARMED (2)  ...`` for
    one snapshot: each channel's status in brackets beside its value."""
    parts = [f"t={snapshot.t_s:.4f} s"]
    for sig in signals:
        v = sig.get(snapshot)
        shown = (sig.name(v) if sig.name is not None else None) or fmt(v)
        text = f"{sig.label}={shown}" + (f" {sig.units}" if sig.units else "")
        if sig.status is not None:
            text += f" [{sig.status(snapshot)}]"
        parts.append(text)
    return "  ".join(parts)


def watch_record(snapshot, signals: list[Signal]) -> dict[str, Any]:
    """One sample as data (``pfma watch --json``, one JSON line each): ``t_s``, ``frame``,
    ``values`` by signal (numbers; angles in (-pi, pi]) and their ``units``; ``status`` by
    signal for the channels that have one, ``names`` for the enumerated fields."""
    values = {sig.label: sig.get(snapshot) for sig in signals}
    out: dict[str, Any] = {"t_s": float(snapshot.t_s), "frame": int(snapshot.frame), "values": values,
                           "units": {sig.label: sig.units for sig in signals}}
    status = {sig.label: sig.status(snapshot) for sig in signals if sig.status is not None}
    if status:
        out["status"] = status
    names = {sig.label: sig.name(values[sig.label]) for sig in signals if sig.name is not None}
    if names:
        out["names"] = names
    return out
