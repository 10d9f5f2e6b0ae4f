"""The world model itself (:class:`WorldModel`): creating and attaching the segment,
reading, queued posts and the communications segment, the header.

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
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import struct
import threading
import time
from typing import Any, Callable, Iterable, Mapping, NamedTuple

import numpy as np

from bit3.buffer import pid_alive
from bit3.layout import SEQ_BLOCK  # the SeqLock counter block before the body
from bit3.segment import Segment, open_shm
from controller.worldmodel.requests import UserRequestRing
from controller.worldmodel.segment import (
    APPLIED, FORMAT_VERSION, HEADER_FIELDS, HEADER_SIZE, MAGIC, READ_TIMEOUT_S, REJECTED, REQUEST_SLOTS,
    ModelInfo, _Layout, _WMSeqLock, decode, list_segments,
)
from controller.worldmodel.spec import AREAS, VarSpec, WorldModelError, WorldModelValueError, coerce
from pfma.clock import MonotonicClock
from pfma.errors import did_you_mean

#: the access key a model gets when none is given and PFMA_WM_KEY is not set
DEFAULT_ACCESS_KEY = "pfma"
#: environment variable overriding the default access key (creator and ``pfma wm set``)
ACCESS_KEY_ENV = "PFMA_WM_KEY"
#: shared-memory name the controller runtime and ``pfma wm`` use when none is given
DEFAULT_NAME = "pfma_wm"
#: a segment without magic and without an owner pid, older than this, was abandoned by a
#: creator killed before it initialised the segment (assumed: creating one takes
#: milliseconds; 2 s is far beyond a loaded host's scheduling delays)
INIT_GRACE_S = 2.0
#: distinct name tuples whose read plan :meth:`WorldModel.get_task_inputs` keeps (the
#: layers' constant tuples; a caller building new tuples every time is not cached past this)
PLAN_CACHE = 256
#: kept user writes (:meth:`WorldModel.keep_user_writes`) the owner may hold untaken; a
#: write beyond them is rejected (assumed: the owner takes them every frame, and a
#: communications segment applies at most REQUEST_SLOTS writes; four segments' worth)
KEPT_WRITES = 4 * REQUEST_SLOTS
#: numpy (kind, itemsize) -> struct code, for scalars read and written without numpy
_STRUCT_CODE = {("f", 8): "d", ("f", 4): "f", ("i", 1): "b", ("i", 2): "h", ("i", 4): "i", ("i", 8): "q",
                ("u", 1): "B", ("u", 2): "H", ("u", 4): "I", ("u", 8): "Q", ("b", 1): "?"}


class _Hot(NamedTuple):
    """What the owner's hot paths need of one variable, derived once from its spec.

    The fast paths (plain ``struct`` for scalars, the array's own bytes for arrays of the
    variable's dtype and shape) give exactly the bytes and values :func:`coerce` and
    :meth:`WorldModel._decode_value` give; anything they do not cover goes the general way
    (which also raises the errors)."""
    writer: str
    offset: int
    dtype: np.dtype
    count: int
    shape: tuple
    kind: str  #: numpy kind of the variable: f, i, u, b
    scalar: struct.Struct | None  #: the scalar's struct (None: an array, or no struct code)
    vector: struct.Struct | None  #: a 1-D f8 array's struct (packs a tuple or list of floats)
    lo: int  #: integer range the fast path takes (0, 0 for other kinds; an enumeration's,
    hi: int  #: or the empty 1, 0 when it has gaps: every post then goes through coerce)
    is_state: bool
    f8: bool
    flo: float  #: the variable's bounds (VarSpec.bounds; -inf, inf: none, finite is enough)
    fhi: float
    ranged: bool  #: an array with bounds: the fast path checks its min and max


def _hot(s: VarSpec, offset: int) -> _Hot:
    dt = s.np_dtype
    order = ">" if dt.str[0] == ">" else "<"
    code = _STRUCT_CODE.get((dt.kind, dt.itemsize))
    scalar = struct.Struct(order + code) if code and s.shape == () else None
    f8 = dt.kind == "f" and dt.itemsize == 8
    vector = struct.Struct(f"{order}{s.shape[0]}d") if f8 and len(s.shape) == 1 else None
    lo, hi = (int(np.iinfo(dt).min), int(np.iinfo(dt).max)) if dt.kind in "iu" else (0, 0)
    if s.enum:  # no extra check per post: a contiguous enumeration is a range
        values = [v for v, _ in s.enum]
        lo, hi = (values[0], values[-1]) if values[-1] - values[0] + 1 == len(values) else (1, 0)
    flo, fhi = s.bounds or (-math.inf, math.inf)
    if s.bounds and dt.kind in "iu":  # an integer scalar's fast path checks lo..hi
        lo, hi = max(lo, int(flo)), min(hi, int(fhi))
    return _Hot(s.writer, offset, dt, s.count, tuple(s.shape), dt.kind, scalar, vector, lo, hi, s.is_state, f8,
                flo, fhi, bool(s.bounds) and s.shape != ())


def _fast_raw(h: _Hot, value: Any) -> bytes | None:
    """``coerce(spec, value).tobytes()`` for the common valid cases without numpy (a Python
    or numpy scalar of the variable's kind, a finite f8; an array of the variable's dtype
    and shape, finite; a tuple or list of floats for a 1-D f8 variable), else None: the
    caller then calls :func:`coerce`, which converts the rest and raises on the invalid."""
    t = type(value)
    st = h.scalar
    if st is not None:
        k = h.kind
        if k == "f":
            if h.f8 and (t is float or t is np.float64) and math.isfinite(value) and h.flo <= value <= h.fhi:
                return st.pack(value)
        elif k == "b":
            if t is bool or t is np.bool_:
                return b"\x01" if value else b"\x00"
        elif (t is int or (isinstance(value, int) and t is not bool)) and h.lo <= value <= h.hi:
            return st.pack(value)  # an int or IntEnum (numpy takes both as integers)
        return None
    if t is np.ndarray:
        if value.dtype != h.dtype or value.shape != h.shape:
            return None
        # a sum of finite floats is finite unless it overflows (then: the general way); any
        # inf or nan makes it non-finite
        if h.kind == "f" or h.ranged:
            xs = value.ravel().tolist()
            if (h.kind == "f" and not math.isfinite(sum(xs))) or (h.ranged and (min(xs) < h.flo or max(xs) > h.fhi)):
                return None
        return value.tobytes()
    vec = h.vector
    if vec is not None and (t is tuple or t is list) and len(value) == h.count:
        for x in value:
            if type(x) is not float:
                return None
        if not math.isfinite(sum(value)) or (h.ranged and (min(value) < h.flo or max(value) > h.fhi)):
            return None
        return vec.pack(*value)
    return None


class WorldModel(UserRequestRing, Segment):
    """The world model. Use :meth:`create` (the owner) or :meth:`attach` (inspection).
    The segment's lifecycle (close, ``with``, :meth:`remove_segment`) is
    :class:`bit3.segment.Segment`'s."""

    def __init__(self) -> None:  # use create()/attach()
        self._views: list[memoryview] = []
        self.name: str | None = None
        self.readonly = True
        self._qlock = threading.Lock()          # the pending-post queue
        self._comm_lock = threading.Lock()      # held during a communications segment
        self._req_tlock = threading.Lock()      # in-process side of the request-ring lock
        self._queue: dict[int, bytes] = {}
        self._in_comm = False
        self._flush_thread = 0
        self._stats = {"frames": 0, "posts": 0, "posts_applied": 0, "deferred_posts": 0, "refused_posts": 0,
                       "user_applied": 0, "user_rejected": 0}
        self.last_refusal = ""  #: the last task post refused (rule 4), in words
        self._key = ""
        self.clock = MonotonicClock()
        # a distributed controller's sections (set_sections, set_importer): none in one process
        self._process: str | None = None
        self._remote: dict[int, str] = {}  # variable index -> the process whose section holds it
        self._remote_models: dict[str, str] = {}  # process -> its world-model name
        self._importer: Callable[[memoryview], None] | None = None
        # variables whose every applied user write the owner takes in order (keep_user_writes)
        self._kept: frozenset[int] = frozenset()
        self._kept_log: list[tuple[int, int, bytes]] = []  # (request id, variable index, value)

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
            mem = self._hold(cls._create_shm(name, lay.total_size))
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
            if cls._abandoned(name):  # its creator died before initialising it: replace it
                cls.remove_segment(name)
                return open_shm(name, create=True, size=size)
            raise WorldModelError(f"world model {name!r}: /dev/shm/{name} exists but cannot be "
                                  f"read ({err}); remove it with WorldModel.remove_segment({name!r}) "
                                  f"if no process uses it") from None
        if info.owner_alive:
            raise WorldModelError(f"world model {name!r} already exists, owned by {info.owner!r} "
                                  f"(pid {info.owner_pid}, running); one writer per world model")
        cls.remove_segment(name)  # its owner is dead: replace it
        return open_shm(name, create=True, size=size)

    @staticmethod
    def _abandoned(name: str) -> bool:
        """Segment ``name`` has no magic (never initialised) and its creator is gone: the
        owner pid in its header (written before the magic) names no running process, or
        none was written and the file is older than :data:`INIT_GRACE_S` (a creator
        initialises in milliseconds; a controller killed inside :meth:`create` leaves such a
        segment, which would otherwise block every later controller of that name)."""
        path = f"/dev/shm/{name}"
        try:
            with open(path, "rb") as f:
                head = f.read(HEADER_SIZE)
            age = time.time() - os.stat(path).st_mtime
        except OSError:
            return False
        if head[0:8] == MAGIC:
            return False  # initialised: not abandoned (attach failed for another reason)
        off, fmt = HEADER_FIELDS["owner_pid"]
        pid = struct.unpack_from("<" + fmt, head, off)[0] if len(head) >= off + 4 else 0
        if pid > 0:
            return not pid_alive(pid)
        return age > INIT_GRACE_S

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
        self._root = memoryview(self._hold(shm))
        try:
            specs, lay = decode(self._root, name)
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
        # the request slots' state words as one view (aligned 4-byte loads), scanned by
        # every communications segment without building a view per slot
        self._req_words = self._req.cast("I")
        self._views.append(self._req_words)
        self._req_step = lay.req_slot_size // 4
        self._hot = tuple(_hot(s, o) for s, o in zip(specs, lay.offsets))
        self._plans: dict[tuple, tuple[tuple[str, int], ...]] = {}
        self._relay_plans: dict[tuple, tuple[tuple[int, int, int, int], ...]] = {}
        #: data between neighbours (controller/neighbours.py): per layer key, what it may
        #: read; the layer whose table or task runs now (None: no layer, nothing refused)
        self._reader: str | None = None
        self._reader_may: frozenset[str] = frozenset()
        self._read_state: dict[str | None, tuple[frozenset[str], dict]] = {None: (frozenset(), self._plans)}
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
            raise WorldModelError(f"no variable {name!r} in world model "
                                  f"{self.name or 'private'}{did_you_mean(name, self._index)}")
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

    def _owner_guard(self) -> None:
        """The owner's own read during its communications segment is refused (as in :meth:`_read`)."""
        if self._in_comm and self._flush_thread == threading.get_ident():
            raise WorldModelError(f"world model {self.name or 'private'}: read during its own "
                                  f"communications segment (the model is locked out)")

    def _value_at(self, i: int) -> Any:
        """Variable ``i`` straight from the body (the owner, holding the segment lock: the
        body changes only in a communications segment, which holds that lock too). The
        same values and types as :meth:`_decode_value`, without a copy of the body."""
        h = self._hot[i]
        if h.scalar is not None:
            return h.dtype.type(h.scalar.unpack_from(self._body, h.offset)[0])
        a = np.frombuffer(self._body, h.dtype, h.count, h.offset)
        return a[0] if h.shape == () else a.reshape(h.shape).copy()

    # --- data between neighbours (issue 33 item 2) ----------------------------------------
    def set_read_rules(self, rules: dict[str, frozenset[str]]) -> None:
        """What each layer may read (controller/neighbours.py ``read_rules``); from now on a
        read made while :meth:`read_as` names a layer is refused outside its rule."""
        self._read_state = {None: self._read_state[None], **{k: (v, {}) for k, v in rules.items()}}

    def read_as(self, key: str | None) -> None:
        """The layer whose table or task runs from now (None: none; the runtime, tools).
        Each reader has its own cache of checked name tuples."""
        if key is self._reader:
            return
        state = self._read_state.get(key)
        if state is None:
            raise WorldModelError(f"no read rule for layer {key!r}")
        self._reader = key
        self._reader_may, self._plans = state

    def _refuse_read(self, name: str) -> None:
        spec = self.spec(name)
        raise WorldModelError(f"layer {self._reader} reads {name} (written by {spec.writer}) without declaring it "
                              f"in its reads: data passes between neighbours only (report 2.3.2; "
                              f"controller/neighbours.py)")

    def get(self, name: str) -> Any:
        """A consistent copy of one variable: a numpy scalar, or a new array."""
        if self._reader is not None and name not in self._reader_may:
            self._refuse_read(name)
        i = self._index.get(name)
        if i is None:
            self.spec(name)
        if not self.readonly:
            self._owner_guard()
            with self._comm_lock:  # pend until the end of a communications segment
                return self._value_at(i)
        s, o = self._specs[i], self._lay.offsets[i]
        buf = bytearray(s.nbytes)
        self._read(lambda: self._lock.read_part_into(memoryview(buf), o))
        return self._decode_value(i, buf)

    def get_task_inputs(self, names: Iterable[str]) -> dict[str, Any]:
        """Several variables from one consistent copy (all from the same frame)."""
        if not self.readonly:
            plan = self._plans.get(names) if type(names) is tuple else None  # type: ignore[call-overload]
            if plan is None:
                plan = self._plan(names)
            self._owner_guard()
            value = self._value_at
            with self._comm_lock:  # pend until the end of a communications segment: consistent
                return {n: value(i) for n, i in plan}
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

    def _plan(self, names: Iterable[str]) -> tuple[tuple[str, int], ...]:
        """(name, index) of ``names`` (unknown names raise), kept for a tuple of names (per
        reader: each plan is checked once against the reading layer's rule)."""
        plan = []
        may = self._reader_may if self._reader is not None else None
        for n in names:
            i = self._index.get(n)
            if i is None:
                self.spec(n)
            if may is not None and n not in may:
                self._refuse_read(n)
            plan.append((n, i))
        out = tuple(plan)
        if type(names) is tuple and len(self._plans) < PLAN_CACHE:
            self._plans[names] = out
        return out

    def snapshot(self) -> dict[str, Any]:
        """Every variable from one consistent copy."""
        return self.get_task_inputs(self.names())

    def get_state_variable(self, name: str) -> int:
        """A short integer state variable (layer command/status) as a Python int."""
        if self._reader is not None and name not in self._reader_may:
            self._refuse_read(name)
        i = self._index.get(name)
        if i is not None and not self.readonly:
            h = self._hot[i]
            if h.is_state and h.scalar is not None:
                self._owner_guard()
                with self._comm_lock:
                    return h.scalar.unpack_from(self._body, h.offset)[0]
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
        p = self._remote.get(i)
        if p is not None:
            raise WorldModelError(f"world-model variable {name!r} (writer {owner!r}) is in the section of "
                                  f"process {p!r}; process {self._process!r} may read it but not post it (a "
                                  f"task writes only its local section)")
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
        index, hot, fast = self._index, self._hot, _fast_raw
        for name, value in values.items():
            i = index.get(name)
            if i is None or hot[i].writer != writer:
                i = self._check_writer(writer, name)  # raises, naming the owner
            raw = fast(hot[i], value)
            if raw is None:
                try:
                    raw = coerce(self._specs[i], value).tobytes()
                except WorldModelValueError as err:
                    self._refused(err)
                    raise
            staged.append((i, raw))
        self._enqueue(staged)

    def relay(self, writer: str, pairs: tuple[tuple[str, str], ...]) -> int:
        """Republish variables of a neighbour under ``writer``'s own names: each ``(dst, src)``
        pair copies ``src`` (read under the reading layer's rule) into ``dst`` (``writer``'s,
        of the same type and shape), queued for the next communications segment like a post,
        and only when its bytes changed. Returns how many were queued. This is how data
        passes a layer on its way to a layer further away (report 2.3.2; controller/relays.py).

        :raises WorldModelError: a ``dst`` not ``writer``'s, a ``src`` the reading layer may not
            read, or a pair whose two variables differ in type or shape
        """
        self._require_owner("relaying")
        key = (self._reader, writer, pairs)
        plan = self._relay_plans.get(key)
        if plan is None:
            plan = self._relay_plans[key] = self._relay_plan(writer, pairs)
        self._owner_guard()
        body = self._body
        staged = []
        with self._comm_lock:  # the body changes only in a communications segment
            for i, o_dst, o_src, n in plan:
                raw = body[o_src:o_src + n]
                if raw != body[o_dst:o_dst + n]:
                    staged.append((i, bytes(raw)))
        if staged:
            self._enqueue(staged)
        return len(staged)

    def _relay_plan(self, writer: str, pairs: tuple[tuple[str, str], ...]) -> tuple[tuple[int, int, int, int], ...]:
        plan = []
        may = self._reader_may if self._reader is not None else None
        for dst, src in pairs:
            i = self._check_writer(writer, dst)
            j = self._index.get(src)
            if j is None:
                self.spec(src)
            if may is not None and src not in may:
                self._refuse_read(src)
            a, b = self._specs[i], self._specs[j]
            if a.dtype != b.dtype or a.shape != b.shape:
                raise WorldModelError(f"relay {src} -> {dst}: {b.type_text} into {a.type_text}")
            plan.append((i, self._lay.offsets[i], self._lay.offsets[j], a.nbytes))
        return tuple(plan)

    def _refused(self, err: Exception) -> None:
        """A task's post refused (rule 4: the variable keeps its last valid value): counted
        (``stats()["refused_posts"]``) and kept (:attr:`last_refusal`); the post raises on,
        and the runtime puts the posting task's layer in ERROR naming it."""
        self._stats["refused_posts"] += 1
        self.last_refusal = str(err)

    def _enqueue(self, staged: list[tuple[int, bytes]]) -> None:
        with self._qlock:
            if self._in_comm:
                self._stats["deferred_posts"] += len(staged)
            for i, raw in staged:
                self._queue[i] = raw
            self._stats["posts"] += len(staged)

    def post_state_variable(self, writer: str, name: str, value: int) -> None:
        """Queue one integer state variable (layer command or status)."""
        i = self._index.get(name)
        if i is not None and not self.readonly:
            h = self._hot[i]
            if h.is_state and h.writer == writer:
                raw = _fast_raw(h, value)
                if raw is not None:
                    self._enqueue([(i, raw)])
                    return
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
                    imp = self._importer
                    if imp is not None:  # a distributed controller: the other processes' sections
                        imp(body)
                    for i, raw in batch.items():
                        body[offs[i]:offs[i] + len(raw)] = raw
                    for rid, slot, i, raw in requests:
                        ok, msg = self._check_request(slot, i, raw)
                        if ok and i in self._kept:
                            ok, msg = self._keep(rid, i, raw)
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

    # --- user writes kept in order (a request queue: controller/layers.py) ---------------

    def keep_user_writes(self, name: str) -> None:
        """Owner: keep every applied user write of ``name``, in order, with its request id,
        for :meth:`take_user_writes`. For a variable whose writes are messages rather than
        a state (System Up/Down's ``ui.request``): two writes applied in one communications
        segment would otherwise leave only the last one's value."""
        self._require_owner("keep_user_writes")
        self._kept = self._kept | {self._index[self.spec(name).name]}

    def _keep(self, rid: int, i: int, raw: bytes) -> tuple[bool, str]:
        if len(self._kept_log) >= KEPT_WRITES:
            return False, (f"{self._specs[i].name}: the owner has not taken its {KEPT_WRITES} earlier "
                           f"writes (is it running?)")
        self._kept_log.append((rid, i, raw))
        return True, ""

    def take_user_writes(self) -> "list[tuple[int, str, Any]] | tuple[()]":
        """Owner: the kept user writes applied since the last call, oldest first, as (request
        id, variable, value); ``()`` when there are none (nothing is built in a frame
        without any)."""
        if not self._kept_log:
            return ()
        log, self._kept_log = self._kept_log, []
        return [(rid, self._specs[i].name, self._decode_value(i, raw)) for rid, i, raw in log]

    # --- a distributed controller's sections (controller/distributed.py) ---------------

    def set_sections(self, process: str, remote: Mapping[str, str],
                     models: Mapping[str, str] | None = None) -> None:
        """Make this model process ``process``'s copy of a distributed controller's world
        model (report 2.2.5: a task writes only its local section, it reads any section).
        ``remote`` maps every variable another process's section holds to that process:
        posting one is refused with a :class:`WorldModelError` naming the process, and so is
        a user write (the importer overwrites the variable every frame). ``models`` gives
        each process's world-model name for those messages."""
        self._require_owner("the sections")
        remote_i = {}
        for name, proc in remote.items():
            i = self._index.get(name)
            if i is None:
                self.spec(name)
            remote_i[i] = proc
        self._process, self._remote, self._remote_models = process, remote_i, dict(models or {})
        # a remote variable's hot writer is "" (never a writer's name: VarSpec refuses an
        # empty one), so every post of it leaves the fast path for _check_writer, which refuses
        self._hot = tuple(h._replace(writer="") if i in remote_i else h for i, h in enumerate(self._hot))

    def remote_owner(self, name: str) -> str | None:
        """The process whose section holds ``name`` (None: this process's, or one process)."""
        i = self._index.get(name)
        return None if i is None else self._remote.get(i)

    def _section_refusal(self, i: int) -> str | None:
        """Why a user may not set variable ``i`` here: another process's section holds it."""
        p = self._remote.get(i)
        if p is None:
            return None
        where = self._remote_models.get(p)
        there = f": set it in world model {where}" if where else " (distributed world model)"
        return f"{self._specs[i].name} belongs to process {p}{there}"

    def set_importer(self, fn: Callable[[memoryview], None] | None) -> None:
        """``fn(body)`` runs inside every communications segment's locked update, before the
        queued posts: it writes the other processes' sections into the body, so a reader
        sees them and this process's posts from one segment (whole frames of every section)."""
        self._require_owner("the importer")
        self._importer = fn

    def layout_signature(self) -> bytes:
        """8 bytes naming the body's layout (every variable's name, type, shape and offset):
        equal in two models exactly when the bytes of one mean the same in the other."""
        doc = [[s.name, s.dtype, list(s.shape), o] for s, o in zip(self._specs, self._lay.offsets)]
        return hashlib.sha256(repr((self._lay.body_size, doc)).encode()).digest()[:8]

    def var_range(self, name: str) -> tuple[int, int]:
        """(offset in the body, bytes) of variable ``name``."""
        i = self._index.get(name)
        if i is None:
            self.spec(name)
        return self._lay.offsets[i], self._specs[i].nbytes

    @property
    def body_size(self) -> int:
        return self._lay.body_size

    def read_body_into(self, buf, *, wait: bool = True) -> int:
        """A consistent copy of the whole data body (``body_size`` bytes) into ``buf``; returns
        the communications segments the owner had completed (read after the copy).

        :param wait: False: an attached reader does not wait for a segment in progress (a
            few copy attempts, then -1 with ``buf`` left as it was), so a process reading
            another's model never spins on a writer that was descheduled mid-segment"""
        mv = memoryview(buf)
        if not self.readonly:
            self._owner_guard()
            with self._comm_lock:  # the body changes only in a communications segment
                mv[:] = self._body
                return self._words["frame"][0]
        if wait:
            self._lock.read_into(mv)
        else:
            scratch = self.__dict__.get("_scratch")
            if scratch is None:
                scratch = self.__dict__["_scratch"] = memoryview(bytearray(self._lay.body_size))
            if self._lock.try_read_into(mv, scratch) < 0:
                return -1
        return self._words["frame"][0]

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

    # --- closing -------------------------------------------------------------------------

    def _unmap(self) -> None:
        """Before :meth:`close` unmaps (the owner's segment stays until :meth:`unlink`)."""
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

    def unlink(self) -> bool:
        """Remove this model's shared-memory name (owner; after or instead of close)."""
        if self.name is None:
            return False
        return self.remove_segment(self.name)

    def __repr__(self) -> str:
        return (f"<WorldModel {self.name or 'private'} {'ro' if self.readonly else 'owner'} "
                f"{len(self._specs)} variables frame={self.frame}>")
