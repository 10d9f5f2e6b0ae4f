"""Versioned, validated calibration files: one JSON file per rack.

A calibration file holds the conversion of **every** analog channel of the rack
(ADC, DAC and resolver channels: ``engineering = scale * raw + offset``, where raw is
volts for ADC/DAC channels and the resolver's angle in rad for RTD channels; a DAC
writes ``volts = (engineering - offset) / scale``), plus optional sections for the CAE
hand controller (centre/deadband/span/sign per axis) and the wrist F/T sensor (bias in
counts, 6x6 counts -> N/N*m matrix, tool payload). Each entry carries its provenance:
date, operator, method, points, residuals and the software version that made it.

Files are written atomically (temporary file, fsync, rename); the file being replaced
is kept, byte for byte, in ``<file>.history/``. A file that is truncated, has a value
of the wrong type, lacks a channel of the rack or names one it does not have is
refused with a :class:`CalibrationError` that names the field; the caller's previous
calibration stays in force (nothing is changed until a file has fully validated).

Format (``format = "pfma-calibration"``, ``format_version = 1``)::

    {"format": "pfma-calibration", "format_version": 1, "rack": "pfma", "version": 3,
     "created": "2024-05-01T10:00:00Z", "software_version": "pfma 0.1.0",
     "previous_hash": "0123456789abcdef",
     "channels": {"shoulder_yaw_rate": {"device": "adc", "units": "rad/s", "scale": 0.04,
                  "offset": 0.0, "provenance": {"date": ..., "operator": ..., "method": ...,
                  "software_version": ..., "points": [[x, y], ...], "residuals": [...]}}, ...},
     "cae": {"x": {"centre_v": 0.0, "deadband_v": 0.5, "span_v": 10.0, "sign": 1,
                   "provenance": {...}}, ...},
     "ft": {"bias_counts": [6], "matrix": [[6] x 6], "payload_mass_kg": 1.5,
            "payload_com_m": [0, 0, 0.06], "provenance": {...}}}
"""

from __future__ import annotations

import copy
import datetime as _dt
import hashlib
import json
import math
import os
import shutil
from dataclasses import replace
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import msgspec
import numpy as np

import pfma
from pfma import config, nominal
from pfma.errors import CalibrationError
from pfma.rack import RackConfig

FORMAT = "pfma-calibration"
FORMAT_VERSION = 1
#: devices whose channels carry a scale/offset conversion in the calibration file
ANALOG_DEVICES = ("adc", "dac", "rtd")
SOFTWARE_VERSION = f"pfma {pfma.__version__}"
PROVENANCE_KEYS = ("date", "operator", "method", "software_version")
CAE_AXIS_NAMES = ("x", "y", "z", "roll", "pitch", "yaw")


def now_iso() -> str:
    """UTC time stamp for provenance (seconds resolution)."""
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def provenance(method: str, operator: str = "", *, date: str | None = None, **extra: Any) -> dict:
    """A provenance record: date, operator, method, software version, plus e.g. points/residuals."""
    p = {"date": date or now_iso(), "operator": operator or os.environ.get("USER", "unknown"),
         "method": method, "software_version": SOFTWARE_VERSION}
    p.update(_plain(extra))
    return p


