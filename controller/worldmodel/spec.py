"""World-model variable specifications: :class:`VarSpec`, the areas, who may set a
variable (``VarSpec.user``), and the value check every post and user write goes through.

Rules kept here (IRSS report 2.2.2 rules 3 and 4, 2.3.6 areas):

- every variable has a name, an area (:data:`AREAS`), a numpy dtype and shape, units, a
  doc string and exactly one writer (report rule 3);
- every variable holds a valid value from creation on (rule 4); every posted value is
  checked by :func:`coerce` (shape, dtype range, finite floats) before it is queued;
- a user-interface write is allowed only for variables that declare it (``VarSpec.user``:
  task outputs, layer commands and statuses never, control-law parameters only while
  powered down, requests always);
- an enumerated variable (``VarSpec.enum``: a state, status, mode or error code) holds only
  the values of its enumeration: any other is refused by :func:`coerce`, whoever posts it,
  and tools show it by name (``VarSpec.value_text``, pfma/show.py). A bit set
  (``VarSpec.flags``) is shown by the names of its bits.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

import numpy as np

from pfma.errors import PfmaError
from pfma.show import flag_names, named

#: the report's world-model areas (2.3.6: task input/output, task internal status, command
#: input, status output, control flags, response output, error reports). The report says
#: "8 separate areas" but names seven kinds; its task input/output is counted twice there.
AREAS = ("task_io", "task_status", "command_input", "status_output", "control_flags",
         "response_output", "error_reports")

#: who may set a variable through :meth:`WorldModel.set_user` / ``pfma wm set`` (``VarSpec.user``)
USER_NEVER, USER_POWERED_DOWN, USER_ALWAYS = "never", "powered_down", "always"
USER_MODES = (USER_NEVER, USER_POWERED_DOWN, USER_ALWAYS)
#: writer names that stand for the user interface: only their variables may be user-set (a
#: user write of a variable a task or table posts would give it a second writer, rule 3)
USER_WRITERS = ("user", "user_interface")
#: areas users may set (if the writer is the user interface); the default ``user`` of a
#: user-written variable there. Task status, status output, response output and error
#: reports describe what a task did: never user-set.
USER_AREAS = {"command_input": USER_ALWAYS, "task_io": USER_ALWAYS, "control_flags": USER_POWERED_DOWN}
#: what a variable of each area is, in a refusal ("... is an output of task servo")
_AREA_ROLE = {"task_io": "an output of task", "task_status": "a status of task",
              "command_input": "a layer command posted by", "status_output": "a status posted by",
              "control_flags": "a control flag posted by", "response_output": "a response posted by",
              "error_reports": "an error report posted by"}

_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_.\-]{0,63}$")

_TAU = 2.0 * math.pi
#: Rule 4 of report 2.2.2 ("always a valid value, in type, scope and magnitude"): the valid
#: range a float variable has by its units when it declares none of its own (``valid=``).
#: Assumed, and deliberately wide: several times anything the PFMA can reach or drive
#: (pfma-model: a reach of about 2 m, joint rates about 1 rad/s, amplifier currents about
#: 10 A, an F/T range of hundreds of N), so that a value outside is no reading or command of
#: this arm, whatever produced it, and a healthy arm never meets a bound. A float whose units
#: have no row here ("", "1") declares its own; tests/controller/test_valid_values.py checks
#: that every variable of the controller's table has one.
UNIT_RANGES: dict[str, tuple[float, float]] = {
    "rad": (-2 * _TAU, 2 * _TAU), "deg": (-720.0, 720.0), "rad/s": (-50.0, 50.0), "rad/s^2": (-1e3, 1e3),
    "m": (-10.0, 10.0), "m/s": (-10.0, 10.0), "m/s^2": (-1e3, 1e3), "m|rad": (-2 * _TAU, 2 * _TAU),
    "A": (-100.0, 100.0), "N": (-1e4, 1e4), "N*m": (-1e4, 1e4), "N|N*m": (-1e4, 1e4),
    "N/m|N*m/rad": (0.0, 1e7), "N*s/m|N*m*s/rad": (0.0, 1e6), "kg|kg*m^2": (0.0, 1e4),
    "1/s": (0.0, 1e4), "Hz": (0.0, 1e6), "s": (0.0, 1e9), "us": (-1e9, 1e9),
}
#: ``valid=`` of a unit quaternion's components (and rounding: |q| = 1 + 2e-16)
UNIT_QUATERNION = (-1.0 - 1e-6, 1.0 + 1e-6)


class WorldModelError(PfmaError):
    """A world-model rule was broken (unknown variable, second writer, key, read-only ...)."""


class WorldModelValueError(WorldModelError, ValueError):
    """A value does not fit its variable (shape, type, range, not finite)."""



def _freeze(v: Any) -> Any:
    """Lists -> tuples, numpy -> Python scalars (hashable, JSON-round-trip equal)."""
    if isinstance(v, np.ndarray):
        v = v.tolist()
    elif isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, (list, tuple)):
        return tuple(_freeze(x) for x in v)
    return v


def _dtype(text: str, where: str) -> np.dtype:
    try:
        dt = np.dtype(text)
    except TypeError as err:
        raise WorldModelError(f"{where}: dtype {text!r} is not a numpy dtype ({err})") from None
    if dt.kind not in "biuf" or dt.fields is not None or dt.subdtype is not None:
        raise WorldModelError(f"{where}: dtype {text!r} is not a plain number/bool type "
                              f"(use f4, f8, i1..i8, u1..u8 or b1)")
    if not dt.isnative:
        raise WorldModelError(f"{where}: dtype {text!r} is not in this machine's byte order")
    return dt


@dataclass(frozen=True)
class VarSpec:
    """One world-model variable.

    :param name: unique name (letters, digits, ``_ . -``; up to 64 characters)
    :param area: one of :data:`AREAS`
    :param dtype: numpy type string (``"f8"``, ``"i4"``, ``"u2"``, ``"i2"``, ``"b1"``, ...)
    :param shape: ``()`` for a scalar, else the array shape
    :param writer: the one task or layer allowed to post it
    :param initial: its valid value from creation on
    :param units: e.g. ``"rad"``, ``"N"``, ``"rad/s"`` (empty for counts, states, flags)
    :param protected: control-law parameter etc.: no user write while powered up (the
        same as ``user="powered_down"``; kept equal to ``user == "powered_down"``)
    :param doc: one line for someone reading ``pfma wm list``
    :param user: who may set it with a keyed user write (:meth:`WorldModel.set_user`):
        ``"never"`` (a task or table posts it), ``"powered_down"`` (control-law parameter),
        ``"always"`` (a request or an operator setting safe live). Default (``""``): derived
        from the writer and area, see :func:`default_user`. Only a variable whose writer is
        the user interface (:data:`USER_WRITERS`) in an area of :data:`USER_AREAS` may be
        anything but ``"never"``.
    :param enum: the values an integer scalar may hold, with their names: a dict
        ``{0: "HOLD", 1: "TELEOP"}``, an IntEnum class or ``(value, name)`` pairs (stored
        as sorted pairs). Every other value is refused, whoever posts it (:func:`coerce`).
    :param flags: the names of the bits of an integer scalar that is a bit set (shown by
        name; any combination is a valid value)
    :param choices: the only values a *user* write may give a scalar variable that is not
        enumerated (a parameter such as ``joint.shoulder_roll_deg``: numbers, no names; empty:
        any value of its type); a user write of another value is refused naming them
        (:func:`coerce_user`). Task posts are not checked against them (the frame path).
        Both refusals read the same: ``"msp.mode: 7 is not one of its values (0 IDLE, ...)"``
        (:meth:`value_refusal`).
    :param valid: ``(lo, hi)``, the closed range every element must lie in, whoever posts it
        (report 2.2.2 rule 4); a float variable without one takes its units' range from
        :data:`UNIT_RANGES` (:attr:`bounds`). A post outside is refused naming the variable
        and the range (:meth:`range_refusal`), as a user write is.
    """

    name: str
    area: str
    dtype: str
    shape: tuple = ()
    writer: str = ""
    initial: Any = 0
    units: str = ""
    protected: bool = False
    doc: str = ""
    user: str = ""
    enum: Any = ()
    flags: Any = ()
    choices: tuple = ()
    valid: tuple = ()

    def __post_init__(self) -> None:
        where = f"world-model variable {self.name!r}"
        dt, shape = self._check_type(where)
        self._check_named_values(where, dt)
        self._check_valid(where, dt)
        self._check_initial(where)
        self._check_user(where)
        self._check_choices(where, shape)
        # derived once: the controller reads variables thousands of times a second
        object.__setattr__(self, "_np_dtype", np.dtype(self.dtype))
        object.__setattr__(self, "_count", int(np.prod(self.shape, dtype=np.int64)))

    def _check_type(self, where: str) -> tuple[np.dtype, tuple]:
        """Name, area, dtype, shape and writer checked; dtype and shape made canonical.
        Returns the dtype and the shape as given (as a tuple, for later messages)."""
        if not isinstance(self.name, str) or not _NAME_RE.match(self.name):
            raise WorldModelError(f"{where}: bad name (letters, digits, '_', '.', '-'; "
                                  f"starts with a letter; at most 64 characters)")
        if self.area not in AREAS:
            raise WorldModelError(f"{where}: area {self.area!r} is not one of {', '.join(AREAS)}")
        dt = _dtype(self.dtype, where)
        object.__setattr__(self, "dtype", dt.str[1:])  # canonical: "f8", "i2", "b1"
        shape = (self.shape,) if isinstance(self.shape, int) else tuple(self.shape)
        if any((not isinstance(n, (int, np.integer))) or n < 1 for n in shape):
            raise WorldModelError(f"{where}: shape {self.shape!r} must be positive integers")
        object.__setattr__(self, "shape", tuple(int(n) for n in shape))
        if not isinstance(self.writer, str) or not self.writer.strip():
            raise WorldModelError(f"{where}: needs exactly one writer (a task or layer name)")
        return dt, shape

    def _check_named_values(self, where: str, dt: np.dtype) -> None:
        """``enum`` and ``flags`` stored as sorted pairs (and as maps), checked to fit."""
        for what in ("enum", "flags"):
            pairs = _named_values(getattr(self, what), f"{where}: {what}")
            if pairs and (self.shape != () or dt.kind not in "iu"):
                raise WorldModelError(f"{where}: {what} needs an integer scalar, not {self.type_text}")
            if pairs and not all(np.iinfo(dt).min <= v <= np.iinfo(dt).max for v, _ in pairs):
                raise WorldModelError(f"{where}: {what} has a value outside {dt.name}")
            object.__setattr__(self, what, pairs)
        if self.enum and self.flags:
            raise WorldModelError(f"{where}: an enumeration or a bit set, not both")
        object.__setattr__(self, "_enum_map", dict(self.enum))
        object.__setattr__(self, "_flag_map", dict(self.flags))

    def _check_initial(self, where: str) -> None:
        try:
            value = coerce(self, self.initial)
        except WorldModelValueError as err:
            raise WorldModelError(f"{where}: initial value is not valid (report rule 4: every "
                                  f"variable holds a valid value after initialisation): {err}") from None
        object.__setattr__(self, "initial", _freeze(value))

    def _check_user(self, where: str) -> None:
        """``user`` derived if not given and checked against the writer and area; ``protected``
        kept equal to ``user == "powered_down"``."""
        user = self.user or default_user(self.area, self.writer, bool(self.protected))
        if user not in USER_MODES:
            raise WorldModelError(f"{where}: user {self.user!r} is not one of {', '.join(USER_MODES)}")
        if self.protected and user != USER_POWERED_DOWN:
            raise WorldModelError(f"{where}: protected=True means user='powered_down', not {user!r}")
        if user != USER_NEVER and (self.writer not in USER_WRITERS or self.area not in USER_AREAS):
            raise WorldModelError(
                f"{where}: user={user!r} (or protected=True) needs the user interface as its one "
                f"writer ({' or '.join(map(repr, USER_WRITERS))}) in area "
                f"{', '.join(USER_AREAS)}; it is {self.area} written by {self.writer!r}, and a user "
                f"write would give it a second writer")
        object.__setattr__(self, "user", user)
        object.__setattr__(self, "protected", user == USER_POWERED_DOWN)

    def _check_valid(self, where: str, dt: np.dtype) -> None:
        """``valid`` checked (two finite numbers, lo <= hi, a number variable that is not
        enumerated) and :attr:`bounds` derived: it, or the units' range for a float."""
        bounds: tuple = ()
        if self.valid:
            try:
                lo, hi = (float(x) for x in self.valid)
            except (TypeError, ValueError):
                raise WorldModelError(f"{where}: valid={self.valid!r} is not a (lo, hi) pair of numbers") from None
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise WorldModelError(f"{where}: valid={self.valid!r}: two finite numbers, lo <= hi")
            if dt.kind == "b" or self.enum or self.flags:
                raise WorldModelError(f"{where}: valid= is for a number variable that is not an "
                                      f"enumeration or a bit set")
            if dt.kind in "iu":
                lo, hi = int(math.ceil(lo)), int(math.floor(hi))
                if lo > hi:
                    raise WorldModelError(f"{where}: valid={self.valid!r} holds no integer")
            bounds = (lo, hi)
            object.__setattr__(self, "valid", bounds)
        elif dt.kind == "f" and self.units in UNIT_RANGES:
            bounds = UNIT_RANGES[self.units]
        object.__setattr__(self, "_bounds", bounds)

    @property
    def bounds(self) -> tuple:
        """``(lo, hi)`` every element must lie in (its own ``valid`` or its units' range);
        ``()``: its type's whole (finite) range."""
        return self._bounds

    def range_text(self) -> str:
        """``"-50..50 rad/s"``; empty without bounds."""
        if not self._bounds:
            return ""
        lo, hi = self._bounds
        return f"{lo:g}..{hi:g}" + self._unit_suffix()

    def _unit_suffix(self) -> str:
        return f" {self.units}" if self.units not in ("", "1") else ""

    def range_refusal(self, bad: Any) -> str:
        """The one refusal of a value outside :attr:`bounds`:
        ``"servo.rate_cmd_rad_s: 80 rad/s is outside its valid range -50..50 rad/s"``."""
        return f"{self.name}: {bad:g}{self._unit_suffix()} is outside its valid range {self.range_text()}"

    def _check_choices(self, where: str, shape: tuple) -> None:
        """``choices`` coerced to the variable's type and checked (``shape``: as given)."""
        if not self.choices:
            object.__setattr__(self, "choices", ())
            return
        if shape != ():
            raise WorldModelError(f"{where}: choices need a scalar variable, not shape {shape}")
        if self.enum or self.flags:
            raise WorldModelError(f"{where}: choices or an enumeration/bit set, not both "
                                  f"(an enumeration already limits its values)")
        try:
            choices = tuple(coerce(self, c).item() for c in self.choices)
        except WorldModelValueError as err:
            raise WorldModelError(f"{where}: a choice is not a valid value: {err}") from None
        object.__setattr__(self, "choices", choices)
        if self.initial not in choices:
            raise WorldModelError(f"{where}: initial value {self.initial!r} is not one of its choices "
                                  f"{', '.join(map(str, choices))}")

    @property
    def np_dtype(self) -> np.dtype:
        return self._np_dtype

    @property
    def count(self) -> int:
        """Number of elements (1 for a scalar)."""
        return self._count

    @property
    def nbytes(self) -> int:
        return self._count * self._np_dtype.itemsize

    @property
    def type_text(self) -> str:
        """``"f8"``, ``"f8[6]"``, ``"f8[3,3]"``."""
        return self.dtype + (f"[{','.join(map(str, self.shape))}]" if self.shape else "")

    @property
    def is_state(self) -> bool:
        """An integer scalar: usable with get/post_state_variable."""
        return self.shape == () and self.np_dtype.kind in "iu"

    @property
    def enum_names(self) -> dict[int, str]:
        """The enumeration as ``{value: name}`` (empty: not enumerated)."""
        return self._enum_map

    @property
    def flag_names(self) -> dict[int, str]:
        """The bit set's names as ``{bit: name}`` (empty: not a bit set)."""
        return self._flag_map

    def value_text(self, value: Any) -> str | None:
        """An enumerated value as ``"ERROR (7)"``, a bit set as ``"resolver|F/T link (5)"``
        (pfma/show.py); None for any other variable (the caller shows the number)."""
        if self._enum_map:
            return named(int(np.asarray(value).item()), self._enum_map)
        if self._flag_map:
            v = int(np.asarray(value).item())
            return f"{flag_names(v, self._flag_map, clear='none')} ({v})"
        return None

    def enum_text(self) -> str:
        """The enumeration in one line: ``0 HOLD, 1 TELEOP, 2 TRAJECTORY``."""
        return ", ".join(f"{v} {n}" for v, n in self.enum)

    def values_text(self) -> str:
        """The values it may take, in one line: the enumeration (:meth:`enum_text`) or the
        choices with the units (``-90, -45, 0, 45, 90 deg``); empty if any value of its type."""
        if self.enum:
            return self.enum_text()
        if self.choices:
            return ", ".join(f"{c:g}" for c in self.choices) + (f" {self.units}" if self.units else "")
        return ""

    def value_refusal(self, shown: Any) -> str:
        """The one refusal of a value outside the enumeration or the choices:
        ``"msp.mode: 7 is not one of its values (0 IDLE, 1 RECORD, 2 PLAY)"``,
        ``"joint.shoulder_roll_deg: 30 deg is not one of its values (-90, ..., 90 deg)"``.
        Short: the owner's verdict in the request ring keeps 96 bytes of it."""
        if isinstance(shown, (int, float)) and not self.enum:
            shown = f"{shown:g}" + (f" {self.units}" if self.units else "")
        return f"{self.name}: {shown} is not one of its values ({self.values_text()})"

    def user_refusal(self, powered_up: bool) -> str | None:
        """Why a user may not set this variable now, or None if one may."""
        if self.user == USER_ALWAYS or (self.user == USER_POWERED_DOWN and not powered_up):
            return None
        if self.user == USER_POWERED_DOWN:
            return (f"{self.name} is protected: it may be set only while powered down "
                    f"(the system is powered up)")
        if self.writer in USER_WRITERS:
            return f"{self.name} (writer {self.writer}) is declared user='never'; users may not set it"
        return f"{self.name} is {_AREA_ROLE[self.area]} {self.writer}; users may not set it"

    def to_json(self) -> dict:
        out = {"name": self.name, "area": self.area, "dtype": self.dtype, "shape": list(self.shape),
               "writer": self.writer, "initial": _jsonable(self.initial), "units": self.units,
               "protected": self.protected, "doc": self.doc, "user": self.user}
        if self.enum:
            out["enum"] = [[v, n] for v, n in self.enum]
        if self.flags:
            out["flags"] = [[v, n] for v, n in self.flags]
        if self.choices:
            out["choices"] = list(self.choices)
        if self.valid:
            out["valid"] = list(self.valid)
        return out

    @classmethod
    def from_json(cls, d: Mapping) -> "VarSpec":
        protected = bool(d.get("protected", False))
        user = d.get("user")
        if user is None:  # a table written before "user" existed: today's rule, never an error
            user = default_user(d["area"], d["writer"], protected, strict=False)
            protected = user == USER_POWERED_DOWN
        return cls(name=d["name"], area=d["area"], dtype=d["dtype"], shape=tuple(d["shape"]),
                   writer=d["writer"], initial=d["initial"], units=d.get("units", ""),
                   protected=protected, doc=d.get("doc", ""), user=user,
                   enum=tuple((int(v), str(n)) for v, n in d.get("enum", ())),
                   flags=tuple((int(v), str(n)) for v, n in d.get("flags", ())),
                   choices=tuple(d.get("choices", ())), valid=tuple(d.get("valid", ())))


