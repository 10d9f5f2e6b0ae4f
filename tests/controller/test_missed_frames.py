"""Missed controller frames and command freshness (issue 14), in simulated time.

The controller's steps are driven by ``SystemSimulator.controller_steps`` (service frame
-> controller steps after it: 0 misses the frame, 2 is a burst on the same inputs)."""

import io
import json
from contextlib import redirect_stdout
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from controller.daq_layer import FAULT_COMMAND, FAULT_NO_OUTPUT
from controller.decision import Status
from controller.frames import FrameConfig
from controller.servo import ERR_MISSED, LeadLag
from sim.system import SystemSimulator
from bit3.client import Client
from bit3.layout import CMD_FOREIGN, CMD_REFUSED, CMD_STALE

S = Status
RATE_CHANNELS = slice(0, 6)  # DAC channels 0..5: the joint rate commands (rack_default.toml)
YAW = 1  # shoulder yaw in command-area order


def _goal_yaw(sim, yaw_rad: float) -> None:
    goal = sim.joint_angles_rad().copy()
    goal[YAW] = yaw_rad
    sim.rt.set_joint_goal(goal)


def test_odd_frames_only_holds_the_goal_with_catch_up_and_counts_the_missed_frames(powered):
    """Issue 14's reproduction: stepping only after odd service frames drove shoulder yaw
    at 6 V into its hard stop (the servo's even-frame slot never ran, the last rate was
    re-sent). Now the servo slot is caught up in the odd frame and the arm holds the goal."""
    rt = powered.rt
    _goal_yaw(powered, 0.1)
    powered.controller_steps = lambda f: f % 2
    peak = -np.inf
    for _ in range(960):  # 3 s
        powered.step(1)
        peak = max(peak, powered.joint_angles_rad()[YAW])
    q = powered.joint_angles_rad()[YAW]
    assert peak < 0.1 + 0.005, f"passed the goal: peak {peak:.4f} rad"
    assert abs(q - 0.1) < 0.005
    assert rt.status("updown") == S.START_UP_COMPLETE  # one missed frame at a time is allowed
    assert rt.missed_frames >= 470 and rt.longest_missed_run == 1
    assert rt.missed_task_slots >= rt.missed_frames
    warn = [m for m in rt.messages.recent(1000, source="runtime") if "missed service frame" in m.text]
    assert 1 <= len(warn) <= 4  # rate-limited: one a second, with a count
    assert "caught up" in warn[0].text and "servo_control" in warn[0].text
    assert "more events" in warn[-1].text
    # the service never saw a command older than its limit
    assert int(rt.daq.snapshot.stale_commands) == 0
    assert not rt.daq.fault_bits


def test_one_frame_in_four_is_a_servo_fault_that_reaches_updown_within_6_controller_frames(powered):
    rt = powered.rt
    _goal_yaw(powered, 0.1)
    powered.controller_steps = lambda f: 1 if f % 4 == 0 else 0  # 3 missed in a row > 2
    powered.run_until(lambda: rt.status("updown") == S.ERROR, 200)
    msg = next(m for m in rt.messages.recent(1000, source="servo") if f"fault {ERR_MISSED}" in m.text)
    assert "missed service frames" in msg.text and "in a row > max_missed_run 2" in msg.text
    k_detect, k_updown = msg.frame, rt.first_change("updown", S.ERROR)
    steps = [r.frame for r in rt.trace if k_detect <= r.frame <= k_updown]
    assert len(steps) - 1 <= 6, f"{len(steps) - 1} controller frames from detection to Up/Down ERROR"
    assert rt.servo.error_code == ERR_MISSED
    powered.step(3)
    assert np.all(powered.dac_volts()[RATE_CHANNELS] == 0.0)
    assert abs(powered.joint_angles_rad()[YAW]) < 0.1 + 0.005


def test_nominal_command_age_is_1_to_2_frames_and_two_missed_frames_at_most_4(powered):
    ages = []
    powered.rig.after_frame.append(lambda info: ages.append(int(powered.rt.daq.snapshot.command_input_age_frames)))
    _goal_yaw(powered, 0.05)
    powered.step(64)
    assert set(ages[2:]) <= {1, 2}
    for miss in (101, 202, 303, 404):  # two frames in a row, starting odd and even
        base = powered.svc_frame()
        ages.clear()
        powered.controller_steps = lambda f, b=base, m=miss % 2: 0 if f in (b + 4 + m, b + 5 + m) else 1
        powered.step(12)
        assert max(ages) <= 4, ages
    assert powered.rt.status("updown") == S.START_UP_COMPLETE
    assert powered.rt.missed_frames == 8 and powered.rt.longest_missed_run == 2