def _plain(obj: Any) -> Any:
    """numpy values -> JSON-able Python values (recursively)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


class Calibration:
    """A validated calibration (the file's JSON object) and where it came from."""

    def __init__(self, data: dict, path: Path | None = None) -> None:
        self.data = data
        self.path = path
        #: ``("signal.field", text)`` per value accepted outside the nominal band by the rack
        #: file's ``[checks] allow_nonnominal`` (set by :func:`validate` given a rack)
        self.nonnominal: tuple[tuple[str, str], ...] = ()

    # accessors
    @property
    def rack_name(self) -> str:
        return self.data["rack"]

    @property
    def version(self) -> int:
        return self.data["version"]

    @property
    def created(self) -> str:
        return self.data["created"]

    @property
    def channels(self) -> dict[str, dict]:
        return self.data["channels"]

    @property
    def cae(self) -> dict | None:
        return self.data.get("cae")

    @property
    def ft(self) -> dict | None:
        return self.data.get("ft")

    def channel(self, signal: str) -> dict:
        try:
            return self.channels[signal]
        except KeyError:
            raise CalibrationError(f"calibration {self.describe()} has no channel {signal!r}") from None

    def hash(self) -> bytes:
        return calibration_hash(self)

    def describe(self) -> str:
        where = str(self.path) if self.path else "<in memory>"
        return f"{where} (rack {self.rack_name}, version {self.version})"

    def updated(self, *, channels: dict[str, dict] | None = None, cae: dict | None = None,
                ft: dict | None = None, rack: RackConfig | None = None) -> "Calibration":
        """A new, validated calibration with these entries replaced (the rest kept)."""
        data = copy.deepcopy(self.data)
        for sig, entry in (channels or {}).items():
            if sig not in data["channels"]:
                raise CalibrationError(f"channels.{sig}: not a channel of this calibration")
            merged = dict(data["channels"][sig])
            merged.update(_plain(entry))
            data["channels"][sig] = merged
        if cae is not None:
            merged = copy.deepcopy(data.get("cae") or {})
            merged.update(_plain(cae))
            data["cae"] = merged
        if ft is not None:
            merged = copy.deepcopy(data.get("ft") or {})
            merged.update(_plain(ft))
            data["ft"] = merged
        return validate(data, rack=rack, source="updated calibration", path=self.path)


# ---------------------------------------------------------------- validation
def _fail(field: str, msg: str, source: str) -> CalibrationError:
    return CalibrationError(f"calibration {source}: {field}: {msg}; file refused, the previous "
                            f"calibration stays in force")


def _typename(v: Any) -> str:
    return "null" if v is None else {dict: "object", list: "list", str: "string", bool: "boolean"}.get(
        type(v), type(v).__name__)


def _field(path: tuple) -> str:
    """``("ft", "matrix", 2, 3)`` -> ``ft.matrix[2][3]`` (how the messages name a field)."""
    return "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in path).lstrip(".") or "(top level)"


# --- the schema: a calibration file's keys and types (checked by pfma.config) -------------
class _Provenance(msgspec.Struct):  # more keys (points, residuals, the method's own) are kept
    date: str
    operator: str
    method: str
    software_version: str
    residuals: list[Any] | dict[str, Any] | None = None
    points: list[Any] | dict[str, Any] | None = None


class _ChannelEntry(msgspec.Struct):
    device: Literal["adc", "dac", "rtd"]
    units: str
    scale: float
    offset: float
    provenance: _Provenance


class _CaeAxis(msgspec.Struct):
    centre_v: float
    deadband_v: float
    span_v: float
    sign: int
    provenance: _Provenance


class _Cae(msgspec.Struct, forbid_unknown_fields=True):  # CAE_AXIS_NAMES
    x: _CaeAxis
    y: _CaeAxis
    z: _CaeAxis
    roll: _CaeAxis
    pitch: _CaeAxis
    yaw: _CaeAxis


_Vec6 = tuple[float, float, float, float, float, float]


class _Ft(msgspec.Struct):
    bias_counts: _Vec6
    matrix: tuple[_Vec6, _Vec6, _Vec6, _Vec6, _Vec6, _Vec6]
    payload_mass_kg: float
    payload_com_m: tuple[float, float, float]
    provenance: dict[str, Any]


class _CalibrationFile(msgspec.Struct, forbid_unknown_fields=True):
    format: str
    format_version: int
    rack: str
    version: int
    created: str
    software_version: str
    channels: dict[str, Any]  # each a _ChannelEntry (converted one by one: errors name the signal)
    previous_hash: str | None = None
    cae: Any = None  # a _Cae
    ft: Any = None  # an _Ft
    comment: Any = None


def _expected(what: str) -> Callable[[Mapping[str, Any]], str]:
    """The message for a value that is not ``what`` ("a number", "a string", ...)."""
    def message(f: Mapping[str, Any]) -> str:
        v = f["value"]
        if what == "a number" and type(v) is int:  # beyond float range
            return f"expected a finite number, got an integer of {len(str(abs(v)))} digits"
        if what == "an object":
            return f"expected an object, got {_typename(v)}"
        return f"expected {what}, got {_typename(v)} {v!r}"
    return message


def _list_of(n: int, what: str = "a list of {n} numbers") -> Callable[[Mapping[str, Any]], str]:
    def message(f: Mapping[str, Any]) -> str:
        v = f["value"]
        return f"expected {what.format(n=n)}, got {_typename(v)}" + (f" of {len(v)}" if isinstance(v, list) else "")
    return message


_NUMBER, _STRING, _INT, _OBJECT = (_expected(w) for w in ("a number", "a string", "an integer", "an object"))
_PROVENANCE = {"provenance": _OBJECT, **{f"provenance.{k}": _STRING for k in PROVENANCE_KEYS},
               **{f"provenance.{k}?": "missing" for k in PROVENANCE_KEYS},
               **{f"provenance.{k}": lambda f: f"expected a list, got {_typename(f['value'])}"
                  for k in ("residuals", "points")}}
_TOP_MESSAGES = {
    "": _OBJECT, "*": "unknown top-level key", "channels": _OBJECT,
    **{f"{k}?": "missing (truncated or partial file?)"
       for k in ("format", "format_version", "rack", "version", "created", "software_version", "channels")},
    **{k: _STRING for k in ("format", "rack", "created", "software_version", "previous_hash")},
    "format_version": _INT, "version": _INT,
}
_CHANNEL_MESSAGES = {
    "": _OBJECT, **{f"{k}?": "missing" for k in ("device", "units", "scale", "offset", "provenance")},
    "device": "expected one of " + ", ".join(ANALOG_DEVICES) + ", got {value!r}",
    "units": _STRING, "scale": _NUMBER, "offset": _NUMBER, **_PROVENANCE,
}
_CAE_MESSAGES = {
    "": _OBJECT, "*": "unknown axis (known: " + ", ".join(CAE_AXIS_NAMES) + ")",
    **{f"{a}?": "missing" for a in CAE_AXIS_NAMES},
    **{f"{a}{k}": m for a in CAE_AXIS_NAMES for k, m in (
        ("", _OBJECT), *((f".{k}?", "missing") for k in ("centre_v", "deadband_v", "span_v", "sign", "provenance")),
        (".centre_v", _NUMBER), (".deadband_v", _NUMBER), (".span_v", _NUMBER), (".sign", _INT),
        *((f".{p}", m) for p, m in _PROVENANCE.items()))},
}
_FT_MESSAGES = {
    "": _OBJECT, **{f"{k}?": "missing" for k in ("bias_counts", "matrix", "payload_mass_kg", "payload_com_m",
                                                 "provenance")},
    "bias_counts": _list_of(6), "bias_counts[]": _NUMBER, "matrix": _list_of(6, "6 rows of 6 numbers"),
    "matrix[]": _list_of(6), "matrix[][]": _NUMBER, "payload_mass_kg": _NUMBER,
    "payload_com_m": _list_of(3), "payload_com_m[]": _NUMBER, "provenance": _OBJECT,
}


def _convert(data: Any, schema: type, messages: dict, source: str, prefix: tuple = (), first: bool = True) -> Any:
    """``data`` into ``schema`` (``first``: its required keys judged first); the first
    mistake is a CalibrationError naming the field (``channels.SIGNAL.scale``)."""
    return config.convert(data, schema, source=source, messages=messages, prefix=prefix, missing_first=first,
                          error=lambda p: _fail(_field(p.path), p.message, source))


def _finite(values: dict[str, float], source: str, *, minimum: dict[str, float] | None = None) -> None:
    """Each value (by field name) a finite number, and at least its ``minimum``."""
    for field, x in values.items():
        if not math.isfinite(x):
            raise _fail(field, f"expected a finite number, got {x!r}", source)
        low = (minimum or {}).get(field)
        if low is not None and x < low:
            raise _fail(field, f"must be >= {low:g}, got {x:g}", source)


def validate(data: Any, rack: RackConfig | None = None, source: str = "<data>",
             path: Path | None = None) -> Calibration:
    """Check a calibration's structure and types (and, given ``rack``, that it covers exactly
    the rack's analog channels). :raises CalibrationError: naming the first bad field"""
    top = _convert(data, _CalibrationFile, _TOP_MESSAGES, source)
    if top.format != FORMAT:
        raise _fail("format", f"expected {FORMAT!r}, got {top.format!r}", source)
    if top.format_version != FORMAT_VERSION:
        raise _fail("format_version", f"this software reads version {FORMAT_VERSION}, "
                    f"got {top.format_version}", source)
    if top.version < 0:
        raise _fail("version", "must be >= 0", source)
    for sig, e in top.channels.items():
        entry = _convert(e, _ChannelEntry, _CHANNEL_MESSAGES, source, ("channels", sig))
        _finite({f"channels.{sig}.scale": entry.scale, f"channels.{sig}.offset": entry.offset}, source)
        if entry.scale == 0:
            raise _fail(f"channels.{sig}.scale", "must not be 0", source)
    nonnominal: tuple[tuple[str, str], ...] = ()
    if rack is not None:
        _check_rack(top.rack, top.channels, rack, source)
        nonnominal = _check_nominal(top.channels, rack, source)
    if top.cae is not None:
        _validate_cae(top.cae, source)
    if top.ft is not None:
        _validate_ft(top.ft, source)
    cal = Calibration(data, path)
    cal.nonnominal = nonnominal
    return cal


def _check_rack(name: str, chans: dict, rack: RackConfig, source: str) -> None:
    """The calibration is for this rack and has exactly its analog channels, each on its device."""
    if name != rack.name:
        raise _fail("rack", f"calibration is for rack {name!r}, the rack configuration "
                    f"({rack.source}) is {rack.name!r}", source)
    for c in rack.channels():
        if c.device not in ANALOG_DEVICES:
            continue
        if c.signal not in chans:
            raise _fail(f"channels.{c.signal}", f"missing: the rack's {c.device} channel "
                        f"{c.channel} on board {c.board} (A16 0x{c.address:04X}) has no conversion", source)
        if chans[c.signal]["device"] != c.device:
            raise _fail(f"channels.{c.signal}.device", f"the rack has it on a {c.device} board "
                        f"({c.board}), not {chans[c.signal]['device']}", source)
    known = {c.signal for c in rack.channels() if c.device in ANALOG_DEVICES}
    extra = sorted(set(chans) - known)
    if extra:
        raise _fail(f"channels.{extra[0]}", f"not an analog channel of rack {rack.name} ({rack.source})", source)


def _check_nominal(chans: dict, rack: RackConfig, source: str) -> tuple[tuple[str, str], ...]:
    """Each joint channel's scale and offset against the nominal arm (:mod:`pfma.nominal`:
    sign, band, offset bound), as the rack file's own values are at parse. A value outside
    is refused unless the rack file's ``[checks] allow_nonnominal`` names it; returns the
    ``("signal.field", text)`` of those accepted so (the service names them at start). The limits are the rack
    file's (checked there against its own scales): a calibration does not change them."""
    accepted: list[tuple[str, str]] = []
    for c in rack.channels():
        e = chans.get(c.signal)
        if e is None or c.device not in ANALOG_DEVICES:
            continue
        for f in nominal.check(c.device, c.joint, c.quantity, c.units, float(e["scale"]), float(e["offset"])):
            what = f"{c.signal}.{f.field}"
            if what in rack.overrides:
                accepted.append((what, f"calibration {source}: {what} = {f.value:g} accepted outside the "
                                       f"nominal band by [checks] allow_nonnominal ({rack.source}): {f.why}"))
                continue
            raise _fail(f"channels.{what}", f"{f.value:g}: {f.why}; a lab that knows better lists "
                        f"\"{what}\" in the rack file's [checks] allow_nonnominal ({rack.source})", source)
    return tuple(accepted)


def _validate_cae(v: Any, source: str) -> None:
    cae = _convert(v, _Cae, _CAE_MESSAGES, source, ("cae",), first=False)  # axis by axis, as the file has them
    for axis in CAE_AXIS_NAMES:
        e, f = getattr(cae, axis), f"cae.{axis}"
        _finite({f"{f}.centre_v": e.centre_v, f"{f}.deadband_v": e.deadband_v, f"{f}.span_v": e.span_v}, source,
                minimum={f"{f}.deadband_v": 0.0})
        if e.sign not in (1, -1):
            raise _fail(f"{f}.sign", f"must be +1 or -1, got {e.sign}", source)
        if not e.deadband_v < e.span_v:
            raise _fail(f"{f}.span_v", f"must exceed deadband_v ({e.deadband_v:g}), got {e.span_v:g}", source)


def _validate_ft(v: Any, source: str) -> None:
    ft = _convert(v, _Ft, _FT_MESSAGES, source, ("ft",))
    _finite({f"ft.bias_counts[{i}]": x for i, x in enumerate(ft.bias_counts)}, source)
    _finite({f"ft.matrix[{i}][{j}]": x for i, row in enumerate(ft.matrix) for j, x in enumerate(row)}, source)
    if abs(np.linalg.det(np.array(ft.matrix))) < 1e-30:
        raise _fail("ft.matrix", "singular", source)
    _finite({"ft.payload_mass_kg": ft.payload_mass_kg}, source, minimum={"ft.payload_mass_kg": 0.0})
    _finite({f"ft.payload_com_m[{i}]": x for i, x in enumerate(ft.payload_com_m)}, source)


# ---------------------------------------------------------------- files
def parse_calibration(text: str, source: str = "<string>", rack: RackConfig | None = None,
                      path: Path | None = None) -> Calibration:
    """Parse and validate calibration JSON text. :raises CalibrationError: naming the field"""
    if not text.strip():
        raise CalibrationError(f"calibration {source}: empty file; file refused, the previous "
                               f"calibration stays in force")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise CalibrationError(f"calibration {source}: not valid JSON (truncated or corrupt?): {err.msg} at line "
                               f"{err.lineno} column {err.colno}; file refused, the previous "
                               f"calibration stays in force") from err
    except RecursionError:
        raise CalibrationError(f"calibration {source}: not a calibration (arrays or objects nested too "
                               f"deeply to read); file refused, the previous calibration stays in force") from None
    except ValueError as err:  # an integer longer than Python converts (sys.get_int_max_str_digits)
        raise CalibrationError(f"calibration {source}: not a calibration ({err}); file refused, the previous "
                               f"calibration stays in force") from None
    return validate(data, rack=rack, source=source, path=path)


def load_calibration(path: str | Path, rack: RackConfig | None = None, *,
                     verify_chain: bool = True) -> Calibration:
    """Load and validate a calibration file (against ``rack`` when given), and verify its
    ``previous_hash`` chain through ``<path>.history/`` (:func:`verify_chain`).

    :param verify_chain: False only for the files of a history itself (their chain is
        walked from the current file)
    :raises CalibrationError: unreadable, truncated, wrong type, missing/unknown channel,
        a value outside the nominal band, a broken hash chain
    """
    p = Path(path)
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise CalibrationError(f"cannot read calibration file {p}: {err}") from err
    cal = parse_calibration(text, str(p), rack, path=p)
    if verify_chain:
        verify_chain_of(cal, p)
    return cal


def verify_chain_of(cal: Calibration, path: str | Path) -> list[Calibration]:
    """Walk ``cal``'s ``previous_hash`` chain back through the versions kept in
    ``<path>.history/`` to its first version (``previous_hash`` null); return the chain,
    newest first.

    Each version names the hash (:func:`calibration_hash`) of the file it replaced
    (:func:`save_calibration`), so a kept version that was edited, deleted or swapped, or
    a current file whose ``previous_hash`` was edited, breaks the chain. ASSUMED: the
    history travels with its file; a file copied without its ``.history`` directory is
    refused like a broken chain (restore the directory, or start a new chain:
    ``pfma calibrate init`` on a new file).

    :raises CalibrationError: naming the version whose ``previous_hash`` matches no kept
        version (or one that is not older)
    """
    p = Path(path)
    hist = history_dir(p)
    kept: dict[str, Calibration] = {}
    if hist.is_dir():
        for f in sorted(hist.glob(f"{p.stem}.v*")):
            try:
                k = load_calibration(f, verify_chain=False)
            except CalibrationError:
                continue  # an unreadable kept file is simply not a link
            kept.setdefault(calibration_hash(k).hex(), k)
    chain = [cal]
    while chain[-1].data.get("previous_hash") is not None:
        cur = chain[-1]
        h = cur.data["previous_hash"]
        where = f"the file (version {cur.version})" if cur is cal else f"kept version {cur.version} ({cur.path})"
        prev = kept.get(h)
        if prev is None:
            raise _fail("previous_hash", f"broken hash chain: {where} names "
                        f"previous_hash {h}, which matches no version kept in {hist}"
                        + ("" if hist.is_dir() else " (no such directory)")
                        + "; a kept version was altered or lost (restore it) or the hash was edited",
                        str(p))
        if prev.version >= cur.version:
            raise _fail("previous_hash", f"broken hash chain: {where} names "
                        f"previous_hash {h}, kept version {prev.version} ({prev.path}), which is not "
                        f"older", str(p))
        chain.append(prev)
    return chain


def resolve(calibration: "Calibration | str | Path", rack: RackConfig | None = None) -> Calibration:
    """A path or a loaded calibration -> a calibration validated against ``rack``."""
    if isinstance(calibration, Calibration):
        return validate(calibration.data, rack=rack, source=calibration.describe(), path=calibration.path)
    return load_calibration(calibration, rack)


def nominal_calibration(rack: RackConfig, operator: str = "", date: str | None = None) -> Calibration:
    """Version 0: the rack configuration's nominal scales (every analog channel)."""
    prov = provenance("nominal (rack configuration)", operator, date=date, rack_file=rack.source)
    chans = {c.signal: {"device": c.device, "units": c.units, "scale": c.scale, "offset": c.offset,
                        "provenance": dict(prov)}
             for c in rack.channels() if c.device in ANALOG_DEVICES}
    data = {"format": FORMAT, "format_version": FORMAT_VERSION, "rack": rack.name, "version": 0,
            "created": prov["date"], "software_version": SOFTWARE_VERSION, "previous_hash": None,
            "channels": chans}
    return validate(data, rack=rack, source="nominal calibration")


def history_dir(path: str | Path) -> Path:
    p = Path(path)
    return p.with_name(p.name + ".history")


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_calibration(cal: Calibration, path: str | Path, rack: RackConfig | None = None) -> Calibration:
    """Write ``cal`` as the next version of ``path``, atomically; the file it replaces is
    kept byte for byte in ``<path>.history/``. Returns the calibration as saved.

    :raises CalibrationError: when ``cal`` does not validate (nothing is written)
    """
    p = Path(path)
    data = copy.deepcopy(cal.data)
    prev_version, prev_hash = -1, None
    if p.exists():
        hist = history_dir(p)
        hist.mkdir(parents=True, exist_ok=True)
        try:
            prev = load_calibration(p, verify_chain=False)
            prev_version, prev_hash = prev.version, calibration_hash(prev).hex()
            keep = hist / f"{p.stem}.v{prev.version:04d}{p.suffix or '.json'}"
        except CalibrationError:
            keep = hist / f"{p.stem}.unreadable-{_dt.datetime.now().strftime('%Y%m%dT%H%M%S%f')}{p.suffix}"
        if not keep.exists():
            shutil.copy2(p, keep)
    data["version"] = max(prev_version + 1, int(data.get("version", 0)))
    data["created"] = now_iso()
    data["software_version"] = SOFTWARE_VERSION
    data["previous_hash"] = prev_hash
    out = validate(data, rack=rack, source=str(p), path=p)
    text = json.dumps(data, indent=1, sort_keys=False) + "\n"
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)
    _fsync_dir(p.parent)
    return out