def _named_values(given: Any, where: str) -> tuple[tuple[int, str], ...]:
    """``VarSpec.enum`` / ``flags`` as sorted ``(value, name)`` pairs, from a dict, an
    IntEnum class, IntEnum members or pairs (a member's name with "_" read as " "); every
    value an integer, every name a distinct non-empty text."""
    if not given:
        return ()
    items: Iterable[Any] = given.items() if isinstance(given, Mapping) else given
    items = [(x.value, x.name.replace("_", " ")) if isinstance(x, enum.Enum) else x for x in items]
    out: dict[int, str] = {}
    for pair in items:
        try:
            v, n = pair
        except (TypeError, ValueError):
            raise WorldModelError(f"{where}: {pair!r} is not a (value, name) pair") from None
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not isinstance(n, str) or not n.strip():
            raise WorldModelError(f"{where}: {pair!r} needs an integer value and a name")
        if int(v) in out:
            raise WorldModelError(f"{where}: value {int(v)} named twice")
        out[int(v)] = n
    if len(set(out.values())) != len(out):
        raise WorldModelError(f"{where}: a name is given to two values")
    return tuple(sorted(out.items()))


def default_user(area: str, writer: str, protected: bool = False, *, strict: bool = True) -> str:
    """The ``user`` of a variable that does not declare one.

    ``"never"`` unless the writer is the user interface (:data:`USER_WRITERS`) and the area
    is in :data:`USER_AREAS`; there ``protected=True`` gives ``"powered_down"``, otherwise the
    area's default (requests in command_input and task_io: ``"always"``; parameters in
    control_flags: ``"powered_down"``). ``protected=True`` on any other variable is an error
    (``strict``) or ``"never"`` (reading an old segment's table).
    """
    if writer in USER_WRITERS and area in USER_AREAS:
        return USER_POWERED_DOWN if protected else USER_AREAS[area]
    if protected and strict:
        return USER_POWERED_DOWN  # refused by VarSpec with the reason
    return USER_NEVER


