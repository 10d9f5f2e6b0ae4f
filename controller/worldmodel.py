"""The controller's world model: the IRSS "blackboard" of named, typed variables.

Source: IRSS report (/work/shared/seeds/000_02a18717a950f150.txt) sections 2.2.2 (world
model rules 1-4), 2.2.3 (communications segment, world model locked out while it is
updated), 2.3.5 "Access Tools" (get-task-inputs, get-state-variable, post-task-outputs,
post-state-variable; asynchronous user-interface access) and 2.3.6 (areas; "Assurance of
World Model Access Validity": the temporary queue and the COMM-INTERRUPT / IN-COMM-FRAME
flags), 2.2.8 (display windows cannot modify data "without proper access keys").

Rules kept here:

- every variable has a name, an area (:data:`AREAS`), a numpy dtype and shape, units, a
  doc string and exactly one writer (report rule 3); a post by anyone else is refused
  with an error that names the owner;
- every variable holds a valid value from :meth:`WorldModel.create` on (rule 4); every
  posted value is checked (shape, dtype range, finite floats) before it is queued;
- posts are queued and applied all together by :meth:`WorldModel.communications_segment`
  under one sequence lock, so a reader (this process or another) never sees half a frame;
- a user-interface write (:meth:`WorldModel.set_user`, ``pfma wm set``) is allowed only for
  variables that declare it (``VarSpec.user``: task outputs, layer commands and statuses
  never, control-law parameters only while powered down, requests always), needs the access
  key, and goes through a small request ring in the segment that the owner applies, after
  checking all of it again, at its next communications segment.

**IRSS queue logic in Python.** IRSS posted into a temporary queue that the
communications-frame interrupt flushed; the COMM-INTERRUPT and IN-COMM-FRAME flags kept
an interrupt from flushing a half-written queue entry, or from missing one written but
not yet marked valid. Here a post is validated and converted into a private array
*first*, then inserted into the pending queue under a ``threading.Lock`` in one step
(an entry is never half there). :meth:`WorldModel.communications_segment` sets
:attr:`WorldModel.in_comm_frame`, swaps the whole pending queue for an empty one under
the same lock (the COMM-INTERRUPT moment), applies the swapped batch under the sequence
lock, and clears the flag. A post that arrives while a segment is flushing therefore
lands in the new queue and goes out with the *next* segment (counted in
``stats()["deferred_posts"]``); it is never lost and never half applied. Readers in the
owning process pend on a lock during the flush (IRSS: accesses "pend until the end of
the communications frame"); readers in other processes retry on the sequence lock.

The segment layout (header, spec JSON, request ring, seqlocked data body) is in
``docs/world-model.md``. The sequence lock, the shared-memory open without the
resource-tracker, the liveness check and the byte lock are those of the Bit3 buffer
(:mod:`bit3.buffer`), including its x86-64 memory-ordering argument.
"""

from __future__ import annotations

import difflib
import hashlib
import hmac
import json
import os
import re
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from bit3.buffer import lock_byte, open_shm, pid_alive
from bit3.layout import SEQ_BLOCK  # the SeqLock counter block before the body
from bit3.seqlock import SeqLock
from pfma.clock import MonotonicClock
from pfma.errors import PfmaError

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

#: the access key a model gets when none is given and PFMA_WM_KEY is not set
DEFAULT_ACCESS_KEY = "pfma"
#: environment variable overriding the default access key (creator and ``pfma wm set``)
ACCESS_KEY_ENV = "PFMA_WM_KEY"
#: shared-memory name the controller runtime and ``pfma wm`` use when none is given
DEFAULT_NAME = "pfma_wm"

MAGIC = b"PFMA-WM\0"
FORMAT_VERSION = 1
HEADER_SIZE = 512
#: user-request ring: slots, fixed part of a slot, minimum value payload
REQUEST_SLOTS = 16
SLOT_HEADER = 192
MIN_PAYLOAD = 64
READ_TIMEOUT_S = 0.1

#: header field -> (offset, struct format); all little-endian, naturally aligned
HEADER_FIELDS: dict[str, tuple[int, str]] = {
    "magic": (0, "8s"), "version": (8, "I"), "header_size": (12, "I"),
    "total_size": (16, "Q"), "spec_offset": (24, "Q"), "spec_len": (32, "Q"),
    "spec_hash": (40, "8s"), "req_offset": (48, "Q"), "req_slots": (56, "I"),
    "req_slot_size": (60, "I"), "seq_offset": (64, "Q"), "body_size": (72, "Q"),
    "powered_up": (80, "I"), "owner_pid": (84, "i"), "frame": (88, "Q"),
    "frame_t_s": (96, "d"), "created_ns": (104, "Q"), "req_next_id": (112, "Q"),
    "lock_byte": (120, "Q"), "user_applied": (128, "Q"), "user_rejected": (136, "Q"),
    "owner_name": (144, "32s"), "key_salt": (176, "16s"), "key_hash": (192, "32s"),
}
#: request-slot field -> (offset, struct format)
SLOT_FIELDS: dict[str, tuple[int, str]] = {
    "state": (0, "I"), "var_index": (4, "I"), "req_id": (8, "Q"), "submit_ns": (16, "Q"),
    "pid": (24, "i"), "nbytes": (28, "I"), "applied_frame": (32, "Q"), "key_hash": (40, "32s"),
    "user": (72, "24s"), "result": (96, "96s"),
}
#: request-slot states
FREE, WRITING, PENDING, APPLIED, REJECTED = 0, 1, 2, 3, 4
STATE_NAMES = {FREE: "free", WRITING: "writing", PENDING: "pending", APPLIED: "applied",
               REJECTED: "rejected"}

