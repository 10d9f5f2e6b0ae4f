"""The JSON channels Foxglove plots: their schemas, their encoders, the recorder's counters.

One channel per device group (``/pfma/joints``, ``/pfma/adc``, ...), written when that
group's sample time changes; :class:`RecorderCounters` is what ``/pfma/recorder`` and
the summary metadata carry.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import orjson

from bit3.buffer import MESSAGE_DTYPE  # noqa: F401  (documented message fields)
from bit3.layout import HC_AXES, Layout, ServiceState
from drivers.pio.registers import decode_matrix_route

def _clean(x: Any) -> Any:
    """NaN/inf -> None (JSON has no NaN; Foxglove refuses it)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x


def _dumps(obj: dict) -> bytes:
    """Compact JSON; NaN and inf become null (orjson does that itself; the recorder encodes
    about a thousand of these a second, ~10x cheaper than the standard library's)."""
    try:
        return orjson.dumps(obj, option=orjson.OPT_SERIALIZE_NUMPY)
    except TypeError:  # a type orjson does not take: the standard library, cleaned
        return json.dumps(_clean(obj), separators=(",", ":"), default=_plain).encode()


def _plain(x: Any) -> Any:
    """numpy scalars and arrays as Python values (the fallback encoder's default)."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serializable: {type(x).__name__}")


# ----------------------------------------------------------------------------------------
# JSON topics: schemas and encoders


def _num(desc: str = "") -> dict:
    return {"type": "number", "description": desc} if desc else {"type": "number"}


def _int(desc: str = "") -> dict:
    return {"type": "integer", "description": desc} if desc else {"type": "integer"}


def _obj(props: dict, desc: str = "") -> dict:
    d = {"type": "object", "properties": props}
    if desc:
        d["description"] = desc
    return d


_HEAD = {"t_s": _num("sample time, service clock (s)"), "frame": _int("service minor frame")}

#: the device channels written when their group's sample time (an inputs field) changes:
#: (topic, sample-time field, :class:`_Topics` encoder name); the recorder and the live
#: Foxglove server (tools/foxglove.py) both go by it
DEVICE_TOPICS = (("/pfma/joints", "t_rtd_s", "joints"), ("/pfma/adc", "t_adc_s", "adc"),
                 ("/pfma/dac", "t_dac_s", "dac"), ("/pfma/ft", "ft_t_s", "ft"), ("/pfma/pio", "t_pio_s", "pio"))


def json_schema(topic: str, schema: dict) -> tuple[str, bytes]:
    """A JSON channel's schema as it is registered (MCAP and the live Foxglove server):
    ``(schema name, JSON Schema document)``, e.g. ``pfma.joints`` for ``/pfma/joints``."""
    doc = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": topic, **schema}
    return "pfma" + topic.replace("/", ".")[5:], json.dumps(doc).encode()


class _Topics:
    """Builds the JSON messages of one inputs snapshot (index arrays precomputed)."""

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        ch = [c for c in layout.channels if c.area == "inputs"]

        def group(kind: str) -> tuple[list[str], np.ndarray, list]:
            cs = [c for c in ch if c.kind == kind and not c.spare]
            return [c.name for c in cs], np.array([c.slot for c in cs], dtype=np.intp), cs

        self.g_rtd = group("rtd")
        self.g_adc = group("adc")
        self.g_dac = group("dac")
        self.g_pio = group("pio")
        self.g_board = group("board")
        self.g_link = group("link")
        self.g_hc = group("hc")

    # --- schemas ---
    def schemas(self) -> dict[str, dict]:
        lay = self.layout

        def per(cs, props):
            return {c.name: _obj(props(c), f"{c.label} [{c.units}]" + (f" ({c.board} ch {c.channel})"
                                                                         if c.channel >= 0 else ""))
                    for c in cs}
        s = {}
        s["/pfma/status"] = _obj({**_HEAD, "state": {"type": "string"},
                                  "service_state": _int("ServiceState"), "fault_code": _int(),
                                  "outputs_enabled": _int(), "brakes_released": _int(),
                                  "watchdog_tripped": _int(), "command_heartbeat": _int(),
                                  "command_age_s": _num("s")}, "service state, every frame")
        s["/pfma/joints"] = _obj({**_HEAD, **per(self.g_rtd[2], lambda c: {
            "angle_rad": _num("rad"), "counts": _int("RDC counts as the driver returns them (drivers.rtd.registers: counts_per_rev per turn)"),
            "status": _int("bits")})}, "resolvers (RTD), at their sample rate")
        s["/pfma/adc"] = _obj({**_HEAD, **per(self.g_adc[2], lambda c: {
            "counts": _int("raw 12-bit code"), "volts": _num("V"), "value": _num(c.units),
            "status": _int("bits")})}, "ADC channels: raw, volts, engineering value")
        s["/pfma/dac"] = _obj({**_HEAD, **per(self.g_dac[2], lambda c: {
            "counts": _int("12-bit code written"), "volts": _num("V"), "value": _num(c.units),
            "status": _int("bits")})}, "DAC channels as applied")
        xyz = _obj({"x": _num(), "y": _num(), "z": _num()})
        s["/pfma/ft"] = _obj({**_HEAD, "counts": {"type": "array", "items": _int()},
                              "force_n": xyz, "torque_nm": xyz, "status": _int("bits")},
                             "F/T sensor record (sensor frame)")
        s["/pfma/hand"] = _obj({**_HEAD, **{c.name: _obj({
            "axes": _obj({a: _num("-1..1") for a in HC_AXES}), "deadman": _int(), "valid": _int(),
            "fault": _int(), "buttons": _int(), "t_s": _num("s")}) for c in self.g_hc[2]}},
            "hand controllers")
        s["/pfma/pio"] = _obj({**_HEAD, "user_inputs": _int("16 bits"), "matrix_route": _int(),
                               "monitor_1_camera": _int("0 = blank"), "monitor_2_camera": _int("0 = blank"),
                               **{c.name: _int("8-bit port") for c in self.g_pio[2]}},
                              "PIA ports; the applied matrix switcher route and each monitor's camera "
                              "(docs/cameras.md)")
        s["/pfma/boards"] = _obj({**_HEAD, **{c.name: _obj({
            "status": _int("bits"), "errors": _int(), "last_error_addr": _int("A16"),
            "last_error_t_s": _num("s")}) for c in self.g_board[2]}}, "board status and errors")
        s["/pfma/links"] = _obj({**_HEAD, **{c.name: _obj({
            "status": _int("bits"), "records": _int(), "bad": _int(), "resyncs": _int(),
            "errors": _int(), "rate_hz": _num("Hz"), "age_s": _num("s")}) for c in self.g_link[2]}},
            "serial/USB link counters")
        cmd = [f for f in lay.fields if f.area == "commands"]
        s["/pfma/commands"] = _obj({f.name: ({"type": "array", "items": _num(f.units)} if f.shape
                                             else _num(f.units)) for f in cmd},
                                   "command area (controller), joint order: " + ", ".join(lay.joint_names))
        st = [f for f in lay.fields if f.area == "stats"]
        s["/pfma/stats"] = _obj({f.name: ({"type": "array", "items": _num(f.units)} if f.shape
                                          else _num(f.units)) for f in st}, "service statistics")
        s["/pfma/messages"] = _obj({"queue": {"type": "string"}, "seq": _int(), "t_s": _num("s"),
                                    "severity": {"type": "string"}, "code": _int(),
                                    "source": _int(), "text": {"type": "string"}}, "message queues")
        s["/pfma/recorder"] = _obj({k: {"type": ["number", "integer", "boolean", "string", "null"]}
                                    for k in RecorderCounters.__dataclass_fields__},
                                   "recorder counters (drops, per-topic counts)")
        return s

    # --- messages ---
    def status(self, r: np.ndarray, head: dict) -> dict:
        st = int(r["service_state"])
        try:
            name = ServiceState(st).name
        except ValueError:
            name = str(st)
        return {**head, "state": name, "service_state": st, "fault_code": int(r["fault_code"]),
                "outputs_enabled": int(r["outputs_enabled"]),
                "brakes_released": int(r["brakes_released"]),
                "watchdog_tripped": int(r["watchdog_tripped"]),
                "command_heartbeat": int(r["command_heartbeat"]),
                "command_age_s": float(r["command_age_s"])}

    @staticmethod
    def _per(names, cols: dict[str, list]) -> dict:
        keys = list(cols)
        vals = list(zip(*cols.values()))
        return {n: dict(zip(keys, v)) for n, v in zip(names, vals)}

    def joints(self, r, head) -> dict:
        n, s, _ = self.g_rtd
        return {**head, **self._per(n, {"angle_rad": r["rtd_angle_rad"][s].tolist(),
                                        "counts": r["rtd_counts"][s].tolist(),
                                        "status": r["rtd_status"][s].tolist()})}

    def adc(self, r, head) -> dict:
        n, s, _ = self.g_adc
        return {**head, **self._per(n, {"counts": r["adc_counts"][s].tolist(),
                                        "volts": r["adc_volts"][s].tolist(),
                                        "value": r["adc_value"][s].tolist(),
                                        "status": r["adc_status"][s].tolist()})}

    def dac(self, r, head) -> dict:
        n, s, _ = self.g_dac
        return {**head, **self._per(n, {"counts": r["dac_counts"][s].tolist(),
                                        "volts": r["dac_volts"][s].tolist(),
                                        "value": r["dac_value"][s].tolist(),
                                        "status": r["dac_status"][s].tolist()})}

    @staticmethod
    def ft(r, head) -> dict:
        f, t = r["ft_force_n"].tolist(), r["ft_torque_nm"].tolist()
        return {**head, "counts": r["ft_counts"].tolist(),
                "force_n": {"x": f[0], "y": f[1], "z": f[2]},
                "torque_nm": {"x": t[0], "y": t[1], "z": t[2]}, "status": int(r["ft_status"])}

    def hand(self, r, head) -> dict:
        n, s, _ = self.g_hc
        out = dict(head)
        axes = r["hc_axes"][s].tolist()
        for i, name in enumerate(n):
            k = int(s[i])
            out[name] = {"axes": dict(zip(HC_AXES, axes[i])), "deadman": int(r["hc_deadman"][k]),
                         "valid": int(r["hc_valid"][k]), "fault": int(r["hc_fault"][k]),
                         "buttons": int(r["hc_buttons"][k]), "t_s": float(r["hc_t_s"][k])}
        return out

    def pio(self, r, head) -> dict:
        n, s, _ = self.g_pio
        route = int(r["matrix_route"])
        m1, m2 = decode_matrix_route(route)
        return {**head, "user_inputs": int(r["pio_user_inputs"]), "matrix_route": route,
                "monitor_1_camera": m1, "monitor_2_camera": m2, **dict(zip(n, r["pio_port_bits"][s].tolist()))}

    def boards(self, r, head) -> dict:
        n, s, _ = self.g_board
        return {**head, **self._per(n, {"status": r["board_status"][s].tolist(),
                                        "errors": r["board_errors"][s].tolist(),
                                        "last_error_addr": r["board_last_error_addr"][s].tolist(),
                                        "last_error_t_s": r["board_last_error_t_s"][s].tolist()})}

    def links(self, r, head) -> dict:
        n, s, _ = self.g_link
        return {**head, **self._per(n, {"status": r["link_status"][s].tolist(),
                                        "records": r["link_records"][s].tolist(),
                                        "bad": r["link_bad"][s].tolist(),
                                        "resyncs": r["link_resyncs"][s].tolist(),
                                        "errors": r["link_errors"][s].tolist(),
                                        "rate_hz": r["link_rate_hz"][s].tolist(),
                                        "age_s": r["link_age_s"][s].tolist()})}

    def links_key(self, r) -> bytes:
        """What makes /pfma/links worth a message (counters and status; not the age)."""
        return (r["link_status"].tobytes() + r["link_records"].tobytes() + r["link_bad"].tobytes()
                + r["link_resyncs"].tobytes() + r["link_errors"].tobytes())

    def boards_key(self, r) -> bytes:
        return (r["board_status"].tobytes() + r["board_errors"].tobytes()
                + r["board_last_error_addr"].tobytes())


# ----------------------------------------------------------------------------------------
# counters


@dataclass
class RecorderCounters:
    """What the recorder saw; written to ``/pfma/recorder`` and the summary metadata."""

    frames_recorded: int = 0          #: inputs frames written (raw stream messages)
    first_frame: int = -1
    last_frame: int = -1
    recorder_missed: int = 0          #: publishes the recorder did not see (sequence jumps)
    service_skipped: int = 0          #: frame numbers the service itself skipped (its overruns)
    frame_gaps: int = 0               #: all missing frame numbers (= skipped + missed frames)
    republished: int = 0              #: publishes repeating the last frame number (e.g. STOPPED)
    sessions: int = 0                 #: service (re)attachments seen
    window_first_frame: int = -1      #: stats window [first, last) (frame numbers)
    window_last_frame: int = -1
    window_service_frames: int = 0    #: frames the service ran in the window (stats.frames)
    window_recorded: int = 0          #: frames recorded in the same window
    window_service_dropped: int = 0   #: stats.dropped_frames over the window
    messages_missed: int = 0          #: message-queue entries overwritten before being read
    messages_total: int = 0           #: MCAP messages written, all topics
    stats_snapshots: int = 0
    commands_recorded: int = 0
    wall_s: float = 0.0
    lossless: bool = True             #: recorder_missed == 0 and the window counts match
    topic_counts: str = "{}"          #: JSON {topic: messages}

    def as_dict(self) -> dict:
        return asdict(self)
