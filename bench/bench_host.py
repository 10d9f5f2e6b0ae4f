"""What this host charges a periodic Python loop, apart from the service's code.

Two figures bound the service's own CPU and frame work (issue 16) from below, and both
belong to the machine, not to the code:

1. **A wake-up's CPU**: a bare loop sleeping to ``now + LIVE_TICK_S`` (the tick the live
   service sleeps on between frames, set by the MVME400's 3-character FIFO) with nothing
   else to do; its process CPU divided by its wake-ups. The live service wakes
   ``service.ticks_per_s`` times a second (``pfma bench service``), so that many times
   this figure is CPU it spends however lean its frames are.
2. **The cold factor**: the service's own work per task on the simulated rack
   (``bench_service.task_costs``, all tasks but the A/D scan), each run following 0.5 ms
   asleep (as in the loop) against the same run following 0.5 ms of busy-wait (the same gap, the CPU kept).
   The code, the data and the arm's step between runs are the same; only the sleep
   differs. A factor above 1 is what a sleep costs the next piece of work on this host
   (caches and branch predictors lost while the CPU was given up, e.g. on a VM's exit and
   re-entry); a periodic loop pays it every frame. On a host without it, the factor is
   about 1.
"""

from __future__ import annotations

import time

import numpy as np

from ioservice.service import LIVE_TICK_S
from pfma.clock import MonotonicClock

#: the tasks the cold factor sums: all but the A/D scan, whose own share (a few us beside
#: ~100 polled CSR reads when run alone) is within the bus meter's error
COLD_TASKS = ("dac (16 ch) + commands", "rtd (2 boards)", "ft decode", "hand controllers", "pio",
              "serial drain", "publish")
#: alternated rounds each way (asleep, busy-waiting): a drift of the host hits both alike
ROUNDS = 3


def wake_figures(seconds: float, tick_s: float = LIVE_TICK_S) -> dict:
    """A bare loop of sleeps of ``tick_s``: wake-ups a second and CPU per wake-up."""
    clock = MonotonicClock()
    n = 0
    t0, c0 = time.monotonic(), time.process_time()
    t_end = t0 + seconds
    while time.monotonic() < t_end:
        clock.sleep_until(clock.now() + tick_s)
        n += 1
    wall, cpu = time.monotonic() - t0, time.process_time() - c0
    return {"tick_us": tick_s * 1e6, "wakes_per_s": n / wall, "cpu_per_wake_us": 1e6 * cpu / max(1, n),
            "cpu_percent": 100 * cpu / wall}


def cold_figures(frames: int) -> dict:
    """The service's own work per task after a sleep and after a busy-wait (us: the median
    over :data:`ROUNDS` alternated rounds of ``frames`` runs each), the sums over
    :data:`COLD_TASKS` per round, and the cold factor of the median sums.

    Each round runs every task ``frames`` times in a row with the same gap, so a busy-wait
    run follows the same task's previous run with no sleep in between (runs alternated one
    by one would put a sleep within a millisecond of every run, and measure that)."""
    from bench.bench_service import task_costs
    rounds: dict[str, list[dict[str, float]]] = {"sleep": [], "spin": []}
    for _ in range(ROUNDS):
        for gap in rounds:
            rounds[gap].append({task: c[2] for task, c in task_costs(frames, gap=gap).items()})
    out: dict = {}
    for gap, rs in rounds.items():
        out[f"own_after_{gap}_us"] = {task: float(np.median([r[task] for r in rs])) for task in rs[0]}
        out[f"tasks_after_{gap}_us"] = [sum(r[t] for t in COLD_TASKS) for r in rs]
    asleep, awake = (float(np.median(out[f"tasks_after_{g}_us"])) for g in ("sleep", "spin"))
    out["cold_factor"] = asleep / awake if awake > 0 else float("nan")
    return out


def figures(seconds: float = 5.0) -> dict:
    """Both figures: ``seconds`` of the bare loop, and 20 runs of each task per round per
    second of ``seconds`` (at least 10)."""
    out = wake_figures(seconds)
    out.update(cold_figures(max(10, int(20 * seconds))))
    return out


def run(seconds: float = 5.0) -> dict:
    f = figures(seconds)
    print(f"a bare loop sleeping {f['tick_us']:.0f} us at a time: {f['wakes_per_s']:.0f} wake-ups/s, "
          f"{f['cpu_per_wake_us']:.1f} us of CPU each ({f['cpu_percent']:.1f} % of a core)")
    print("the service's own work per task on the simulated rack, us, after 0.5 ms asleep / after "
          "0.5 ms of busy-wait:")
    for task, asleep in f["own_after_sleep_us"].items():
        note = "" if task in COLD_TASKS else "  (not summed: within the bus meter's error)"
        print(f"  {task:24} {asleep:6.1f} / {f['own_after_spin_us'][task]:6.1f}{note}")
    rounds = " / ".join(", ".join(f"{x:.0f}" for x in f[f"tasks_after_{g}_us"]) for g in ("sleep", "spin"))
    print(f"all but the A/D scan, per round: {rounds} us after a sleep / without: "
          f"cold factor {f['cold_factor']:.2f} (of the medians)")
    return f
