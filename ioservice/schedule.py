"""The acquisition schedule: what runs in which minor frame.

IRSS report 2.3.5: minor frames of about 3 ms, 16 minor frames per major frame,
tasks phased relative to each other by frame number. Here the minor frame is
3.125 ms (320 Hz) by default and each I/O task has a divider (run every N-th
frame) and a phase (which frame of N). Defaults, from the report and the design
card: DAC outputs every frame (320 Hz), resolvers and ADC every 2nd (160 Hz), F/T
and the serial hand controller every 4th (80 Hz), the parallel ports every 8th
(40 Hz: the user I/F box is a panel of switches; 40 Hz gives a 25 ms response,
well under what an operator notices, and keeps their bus traffic off the
resolver/ADC frames).

The schedule is configuration (``[schedule]`` in a service TOML or keyword
arguments), validated at start.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgspec

from pfma import config
from pfma.errors import ConfigError

MINOR_FRAMES_PER_MAJOR = 16  # IRSS report 2.3.5

#: task name -> what it does (the service implements each)
TASKS = {
    "dac": "write joint rate commands and current limits to the DAC (or safe 0 V)",
    "rtd": "sample both resolver boards",
    "adc": "scan all 32 ADC channels (motor currents, tach rates, CAE stick)",
    "ft": "pick up the latest F/T record from its reader",
    "hand": "pick up the latest serial/HID hand-controller state",
    "pio": "read the user I/F box, write the matrix switcher route when it changes",
    "publish": "publish the input area and statistics to the Bit3 buffer",
}

#: documented rates (Hz) each task must keep at the default 320 Hz minor frame
DOCUMENTED_RATES_HZ = {"dac": 320.0, "rtd": 160.0, "adc": 160.0, "ft": 80.0, "hand": 80.0}


@dataclass(frozen=True)
class TaskSlot:
    divider: int  #: run every ``divider`` minor frames
    phase: int = 0  #: in frame k when k % divider == phase


DEFAULT_SLOTS = {
    "dac": TaskSlot(1, 0),
    "rtd": TaskSlot(2, 0),
    "adc": TaskSlot(2, 0),
    "ft": TaskSlot(4, 1),
    "hand": TaskSlot(4, 3),
    "pio": TaskSlot(8, 5),
    "publish": TaskSlot(1, 0),
}


class _TaskTable(msgspec.Struct, forbid_unknown_fields=True):
    divider: int = 1
    phase: int = 0


class _ScheduleTable(msgspec.Struct, forbid_unknown_fields=True):
    frame_rate_hz: float = 320.0
    tasks: dict[str, Any] = msgspec.field(default_factory=dict)  # each a _TaskTable (named in its errors)


_MESSAGES = {"": "must be a table (frame_rate_hz, tasks)", "*": "unknown key(s) {key}",
             "frame_rate_hz": "frame_rate_hz must be a number (Hz), not {value!r}",
             "tasks": "tasks must be a table of task = {{divider = N, phase = K}}"}
_TASK_MESSAGES = {"": "must be a table {{divider = N, phase = K}}", "*": "unknown key(s) {key}",
                  "divider": "divider must be an integer, not {value!r}", "phase": "phase must be an integer, not {value!r}"}


def _error(p: config.Problem) -> ConfigError:
    return ConfigError(f"schedule: {p.message}")


@dataclass(frozen=True)
class Schedule:
    """A validated acquisition schedule.

    :param frame_rate_hz: minor-frame rate (320 by default; 1000 for the fast profile)
    :param slots: task name -> TaskSlot
    """

    frame_rate_hz: float = 320.0
    slots: dict[str, TaskSlot] = field(default_factory=lambda: dict(DEFAULT_SLOTS))

    def __post_init__(self) -> None:
        if not 1.0 <= self.frame_rate_hz <= 5000.0:
            raise ConfigError(f"schedule: frame_rate_hz {self.frame_rate_hz} outside 1..5000 Hz")
        for name, slot in self.slots.items():
            if name not in TASKS:
                raise ConfigError(f"schedule: unknown task {name!r}; known: {', '.join(TASKS)}")
            if slot.divider < 1 or MINOR_FRAMES_PER_MAJOR % slot.divider:
                raise ConfigError(f"schedule: task {name} divider {slot.divider} must divide "
                                  f"the {MINOR_FRAMES_PER_MAJOR}-frame major frame")
            if not 0 <= slot.phase < slot.divider:
                raise ConfigError(f"schedule: task {name} phase {slot.phase} not in 0..{slot.divider - 1}")
        for name in ("dac", "publish"):
            if name not in self.slots:
                raise ConfigError(f"schedule: task {name!r} is required (outputs and publishing)")
            if self.slots[name].divider != 1:
                raise ConfigError(f"schedule: task {name!r} must run every frame (the watchdog "
                                  f"and the buffer depend on it)")

    @property
    def period_s(self) -> float:
        return 1.0 / self.frame_rate_hz

    def rate_hz(self, task: str) -> float:
        return self.frame_rate_hz / self.slots[task].divider

    def frame_table(self) -> tuple[tuple[str, ...], ...]:
        """One tuple of task names per minor frame of the major frame, in run order."""
        order = list(TASKS)  # the service runs them in this order: DAC first, inputs, publish
        return tuple(tuple(t for t in order if t in self.slots
                           and k % self.slots[t].divider == self.slots[t].phase)
                     for k in range(MINOR_FRAMES_PER_MAJOR))

    def check_documented_rates(self) -> list[str]:
        """Differences from the report's rates (empty when the schedule keeps them)."""
        return [f"{t}: {self.rate_hz(t):g} Hz (documented {hz:g} Hz)"
                for t, hz in DOCUMENTED_RATES_HZ.items()
                if t in self.slots and abs(self.rate_hz(t) - hz) > 1e-9]

    @classmethod
    def from_config(cls, cfg: dict | None) -> "Schedule":
        """Build from a ``[schedule]`` table: ``frame_rate_hz = 320`` and
        ``[schedule.tasks] rtd = {divider = 2, phase = 0}`` (:class:`_ScheduleTable`)."""
        raw = config.convert(cfg or {}, _ScheduleTable, source="schedule", prefix=("schedule",),
                             messages=_MESSAGES, error=_error)
        slots = dict(DEFAULT_SLOTS)
        for name, t in raw.tasks.items():
            task = config.convert(t, _TaskTable, source="schedule", prefix=("schedule", "tasks", name),
                                  messages={k: f"task {name}: {v}" for k, v in _TASK_MESSAGES.items()}, error=_error)
            slots[name] = TaskSlot(task.divider, task.phase)
        return cls(frame_rate_hz=float(raw.frame_rate_hz), slots=slots)

    @classmethod
    def scaled(cls, frame_rate_hz: float) -> "Schedule":
        """A schedule at another minor-frame rate that keeps the documented task rates
        where the divider allows (e.g. 1 kHz is not a multiple of 160 Hz: the dividers
        are chosen to give the nearest rate at or above the documented one)."""
        slots = {}
        for name, slot in DEFAULT_SLOTS.items():
            want = DOCUMENTED_RATES_HZ.get(name)
            if want is None or name in ("dac", "publish"):
                slots[name] = TaskSlot(slot.divider, slot.phase) if name not in ("dac", "publish") else slot
                continue
            divs = [d for d in (1, 2, 4, 8, 16) if frame_rate_hz / d >= want]
            d = max(divs) if divs else 1
            slots[name] = TaskSlot(d, slot.phase % d)
        return cls(frame_rate_hz=frame_rate_hz, slots=slots)


