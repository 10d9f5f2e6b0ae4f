"""The checkout fault matrix (issue 32 item 3; tools/checkout/faultmatrix.py): every fault of
``pfma fault list`` on every target it takes, ``pfma checkout`` on the simulated rack with it
injected, its first failure judged: detected, the right part named, the right kind named.

``pfma bench faults`` runs the whole matrix (~1,500 cases, about 2 s each: most of an hour
on a 2-core host); ``--trials N`` a seeded sample of N (at least one case of every kind),
``--seed`` its seed (default 1); ``--sim-errors SEED`` runs it on a rack with a real rack's
imperfections (noise among them; default 0, the perfect rack); ``--json`` prints the
figures and every miss. Prints
figures, never asserts (the sample in make test is tests/tools/checkout/test_fault_matrix.py).
"""

from __future__ import annotations

import json

from tools.checkout.faultmatrix import cases, run_matrix, sample

DEFAULT_SEED = 1


def run(seconds: float | None = None, trials: int | None = None, seed: int | None = None,
        as_json: bool = False, sim_errors: int = 0) -> dict:
    """The matrix (or a sample of ``trials`` cases); its figures, printed."""
    every = cases()
    which = every if trials is None else sample(every, trials, DEFAULT_SEED if seed is None else seed)

    def progress(i: int, n: int, v) -> None:
        if not as_json:
            mark = ("named right" if v.part_right and v.kind_right else "detected") if v.detected else \
                ("undetectable" if v.undetectable else "MISSED")
            print(f"  {i}/{n} {v.case.spec}: {mark}" + (f" ({v.first[:100]})" if v.detected else ""), flush=True)
    rep = run_matrix(which, progress=progress, sim_errors=sim_errors).as_dict()
    rep.update(matrix_cases=len(every), seed=None if trials is None else (DEFAULT_SEED if seed is None else seed),
               sim_errors=sim_errors)
    if as_json:
        print(json.dumps(rep, indent=1))
        return rep
    print(f"checkout fault matrix ({f'rack errors of seed {sim_errors}' if sim_errors else 'perfect rack'}): "
          f"{rep['cases']} of {len(every)} cases: detected {rep['detected']} "
          f"({rep['detected_fraction']:.1%}), named right {rep['named_right']} "
          f"({(rep['named_right_fraction_of_detected'] or 0):.1%} of those detected); "
          f"{rep['detectable']} detectable (the rest: a stuck bit that never changed a word, or on a spare "
          f"channel), detected {rep['detectable_detected']} ({(rep['detected_fraction_of_detectable'] or 0):.1%})")
    print(f"  {'kind':<18}{'cases':>6}{'detected':>10}{'part right':>12}{'kind right':>12}")
    for kind, k in rep["per_kind"].items():
        print(f"  {kind:<18}{k['cases']:>6}{k['detected']:>10}{k['part_right']:>12}{k['kind_right']:>12}")
    print("  confusion (injected -> the kind the first failure names):")
    for kind, row in rep["confusion"].items():
        print(f"    {kind}: " + ", ".join(f"{n} {col}" for col, n in sorted(row.items(), key=lambda kv: -kv[1])))
    return rep


def figures(trials: int = 40, seed: int = DEFAULT_SEED) -> dict:
    """The sample's figures (no per-case lines)."""
    rep = run_matrix(sample(cases(), trials, seed)).as_dict()
    rep.pop("misses")
    return rep
