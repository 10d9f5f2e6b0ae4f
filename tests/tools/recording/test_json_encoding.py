"""The recorder's JSON channels: compact, NaN and inf as null (JSON has neither; Foxglove
refuses them), numpy values as plain numbers, every float back exactly."""

from __future__ import annotations

import json
import math

import numpy as np

from tools.recording.topics import _dumps


def test_nan_and_inf_become_null_and_the_rest_is_unchanged():
    obj = {"t_s": 1.25, "frame": 7, "v": [0.1, math.nan, -math.inf, 3.0], "nested": {"x": math.inf, "ok": True}}
    out = _dumps(obj)
    assert json.loads(out) == {"t_s": 1.25, "frame": 7, "v": [0.1, None, None, 3.0],
                               "nested": {"x": None, "ok": True}}
    assert b" " not in out  # compact, as the channels always were


def test_finite_values_round_trip_exactly():
    obj = {"t_s": 0.1 + 0.2, "frame": 2**40, "names": ["a", "b"], "rates": [1e-9, -2.5e300, 5e-324]}
    assert json.loads(_dumps(obj)) == obj  # every float back bit for bit (shortest repr)


def test_numpy_values_are_plain_numbers():
    obj = {"a": np.float64(1.5), "b": np.int32(3), "c": np.array([1.0, np.nan]), "d": np.bool_(True)}
    assert json.loads(_dumps(obj)) == {"a": 1.5, "b": 3, "c": [1.0, None], "d": True}
