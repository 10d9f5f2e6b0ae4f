"""The periodic frame loop: absolute deadlines, dropped frames counted, statistics live.

Deadlines are ``t0 + k * period`` (never "now + period"), so the loop does not
drift. When the loop wakes later than the next deadline (a host stall, a slow
frame), the frames it missed are *dropped* and counted; it never runs them as a
burst to catch up. The tasks that were due in the dropped frames run once, in the
frame the loop wakes in (at most once per task), so a sensor keeps its sample
rate across a single late frame without any burst.

Statistics are kept in preallocated numpy rings; percentiles are computed only
when asked (``LoopStats.summary``), outside the frame's hot path.
"""

from __future__ import annotations

import gc
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from pfma.clock import Clock


class LoopStats:
    """Per-frame timing rings and counters.

    :param window: frames kept for percentiles
    """

    def __init__(self, window: int = 4096) -> None:
        self.window = window
        self.wake_latency_s = np.zeros(window)
        self.period_s = np.zeros(window)
        self.work_s = np.zeros(window)
        np.percentile(self.work_s[:8], [50, 99, 99.9])  # numpy's first call costs ~10 ms: not in a frame
        self.n = 0  #: frames run
        self.dropped = 0  #: frames skipped because the loop woke too late
        self.overruns = 0  #: frames whose work ended after the next deadline
        self.overrun_run = 0  #: current run of consecutive overruns
        self.longest_overrun_run = 0
        self.stalls = 0  #: wake-ups more than 10 periods late
        self.gc_gen2_at_start = gc.get_stats()[2]["collections"]  #: reset when a run starts
        self._last_wake = math.nan

    def record(self, wake_latency_s: float, t_wake: float, work_s: float, overrun: bool) -> None:
        i = self.n % self.window
        self.wake_latency_s[i] = wake_latency_s
        self.period_s[i] = t_wake - self._last_wake if self.n else math.nan
        self.work_s[i] = work_s
        self._last_wake = t_wake
        self.n += 1
        if overrun:
            self.overruns += 1
            self.overrun_run += 1
            if self.overrun_run > self.longest_overrun_run:
                self.longest_overrun_run = self.overrun_run
        else:
            self.overrun_run = 0

    def summary(self) -> dict:
        """p50/p99/p99.9/max of wake latency, period and work (seconds), the counters, and
        ``rate_hz``: the frames actually run in the window over the time they span (the sum
        of their wake-to-wake periods), so a dropped frame, whose time is in the next
        frame's period, lowers it (a median period would not: issue 29 item 8); NaN before
        two frames have run."""
        m = min(self.n, self.window)
        out = {"frames": self.n, "dropped": self.dropped, "overruns": self.overruns,
               "longest_overrun_run": self.longest_overrun_run, "stalls": self.stalls,
               "gc_gen2_in_loop": gc.get_stats()[2]["collections"] - self.gc_gen2_at_start}
        periods = self.period_s[:m]
        periods = periods[~np.isnan(periods)]
        span = float(periods.sum()) if periods.size else 0.0
        out["rate_hz"] = periods.size / span if span > 0 else math.nan
        out["rate_window_s"] = span
        for name, ring in (("wake_latency_s", self.wake_latency_s), ("period_s", self.period_s),
                           ("work_s", self.work_s)):
            data = ring[:m]
            data = data[~np.isnan(data)]
            if data.size:
                p50, p99, p999 = np.percentile(data, [50, 99, 99.9])
                out[name] = {"p50": float(p50), "p99": float(p99), "p999": float(p999),
                             "max": float(data.max())}
            else:
                out[name] = {"p50": math.nan, "p99": math.nan, "p999": math.nan, "max": math.nan}
        return out


@dataclass
class FrameInfo:
    """What the frame body is told about the frame it runs in."""

    index: int = 0  #: frame number k since t0
    deadline: float = 0.0  #: t0 + k * period
    t_wake: float = 0.0  #: when the loop actually woke
    missed: int = 0  #: frames dropped just before this one