def test_a_raising_servo_task_zeroes_the_rates_at_once(powered):
    rt = powered.rt
    _goal_yaw(powered, 0.3)
    powered.step(40)
    assert np.any(powered.dac_volts()[RATE_CHANNELS] != 0.0)

    def boom(rt_):
        raise RuntimeError("injected")
    rt._impl["servo_control"] = boom
    rt._table = tuple(tuple((n, boom if n == "servo_control" else fn) for n, fn in fr) for fr in rt._table)
    powered.run_until(lambda: rt.servo.fault, 4)
    k = rt.frame
    powered.step(2)  # the next output sends 0 rates, the service applies them one frame later
    assert np.all(powered.dac_volts()[RATE_CHANNELS] == 0.0)
    powered.run_until(lambda: rt.status("updown") == S.ERROR, 10)
    assert rt.first_change("updown", S.ERROR) - k <= 7


def test_a_servo_output_that_is_not_there_is_data_acquisitions_own_fault(powered):
    """The servo task stops computing (a remote servo's output late, a task that returns
    nothing): Data Acquisition sends 0 V and reports it through its own status (fault bit
    128), never by setting Servo Control's flag (report 2.3.2); the tables carry it up. It
    is an event: ERROR RESET clears it."""
    from controller.layers import Request, Response
    rt = powered.rt
    _goal_yaw(powered, 0.3)
    powered.step(40)
    assert np.any(powered.dac_volts()[RATE_CHANNELS] != 0.0)
    servo = rt.servo
    real = servo.periodic["servo_control"]
    servo.periodic["servo_control"] = lambda rt_: None
    rt._build_schedule()
    powered.run_until(lambda: rt.status("daq") == S.ERROR, 10)
    assert rt.daq.error_code == FAULT_NO_OUTPUT and int(rt.wm.get("daq.error")) == FAULT_NO_OUTPUT
    assert "no servo output for the servo period of frame" in rt.daq.fault_text
    assert not servo.error_code and int(rt.wm.get("servo.error")) == 0  # not the servo's flag
    powered.run_until(lambda: rt.status("updown") == S.ERROR, 2)
    powered.step(2)
    assert np.all(powered.dac_volts()[RATE_CHANNELS] == 0.0)
    servo.periodic["servo_control"] = real
    rt._build_schedule()
    powered.step(200)  # safe tasks finished
    code, text = powered.request(Request.ERROR_RESET, max_frames=600)
    assert code == Response.COMPLETE, text
    assert rt.all_status(S.SHUT_DOWN) and not rt.daq.no_output and int(rt.wm.get("daq.fault_bits")) == 0


def test_missed_frames_while_shut_down_are_only_counted(sim):
    rt = sim.rt
    sim.controller_steps = lambda f: 1 if f % 3 == 0 else 0
    sim.step(30)
    assert rt.all_status(S.SHUT_DOWN) and rt.missed_frames >= 18
    assert not rt.servo.fault


def test_max_missed_run_is_configurable():
    with SystemSimulator(frames=FrameConfig(max_missed_run=2)) as s:
        s.step(10)
        s.power_up(400)
        s.controller_steps = lambda f: 1 if f % 3 == 0 else 0
        s.step(60)
        assert s.rt.longest_missed_run == 2 and not s.rt.servo.fault
    with SystemSimulator(frames=FrameConfig(max_missed_run=1)) as s:
        s.step(10)
        s.power_up(400)
        s.controller_steps = lambda f: 1 if f % 3 == 0 else 0
        s.step(60)
        assert s.rt.servo.fault and s.rt.servo.error_code == ERR_MISSED
    with pytest.raises(Exception, match="max_missed_run"):
        FrameConfig(max_missed_run=-1).validate()


# --- the property: no stale rate reaches the arm, every refusal reaches Up/Down -------------
PATTERN = st.lists(st.tuples(st.sampled_from(["run", "skip", "stall", "burst"]), st.integers(1, 12)),
                   min_size=1, max_size=8)


def _steps(pattern) -> list[int]:
    out: list[int] = []
    for kind, n in pattern:
        if kind == "run":
            out += [1] * n
        elif kind == "skip":
            out += [0, 1] * n
        elif kind == "stall":
            out += [0] * min(n, 8) + [1]
        else:
            out += [2 + n % 2] * min(n, 3)
    return out


@settings(derandomize=True, max_examples=30, deadline=None,
          phases=(Phase.explicit, Phase.reuse, Phase.generate))  # no shrinking: each example is a whole run
