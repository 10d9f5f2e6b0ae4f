"""``pfma bench``: run the benchmarks in ``bench/`` and print their figures.

Benchmarks print measurements; they never assert. Each ``bench/bench_<name>.py``
module has ``run(seconds=...)``.
"""

from __future__ import annotations

import importlib
import pkgutil

import bench


def _names() -> list[str]:
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules(bench.__path__)
                  if m.name.startswith("bench_"))


def add_parser(sub):
    p = sub.add_parser("bench", help="run benchmarks (loop latency, buffer, service) and print figures")
    p.add_argument("names", nargs="*", help=f"which benchmarks (default: all): {', '.join(_names())}")
    p.add_argument("--seconds", type=float, default=5.0, help="seconds per measured run (default 5)")
    return p


def run(args) -> int:
    names = args.names or _names()
    unknown = set(names) - set(_names())
    if unknown:
        print(f"unknown benchmark(s): {', '.join(sorted(unknown))}; known: {', '.join(_names())}")
        return 2
    for name in names:
        print(f"== bench {name} ==")
        importlib.import_module(f"bench.bench_{name}").run(seconds=args.seconds)
        print()
    return 0
