"""Freshness that knows whose fault it was (issue 29 item 1, the service's part): a command's
age is counted in frames the service ran. A host stall of the service (its loop drops the
frames it did not run) does not make the controller's command stale: no newer inputs existed
for the controller to answer. A stall shorter than the watchdog rides through, named once; a
controller that really fell behind is still stale; a stall longer than the watchdog still
trips. Simulated time (``SimRig``): a stall is the clock advanced after a service frame."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bit3.layout import CMD_STALE, ServiceState
from sim.rig import SimRig
from tests.ioservice.test_command_path import Ctl, texts, volts

P = 1 / 320


class ClosedLoop(Ctl):
    """A controller one frame behind, as a live one is: each command computed from the
    inputs the service published the frame before last (age 2 when obeyed)."""

    def __call__(self, info) -> None:
        if not self.enabled:
            return
        newest = int(self.rig.reader.read_inputs().frame)
        self.client.write_commands(**self.cmd, inputs_frame=max(0, newest - 1))


def _armed_open_loop(rig, rate=0.1):
    ctl = ClosedLoop(rig)
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    ctl.cmd["joint_rate_rad_s"] = [rate, 0, 0, 0, 0, 0]
    rig.run(0.1)  # through the slew limit's ramp
    assert rig.reader.read_inputs().command_input_age_frames == 2
    return ctl


def _stall_after(rig, frames_s: dict[int, float], ctl=None):
    """After service frame k (relative to now), the host freezes for frames_s[k] seconds;
    with ``ctl``, the service wakes first after it (the controller writes again only after
    the service's next frame)."""
    start = [None]
    held = [False]

    def stall(info):
        if start[0] is None:
            start[0] = info.index
        if held[0]:
            held[0] = False
            ctl.enabled = True
        s = frames_s.get(info.index - start[0])
        if s:
            rig.clock.advance(s)
            if ctl is not None:
                ctl.enabled = False
                held[0] = True
    rig.after_frame.append(stall)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(stalls=st.lists(st.tuples(st.integers(5, 60), st.floats(0.0065, 0.0135)), min_size=1, max_size=4))
def test_service_stalls_shorter_than_the_watchdog_ride_through(stalls):
    """Random service stalls of 6.5-13.5 ms (1-3 dropped frames each; the controller writes
    again before the service's next frame, so the heartbeat stays fresh): never stale, never a
    trip, the rate driven throughout. Before, a 13 ms stall (3 dropped frames) made the
    command computed 2 frames before it "rates 0V: cmd inputs 5 fr old > 4", and the
    controller's Data Acquisition turned that into an ERROR of every layer."""
    rig = SimRig(prefix="pfma-stall-")
    try:
        _armed_open_loop(rig)
        plan: dict[int, float] = {}
        k = 0
        for gap, s in stalls:
            k += gap
            plan[k] = s
        _stall_after(rig, plan)
        rig.run((k + 20) * P + sum(plan.values()))
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.ARMED, texts(rig)
        assert s.stale_commands == 0 and not s.command_status & CMD_STALE, texts(rig)
        assert rig.svc._dropped_total >= len(plan)  # every stall dropped frames
        assert volts(rig)[0] == pytest.approx(0.1 / 0.04, abs=0.01)
        assert not any("cmd inputs" in t for t in texts(rig)), texts(rig)
    finally:
        rig.close()


def test_a_controller_that_fell_behind_is_still_stale(rig):
    """The service runs every frame; the controller's commands are 5 frames old: stale, as
    before (frames the service ran count)."""
    ctl = _armed_open_loop(rig)
    ctl.enabled = False
    old = Ctl(rig, joint_rate_rad_s=[0.1, 0, 0, 0, 0, 0])
    old.frames_old = 4  # computed from inputs 5 frames before the frame that obeys them
    rig.run_frames(4)
    s = rig.reader.read_inputs()
    assert s.command_status & CMD_STALE and s.command_input_age_frames == 5
    assert np.all(volts(rig)[:6] == 0.0)


def test_a_stall_longer_than_the_watchdog_still_trips_named(rig):
    ctl = _armed_open_loop(rig)
    _stall_after(rig, {10: 0.030}, ctl)
    rig.run(0.1)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT
    t = texts(rig)
    assert any(x.startswith("host stall: service did not run for 3") for x in t), t
    assert any("stale heartbeat" in x and "(stall 3" in x for x in t), t


# --- the controller's half: frames the service never published are not the controller's -----

@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(stall_s=st.floats(0.0135, 0.0145), at=st.integers(20, 120))
def test_a_powered_up_controller_rides_through_a_service_stall(stall_s, at):
    """The whole stack in the system simulator, powered up; the host freezes the service for
    13.5-14.5 ms (3-4 frames it drops, more than the controller's max_missed_run of 2; the
    controller runs right after each service frame, so its heartbeat stays fresh). The
    service measures the stall (in the simulator, without the live loop's between-frame
    ticks, a gap counts as a stall beyond HOST_STALL_S plus one period, 13.1 ms; live beyond
    10 ms), and the controller subtracts the frames it dropped. Before: 'rates 0V: cmd inputs 5 fr old > 4' at the service
    (Data Acquisition's fault 64) and the servo's fault 12 'controller missed service frames':
    every layer in ERROR. Now: every layer stays START UP COMPLETE, the missed frames are said
    as the service's, no stale command."""
    from controller.decision import Status
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        sim.step(20)
        done = []

        def stall(info):
            if not done and info.index >= at + 40:
                done.append(info.index)
                sim.clock.advance(stall_s)
        sim.rig.after_frame.insert(0, stall)
        sim.step(at + 120)
        assert done
        assert sim.rt.all_status(Status.START_UP_COMPLETE), [m.text for m in sim.rt.messages.recent(20)]
        s = sim.client.read_inputs()
        assert s.stale_commands == 0 and s.service_state == ServiceState.ARMED
        # the gap was counted as the service's (the WARNING that says so is rate-limited)
        assert sim.rt.service_dropped_frames >= 2 and sim.rt.missed_frames == sim.rt.service_dropped_frames


def test_a_controller_that_misses_frames_itself_is_still_faulted():
    """The service runs every frame; the controller skips 3 of them (its own stall): the
    servo's fault 12 as before."""
    from controller.servo import ERR_MISSED
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        sim.step(20)
        base = sim.svc_frame()
        sim.controller_steps = lambda f: 0 if base + 10 <= f < base + 13 else 1
        sim.step(40)
        assert int(sim.rt.wm.get("servo.error")) == ERR_MISSED or sim.rt.servo.error_code == ERR_MISSED