@given(PATTERN)
def test_no_stale_rate_reaches_the_dac_and_every_refusal_reaches_updown(pattern):
    steps = _steps(pattern)
    with SystemSimulator() as s:
        s.step(10)
        s.power_up(400)
        _goal_yaw(s, 0.2)
        s.step(16)
        max_age = s.svc.policy.max_input_age_frames
        rt = s.rt
        reader = Client.attach(s.name)
        seen = []  # (service frame, age, command_status, rate volts non-zero)

        def check(info) -> None:
            snap = reader.read_inputs()
            seen.append((int(snap.frame), int(snap.command_input_age_frames), int(snap.command_status),
                         bool(np.any(s.dac_volts()[RATE_CHANNELS] != 0.0))))
        base = s.svc_frame()
        s.controller_steps = lambda f: steps[f - base - 1] if 0 < f - base <= len(steps) else 1
        s.rig.after_frame.append(check)
        try:
            s.step(len(steps) + 30)
        finally:
            reader.close()
        for frame, age, status, moving in seen:
            assert not (moving and age > max_age), f"frame {frame}: rate channels driven from inputs {age} old"
        bad = [fr for fr, _, status, _ in seen if status & (CMD_STALE | CMD_REFUSED | CMD_FOREIGN)]
        if bad:
            after = [r for r in rt.trace if r.frame >= bad[0]]  # controller frames from the refusal on
            n_err = next((i for i, r in enumerate(after) if r.layers[0].status == S.ERROR), None)
            assert n_err is not None, f"refusal at frame {bad[0]} never reached System Up/Down"
            assert n_err <= 6, f"{n_err} controller frames from the refusal to Up/Down ERROR"
            assert any("command refused/stale" in m.text for m in rt.messages.recent(1000, source="daq"))
            assert rt.daq.fault_bits & FAULT_COMMAND or rt.status("daq") == S.ERROR


# --- anti-windup -----------------------------------------------------------------------------
def _lag_step_overshoot(anti_windup: bool) -> float:
    """A lag compensator (K 40 1/s, tau_z 0.5 s, tau_p 2.5 s) on an integrating joint
    (q' = rate) with a 0.2 rad/s rate limit: a 1 rad step saturates for ~5 s."""
    T, lim = 1 / 160, 0.2
    c = LeadLag([40.0], [0.5], [2.5], T)
    q, peak = 0.0, 0.0
    for _ in range(int(20 / T)):
        e = np.array([1.0 - q])
        if anti_windup:
            u = c.step(e, lim)
        else:
            u = np.clip(c.step(e), -lim, lim)
        q += float(u[0]) * T
        peak = max(peak, q)
    return peak - 1.0


def test_lead_lag_anti_windup_recovers_from_a_long_saturation_without_overshoot():
    wound = _lag_step_overshoot(False)
    assert wound > 0.3  # the windup the unsaturated state causes
    assert _lag_step_overshoot(True) < 0.02


# --- controller statistics -----------------------------------------------------------------
def test_controller_stats_are_published_and_pfma_stats_shows_them(powered):
    from tools.cli import stats as stats_cli
    powered.controller_steps = lambda f: 0 if f % 50 == 0 else 1
    powered.step(400)
    rt = powered.rt
    assert rt.stats_published >= 2
    v = rt.wm.get_task_inputs(("runtime.frames", "runtime.missed_frames", "runtime.wake_latency_us"))
    assert int(v["runtime.frames"]) > 300 and int(v["runtime.missed_frames"]) >= 6
    with Client.attach(powered.name) as c:
        cs = c.read("controller_stats")
        assert cs.frames > 300 and cs.missed_frames >= 4 and cs.max_missed_run == 2  # published at 2 Hz
        assert cs.period_s == pytest.approx(1 / 320) and 300 < cs.rate_hz < 340
        d = stats_cli.collect(c)
    assert d["controller"]["missed_frames"] >= 4
    json.dumps(d)
    out = io.StringIO()
    with redirect_stdout(out):
        assert stats_cli.run(SimpleNamespace(buffer=powered.name, json=False)) == 0
    assert "controller controller" in out.getvalue() and "missed frames" in out.getvalue()


def test_pfma_stats_without_a_controller_says_so():
    from sim.rig import SimRig
    from tools.cli import stats as stats_cli
    with SimRig(prefix="pfma-sim-") as rig:
        rig.svc.loop.run(frames=5, freeze_gc=False)
        out = io.StringIO()
        with redirect_stdout(out):
            assert stats_cli.run(SimpleNamespace(buffer=rig.name, json=False)) == 0
        assert "no controller attached" in out.getvalue()
