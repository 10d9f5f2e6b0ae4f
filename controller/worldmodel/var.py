"""World-model variables a tool can follow: each layer declares its variables once, as
typed attributes of a :class:`VarGroup` (in the spirit of ophyd-async's ``SignalR[float]``).

A :class:`Var` *is* its name (a ``str``: ``DAQ.joint_angle_rad == "daq.joint_angle_rad"``),
so it goes wherever a name went: ``wm.get(DAQ.joint_angle_rad)``, ``get_task_inputs``,
the keys of ``post_task_outputs``. It also carries its :class:`VarSpec` (area, dtype and
shape, writer, units, doc), from which the layer's variable table is made
(:meth:`VarGroup.specs`): the table and the code that reads and writes cannot drift, a
misspelt variable is an ``AttributeError`` at import or wiring (and a mypy error), and
"find references" on ``DAQ.joint_angle_rad`` finds every reader and writer. The type
parameter says what a read gives (``Var[np.ndarray]``, ``Var[int]``, ``Var[bool]``).

The names are unchanged: the CLI, the console, recordings and the segment's table JSON see
plain strings (a ``Var``'s repr, str, format, hash and equality are its name's; it pickles
as a plain ``str``).

Declaring::

    class DaqVars(VarGroup, prefix="daq", writer="daq"):
        joint_angle_rad: Var[np.ndarray] = var("task_io", "f8", (6,), [0.0] * 6, "rad", doc="...")

    DAQ = DaqVars  # DAQ.joint_angle_rad is the Var "daq.joint_angle_rad"

Speed: the variable's ``VarSpec.name`` is the ``Var`` object itself, so the model's tables
are keyed by it and a lookup with the ``Var`` hits by identity; a plain string still finds
it (a string compare). Per-frame code keeps its name tuples in module or class constants,
as it kept literals (measured: docs/world-model.md "Variables a tool can follow").
"""

from __future__ import annotations

from typing import Any, ClassVar, Generic, TypeVar

from controller.worldmodel.spec import UNIT_QUATERNION, VarSpec, WorldModelError

__all__ = ["UNIT_QUATERNION", "Var", "VarGroup", "var"]

T = TypeVar("T")


class Var(str, Generic[T]):
    """One world-model variable: its name (the ``str`` itself) and its :attr:`spec`."""

    spec: VarSpec

    def __new__(cls, spec: VarSpec) -> "Var[T]":
        self = super().__new__(cls, spec.name)
        self.spec = spec
        object.__setattr__(spec, "name", self)  # the model's tables are keyed by this very object
        return self

    @property
    def name(self) -> str:
        return str.__str__(self)

    @property
    def writer(self) -> str:
        return self.spec.writer

    @property
    def units(self) -> str:
        return self.spec.units

    @property
    def doc(self) -> str:
        return self.spec.doc

    # repr, str, format, hash and == are the name's (a Var is a str): the world model's layout
    # signature (repr of the names) and every message that names a variable are unchanged

    def __reduce__(self) -> Any:  # pickles (multiprocessing, recordings) as the plain name
        return (str, (str(self),))


class _Decl:
    """A declaration inside a :class:`VarGroup` body, made a :class:`Var` by the group."""

    __slots__ = ("args", "kw")

    def __init__(self, args: tuple, kw: dict) -> None:
        self.args, self.kw = args, kw


def var(area: str, dtype: str, shape: tuple | int = (), initial: Any = 0, units: str = "", *,
        name: str = "", writer: str = "", **kw: Any) -> Any:
    """Declare a variable in a :class:`VarGroup` body (the arguments of :class:`VarSpec`,
    without name and writer). ``name=``: a full name outside the group's prefix (a layer
    that writes another's name space, ``servo.q_cmd_rad`` written by the Joint Planner);
    ``writer=``: another writer than the group's (``"user"`` for a user request)."""
    return _Decl((area, dtype, shape, initial, units), dict(kw, name=name, writer=writer))


class VarGroup:
    """The variables of one layer (or task): subclass with ``prefix=`` and ``writer=``, one
    attribute per variable, each made with :func:`var`. The class is the namespace; it is
    never instantiated."""

    prefix: ClassVar[str] = ""
    writer: ClassVar[str] = ""
    _vars: ClassVar[tuple[Var, ...]] = ()
    _attrs: ClassVar[tuple[tuple[str, Var], ...]] = ()

    def __init_subclass__(cls, prefix: str = "", writer: str = "", **kw: Any) -> None:
        super().__init_subclass__(**kw)
        cls.prefix, cls.writer = prefix, writer or prefix
        made: list[tuple[str, Var]] = []
        for attr, decl in list(vars(cls).items()):
            if not isinstance(decl, _Decl):
                continue
            area, dtype, shape, initial, units = decl.args
            extra = dict(decl.kw)
            name = extra.pop("name") or f"{prefix}.{attr}"
            writer_ = extra.pop("writer") or cls.writer
            if not name or name.startswith("."):
                raise WorldModelError(f"{cls.__name__}.{attr}: the group has no prefix and the variable no name")
            v: Var = Var(VarSpec(name, area, dtype, shape, writer_, initial, units, **extra))
            setattr(cls, attr, v)
            made.append((attr, v))
        cls._attrs = tuple(made)
        cls._vars = tuple(v for _, v in made)

    @classmethod
    def all(cls) -> tuple[Var, ...]:
        """The group's variables, in declaration order."""
        return cls._vars

    @classmethod
    def attributes(cls) -> tuple[tuple[str, Var], ...]:
        """(attribute, variable) pairs, in declaration order."""
        return cls._attrs

    @classmethod
    def specs(cls) -> list[VarSpec]:
        """The group's rows of the variable table, in declaration order."""
        return [v.spec for v in cls._vars]
