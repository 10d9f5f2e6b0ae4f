"""Text views of the buffer for ``pfma monitor`` (every channel) and ``pfma watch`` (a few).

Pure functions of a :class:`bit3.client.Client`; the CLI modules only loop, pace
and redraw.
"""

from __future__ import annotations

import fnmatch
import math
import re
from typing import Any, Callable

import numpy as np

from bit3.layout import (
    BOARD_FAULT, BOARD_INIT, BOARD_OK, CHANNEL_BUS_ERROR, DAC_CLIPPED, DAC_FORCED_SAFE, DEVICE_GROUPS, LINK_FAULT,
    LINK_OPEN, LINK_STALE, LINK_SYNCED, RTD_LOSS_OF_SIGNAL, RTD_NO_REFERENCE, ServiceState,
)
from pfma.errors import PfmaError, did_you_mean

RTD_BITS = {RTD_LOSS_OF_SIGNAL: "LOS", RTD_NO_REFERENCE: "NOREF", CHANNEL_BUS_ERROR: "BUSERR"}
ADC_BITS = {CHANNEL_BUS_ERROR: "BUSERR"}
DAC_BITS = {DAC_CLIPPED: "CLIPPED", DAC_FORCED_SAFE: "SAFE"}
BOARD_BITS = {BOARD_OK: "OK", BOARD_INIT: "INIT", BOARD_FAULT: "FAULT"}
LINK_BITS = {LINK_OPEN: "OPEN", LINK_SYNCED: "SYNCED", LINK_FAULT: "FAULT", LINK_STALE: "STALE"}
#: which device group's measured rate applies to a channel kind
KIND_DEVICE = {"rtd": "rtd", "adc": "adc", "dac": "dac", "pio": "pio"}
HC_DEVICE = {"cae": "adc", "crl": "crl", "hid": "hid"}


def bits(value: int, names: dict[int, str]) -> str:
    if not value:
        return "-"
    out = [n for b, n in names.items() if value & b]
    rest = value & ~sum(names)
    if rest:
        out.append(f"0x{rest:X}")
    return "|".join(out)


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


def monitor_lines(client, filter_text: str | None = None, messages: int = 5) -> list[str]:
    """Every channel of the input area, one line each, with a header and the last messages."""
    s = client.read_inputs()
    st = client.read_stats()
    lay = client.layout
    dev_rate = {g: float(st.device_rate_hz[lay.slot("device", g)]) for g in DEVICE_GROUPS}
    hdr = client.header()
    state = ServiceState(s.service_state).name
    out = [
        f"pfma monitor  buffer {client.buffer.name}  rack {hdr.rack_name}  state {state}  "
        f"frame {s.frame}  t {s.t_s:.3f} s  fault {s.fault_code}",
        f"outputs {'ENABLED' if s.outputs_enabled else 'off'}  brakes {'released' if s.brakes_released else 'set'}  "
        f"watchdog {'TRIPPED' if s.watchdog_tripped else 'ok'}  command heartbeat {s.command_heartbeat} "
        f"(age {s.command_age_s * 1e3:.1f} ms)  frames {st.rate_hz:.1f} Hz  dropped {st.dropped_frames}  "
        f"overruns {st.overruns}",
        "rates: " + "  ".join(f"{g} {dev_rate[g]:.1f} Hz/{int(st.device_errors[lay.slot('device', g)])} err"
                              for g in DEVICE_GROUPS if int(st.device_samples[lay.slot('device', g)])),
        "",
        f"{'name':30s} {'kind':5s} {'value':>14s} {'units':6s} {'raw':30s} {'status':14s} {'rate Hz':>8s}  where",
    ]
    rows = []
    for c in lay.channels:
        if c.area != "inputs" or not matches(filter_text, c.name, c.label, c.kind, c.board):
            continue
        i = c.slot
        where = f"{c.board}/{c.channel}" if c.channel >= 0 else c.board
        rate = dev_rate.get(KIND_DEVICE.get(c.kind, ""), float("nan"))
        if c.kind == "rtd":
            val, raw = fmt(s.rtd_angle_rad[i]), f"{int(s.rtd_counts[i])} counts {math.degrees(s.rtd_angle_rad[i]):.2f} deg"
            stat = bits(int(s.rtd_status[i]), RTD_BITS)
        elif c.kind == "adc":
            val, raw = fmt(s.adc_value[i]), f"{s.adc_volts[i]:+.4f} V {int(s.adc_counts[i])} counts"
            stat = bits(int(s.adc_status[i]), ADC_BITS)
        elif c.kind == "dac":
            val, raw = fmt(s.dac_value[i]), f"{s.dac_volts[i]:+.4f} V {int(s.dac_counts[i])} counts"
            stat = bits(int(s.dac_status[i]), DAC_BITS)
        elif c.kind == "pio":
            b = int(s.pio_port_bits[i])
            val, raw, stat = f"0x{b:02X}", f"{b:08b}", "-"
        elif c.kind == "board":
            val = str(int(s.board_errors[i]))
            addr = int(s.board_last_error_addr[i])
            raw = f"errors; last at A16 0x{addr:04X}" if addr else "errors"
            stat, rate, where = bits(int(s.board_status[i]), BOARD_BITS), float("nan"), c.board
        elif c.kind == "link":
            val = fmt(s.link_records[i])
            raw = (f"bad {int(s.link_bad[i])} resyncs {int(s.link_resyncs[i])} "
                   f"age {s.link_age_s[i] * 1e3:.0f} ms")
            stat, rate = bits(int(s.link_status[i]), LINK_BITS), float(s.link_rate_hz[i])
        elif c.kind == "hc":
            val = fmt(np.round(s.hc_axes[i], 3))
            raw = f"buttons 0x{int(s.hc_buttons[i]):X}"
            flags = [n for n, on in (("VALID", s.hc_valid[i]), ("DEADMAN", s.hc_deadman[i]),
                                     ("FAULT", s.hc_fault[i])) if on]
            stat, rate = "|".join(flags) or "-", dev_rate.get(HC_DEVICE.get(c.name, ""), float("nan"))
        else:
            continue
        units = "recs" if c.kind == "link" else ("err" if c.kind == "board" else c.units)
        rate_s = "" if math.isnan(rate) else f"{rate:.1f}"
        label = c.name + (" (spare)" if c.spare else "")
        rows.append(f"{label:30s} {c.kind:5s} {val:>14s} {units:6s} {raw:30s} {stat:14s} {rate_s:>8s}  {where}")
    for name, units in (("ft_force_n", "N"), ("ft_torque_nm", "N*m")):
        if matches(filter_text, name, "ft force torque"):
            rows.append(f"{name:30s} {'ft':5s} {fmt(np.round(s[name], 3)):>14s} {units:6s} "
                        f"{'status 0x%X t %.3f s' % (int(s.ft_status), s.ft_t_s):30s} {'-':14s} "
                        f"{dev_rate['ft']:>8.1f}  sio")
    out += rows if rows else [f"(no channel matches {filter_text!r})"]
    if messages:
        msgs = client.messages()[-messages:]
        if msgs:
            out += ["", "messages:"] + [f"  {m.format()}" for m in msgs]
    return out


