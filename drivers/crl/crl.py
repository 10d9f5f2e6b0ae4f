"""CRL force-reflecting hand controller (FRHC) over a serial byte port.

The master sends a position frame every 20 ms; the controller answers with
force/torque commands (placeholder framing: :mod:`drivers.crl.crl_codec`). The port
is anything pyserial-like (``read(n)``, ``write(b)``, ``in_waiting``, ``timeout``):
``serial.serial_for_url("/dev/ttyUSB0")``, a pty, ``loop://`` or the MVME400 byte port.

Safety (pfma-model.md 8.6, assumed): 3 consecutive missing or bad frames (60 ms) trip
the watchdog. While tripped the state is invalid with ``fault=True`` and the deadman
released, and :meth:`CrlHandController.send_force` sends zero forces. After a trip (and
at start) the deadman reads released until a frame with the deadman button released
has arrived (``rearm_after_watchdog``), so a held switch cannot re-engage motion by
itself when the link comes back.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

from drivers.crl import crl_codec as codec
from drivers.crl.state import HandControllerState, safe_state
from pfma.clock import Clock, MonotonicClock
from pfma.errors import LinkError
from drivers.ratewindow import RateWindow

#: meaning of ``HandControllerState.buttons`` for source "crl" (the frame's buttons byte)
BUTTONS: dict[int, str] = {codec.BTN_DEADMAN: "deadman", codec.BTN_INDEX: "index (clutch)",
                           codec.BTN_TRIGGER: "trigger"}


def _saturate(vec: tuple[float, ...], limit: float) -> tuple[tuple[float, ...], bool]:
    """Scale ``vec`` down so its magnitude is at most ``limit`` (direction kept)."""
    mag = math.sqrt(sum(v * v for v in vec))
    if mag <= limit:
        return tuple(float(v) for v in vec), False
    k = limit / mag
    return tuple(v * k for v in vec), True


class CrlHandController:
    """Driver of the CRL force-reflecting hand controller.

    :param port: pyserial-like byte port, already open (19200 8N1 on real hardware)
    :param clock: time base for timestamps and the watchdog (default monotonic)
    :param watchdog_frames: missing/bad frames that trip the watchdog (default 3)
    :param frame_period_s: nominal frame period (default 20 ms)
    :param rearm_after_watchdog: require a deadman release after start and after a trip
    """

    def __init__(self, port: Any, clock: Clock | None = None, *,
                 watchdog_frames: int = codec.WATCHDOG_FRAMES,
                 frame_period_s: float = codec.FRAME_PERIOD_S,
                 rearm_after_watchdog: bool = True) -> None:
        self.port = port
        self.clock = clock if clock is not None else MonotonicClock()
        self.watchdog_frames = int(watchdog_frames)
        self.watchdog_s = watchdog_frames * frame_period_s
        self.rearm_after_watchdog = rearm_after_watchdog
        self.decoder = codec.FrameDecoder("master")
        self.watchdog_trips = 0
        self.tx_frames = 0
        self.tx_saturated = 0
        self.port_errors = 0
        self.last_error = ""
        self._tripped = False
        self._need_release = rearm_after_watchdog
        self._tx_seq = 0
        self._last_frame: codec.MasterFrame | None = None
        self._last_good_t = self.clock.now()
        self._rate = RateWindow(1.0)  # good frames per second
        self._state = safe_state("crl", self._last_good_t, "waiting for the first frame", fault=False)

    @classmethod
    def open(cls, url: str, clock: Clock | None = None, **kwargs) -> "CrlHandController":
        """Open ``url`` with ``serial.serial_for_url`` (19200 8N1, non-blocking reads)."""
        import serial

        try:
            port = serial.serial_for_url(url, baudrate=codec.BAUD, timeout=0, write_timeout=0.5)
        except (serial.SerialException, OSError) as err:
            raise LinkError(f"CRL hand controller: cannot open port {url}: {err}") from err
        return cls(port, clock, **kwargs)

    # -- helpers ------------------------------------------------------------------
    @property
    def port_name(self) -> str:
        return str(getattr(self.port, "port", None) or getattr(self.port, "name", None) or self.port)

    @property
    def state(self) -> HandControllerState:
        """The last state returned by :meth:`update`."""
        return self._state

    @property
    def tripped(self) -> bool:
        """True while the watchdog holds the link as lost."""
        return self._tripped

    def _read_available(self) -> bytes:
        n = getattr(self.port, "in_waiting", None)
        if n is None:
            return self.port.read(codec.FRAME_LEN * 8) or b""
        return self.port.read(n) if n else b""

    # -- receive ------------------------------------------------------------------
    def update(self) -> HandControllerState:
        """Take in every byte waiting on the port; return the current state.

        Never raises for link trouble: a port error or a watchdog trip gives a state
        with ``fault=True``, ``valid=False`` and the deadman released.
        """
        now = self.clock.now()
        try:
            data = self._read_available()
        except (OSError, ValueError) as err:  # SerialException is an IOError
            self.port_errors += 1
            self.last_error = f"CRL hand controller on {self.port_name}: read failed: {err}"
            self._trip()
            self._state = safe_state("crl", now, self.last_error)
            return self._state
        for frame in self.decoder.feed(data):
            self._last_frame = frame
            self._last_good_t = now
            self._rate.mark(now)
        return self._evaluate(now)

    def _trip(self) -> None:
        if not self._tripped:
            self.watchdog_trips += 1
        self._tripped = True
        if self.rearm_after_watchdog:
            self._need_release = True

    def _evaluate(self, now: float) -> HandControllerState:
        silent_s = now - self._last_good_t
        bad = self.decoder.bad_since_good
        if bad >= self.watchdog_frames or silent_s > self.watchdog_s + 1e-9:
            if bad >= self.watchdog_frames:
                reason = f"watchdog: {bad} bad frames in a row"
            else:
                reason = f"watchdog: no good frame for {silent_s * 1e3:.0f} ms"
            self._trip()
            self._state = safe_state("crl", now, reason,
                                     buttons=self._last_frame.buttons if self._last_frame else 0)
            return self._state
        frame = self._last_frame
        if frame is None:
            self._state = safe_state("crl", now, "waiting for the first frame", fault=False)
            return self._state
        self._tripped = False
        pressed = frame.deadman
        if not pressed:
            self._need_release = False
        reason = "deadman must be released once (re-arm)" if pressed and self._need_release else ""
        self._state = HandControllerState(
            axes=tuple(codec.counts_to_unit(c) for c in frame.axes_counts),
            deadman=pressed and not self._need_release,
            buttons=frame.buttons, source="crl", t_s=self._last_good_t, valid=True,
            fault=False, reason=reason, raw=tuple(frame.axes_counts))
        return self._state

    def pose(self) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """Last master position in engineering units ((x,y,z) m, (roll,pitch,yaw) rad), or None."""
        if self._last_frame is None or not self._state.valid:
            return None
        return codec.counts_to_pose(self._last_frame.axes_counts)

    # -- transmit -----------------------------------------------------------------
    def send_force(self, force_n: Sequence[float], torque_nm: Sequence[float],
                   enable: bool = True) -> codec.ForceFrame:
        """Send one force-reflection frame; return the frame actually sent.

        Force and torque are saturated to the display limits (40 N, 2 N.m) as vectors,
        keeping their direction. Zero forces with enable off are sent instead while the
        watchdog is tripped (fault bit set) or the deadman is released.

        :raises ValueError: for a non-finite value (a zero, disabled frame is sent first)
        :raises LinkError: when the port write fails
        """
        force_n, torque_nm = tuple(force_n), tuple(torque_nm)
        asked = (force_n, torque_nm)
        if len(force_n) != 3 or len(torque_nm) != 3:
            raise ValueError(f"send_force needs 3 forces and 3 torques, got {len(force_n)}, {len(torque_nm)}")
        finite = all(math.isfinite(v) for v in force_n + torque_nm)
        flags = 0
        if not finite or self._tripped or not self._state.active:
            force_n, torque_nm, enable = (0.0,) * 3, (0.0,) * 3, False
            if self._tripped or not finite:
                flags |= codec.FLAG_FAULT
        f_sat, f_clipped = _saturate(force_n, codec.FORCE_LIMIT_N)
        t_sat, t_clipped = _saturate(torque_nm, codec.TORQUE_LIMIT_NM)
        self.tx_saturated += int(f_clipped or t_clipped)
        if enable:
            flags |= codec.FLAG_FORCE_ENABLE
        counts = codec.wrench_to_counts(f_sat, t_sat)
        data = codec.encode_force_frame(self._tx_seq, counts, flags)
        sent = codec.ForceFrame(self._tx_seq, counts, flags)
        self._tx_seq = (self._tx_seq + 1) & 0xFF
        try:
            self.port.write(data)
        except (OSError, ValueError) as err:
            self.port_errors += 1
            self.last_error = f"CRL hand controller on {self.port_name}: write failed: {err}"
            raise LinkError(self.last_error) from err
        self.tx_frames += 1
        if not finite:
            raise ValueError(f"CRL send_force: non-finite force {asked[0]} / torque {asked[1]}; "
                             "sent zero forces, disabled")
        return sent

    def link_stats(self) -> dict:
        """Receive counters plus watchdog trips, transmitted frames and port errors, the
        good-frame rate over the last second and the age of the last good frame."""
        now = self.clock.now()
        d = self.decoder.stats.as_dict()
        d.update(watchdog_trips=self.watchdog_trips, tx_frames=self.tx_frames,
                 tx_saturated=self.tx_saturated, port_errors=self.port_errors,
                 tripped=self._tripped, rate_hz=self._rate.rate_hz(now), age_s=now - self._last_good_t)
        return d

    def close(self) -> None:
        """Send a last zero, disabled frame (best effort) and close the port."""
        try:
            self._tripped = True
            self.send_force((0.0,) * 3, (0.0,) * 3, enable=False)
        except (LinkError, ValueError):
            pass
        close = getattr(self.port, "close", None)
        if close is not None:
            close()

    def __enter__(self) -> "CrlHandController":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
