"""Fuzzed calibration files (issue 20 item 3): a full calibration (every analog channel,
the F/T section, the CAE stick's axes) with fields replaced by arbitrary JSON values or
removed, or its text cut, garbled or extended, is either a calibration or one
CalibrationError naming the file and the field ("file refused, the previous calibration
stays in force"); an accepted one hashes and compares without an exception.

Not repeated here: the hand-picked bad files of tests/calibration/test_files.py.
"""

from __future__ import annotations

import copy
import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.files import (
    CAE_AXIS_NAMES, Calibration, calibration_hash, diff, nominal_calibration, nominal_ft, parse_calibration,
    provenance,
)
from pfma.errors import CalibrationError
from pfma.rack import load_rack
from tests.fuzz._mutate import FUZZ, JSON_VALUES

RACK = load_rack()
SOURCE = "fuzz-calibration.json"


def full_calibration() -> dict:
    data = copy.deepcopy(nominal_calibration(RACK, date="2026-01-01T00:00:00Z").data)
    data["ft"] = nominal_ft()
    data["cae"] = {a: {"centre_v": 0.0, "deadband_v": 0.5, "span_v": 10.0, "sign": 1,
                       "provenance": provenance("fuzz base", date="2026-01-01T00:00:00Z")}
                   for a in CAE_AXIS_NAMES}
    return data


BASE = full_calibration()
NOMINAL = Calibration(BASE)
TEXT = json.dumps(BASE, indent=1)


def _paths(d, prefix=()):
    """Every path (tuple of keys/indices) into the nested data."""
    yield prefix
    if isinstance(d, dict):
        for k, v in d.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield from _paths(v, prefix + (i,))


PATHS = [p for p in _paths(BASE) if p]

#: one structural edit: (path index fraction, replace or delete, the new value)
_edit = st.tuples(st.floats(0, 1, exclude_max=True), st.sampled_from(["replace", "replace", "delete"]),
                  JSON_VALUES)


def _apply(data: dict, edits) -> dict:
    d = copy.deepcopy(data)
    for frac, kind, value in edits:
        paths = [p for p in _paths(d) if p]
        path = paths[int(frac * len(paths))]
        parent = d
        for k in path[:-1]:
            parent = parent[k]
        if kind == "delete":
            del parent[path[-1]]
        else:
            parent[path[-1]] = value
    return d


def _check(text: str) -> None:
    try:
        cal = parse_calibration(text, SOURCE, RACK)
    except CalibrationError as err:
        msg = str(err)
        assert msg.startswith(f"calibration {SOURCE}: ") and msg.endswith(
            "file refused, the previous calibration stays in force"), msg
        return
    calibration_hash(cal)
    diff(NOMINAL, cal)


@settings(FUZZ, max_examples=200)
@given(st.lists(_edit, min_size=1, max_size=3))
def test_a_calibration_with_fields_replaced_or_removed_is_accepted_or_refused_naming_the_field(edits):
    _check(json.dumps(_apply(BASE, edits), allow_nan=True))


@settings(FUZZ, max_examples=100)
@given(st.floats(0, 1), st.sampled_from(["truncate", "flip", "insert"]), st.binary(min_size=1, max_size=8))
def test_a_calibration_file_cut_garbled_or_extended_is_accepted_or_refused(at, kind, junk):
    raw = TEXT.encode()
    i = int(at * len(raw))
    if kind == "truncate":
        raw = raw[:i]
    elif kind == "flip":
        raw = raw[:i] + bytes(b ^ 0x5A for b in junk) + raw[i + len(junk):]
    else:
        raw = raw[:i] + junk + raw[i:]
    _check(raw.decode("utf-8", "replace"))


# -- found by the fuzzing above: exceptions parse_calibration let through (now CalibrationErrors) --------


def test_a_number_beyond_float_range_is_refused_naming_the_field():
    data = copy.deepcopy(BASE)
    sig = next(iter(data["channels"]))
    data["channels"][sig]["scale"] = 10 ** 400  # a JSON integer float() cannot hold
    with pytest.raises(CalibrationError, match=f"channels.{sig}.scale"):
        parse_calibration(json.dumps(data), SOURCE, RACK)


def test_an_integer_of_5000_digits_is_refused():
    with pytest.raises(CalibrationError):
        parse_calibration('{"format": ' + "9" * 5000 + "}", SOURCE, RACK)


def test_deeply_nested_json_is_refused():
    with pytest.raises(CalibrationError):
        parse_calibration("[" * 100_000, SOURCE, RACK)
