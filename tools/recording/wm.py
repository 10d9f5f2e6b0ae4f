"""World-model topics: chosen controller variables in the same MCAP as the Bit3 topics.

``pfma record FILE.mcap --wm NAME --var PATTERN[@RATE] ...`` (docs/recording.md,
"World-model topics"). The recorder attaches the controller's world model **read-only**
(:meth:`WorldModel.attach`, as ``pfma wm`` does) and never writes to it. From its writing
loop (``Recorder.poll``; no thread of its own) it looks at the world model's frame counter;
when a new communications segment has completed and a chosen variable is due, it takes one
consistent copy of the due variables (:meth:`WorldModel.get_task_inputs`) and writes one
JSON message per world-model area on ``/pfma/wm/<area>``.

- **Patterns** are ``fnmatch`` globs over variable names, case-sensitive (``servo.*``,
  ``ui.state``, ``*.status``). A pattern that matches nothing is a usage mistake
  (:class:`WmUsageError`: one message with the closest names; ``pfma record`` exits 2).
- **Rates.** ``PATTERN@RATE`` samples at RATE Hz of the world model's frame time: a
  variable is due at the first frame at or after ``t0 + k / RATE``; the average rate is
  exact, single samples jitter by one controller frame. No rate, or a rate at or above the
  frame rate, is every controller frame the recorder sees, capped at the service's frame
  rate (the controller's frame is locked to the service's): the controller runs two
  communications segments per minor frame (inputs in, outputs out), and at most one
  sample is taken per half a frame period. A variable matched by several patterns takes
  the highest rate.
- **What a sample is.** The world model as the recorder found it when it looked (the
  writing loop looks every 2 ms): nearly always the end of a controller frame; a look that
  falls between a frame's two segments copies the state after the first one (the new
  inputs, the previous outputs), stamped with that segment's time.
- **Time.** A sample's ``log_time`` is the world model's frame time (``frame_t_s``, the
  controller's ``time.monotonic()`` at the end of the communications segment) * 1e9 +
  the recording's ``epoch_offset_ns``, exactly as the service's ``t_s`` is mapped: both
  are CLOCK_MONOTONIC of the same host, so no further mapping is needed (ASSUMPTION: the
  controller and the service run on one host; on two hosts their monotonic clocks are
  unrelated and the world-model topics would be offset by the difference of the hosts'
  boot times).
- **Consistency.** The frame number is read before and after the copy; the copy belongs
  to that frame only when the two agree (a segment that completes in between changes the
  frame, and the copy is retried, at most :data:`READ_ATTEMPTS` times).
- **Messages**: ``{"t_s", "frame", <prefix>: {<rest>: value}}``: a variable ``servo.error_rad``
  is the field ``servo.error_rad`` of ``/pfma/wm/task_status`` as nested objects, so
  Foxglove's Plot panel takes the path ``/pfma/wm/task_status.servo.error_rad[2]``.
  Arrays are lists; NaN and infinity are ``null`` (as on the other JSON topics). A message
  holds the variables of its area that were due at that frame.
- **Not lossless.** The world model keeps only its newest frame (no ring): a recorder
  descheduled for more than a controller frame does not see that frame. The controller
  frames between two every-frame samples are counted from the frame times
  (``frames_unseen`` in the ``pfma.wm.summary`` metadata).
- **A controller that stops** (its process gone, or its segment closed or replaced): the
  recording goes on with the Bit3 topics and says so once; every :data:`RETRY_S` the
  recorder looks for the world model again and, when one with the chosen variables (same
  names, types and shapes) is back, continues its topics (a new session:
  ``sessions`` + 1).
"""

from __future__ import annotations

import fnmatch
import json
import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Iterable, Sequence

import numpy as np

from pfma.errors import PfmaError, did_you_mean
from tools.attach import shm_id as _shm_id
from tools.recording.schema import _ns

if TYPE_CHECKING:
    from controller.worldmodel import VarSpec, WorldModel
    from tools.recording.writer import Recorder