_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_.\-]{0,63}$")


class WorldModelError(PfmaError):
    """A world-model rule was broken (unknown variable, second writer, key, read-only ...)."""


class WorldModelValueError(WorldModelError, ValueError):
    """A value does not fit its variable (shape, type, range, not finite)."""


class _WMSeqLock(SeqLock):
    __slots__ = ()
    kind = "world model"


# ----------------------------------------------------------------------------------------
# variable specifications


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

    def __post_init__(self) -> None:
        where = f"world-model variable {self.name!r}"
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
        try:
            value = coerce(self, self.initial)
        except WorldModelValueError as err:
            raise WorldModelError(f"{where}: initial value is not valid (report rule 4: every "
                                  f"variable holds a valid value after initialisation): {err}") from None
        object.__setattr__(self, "initial", _freeze(value))
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
        # derived once: the controller reads variables thousands of times a second
        object.__setattr__(self, "_np_dtype", np.dtype(self.dtype))
        object.__setattr__(self, "_count", int(np.prod(self.shape, dtype=np.int64)))

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
        return {"name": self.name, "area": self.area, "dtype": self.dtype, "shape": list(self.shape),
                "writer": self.writer, "initial": _jsonable(self.initial), "units": self.units,
                "protected": self.protected, "doc": self.doc, "user": self.user}

    @classmethod
    def from_json(cls, d: Mapping) -> "VarSpec":
        protected = bool(d.get("protected", False))
        user = d.get("user")
        if user is None:  # a table written before "user" existed: today's rule, never an error
            user = default_user(d["area"], d["writer"], protected, strict=False)
            protected = user == USER_POWERED_DOWN
        return cls(name=d["name"], area=d["area"], dtype=d["dtype"], shape=tuple(d["shape"]),
                   writer=d["writer"], initial=d["initial"], units=d.get("units", ""),
                   protected=protected, doc=d.get("doc", ""), user=user)


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
        got = "a scalar" if a.shape == () else f"shape {a.shape}"
        want = "a scalar" if spec.shape == () else f"shape {spec.shape}"
        raise WorldModelValueError(f"{_where(spec)}: {got} given, {want} expected")
    k = a.dtype.kind
    if k not in "biuf":
        raise WorldModelValueError(f"{_where(spec)}: {value!r} is not a number (numpy kind {k!r})")
    if dt.kind == "b":
        if k != "b" and not (k in "iu" and bool(np.all((a == 0) | (a == 1)))):
            raise WorldModelValueError(f"{_where(spec)}: boolean variable needs true/false or 0/1, got {value!r}")
        return np.array(a, dtype=dt, order="C")
    if k == "b":
        raise WorldModelValueError(f"{_where(spec)}: a boolean given for a {dt.name} variable")
    if dt.kind in "iu":
        if k == "f":
            raise WorldModelValueError(f"{_where(spec)}: a float given for an integer variable ({value!r})")
        if a.size:
            info = np.iinfo(dt)
            lo, hi = int(a.min()), int(a.max())
            if lo < info.min or hi > info.max:
                raise WorldModelValueError(f"{_where(spec)}: {lo if lo < info.min else hi} is outside "
                                           f"{dt.name} range [{info.min}, {info.max}]")
        return np.array(a, dtype=dt, order="C")
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.array(a, dtype=dt, order="C")
    if not bool(np.all(np.isfinite(out))):
        bad = (a if a.shape == () else a[~np.isfinite(out)][0]).item()
        raise WorldModelValueError(f"{_where(spec)}: value {bad!r} is not finite as {dt.name}")
    return out


def _round(n: int, to: int) -> int:
    return (n + to - 1) // to * to


# ----------------------------------------------------------------------------------------
# segment layout


