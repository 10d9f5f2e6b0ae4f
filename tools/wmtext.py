"""A world-model value as a person writes and reads it: the text side of ``pfma wm``, shared
by the CLI and the operator console (``pfma wm get``/``set``, the console's variable view
and its user menus)."""

from __future__ import annotations

import json

import numpy as np


def _py(v):
    """A JSON-ready Python value."""
    return v.tolist() if isinstance(v, (np.ndarray, np.generic)) else v


def format_value(v, width: int | None = None) -> str:
    """Readable value text: ``%.6g`` floats, ints, ``[a, b, c]`` arrays (cut to ``width``)."""
    def one(x) -> str:
        if isinstance(x, (bool, np.bool_)):
            return "true" if x else "false"
        if isinstance(x, (float, np.floating)):
            return f"{float(x):.6g}"
        return str(int(x))

    a = np.asarray(v)
    if a.shape == ():
        text = one(a.item())
    else:
        def rec(x) -> str:
            return "[" + ", ".join(rec(e) if isinstance(e, list) else one(e) for e in x) + "]"
        text = rec(a.tolist())
    if width is not None and len(text) > width:
        text = text[:width - 3] + "..."
    return text


def value_text(spec, v, width: int | None = None) -> str:
    """A variable's value as a person reads it: an enumeration or a bit set by name with
    the number beside it (``ERROR (7)``, :meth:`VarSpec.value_text`), else :func:`format_value`."""
    named = spec.value_text(v)
    if named is None:
        return format_value(v, width)
    return named if width is None or len(named) <= width else named[:width - 3] + "..."


def parse_value(text: str, spec=None):
    """VALUE as JSON; else numbers separated by commas/spaces (``1,2,3`` or ``"1 2 3"``); for
    an enumerated variable (``spec.enum``) also a name of its enumeration (``PLAY``, ``play``).

    :raises WorldModelValueError: neither (for an enumerated variable the message lists its
        values; a number outside them is refused by the value check, :func:`coerce`)
    """
    from controller.worldmodel import WorldModelValueError
    enum = spec.enum_names if spec is not None and spec.enum else None
    if enum:
        from pfma.show import value_of
        v = value_of(text.strip().strip('"'), enum)
        if v is not None:
            return v
    value = _parse_json_or_numbers(text)
    if enum and (value is _NOT_PARSED or isinstance(value, str)):
        raise WorldModelValueError(spec.value_refusal(repr(text)))
    if value is _NOT_PARSED:
        raise WorldModelValueError(f"value {text!r} is not JSON (examples: 1.5, -3, true, [0.1, 0.2, 0.3])")
    return value


_NOT_PARSED = object()


def _parse_json_or_numbers(text: str):
    """``text`` as JSON, else as numbers separated by commas/spaces; :data:`_NOT_PARSED` if neither."""
    try:
        return json.loads(text)
    except ValueError:
        pass

    def number(p: str):
        try:
            return json.loads(p)
        except ValueError:
            return float(p)  # also "nan", "inf": refused later with a clear "not finite"

    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        if len(parts) == 1:
            return number(parts[0])
        if len(parts) > 1:
            return [number(p) for p in parts]
    except ValueError:
        pass
    return _NOT_PARSED