#: topics are ``/pfma/wm/<area>``
TOPIC_PREFIX = "/pfma/wm/"
#: no new world-model frame for this long (wall time): look whether its owner is still there
STALE_S = 1.0
#: while the world model is gone: look for it again this often (one attach, wall time)
RETRY_S = 1.0
#: copies of the due variables tried before a sample is given up (a segment completed
#: during each copy); counted as ``torn_reads``
READ_ATTEMPTS = 4


class WmUsageError(PfmaError, ValueError):
    """A bad ``--var`` (no match, bad rate) or ``--wm`` use: a usage mistake (exit 2)."""


@dataclass(frozen=True)
class VarPattern:
    """One ``--var PATTERN[@RATE]``."""

    text: str
    pattern: str
    rate_hz: float | None  #: None: every controller frame the recorder sees


def parse_var(text: str) -> VarPattern:
    """``PATTERN[@RATE]`` -> :class:`VarPattern`; :class:`WmUsageError` for a bad rate."""
    pattern, at, rate = text.rpartition("@")
    if not at:
        pattern, rate = text, ""
    if not pattern.strip():
        raise WmUsageError(f"--var {text!r}: no variable pattern (e.g. --var 'servo.*' or "
                           f"--var 'servo.error_rad@100')")
    if not at:
        return VarPattern(text, pattern, None)
    try:
        hz = float(rate)
    except ValueError:
        hz = math.nan
    if not math.isfinite(hz) or hz <= 0:
        raise WmUsageError(f"--var {text!r}: bad rate {rate!r}: after '@' give a positive number "
                           f"of samples per second (e.g. {pattern}@100), or leave '@RATE' out for "
                           f"every controller frame")
    return VarPattern(text, pattern, hz)


@dataclass(frozen=True)
class WmVar:
    """One chosen variable: what the schema and the metadata say about it."""

    name: str
    area: str
    dtype: str
    shape: tuple
    units: str
    writer: str
    doc: str
    rate_hz: float | None  #: None: every frame

    def as_json(self) -> dict:
        return {"name": self.name, "area": self.area, "dtype": self.dtype, "shape": list(self.shape),
                "units": self.units, "writer": self.writer, "doc": self.doc,
                "rate_hz": self.rate_hz if self.rate_hz is not None else "every frame"}


def select(specs: Sequence["VarSpec"], patterns: Iterable[VarPattern], *, wm_name: str = "",
           frame_rate_hz: float | None = None) -> list[WmVar]:
    """The variables the patterns choose, in the world model's order (by area).

    A rate at or above ``frame_rate_hz`` is every frame; a variable several patterns
    match takes the highest rate (every frame is the highest).

    :raises WmUsageError: a pattern matches no variable (one message for all of them)
    """
    names = [s.name for s in specs]
    rate: dict[str, float | None] = {}
    bad = []
    for p in patterns:
        hits = fnmatch.filter(names, p.pattern)
        if not hits:
            bad.append(p)
            continue
        r = p.rate_hz
        if r is not None and frame_rate_hz and r >= frame_rate_hz:
            r = None
        for n in hits:
            if n not in rate or _faster(r, rate[n]):
                rate[n] = r
    if bad:
        raise WmUsageError("; ".join(_no_match(p, names, specs, wm_name) for p in bad)
                           + f" (`pfma wm list --wm {wm_name or 'NAME'}` lists the variables)")
    return [WmVar(s.name, s.area, s.dtype, tuple(s.shape), s.units, s.writer, s.doc, rate[s.name])
            for s in specs if s.name in rate]


def _faster(a: float | None, b: float | None) -> bool:
    """Rate ``a`` samples more often than ``b`` (None = every frame, the fastest)."""
    return b is not None and (a is None or a > b)


def _no_match(p: VarPattern, names: list[str], specs: Sequence["VarSpec"], wm_name: str) -> str:
    where = f"world model {wm_name!r}" if wm_name else "the world model"
    text = f"--var {p.pattern!r} matches no variable of {where}"
    globs = sorted({n.split(".", 1)[0] + ".*" for n in names})
    areas = sorted({s.area for s in specs})
    bare = p.pattern.strip("*")
    if bare in areas:
        hint = (f"; {bare!r} is an area: patterns match variable names "
                f"(`pfma wm list --area {bare}` shows its variables)")
    elif fnmatch.filter([n.lower() for n in names], p.pattern.lower()):
        hint = f"; patterns are case-sensitive (did you mean {p.pattern.lower()}?)"
    elif any(c in p.pattern for c in "*?["):  # a glob: the closest prefix globs, then names
        hint = did_you_mean(p.pattern, globs)
        core = p.pattern.strip("*?.")
        close = [n for n in names if core and core.lower() in n.lower()][:3]
        if not hint and close:
            hint = f"; did you mean {', '.join(close)}?"
    else:
        hint = did_you_mean(p.pattern, names)
    return text + hint