# ---------------------------------------------------------------------------------- watch
Getter = Callable[[Any], Any]
_INDEXED = re.compile(r"^(\w+)\[(\d+)\]$")


def resolve_signals(layout, names: list[str]) -> list[tuple[str, Getter, str]]:
    """``(label, getter(snapshot), units)`` for each name: a rack channel / board / link /
    hand controller, an input-area field (``ft_force_n``) or one element (``ft_force_n[2]``).

    :raises PfmaError: for an unknown name, with the closest known ones
    """
    fields = {f.name: f for f in layout.fields if f.area == "inputs"}
    channels = {c.name: c for c in layout.channels if c.area == "inputs"}
    out = []
    for name in names:
        if name in channels:
            c = channels[name]
            units = {"board": "err", "link": "recs"}.get(c.kind, c.units)
            out.append((name, lambda s, n=name: s.value(n), units))
            continue
        m = _INDEXED.match(name)
        base, idx = (m.group(1), int(m.group(2))) if m else (name, None)
        if base in fields:
            f = fields[base]
            if idx is not None:
                n_el = int(np.prod(f.shape)) if f.shape else 1
                if not f.shape or idx >= f.shape[0]:
                    raise PfmaError(f"watch: {name}: field {base} has {n_el} element(s)")
                out.append((name, lambda s, b=base, i=idx: s[b][i], f.units))
            else:
                out.append((name, lambda s, b=base: s[b], f.units))
            continue
        raise PfmaError(f"watch: no channel or input field {name!r}"
                        + (did_you_mean(name, list(channels) + list(fields), n=4, cutoff=0.5)
                           or "; `pfma channels` lists the rack's channels"))
    return out


def watch_line(snapshot, signals: list[tuple[str, Getter, str]]) -> str:
    """``t=12.3456 s  elbow_pitch_angle=-1.5708 rad  ...`` for one snapshot."""
    parts = [f"t={snapshot.t_s:.4f} s"]
    for label, get, units in signals:
        parts.append(f"{label}={fmt(get(snapshot))}" + (f" {units}" if units else ""))
    return "  ".join(parts)
