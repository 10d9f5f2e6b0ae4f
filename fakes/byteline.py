"""The far end of a serial line, with the line faults every byte-stream fake offers.

A byte-stream device model (the F/T controller, the CRL master) keeps its output in
``self._tx`` and its own time in ``self.t_s``; :class:`FaultyLine` gives it
``transmit(max_bytes)`` with scheduled noise bytes, dropped bytes, stalls and a
disconnect, counted so tests can compare what went out with what the driver saw.
Models that produce output lazily override :meth:`_refill`.

Every fault can also be ended (a technician's "clear"): :meth:`noise_every` and
:meth:`drop_every` repeat a burst every N model bytes until :meth:`stop_noise` /
:meth:`stop_drops`; :meth:`stall` without a duration lasts until :meth:`resume`;
:meth:`reconnect` ends a :meth:`disconnect`.
"""

from __future__ import annotations


class FaultyLine:
    """Mixin: call :meth:`_init_line` from ``__init__``."""

    def _init_line(self) -> None:
        self._tx = bytearray()
        self.t_s = getattr(self, "t_s", 0.0)
        self.connected = True
        self._noise: list[tuple[int, bytes]] = []  # (due at tx_count, bytes)
        self._drops: list[tuple[int, int]] = []  # (due at tx_count, n)
        self._drop_left = 0
        self._stall_until_s = -1.0
        self._noise_every: tuple[bytes, int] | None = None  # (burst, every N model bytes)
        self._drop_every: tuple[int, int] | None = None  # (n lost, every N model bytes)
        self._next_noise_at = 0
        self._next_drop_at = 0
        self.tx_count = 0  #: model bytes taken from the output queue (incl. dropped)
        self.noise_bytes_sent = 0
        self.bytes_dropped = 0
        #: called after a fault is set or ended (the serial board's line model: the far end's
        #: ``next_output_s`` may have changed)
        self.on_line_change = None

    def _line_changed(self) -> None:
        if self.on_line_change is not None:
            self.on_line_change()

    def next_output_s(self) -> float | None:
        """This end's own time before which :meth:`transmit` surely returns nothing (so the
        serial board model need not ask it before then); None when it cannot say: output
        already queued, a fault schedule active, stalled or disconnected. Lazy producers
        say when their next output is due in :meth:`_quiet_until_s`."""
        if self._tx or self._noise or self._drops or self._noise_every is not None \
                or self._drop_every is not None or self.stalled or not self.connected:
            return None
        return self._quiet_until_s()

    def _quiet_until_s(self) -> float | None:
        """Lazy producers: when the next output is due (own time; inf: only after input)."""
        return None

    def _refill(self) -> None:
        """Called when the output queue is empty (lazy producers put their next bytes)."""

    @property
    def stalled(self) -> bool:
        return self.t_s < self._stall_until_s

    def transmit(self, max_bytes: int) -> bytes:
        """Up to ``max_bytes`` bytes ready for the line (the owner paces them)."""
        if not self.connected or max_bytes <= 0 or self.stalled:
            return b""
        if self._noise_every is not None or self._drop_every is not None:
            self._schedule_repeats(self.tx_count + max_bytes)
        if not self._tx and not self._noise:  # the usual idle poll: nothing to build
            self._refill()
            if not self._tx:
                return b""
        out = bytearray()
        while len(out) < max_bytes:
            if self._noise and self._noise[0][0] <= self.tx_count:
                _, noise = self._noise.pop(0)
                take = noise[: max_bytes - len(out)]
                if len(take) < len(noise):
                    self._noise.insert(0, (self.tx_count, noise[len(take):]))
                out += take
                self.noise_bytes_sent += len(take)
                continue
            if not self._tx:
                self._refill()
                if not self._tx:
                    break
            if self._drops and self._drops[0][0] <= self.tx_count:
                self._drop_left += self._drops.pop(0)[1]
            b = self._tx.pop(0)
            self.tx_count += 1
            if self._drop_left:
                self._drop_left -= 1
                self.bytes_dropped += 1
                continue
            out.append(b)
        return bytes(out)

    def _schedule_repeats(self, horizon: int) -> None:
        """Put the repeating bursts due up to model byte ``horizon`` on the schedules."""
        if self._noise_every is not None:
            data, every = self._noise_every
            while self._next_noise_at <= horizon:
                self._noise.append((self._next_noise_at, data))
                self._next_noise_at += every
            self._noise.sort(key=lambda e: e[0])
        if self._drop_every is not None:
            n, every = self._drop_every
            while self._next_drop_at <= horizon:
                self._drops.append((self._next_drop_at, n))
                self._next_drop_at += every
            self._drops.sort(key=lambda e: e[0])

    # -- faults ---------------------------------------------------------------------------
    def inject_noise(self, data: bytes, after_bytes: int = 0) -> None:
        """Insert ``data`` into the output after ``after_bytes`` more model bytes."""
        self._noise.append((self.tx_count + after_bytes, bytes(data)))
        self._noise.sort(key=lambda e: e[0])
        self._line_changed()

    def drop_next(self, n: int, after_bytes: int = 0) -> None:
        """Lose ``n`` output bytes, starting after ``after_bytes`` more model bytes."""
        self._drops.append((self.tx_count + after_bytes, int(n)))
        self._drops.sort(key=lambda e: e[0])
        self._line_changed()

    def noise_every(self, data: bytes, every_bytes: int) -> None:
        """Insert ``data`` after every ``every_bytes`` model bytes, from the next one on,
        until :meth:`stop_noise` (a line picking up interference for a while)."""
        if every_bytes < 1 or not data:
            raise ValueError("noise_every needs data and every_bytes >= 1")
        self._noise_every = (bytes(data), int(every_bytes))
        self._next_noise_at = self.tx_count + int(every_bytes)
        self._line_changed()

    def stop_noise(self) -> None:
        """End the noise: repeating and scheduled bursts not yet sent are dropped."""
        self._noise_every = None
        self._noise.clear()
        self._line_changed()

    def drop_every(self, n: int, every_bytes: int) -> None:
        """Lose ``n`` output bytes after every ``every_bytes`` model bytes until
        :meth:`stop_drops`."""
        if every_bytes < 1 or n < 1:
            raise ValueError("drop_every needs n >= 1 and every_bytes >= 1")
        self._drop_every = (int(n), int(every_bytes))
        self._next_drop_at = self.tx_count + int(every_bytes)
        self._line_changed()

    def stop_drops(self) -> None:
        """End the drops (scheduled ones not yet due are cancelled; a run in progress ends)."""
        self._drop_every = None
        self._drops.clear()
        self._drop_left = 0
        self._line_changed()

    def stall(self, seconds: float = float("inf")) -> None:
        """Send nothing for ``seconds`` of the model's time (default: until :meth:`resume`)."""
        self._stall_until_s = self.t_s + seconds
        self._line_changed()

    def resume(self) -> None:
        """End a stall now."""
        self._stall_until_s = -1.0
        self._line_changed()

    def disconnect(self) -> None:
        """Go silent for good (a PtyDevice owner then closes the line)."""
        self.connected = False
        self._line_changed()

    def reconnect(self) -> None:
        """Talk again after :meth:`disconnect` (the output queue carries on where it was)."""
        self.connected = True
        self._line_changed()
