"""One way to show a value (issue 29 item 5): the rules every tool follows, each named once here.

- **Angles** are shown in radians in (-pi, pi] (:func:`wrap_angle`): the resolvers read
  0..2 pi, so a joint just below 0 would otherwise read near 2 pi (-1.5708 and 4.71239 are
  the same elbow angle). The buffer and the world model keep what their writers posted.
- **Enumerations** (states, statuses, error codes, modes) are shown by name with the number
  beside it, ``ERROR (7)`` (:func:`named`), or by name alone where the number says nothing
  more (:func:`name_of`). A value outside its enumeration is shown as ``7 (unknown)``,
  never as a guess.
- **Bit sets** (status words, hardware checks) are shown as the names of the bits that are
  set, joined by ``|`` (:func:`flag_names`); bits without a name as hex. A clear word is
  ``ok`` unless the caller says otherwise.
- ``--json`` keeps the numbers; where a document shows an enumeration or a status word it
  gives the name beside the number (e.g. ``"status": 7, "status_name": "ERROR"``).

Each enumeration itself has one home: the layer states in ``controller.decision``, the
service states, fault codes and status bits in ``bit3.layout``, a world-model variable's
values in its ``VarSpec.enum`` (stored with the model, so tools read them without the
controller's code).
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

#: what :func:`flag_names` shows for a word with no bit set
CLEAR = "ok"


def wrap_angle(a: float) -> float:
    """``a`` (rad) in (-pi, pi]: the one way an angle is shown."""
    return math.pi - (math.pi - float(a)) % math.tau


def _pairs(names: Mapping[int, str] | Iterable[Any]) -> Mapping[int, str]:
    if isinstance(names, Mapping):
        return names
    out: dict[int, str] = {}
    for x in names:  # an IntEnum class or (value, name) pairs
        if isinstance(x, tuple):
            out[int(x[0])] = str(x[1])
        else:
            out[int(x)] = str(getattr(x, "name", x)).replace("_", " ")
    return out


def name_of(value: int, names: Mapping[int, str] | Iterable[Any]) -> str:
    """The name of ``value`` in ``names`` (a dict, an IntEnum class or (value, name) pairs),
    or ``"7 (unknown)"``."""
    try:
        v = int(value)
    except (TypeError, ValueError):
        return f"{value} (unknown)"
    n = _pairs(names).get(v)
    return n if n is not None else f"{v} (unknown)"


def named(value: int, names: Mapping[int, str] | Iterable[Any]) -> str:
    """``"ERROR (7)"``: the name and the number; ``"12 (unknown)"`` outside the enumeration."""
    try:
        v = int(value)
    except (TypeError, ValueError):
        return f"{value} (unknown)"
    n = _pairs(names).get(v)
    return f"{n} ({v})" if n is not None else f"{v} (unknown)"


def flag_names(value: int, names: Mapping[int, str], clear: str = CLEAR) -> str:
    """The names of the bits set in ``value``, joined by ``|`` (bits without a name as
    ``0x..``); ``clear`` when no bit is set."""
    v = int(value)
    if not v:
        return clear
    out = [n for b, n in names.items() if v & b]
    rest = v & ~sum(names)
    if rest:
        out.append(f"0x{rest:X}")
    return "|".join(out)


def value_of(text: str, names: Mapping[int, str] | Iterable[Any]) -> int | None:
    """The number whose name is ``text`` (case, spaces and underscores do not matter), or
    None: lets a person type ``PLAY`` where ``2`` is meant."""
    key = text.strip().upper().replace("_", " ").replace("-", " ")
    key = " ".join(key.split())
    for v, n in _pairs(names).items():
        if " ".join(n.upper().replace("_", " ").replace("-", " ").split()) == key:
            return v
    return None
