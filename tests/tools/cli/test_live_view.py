"""``make run`` reads right (issue 17, item 8): the live view's formatting and the demo
controller's hold loop."""

from __future__ import annotations

import math

import pytest

from sim import demo
from bit3.layout import ServiceState, default_layout
from sim.rig import SimRig
from tools.stacks.service_views import live_header as _live_header, live_lines as _live_lines, live_message as _live_message, wrap_pi as _wrap_pi

JOINTS = default_layout().joint_names


@pytest.mark.parametrize("a, want", [(0.0, 0.0), (6.283, 6.283 - 2 * math.pi), (0.436, 0.436),
                                     (4.709, 4.709 - 2 * math.pi), (math.pi, math.pi),
                                     (-math.pi, math.pi), (3 * math.pi, math.pi), (-7.0, -7.0 + 2 * math.pi)])
def test_angles_are_wrapped_into_minus_pi_pi(a, want):
    w = _wrap_pi(a)
    assert -math.pi < w <= math.pi
    assert w == pytest.approx(want, abs=1e-12)


def test_header_names_the_joints_in_command_area_order():
    assert JOINTS == ("shoulder_pitch", "shoulder_yaw", "elbow_pitch", "wrist_yaw", "wrist_pitch",
                      "wrist_roll")
    head = _live_header(JOINTS)
    assert head[1].split()[3:] == ["SP", "SY", "EP", "WY", "WP", "WR", "deg"]
    assert "since the service started" in head[0]
    assert all(len(x) <= 80 for x in head)


def test_an_update_reads_right():
    q = [0.523, 0.460, 4.709, 1.047, 0.0, 6.283]  # resolver angles, 0..2 pi
    lines = _live_lines(12.3456, 3951, "ARMED", q, [-6.2, -13.3, 0.9], [160, 160, 320, 81], 370.4)
    assert len(lines) == 2 and all(len(x) <= 80 for x in lines)
    cols = lines[0].split()
    assert cols[:3] == ["12.35", "3951", "ARMED"]  # t since start, not the machine's uptime
    deg = [float(x) for x in cols[3:]]
    assert deg == pytest.approx([30.0, 26.4, -90.2, 60.0, 0.0, -0.0], abs=0.06)
    assert all(-180 < d <= 180 for d in deg)
    assert "F[N]   -6.2  -13.3   +0.9" in lines[1]
    assert "160/160/320/81 Hz" in lines[1] and "work p50 370 us" in lines[1]
    # the columns of the update line up under the header's
    head = _live_header(JOINTS)[1]
    for label, value in zip(head.split()[3:9], cols[3:]):
        assert head.index(label) + len(label) == lines[0].index(value) + len(value)


def test_the_widest_update_stays_within_80_columns():
    for state in ServiceState:
        lines = _live_lines(99999.99, 9_999_999, state.name, [-3.14159] * 6, [-999.9, -999.9, -999.9],
                            [160, 160, 320, 80], float("nan"))
        assert all(len(x) <= 80 for x in lines), lines
        assert "work p50 --" in lines[1]


def test_messages_keep_their_whole_text_and_time_since_start():
    class M:
        t_s, queue, seq, code, source = 7912.5, "service_messages", 3, 12, "service"
        severity = ServiceState.ARMED  # anything with a .name
        text = "x" * 55 + "!"  # a full 56-byte queue entry
    out = _live_message(M, t_start_s=7900.0)
    assert out.endswith("x" * 55 + "!")
    assert "12.50" in out and "7912" not in out


def test_demo_hold_rate_is_unwrapped_and_clipped():
    assert demo.hold_rate(0.52, 0.52) == 0.0
    assert demo.hold_rate(0.50, 0.52) == pytest.approx(0.04)
    assert demo.hold_rate(6.28, 0.01) == pytest.approx(2.0 * (0.01 - 6.28 + 2 * math.pi))  # across 0/2 pi
    assert demo.hold_rate(0.0, 0.52) == demo.HOLD_MAX_RATE_RAD_S
    assert demo.hold_rate(1.0, 0.52) == -demo.HOLD_MAX_RATE_RAD_S
    assert demo.frame_rates(0.2, JOINTS, [0.0] * 6, [1.0] * 6) == [0.0] * 6  # arming: rates 0
    assert demo.HOLD_MAX_RATE_RAD_S < 0.4


def test_demo_holds_the_shoulder_pitch_in_simulated_time():
    """The demo's per-frame command on the simulated rack: after 8 s the joints it does not
    swing are still at their start pose (without the hold the shoulder pitch sags to ~0)."""
    with SimRig(prefix="pfma-test-") as rig:
        c = rig.controller("demo-test")
        joints = list(c.layout.joint_names)
        state = {"q0": None, "t0": None, "max_rate": 0.0}

        def step(info) -> None:
            snap = rig.reader.read_inputs()
            q = demo.joint_angles(snap, joints)
            if state["q0"] is None:
                state["q0"], state["t0"] = q, rig.clock.now()
                c.write_commands(joint_rate_rad_s=[0.0] * len(joints),
                                 current_limit_a=demo.DEMO_CURRENT_LIMIT_A, arm_request=1,
                                 rearm_counter=int(c.command["rearm_counter"]) + 1,
                                 inputs_frame=snap.frame)
                return
            rates = demo.frame_rates(rig.clock.now() - state["t0"], joints, q, state["q0"])
            state["max_rate"] = max([state["max_rate"]] + [abs(r) for j, r in zip(joints, rates)
                                                            if j not in demo.SWING])
            c.write_commands(joint_rate_rad_s=rates, current_limit_a=demo.DEMO_CURRENT_LIMIT_A,
                             arm_request=1, inputs_frame=snap.frame)

        rig.after_frame.append(step)
        rig.run(8.0)
        snap = rig.reader.read_inputs()
        assert ServiceState(snap.service_state) is ServiceState.ARMED
        q = demo.joint_angles(snap, joints)
        for j, qi, q0i in zip(joints, q, state["q0"]):
            if j not in demo.SWING:
                assert abs(math.remainder(qi - q0i, 2 * math.pi)) < 0.02, (j, qi, q0i)
        assert state["max_rate"] <= demo.HOLD_MAX_RATE_RAD_S
