"""Seeded mutations of text files for the fuzz tests (issue 20 item 3).

Every fuzz test here is ``@settings(derandomize=True)``: hypothesis draws its examples
from a seed derived from the test itself, so a run is reproducible, in CI and here.
Each test's ``max_examples`` is chosen so that all of tests/fuzz/ together cost <= 40 s
(docs/reliability.md has the figures).
"""

from __future__ import annotations

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

#: the settings every fuzz test starts from (each sets its own max_examples)
FUZZ = settings(derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])

#: values a mutated ``key = value`` TOML line takes
TOML_VALUES = st.sampled_from([
    "0", "-1", "1", "7", "65535", "65536", "9223372036854775807", "-9223372036854775808",
    "0.0", "-0.0", "0.5", "1e308", "-1e308", "inf", "-inf", "nan", "true", "false",
    '""', '"x"', '"\u00e9\u00e8"', '"rtd"', '"adc"', '"dac"', "[]", "[1, 2]", '["a", "b"]', "{}",
    "{ ch = 0 }", "1979-05-27", "0x0100", "0x0201", "0xFFFF", "0o777", "0b101",
])

#: JSON values a mutated calibration field takes
JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70),
              st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=7), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=12)


def text_edits(n_max: int = 4):
    """A list of edits of a text: (kind, position fraction, payload)."""
    edit = st.tuples(
        st.sampled_from(["value", "value", "value", "delete", "duplicate", "swap", "truncate", "insert"]),
        st.floats(0, 1, exclude_max=True),
        st.floats(0, 1, exclude_max=True),
        st.one_of(TOML_VALUES, st.text(max_size=12)),
    )
    return st.lists(edit, min_size=1, max_size=n_max)


def apply_text_edits(text: str, edits) -> str:
    """Apply :func:`text_edits` to a line-oriented text (TOML)."""
    lines = text.split("\n")
    for kind, a, b, payload in edits:
        if not lines:
            break
        i = int(a * len(lines))
        if kind == "value":
            keyed = [k for k, ln in enumerate(lines) if "=" in ln and not ln.lstrip().startswith("#")]
            if keyed:
                k = keyed[int(a * len(keyed))]
                ln = lines[k]
                # inside an inline table row ({ ch = 0, signal = ... }) pick one of its keys
                eqs = [p for p, c in enumerate(ln) if c == "="]
                p = eqs[int(b * len(eqs))]
                end = ln.find(",", p)
                end = len(ln) if end < 0 or "{" not in ln else end
                lines[k] = ln[:p + 1] + " " + payload + ln[end:]
        elif kind == "delete":
            del lines[i]
        elif kind == "duplicate":
            lines.insert(i, lines[i])
        elif kind == "swap":
            j = int(b * len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "truncate":
            s = "\n".join(lines)
            return s[:int(a * len(s))]
        else:
            ln = lines[i]
            p = int(b * (len(ln) + 1))
            lines[i] = ln[:p] + payload + ln[p:]
    return "\n".join(lines)