# ----------------------------------------------------------------------------------------
# messages and schemas


def _path(name: str) -> list[str]:
    return name.split(".")


def _leaf_schema(v: WmVar) -> dict:
    kind = np.dtype(v.dtype).kind
    base = {"b": {"type": "boolean"}, "f": {"type": ["number", "null"]}}.get(kind, {"type": "integer"})
    s: dict = dict(base)
    for n in reversed(v.shape):
        s = {"type": "array", "items": s, "minItems": int(n), "maxItems": int(n)}
    desc = v.doc or v.name
    desc += f" [{v.units}]" if v.units else ""
    desc += f"; {v.dtype}{list(v.shape) if v.shape else ''}; writer {v.writer}"
    desc += f"; {v.rate_hz:g} Hz" if v.rate_hz is not None else "; every frame"
    s["description"] = desc
    return s


def _layout(variables: Sequence[WmVar]) -> dict[str, tuple[str, ...]]:
    """Each variable's key path in its message: its name split at the dots, or the whole
    name as one key where a name is also another chosen name's prefix (``a.b`` and
    ``a.b.c``: then ``a.b.c`` keeps its dotted name)."""
    out: dict[str, tuple[str, ...]] = {}
    by_area: dict[str, list[str]] = defaultdict(list)
    for v in variables:
        by_area[v.area].append(v.name)
    for names in by_area.values():
        leaves = set(names)
        for n in names:
            parts = _path(n)
            prefixes = {".".join(parts[:k]) for k in range(1, len(parts))}
            out[n] = (n,) if prefixes & leaves else tuple(parts)
    return out


def topic_schemas(variables: Sequence[WmVar], wm_name: str) -> dict[str, dict]:
    """``/pfma/wm/<area>`` -> its JSON schema (the variables nested as in the messages)."""
    paths = _layout(variables)
    per: dict[str, dict] = {}
    for v in variables:
        root = per.setdefault(v.area, {})
        node = root
        keys = paths[v.name]
        for k in keys[:-1]:
            node = node.setdefault(k, {"type": "object", "properties": {}})["properties"]
        node[keys[-1]] = _leaf_schema(v)
    out = {}
    for area, props in per.items():
        out[TOPIC_PREFIX + area] = {
            "type": "object",
            "description": f"world model {wm_name!r}, area {area}: the chosen variables due at "
                           f"this controller frame (read-only copy; null = NaN or infinity)",
            "properties": {"t_s": {"type": "number", "description": "world-model frame time, "
                                   "controller clock = service clock (s)"},
                           "frame": {"type": "integer", "description": "world-model frame "
                                     "(communications segments completed)"},
                           **props}}
    return out


def _value(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


# ----------------------------------------------------------------------------------------
# the sampler


@dataclass
class WmCounters:
    """What ``pfma.wm.summary`` carries."""

    frames_seen: int = 0        #: new world-model frames (communications segments) the recorder looked at
    frames_unseen: int = 0      #: controller frames between two every-frame samples (by frame time)
    samples: int = 0            #: consistent copies written (one per due frame)
    torn_reads: int = 0         #: due frames given up: a segment completed during every copy
    sessions: int = 0           #: attachments to a world model (1 + reattachments)
    went_away: int = 0          #: times the world model went away mid-recording
    messages: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"frames_seen": self.frames_seen, "frames_unseen": self.frames_unseen,
                "samples": self.samples, "torn_reads": self.torn_reads, "sessions": self.sessions,
                "went_away": self.went_away, "messages": dict(self.messages)}


def _attach(name: str) -> "WorldModel":
    from controller.worldmodel import WorldModel
    return WorldModel.attach(name)


