"""The service keeps the first cause of its trip episode (issue 29 item 3): the first trip
or refusal since the outputs were last armed is in ``OutputGuard.first_trip`` and the Bit3
inputs area (``first_trip_code``, ``first_trip_t_s``, ``first_trip_text``); the notices after
it do not replace it; arming again clears it. Simulated time."""

import numpy as np

from bit3.layout import FIRST_TRIP_TEXT_BYTES, ServiceState


def _controller(rig):
    ctl = rig.controller()
    state = {"rates": [0.0] * 6, "rearm": 0, "alive": True}

    def command(info):
        if state["alive"]:
            ctl.write_commands(joint_rate_rad_s=state["rates"], current_limit_a=(5, 5, 5, 2.5, 2.5, 2.5, 0),
                               arm_request=1, rearm_counter=state["rearm"])
    rig.on_frame.append(command)
    return ctl, state


def test_the_first_trip_stays_through_later_notices_and_arming_clears_it(rig):
    ctl, state = _controller(rig)
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.ARMED
    assert (s.first_trip_code, s.text("first_trip_text")) == (0, "")
    state["alive"] = False  # the controller dies: the watchdog trips
    rig.run(0.1)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT
    code, reason, t = rig.svc.guard.first_trip
    assert "stale heartbeat" in reason
    assert (s.first_trip_code, s.text("first_trip_text"), s.first_trip_t_s) == (code, reason, t)
    # a board failure after it: posted, but the episode's first cause stays
    rig.world.bus["rtd1"].inject("no_answer")
    rig.run(0.1)
    assert any("rtd1" in m.text for m in rig.reader.messages())
    assert rig.reader.read_inputs().text("first_trip_text") == reason


def test_a_refusal_is_a_first_cause_and_a_new_arm_clears_it(rig):
    ctl, state = _controller(rig)
    rig.run(0.05)
    joints = list(rig.reader.layout.joint_names)
    state["rates"][joints.index("wrist_roll")] = 1e3  # beyond its limit: refused, outputs safe
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.SAFE
    text = s.text("first_trip_text")
    assert text.startswith("refused") and text == rig.svc.guard.first_trip[1][:FIRST_TRIP_TEXT_BYTES]
    state["rates"] = [0.0] * 6
    state["rearm"] += 1  # re-armed: the episode is over
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.ARMED
    assert (s.first_trip_code, s.text("first_trip_text")) == (0, "") and rig.svc.guard.first_trip is None
    assert np.all(s.record["first_trip_text"] == 0)


def test_pfma_stats_names_the_first_trip(rig):
    from tools.cli import stats as stats_cli
    ctl, state = _controller(rig)
    rig.run(0.05)
    d = stats_cli.collect(rig.reader)
    assert d["first_trip"] is None
    assert stats_cli.format_first_causes(d) == ["service first trip since the last arm: none"]
    state["alive"] = False
    rig.run(0.1)
    d = stats_cli.collect(rig.reader)
    code, reason, t = rig.svc.guard.first_trip
    assert d["first_trip"] == {"code": code, "t_s": t, "text": reason}
    d["controller_first_cause"] = "daq: fault 1: shoulder_pitch resolver status 0x1"
    assert stats_cli.format_first_causes(d) == [
        f"service first trip since the last arm: {reason} (code {code}, t={t:.1f} s)",
        "controller first cause of the ERROR: daq: fault 1: shoulder_pitch resolver status 0x1"]
