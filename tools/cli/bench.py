"""``pfma bench``: run the benchmarks in ``bench/`` and print their figures.

Benchmarks print measurements; they never assert. Each ``bench/bench_<name>.py``
module has ``run(seconds=...)`` (its text report). ``stack`` (the whole stack for
``--minutes``, default 10), ``chaos`` (the kill matrix: ``--trials`` per process kind,
default 3, ``--seed``, ``--kinds``), ``supervision`` (every motion fault on every joint of a
flying arm, ``--trials`` seeds each: the confusion matrix of docs/safety.md), ``faults`` (the
checkout fault matrix of docs/checkout.md: every fault on every target, or ``--trials N``
of them) and ``soak`` (the simulated stack flying a looping path
for ``--minutes``, default 60) run only when named; ``pfma bench chaos --json`` and ``pfma
bench soak --json`` print their whole report.

``--check`` (``soak`` and ``flood`` only, named alone): after the figures, judge them
against issue 20's criteria (``judge(report)`` of ``bench/bench_soak.py`` and
``bench/bench_flood.py``, where the criteria are written once) and exit 1 with one line per
failed criterion, else exit 0 with one line ``soak: passed (...)`` / ``flood: passed
(...)`` (with ``--json`` those lines go to stderr, the JSON alone to stdout). ``make soak``
runs ``pfma bench soak --minutes 10 --check``.

``pfma bench --json`` runs the set :data:`JSON_SET` and prints ONE JSON object, a key per
benchmark, from each module's ``figures()`` (a dict; no printed text is parsed):
``service`` (the service on the simulated rack at 320 Hz, the fakes metered out),
``controller`` (the minor-frame cost in the system simulator), ``stack`` (the whole stack
for ``--minutes``, default 0.5 here; it names its duration), ``modbus`` (the service
over a loopback Modbus gateway; ``{"skipped": why}`` where that cannot run) and ``bridge``
(inputs latency across ``pfma bridge`` on loopback beside shared memory, p50/p99, the share
of publishes delivered, the bridge's CPU: tools/bridge/latency.py) and ``host`` (what this
machine charges a periodic Python loop apart from the code: CPU per wake-up, and the cold
factor of the service's tasks after a sleep: bench/bench_host.py). Names after
``--json`` pick from that set; ``pfma bench stack --json`` alone prints the stack's full
report, as before.
"""

from __future__ import annotations

import importlib
import json
import math
import pkgutil
import os
import sys

import bench
from tools.cli.args import sim_errors_seed


def _names() -> list[str]:
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules(bench.__path__)
                  if m.name.startswith("bench_"))


#: benchmarks that run only when named (long)
ON_REQUEST = ("stack", "chaos", "soak", "supervision", "faults")
#: benchmarks ``--check`` judges (each module's ``judge(report) -> list[str]`` and ``passed_line``)
CHECKED = ("soak", "flood")
#: benchmarks named alone with ``--json``: their own whole report (not the JSON set)
FULL_JSON = ("stack", "chaos", "soak", "faults")
#: ``--minutes`` of the soak when none is given
SOAK_MINUTES = 60.0
#: what ``pfma bench --json`` measures, in this order
JSON_SET = ("service", "controller", "stack", "modbus", "bridge", "host")
#: ``--minutes`` of the stack when none is given: text report / --json set
STACK_MINUTES = 10.0
STACK_MINUTES_JSON = 0.5


