"""Characterisation of ``tools.cli.bench._refusal`` (issue 31): the exact refusal line and
``--kinds`` it gave, before its split into a table of option checks, for each option
alone, the first mistake winning, and the options a verb does not have (no attribute)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from tools.cli.bench import _refusal

CASES = {
    "check_all": {"check": True, "names": []},
    "check_chaos": {"check": True, "names": ["chaos"]},
    "check_flood": {"check": True, "names": ["flood"]},
    "check_off": {"check": False, "names": ["chaos"]},
    "check_soak": {"check": True, "names": ["soak"]},
    "check_two": {"check": True, "names": ["soak", "flood"]},
    "first_wins": {"kinds": "teapot", "minutes": -1.0, "seconds": 0.0, "trials": 0},
    "kinds_bad": {"kinds": "service,teapot,kettle"},
    "kinds_commas": {"kinds": ",,"},
    "kinds_empty_str": {"kinds": ""},
    "kinds_none": {"kinds": None},
    "kinds_ok": {"kinds": "service, gateway"},
    "minutes_neg": {"minutes": -1.0},
    "minutes_zero": {"minutes": 0.0},
    "nothing": {},
    "rounds_neg": {"rounds": -1},
    "rounds_ok": {"rounds": 2},
    "seconds_neg": {"seconds": -2.5},
    "seconds_ok": {"seconds": 1.5},
    "seconds_zero": {"seconds": 0.0},
    "trials_ok": {"trials": 3},
    "trials_zero": {"trials": 0},
}
EXPECTED = {
    "check_all": ("--check judges one of soak, flood, named alone (got: all benchmarks)", None),
    "check_chaos": ("--check judges one of soak, flood, named alone (got: chaos)", None),
    "check_flood": (None, None),
    "check_off": (None, None),
    "check_soak": (None, None),
    "check_two": ("--check judges one of soak, flood, named alone (got: soak flood)", None),
    "first_wins": ("--seconds 0: must be positive", None),
    "kinds_bad": (
        "--kinds service,teapot,kettle: unknown teapot, kettle; known: service, controller, recorder, "
        "console, bridge, gateway, export",
        None,
    ),
    "kinds_commas": (
        "--kinds ,,: unknown nothing; known: service, controller, recorder, console, bridge, gateway, export",
        None,
    ),
    "kinds_empty_str": (None, None),
    "kinds_none": (None, None),
    "kinds_ok": (None, ("service", "gateway")),
    "minutes_neg": ("--minutes -1: must not be negative", None),
    "minutes_zero": (None, None),
    "nothing": (None, None),
    "rounds_neg": ("--rounds -1: must be positive", None),
    "rounds_ok": (None, None),
    "seconds_neg": ("--seconds -2.5: must be positive", None),
    "seconds_ok": (None, None),
    "seconds_zero": ("--seconds 0: must be positive", None),
    "trials_ok": (None, None),
    "trials_zero": ("--trials 0: must be positive", None),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_refusal_gives_todays_line_and_kinds(name):
    args = SimpleNamespace(**{"seconds": None, "minutes": None, "names": [], **CASES[name]})
    assert _refusal(args) == EXPECTED[name]
