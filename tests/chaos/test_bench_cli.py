"""``pfma bench chaos`` / ``soak`` / ``flood`` options: a mistake is one line and exit 2 (nothing runs)."""

from __future__ import annotations

import pytest

from tools.cli import main
from tools.cli.bench import ON_REQUEST


def test_chaos_and_soak_run_only_when_named():
    assert {"chaos", "soak"} <= set(ON_REQUEST)


@pytest.mark.parametrize("argv, words", [
    (["bench", "chaos", "--trials", "0"], "--trials 0: must be positive"),
    (["bench", "chaos", "--kinds", "service,teapot"], "--kinds service,teapot: unknown teapot; known: service"),
    (["bench", "chaos", "--kinds", ","], "unknown nothing"),
    (["bench", "soak", "--minutes", "-1"], "--minutes -1: must not be negative"),
    (["bench", "chaos", "service", "--json"], "--json measures"),
    (["bench", "chaos", "--check"], "--check judges one of soak, flood, named alone (got: chaos)"),
    (["bench", "soak", "flood", "--check"], "--check judges one of soak, flood, named alone"),
    (["bench", "--check"], "(got: all benchmarks)"),
    (["bench", "flood", "--rounds", "0"], "--rounds 0: must be positive"),
])
def test_bad_chaos_and_soak_options_are_one_message(argv, words, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and err.count("\n") == 1
