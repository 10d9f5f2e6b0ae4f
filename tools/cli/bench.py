"""``pfma bench``: run the benchmarks in ``bench/`` and print their figures.

Benchmarks print measurements; they never assert. Each ``bench/bench_<name>.py``
module has ``run(seconds=...)``. ``stack`` (the whole stack for ``--minutes``, default 10)
runs only when named, and is the one that prints ``--json``.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

import bench


def _names() -> list[str]:
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules(bench.__path__)
                  if m.name.startswith("bench_"))


#: benchmarks that run only when named (long)
ON_REQUEST = ("stack",)


def add_parser(sub):
    p = sub.add_parser("bench", help="run benchmarks (loop latency, buffer, service) and print figures")
    p.add_argument("names", nargs="*", help=f"which benchmarks (default: all): {', '.join(_names())}")
    p.add_argument("--seconds", type=float, default=None, help="seconds per measured run (default 5)")
    p.add_argument("--minutes", type=float, default=10.0,
                   help="stack: minutes the whole stack runs (default 10; 0.05 for a quick check)")
    p.add_argument("--json", action="store_true", help="stack: print the report as JSON")
    p.add_argument("--realtime", action="store_true",
                   help="stack: run the service and the controller with --realtime (SCHED_FIFO, pinned CPUs)")
    return p


def run(args) -> int:
    names = args.names or [n for n in _names() if n not in ON_REQUEST]
    unknown = set(names) - set(_names())
    if unknown:
        print(f"unknown benchmark(s): {', '.join(sorted(unknown))}; known: {', '.join(_names())}")
        return 2
    if args.json and names != ["stack"]:
        print("--json is for `pfma bench stack` alone", file=sys.stderr)
        return 2
    seconds = 5.0 if args.seconds is None else args.seconds
    for name in names:
        mod = importlib.import_module(f"bench.bench_{name}")
        if name == "stack":
            if not args.json:
                print(f"== bench {name} ==")
            rep = mod.run(seconds=args.seconds, minutes=args.minutes, as_json=args.json, realtime=args.realtime)
            if rep.get("errors") and args.json:
                return 1
            continue
        print(f"== bench {name} ==")
        mod.run(seconds=seconds)
        print()
    return 0
