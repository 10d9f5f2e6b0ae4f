"""The joint supervision's confusion matrix (issue 28 item 3): every motion fault on every
joint of a flying arm in the system simulator, ``trials`` seeded trials each
(:mod:`sim.motion_faults`), and what the supervision named.

Prints one row per injected fault: how many trials named each cause, how many were stopped
within docs/safety.md's bound, and how many named the right joint and cause; then the
slowest detection and the largest excursion per fault. docs/safety.md quotes it
(``pfma bench supervision --trials 5``).
"""

from __future__ import annotations

import time

from sim.motion_faults import BOUND_DEG, FAULTS, confusion, matrix

#: seeded trials per fault and joint when none is given
DEFAULT_TRIALS = 3


def run(seconds: float | None = None, trials: int | None = None) -> list:
    """Run the matrix and print it; returns the trial results. ``seconds`` is ignored (the
    matrix runs a fixed number of simulated trials)."""
    n = DEFAULT_TRIALS if trials is None else trials
    t0 = time.perf_counter()
    results = matrix(seeds=n)
    print(f"{len(FAULTS)} faults x 6 joints x {n} seeded trials ({len(results)} in all, "
          f"{time.perf_counter() - t0:.0f} s of wall time, simulated time each)")
    for line in confusion(results):
        print(line)
    print(f"{'fault':<14}{'slowest detection':>20}{'largest excursion':>20}  (bound {BOUND_DEG:g} deg)")
    for f in FAULTS:
        rows = [r for r in results if r.fault == f]
        print(f"{f:<14}{max(r.detect_ms for r in rows):>17.0f} ms{max(r.excursion_deg for r in rows):>16.1f} deg")
    wrong = [r for r in results if not (r.right and r.ok)]
    for r in wrong:
        print(f"  {r.spec} (seed {r.seed}): named {r.trip_joint or 'nothing'}, {r.message or 'no trip'}")
    return results
