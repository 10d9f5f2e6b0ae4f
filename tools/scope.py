"""The scope: signals captured at the native frame rate around a trigger, saved as MCAP.

A signal is a rack channel (its engineering value), an inputs-area field or one element
of one (``ft_force_n[2]``). :class:`ScopeCapture` looks at every published frame, keeps
the last ``pre_s`` seconds in a ring and, when the trigger condition becomes true (an
edge), captures ``post_s`` more seconds; :func:`capture_live` feeds it from a live
service. :func:`save` writes one JSON channel ``/pfma/scope`` ({t_s, frame, <signal>:
value}) that Foxglove plots; :func:`load` and :func:`render` read it back as a table and
a text plot. The verb is ``pfma scope`` (:mod:`tools.cli.scope`).
"""

from __future__ import annotations

import json
import math
import re
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from bit3.layout import Layout
from pfma.errors import did_you_mean

_ANSI = re.compile(r"\x1b\[[0-9;]*m")  # plotext ends lines with a colour reset even without colour

SCOPE_TOPIC = "/pfma/scope"
_TRIG = re.compile(r"^\s*([A-Za-z_][\w\[\]]*)\s*([<>])\s*([-+0-9.eE]+)\s*$")
_ELEM = re.compile(r"^([A-Za-z_]\w*)\[(\d+)\]$")


@dataclass(frozen=True)
class SignalRef:
    """Where one scope signal lives in the inputs record."""

    name: str
    field: str
    index: int | None
    units: str

    def get(self, record: np.ndarray) -> float:
        v = record[self.field]
        return float(v if self.index is None else v[self.index])


def resolve(layout: Layout, name: str) -> SignalRef:
    """A rack channel, a scalar inputs field, or ``field[i]`` -> :class:`SignalRef`.

    :raises KeyError: naming the signal and where to look
    """
    from bit3.client import PRIMARY_FIELD
    try:
        c = layout.channel(name, "inputs")
        f = PRIMARY_FIELD.get(c.kind, c.fields[0][0])
        idx = next(i for fl, i, _ in c.fields if fl == f)
        spec = layout.field(f, "inputs")
        if len(spec.shape) > 1:
            raise KeyError(f"scope signal {name!r} is a vector ({f}); give one element")
        return SignalRef(name, f, idx, c.units or spec.units)
    except KeyError:
        pass
    m = _ELEM.match(name)
    fname, idx = (m.group(1), int(m.group(2))) if m else (name, None)
    try:
        spec = layout.field(fname, "inputs")
    except KeyError:
        known = [c.name for c in layout.channels if c.area == "inputs"] + [f.name for f in layout.fields
                                                                            if f.area == "inputs"]
        raise KeyError(f"scope: no rack channel or inputs field {name!r}"
                       + (did_you_mean(name, known) or " (see pfma layout --channels)")) from None
    if spec.shape and idx is None:
        raise KeyError(f"scope: field {fname} has shape {list(spec.shape)}; give an element, e.g. {fname}[0]")
    if len(spec.shape) > 1 or (idx is not None and not spec.shape):
        raise KeyError(f"scope: {name!r}: use a scalar field or one element of a 1-d field")
    if idx is not None and idx >= spec.shape[0]:
        raise KeyError(f"scope: {name!r}: index out of range (shape {list(spec.shape)})")
    return SignalRef(name, fname, idx, spec.units)


@dataclass
class Trigger:
    signal: SignalRef
    op: str
    level: float

    def test(self, v: float) -> bool:
        return v > self.level if self.op == ">" else v < self.level


def parse_trigger(layout: Layout, text: str) -> Trigger:
    m = _TRIG.match(text)
    if not m:
        raise ValueError(f"scope: trigger {text!r}: write SIGNAL>VALUE or SIGNAL<VALUE")
    return Trigger(resolve(layout, m.group(1)), m.group(2), float(m.group(3)))


@dataclass
class Capture:
    """A finished (or running) capture: rows of (t_s, frame, values...)."""

    signals: list[str]
    units: list[str]
    t_s: list[float] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    values: list[list[float]] = field(default_factory=list)
    trigger: str = ""
    trigger_t_s: float = math.nan
    trigger_frame: int = -1
    pre_s: float = 0.0
    post_s: float = 0.0

    @property
    def trigger_index(self) -> int:
        return self.frames.index(self.trigger_frame) if self.trigger_frame in self.frames else -1


