"""The controller's layers distributed across processes by configuration (issue 19 item 3).

IRSS report 2.1.2 / 2.2.5: "in the matter of a few days, a user can distribute his entire
system across the multi-processor environment", because of two world-model rules: a task
writes only its local section; it reads any section. Here:

* a TOML file (:func:`load_config`, e.g. ``examples/distributed.toml``) assigns the seven
  layers (:data:`controller.runtime.LAYER_KEYS`) to named processes; moving a layer is a
  change of that file;
* each process runs a :class:`~controller.runtime.ControllerRuntime` that executes only its
  layers' decision tables and tasks (``local_layers``), over its own world model
  ``<BASE>.<process>`` holding the full variable set;
* the **section** of a process is every variable its layers write (:func:`section_owners`:
  a variable belongs to its writer's layer - a layer key, or one of its periodic tasks -
  and a user-interface variable to the layer that declares it; the runtime's own
  ``runtime.*`` statistics are every process's own and never travel). Posting a variable of
  another process's section is refused naming that process
  (:meth:`WorldModel.set_sections`), and so is a user write of one;
* at each step's first communications segment the process imports the other sections
  (:class:`Importer`): a consistent (seqlocked) copy of each remote world model, of which
  the bytes of the variables that process owns are written into this process's body inside
  the same locked update as its own queued posts, so a reader sees whole frames of every
  section. On one host the source is the remote's shared-memory segment
  (:class:`ModelSource`); across hosts each process publishes its section's bytes after its
  frame and the importer takes the newest whole one (``tools/wm_sections.py``, Zenoh);
* only the process that runs Data Acquisition reads inputs into the world model and writes
  the Bit3 command area (one writer); the others read the service's inputs only for the
  frame number, and pace on the service's frames the same way.

Timing: the import reads each remote section as the remote left it at the end of its
latest frame, which is what a layer's table in one process sees of its neighbour too (a
decision is applied at the end of the frame that made it). A status therefore still climbs
one layer per minor frame across a process boundary: the power-up figures are those of one
process (``sim.distributed``). An ERROR climbs every layer of one process in the frame it
is decided and crosses each boundary at the next frame (one frame per boundary). Data
crossing a boundary upward (the Data Acquisition inputs, the Joint Planner's measured tool pose read by the
Cartesian Engine) are one frame older than in one process, because one process acquires
before its own communications segment.

Assumptions (named once here, and in docs/controller.md "Distributing the layers"):

* Servo Control runs in the process of Data Acquisition: the servo's rates must reach the
  command area in the frame they are computed, and Data Acquisition faults the servo
  itself for a missing output (``daq_layer``): across a process boundary they would be
  a frame older than the freshness rule allows;
* :data:`SECTION_LOST_FRAMES`: a remote section whose owner has not completed a
  communications segment for that many service frames is lost (service frames, not this
  process's steps: steps repeated on one frame while the service stalls do not count); each local layer next to a layer
  of that process (its superior or subordinate) gets fault :data:`ERR_SECTION_LOST` while
  it is not SHUT DOWN, so a lost planner brings the arm to a safe stop and a lost rack
  takes System Up/Down to ERROR;
* halt and single step (docs/console.md) stay with a controller in one process (refused
  when distributed); messages of a process without Data Acquisition stay in that process
  (only the Bit3 command writer forwards messages to the buffer's controller queue).
"""

from __future__ import annotations

import re
import struct
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Callable, Iterable, Mapping, Protocol, Sequence

import msgspec

from controller.decision import Status, TaskState
from controller.frames import TASK_DOCS
from controller.layers import ERR_PROCESS_STOPPING, ERR_SECTION_LOST
from controller.messages import Level
from controller.runtime import LAYER_KEYS, ControllerRuntime
from controller.worldmodel import WorldModel, WorldModelError
from pfma import config
from pfma.errors import ConfigError, did_you_mean