def add_parser(sub):
    p = sub.add_parser("bench", help="run benchmarks (loop latency, buffer, service) and print figures")
    p.add_argument("names", nargs="*", help=f"which benchmarks (default: all): {', '.join(_names())}")
    p.add_argument("--seconds", type=float, default=None, help="seconds per measured run (default 5; flood 10)")
    p.add_argument("--minutes", type=float, default=None,
                   help=f"stack: minutes the whole stack runs (default {STACK_MINUTES:g}; with --json "
                        f"{STACK_MINUTES_JSON:g}; 0.05 for a quick check); soak: minutes (default {SOAK_MINUTES:g})")
    p.add_argument("--json", action="store_true",
                   help=f"print one JSON object with the figures of {', '.join(JSON_SET)} "
                        f"(`pfma bench stack --json`: the stack's full report)")
    p.add_argument("--realtime", action="store_true",
                   help="stack, chaos, soak, flood: run the service (and the controller) with --realtime "
                        "(SCHED_FIFO, pinned CPUs)")
    p.add_argument("--clock", choices=("locked", "own"), default="locked",
                   help="stack: the controller's frame clock (pfma controller --clock; default locked)")
    p.add_argument("--profile", default="layers", choices=("layers", "overview"),
                   help="stack: the controller's rate profile (pfma controller --profile; default layers)")
    p.add_argument("--hog", action="store_true",
                   help="stack: one CPU hog (a busy process at nice 0) beside the stack, reported")
    p.add_argument("--check", action="store_true",
                   help="soak, flood (named alone): judge the figures against issue 20's criteria; exit 1 "
                        "with one line per failed criterion")
    p.add_argument("--rounds", type=int, default=None,
                   help="flood: pairs of a quiet and a flooded run, alternated (default 1)")
    p.add_argument("--trials", type=int, default=None,
                   help="chaos: trials per process kind (default 3; 100 for the full matrix); supervision: "
                        "seeded trials per fault and joint (default 3); faults: a seeded sample of this many "
                        "cases (default: the whole checkout fault matrix)")
    p.add_argument("--seed", type=int, default=None,
                   help="chaos: the seed of the kill plan (default 20); faults: the sample's (default 1)")
    p.add_argument("--sim-errors", type=sim_errors_seed, default=0, metavar="SEED",
                   help="faults: run the matrix on a simulated rack with a real rack's imperfections drawn "
                        "from SEED (noise among them; docs/simulated-arm.md; 0, the default: the perfect rack)")
    p.add_argument("--kinds", default=None, metavar="KIND,...",
                   help="chaos: which process kinds (default all: service, controller, recorder, console, "
                        "bridge, gateway, export)")
    return p


