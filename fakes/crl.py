"""Fake CRL force-reflecting hand controller (the "master"): a byte-stream model.

No threads, no ptys: the owner moves bytes and time. ``advance(dt_s)`` moves the
master's clock and queues one position frame every 20 ms; ``transmit(max_bytes)``
returns what is ready for the line (the owner paces it at the baud rate);
``receive(data)`` takes the host's force-reflection frames. The same object runs
behind ``fakes.pty.PtyDevice`` (a real pty) or on the fake MVME400 serial channel.

Framing comes from the shared protocol table ``drivers.crl.crl_codec`` (a
PLACEHOLDER, pfma-model.md 8.6 / R8); fakes may import protocol tables as they
import ``registers.py`` tables, never a driver.

Master-side safety modelled (8.6): when no good force frame has arrived for 3
frame periods (60 ms), the displayed forces go to zero until the next good frame.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from fakes.byteline import FaultyLine
from drivers.crl import crl_codec as codec

AxesFn = Callable[[float], Sequence[float]]  # t_s -> 6 normalised axes


@dataclass(frozen=True)
class SentMasterFrame:
    """Ground truth: one position frame the master put on the wire."""

    frame: codec.MasterFrame
    t_s: float
    corrupted: bool = False  #: sent with a wrong checksum on purpose


@dataclass(frozen=True)
class ReceivedForce:
    """One good force-reflection frame the master received."""

    frame: codec.ForceFrame
    t_s: float

    @property
    def force_n(self) -> tuple[float, ...]:
        return self.frame.wrench()[0]

    @property
    def torque_nm(self) -> tuple[float, ...]:
        return self.frame.wrench()[1]


#: frames of ground truth a fake CRL master keeps, each way (newest first out): 40 s at 50 Hz
HISTORY_KEEP = 2_000

class FakeCrlMaster(FaultyLine):
    """Byte-stream model of the CRL force-reflecting hand controller.

    :param axes_fn: optional ``t_s -> 6 axes (-1..1)``, sampled for every frame (a moving stick)
    :param frame_period_s: position frame period (default 20 ms, 8.6)
    """

    def __init__(self, axes_fn: AxesFn | None = None,
                 frame_period_s: float = codec.FRAME_PERIOD_S) -> None:
        self.axes_fn = axes_fn
        self.frame_period_s = frame_period_s
        self.t_s = 0.0
        self._init_line()
        self._next_frame_s = 0.0
        self.seq = 0
        self.axes_counts: tuple[int, ...] = (0,) * 6
        self.buttons = 0
        self._rx = codec.FrameDecoder("force")
        self.sent_frames: deque[SentMasterFrame] = deque(maxlen=HISTORY_KEEP)  #: ground truth (newest)
        self.frames_sent = 0
        self.frames_skipped = 0  #: frames not queued because the line was still busy
        #: good force frames, in order (the newest HISTORY_KEEP: 40 Hz for hours must not grow)
        self.received: deque[ReceivedForce] = deque(maxlen=HISTORY_KEEP)
        self.displayed_force_n: tuple[float, ...] = (0.0,) * 3  #: what the motors display now
        self.displayed_torque_nm: tuple[float, ...] = (0.0,) * 3
        self._t_last_force = None
        self.watchdog_trips = 0  #: times the master zeroed its forces for lack of frames
        self._corrupt_left = 0

    # -- physical side --------------------------------------------------------------------
    def set_axes(self, axes: Sequence[float]) -> None:
        """Stick position as six normalised axes (x, y, z, roll, pitch, yaw; 1 = full scale)."""
        if len(axes) != 6:
            raise ValueError(f"FakeCrlMaster.set_axes needs 6 values, got {len(axes)}")
        self.axes_counts = tuple(codec.unit_to_counts(a) for a in axes)

    def set_pose(self, xyz_m: Sequence[float], rpy_rad: Sequence[float]) -> None:
        """Stick position in engineering units (+-0.20 m, +-60 deg full scale)."""
        self.set_axes([v / codec.POS_FULL_SCALE_M for v in xyz_m]
                      + [v / codec.ROT_FULL_SCALE_RAD for v in rpy_rad])

    def set_buttons(self, deadman: bool = False, index: bool = False, trigger: bool = False) -> None:
        self.buttons = ((codec.BTN_DEADMAN if deadman else 0) | (codec.BTN_INDEX if index else 0)
                        | (codec.BTN_TRIGGER if trigger else 0))

    @property
    def deadman(self) -> bool:
        return bool(self.buttons & codec.BTN_DEADMAN)

    @deadman.setter
    def deadman(self, pressed: bool) -> None:
        self.buttons = (self.buttons | codec.BTN_DEADMAN) if pressed else (self.buttons & ~codec.BTN_DEADMAN)

    @property
    def last_force(self) -> ReceivedForce | None:
        return self.received[-1] if self.received else None

    # -- device interface -------------------------------------------------------------------
    def _quiet_until_s(self) -> float | None:
        """The next position frame (queued by :meth:`advance` when its time comes, within
        the 1e-12 s it allows)."""
        return self._next_frame_s - 1e-9

    def advance(self, dt_s: float) -> None:
        """Move the master's time; queue a position frame every frame period."""
        if dt_s < 0:
            raise ValueError(f"cannot advance backwards (dt_s={dt_s})")
        self.t_s += dt_s
        while self._next_frame_s <= self.t_s + 1e-12:
            self._queue_frame(self._next_frame_s)
            self._next_frame_s += self.frame_period_s
        self._force_watchdog()

    def receive(self, data: bytes) -> None:
        """Bytes from the host: force-reflection frames (noise is skipped by the decoder)."""
        if not self.connected:
            return
        for frame in self._rx.feed(bytes(data)):
            self.received.append(ReceivedForce(frame, self.t_s))
            self._t_last_force = self.t_s
            on = frame.enabled and not frame.flags & codec.FLAG_FAULT
            force_n, torque_nm = frame.wrench()
            self.displayed_force_n = force_n if on else (0.0,) * 3
            self.displayed_torque_nm = torque_nm if on else (0.0,) * 3

    @property
    def rx_stats(self) -> codec.LinkStats:
        """Counters of the force frames received."""
        return self._rx.stats

    # -- faults (noise, drops, stall, disconnect: FaultyLine) ----------------------------
    def corrupt_next(self, n_frames: int) -> None:
        """Send the next ``n_frames`` position frames with a wrong checksum."""
        self._corrupt_left += int(n_frames)

    # -- internals --------------------------------------------------------------------------
    def _queue_frame(self, t_s: float) -> None:
        if self.axes_fn is not None:
            self.set_axes([max(-1.0, min(1.0, float(a))) if math.isfinite(a) else 0.0
                           for a in self.axes_fn(t_s)])
        if t_s < self._stall_until_s or len(self._tx) >= 2 * codec.FRAME_LEN:
            self.frames_skipped += 1
            self.seq = (self.seq + 1) & 0xFF  # the master still counts the frame
            return
        data = bytearray(codec.encode_master_frame(self.seq, self.axes_counts, self.buttons))
        corrupted = self._corrupt_left > 0
        if corrupted:
            self._corrupt_left -= 1
            data[-1] ^= 0x5A
        frame = codec.MasterFrame(self.seq, self.axes_counts, self.buttons)
        self.sent_frames.append(SentMasterFrame(frame, t_s, corrupted))
        self._tx += data
        self.frames_sent += 1
        self.seq = (self.seq + 1) & 0xFF

    def _force_watchdog(self) -> None:
        if self._t_last_force is None:
            return
        if self.t_s - self._t_last_force > codec.WATCHDOG_FRAMES * self.frame_period_s + 1e-9:
            if any(self.displayed_force_n) or any(self.displayed_torque_nm):
                self.watchdog_trips += 1
            self.displayed_force_n = (0.0,) * 3
            self.displayed_torque_nm = (0.0,) * 3


def gentle_axes(t_s: float) -> tuple[float, ...]:
    """A slowly moving stick for demos: each axis a slow sine of a different period."""
    periods = (7.0, 9.0, 11.0, 13.0, 17.0, 19.0)
    return tuple(0.5 * math.sin(2 * math.pi * t_s / p) for p in periods)