def _jsonable(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_jsonable(x) for x in v]
    return v


def _where(spec: VarSpec) -> str:
    """The variable as named in error messages (built only when one is raised)."""
    return f"world-model variable {spec.name!r} ({spec.type_text}" + (f" {spec.units})" if spec.units else ")")


def coerce(spec: VarSpec, value: Any) -> np.ndarray:
    """``value`` as a C-contiguous array of the variable's dtype and shape.

    :raises WorldModelValueError: wrong shape, a non-number, an integer out of range or a
        fractional/bool value for an integer, a non-finite float
    """
    dt = np.dtype(spec.dtype)
    try:
        a = np.asarray(value)
    except (ValueError, TypeError) as err:  # ragged lists
        raise WorldModelValueError(f"{_where(spec)}: {value!r} is not a regular array ({err})") from None
    if a.shape != spec.shape:
        raise WorldModelValueError(_shape_refusal(spec, a))
    k = a.dtype.kind
    if k not in "biuf":
        raise WorldModelValueError(f"{_where(spec)}: {value!r} is not a number (numpy kind {k!r})")
    if dt.kind == "b":
        return _coerce_bool(spec, dt, a, value)
    if k == "b":
        raise WorldModelValueError(f"{_where(spec)}: a boolean given for a {dt.name} variable")
    if dt.kind in "iu":
        return _coerce_int(spec, dt, a, value)
    return _coerce_float(spec, dt, a)


