"""One declarative way to read a configuration file (issue 31 item 3).

A file format is a typed schema (``msgspec.Struct`` classes: key names, types, ranges,
defaults, unknown keys refused) plus, beside it, the cross-field checks that need code
(address overlap, joint roles, ...). This module does the common part for every format:

- :func:`read_text`: the file's bytes as UTF-8 text (a bad byte is named by its line);
- :func:`parse_toml` / :func:`parse_json`: the text as plain data;
- :func:`convert`: the data into the schema; the first mistake becomes a
  :class:`Problem`, ``FILE:LINE: field: message``, the line found from the key path in the
  source text (:func:`key_lines`), the field named as the file writes it (``[bit3] size``,
  ``page 1 var 2 format``);
- :func:`fail`: a cross-field check's mistake, in the same form.

A format may replace the library's wording with its own for a field (``messages``: a key
pattern such as ``"board[].base"`` -> a template formatted with the bad ``value``, the
field's ``key`` and the keys of the table holding it).

Each format keeps its own exception class (``ConfigError``, ``MenuError``, ...): the
callers give :func:`convert` an ``error`` factory taking the :class:`Problem`.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import msgspec

from pfma.errors import ConfigError, did_you_mean

T = TypeVar("T")
KeyPath = tuple["str | int", ...]

__all__ = ["Problem", "ConfigFileError", "convert", "fail", "field_name", "key_lines", "line_of", "parse_json",
           "parse_toml", "read_text"]


@dataclass(frozen=True)
class Problem:
    """One mistake in a file: where (source, line, field) and what."""

    source: str
    line: int | None
    field: str  #: "" when the message names its field itself
    message: str
    path: KeyPath = ()  #: the key path of the field in the file's data

    def __str__(self) -> str:
        where = f"{self.source}:{self.line}" if self.line else self.source
        return f"{where}: {self.field}: {self.message}" if self.field else f"{where}: {self.message}"


class ConfigFileError(ConfigError):
    """A :class:`ConfigError` carrying its :class:`Problem` (the default ``error`` factory)."""

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        super().__init__(str(problem))


ErrorFactory = Callable[[Problem], Exception]


# --- reading -------------------------------------------------------------------------------
def read_text(path: str | Path, what: str = "file") -> str:
    """The UTF-8 text of ``path``. :raises ConfigError: ``cannot read WHAT PATH: why``, or
    ``PATH:LINE: not UTF-8 text (byte 0xNN at offset K)``"""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        raise ConfigError(f"cannot read {what} {p}: {err.strerror or err}") from err
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        line = raw.count(b"\n", 0, err.start) + 1
        raise ConfigError(f"{p}:{line}: not UTF-8 text (byte 0x{raw[err.start]:02X} at offset "
                          f"{err.start}); {'JSON' if p.suffix == '.json' else 'TOML'} files are UTF-8") from None


def parse_toml(text: str, source: str, what: str = "a configuration file") -> dict[str, Any]:
    """TOML text as a dict. :raises ConfigError: ``SOURCE: not valid TOML: ...``"""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{source}: not valid TOML: {err}") from err
    except RecursionError:
        raise ConfigError(f"{source}: not {what}: arrays or tables nested too deeply to read") from None


def parse_json(text: str, source: str) -> Any:
    """JSON text as Python data. :raises ConfigError: ``SOURCE: not valid JSON: ...``"""
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ConfigError(f"{source}:{err.lineno}: not valid JSON: {err.msg} (column {err.colno})") from err
    except (RecursionError, ValueError) as err:
        raise ConfigError(f"{source}: not valid JSON: {err}") from None


# --- converting into the schema ------------------------------------------------------------
_PATH_PART = re.compile(r"\.([^.\[]+)|\[(\d+)\]")
_REASON = re.compile(r"^(?P<reason>.*?)(?: - at `\$(?P<path>[^`]*)`)?$", re.S)
_UNKNOWN = re.compile(r"^Object contains unknown field `(?P<key>[^`]*)`$")
_MISSING = re.compile(r"^Object missing required field `(?P<key>[^`]*)`$")


def _error_path(err: msgspec.ValidationError) -> tuple[KeyPath, str, str]:
    """(key path, kind, reason) of a msgspec error; kind is "unknown", "missing" or "value"
    (for the first two, the path ends with the offending key)."""
    m = _REASON.match(str(err))
    assert m is not None
    reason, raw_path = m.group("reason"), m.group("path") or ""
    path: list[str | int] = [int(i) if i else k for k, i in _PATH_PART.findall(raw_path)]
    for kind, pattern in (("unknown", _UNKNOWN), ("missing", _MISSING)):
        km = pattern.match(reason)
        if km:
            return (*path, km.group("key")), kind, reason
    return tuple(path), "value", reason


def _at(data: Any, path: KeyPath) -> Any:
    """The value at ``path`` in ``data`` (None where it does not lead anywhere)."""
    for k in path:
        try:
            data = data[k]
        except (KeyError, IndexError, TypeError):
            return None
    return data


def _pattern(path: KeyPath) -> str:
    """``("board", 2, "base")`` -> ``"board[].base"`` (a ``messages`` key)."""
    return "".join("[]" if isinstance(k, int) else f".{k}" for k in path).lstrip(".")


def field_name(path: KeyPath, data: Any = None) -> str:
    """A key path as the file writes it: a top-level table's keys ``[bit3] size``, indices
    1-based ``page 1 var 2 format``, otherwise keys joined by spaces."""
    words = [str(k + 1) if isinstance(k, int) else k for k in path]
    if len(path) >= 1 and isinstance(path[0], str) and isinstance(_at(data, path[:1]), dict):
        return " ".join([f"[{path[0]}]", *words[1:]])
    return " ".join(words)


class _Fields(dict):
    def __missing__(self, key: str) -> str:
        return "?"


def _message(kind: str, path: KeyPath, reason: str, value: Any, known: Callable[[KeyPath], list[str]]) -> str:
    key = path[-1] if path else ""
    if kind == "unknown":
        keys = known(path[:-1])
        return "unknown key" + (f"{did_you_mean(str(key), keys)}; known: {', '.join(keys)}" if keys else "")
    if kind == "missing":
        return "missing (a required key)"
    return f"{reason[0].lower()}{reason[1:]}, not {value!r}" if reason.startswith("Expected") else reason


def convert(data: Any, schema: type[T], *, source: str, text: str | None = None,
            messages: Mapping[str, str | Callable[[Mapping[str, Any]], str]] | None = None, named: bool = False,
            prefix: KeyPath = (), error: ErrorFactory = ConfigFileError, whole: Any = None,
            missing_first: bool = False) -> T:
    """``data`` as an instance of ``schema`` (strict types: no bool for a number, no string
    for an int).

    :param source: the file's name, as messages start with it
    :param text: the file's text, to find the line of a bad key (None: no line)
    :param messages: key pattern (``"board[].base"``; ``"bit3.*"``: an unknown key of
        ``[bit3]``, ``"*"`` one at the top; ``"amplifier_enable.bit?"``: that key missing) ->
        the whole message after ``FILE:LINE:``, formatted with ``value``, ``key`` and the keys
        of the tables holding the field (``{name}``: the innermost table's ``name``), or a
        function of that mapping returning the message
    :param named: the messages say what is wrong with the field, which the :class:`Problem`
        names (``FILE:LINE: page 1 var 2 format: MESSAGE``); False: they name it themselves
    :param prefix: where ``data`` is inside the file (converting one table of it; the
        ``messages`` patterns are then relative to that table)
    :param whole: the whole file's data when ``data`` is a part of it (field names)
    :param missing_first: a required key of ``schema`` missing is the first mistake (in
        the schema's order), before any of a present key (msgspec judges those first)
    :raises: ``error(Problem)`` for the first mistake
    """
    try:
        if missing_first and isinstance(data, dict):
            _require(data, schema)
        return msgspec.convert(data, schema, strict=True)
    except msgspec.ValidationError as err:
        rel, kind, reason = _error_path(err)
        path = (*prefix, *rel)
        root = data if whole is None else whole
        fields = _Fields()
        for n in range(len(rel)):  # the keys of every table holding the field, the innermost last
            table = _at(data, rel[:n])
            if isinstance(table, dict):
                fields.update(table)
        fields.update(value=_at(data, rel), key=path[-1] if path else "", reason=reason, path=path)
        templates = messages or {}
        template = {"unknown": templates.get(f"{_pattern(rel[:-1])}.*".lstrip(".")),
                    "missing": templates.get(f"{_pattern(rel)}?"),
                    "value": templates.get(_pattern(rel))}[kind]
        field = field_name(path, root) or "(top level)"
        if template is not None:
            msg = template(fields) if callable(template) else template.format_map(fields)
            problem = Problem(source, line_of(text, path), field if named else "", msg, path)
        else:
            problem = Problem(source, line_of(text, path), field,
                              _message(kind, path, reason, fields["value"], _known_keys(schema, prefix)), path)
        raise error(problem) from None


def _require(data: dict, schema: Any) -> None:
    """A msgspec-like error for the first required key of ``schema`` missing from ``data``."""
    for f in msgspec.structs.fields(schema):
        if f.required and f.encode_name not in data:
            raise msgspec.ValidationError(f"Object missing required field `{f.encode_name}`")


def _known_keys(schema: Any, prefix: KeyPath) -> Callable[[KeyPath], list[str]]:
    """The keys the schema knows for the table at a key path (for "known: ..." hints)."""
    def known(path: KeyPath) -> list[str]:
        info: Any = msgspec.inspect.type_info(schema)
        for k in path[len(prefix):]:
            while isinstance(info, (msgspec.inspect.ListType, msgspec.inspect.DictType)):
                info = info.item_type if isinstance(info, msgspec.inspect.ListType) else info.value_type
            if isinstance(k, int):
                continue
            if not isinstance(info, msgspec.inspect.StructType):
                return []
            info = next((f.type for f in info.fields if f.encode_name == k), None)
        while isinstance(info, msgspec.inspect.ListType):
            info = info.item_type
        if isinstance(info, msgspec.inspect.StructType):
            return sorted(f.encode_name for f in info.fields)
        return []
    return known


def fail(source: str, text: str | None, path: KeyPath, message: str, *, field: str = "",
         error: ErrorFactory = ConfigFileError) -> NoReturn:
    """Raise ``error(Problem)`` for a cross-field check, at the line of ``path``."""
    raise error(Problem(source, line_of(text, path), field, message, path))


# --- where a key is --------------------------------------------------------------------------
_TOKEN = re.compile(r'''
    (?P<nl>\n) | (?P<ws>[ \t\r]+) | (?P<comment>\#[^\n]*)
  | (?P<str>"""(?:\\.|[^\\])*?"""|\'\'\'.*?\'\'\'|"(?:\\.|[^"\\\n])*"|'[^'\n]*')
  | (?P<punct>[\[\]{}=,:])
  | (?P<word>[^\s\[\]{}=,:\#"']+)
''', re.X | re.S)


def _tokens(text: str) -> list[tuple[str, str, int]]:
    """(kind, text, line) of each TOML/JSON token ("nl", "str", "punct", "word")."""
    out, n = [], 1
    for m in _TOKEN.finditer(text):
        kind = m.lastgroup or ""
        if kind not in ("ws", "comment"):
            out.append((kind, m.group(), n))
        n += m.group().count("\n")
    return out


def _key_parts(tok: tuple[str, str, int]) -> list[str]:
    kind, s, _ = tok
    if kind == "str":
        try:
            return [json.loads(s) if s.startswith('"') else s.strip("'")]
        except ValueError:  # a TOML escape JSON does not know: the key as written
            return [s.strip('"')]
    return s.split(".")


class _Scanner:
    """Key path -> first line, for TOML (tables, arrays of tables, inline tables and
    arrays) and JSON (the same inline grammar with ``:``)."""

    def __init__(self, text: str) -> None:
        self.toks = _tokens(text)
        self.lines: dict[KeyPath, int] = {}
        self.aot: dict[KeyPath, int] = {}

    def skip(self, i: int, also: str = "") -> int:
        while i < len(self.toks) and (self.toks[i][0] == "nl" or self.toks[i][1] in also and also):
            i += 1
        return i

    def scan(self) -> dict[KeyPath, int]:
        table: KeyPath = ()
        i = self.skip(0)
        if i < len(self.toks) and self.toks[i][1] in "[{" and self._is_json():
            self.value(i, ())
            return self.lines
        while i < len(self.toks):
            if self.toks[i][1] == "[":
                i, table = self.header(i)
            else:
                i = self.key_value(i, table, "=")
            while i < len(self.toks) and self.toks[i][0] != "nl":
                i += 1
            i = self.skip(i)
        return self.lines

    def _is_json(self) -> bool:
        return any(t[1] == ":" for t in self.toks[:4]) or self.toks[self.skip(0)][1] == "{"

    def header(self, i: int) -> tuple[int, KeyPath]:
        line = self.toks[i][2]
        double = i + 1 < len(self.toks) and self.toks[i + 1][1] == "["
        i += 2 if double else 1
        parts: list[str] = []
        while i < len(self.toks) and self.toks[i][1] != "]" and self.toks[i][0] != "nl":
            parts += [p for p in _key_parts(self.toks[i]) if p]
            i += 1
        path: KeyPath = ()
        for k, part in enumerate(parts):
            path = (*path, part)
            if k < len(parts) - 1 and path in self.aot:
                path = (*path, self.aot[path])
        if double:
            self.aot[path] = self.aot.get(path, -1) + 1
            self.lines.setdefault(path, line)
            path = (*path, self.aot[path])
        self.lines.setdefault(path, line)
        return i, path

    def key_value(self, i: int, table: KeyPath, sep: str) -> int:
        parts: list[str] = []
        while i < len(self.toks) and self.toks[i][1] not in ("=", ":", "}", "]"):
            if self.toks[i][0] != "nl":
                parts += _key_parts(self.toks[i])
            i += 1
        if i >= len(self.toks) or self.toks[i][1] not in ("=", ":"):
            return i
        return self.value(i + 1, (*table, *parts))

    def value(self, i: int, path: KeyPath) -> int:
        i = self.skip(i)
        if i >= len(self.toks):
            return i
        kind, s, line = self.toks[i]
        self.lines.setdefault(path, line)
        if s == "[":
            return self._items(i + 1, path)
        if s == "{":
            i += 1
            while True:
                i = self.skip(i, ",")
                if i >= len(self.toks) or self.toks[i][1] == "}":
                    return i + 1
                i = self.key_value(i, path, "=")
        while i < len(self.toks) and self.toks[i][1] not in (",", "]", "}") and self.toks[i][0] != "nl":
            i += 1
        return i

    def _items(self, i: int, path: KeyPath) -> int:
        index = 0
        while True:
            i = self.skip(i, ",")
            if i >= len(self.toks) or self.toks[i][1] == "]":
                return i + 1
            i = self.value(i, (*path, index))
            index += 1


def key_lines(text: str) -> dict[KeyPath, int]:
    """Where each table, key and array entry of TOML or JSON text starts: key path -> line."""
    return _Scanner(text).scan()


_CACHE: dict[int, tuple[str, dict[KeyPath, int]]] = {}


def line_of(text: str | None, path: KeyPath) -> int | None:
    """The line of ``path`` in ``text``, or of the nearest table holding it (None: none)."""
    if text is None:
        return None
    hit = _CACHE.get(id(text))
    if hit is None or hit[0] is not text:
        _CACHE.clear()
        try:
            found = key_lines(text)
        except RecursionError:  # nested too deeply to follow: name the file only
            found = {}
        hit = _CACHE[id(text)] = (text, found)
    lines = hit[1]
    for n in range(len(path), 0, -1):
        if path[:n] in lines:
            return lines[path[:n]]
    return None