def history(path: str | Path) -> list[Calibration]:
    """Every kept version of ``path`` (oldest first), then the current file. Unreadable
    history files are skipped; the hash chain is not verified (this is what
    ``pfma calibrate history`` shows, also of a broken chain)."""
    p = Path(path)
    out = []
    hist = history_dir(p)
    if hist.is_dir():
        for f in sorted(hist.glob(f"{p.stem}.v*")):
            try:
                out.append(load_calibration(f, verify_chain=False))
            except CalibrationError:
                continue
    if p.exists():
        out.append(load_calibration(p, verify_chain=False))
    return out


def load_version(path: str | Path, version: int) -> Calibration:
    """One version of ``path`` (current or from its history)."""
    for c in history(path):
        if c.version == version:
            return c
    raise CalibrationError(f"calibration {path}: no version {version} (have "
                           f"{', '.join(str(c.version) for c in history(path)) or 'none'})")


def previous(path: str | Path) -> Calibration | None:
    """The current file of ``path`` if it loads, else None (first calibration)."""
    try:
        return load_calibration(path)
    except CalibrationError:
        return None


# ---------------------------------------------------------------- consumers
def calibration_hash(cal: Calibration) -> bytes:
    """8-byte digest (SHA-256 prefix) of the calibration's canonical JSON: stamped in the
    Bit3 header so every consumer and recording knows which calibration made its numbers."""
    canon = json.dumps(cal.data, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(canon.encode()).digest()[:8]


def apply_to_rack(rack: RackConfig, cal: Calibration) -> RackConfig:
    """A rack configuration whose analog channels carry the calibrated scale and offset.

    :raises CalibrationError: when the calibration lacks one of the rack's analog channels
    """
    chans = cal.channels
    boards = []
    for b in rack.boards:
        new = []
        for c in b.channels:
            if c.device in ANALOG_DEVICES:
                e = chans.get(c.signal)
                if e is None:
                    raise CalibrationError(f"calibration {cal.describe()}: channels.{c.signal}: missing "
                                           f"({c.device} channel {c.channel} on {c.board}, A16 0x{c.address:04X})")
                c = replace(c, scale=float(e["scale"]), offset=float(e["offset"]))
            new.append(c)
        boards.append(replace(b, channels=tuple(new)))
    return replace(rack, boards=tuple(boards))


def cae_calibration(cal: Calibration):
    """The CAE section as a ``drivers.crl.cae.CaeCalibration`` (None when absent)."""
    from drivers.crl.cae import CaeAxisCal, CaeCalibration
    if not cal.cae:
        return None
    return CaeCalibration(axes={a: CaeAxisCal(centre_v=float(e["centre_v"]), deadband_v=float(e["deadband_v"]),
                                              span_v=float(e["span_v"]), sign=int(e["sign"]))
                                for a, e in cal.cae.items()})


def nominal_ft(cpf: float | None = None, cpt: float | None = None) -> dict:
    """The F/T section from the sensor's nominal counts per unit (no bias, no payload)."""
    from drivers.serial_ft.protocol import NOMINAL
    cpf = NOMINAL.cpf if cpf is None else cpf
    cpt = NOMINAL.cpt if cpt is None else cpt
    return {"bias_counts": [0.0] * 6,
            "matrix": np.diag([1 / cpf] * 3 + [1 / cpt] * 3).tolist(),
            "payload_mass_kg": 0.0, "payload_com_m": [0.0, 0.0, 0.0],
            "provenance": {"matrix": provenance("nominal (sensor CPF/CPT)")}}


# ---------------------------------------------------------------- comparison
def diff(a: Calibration, b: Calibration, rel_tol: float = 1e-12) -> list[dict]:
    """Entries that differ between ``a`` (older) and ``b`` (newer): one dict per value."""
    return _diff_channels(a, b, rel_tol) + _diff_cae(a, b) + _diff_ft(a, b)


def _change(va, vb):
    """``vb - va``, or None when either side is missing."""
    return None if va is None or vb is None else vb - va


def _channel_differs(va, vb, rel_tol: float) -> bool:
    """A channel's scale or offset differs: missing on either side, or not close."""
    return va is None or vb is None or not math.isclose(va, vb, rel_tol=rel_tol, abs_tol=1e-15)


def _diff_channels(a: Calibration, b: Calibration, rel_tol: float) -> list[dict]:
    """The ``channels.SIG.scale|offset`` entries that differ (beyond ``rel_tol``)."""
    out = []
    for sig in sorted(set(a.channels) | set(b.channels)):
        ea, eb = a.channels.get(sig) or {}, b.channels.get(sig)
        method = (eb or {}).get("provenance", {}).get("method")
        for key in ("scale", "offset"):
            va, vb = ea.get(key), (eb or {}).get(key)
            if _channel_differs(va, vb, rel_tol):
                out.append({"entry": f"channels.{sig}.{key}", "old": va, "new": vb,
                            "change": _change(va, vb), "method": method})
    return out


def _diff_cae(a: Calibration, b: Calibration) -> list[dict]:
    """The ``cae.AXIS.KEY`` entries that differ."""
    out = []
    for sec, keys in (("cae", ("centre_v", "deadband_v", "span_v", "sign")),):
        sa, sb = a.data.get(sec) or {}, b.data.get(sec) or {}
        for axis in sorted(set(sa) | set(sb)):
            for key in keys:
                va, vb = (sa.get(axis) or {}).get(key), (sb.get(axis) or {}).get(key)
                if va != vb:
                    out.append({"entry": f"{sec}.{axis}.{key}", "old": va, "new": vb,
                                "change": _change(va, vb), "method": None})
    return out


def _ft_change(va, vb) -> float | None:
    """The largest absolute element change between two F/T values (None when either is missing)."""
    if va is None or vb is None:
        return None
    return float(np.max(np.abs(np.asarray(vb, float) - np.asarray(va, float))))


def _diff_ft(a: Calibration, b: Calibration) -> list[dict]:
    """The ``ft.KEY`` entries that differ."""
    fa, fb = a.ft or {}, b.ft or {}
    return [{"entry": f"ft.{key}", "old": fa.get(key), "new": fb.get(key),
             "change": _ft_change(fa.get(key), fb.get(key)), "method": None}
            for key in ("bias_counts", "matrix", "payload_mass_kg", "payload_com_m")
            if fa.get(key) != fb.get(key)]