def wm_problem(name: str) -> tuple["WorldModel | None", str]:
    """``(attached model, "")`` when a live controller owns world model ``name``, else
    ``(None, why)`` (the why names the world models on this host, with a did-you-mean).

    :raises WmUsageError: ``name`` is a Bit3 buffer (waiting would never end)"""
    from controller.worldmodel import WorldModelError, list_segments
    try:
        wm = _attach(name)
    except WorldModelError as err:
        text = str(err)
        if "no magic" in text and _is_bit3_buffer(name):
            raise WmUsageError(f"/dev/shm/{name} is a Bit3 buffer (the service's --buffer), not a "
                               f"world model; --wm names the controller's world model (`pfma "
                               f"controller --wm NAME`, default pfma_wm)") from None
        if "no world model" in text:
            others = list_segments()
            hint = did_you_mean(name, others)
            here = f"; world models here: {', '.join(others)}" if others else "; no world model on this host"
            return None, f"no world model /dev/shm/{name}{hint}{here}"
        return None, text
    except (OSError, ValueError) as err:
        return None, f"world model /dev/shm/{name} not readable yet ({err})"
    info = wm.info()
    if info.owner_pid <= 0 or not info.owner_alive:
        wm.close()
        who = f"its owner {info.owner!r} (pid {info.owner_pid}) is not running" if info.owner_pid > 0 \
            else f"its owner {info.owner!r} closed it"
        return None, f"world model /dev/shm/{name} exists but {who}"
    return wm, ""


def _is_bit3_buffer(name: str) -> bool:
    from bit3.layout import MAGIC
    try:
        with open(f"/dev/shm/{name}", "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def wait_for_wm(name: str, *, timeout_s: float | None = None, say: Callable[[str], None] = print,
                stop: Callable[[], bool] = lambda: False, poll_s: float = 0.2,
                remind_every_s: float = 10.0, sleep: Callable[[float], None] = time.sleep,
                now: Callable[[], float] = time.monotonic) -> tuple["WorldModel | None", str]:
    """Attach world model ``name`` once a live controller owns it, saying once (and every
    ``remind_every_s``) why it is waiting; ``(None, why)`` on time-out or ``stop()``."""
    t0 = now()
    said = None
    next_notice = t0
    while True:
        wm, why = wm_problem(name)
        if wm is not None:
            if said is not None:
                say(f"world model /dev/shm/{name} is up (after {now() - t0:.1f} s)")
            return wm, ""
        t = now()
        if said is None or why != said:
            say(f"waiting for world model /dev/shm/{name} ... ({why}; Ctrl-C gives up)")
            said, next_notice = why, t + remind_every_s
        elif t >= next_notice:
            say(f"still waiting for world model /dev/shm/{name} ({t - t0:.0f} s; {why})")
            next_notice = t + remind_every_s
        if stop() or (timeout_s is not None and t - t0 >= timeout_s):
            return None, why
        sleep(poll_s)