def _shape_refusal(spec: VarSpec, a: np.ndarray) -> str:
    got = "a scalar" if a.shape == () else f"shape {a.shape}"
    want = "a scalar" if spec.shape == () else f"shape {spec.shape}"
    return f"{_where(spec)}: {got} given, {want} expected"


def _coerce_bool(spec: VarSpec, dt: np.dtype, a: np.ndarray, value: Any) -> np.ndarray:
    """:func:`coerce` for a boolean variable: booleans, or integers 0/1."""
    k = a.dtype.kind
    if k != "b" and not (k in "iu" and bool(np.all((a == 0) | (a == 1)))):
        raise WorldModelValueError(f"{_where(spec)}: boolean variable needs true/false or 0/1, got {value!r}")
    return np.array(a, dtype=dt, order="C")


def _coerce_int(spec: VarSpec, dt: np.dtype, a: np.ndarray, value: Any) -> np.ndarray:
    """:func:`coerce` for an integer variable (``a``: integers or floats, not booleans):
    no floats, in the dtype's range, one of the enumeration if any."""
    if a.dtype.kind == "f":
        raise WorldModelValueError(f"{_where(spec)}: a float given for an integer variable ({value!r})")
    if a.size:
        info = np.iinfo(dt)
        lo, hi = int(a.min()), int(a.max())
        if lo < info.min or hi > info.max:
            raise WorldModelValueError(f"{_where(spec)}: {lo if lo < info.min else hi} is outside "
                                       f"{dt.name} range [{info.min}, {info.max}]")
    if spec.enum and int(a.item()) not in spec.enum_names:
        raise WorldModelValueError(spec.value_refusal(int(a.item())))
    out = np.array(a, dtype=dt, order="C")
    _check_bounds(spec, out)
    return out


