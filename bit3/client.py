"""The small Python API other folders use to read and write the Bit3 buffer.

Tools read (the default is read-only)::

    with Client.attach("pfma") as c:
        snap = c.read_inputs()
        snap.frame, snap.t_s, snap.adc_value[3]     # fields by name
        snap.elbow_pitch_angle                      # a rack channel's engineering value
        for m in c.new_messages(): print(m.format())

A controller claims the command area (and its message queue) and writes::

    c = Client.attach("pfma", writer="commands", owner="controller")
    c.write_commands(joint_rate_rad_s=[0.1, 0, 0, 0, 0, 0], arm_request=1)
    c.write_commands(elbow_pitch_command=0.05)     # one DAC channel by its rack signal
    c.post_message("trajectory started")

Every ``write_commands`` increments ``heartbeat`` and stamps ``t_s``; the service's
watchdog forces the outputs safe when the heartbeat stops.

Snapshots are preallocated: ``read_inputs()`` refreshes and returns the same
:class:`Snapshot` each call (nothing is allocated); use ``snap.copy()`` to keep one.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Iterable, Literal

import numpy as np

from bit3.layout import (
    Layout, ServiceState, Severity, build_layout, default_layout, resolve_role, struct_names,
)
from bit3.buffer import (
    DEFAULT_READ_TIMEOUT_S, AreaReader, Bit3Buffer, Bit3Error, HeaderInfo, Message, OwnerInfo,
)
from pfma.rack import load_rack

#: the engineering value of a channel entry, by kind
PRIMARY_FIELD = {"rtd": "rtd_angle_rad", "adc": "adc_value", "dac": "dac_value",
                 "pio": "pio_port_bits", "board": "board_status", "link": "link_status",
                 "hc": "hc_axes", "device": "device_rate_hz"}
QUEUES = {"service": "service_messages", "controller": "controller_messages"}


class Snapshot:
    """One area's record with attribute access by field name and by channel name.

    ``snap.field`` gives a Python scalar for scalar fields and a numpy view (into this
    snapshot) for array fields; ``snap.<signal>`` or ``snap.value(signal)`` gives a
    channel's engineering value; ``snap.channel(signal)`` all of its elements.
    """

    __slots__ = ("record", "area", "seq", "_layout", "_names")

    def __init__(self, record: np.ndarray, area: str, layout: Layout, seq: int = -1) -> None:
        self.record = record
        self.area = area
        self.seq = seq  #: sequence number of the copy (even)
        self._layout = layout
        self._names = frozenset(struct_names(record.dtype))

    @property
    def layout(self) -> Layout:
        """The layout this snapshot was read with (channel names and roles)."""
        return self._layout

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        if name in self._names:
            return self[name]
        try:
            return self.value(name)
        except KeyError:
            raise AttributeError(f"area {self.area} has no field or channel {name!r}") from None

    def __getitem__(self, name: str) -> Any:
        v = self.record[name]
        return v.item() if v.ndim == 0 else v

    def text(self, name: str) -> str:
        """A zero-padded UTF-8 byte-array field as text (``inputs.first_trip_text``)."""
        return bytes(self.record[name]).rstrip(b"\0").decode(errors="replace")

    def _entry(self, signal: str):
        return self._layout.channel(signal, self.area)

    def value(self, signal: str) -> Any:
        """Engineering value of a rack channel (or board/link/HC/device entry) in this area."""
        c = self._entry(signal)
        fname = PRIMARY_FIELD.get(c.kind, c.fields[0][0])
        idx = next(i for f, i, _ in c.fields if f == fname)
        v = self.record[fname][idx]
        return v.item() if np.ndim(v) == 0 else v

    def channel(self, signal: str) -> dict[str, Any]:
        """Every element of one entry: ``{"rtd_counts": .., "rtd_angle_rad": .., ...}``."""
        c = self._entry(signal)
        out = {}
        for f, i, _ in c.fields:
            v = self.record[f][i]
            out[f] = v.item() if np.ndim(v) == 0 else v.copy()
        return out

    def copy(self) -> "Snapshot":
        return Snapshot(self.record.copy(), self.area, self._layout, self.seq)

    def as_dict(self) -> dict[str, Any]:
        out = {}
        for n in struct_names(self.record.dtype):
            v = self.record[n]
            out[n] = v.item() if v.ndim == 0 else v.tolist()
        return out

    def __dir__(self) -> Iterable[str]:
        return list(self._names) + [c.name for c in self._layout.channels]

    def __repr__(self) -> str:
        return f"<Snapshot {self.area} seq={self.seq}>"


#: command fields the client stamps itself
_STAMPS = ("heartbeat", "t_s", "writer_pid", "writer_token")


def _check_finite(key: str, value: Any) -> None:
    """Bit3Error unless every float or complex number in ``value`` is finite: what
    ``np.all(np.isfinite(np.asarray(value)))`` decides for a value numpy reads as float or
    complex, with the common cases (a Python or float64 scalar, an int, a float64 array)
    decided without building an array."""
    t = type(value)
    if t is float or t is np.float64:
        ok = math.isfinite(value)
    elif t is int or t is bool:
        return
    elif t is np.ndarray and value.dtype.kind == "f":
        ok = bool(np.isfinite(value).all()) if value.size > 16 else \
            all(map(math.isfinite, value.ravel().tolist()))
    else:
        arr = np.asarray(value)
        ok = arr.dtype.kind not in "fc" or bool(np.all(np.isfinite(arr)))
    if not ok:
        raise Bit3Error(f"command {key} = {value!r} is not finite")


class Client:
    """Attach to the buffer as a reader, or as the writer of one role's areas."""

    def __init__(self, buf: Bit3Buffer, role: str | None = None, owner: str | None = None,
                 clock_now: Callable[[], float] | None = None) -> None:
        self.buffer = buf
        self.layout = buf.layout
        self.role = role
        self.owner = owner
        self._now = clock_now or buf.clock_now
        self._readers: dict[str, AreaReader] = {}
        self._snaps: dict[str, Snapshot] = {}
        self._cursor = {q: 0 for q in QUEUES.values()}
        self._cmd = None
        self._frame_word: memoryview[Any] | None = None  #: header frame word (writers)
        self._closed_loop = False
        #: write_commands key -> (field, index or None), resolved once per key
        self._targets: dict[str, tuple[str, int | None]] = {}
        if role == "controller":
            self._cmd = buf.writer("commands")
            claim = buf.owner("commands")
            # the claim's pid and token ride in every command body: the service obeys a
            # command area only while both match the header's owner slot (second writers refused)
            self._cmd.record["writer_pid"] = claim.pid
            self._cmd.record["writer_token"] = claim.claimed_ns
            self._frame_word = buf._word(buf._hdr_off["frame"], "Q")

    @classmethod
    def attach(cls, name: str = "pfma", writer: str | Literal[False] | None = False,
               owner: str | None = None, *, rack: str | Path | None = None,
               layout: Layout | None = None, path: str | Path | None = None,
               clock_now: Callable[[], float] | None = None,
               timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> "Client":
        """Attach to shared memory ``name`` (or the file/device window ``path``).

        :param writer: False/None = read-only; ``"commands"``/``"controller"`` or
            ``"inputs"``/``"service"`` to claim that role's areas
        :param owner: the name written into the header's owner slots (required for writers)
        :param rack: rack TOML the layout is built from (default: the IRSS rack)
        :raises LayoutMismatchError, OwnershipError, Bit3Error:
        """
        if layout is None:
            layout = build_layout(load_rack(rack)) if rack not in (None, "fake", "default") \
                else default_layout()
        role = resolve_role(writer) if writer else None
        if role and not owner:
            raise Bit3Error("a writer needs an owner name (owner='my-controller')")
        readonly = role is None
        if path is not None:
            buf = Bit3Buffer.from_file(path, layout, readonly=readonly)
        else:
            buf = Bit3Buffer.attach(name, readonly=readonly, layout=layout)
        if clock_now is not None:
            buf.clock_now = clock_now
        for lk in (buf.lock(a.name) for a in layout.areas if a.seqlocked):
            lk.timeout_s = timeout_s
        try:
            if role:
                assert owner  # checked above: a writer needs an owner
                buf.claim(role, owner)
            return cls(buf, role, owner, clock_now)
        except BaseException:
            buf.close()
            raise

    # --- reading -----------------------------------------------------------------------

    def read(self, area: str) -> Snapshot:
        """A consistent copy of a data area (preallocated; overwritten by the next read)."""
        r = self._readers.get(area)
        if r is None:
            r = self._readers[area] = self.buffer.reader(area)
            self._snaps[area] = Snapshot(r.record, area, self.layout)
        snap = self._snaps[area]
        snap.seq = r.read()
        return snap

    def read_inputs(self) -> Snapshot:
        return self.read("inputs")

    def read_stats(self) -> Snapshot:
        return self.read("stats")

    def read_commands(self) -> Snapshot:
        return self.read("commands")

    def changed(self, area: str = "inputs") -> bool:
        """Something newer than the last ``read(area)`` was published (cheap poll)."""
        r = self._readers.get(area)
        return True if r is None else r.changed()

    def header(self) -> HeaderInfo:
        return self.buffer.header()

    @property
    def service_state(self) -> ServiceState:
        return self.buffer.header().service_state

    def owners(self) -> dict[str, OwnerInfo]:
        return {o.area: o for o in self.buffer.header().owners}

    def messages(self, since_seq: int = 0, queue: str = "service") -> list[Message]:
        """Messages newer than ``since_seq`` in one queue (``"service"`` or ``"controller"``)."""
        return self.buffer.queue(QUEUES.get(queue, queue)).read(since_seq)

    def new_messages(self) -> list[Message]:
        """Messages of both queues not returned by earlier calls, in time order."""
        out: list[Message] = []
        for q in QUEUES.values():
            got = self.buffer.queue(q).read(self._cursor[q])
            if got:
                self._cursor[q] = got[-1].seq
            out += got
        out.sort(key=lambda m: (m.t_s, m.queue, m.seq))
        return out

    # --- writing (controller) ----------------------------------------------------------

    @property
    def command(self) -> np.ndarray:
        """The private command record ``write_commands`` publishes (controller only)."""
        return self._writer_check().record

    def _writer_check(self):
        if self._cmd is None:
            raise Bit3Error("this client does not own the command area; attach with "
                            "writer='commands', owner='...'")
        return self._cmd

    def write_commands(self, **fields: Any) -> int:
        """Set command fields (others keep their values), bump the heartbeat, publish.

        Keys are command-area fields (``joint_rate_rad_s``, ``current_limit_a``,
        ``gripper``, ``matrix_route``, ``arm_request``, ``rearm_counter``, ``mode``,
        ``inputs_frame``, ``controller_frame``) or DAC channel signals
        (``elbow_pitch_command``, ``gripper_current_limit``). Non-finite numbers are
        refused. Returns the new heartbeat.

        ``inputs_frame`` says which service frame's inputs the rate commands were computed
        from; the service drives rate channels only from commands at most its configured
        age old (default 4 frames). A write that does not give it is stamped with the
        newest frame the service has published at each publish, keep-alives included (right
        for an open-loop writer whose commands do not depend on the inputs: a fixed
        setpoint, an operator's jog, a checkout step). Once a writer passes
        ``inputs_frame``, the client never stamps it again: a controller closing a loop
        gives it on every write, and a keep-alive (:meth:`publish_commands`) does not make
        its old rates fresh.
        """
        w = self._writer_check()
        rec = w.record
        # all or nothing: a bad key or value leaves the record unchanged. The record is a
        # view of the writer's ``raw`` bytes, so one bytes copy of the body is the undo
        # (cheaper than a structured-record copy; same effect)
        src = w._src
        backup = bytes(src)
        if "inputs_frame" in fields:
            self._closed_loop = True  # from now on the writer says which inputs it used
        targets = self._targets
        try:
            for key, value in fields.items():
                hit = targets.get(key)
                if hit is None:
                    hit = targets[key] = self._command_target(key, rec.dtype.names)
                target, idx = hit
                _check_finite(key, value)
                try:
                    if idx is None:
                        rec[target] = value
                    else:
                        rec[target][idx] = value
                except (ValueError, TypeError, OverflowError) as err:
                    raise Bit3Error(f"command {key} = {value!r}: {err}") from err
        except BaseException:
            src[:] = backup
            raise
        return self.publish_commands()

    def _command_target(self, key: str, names: tuple[str, ...]) -> tuple[str, int | None]:
        if key in ("heartbeat", "t_s", "writer_pid", "writer_token"):
            raise Bit3Error(f"command field {key!r} is set by write_commands itself")
        if key in names:
            return key, None
        try:
            c = self.layout.channel(key, "commands")
        except KeyError:
            raise Bit3Error(f"no command field or DAC command channel {key!r}; fields: "
                            f"{', '.join(n for n in names if n not in _STAMPS)}; "
                            f"channels: {', '.join(c.name for c in self.layout.channels if c.area == 'commands')}"
                            ) from None
        return c.fields[0][0], c.fields[0][1]

    @property
    def service_frame(self) -> int:
        """The newest frame number the service has published (a command writer's view)."""
        self._writer_check()
        assert self._frame_word is not None
        return int(self._frame_word[0])

    def publish_commands(self) -> int:
        """Publish :attr:`command` as it is (heartbeat + 1, t_s = now)."""
        w = self._writer_check()
        rec = w.record
        hb = int(rec["heartbeat"]) + 1
        rec["heartbeat"] = hb
        if not self._closed_loop:  # an open-loop writer: its setpoint is as new as the inputs
            assert self._frame_word is not None  # set with the command writer _writer_check found
            rec["inputs_frame"] = self._frame_word[0]
        rec["t_s"] = self._now()
        w.publish()
        return hb

    def post_message(self, text: str, severity: Severity | int = Severity.INFO, code: int = 0,
                     source: int = 0) -> int:
        """Append to this writer's message queue; returns the message's sequence number."""
        if self.role is None:
            raise Bit3Error("a read-only client cannot post messages; attach as a writer")
        q = "service_messages" if self.role == "service" else "controller_messages"
        return self.buffer.queue(q).post(text, severity, code, source, t_s=self._now())

    # --- life cycle ----------------------------------------------------------------------

    def close(self) -> None:
        self._readers.clear()
        self._snaps.clear()
        self._cmd = None
        self._frame_word = None  # a view the buffer releases itself
        self.buffer.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<Client {self.buffer.name} role={self.role or 'reader'} owner={self.owner!r}>"
