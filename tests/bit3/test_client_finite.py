"""``bit3.client._check_finite`` decides as ``np.all(np.isfinite(np.asarray(v)))`` did for
values numpy reads as float or complex, and lets everything else through to the assignment."""

import math

import numpy as np
import pytest

from bit3.buffer import Bit3Error
from bit3.client import _check_finite

VALUES = [
    0.0, -1.5, math.inf, -math.inf, math.nan, np.float64(2.0), np.float64(math.nan), np.float32(math.inf),
    np.float32(1.0), 3, True, 2 ** 70, np.int32(4), [1.0, 2.0], [1, math.nan], (0.5, math.inf), [1, 2],
    np.zeros(7), np.array([0.0, math.nan, 1.0]), np.array([math.inf]), np.zeros(40), np.r_[np.zeros(39), math.nan],
    np.zeros((2, 3)), np.array([[0.0, math.inf]]), np.array([1, 2]), np.array([1.0], dtype=np.float32),
    np.array([math.nan], dtype=np.float16), np.array([1 + 1j, complex(math.inf, 0)]), complex(1, 2),
    "text", None,
]


def _numpy_rule(value) -> bool:
    arr = np.asarray(value)
    return arr.dtype.kind not in "fc" or bool(np.all(np.isfinite(arr)))


@pytest.mark.parametrize("value", VALUES, ids=[repr(v)[:30] for v in VALUES])
def test_check_finite_agrees_with_the_numpy_rule(value):
    if _numpy_rule(value):
        _check_finite("f", value)
    else:
        with pytest.raises(Bit3Error, match="(?s)command f = .* is not finite"):
            _check_finite("f", value)


def test_the_table_has_both_outcomes():
    outcomes = {_numpy_rule(v) for v in VALUES}
    assert outcomes == {True, False}