# -------------------------------------------------------------------- what the bus can keep
#: share of a minor frame that the frame's bus work may take: the rest is the frame's own
#: computing and publishing (about 0.1-0.3 ms at 320 Hz) and the wake-up latency (p99 up to
#: ~0.85 ms on a shared VM). Assumed: 0.75
BUS_SHARE = 0.75
#: the tasks that touch the register bus (F/T and hand controller decode what the serial
#: drain has already read; ``publish`` writes shared memory only)
BUS_TASKS = ("dac", "rtd", "adc", "pio")


class BusTooSlow(ConfigError):
    """The register bus cannot do a frame's work within the frame (the message has the figures)."""


def frame_costs(schedule: Schedule, task_cost_s: dict[str, float], every_frame_s: float = 0.0) -> list[float]:
    """Bus time (s) of each minor frame of the major frame: the costs of the tasks it runs,
    plus ``every_frame_s`` (the serial drains at its start and end)."""
    return [every_frame_s + sum(task_cost_s.get(t, 0.0) for t in frame) for frame in schedule.frame_table()]


def busiest_frame(schedule: Schedule, task_cost_s: dict[str, float],
                  every_frame_s: float = 0.0) -> tuple[float, tuple[str, ...]]:
    """(bus time, task names) of the frame with the most bus work."""
    costs = frame_costs(schedule, task_cost_s, every_frame_s)
    k = max(range(len(costs)), key=costs.__getitem__)
    return costs[k], tuple(t for t in schedule.frame_table()[k] if task_cost_s.get(t))


