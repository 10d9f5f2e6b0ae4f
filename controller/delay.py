"""Synthetic time delay: timestamped FIFOs on the command (up) and telemetry (down) paths.

Facts (pfma-model.md section 6 and 8.10, ASSUMED there as the "recommended experimental
set"): round-trip delay 0 s by default, selectable {0.5, 1, 2, 4} s, split equally
uplink/downlink; one FIFO per direction; optional uniform jitter of +-10 % per packet
with order preserved (no reordering). Above about 0.5 s round trip force reflection to
the force-reflecting hand controller is disabled (section 6, Sheridan 1993; 8.6) -
that gate lives in :mod:`controller.teleop`.

Everything here runs in the controller's time (``rt.now``: simulated time on the
system simulator), so a delay is exact and deterministic. A packet pushed at time t
with one-way delay d comes out at the first poll at or after ``t + d`` (1 us of
tolerance for float sums of the frame period); with jitter the delay of each packet
is ``d (1 + j u)``, u uniform in -1..1 from a seeded generator, and never earlier than
the packet before it (order preserved).
"""

from __future__ import annotations

import random
from collections import deque
from typing import Any, Generic, TypeVar

from controller.worldmodel.var import Var, VarGroup, var
from pfma.errors import ConfigError

SOURCE = "pfma-model.md 6 and 8.10 (time-delay defaults, assumed)"
#: 8.10: selectable round-trip delays (s); any value 0..MAX_ROUND_TRIP_S is accepted
ROUND_TRIPS_S: tuple[float, ...] = (0.0, 0.5, 1.0, 2.0, 4.0)
#: accepted round-trip range (s): "0 to several seconds" (issue 6); 8 s covers the JPL 2-8 s
MAX_ROUND_TRIP_S = 8.0
#: 8.10: jitter fraction when jitter is on (+-10 %)
DEFAULT_JITTER = 0.10
#: 8.10: the round trip is split equally (fraction going to the uplink)
DEFAULT_UP_FRACTION = 0.5
#: release tolerance (s): float sums of frame periods must not cost a whole frame
EPS_S = 1e-6
#: packets kept per direction before the oldest is dropped (8 s at 320 Hz is 2560)
MAX_PACKETS = 4096

T = TypeVar("T")


class DelayLine(Generic[T]):
    """One direction: a FIFO of (release time, packet).

    :param jitter: fraction (0..0.5) of the delay added per packet, uniform +-
    :param seed: seed of the jitter generator (deterministic runs)
    :param name: "up" or "down", for messages
    """

    def __init__(self, jitter: float = 0.0, seed: int = 1, name: str = "delay") -> None:
        if not 0.0 <= jitter <= 0.5:
            raise ConfigError(f"{name} delay line: jitter {jitter} outside 0..0.5")
        self.name = name
        self.jitter = float(jitter)
        self._rng = random.Random(seed)
        self._fifo: deque[tuple[float, T]] = deque()
        self._last_release = -float("inf")
        self.pushed = 0
        self.released = 0
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._fifo)

    def push(self, t_s: float, packet: T, delay_s: float) -> float:
        """Queue ``packet`` sent at ``t_s`` with one-way delay ``delay_s``; returns its release time."""
        d = max(0.0, float(delay_s))
        if self.jitter and d > 0.0:
            d *= 1.0 + self.jitter * (2.0 * self._rng.random() - 1.0)
        release = max(t_s + d, self._last_release)  # order preserved
        self._last_release = release
        if len(self._fifo) >= MAX_PACKETS:
            self._fifo.popleft()
            self.dropped += 1
        self._fifo.append((release, packet))
        self.pushed += 1
        return release

    def poll(self, t_s: float) -> list[T]:
        """Every packet due at ``t_s``, oldest first."""
        out = []
        while self._fifo and self._fifo[0][0] <= t_s + EPS_S:
            out.append(self._fifo.popleft()[1])
        self.released += len(out)
        return out

    def clear(self) -> None:
        self._fifo.clear()
        self._last_release = -float("inf")


class SyntheticDelay(Generic[T]):
    """Round-trip delay split into an uplink (operator -> robot: hand-controller commands)
    and a downlink (robot -> operator: telemetry), each a :class:`DelayLine` whose output
    is sampled and held (the latest packet out is the current value).

    :param round_trip_s: 0 .. MAX_ROUND_TRIP_S
    :param up_fraction: share of the round trip on the uplink (0.5: split equally, 8.10)
    :param jitter: +- fraction per packet (0, or DEFAULT_JITTER = 0.1 per 8.10)
    """

    def __init__(self, round_trip_s: float = 0.0, up_fraction: float = DEFAULT_UP_FRACTION,
                 jitter: float = 0.0, seed: int = 1) -> None:
        if not 0.0 <= up_fraction <= 1.0:
            raise ConfigError(f"synthetic delay: up_fraction {up_fraction} outside 0..1")
        self.up_fraction = float(up_fraction)
        self.round_trip_s = 0.0
        self.set_round_trip(round_trip_s)
        self.up: DelayLine = DelayLine(jitter, seed, "up")
        self.down: DelayLine = DelayLine(jitter, seed + 1, "down")
        self.up_value: Any = None  #: last packet out of the uplink (None before the first)
        self.down_value: Any = None

    @staticmethod
    def check_round_trip(round_trip_s: float) -> float:
        """:raises ConfigError: a round trip outside 0 .. MAX_ROUND_TRIP_S (or not finite)"""
        rt = float(round_trip_s)
        if not 0.0 <= rt <= MAX_ROUND_TRIP_S:  # NaN fails too
            raise ConfigError(f"synthetic delay: round trip {round_trip_s!r} s outside 0..{MAX_ROUND_TRIP_S:g} s")
        return rt

    def set_round_trip(self, round_trip_s: float) -> None:
        """Change the delay; packets already queued keep their release times."""
        self.round_trip_s = self.check_round_trip(round_trip_s)

    @property
    def up_s(self) -> float:
        return self.round_trip_s * self.up_fraction

    @property
    def down_s(self) -> float:
        return self.round_trip_s * (1.0 - self.up_fraction)

    def send_up(self, t_s: float, packet: Any) -> Any:
        """Operator -> robot: queue ``packet``; return what the robot sees at ``t_s``."""
        self.up.push(t_s, packet, self.up_s)
        for p in self.up.poll(t_s):
            self.up_value = p
        return self.up_value

    def send_down(self, t_s: float, packet: Any) -> Any:
        """Robot -> operator: queue ``packet``; return what the operator sees at ``t_s``."""
        self.down.push(t_s, packet, self.down_s)
        for p in self.down.poll(t_s):
            self.down_value = p
        return self.down_value

    def reset(self) -> None:
        """Empty both directions (the link starts again: nothing in flight)."""
        self.up.clear()
        self.down.clear()
        self.up_value = self.down_value = None


class DelayVars(VarGroup, prefix="delay", writer="user"):
    """The synthetic delay's user controls (read by the Cartesian layer)."""

    round_trip_s: Var[float] = var("command_input", "f8", (), 0.0, "s",
                                   doc="synthetic round-trip delay, split equally up/down (0..8 s)")
    jitter: Var[float] = var("command_input", "f8", (), 0.0, "1", valid=(0.0, 0.5),
                             doc="synthetic delay jitter fraction per packet (0 or 0.1; order preserved)")


DELAY = DelayVars