#: frames without a new communications segment of a remote process before its section is
#: lost (assumed: 100 ms at 320 Hz, like the service's F/T stale age: far beyond a host
#: hiccup or the Zenoh p99 latency, well inside the 1 s a human notices)
SECTION_LOST_FRAMES = 32
# error codes (controller.layers, docs/controller.md): ERR_SECTION_LOST of a layer whose
# neighbour's process is lost; ERR_PROCESS_STOPPING of a layer next to another process's when
# its own process stops while the system is up (:meth:`DistributedProcess.leave`): the
# layers below it stop safely
#: frames between attempts to attach a remote world model not there yet (0.1 s at 320 Hz)
ATTACH_RETRY_FRAMES = 32
#: a process's world model is ``<base><WM_SEPARATOR><process>``
WM_SEPARATOR = "."
#: the port the first process listens on when transport is zenoh and no endpoints are
#: given, the next ones on the ports after it (assumed; the bridge's default is 7447):
#: loopback only
DEFAULT_ZENOH_PORT = 7460
#: a section published over Zenoh: the layout signature (8 bytes), the owner's
#: communications-segment count (u8), then the section's bytes (:meth:`Section.pack`)
PAYLOAD_HEADER = struct.Struct("<8sQ")

_PROCESS_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,31}$")
_WM_BASE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")
_ENDPOINT = re.compile(r"^tcp/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
_PROCESS_KEYS = ("layers", "listen", "connect")
_TOP_KEYS = ("distributed", "process")
_DISTRIBUTED_KEYS = ("wm", "transport")
TRANSPORTS = ("shm", "zenoh")


class DistributedConfigError(ConfigError):
    """A distribution file with mistakes: :attr:`problems` has one message per mistake."""

    def __init__(self, source: str, problems: Sequence[str]) -> None:
        self.source = source
        self.problems = tuple(problems)
        super().__init__("\n".join(f"{source}: {p}" for p in self.problems))


# --- configuration -----------------------------------------------------------------------
@dataclass(frozen=True)
class ProcessSpec:
    """One process of a distributed controller: its name, layers and Zenoh endpoints."""

    name: str
    layers: tuple[str, ...]
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()


@dataclass(frozen=True)
class DistributedConfig:
    """Which process runs which layers (:func:`load_config`, :func:`parse_config`)."""

    processes: tuple[ProcessSpec, ...]
    wm: str | None = None  #: the world models' base name (``--wm`` overrides)
    transport: str = "shm"  #: "shm" (one host) or "zenoh" (sections published, any host)
    source: str = "<config>"

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.processes)

    def process(self, name: str) -> ProcessSpec:
        for p in self.processes:
            if p.name == name:
                return p
        raise DistributedConfigError(self.source, [
            f"no process {name!r} (processes: {', '.join(self.names)}){did_you_mean(name, self.names)}"])

    def process_of(self, layer: str) -> str:
        """The process that runs layer ``layer``."""
        for p in self.processes:
            if layer in p.layers:
                return p.name
        raise KeyError(layer)

    def wm_name(self, base: str, process: str) -> str:
        """Process ``process``'s world-model name."""
        return f"{base}{WM_SEPARATOR}{process}"

    def endpoints(self, process: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """(listen, connect) of a process on Zenoh. With none given anywhere, on loopback: the
        i-th process (from 0, file order) listens on :data:`DEFAULT_ZENOH_PORT` + i and
        connects to every earlier one, so each pair has its own link (Zenoh peers do not
        route for each other). Endpoints given in the file must link every pair too."""
        p = self.process(process)
        if any(q.listen or q.connect for q in self.processes):
            return p.listen, p.connect
        i = self.processes.index(p)
        ep = [f"tcp/127.0.0.1:{DEFAULT_ZENOH_PORT + j}" for j in range(i + 1)]
        return (ep[i],), tuple(ep[:i])


def load_config(path: str | Path) -> DistributedConfig:
    """Read and check a distribution file.

    :raises DistributedConfigError: unreadable, not TOML, or any mistake (each one named)
    """
    source = str(path)
    try:
        text = Path(path).read_bytes().decode()
    except OSError as err:
        raise DistributedConfigError(source, [f"cannot read it ({err.strerror or err})"]) from None
    except UnicodeDecodeError as err:
        raise DistributedConfigError(source, [f"not UTF-8 text ({err.reason} at byte {err.start})"]) from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise DistributedConfigError(source, [f"not valid TOML: {err}"]) from None
    except RecursionError:
        raise DistributedConfigError(source, ["not valid TOML: nested too deeply"]) from None
    return parse_config(doc, source)


class _DistributedTable(msgspec.Struct, forbid_unknown_fields=True):
    wm: Annotated[str, msgspec.Meta(pattern=_WM_BASE.pattern)] | None = None
    transport: Any = None  # judged with the endpoints (_transport)


class _ProcessTable(msgspec.Struct, forbid_unknown_fields=True):
    layers: Annotated[list[str], msgspec.Meta(min_length=1)]
    listen: list[str] = msgspec.field(default_factory=list)
    connect: list[str] = msgspec.field(default_factory=list)


class _Problem(Exception):
    """One problem of one table (pfma.config.convert's error): collected, not raised on."""

    def __init__(self, p: config.Problem) -> None:
        super().__init__(p.message)
        self.message = p.message


def _unknown(where: str, keys: Sequence[str]) -> Callable[[Mapping[str, Any]], str]:
    return lambda f: f"{where}: unknown key {f['key']!r} (keys: {', '.join(keys)}){did_you_mean(f['key'], keys)}"


_DISTRIBUTED_MESSAGES: dict[str, Any] = {
    "": "[distributed] must be a table (wm, transport)",
    "*": _unknown("[distributed]", _DISTRIBUTED_KEYS),
    "wm": "[distributed] wm = {value!r}: a world-model base name (letters, digits, '_', '.', '-')",
}


def _process_messages(where: str) -> dict[str, Any]:
    layers = f"{where}: layers must be a non-empty list of layer keys ({', '.join(LAYER_KEYS)})"
    ends = {f"{k}{suffix}": f"{where}: {k} must be a list of Zenoh endpoints like \"tcp/127.0.0.1:{DEFAULT_ZENOH_PORT}\""
            for k in ("listen", "connect") for suffix in ("", "[]")}
    return {"": f"{where}: must be a table with layers = [...]", "*": _unknown(where, _PROCESS_KEYS),
            "layers": layers, "layers?": layers, "layers[]": layers, **ends}


def parse_config(doc: Mapping[str, Any], source: str = "<config>") -> DistributedConfig:
    """A :class:`DistributedConfig` from a parsed TOML document.

    :raises DistributedConfigError: every mistake, one message each (the first of each
        table's keys and types, then every one of the placement): an unknown key, a
        process without layers, an unknown layer, a layer in two processes or in none,
        Servo Control apart from Data Acquisition, a bad endpoint or transport
    """
    problems: list[str] = []
    for k in doc:
        if k not in _TOP_KEYS:
            problems.append(f"unknown table {k!r} (tables: [distributed], [process.NAME])"
                            f"{did_you_mean(k, _TOP_KEYS)}")
    top = _distributed(doc.get("distributed", {}), source, problems)
    procs_doc = doc.get("process")
    if not isinstance(procs_doc, Mapping) or not procs_doc:
        problems.append("no processes: add a [process.NAME] table with layers = [...] for each process")
        procs_doc = {}
    processes = [p for p in (_process(name, body, source, problems) for name, body in procs_doc.items()) if p]
    _placement(processes, problems)
    transport = _transport(top.transport, processes, problems)
    if problems:
        raise DistributedConfigError(source, problems)
    return DistributedConfig(tuple(processes), top.wm, str(transport), source)


def _distributed(top: Any, source: str, problems: list[str]) -> _DistributedTable:
    """``[distributed]``: wm and transport (what is wrong with it goes to ``problems``)."""
    try:
        return config.convert(top, _DistributedTable, source=source, prefix=("distributed",),
                              messages=_DISTRIBUTED_MESSAGES, error=_Problem)
    except _Problem as err:
        problems.append(err.message)
        return _DistributedTable(transport=top.get("transport") if isinstance(top, Mapping) else None)


def _process(name: str, body: Any, source: str, problems: list[str]) -> ProcessSpec | None:
    """``[process.NAME]``: its layers (known, each once) and endpoints; None when the name
    or the table cannot be read at all."""
    where = f"[process.{name}]"
    if not _PROCESS_NAME.match(name):
        problems.append(f"{where}: a process name is a letter, then letters, digits, '_' or '-' (at most 32)")
        return None
    try:
        p = config.convert(body, _ProcessTable, source=source, prefix=("process", name),
                           messages=_process_messages(where), error=_Problem)
    except _Problem as err:
        problems.append(err.message)
        if not isinstance(body, Mapping):
            return None
        p = _ProcessTable(*(_strings(body.get(k)) for k in _PROCESS_KEYS))  # the rest still judged
    keys: list[str] = []
    for key in p.layers:
        if key not in LAYER_KEYS:
            task = TASK_DOCS.get(key)
            hint = f"; {key} is a task of layer {task[0]}: name the layer" if task else did_you_mean(key, LAYER_KEYS)
            problems.append(f"{where}: unknown layer {key!r} (layers: {', '.join(LAYER_KEYS)}){hint}")
        elif key in keys:
            problems.append(f"{where}: layer {key} named twice")
        else:
            keys.append(key)
    for k, ends in (("listen", p.listen), ("connect", p.connect)):
        for e in ends:
            m = _ENDPOINT.match(e)
            if not m or not 0 < int(m.group(2)) < 65536:
                problems.append(f"{where}: {k} endpoint {e!r} is not tcp/HOST:PORT "
                                f"(e.g. tcp/127.0.0.1:{DEFAULT_ZENOH_PORT})")
    return ProcessSpec(name, tuple(sorted(keys, key=LAYER_KEYS.index)), tuple(p.listen), tuple(p.connect))


def _strings(v: Any) -> list[str]:
    """``v`` when it is a list of strings, else [] (a table whose keys were refused)."""
    return v if isinstance(v, list) and all(isinstance(x, str) for x in v) else []


def _placement(processes: list[ProcessSpec], problems: list[str]) -> None:
    """Every layer in exactly one process; Servo Control with Data Acquisition."""
    where_is: dict[str, list[str]] = {}
    for p in processes:
        for key in p.layers:
            where_is.setdefault(key, []).append(p.name)
    for key in LAYER_KEYS:
        owners = where_is.get(key, [])
        if len(owners) > 1:
            problems.append(f"layer {key} is in processes {' and '.join(owners)}: each layer runs in exactly one")
    if processes:  # every layer somewhere (said once there are processes at all)
        for key in (k for k in LAYER_KEYS if k not in where_is):
            problems.append(f"layer {key} is in no process: add it to one process's layers")
    servo, daq = where_is.get("servo", []), where_is.get("daq", [])
    if len(servo) == 1 and len(daq) == 1 and servo != daq:
        problems.append(f"servo is in process {servo[0]} but daq, the one writer of the Bit3 command area, in "
                        f"process {daq[0]}: they run in one process (the servo's rates go to the command area "
                        f"in the frame they are computed)")


def _transport(given: Any, processes: list[ProcessSpec], problems: list[str]) -> str:
    """``[distributed] transport``: zenoh when endpoints are given, else shm by default."""
    has_ends = any(p.listen or p.connect for p in processes)
    transport = given if given is not None else ("zenoh" if has_ends else "shm")
    if transport not in TRANSPORTS:
        problems.append(f"[distributed] transport = {transport!r}: one of {', '.join(TRANSPORTS)}")
    elif transport == "shm" and has_ends:
        problems.append("listen/connect endpoints need transport = \"zenoh\" (shm: one host, shared memory)")
    return str(transport)


# --- sections ----------------------------------------------------------------------------
def section_owners(layers: Sequence[Any], config: DistributedConfig) -> dict[str, str]:
    """Variable name -> the process whose section holds it, for every variable of the
    layers (the runtime's own ``runtime.*`` are not in any section: each process has its own).

    A variable belongs to its writer's layer: a layer key, or one of the layer's periodic
    tasks (``updown_requests``); a user-interface variable (writer ``user``) to the layer
    that declares it (its requests are applied by that layer's process)."""
    writer_layer: dict[str, str] = {}
    for l in layers:
        writer_layer[l.key] = l.key
        for task in l.periodic:
            writer_layer[task] = l.key
    out: dict[str, str] = {}
    for l in layers:
        for s in l.all_specs():
            layer = writer_layer.get(s.writer, l.key)
            out[s.name] = config.process_of(layer)
    return out


class Section:
    """One process's section of a world model: the byte ranges of its variables in the
    body, merged where they are adjacent (the body is sorted by area, then layer order),
    and their packed size (:meth:`pack`, a published payload)."""

    def __init__(self, wm: WorldModel, names: Iterable[str]) -> None:
        owned = set(names)
        ranges: list[list[int]] = []
        prev = False
        # every variable in body order: a run of this section's variables is one range (with
        # the alignment padding between them); another section's variable ends the run
        for (off, n), mine in sorted((wm.var_range(s.name), s.name in owned) for s in wm.specs):
            if mine and prev:
                ranges[-1][1] = off + n
            elif mine:
                ranges.append([off, off + n])
            prev = mine
        pos = 0
        self.ranges: tuple[tuple[int, int, int], ...]  #: (body offset, bytes, packed offset)
        out = []
        for a, b in ranges:
            out.append((a, b - a, pos))
            pos += b - a
        self.ranges = tuple(out)
        self.size = pos  #: packed bytes
        self.names = tuple(sorted(owned))

    def pack(self, body, into: bytearray, at: int = 0) -> None:
        """The section's bytes from ``body`` into ``into`` from offset ``at``."""
        mv, src = memoryview(into), memoryview(body)
        for off, n, p in self.ranges:
            mv[at + p:at + p + n] = src[off:off + n]

    def copy_body(self, src, body: memoryview) -> None:
        """The section's variables from a whole body ``src`` into ``body``."""
        s = memoryview(src)
        for off, n, _ in self.ranges:
            body[off:off + n] = s[off:off + n]

    def unpack(self, packed, body: memoryview, at: int = 0) -> None:
        """The section's variables from packed bytes (:meth:`pack`) into ``body``."""
        s = memoryview(packed)
        for off, n, p in self.ranges:
            body[off:off + n] = s[at + p:at + p + n]


class SectionSource(Protocol):
    """Where one remote process's section comes from (:class:`ModelSource`: a world model,
    shared memory on this host or a model object in the simulator; Zenoh: tools/wm_sections.py)."""

    #: False: :meth:`read` fills a whole body; True: the packed section (:meth:`Section.pack`)
    packed: bool

    def read(self, into: bytearray) -> int | None:
        """Copy the newest whole section into ``into``; return the owner's communications
        segment count (None: nothing there yet or any more)."""

    def problem(self) -> str | None:
        """A message for something that stays wrong (another layout), once; else None."""

    def close(self) -> None:
        """Let go of the remote."""


class ModelSource:
    """A remote process's world model read directly: attached by name from shared memory
    (retried every :data:`ATTACH_RETRY_FRAMES` reads until it is there; a model whose
    owner died is let go and attached again when it comes back), or a model object of the
    same process (the distributed simulator)."""

    packed = False

    def __init__(self, target: "str | WorldModel", signature: bytes) -> None:
        self._sig = signature
        self._name = target if isinstance(target, str) else None
        self._wm: WorldModel | None = None if isinstance(target, str) else target
        self._retry = 0
        self._problem: str | None = None
        self._told = ""
        self._last = -1
        self._same = 0
        if self._wm is not None and self._wm.layout_signature() != signature:
            self._problem = "its world model (in this process) has another variable layout"
            self._wm = None

    def _attach(self) -> WorldModel | None:
        if self._retry > 0:
            self._retry -= 1
            return None
        self._retry = ATTACH_RETRY_FRAMES
        assert self._name is not None
        try:
            wm = WorldModel.attach(self._name)
        except WorldModelError:
            return None
        if wm.layout_signature() != self._sig:
            wm.close()
            self._problem = (f"world model {self._name} has another variable layout (a different version or "
                             f"configuration of the controller): its section is not imported")
            return None
        return wm

    def read(self, into: bytearray) -> int | None:
        wm = self._wm
        if wm is None:
            if self._name is None:
                return None
            wm = self._wm = self._attach()
            if wm is None:
                return None
        frame = wm.read_body_into(into, wait=False)
        if frame < 0:  # a segment in progress: the copy before stands (never wait on another process)
            return self._last if self._last >= 0 else None
        if frame == self._last and self._name is not None:
            self._same += 1
            if self._same >= ATTACH_RETRY_FRAMES and not wm.info().owner_alive:
                wm.close()  # its owner died: a restarted process makes a new segment
                self._wm, self._same, self._retry = None, 0, 0
                return None
        else:
            self._same = 0
        self._last = frame
        return frame

    def problem(self) -> str | None:
        p = self._problem
        if p is not None and p != self._told:
            self._told = p
            return p
        return None

    def close(self) -> None:
        if self._name is not None and self._wm is not None:
            self._wm.close()
        self._wm = None


class _Remote:
    """What the importer keeps of one remote process."""

    def __init__(self, name: str, section: Section, source: SectionSource, body_size: int) -> None:
        self.name = name
        self.section = section
        self.source = source
        self.buf = bytearray(section.size if source.packed else body_size)
        self.frame: int | None = None  #: the owner's segment count of the newest copy
        self.staged = False  #: a new copy waits for the next communications segment
        self.fresh = False  #: a new copy arrived since the last lost-check
        self.since: int | None = None  #: service frame of the lost-check that saw the newest copy
        self.seen = False  #: a copy has arrived at least once
        self.lost = False


class Importer:
    """Imports the other processes' sections into one process's world model.

    :meth:`fetch` reads each remote (a consistent copy; before the communications segment,
    outside its lock); the copy is written into the body by :meth:`apply`, which the world
    model runs inside the segment's locked update (:meth:`WorldModel.set_importer`).
    :meth:`frame_hook` is the runtime's ``before_segment``: fetch (unless the driver fetched
    already, :attr:`prefetched`: the simulator fetches every process before any steps),
    then the lost-section faults."""

    def __init__(self, rt: ControllerRuntime, config: DistributedConfig, process: str,
                 sections: Mapping[str, Section], sources: Mapping[str, SectionSource]) -> None:
        self.rt = rt
        self.config = config
        self.process = process
        self.remotes = {p: _Remote(p, sections[p], sources[p], rt.wm.body_size) for p in sources}
        self.prefetched = False
        self.imports = 0  #: sections written into the body
        self.lost_events = 0
        #: (local layer, the other process, what it is to the layer) for each local layer
        #: next to another process's layer (its superior or subordinate)
        self.edges: list[tuple[Any, str, str]] = []
        for l in rt.run_layers:
            for other, how in ((l.superior, "superior"), (l.subordinate, "subordinate")):
                if other is not None and other.key not in rt.local_keys:
                    self.edges.append((l, config.process_of(other.key), f"{how} {other.title}"))
        rt.wm.set_importer(self.apply)

    def fetch(self) -> None:
        for r in self.remotes.values():
            frame = r.source.read(r.buf)
            why = r.source.problem()
            if why is not None:
                self.rt.post("runtime", Level.ERROR, f"process {r.name}: {why}")
            if frame is not None and frame != r.frame:
                r.frame, r.staged, r.fresh, r.seen = frame, True, True, True

    def _update_lost(self) -> None:
        """Lost: no new copy for :data:`SECTION_LOST_FRAMES` service frames (counted in the
        service's frames, not in this process's steps: a burst of steps on one frame, while
        the service stalls, is no time for the others to have run)."""
        f = self.rt.frame
        for r in self.remotes.values():
            if r.fresh or r.since is None:
                r.since, r.fresh = f, False
            lost = f - r.since >= SECTION_LOST_FRAMES
            if lost != r.lost:
                r.lost = lost
                if lost:
                    self.lost_events += 1
                    self.rt.post("runtime", Level.WARNING if not r.seen else Level.ERROR,
                                 f"process {r.name}: its world-model section "
                                 f"{'has not arrived' if not r.seen else 'stopped'} "
                                 f"({SECTION_LOST_FRAMES} frames without a new one)")
                else:
                    self.rt.post("runtime", Level.INFO, f"process {r.name}: its world-model section is back")

    def apply(self, body: memoryview) -> None:
        for r in self.remotes.values():
            if r.staged:
                r.staged = False
                if r.source.packed:
                    r.section.unpack(r.buf, body)
                else:
                    r.section.copy_body(r.buf, body)
                self.imports += 1

    def frame_hook(self) -> None:
        if not self.prefetched:
            self.fetch()
        self.prefetched = False
        self._update_lost()
        self.check_lost()

    def check_lost(self) -> None:
        """Fault each local layer next to a lost process's layer while it is not SHUT DOWN;
        clear the fault when the section is back (ERROR itself stays until ERROR RESET)."""
        rt = self.rt
        for layer, proc, what in self.edges:
            lost = self.remotes[proc].lost
            if lost and not (layer.fault and layer.error_code == ERR_SECTION_LOST):
                if rt.wm.get_state_variable(layer.v_status) != Status.SHUT_DOWN:
                    layer.set_fault(rt, ERR_SECTION_LOST, f"process {proc} ({what}) lost: no world-model "
                                                          f"section for {SECTION_LOST_FRAMES} frames")
            elif not lost and layer.error_code == ERR_SECTION_LOST:
                layer.clear_fault(rt)

    @property
    def seen_all(self) -> bool:
        """Every remote section has arrived at least once."""
        return all(r.seen for r in self.remotes.values())

    def missing(self) -> list[str]:
        """The processes whose section has not arrived yet, or is lost."""
        return [r.name for r in self.remotes.values() if not r.seen or r.lost]

    def close(self) -> None:
        for r in self.remotes.values():
            r.source.close()


class DistributedProcess:
    """One process of a distributed controller: its runtime, sections and importer.

    :param config: the distribution (:func:`load_config`)
    :param process: this process's name in it
    :param client: the command writer (``writer="commands"``) where this process runs
        Data Acquisition, else any reader of the service's inputs (frames only)
    :param wm_base: the world models' base name (``<base>.<process>``); None: private
        memory (the simulator), then ``sources`` must be given
    :param sources: each other process's :class:`SectionSource` (default: its shared-memory
        world model by name, :class:`ModelSource`)
    :param runtime_kw: further :class:`ControllerRuntime` arguments (frames, clock ...)
    """

    def __init__(self, config: DistributedConfig, process: str, client, *, wm_base: str | None = None,
                 sources: Mapping[str, SectionSource] | Callable[["DistributedProcess"], Mapping[str,
                                                                                           SectionSource]] | None = None,
                 **runtime_kw) -> None:
        self.config = config
        self.spec = config.process(process)
        self.name = process
        self.wm_base = wm_base
        self.wm_name = config.wm_name(wm_base, process) if wm_base else None
        self.rt = ControllerRuntime(client, wm_name=self.wm_name, local_layers=self.spec.layers, **runtime_kw)
        self.importer: Importer | None = None
        try:
            owners = section_owners(self.rt.layers, config)
            self.owners = owners
            models = {p: config.wm_name(wm_base, p) for p in config.names} if wm_base else {}
            self.rt.wm.set_sections(process, {n: p for n, p in owners.items() if p != process}, models)
            self.sections = {p: Section(self.rt.wm, [n for n, q in owners.items() if q == p]) for p in config.names}
            #: this process's own section (what it publishes over Zenoh)
            self.section = self.sections[process]
            self.signature = self.rt.wm.layout_signature()
            if callable(sources):
                sources = sources(self)
            if sources is None:
                if wm_base is None:
                    raise ValueError("a distributed process in private memory needs its sources")
                sources = {p: ModelSource(config.wm_name(wm_base, p), self.signature)
                           for p in config.names if p != process}
            self.importer = Importer(self.rt, config, process, self.sections, sources)
            self.rt.before_segment = self.importer.frame_hook
        except BaseException:
            self.close()
            raise
        self._payload = bytearray(PAYLOAD_HEADER.size + self.section.size)
        self._body = bytearray(self.rt.wm.body_size)

    def payload(self) -> bytes:
        """This process's section as published after its frame: the layout signature, its
        communications-segment count, the section's bytes (one consistent copy)."""
        frame = self.rt.wm.read_body_into(self._body)
        PAYLOAD_HEADER.pack_into(self._payload, 0, self.signature, frame)
        self.section.pack(self._body, self._payload, PAYLOAD_HEADER.size)
        return bytes(self._payload)

    @property
    def layers(self) -> tuple[str, ...]:
        return self.spec.layers

    def leave(self) -> bool:
        """This process is stopping while its layers run: fault each local layer next to
        another process's (:data:`ERR_PROCESS_STOPPING`), so its table goes to ERROR and
        commands SHUT DOWN below (the servo's safe stop, Data Acquisition's disarm) and the
        processes above see ERROR. Returns False when there is nothing to stop. (The
        process with System Up/Down powers down in order instead: a POWER DOWN request.)"""
        if self.stopped():
            return False
        rt = self.rt
        assert self.importer is not None
        for layer, proc, what in self.importer.edges:
            if rt.wm.get_state_variable(layer.v_status) != Status.SHUT_DOWN:
                layer.set_fault(rt, ERR_PROCESS_STOPPING, f"process {self.name} is stopping (its {what} runs in "
                                                          f"process {proc})")
        return True

    def stopped(self) -> bool:
        """Every local layer is SHUT DOWN, or in ERROR with its safe task no longer running."""
        get = self.rt.wm.get_state_variable
        for layer in self.rt.run_layers:
            st = get(layer.v_status)
            if st != Status.SHUT_DOWN and (st != Status.ERROR or layer.task_state == TaskState.RUNNING):
                return False
        return True

    def close(self, unlink: bool = False) -> None:
        """Let go of the other sections and close the world model (``unlink``: remove its
        shared-memory name too; otherwise it stays, ownerless, like one process's)."""
        if self.importer is not None:
            self.importer.close()
        self.rt.close()
        if unlink and self.wm_name is not None:
            WorldModel.remove_segment(self.wm_name)


__all__ = ["DistributedConfig", "DistributedConfigError", "DistributedProcess", "Importer", "ModelSource",
           "ProcessSpec", "Section", "SectionSource", "load_config", "parse_config", "section_owners",
           "SECTION_LOST_FRAMES", "ERR_SECTION_LOST", "ERR_PROCESS_STOPPING", "DEFAULT_ZENOH_PORT", "PAYLOAD_HEADER", "WM_SEPARATOR"]