@dataclass(frozen=True)
class _Layout:
    """Where everything lives in one segment (offsets from its start)."""

    spec_json: bytes
    spec_hash: bytes
    offsets: tuple[int, ...]       # of each variable, from the body start
    body_size: int
    spec_offset: int
    req_offset: int
    req_slot_size: int
    seq_offset: int
    total_size: int

    @classmethod
    def build(cls, specs: tuple[VarSpec, ...], name: str | None, owner: str) -> "_Layout":
        offsets, pos = [], 0
        for s in specs:  # specs are sorted by area already
            align = min(8, s.np_dtype.itemsize)
            pos = _round(pos, align)
            offsets.append(pos)
            pos += s.nbytes
        body_size = _round(max(pos, 8), 8)
        doc = {"format": "pfma.worldmodel", "version": FORMAT_VERSION, "name": name,
               "owner": owner, "areas": list(AREAS), "body_size": body_size,
               "variables": [dict(s.to_json(), offset=o, nbytes=s.nbytes)
                             for s, o in zip(specs, offsets)]}
        raw = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
        spec_offset = HEADER_SIZE
        req_offset = _round(spec_offset + len(raw), 64)
        payload = _round(max(MIN_PAYLOAD, max((s.nbytes for s in specs), default=0)), 8)
        slot = SLOT_HEADER + payload
        seq_offset = _round(req_offset + REQUEST_SLOTS * slot, 64)
        total = _round(seq_offset + SEQ_BLOCK + body_size, 4096)
        return cls(raw, hashlib.sha256(raw).digest()[:8], tuple(offsets), body_size, spec_offset,
                   req_offset, slot, seq_offset, total)


@dataclass(frozen=True)
class UserRequest:
    """One entry of the user-request ring (``pfma wm requests``)."""

    req_id: int
    state: str
    variable: str
    user: str
    pid: int
    submit_ns: int
    applied_frame: int
    result: str


@dataclass(frozen=True)
class ModelInfo:
    """Header summary of a world model."""

    name: str | None
    owner: str
    owner_pid: int
    owner_alive: bool
    frame: int
    frame_t_s: float
    powered_up: bool
    created_ns: int
    n_variables: int
    total_size: int
    spec_hash: str
    user_applied: int
    user_rejected: int


# ----------------------------------------------------------------------------------------
# the model