class WmSampler:
    """Samples the chosen variables of one world model into a :class:`Recorder`.

    :param wm: the world model attached read-only (``WorldModel.attach``); the sampler
        owns it (closes it when it goes away and at :meth:`close`)
    :param variables: from :func:`select`
    :param say: one line for the user (the world model went away, came back)
    :param wall: wall-time source for noticing a stopped controller (tests pass theirs)
    :param attach: ``name -> (model, why)`` used to reattach (default :func:`wm_problem`)
    """

    def __init__(self, wm: "WorldModel", variables: Sequence[WmVar], *, patterns: Sequence[VarPattern] = (),
                 frame_rate_hz: float | None = None, say: Callable[[str], None] = lambda _t: None,
                 wall: Callable[[], float] = time.monotonic,
                 attach: Callable[[str], tuple["WorldModel | None", str]] | None = None) -> None:
        if not variables:
            raise WmUsageError("no world-model variable chosen")
        if not wm.readonly:
            raise ValueError("WmSampler: attach the world model read-only (WorldModel.attach)")
        self.name = wm.name or "private"
        self.variables = tuple(variables)
        self.patterns = tuple(patterns)
        self.frame_rate_hz = frame_rate_hz
        self.say = say
        self.wall = wall
        self._attach = attach or wm_problem
        self.counters = WmCounters()
        self._paths = _layout(self.variables)
        self._signature = self._sig_of(wm)
        groups: dict[float | None, list[WmVar]] = defaultdict(list)
        for v in self.variables:
            groups[v.rate_hz].append(v)
        #: rate -> (names tuple, [(area, name, key path)])
        self._groups = {r: (tuple(v.name for v in vs), [(v.area, v.name, self._paths[v.name]) for v in vs])
                        for r, vs in groups.items()}
        self._topics = {TOPIC_PREFIX + a: a for a in dict.fromkeys(v.area for v in self.variables)}
        self.wm: "WorldModel | None" = None
        self._gone_note = ""
        self._start(wm)

    # --- attachment -------------------------------------------------------------------
    def _sig_of(self, wm: "WorldModel") -> dict[str, tuple]:
        chosen = {v.name for v in self.variables}
        return {s.name: (s.dtype, tuple(s.shape)) for s in wm.specs if s.name in chosen}

    def _start(self, wm: "WorldModel") -> None:
        self.wm = wm
        self.counters.sessions += 1
        self._shm = _shm_id(wm.name) if wm.name else None
        self._last_frame = -1
        self._due: dict[float | None, float] = {}
        self._last_every_t: float | None = None
        self._last_new = self.wall()
        self._stale_said = False
        self._next_retry = 0.0
        self._next_check = 0.0

    def topics(self) -> dict[str, dict]:
        """``/pfma/wm/<area>`` -> JSON schema, for the recorder to register."""
        return topic_schemas(self.variables, self.name)

    def metadata(self) -> dict[str, str]:
        """The ``pfma.wm`` metadata record (strings)."""
        info = self.wm.info() if self.wm is not None else None
        return {"name": self.name, "owner": info.owner if info else "",
                "owner_pid": str(info.owner_pid) if info else "",
                "spec_hash": info.spec_hash if info else "",
                "patterns": json.dumps([p.text for p in self.patterns]),
                "variables": json.dumps([v.as_json() for v in self.variables]),
                "topics": json.dumps(sorted(self._topics)),
                "frame_rate_hz": f"{self.frame_rate_hz:g}" if self.frame_rate_hz else "unknown",
                "log_time": "world-model frame_t_s * 1e9 + epoch_offset_ns (both clocks are "
                            "CLOCK_MONOTONIC of one host: the service's t_s is mapped the same way)",
                "read_only": "true"}

    # --- sampling ---------------------------------------------------------------------
    def poll(self, rec: "Recorder") -> int:
        """One look from the recorder's writing loop; returns the messages written."""
        wm = self.wm
        if wm is None:
            self._retry()
            return 0
        try:
            frame = wm.frame
        except (ValueError, TypeError):  # pragma: no cover - unmapped under us
            self._went_away("its memory is gone")
            return 0
        if frame == self._last_frame:
            now = self.wall()
            if now - self._last_new > STALE_S and now >= self._next_check:
                self._next_check = now + STALE_S  # one look a second while nothing comes
                self._check_alive()
            return 0
        if frame < self._last_frame:  # the same segment reused by a new owner
            self._went_away("its frame counter went back (a new controller on the same name)")
            return 0
        self._last_new = self.wall()
        self._stale_said = False
        self._last_frame = frame
        self.counters.frames_seen += 1
        return self._sample(rec, wm, frame)

    def _sample(self, rec: "Recorder", wm: "WorldModel", frame: int) -> int:
        from controller.worldmodel import WorldModelError
        names: list[str] = []
        due_rates = []
        for _attempt in range(READ_ATTEMPTS):
            try:
                t_s = wm.info().frame_t_s
                due_rates = [r for r in self._groups if self._is_due(r, t_s, commit=False)]
                if not due_rates:
                    return 0
                names = [n for r in due_rates for n in self._groups[r][0]]
                values = wm.get_task_inputs(names)
                f2 = wm.frame
            except WorldModelError as err:  # e.g. a writer dead mid-segment (seqlock time-out)
                self._went_away(str(err))
                return 0
            if f2 == frame:
                break
            frame = f2  # a segment completed during the copy: take the newer frame
            self._last_frame = f2
        else:
            self.counters.torn_reads += 1
            return 0
        for r in due_rates:
            self._is_due(r, t_s, commit=True)
        if None in due_rates:  # controller frames between two every-frame samples
            fr = self.frame_rate_hz
            if fr and self._last_every_t is not None and t_s - self._last_every_t > 1.5 / fr:
                self.counters.frames_unseen += round((t_s - self._last_every_t) * fr) - 1
            self._last_every_t = t_s
        msgs: dict[str, dict] = {}
        for r in due_rates:
            for area, name, keys in self._groups[r][1]:
                m = msgs.get(area)
                if m is None:
                    m = msgs[area] = {"t_s": t_s, "frame": frame}
                node = m
                for k in keys[:-1]:
                    node = node.setdefault(k, {})
                node[keys[-1]] = _value(values[name])
        t_ns = _ns(t_s, rec.offset_ns)
        from tools.recording.topics import _dumps
        for area, m in msgs.items():
            topic = TOPIC_PREFIX + area
            rec.put(topic, t_ns, _dumps(m))
            self.counters.messages[topic] = self.counters.messages.get(topic, 0) + 1
        self.counters.samples += 1
        return len(msgs)

    def _is_due(self, rate: float | None, t_s: float, *, commit: bool) -> bool:
        """Whether the group of ``rate`` is due at world-model time ``t_s`` (with ``commit``:
        and take it). Every frame (``None``): at most once per half a frame period, so the
        controller's two communications segments of one minor frame give one sample and the
        rate stays at or below the service's frame rate. A rate: the first frame at or after
        each point of the grid ``t0 + k / rate`` (a pause longer than a period restarts it)."""
        due = self._due.get(rate)
        if due is not None and t_s < due - 1e-9:
            return False
        if commit:
            if rate is None:
                nxt = t_s + (0.5 / self.frame_rate_hz if self.frame_rate_hz else 0.0)
            else:
                period = 1.0 / rate
                nxt = t_s + period if due is None else due + period
                if nxt <= t_s:  # fell behind by more than a period (a pause): restart the grid here
                    nxt = t_s + period
            self._due[rate] = nxt
        return True

    # --- the controller going away and coming back ------------------------------------
    def _check_alive(self) -> None:
        wm = self.wm
        if wm is None:
            return
        name = wm.name
        why = ""
        if name and _shm_id(name) != self._shm:
            why = "its shared memory was removed or re-created"
        else:
            info = wm.info()
            if info.owner_pid <= 0:
                why = f"its owner {info.owner!r} closed it"
            elif not info.owner_alive:
                why = f"its owner {info.owner!r} (pid {info.owner_pid}) is not running"
            elif not self._stale_said:
                self._stale_said = True
                self.say(f"world model {self.name!r}: no new frame for {self.wall() - self._last_new:.1f} s "
                         f"(its owner pid {info.owner_pid} is running: halted?)")
        if why:
            self._went_away(why)

    def _went_away(self, why: str) -> None:
        wm, self.wm = self.wm, None
        if wm is not None:
            try:
                wm.close()
            except Exception:  # noqa: BLE001 - already unusable
                pass
        self.counters.went_away += 1
        self.say(f"world model {self.name!r} went away after frame {self._last_frame} ({why}); the "
                 f"recording continues with the Bit3 topics and takes the world-model topics up "
                 f"again if it comes back")
        self._next_retry = self.wall() + RETRY_S
        self._gone_note = ""

    def _retry(self) -> None:
        now = self.wall()
        if now < self._next_retry or self.name == "private":
            return
        self._next_retry = now + RETRY_S
        wm, _why = self._attach(self.name)
        if wm is None:
            return
        sig = self._sig_of(wm)
        if sig != self._signature:
            wm.close()
            note = "its chosen variables differ (names, types or shapes)"
            if note != self._gone_note:
                self._gone_note = note
                self.say(f"world model {self.name!r} is back but {note}; its topics stay stopped")
            return
        self._start(wm)
        info = wm.info()
        self.say(f"world model {self.name!r} is back (owner {info.owner!r}, pid {info.owner_pid}): "
                 f"its topics continue (world-model session {self.counters.sessions})")

    def close(self) -> None:
        if self.wm is not None:
            self.wm.close()
            self.wm = None