def fits(schedule: Schedule, task_cost_s: dict[str, float], every_frame_s: float = 0.0) -> bool:
    """True when every frame's bus work takes at most BUS_SHARE of the period."""
    return busiest_frame(schedule, task_cost_s, every_frame_s)[0] <= BUS_SHARE * schedule.period_s


def input_rate_hz(schedule: Schedule) -> float:
    """The slower of the resolver and ADC rates (what a slower schedule gives up first)."""
    return min(schedule.rate_hz(t) for t in ("rtd", "adc") if t in schedule.slots)


def describe_rates(schedule: Schedule) -> str:
    """``resolvers 160 Hz, ADC 160 Hz, DAC 320 Hz in 320 Hz frames``."""
    names = {"rtd": "resolvers", "adc": "ADC", "dac": "DAC"}
    return (", ".join(f"{names[t]} {schedule.rate_hz(t):g} Hz" for t in names if t in schedule.slots)
            + f" in {schedule.frame_rate_hz:g} Hz frames")


def slower_schedules(base: Schedule, max_period_s: float) -> list[Schedule]:
    """The schedules a slow bus may fall back to, best first: the frame rate halved (down to
    a period of ``max_period_s``, the command watchdog), the resolver and ADC dividers
    multiplied, and the ADC moved to the frame after the resolvers (so one frame does not
    carry both). Best = the highest resolver/ADC rate, then the highest DAC rate, then the
    fewest changes."""
    out: dict[tuple, tuple[tuple, Schedule]] = {}
    rate = base.frame_rate_hz
    level = 0
    while 1.0 / rate <= max_period_s + 1e-12 and rate >= 1.0:
        frame_base = base if level == 0 else Schedule.scaled(rate)
        for mult in (1, 2, 4, 8):
            for split in (False, True):
                if "rtd" not in frame_base.slots or "adc" not in frame_base.slots:
                    continue
                d = frame_base.slots["rtd"].divider * mult
                if d > MINOR_FRAMES_PER_MAJOR or MINOR_FRAMES_PER_MAJOR % d or (split and d == 1):
                    continue
                p = frame_base.slots["rtd"].phase % d
                slots = dict(frame_base.slots)
                slots["rtd"] = TaskSlot(d, p)
                slots["adc"] = TaskSlot(d, (p + 1) % d if split else p)
                s = Schedule(frame_rate_hz=rate, slots=slots)
                key = (s.frame_rate_hz, tuple(sorted((n, x.divider, x.phase) for n, x in slots.items())))
                rank = (input_rate_hz(s), s.rate_hz("dac"), -level, -mult, not split)
                if key not in out:
                    out[key] = (rank, s)
        rate /= 2
        level += 1
    return [s for _rank, s in sorted(out.values(), key=lambda rs: rs[0], reverse=True)]