class ScopeCapture:
    """Feed it every inputs record; it keeps a pre-trigger ring and completes after ``post_s``."""

    def __init__(self, layout: Layout, signals: list[str], trigger: str | None = None,
                 pre_s: float = 0.1, post_s: float = 0.5) -> None:
        self.refs = [resolve(layout, s) for s in signals]
        if not self.refs:
            raise ValueError("scope: name at least one signal")
        self.trigger = parse_trigger(layout, trigger) if trigger else None
        self.pre_s, self.post_s = max(0.0, pre_s), max(0.0, post_s)
        self.capture = Capture([r.name for r in self.refs], [r.units for r in self.refs],
                               trigger=trigger or "", pre_s=self.pre_s, post_s=self.post_s)
        self._ring: deque = deque()
        self._prev: bool | None = None
        self.triggered = False
        self.done = False
        self._last_frame = -1

    def feed(self, record: np.ndarray) -> bool:
        """One frame; returns True once the capture is complete."""
        if self.done:
            return True
        frame = int(record["frame"])
        if frame == self._last_frame:
            return False
        self._last_frame = frame
        t = float(record["t_s"])
        row = (t, frame, [r.get(record) for r in self.refs])
        cap = self.capture
        if not self.triggered:
            fire = True
            if self.trigger is not None:
                now = self.trigger.test(self.trigger.signal.get(record))
                fire = now and self._prev is False
                self._prev = now
            if fire:
                self.triggered = True
                cap.trigger_t_s, cap.trigger_frame = t, frame
                for rt, rf, rv in self._ring:
                    if rt >= t - self.pre_s - 1e-12:
                        cap.t_s.append(rt), cap.frames.append(rf), cap.values.append(rv)
                self._ring.clear()
            else:
                self._ring.append(row)
                while self._ring and self._ring[0][0] < t - self.pre_s - 1e-12:
                    self._ring.popleft()
                return False
        cap.t_s.append(t), cap.frames.append(frame), cap.values.append(row[2])
        if t >= cap.trigger_t_s + self.post_s - 1e-12:
            self.done = True
        return self.done


def save(cap: Capture, path: str | Path, *, epoch_offset_ns: int, meta: dict[str, str] | None = None) -> int:
    """Write a capture as MCAP (JSON channel ``/pfma/scope``); returns messages written."""
    from mcap.writer import CompressionType, Writer
    schema = {"type": "object", "title": SCOPE_TOPIC, "properties": {
        "t_s": {"type": "number"}, "frame": {"type": "integer"},
        **{s: {"type": "number", "description": u} for s, u in zip(cap.signals, cap.units)}}}
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="pfma", library="pfma-scope 1")
        sid = w.register_schema("pfma.scope", "jsonschema", json.dumps(schema).encode())
        cid = w.register_channel(SCOPE_TOPIC, "json", sid, {"signals": ",".join(cap.signals)})
        w.add_metadata("pfma.scope", {
            "signals": json.dumps(cap.signals), "units": json.dumps(cap.units), "trigger": cap.trigger,
            "trigger_t_s": repr(cap.trigger_t_s), "trigger_frame": str(cap.trigger_frame),
            "pre_s": repr(cap.pre_s), "post_s": repr(cap.post_s),
            "epoch_offset_ns": str(epoch_offset_ns), **(meta or {})})
        for i, (t, fr, vals) in enumerate(zip(cap.t_s, cap.frames, cap.values)):
            d = {s: (v if math.isfinite(v) else None) for s, v in zip(cap.signals, vals)}
            d.update({"t_s": t, "frame": fr})  # a signal named frame/t_s holds the same value
            ns = epoch_offset_ns + int(round(t * 1e9))
            w.add_message(cid, ns, json.dumps(d).encode(), ns, i)
        w.finish()
    return len(cap.t_s)


