"""The gripper's motion logic (pfma/gripper.py) on synthetic tach and current samples at the
controller's 40 Hz: stall detection, its classification by the motor current, the grip force,
the limits and the jaw estimate. Time is the samples' own (no clock)."""

from __future__ import annotations

import pytest

from pfma.arm import GRIPPER
from pfma.gripper import (
    COMPLETE, FAILED, GRIP_FORCE_MIN_N, GRIP_SPEED_M_S, IN_PROGRESS, JAW_EMPTY_M, MOVE_TIMEOUT_S, NOTE, REFUSED,
    STALL_TIME_S, START_GRACE_S, GripperMotion, GripperRequest as R, GripperState as S, check_force, describe,
)

DT = 1 / 40  # the controller's gripper task


class Jaw:
    """A crude jaw for the logic: moves at the commanded speed (opening positive) between its
    stops and an object; at a stop or the object it does not move and the motor draws the
    current limit (the drive answers) or nothing (``dead``)."""

    def __init__(self, q: float, obj: float | None = None, dead: bool = False) -> None:
        self.q, self.obj, self.dead = q, obj, dead

    def sample(self, m: GripperMotion) -> tuple[float, float]:
        lo = self.obj if self.obj is not None else 0.0
        v = 0.0 if self.dead else max(-GRIP_SPEED_M_S, min(GRIP_SPEED_M_S, m.rate_cmd_m_s))
        new = min(max(self.q + v * DT, lo), GRIPPER.travel_m)
        rate = (new - self.q) / DT
        self.q = new
        pushing = m.rate_cmd_m_s != 0.0 and abs(rate) < 1e-9 and not self.dead
        return rate, (m.current_limit_a if pushing else 0.0) * (1 if m.rate_cmd_m_s > 0 else -1)


def run(m: GripperMotion, jaw: Jaw, t: float, seconds: float) -> tuple[float, list]:
    out = []
    for _ in range(int(round(seconds / DT))):
        t += DT
        r = m.update(t, *jaw.sample(m))
        if r is not None:
            out.append((round(t, 4), r))
    return t, out


def powered(force_n: float = 40.0) -> GripperMotion:
    m = GripperMotion(force_n=force_n)
    m.power(True, 0.0)
    return m


def test_an_open_ends_at_the_stop_and_references_the_jaw_estimate():
    m, jaw = powered(), Jaw(0.05)
    assert (m.state, m.jaw_m, m.rate_cmd_m_s) == (S.STOPPED, None, 0.0)
    assert m.request(R.OPEN, 0.0, 0.0) == (IN_PROGRESS, "OPENING at 20 mm/s, 40 N")
    assert m.rate_cmd_m_s == GRIP_SPEED_M_S and m.current_limit_a == 40.0 / GRIPPER.force_per_amp
    t, ends = run(m, jaw, 0.0, 5.0)
    assert len(ends) == 1 and ends[0][1].code == COMPLETE and ends[0][1].text.startswith("OPEN: at the open stop")
    # 50 mm at 20 mm/s, then STALL_TIME_S of standing still (the first still sample counts at once)
    assert ends[0][0] == pytest.approx(0.05 / GRIP_SPEED_M_S + STALL_TIME_S, abs=2 * DT)
    assert (m.state, m.jaw_m, m.rate_cmd_m_s) == (S.OPEN, GRIPPER.travel_m, 0.0)
    assert m.request(R.OPEN, 0.0, t).text == "already OPEN"


def test_a_close_on_an_object_grips_at_full_scale_with_the_set_force_and_the_estimate_follows():
    m, jaw = powered(), Jaw(GRIPPER.travel_m, obj=0.04)
    m.jaw_m = GRIPPER.travel_m  # referenced (an open reached the stop)
    assert m.request(R.CLOSE, 60.0, 0.0).code == IN_PROGRESS
    assert m.force_n == 60.0 and m.current_limit_a == pytest.approx(1.5)
    _, ends = run(m, jaw, 0.0, 5.0)
    assert [e.code for _, e in ends] == [COMPLETE]
    assert m.state == S.GRIPPING and "holding at 60 N; jaw ~40 mm" in ends[0][1].text
    # the hold: full-scale closing so the amplifier saturates at the limit the grip force sets
    assert m.rate_cmd_m_s == -GRIPPER.omega_fs_m_s and m.current_limit_a == pytest.approx(1.5)
    assert m.jaw_m == pytest.approx(0.04, abs=1e-3)
    assert m.motor_force_n == pytest.approx(60.0)
    assert m.request(R.CLOSE, 0.0, 9.0).text == "already GRIPPING at 60 N"
    assert m.request(R.FORCE, 120.0, 9.0).code == COMPLETE and m.current_limit_a == pytest.approx(3.0)


def test_a_close_with_nothing_between_the_jaws_ends_closed_and_zeroes_the_estimate():
    m, jaw = powered(), Jaw(0.01)
    m.jaw_m = 0.0105  # a little off: it is an estimate
    m.request(R.CLOSE, 0.0, 0.0)
    _, ends = run(m, jaw, 0.0, 2.0)
    assert ends[0][1].code == COMPLETE and ends[0][1].text.startswith("CLOSED")
    assert (m.state, m.jaw_m) == (S.CLOSED, 0.0) and JAW_EMPTY_M > 0


def test_without_a_reference_a_close_on_contact_is_gripping_and_says_the_jaw_is_unknown():
    m, jaw = powered(), Jaw(0.05, obj=0.03)
    m.request(R.CLOSE, 0.0, 0.0)
    _, ends = run(m, jaw, 0.0, 3.0)
    assert m.state == S.GRIPPING and m.jaw_m is None
    assert "jaw position not known (no open to the stop yet)" in ends[0][1].text