def _finite(x):
    """JSON has no inf/nan: such a figure is written as null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _json_set(names: list[str], args) -> int:
    seconds = 5.0 if args.seconds is None else args.seconds
    minutes = STACK_MINUTES_JSON if args.minutes is None else args.minutes
    out: dict = {"seconds": seconds}
    failed = False
    for name in names:
        mod = importlib.import_module(f"bench.bench_{name}")
        try:
            if name == "stack":
                out[name] = mod.figures(minutes=minutes, realtime=args.realtime, hog=args.hog, clock=args.clock,
                                        profile=args.profile)
                failed |= bool(out[name]["errors"])
            else:
                out[name] = mod.figures(seconds=seconds)
                failed |= "error" in out[name]
        except Exception as err:  # noqa: BLE001 - the object says which benchmark failed, never a traceback
            out[name] = {"error": f"{type(err).__name__}: {err}"}
            failed = True
    print(json.dumps(_finite(out), indent=1))
    return 1 if failed else 0


#: the numeric options' rules, in the order they are checked: (option, refused when, why)
_NUMBER_RULES = (
    ("seconds", lambda v: v <= 0, lambda v: f"--seconds {v:g}: must be positive"),
    ("minutes", lambda v: v < 0, lambda v: f"--minutes {v:g}: must not be negative"),
    ("trials", lambda v: v <= 0, lambda v: f"--trials {v}: must be positive"),
    ("rounds", lambda v: v <= 0, lambda v: f"--rounds {v}: must be positive"),
)


def _refusal(args) -> tuple[str | None, tuple[str, ...] | None]:
    """Why these options are refused (one line, without the ``pfma bench: `` prefix), or
    None; and the ``--kinds`` asked for (None: all)."""
    why = _bad_number(args) or _bad_check(args)
    if why:
        return why, None
    if not getattr(args, "kinds", None):
        return None, None
    return _kinds(args.kinds)


def _bad_number(args) -> str | None:
    """The first numeric option out of its range (:data:`_NUMBER_RULES`), said; None: all good."""
    for option, refused, why in _NUMBER_RULES:
        v = getattr(args, option, None)
        if v is not None and refused(v):
            return why(v)
    return None


def _bad_check(args) -> str | None:
    """``--check`` with other than one of :data:`CHECKED` named alone, said; else None."""
    if getattr(args, "check", False) and not (len(args.names) == 1 and args.names[0] in CHECKED):
        return (f"--check judges one of {', '.join(CHECKED)}, named alone (got: "
                f"{' '.join(args.names) or 'all benchmarks'})")
    return None


def _kinds(text: str) -> tuple[str | None, tuple[str, ...] | None]:
    """``--kinds`` (comma-separated) as the kill matrix's kinds: (refusal, None) when one is
    unknown or none is named, else (None, the kinds)."""
    from bench.bench_chaos import KINDS
    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        return f"--kinds {text}: unknown {', '.join(bad) or 'nothing'}; known: {', '.join(KINDS)}", None
    return None, kinds


def run(args) -> int:
    why, kinds = _refusal(args)
    if why:
        print(f"pfma bench: {why}", file=sys.stderr)
        return 2
    if not args.realtime:  # every process a bench starts stays time-shared and unpinned (a
        # 2-core host is not filled with SCHED_FIFO processes): ioservice.loop.REALTIME_ENV
        from ioservice.loop import REALTIME_ENV
        os.environ[REALTIME_ENV] = "off"
    known = _names()
    unknown = set(args.names) - set(known)
    if unknown:
        print(f"pfma bench: unknown benchmark(s): {', '.join(sorted(unknown))}; known: {', '.join(known)}",
              file=sys.stderr)
        return 2
    if args.json and not (len(args.names) == 1 and args.names[0] in FULL_JSON):
        names = args.names or list(JSON_SET)
        other = [n for n in names if n not in JSON_SET]
        if other:
            print(f"pfma bench: --json measures {', '.join(JSON_SET)}; not {', '.join(other)}", file=sys.stderr)
            return 2
        return _json_set(names, args)
    for name in args.names or [n for n in known if n not in ON_REQUEST]:
        rc = _run_one(name, args, kinds)
        if rc is not None:
            return rc
    return 0


def _run_one(name: str, args, kinds: tuple[str, ...] | None) -> int | None:
    """Run benchmark ``name`` and print it; an exit code when the run ends here (``--check``,
    a stack's errors with ``--json``), else None."""
    mod = importlib.import_module(f"bench.bench_{name}")
    if name in FULL_JSON:
        return _run_long(name, mod, args, kinds)
    print(f"== bench {name} ==")
    if name == "supervision":
        mod.run(trials=args.trials)
    elif name == "flood":
        rep = mod.run(seconds=args.seconds if args.seconds is not None else mod.DEFAULT_SECONDS,
                      rounds=args.rounds or 1, realtime=args.realtime)
        if args.check:
            return _verdict(mod, rep, False)
    else:
        mod.run(seconds=5.0 if args.seconds is None else args.seconds)
    print()
    return None


def _run_long(name: str, mod, args, kinds: tuple[str, ...] | None) -> int | None:
    """``stack``, ``chaos``, ``soak``: their own whole report with ``--json``."""
    if not args.json:
        print(f"== bench {name} ==")
    if name == "stack":
        rep = mod.run(seconds=args.seconds, minutes=STACK_MINUTES if args.minutes is None else args.minutes,
                      as_json=args.json, realtime=args.realtime, hog=args.hog, clock=args.clock,
                      profile=args.profile)
        return 1 if rep.get("errors") and args.json else None
    if name == "chaos":
        mod.run(trials=args.trials, seed=args.seed, as_json=args.json, realtime=args.realtime,
                **({"kinds": kinds} if kinds else {}))
    elif name == "faults":
        mod.run(trials=args.trials, seed=args.seed, as_json=args.json, sim_errors=args.sim_errors)
    else:
        rep = mod.run(minutes=SOAK_MINUTES if args.minutes is None else args.minutes, as_json=args.json,
                      realtime=args.realtime)
        if args.check:
            return _verdict(mod, rep, args.json)
    if not args.json:
        print()
    return None


def _verdict(mod, rep: dict, as_json: bool) -> int:
    """``--check``: the benchmark's own judgement of its report, one line per failed
    criterion (exit 1) or its one passed line (exit 0)."""
    failed = mod.judge(rep)
    out = sys.stderr if as_json else sys.stdout
    for line in failed or [mod.passed_line(rep)]:
        print(line, file=out)
    return 1 if failed else 0