def load(path: str | Path) -> Capture:
    """Read a capture written by :func:`save` (or any MCAP with a ``/pfma/scope`` channel)."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        r = make_reader(f)
        meta = {m.name: dict(m.metadata) for m in r.iter_metadata()}.get("pfma.scope", {})
        rows = [json.loads(m.data) for _, _, m in r.iter_messages(topics=[SCOPE_TOPIC], log_time_order=True)]
    signals = json.loads(meta["signals"]) if "signals" in meta else \
        [k for k in (rows[0] if rows else {}) if k not in ("t_s", "frame")]
    cap = Capture(signals, json.loads(meta.get("units", "[]")) or [""] * len(signals),
                  trigger=meta.get("trigger", ""), trigger_t_s=float(meta.get("trigger_t_s", "nan")),
                  trigger_frame=int(meta.get("trigger_frame", "-1")), pre_s=float(meta.get("pre_s", "0")),
                  post_s=float(meta.get("post_s", "0")))
    for d in rows:
        cap.t_s.append(float(d["t_s"])), cap.frames.append(int(d["frame"]))
        cap.values.append([math.nan if d.get(s) is None else d[s] for s in signals])
    return cap


def _signal_arrays(cap: Capture, t0: float) -> tuple[np.ndarray, np.ndarray]:
    """Time relative to ``t0`` in ms, and the values (NaN where a sample had none)."""
    return (np.array(cap.t_s, dtype=float) - t0) * 1e3, np.array(cap.values, dtype=float).reshape(len(cap.t_s), -1)


def text_plots(cap: Capture, t0: float, width: int = 72, height: int = 12) -> str:
    """One terminal plot per signal (plotext, braille dots, no colour), the trigger a vertical
    line at t = 0."""
    import plotext as plt

    t_ms, arr = _signal_arrays(cap, t0)
    blocks = []
    for j, name in enumerate(cap.signals):
        ok = np.isfinite(arr[:, j])
        if not ok.any():
            blocks.append(f"{name}: no samples")
            continue
        unit = cap.units[j] if j < len(cap.units) else ""
        plt.clear_figure()
        plt.plotsize(width, height)
        plt.theme("clear")
        plt.plot(t_ms[ok].tolist(), arr[ok, j].tolist(), marker="braille")
        if math.isfinite(cap.trigger_t_s):
            plt.vline(0.0)
        plt.title(f"{name} [{unit}]")
        plt.xlabel("t - trigger (ms)" if math.isfinite(cap.trigger_t_s) else "t (ms)")
        blocks.append(_ANSI.sub("", plt.build()).rstrip())
    return "\n\n".join(blocks)


def save_png(cap: Capture, path: str | Path) -> Path:
    """The capture as a PNG (matplotlib, Agg): one panel per signal with its units, the trigger
    marked; written beside the capture's MCAP by ``pfma scope``."""
    from matplotlib.figure import Figure

    n = max(1, len(cap.signals))
    t0 = cap.trigger_t_s if math.isfinite(cap.trigger_t_s) else (cap.t_s[0] if cap.t_s else 0.0)
    t_ms, arr = _signal_arrays(cap, t0)
    fig = Figure(figsize=(8, 2.2 * n), dpi=100)
    axes = fig.subplots(n, 1, squeeze=False, sharex=True)[:, 0]
    for j, ax in enumerate(axes):
        if j < len(cap.signals):
            unit = cap.units[j] if j < len(cap.units) else ""
            ax.plot(t_ms, arr[:, j], "-", lw=1.0, color="tab:blue")
            ax.set_ylabel(f"{cap.signals[j]}\n({unit})", fontsize=8)
        if math.isfinite(cap.trigger_t_s):
            ax.axvline(0.0, color="tab:red", lw=0.8, ls="--", label="trigger")
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("t - trigger (ms)" if math.isfinite(cap.trigger_t_s) else "t (ms)", fontsize=8)
    fig.suptitle(f"pfma scope: {len(cap.t_s)} samples, trigger {cap.trigger or '(none: immediate)'}", fontsize=10)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, format="png")
    return p


def render(cap: Capture, rows: int = 20, width: int = 72, height: int = 12) -> str:
    """A table (decimated to ``rows``) and one terminal plot per signal; t relative to the trigger."""
    out = []
    n = len(cap.t_s)
    t0 = cap.trigger_t_s if math.isfinite(cap.trigger_t_s) else (cap.t_s[0] if n else 0.0)
    out.append(f"{n} samples, trigger {cap.trigger or '(none: immediate)'} at frame {cap.trigger_frame}, "
               f"pre {cap.pre_s:g} s, post {cap.post_s:g} s")
    if not n:
        return "\n".join(out)
    out.append(f"{'t-trig [ms]':>12} {'frame':>8} " + " ".join(f"{s[:16]:>16}" for s in cap.signals))
    step = max(1, n // rows)
    idx = list(range(0, n, step))
    ti = cap.trigger_index
    if ti >= 0 and ti not in idx:
        idx = sorted(set(idx) | {ti})
    for i in idx:
        mark = "*" if i == ti else " "
        out.append(f"{(cap.t_s[i] - t0) * 1e3:11.2f}{mark} {cap.frames[i]:8d} "
                   + " ".join(f"{v:16.6g}" for v in cap.values[i]))
    out += ["", text_plots(cap, t0, width=width, height=height)]
    return "\n".join(out)




def capture_live(client, sc: ScopeCapture, *, trigger: str | None, timeout_s: float | None, t_start: float,
                 stop: Callable[[], bool], say: Callable[[str], None]) -> str:
    """Feed ``sc`` every frame the service publishes until it completes.

    :returns: ``"done"``, ``"timeout"`` (no trigger within ``timeout_s`` of ``t_start``)
        or ``"stopped"`` (``stop()`` turned true first)
    """
    last_note = time.monotonic()
    while not stop():
        if client.changed("inputs"):
            snap = client.read_inputs()
            if snap.seq and sc.feed(snap.record):  # seq 0: nothing published yet
                break
            continue
        now = time.monotonic()
        if timeout_s is not None and now - t_start > timeout_s:
            return "timeout"
        if now - last_note > 10:
            say(f"still waiting for the trigger {trigger} (frame {client.read_inputs().frame})")
            last_note = now
        time.sleep(0.0003)
    return "done" if sc.done else "stopped"