def test_a_drive_that_draws_no_current_is_stalled_and_the_move_fails():
    m, jaw = powered(), Jaw(0.05, dead=True)
    m.request(R.OPEN, 0.0, 0.0)
    _, ends = run(m, jaw, 0.0, 1.0)
    assert [e.code for _, e in ends] == [FAILED] and m.state == S.STALLED and m.rate_cmd_m_s == 0.0
    assert ends[0][0] == pytest.approx(START_GRACE_S + STALL_TIME_S, abs=DT + 1e-9)
    assert "the drive does not answer" in ends[0][1].text


def test_a_move_that_never_stalls_is_stopped_and_fails_after_the_timeout():
    m = powered()
    m.request(R.CLOSE, 0.0, 0.0)
    t, ends = 0.0, []
    while not ends and t < MOVE_TIMEOUT_S + 1:
        t += DT
        r = m.update(t, -GRIP_SPEED_M_S, 0.5)  # a tach that says it moves forever
        if r is not None:
            ends.append((t, r))
    assert ends and ends[0][1].code == FAILED and "did not end within" in ends[0][1].text
    assert ends[0][0] == pytest.approx(MOVE_TIMEOUT_S, abs=DT + 1e-9)
    assert m.state == S.STOPPED and m.rate_cmd_m_s == 0.0 and m.jaw_m is None


def test_stop_ends_a_move_and_releases_a_grip():
    m, jaw = powered(), Jaw(0.08)
    m.request(R.CLOSE, 0.0, 0.0)
    t, _ = run(m, jaw, 0.0, 0.5)
    out = m.request(R.STOP, 0.0, t)
    assert out.code == COMPLETE and out.text.startswith("stopped (CLOSING ended)")
    assert (m.state, m.rate_cmd_m_s) == (S.STOPPED, 0.0)
    q = jaw.q
    run(m, jaw, t, 0.5)
    assert jaw.q == q  # nothing commands it any more
    assert m.request(R.STOP, 0.0, t).text == "not moving (STOPPED)"


def test_a_grip_lost_resumes_the_close_and_says_so():
    m, jaw = powered(), Jaw(0.05, obj=0.03)
    m.request(R.CLOSE, 0.0, 0.0)
    t, _ = run(m, jaw, 0.0, 3.0)
    assert m.state == S.GRIPPING
    jaw.obj = None  # the part is taken out of the jaws
    t, ends = run(m, jaw, t, 3.0)
    assert [e.code for _, e in ends] == [NOTE, COMPLETE]
    assert ends[0][1].text.startswith("grip lost while GRIPPING")
    assert m.state == S.GRIPPING and jaw.q == 0.0  # closed on itself (no reference: not known to be empty)


@pytest.mark.parametrize("kind, force, says", [
    (R.FORCE, 500.0, "grip force 500 N is outside 10..200 N (current limit 0.25..5 A at 40 N/A)"),
    (R.CLOSE, 5.0, "grip force 5 N is outside 10..200 N"),
    (R.FORCE, 0.0, "grip force 0 N is outside"),
    (R.OPEN, float("nan"), "grip force nan is not a number"),
    (9, 0.0, "unknown gripper request 9 (1 OPEN 2 CLOSE 3 STOP 4 FORCE)"),
    (R.NONE, 0.0, "no gripper request"),
])
def test_limits_and_unknown_requests_are_refused_with_the_reason_and_change_nothing(kind, force, says):
    m = powered()
    before = (m.state, m.force_n, m.current_limit_a, m.rate_cmd_m_s)
    out = m.request(kind, force, 0.0)
    assert out.code == REFUSED and says in out.text
    assert (m.state, m.force_n, m.current_limit_a, m.rate_cmd_m_s) == before


def test_the_cap_lowers_the_largest_force_and_a_drive_that_is_off_refuses_moves():
    m = GripperMotion()
    assert m.request(R.CLOSE, 0.0, 0.0) == (REFUSED, "the gripper drive is off (power up first)")
    assert m.request(R.FORCE, 80.0, 0.0) == (COMPLETE, "grip force 80 N, current limit 2 A (in force from the "
                                                       "next power-up)")
    m.set_force_cap(40.0)  # the controller's current-limit parameter: 1 A
    assert m.force_n == 40.0
    assert "outside 10..40 N" in m.request(R.FORCE, 60.0, 0.0).text
    assert check_force(GRIP_FORCE_MIN_N, 5.0).startswith("the gripper's current limit allows 5 N")


def test_a_power_down_fails_the_move_and_forgets_the_jaw():
    m, jaw = powered(), Jaw(0.05)
    m.jaw_m = 0.05
    m.request(R.OPEN, 0.0, 0.0)
    run(m, jaw, 0.0, 0.5)
    out = m.power(False, 0.5)
    assert out is not None and out.code == FAILED and "switched off" in out.text
    assert (m.state, m.rate_cmd_m_s, m.current_limit_a, m.jaw_m) == (S.OFF, 0.0, 0.0, None)
    assert describe(m.state, m.force_n, 0.0, None) == "gripper OFF  grip 40 N set, motor 0 N  jaw not known (not sensed)"
    longest = describe(S.GRIPPING, 200.0, 200.0, 0.1)
    assert longest == "gripper GRIPPING  grip 200 N set, motor 200 N  jaw ~100 mm (tach estimate)"
    assert len(longest) <= 76  # World Status's width (docs/console.md "Sizes")