def _check_bounds(spec: VarSpec, out: np.ndarray) -> None:
    """Every element inside the variable's :attr:`VarSpec.bounds` (rule 4)."""
    b = spec.bounds
    if b and out.size:
        lo, hi = b
        xs = out.ravel().tolist()  # Python numbers: no numpy reduction on the frame path
        amin, amax = min(xs), max(xs)
        if amin < lo or amax > hi:
            raise WorldModelValueError(spec.range_refusal(amin if amin < lo else amax))


def _coerce_float(spec: VarSpec, dt: np.dtype, a: np.ndarray) -> np.ndarray:
    """:func:`coerce` for a float variable (``a``: numbers, not booleans): finite as ``dt``."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(a, dtype=dt, order="C")
    if not bool(np.all(np.isfinite(out))):
        bad = (a if a.shape == () else a[~np.isfinite(out)][0]).item()
        raise WorldModelValueError(f"{_where(spec)}: value {bad!r} is not finite as {dt.name}")
    _check_bounds(spec, out)
    return out


def coerce_user(spec: VarSpec, value: Any) -> np.ndarray:
    """:func:`coerce`, then the variable's allowed values (``VarSpec.choices``): the check of
    every user write (``set_user`` when it is made and again when the owner applies it, the
    console's editor). Task posts go through :func:`coerce` alone.

    :raises WorldModelValueError: the value does not fit the variable, or is not one of its choices
    """
    out = coerce(spec, value)
    if spec.choices and out.item() not in spec.choices:
        raise WorldModelValueError(spec.value_refusal(out.item()))
    return out
