"""Characterisation of :func:`bench.bench_chaos.judge_outputs` (issue 31): the exact
verdict, detail text and figures it gave, before its split into small functions, on frames
shaped like a recorded ring (test_chaos_fixes' ``_rows``) around each branch."""

import copy

import pytest

from bench.bench_chaos import WATCHDOG_S, judge_outputs
from tests.chaos.test_chaos_fixes import ARMED, PERIOD, SAFE, _msg, _rows


def judge_cases():
    c = []
    t = 1.0
    last_hb = max(k * PERIOD for k in range(640) if k * PERIOD <= t)
    c.append(("trip_ok", _rows(t, WATCHDOG_S), [_msg(last_hb + 0.0152, 15.2)], t, {}))
    c.append(("late", _rows(t, 0.030), [_msg(last_hb + 0.031, 31.0)], t, {}))
    c.append(("late_nomsg", _rows(t, 0.030), [], t, {}))
    c.append(("still_armed", _rows(t, None), [], t, {}))
    c.append(("volts", _rows(t, WATCHDOG_S, volts_after=0.5), [], t, {}))
    c.append(("safe", _rows(t, 0.004, state_after=SAFE), [], t, {}))
    st = [_msg(last_hb + 0.070, 70.0)]
    st[0].text = "outputs safe: stale heartbeat 70>15 ms (stall 60 ms)"
    c.append(("stall", _rows(t, 0.069), st, t, {}))
    r = _rows(t, WATCHDOG_S)
    r[-1]["vmax"] = 2.0
    c.append(("later_volts", r, [], t, {}))
    r = _rows(t, WATCHDOG_S)
    r[-5]["state"] = ARMED
    c.append(("later_armed", r, [], t, {}))
    un = _rows(t, None)
    for x in un:
        x["state"], x["vmax"] = SAFE, 0.0
    c.append(("unarmed_ok", un, [], t, {}))
    c.append(("unarmed_ok_ret", un, [], t, {"writer_returns": True}))
    u2 = copy.deepcopy(un)
    u2[-1]["vmax"] = 1.0
    c.append(("unarmed_volts", u2, [], t, {}))
    u3 = copy.deepcopy(un)
    for x in u3[len(u3) // 2 + 20 :]:
        x["state"], x["vmax"] = ARMED, 0.2
    c.append(("unarmed_rearm_ret", u3, [], t, {"writer_returns": True}))
    c.append(("unarmed_rearm", u3, [], t, {}))
    u4 = copy.deepcopy(u3)
    u4[-1]["state"] = SAFE
    c.append(("unarmed_rearm_ret_bad", u4, [], t, {"writer_returns": True}))
    c.append(("no_cover", un[:10], [], t, {}))
    c.append(("no_before", un, [], -1.0, {}))
    c.append(
        ("custom_limits", _rows(t, 0.030), [_msg(last_hb + 0.031, 31.0)], t, {"watchdog_s": 0.05, "period_s": 0.01})
    )
    return c


EXPECTED = {
    "custom_limits": (
        True,
        "0 V 31.0 ms after the last heartbeat (outputs safe: stale heartbeat 31.0>15 ms)",
        {"armed_at_kill": True, "kill_to_0v_ms": 31.0, "trip_age_ms": 31.0},
    ),
    "late": (
        False,
        "late: 0 V 31.0 ms after the last heartbeat > watchdog + one frame 18.1 ms (outputs safe: stale "
        "heartbeat 31.0>15 ms)",
        {"armed_at_kill": True, "kill_to_0v_ms": 31.0, "trip_age_ms": 31.0},
    ),
    "late_nomsg": (
        False,
        "late: 0 V 31.2 ms after the last heartbeat > watchdog + one frame 18.1 ms ((no watchdog message))",
        {"armed_at_kill": True, "kill_to_0v_ms": 31.25, "trip_age_ms": 31.25},
    ),
    "later_armed": (
        False,
        "frame 635 after the trip has 0.000 V",
        {"armed_at_kill": True, "kill_to_0v_ms": 15.62, "trip_age_ms": 15.62},
    ),
    "later_volts": (
        False,
        "frame 639 after the trip has 2.000 V",
        {"armed_at_kill": True, "kill_to_0v_ms": 15.62, "trip_age_ms": 15.62},
    ),
    "no_before": (False, "the frame ring does not cover the kill (0 frames before, 640 after)", {}),
    "no_cover": (False, "the frame ring does not cover the kill (10 frames before, 0 after)", {}),
    "safe": (
        True,
        "0 V 6.3 ms after the last heartbeat ((no watchdog message))",
        {"armed_at_kill": True, "kill_to_0v_ms": 6.25, "trip_age_ms": 6.25},
    ),
    "stall": (
        False,
        "host stall named by the service: 0 V 70.0 ms after the last heartbeat > watchdog + one frame "
        "18.1 ms (outputs safe: stale heartbeat 70>15 ms (stall 60 ms))",
        {"armed_at_kill": True, "kill_to_0v_ms": 70.0, "trip_age_ms": 70.0},
    ),
    "still_armed": (False, "still ARMED 0.997 s after the kill (frame 639, 5.000 V)", {"armed_at_kill": True}),
    "trip_ok": (
        True,
        "0 V 15.2 ms after the last heartbeat (outputs safe: stale heartbeat 15.2>15 ms)",
        {"armed_at_kill": True, "kill_to_0v_ms": 15.2, "trip_age_ms": 15.2},
    ),
    "unarmed_ok": (True, "not armed at the kill (state 1); 0 V in all 319 frames after", {"armed_at_kill": False}),
    "unarmed_ok_ret": (True, "not armed at the kill (state 1); 0 V in all 319 frames after", {"armed_at_kill": False}),
    "unarmed_rearm": (False, "not armed at the kill, yet frame 340 is ARMED with 0.200 V", {"armed_at_kill": False}),
    "unarmed_rearm_ret": (
        True,
        "not armed at the kill (state 1); 0 V in all 319 frames after",
        {"armed_at_kill": False},
    ),
    "unarmed_rearm_ret_bad": (
        False,
        "not armed at the kill, yet frame 639 is state 1 with 0.200 V",
        {"armed_at_kill": False},
    ),
    "unarmed_volts": (False, "not armed at the kill, yet frame 639 is state 1 with 1.000 V", {"armed_at_kill": False}),
    "volts": (
        False,
        "frame 325 left ARMED for state 3 with 0.500 V ((no watchdog message))",
        {"armed_at_kill": True, "kill_to_0v_ms": 15.62, "trip_age_ms": 15.62},
    ),
}


@pytest.mark.parametrize(
    "name, rows, messages, t_gone, kw", judge_cases(), ids=lambda v: v if isinstance(v, str) else ""
)
def test_judge_outputs_gives_todays_verdict_text_and_figures(name, rows, messages, t_gone, kw):
    assert judge_outputs(rows, messages, t_gone, **kw) == EXPECTED[name]


def test_every_case_has_its_expectation():
    assert {c[0] for c in judge_cases()} == set(EXPECTED)
