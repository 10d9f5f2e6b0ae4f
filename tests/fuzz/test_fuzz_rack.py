"""Fuzzed rack files (issue 20 item 3): a mutated default rack TOML (values replaced by
other types and extremes, lines deleted, duplicated, swapped, text inserted, the file cut
short) is either a rack or one ConfigError naming the file; through ``pfma channels
--rack`` it is one ``pfma channels:`` line and exit 1, never a traceback.

Not repeated here: the hand-picked bad rack files of tests/tools/cli/test_bad_inputs.py.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings

from bit3.layout import build_layout
from pfma.errors import ConfigError
from pfma.rack import DEFAULT_RACK, RackConfig, parse_rack
from tests.fuzz._mutate import FUZZ, apply_text_edits, text_edits
from tools.cli import main

TEXT = DEFAULT_RACK.read_text()
SOURCE = "fuzz-rack.toml"


@settings(FUZZ, max_examples=150)
@given(text_edits())
def test_a_mutated_rack_file_is_a_rack_or_one_message_naming_the_file(edits):
    text = apply_text_edits(TEXT, edits)
    try:
        rack = parse_rack(text, SOURCE)
    except ConfigError as err:
        assert str(err).startswith(SOURCE), str(err)
        return
    assert isinstance(rack, RackConfig)
    try:
        build_layout(rack)  # what the service makes of an accepted rack
    except ConfigError as err:
        assert str(err), "an empty message"


@settings(FUZZ, max_examples=25)
@given(text_edits(2))
def test_pfma_channels_on_a_mutated_rack_file_exits_0_or_1_with_one_line(tmp_path_factory, capsys, edits):
    path = tmp_path_factory.mktemp("rack") / "mutated.toml"
    path.write_text(apply_text_edits(TEXT, edits))
    code = main(["channels", "--rack", str(path)])
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
    assert code in (0, 1), code
    if code == 1:
        lines = [ln for ln in out.err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("pfma channels:") and str(path) in lines[0], out.err


def test_a_deeply_nested_rack_value_is_one_message():
    with pytest.raises(ConfigError, match=SOURCE):
        parse_rack(TEXT + "\nx = " + "[" * 5000 + "]" * 5000 + "\n", SOURCE)