class WorldModel:
    """The world model. Use :meth:`create` (the owner) or :meth:`attach` (inspection)."""

    def __init__(self) -> None:  # use create()/attach()
        self._views: list[memoryview] = []
        self._closer = None
        self._shm = None
        self._fd = -1
        self.name: str | None = None
        self.readonly = True
        self._qlock = threading.Lock()          # the pending-post queue
        self._comm_lock = threading.Lock()      # held during a communications segment
        self._req_tlock = threading.Lock()      # in-process side of the request-ring lock
        self._queue: dict[int, bytes] = {}
        self._in_comm = False
        self._flush_thread = 0
        self._stats = {"frames": 0, "posts": 0, "posts_applied": 0, "deferred_posts": 0,
                       "user_applied": 0, "user_rejected": 0}
        self._key = ""
        self.clock = MonotonicClock()

    # --- opening ---------------------------------------------------------------------

    @classmethod
    def create(cls, specs: Iterable[VarSpec], name: str | None = None, clock=None, *,
               access_key: str | None = None, owner: str = "controller") -> "WorldModel":
        """Build the model, every variable at its initial value.

        :param name: POSIX shared-memory name (``/dev/shm/<name>``) so tools can inspect it
            while it runs, or ``None`` for private in-process memory (tests, simulation)
        :param access_key: key for user writes; default ``$PFMA_WM_KEY`` or
            :data:`DEFAULT_ACCESS_KEY`
        :param owner: the owning process's name, shown by tools and in errors
        :raises WorldModelError: duplicate names, invalid specs, or ``name`` in use by a
            running owner (a dead owner's segment is replaced)
        """
        specs = tuple(specs)
        for s in specs:
            if not isinstance(s, VarSpec):
                raise WorldModelError(f"world model: {s!r} is not a VarSpec")
        seen: dict[str, VarSpec] = {}
        for s in specs:
            if s.name in seen:
                raise WorldModelError(f"world model: variable {s.name!r} defined twice (writers "
                                      f"{seen[s.name].writer!r} and {s.writer!r}); one name, one writer")
            seen[s.name] = s
        specs = tuple(sorted(specs, key=lambda s: AREAS.index(s.area)))  # stable within areas
        lay = _Layout.build(specs, name, owner)
        self = cls()
        self.name = name
        self.readonly = False
        self.clock = clock or MonotonicClock()
        if name is None:
            mem = bytearray(lay.total_size)
            self._closer = lambda: None
        else:
            shm = cls._create_shm(name, lay.total_size)
            self._shm, self._fd, self._closer = shm, shm._fd, shm.close
            mem = shm.buf
        self._root = memoryview(mem)
        try:
            self._setup(specs, lay, writable=True)
            self._initialise(lay, owner)
            self.access_key = access_key if access_key is not None else \
                os.environ.get(ACCESS_KEY_ENV) or DEFAULT_ACCESS_KEY
            self._root[0:8] = MAGIC  # last: no magic = not initialised yet
        except BaseException:
            self.close()
            if name is not None:
                cls.remove_segment(name)
            raise
        return self

    @classmethod
    def _create_shm(cls, name: str, size: int):
        try:
            return open_shm(name, create=True, size=size)
        except FileExistsError:
            pass
        try:
            info = cls.attach(name).close_after(lambda m: m.info())
        except WorldModelError as err:
            raise WorldModelError(f"world model {name!r}: /dev/shm/{name} exists but cannot be "
                                  f"read ({err}); remove it with WorldModel.remove_segment({name!r}) "
                                  f"if no process uses it") from None
        if info.owner_alive:
            raise WorldModelError(f"world model {name!r} already exists, owned by {info.owner!r} "
                                  f"(pid {info.owner_pid}, running); one writer per world model")
        cls.remove_segment(name)  # its owner is dead: replace it
        return open_shm(name, create=True, size=size)

    @classmethod
    def attach(cls, name: str = DEFAULT_NAME) -> "WorldModel":
        """Attach to a running model for inspection: reads, the header, and user requests
        (:meth:`set_user`); posting is refused. Names and types come from the JSON stored
        in the segment, so no controller code is needed.
        """
        try:
            shm = open_shm(name, create=False)
        except FileNotFoundError:
            others = list_segments()
            hint = f" (world models here: {', '.join(others)})" if others else ""
            raise WorldModelError(f"no world model {name!r} (/dev/shm/{name}); is the controller "
                                  f"running?{hint}") from None
        self = cls()
        self.name = name
        self._shm, self._fd, self._closer = shm, shm._fd, shm.close
        self._root = memoryview(shm.buf)
        try:
            specs, lay = self._decode(self._root, name)
            self._setup(specs, lay, writable=False)
        except BaseException:
            self.close()
            raise
        return self

    def close_after(self, fn):
        """``fn(self)``, then :meth:`close` (one-shot reads)."""
        try:
            return fn(self)
        finally:
            self.close()

    @staticmethod
    def _decode(mv: memoryview, name: str) -> tuple[tuple[VarSpec, ...], _Layout]:
        size = len(mv)
        if size < HEADER_SIZE or bytes(mv[0:8]) != MAGIC:
            raise WorldModelError(f"world model {name!r}: no magic {MAGIC!r} (not initialised yet, "
                                  f"or not a world model)")
        h = {k: struct.unpack_from("<" + f, mv, o)[0] for k, (o, f) in HEADER_FIELDS.items()
             if k in ("version", "total_size", "spec_offset", "spec_len", "spec_hash",
                      "req_offset", "req_slot_size", "req_slots", "seq_offset", "body_size")}
        if h["version"] != FORMAT_VERSION:
            raise WorldModelError(f"world model {name!r}: format version {h['version']}, this "
                                  f"program reads {FORMAT_VERSION}")
        if h["total_size"] > size or h["spec_offset"] + h["spec_len"] > size:
            raise WorldModelError(f"world model {name!r}: header sizes exceed the segment "
                                  f"({size} bytes)")
        raw = bytes(mv[h["spec_offset"]:h["spec_offset"] + h["spec_len"]])
        if hashlib.sha256(raw).digest()[:8] != h["spec_hash"]:
            raise WorldModelError(f"world model {name!r}: variable table does not match its hash "
                                  f"{h['spec_hash'].hex()} (corrupt segment)")
        doc = json.loads(raw)
        specs = tuple(VarSpec.from_json(v) for v in doc["variables"])
        offsets = tuple(int(v["offset"]) for v in doc["variables"])
        for s, o in zip(specs, offsets):
            if o + s.nbytes > h["body_size"]:
                raise WorldModelError(f"world model {name!r}: variable {s.name!r} lies outside the body")
        if h["req_slots"] != REQUEST_SLOTS:
            raise WorldModelError(f"world model {name!r}: {h['req_slots']} request slots, "
                                  f"expected {REQUEST_SLOTS}")
        lay = _Layout(raw, h["spec_hash"], offsets, h["body_size"], h["spec_offset"],
                      h["req_offset"], h["req_slot_size"], h["seq_offset"], h["total_size"])
        return specs, lay

    def _setup(self, specs: tuple[VarSpec, ...], lay: _Layout, writable: bool) -> None:
        self._specs = specs
        self._lay = lay
        self._index = {s.name: i for i, s in enumerate(specs)}
        data = self._root if writable else self._root.toreadonly()
        if data is not self._root:
            self._views.append(data)
        self._lock = _WMSeqLock(data, lay.seq_offset, lay.body_size,
                                f"{self.name or 'private'}", READ_TIMEOUT_S)
        self._body = data[lay.seq_offset + SEQ_BLOCK:lay.seq_offset + SEQ_BLOCK + lay.body_size]
        self._views.append(self._body)
        # the request ring is writable from every attachment (pfma wm set)
        self._req = self._root[lay.req_offset:lay.req_offset + REQUEST_SLOTS * lay.req_slot_size]
        self._views.append(self._req)
        self._words = {k: self._word(k) for k in ("powered_up", "owner_pid", "frame", "frame_t_s",
                                                  "req_next_id", "user_applied", "user_rejected")}

    def _word(self, fld: str) -> memoryview:
        off, fmt = HEADER_FIELDS[fld]
        v = self._root[off:off + struct.calcsize(fmt)].cast(fmt)
        self._views.append(v)
        return v

    def _initialise(self, lay: _Layout, owner: str) -> None:
        mv = self._root
        mv[:] = bytes(len(mv))

        def put(fld: str, value) -> None:
            off, fmt = HEADER_FIELDS[fld]
            struct.pack_into("<" + fmt, mv, off, value)

        put("version", FORMAT_VERSION)
        put("header_size", HEADER_SIZE)
        put("total_size", lay.total_size)
        put("spec_offset", lay.spec_offset)
        put("spec_len", len(lay.spec_json))
        put("spec_hash", lay.spec_hash)
        put("req_offset", lay.req_offset)
        put("req_slots", REQUEST_SLOTS)
        put("req_slot_size", lay.req_slot_size)
        put("seq_offset", lay.seq_offset)
        put("body_size", lay.body_size)
        put("owner_pid", os.getpid())
        put("created_ns", time.time_ns())
        put("lock_byte", HEADER_FIELDS["lock_byte"][0])
        put("owner_name", owner.encode()[:32])
        mv[lay.spec_offset:lay.spec_offset + len(lay.spec_json)] = lay.spec_json
        for s, o in zip(self._specs, lay.offsets):  # rule 4: valid from the start
            self._body[o:o + s.nbytes] = coerce(s, s.initial).tobytes()
        self._words["frame_t_s"][0] = self.clock.now()

    # --- the variable table ------------------------------------------------------------

    @property
    def specs(self) -> tuple[VarSpec, ...]:
        """Every variable, grouped by area in :data:`AREAS` order."""
        return self._specs

    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self._specs)

    def spec(self, name: str) -> VarSpec:
        """The variable's spec; :class:`WorldModelError` (with close matches) if unknown."""
        i = self._index.get(name)
        if i is None:
            close = difflib.get_close_matches(name, self._index, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise WorldModelError(f"no variable {name!r} in world model "
                                  f"{self.name or 'private'}{hint}")
        return self._specs[i]

    def variables_of(self, writer: str) -> tuple[str, ...]:
        """Names of the variables ``writer`` owns."""
        return tuple(s.name for s in self._specs if s.writer == writer)

    # --- reading -------------------------------------------------------------------------

    def _decode_value(self, i: int, raw) -> Any:
        s = self._specs[i]
        a = np.frombuffer(raw, s.np_dtype, count=s.count)
        return a[0] if s.shape == () else a.reshape(s.shape).copy()

    def _read(self, fn):
        if self.readonly:
            return fn()
        if self._in_comm and self._flush_thread == threading.get_ident():
            raise WorldModelError(f"world model {self.name or 'private'}: read during its own "
                                  f"communications segment (the model is locked out)")
        with self._comm_lock:  # pend until the end of a communications segment
            return fn()

    def get(self, name: str) -> Any:
        """A consistent copy of one variable: a numpy scalar, or a new array."""
        i = self._index.get(name)
        if i is None:
            self.spec(name)
        s, o = self._specs[i], self._lay.offsets[i]
        buf = bytearray(s.nbytes)
        self._read(lambda: self._lock.read_part_into(memoryview(buf), o))
        return self._decode_value(i, buf)

    def get_task_inputs(self, names: Iterable[str]) -> dict[str, Any]:
        """Several variables from one consistent copy (all from the same frame)."""
        idx = []
        for n in names:
            i = self._index.get(n)
            if i is None:
                self.spec(n)
            idx.append(i)
        frame = {}
        snap = bytearray(self._lay.body_size)  # per call: thread-safe

        def grab() -> None:
            self._lock.read_into(memoryview(snap))
            for i in idx:
                o = self._lay.offsets[i]
                frame[self._specs[i].name] = self._decode_value(i, snap[o:o + self._specs[i].nbytes])

        self._read(grab)
        return frame

    def snapshot(self) -> dict[str, Any]:
        """Every variable from one consistent copy."""
        return self.get_task_inputs(self.names())

    def get_state_variable(self, name: str) -> int:
        """A short integer state variable (layer command/status) as a Python int."""
        s = self.spec(name)
        if not s.is_state:
            raise WorldModelError(f"world-model variable {name!r} is {s.type_text}, not an integer "
                                  f"state variable; use get()")
        return int(self.get(name))

    # --- posting -------------------------------------------------------------------------

    def _require_owner(self, what: str) -> None:
        if self.readonly:
            info = self.info()
            raise WorldModelError(f"world model {self.name!r} is attached read-only here; {what} "
                                  f"belongs to its owner {info.owner!r} (pid {info.owner_pid})")

    def _check_writer(self, writer: str, name: str) -> int:
        i = self._index.get(name)
        if i is None:
            self.spec(name)
        owner = self._specs[i].writer
        if writer != owner:
            raise WorldModelError(f"world-model variable {name!r} is written only by {owner!r}; "
                                  f"{writer!r} may read it but not post it (one writer per variable)")
        return i

    def post_task_outputs(self, writer: str, values: Mapping[str, Any]) -> None:
        """Queue ``values`` (name -> value) for the next communications segment.

        All-or-nothing: every value is checked before any is queued. A later post of the
        same variable before the segment replaces the earlier one (fresh data wins).

        :raises WorldModelError: ``writer`` is not a variable's one writer (names the owner)
        :raises WorldModelValueError: (also a ValueError) wrong shape/type, out of range,
            not finite
        """
        self._require_owner("posting")
        staged = []
        for name, value in values.items():
            i = self._check_writer(writer, name)
            staged.append((i, coerce(self._specs[i], value).tobytes()))
        with self._qlock:
            if self._in_comm:
                self._stats["deferred_posts"] += len(staged)
            for i, raw in staged:
                self._queue[i] = raw
            self._stats["posts"] += len(staged)

    def post_state_variable(self, writer: str, name: str, value: int) -> None:
        """Queue one integer state variable (layer command or status)."""
        s = self.spec(name)
        if not s.is_state:
            raise WorldModelError(f"world-model variable {name!r} is {s.type_text}, not an integer "
                                  f"state variable; use post_task_outputs()")
        self.post_task_outputs(writer, {name: value})

    @property
    def pending(self) -> int:
        """Variables queued for the next communications segment."""
        return len(self._queue)

    @property
    def in_comm_frame(self) -> bool:
        """True while a communications segment is flushing (IRSS IN-COMM-FRAME)."""
        return self._in_comm

    def communications_segment(self) -> int:
        """Apply every queued post, then pending user requests, at once under the sequence
        lock; count the frame. Returns the number of variables written."""
        self._require_owner("the communications segment")
        with self._comm_lock:
            self._flush_thread = threading.get_ident()
            self._in_comm = True  # IN-COMM-FRAME: new posts go to the next segment
            try:
                with self._qlock:  # COMM-INTERRUPT: take the whole queue in one step
                    batch, self._queue = self._queue, {}
                requests = self._pending_requests()
                body, offs = self._body, self._lay.offsets
                applied: list[tuple[int, int, str]] = []
                frame = self._words["frame"][0] + 1
                self._lock.begin()
                try:
                    for i, raw in batch.items():
                        body[offs[i]:offs[i] + len(raw)] = raw
                    for slot, i, raw in requests:
                        ok, msg = self._check_request(slot, i, raw)
                        if ok:
                            body[offs[i]:offs[i] + len(raw)] = raw
                        applied.append((slot, ok, msg))
                    self._words["frame_t_s"][0] = self.clock.now()
                    self._words["frame"][0] = frame
                finally:
                    self._lock.end()
            finally:
                self._in_comm = False
                self._flush_thread = 0
        n_user = 0
        for slot, ok, msg in applied:  # results after the data is visible
            n_user += ok
            self._finish_request(slot, APPLIED if ok else REJECTED, frame,
                                 f"applied at frame {frame}" if ok else msg)
        self._stats["frames"] += 1
        self._stats["posts_applied"] += len(batch)
        return len(batch) + n_user

    @property
    def read_retries(self) -> int:
        """Reads of this attachment that met a segment in progress and retried."""
        return self._lock.retries

    def stats(self) -> dict[str, int]:
        """Counters of this process: frames, posts, posts_applied, deferred_posts,
        user_applied, user_rejected."""
        return dict(self._stats)

    # --- header --------------------------------------------------------------------------

    @property
    def frame(self) -> int:
        """Communications segments completed."""
        return self._words["frame"][0]

    @property
    def powered_up(self) -> bool:
        """System power-up complete (START UP COMPLETE); protected variables are locked."""
        return bool(self._words["powered_up"][0])

    @powered_up.setter
    def powered_up(self, value: bool) -> None:
        self._require_owner("powered_up")
        self._words["powered_up"][0] = 1 if value else 0

    @property
    def access_key(self) -> str:
        """The key user writes need (owner only: the segment stores only a salted hash)."""
        self._require_owner("the access key")
        return self._key

    @access_key.setter
    def access_key(self, key: str) -> None:
        self._require_owner("the access key")
        if not isinstance(key, str) or not key:
            raise WorldModelError("world-model access key must be a non-empty string")
        salt = os.urandom(16)
        o1, o2 = HEADER_FIELDS["key_salt"][0], HEADER_FIELDS["key_hash"][0]
        self._root[o1:o1 + 16] = salt
        self._root[o2:o2 + 32] = hashlib.sha256(salt + key.encode()).digest()
        self._key = key

    def _key_hash(self, key: str) -> bytes:
        o = HEADER_FIELDS["key_salt"][0]
        return hashlib.sha256(bytes(self._root[o:o + 16]) + key.encode()).digest()

    def check_key(self, key: str | None) -> bool:
        """``key`` is this model's access key."""
        if not key:
            return False
        o = HEADER_FIELDS["key_hash"][0]
        return hmac.compare_digest(self._key_hash(key), bytes(self._root[o:o + 32]))

    def info(self) -> ModelInfo:
        mv = self._root

        def get(fld: str):
            off, fmt = HEADER_FIELDS[fld]
            return struct.unpack_from("<" + fmt, mv, off)[0]

        pid = get("owner_pid")
        return ModelInfo(
            name=self.name, owner=get("owner_name").rstrip(b"\0").decode(errors="replace"),
            owner_pid=pid, owner_alive=pid > 0 and pid_alive(pid), frame=self.frame,
            frame_t_s=get("frame_t_s"), powered_up=self.powered_up, created_ns=get("created_ns"),
            n_variables=len(self._specs), total_size=get("total_size"),
            spec_hash=get("spec_hash").hex(), user_applied=get("user_applied"),
            user_rejected=get("user_rejected"))

    # --- user requests -------------------------------------------------------------------

    def _slot(self, k: int) -> memoryview:
        n = self._lay.req_slot_size
        return self._req[k * n:(k + 1) * n]

    def _slot_get(self, k: int, fld: str):
        off, fmt = SLOT_FIELDS[fld]
        return struct.unpack_from("<" + fmt, self._req, k * self._lay.req_slot_size + off)[0]

    def _slot_state(self, k: int) -> memoryview:
        off = k * self._lay.req_slot_size
        return self._req[off:off + 4].cast("I")  # one aligned 4-byte store/load

    def set_user(self, name: str, value: Any, key: str | None, *, user: str | None = None) -> int:
        """Asynchronous user-interface write (``pfma wm set``): checked now, applied by the
        owner at its next communications segment. Returns the request id.

        :raises WorldModelError: unknown variable, not user-settable (a task's output, a layer
            command, a status ...: names the owner), protected while powered up, wrong key,
            request ring full, owner not running
        :raises WorldModelValueError: the value does not fit the variable
        """
        s = self.check_user_settable(name)
        if not self.check_key(key):
            raise WorldModelError(f"world-model variable {name!r}: wrong or missing access key; "
                                  f"user writes need the model's access key")
        raw = coerce(s, value).tobytes()
        if self.readonly:
            info = self.info()
            if not info.owner_alive:
                raise WorldModelError(f"world model {self.name!r}: its owner {info.owner!r} (pid "
                                      f"{info.owner_pid}) is not running; nobody would apply the write")
        return self._submit(self._index[name], raw, self._key_hash(key), user)

    def check_user_settable(self, name: str) -> VarSpec:
        """The variable's spec if a user may set it now (its ``user`` declaration and the
        power state; the key is not checked). Refusals hold with or without the key.

        :raises WorldModelError: unknown variable, or why not (names the owner)
        """
        s = self.spec(name)
        why = s.user_refusal(self.powered_up)
        if why is not None:
            raise WorldModelError(why)
        return s

    def _submit(self, i: int, raw: bytes, key_hash: bytes, user: str | None) -> int:
        with self._req_tlock:
            self._lock_ring(True)
            try:
                nxt = self._words["req_next_id"]
                rid = nxt[0] + 1
                k = (rid - 1) % REQUEST_SLOTS
                st = self._slot_state(k)
                try:
                    # a WRITING slot seen while holding the lock was abandoned by a
                    # submitter that died mid-write (writers hold the lock): reuse it
                    if st[0] == PENDING:
                        raise WorldModelError(
                            f"world model {self.name or 'private'}: user request queue full "
                            f"({REQUEST_SLOTS} pending); the owner applies them at each "
                            f"communications segment - is it running?")
                    st[0] = WRITING
                    base = k * self._lay.req_slot_size
                    for fld, v in (("var_index", i), ("req_id", rid), ("submit_ns", time.time_ns()),
                                   ("pid", os.getpid()), ("nbytes", len(raw)), ("applied_frame", 0),
                                   ("key_hash", key_hash),
                                   ("user", (user or _login()).encode()[:24]),
                                   ("result", b"")):
                        off, fmt = SLOT_FIELDS[fld]
                        struct.pack_into("<" + fmt, self._req, base + off, v)
                    self._req[base + SLOT_HEADER:base + SLOT_HEADER + len(raw)] = raw
                    st[0] = PENDING  # last: the owner takes only complete entries
                finally:
                    st.release()
                nxt[0] = rid
                return rid
            finally:
                self._lock_ring(False)

    def _lock_ring(self, lock: bool) -> None:
        """Exclusive access to the ring among submitting processes (OFD byte lock)."""
        if self._fd < 0:
            return
        idx = HEADER_FIELDS["lock_byte"][0]
        if not lock:
            lock_byte(self._fd, idx, False)
            return
        deadline = time.monotonic() + 1.0
        while True:
            try:
                lock_byte(self._fd, idx, True)
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise WorldModelError(f"world model {self.name!r}: user request queue is "
                                          f"locked by another process for over 1 s") from None
                os.sched_yield()

    def _pending_requests(self) -> list[tuple[int, int, bytes]]:
        """(slot, variable index, value bytes) of every pending request, oldest first."""
        out = []
        for k in range(REQUEST_SLOTS):
            st = self._slot_state(k)
            try:
                if st[0] != PENDING:
                    continue
            finally:
                st.release()
            i = self._slot_get(k, "var_index")
            n = self._slot_get(k, "nbytes")
            base = k * self._lay.req_slot_size + SLOT_HEADER
            out.append((self._slot_get(k, "req_id"), k, i, bytes(self._req[base:base + n])))
        out.sort()  # oldest first
        return [(k, i, raw) for _rid, k, i, raw in out]

    def _check_request(self, k: int, i: int, raw: bytes) -> tuple[bool, str]:
        """Re-check a request at apply time: the ring is shared memory any process can write
        (so who may set the variable is checked again), and the power state or key may have
        changed since it was queued."""
        if not 0 <= i < len(self._specs):
            return False, f"unknown variable index {i}"
        s = self._specs[i]
        why = s.user_refusal(self.powered_up)
        if why is not None:
            return False, why
        if len(raw) != s.nbytes:
            return False, f"{s.name}: {len(raw)} bytes given, {s.nbytes} expected"
        o = HEADER_FIELDS["key_hash"][0]
        if not hmac.compare_digest(self._slot_get(k, "key_hash"), bytes(self._root[o:o + 32])):
            return False, f"{s.name}: wrong access key"
        try:
            coerce(s, self._decode_value(i, raw))
        except WorldModelValueError as err:
            return False, str(err)
        return True, ""

    def _finish_request(self, k: int, state: int, frame: int, msg: str) -> None:
        base = k * self._lay.req_slot_size
        off, _ = SLOT_FIELDS["applied_frame"]
        struct.pack_into("<Q", self._req, base + off, frame)
        off, _ = SLOT_FIELDS["result"]
        struct.pack_into("<96s", self._req, base + off, msg.encode()[:96])
        st = self._slot_state(k)
        st[0] = state
        st.release()
        w = self._words["user_applied" if state == APPLIED else "user_rejected"]
        w[0] = w[0] + 1
        self._stats["user_applied" if state == APPLIED else "user_rejected"] += 1

    def request(self, req_id: int) -> UserRequest | None:
        """The ring entry of request ``req_id`` (None once its slot was reused)."""
        for r in self.requests():
            if r.req_id == req_id:
                return r
        return None

    def requests(self) -> list[UserRequest]:
        """Every used slot of the request ring, oldest first."""
        out = []
        for k in range(REQUEST_SLOTS):
            st = self._slot_get(k, "state")
            rid = self._slot_get(k, "req_id")
            if st == FREE or rid == 0:
                continue
            i = self._slot_get(k, "var_index")
            var = self._specs[i].name if 0 <= i < len(self._specs) else f"#{i}"
            out.append(UserRequest(
                rid, STATE_NAMES.get(st, str(st)), var,
                self._slot_get(k, "user").rstrip(b"\0").decode(errors="replace"),
                self._slot_get(k, "pid"), self._slot_get(k, "submit_ns"),
                self._slot_get(k, "applied_frame"),
                self._slot_get(k, "result").rstrip(b"\0").decode(errors="replace")))
        return sorted(out, key=lambda r: r.req_id)

    def user_requests_pending(self) -> int:
        return sum(1 for k in range(REQUEST_SLOTS) if self._slot_get(k, "state") == PENDING)

    # --- closing -------------------------------------------------------------------------

    def close(self) -> None:
        """Unmap (the owner's segment stays until :meth:`unlink`)."""
        if self._closer is None:
            return
        if not self.readonly and self._shm is not None:
            try:
                self._words["owner_pid"][0] = 0  # no owner any more: tools say so
            except (KeyError, ValueError, AttributeError):
                pass
        lk = getattr(self, "_lock", None)
        if lk is not None:
            lk.release()
        for v in reversed(self._views):
            v.release()
        self._views.clear()
        root = getattr(self, "_root", None)
        if root is not None:
            root.release()
        closer, self._closer = self._closer, None
        closer()

    def unlink(self) -> bool:
        """Remove this model's shared-memory name (owner; after or instead of close)."""
        if self.name is None:
            return False
        return self.remove_segment(self.name)

    @staticmethod
    def remove_segment(name: str) -> bool:
        """Remove POSIX shared memory ``name``; False if it did not exist."""
        from multiprocessing import shared_memory
        try:
            shared_memory._posixshmem.shm_unlink("/" + name)  # no tracker round trip
        except FileNotFoundError:
            return False
        return True

    def __del__(self) -> None:
        if getattr(self, "_closer", None) is not None:
            try:
                self.close()
            except Exception:
                pass

    def __enter__(self) -> "WorldModel":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"<WorldModel {self.name or 'private'} {'ro' if self.readonly else 'owner'} "
                f"{len(self._specs)} variables frame={self.frame}>")


def _login() -> str:
    try:
        import getpass
        return getpass.getuser()
    except Exception:  # no USER and no passwd entry (containers)
        return f"uid{os.getuid()}"


def list_segments(shm_dir: str = "/dev/shm") -> list[str]:
    """Names of world-model segments on this host (files starting with the magic)."""
    out = []
    try:
        entries = sorted(Path(shm_dir).iterdir())
    except OSError:
        return out
    for p in entries:
        try:
            with open(p, "rb") as f:
                if f.read(8) == MAGIC:
                    out.append(p.name)
        except OSError:
            continue
    return out