class FrameLoop:
    """Runs ``body(info)`` once per minor frame on an absolute-deadline grid.

    :param clock: a MonotonicClock in service, a SimClock in tests
    :param period_s: minor-frame period
    :param body: called with a :class:`FrameInfo` (the same object each frame)
    :param stats: where timing goes (a new LoopStats by default)
    """

    def __init__(self, clock: Clock, period_s: float, body: Callable[[FrameInfo], None],
                 stats: LoopStats | None = None) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be positive")
        self.clock = clock
        self.period_s = period_s
        self.body = body
        self.stats = stats if stats is not None else LoopStats()
        self.stop_requested = False
        self.t0: float | None = None
        self.k = 0
        self._info = FrameInfo()

    def stop(self) -> None:
        """Ask the loop to end after the current frame (safe from a signal handler)."""
        self.stop_requested = True

    def run(self, frames: int | None = None, duration_s: float | None = None,
            freeze_gc: bool = True) -> LoopStats:
        """Run until ``stop()``, ``frames`` frames or ``duration_s`` seconds.

        With ``freeze_gc`` everything allocated so far is moved out of the garbage
        collector's reach (``gc.freeze``) and automatic collection is off while the
        loop runs, so no full collection happens inside a frame.
        """
        clock, period, stats, info = self.clock, self.period_s, self.stats, self._info
        gc_was_enabled = gc.isenabled()
        if freeze_gc:
            gc.collect()
            gc.freeze()
            gc.disable()
        stats.gc_gen2_at_start = gc.get_stats()[2]["collections"]
        if self.t0 is None:
            self.t0 = clock.now()
        end_k = None if frames is None else self.k + frames
        end_t = None if duration_s is None else clock.now() + duration_s
        try:
            while not self.stop_requested:
                if end_k is not None and self.k >= end_k:
                    break
                deadline = self.t0 + self.k * period
                if end_t is not None and deadline >= end_t:
                    break
                clock.sleep_until(deadline)
                t_wake = clock.now()
                late = t_wake - deadline
                missed = 0
                if late >= period:
                    missed = int(late // period)
                    self.k += missed
                    stats.dropped += missed
                    if missed >= 10:
                        stats.stalls += 1
                    deadline = self.t0 + self.k * period
                    late = t_wake - deadline
                info.index, info.deadline, info.t_wake, info.missed = self.k, deadline, t_wake, missed
                self.body(info)
                t_end = clock.now()
                stats.record(late, t_wake, t_end - t_wake, t_end > deadline + period)
                self.k += 1
        finally:
            if freeze_gc:
                gc.unfreeze()
                if gc_was_enabled:
                    gc.enable()
        return stats


#: the environment variable that turns real-time scheduling's default off for every process
#: started beneath it (``PFMA_REALTIME=off``): the test suite (tests/conftest.py) and ``pfma
#: bench`` without ``--realtime`` set it, so a 2-core CI host running everything as root is
#: never filled with SCHED_FIFO processes. An explicit ``--realtime`` still takes it.
REALTIME_ENV = "PFMA_REALTIME"


def realtime_default() -> bool:
    """Whether a process started without ``--realtime``/``--no-realtime`` tries real-time
    scheduling: yes, unless :data:`REALTIME_ENV` says ``off`` (or ``0``, ``no``)."""
    import os
    return os.environ.get(REALTIME_ENV, "").strip().lower() not in ("off", "0", "no", "false")


def realtime_start(prog: str, flag: bool | None, cpu: int | None, fifo_priority: int,
                   watchdog_ms: float | None = None) -> list[str]:
    """The real-time set-up of a live process (``pfma serve``, ``pfma controller``), by
    default where permitted (issue 29 item 2); returns the lines to print (one, plus any
    partial failure).

    :param flag: ``--realtime`` (True: asked for), ``--no-realtime`` (False), neither (None:
        :func:`realtime_default`; without it, nothing is tried and nothing said, since the
        caller's environment said so once).
    :param watchdog_ms: named in the line that says what a time-shared process costs.
    """
    if flag is False:
        return [f"{prog}: real-time off (--no-realtime): time-shared, not pinned"]
    if flag is None and not realtime_default():
        return []
    warnings = realtime_setup(cpu=cpu, fifo_priority=fifo_priority)
    if warnings and warnings[0].startswith("SCHED_FIFO"):
        cost = (f"a host stall longer than the {watchdog_ms:g} ms watchdog puts the outputs to 0 V"
                if watchdog_ms else "its frames wait behind every other process on a busy host")
        return [f"{prog}: real-time not permitted for this user (SCHED_FIFO needs root, CAP_SYS_NICE or an "
                f"RLIMIT_RTPRIO; docs/deployment.md): running time-shared and not pinned; {cost}",
                *(f"{prog}: {w}" for w in warnings[1:])]
    pinned = f", pinned to CPU {cpu}" if cpu is not None and not any(w.startswith("could not pin")
                                                                      for w in warnings) else ""
    return [f"{prog}: real-time: SCHED_FIFO priority {fifo_priority}{pinned} (--no-realtime opts out)",
            *(f"{prog}: {w}" for w in warnings)]


def realtime_setup(cpu: int | None = None, fifo_priority: int | None = 50) -> list[str]:
    """Best-effort real-time set-up for the loop's process; returns warnings (empty = all done).

    SCHED_FIFO at ``fifo_priority`` when permitted, then (only if it was) pinned to ``cpu``
    when given, timer slack 1 ns (prctl PR_SET_TIMERSLACK) so sleeps wake on time.
    """
    import ctypes
    import os
    warnings: list[str] = []
    fifo = False
    if fifo_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
            fifo = True
        except (OSError, AttributeError) as err:
            warnings.append(f"SCHED_FIFO not permitted ({getattr(err, 'strerror', err)}); "
                            f"running SCHED_OTHER, expect more wake-up jitter")
    if cpu is not None and fifo:  # never pinned without SCHED_FIFO: a time-shared process
        try:                      # pinned to one CPU only loses the other when that one is busy
            os.sched_setaffinity(0, {cpu})
        except OSError as err:
            warnings.append(f"could not pin to CPU {cpu}: {err.strerror}")
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_TIMERSLACK = 29
        if libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0) != 0:
            warnings.append("could not set timer slack to 1 ns")
    except OSError:
        warnings.append("prctl unavailable; default timer slack (50 us) applies")
    return warnings
