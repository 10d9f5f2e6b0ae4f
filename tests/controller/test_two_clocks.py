"""Issue 33 item 5: the controller on its own frame clock (``FrameConfig.clock`` "own", the
report's board-2 frame interrupt) while the service keeps its own rates, in simulated time.
The two meet only in the Bit3 buffer: the controller reads the newest whole inputs, its
commands carry the service frame of the inputs they came from (the service's freshness rule
unchanged), and its missed frames are counted on its own clock."""

from __future__ import annotations

import numpy as np
import pytest

from controller.decision import Status
from controller.frames import FrameConfig, ScheduleError
from controller.servo import ERR_MISSED
from sim.system import SystemSimulator


def _own(profile: str = "overview", **kw) -> FrameConfig:
    return FrameConfig.profile(profile, clock="own", **kw)


@pytest.fixture(scope="module")
def powered():
    """The overview profile (268 Hz minor frames) on its own clock over a 320 Hz service,
    powered up, then 2 s of service frames with each frame's command age noted."""
    with SystemSimulator(frames=_own()) as sim:
        sim.step(10)
        sim.power_up(2000)
        ages, stamps = [], []

        def note(_info) -> None:
            s = sim.client.read_inputs()
            ages.append(int(s.frame) - int(s.command_inputs_frame))
            stamps.append(int(s.command_inputs_frame))
        sim.rig.after_frame.append(note)
        t0, f0, c0 = sim.clock.now(), sim.svc_frame(), sim.rt.stats()["frames"]
        sim.step(int(round(2.0 / sim.service_period_s)))
        yield {"sim": sim, "ages": np.array(ages), "stamps": np.array(stamps), "dt": sim.clock.now() - t0,
               "service_frames": sim.svc_frame() - f0, "controller_frames": sim.rt.stats()["frames"] - c0,
               "inputs": sim.client.read_inputs()}


def test_the_service_keeps_its_rates_while_the_controller_runs_its_own(powered):
    sim, dt = powered["sim"], powered["dt"]
    assert sim.svc.schedule.frame_rate_hz == 320.0
    assert powered["service_frames"] / dt == pytest.approx(320.0, abs=1.0)
    assert powered["controller_frames"] / dt == pytest.approx(268.0, abs=1.0)
    assert sim.period_s == pytest.approx(1 / 268.0)
    assert sim.rt.all_status(Status.START_UP_COMPLETE)


def test_commands_carry_service_frames_and_stay_fresh_without_a_missed_frame(powered):
    ages, stamps, s = powered["ages"], powered["stamps"], powered["inputs"]
    # the stamps are the service's frame numbers (not the controller's own, ~16 % fewer)
    assert stamps.max() <= int(s.frame) and stamps.max() > int(s.frame) - 5
    # a 134 Hz servo output is 2.4 service frames long: ages 1..3 (locked at 320 Hz: 1..2)
    assert ages.min() >= 1 and ages.max() <= 3
    assert (ages == 3).sum() > 0.1 * len(ages)
    assert int(s.stale_commands) == 0 and int(s.refused_commands) == 0
    st = powered["sim"].rt.stats()
    assert st["missed_frames"] == 0 and st["overruns"] == 0


def test_the_frames_of_the_own_clock_are_due_a_period_apart_on_the_simulated_clock(powered):
    rt = powered["sim"].rt
    due = rt.next_frame_due()
    assert due is not None and due > powered["sim"].clock.now()
    assert due - rt._epoch == pytest.approx((rt.prev_frame + 1) / 268.0)


def test_missed_frames_are_counted_on_the_own_clock_and_a_long_run_is_servo_fault_12():
    with SystemSimulator(frames=_own()) as sim:
        sim.step(10)
        sim.power_up(2000)
        k0 = sim.rt.prev_frame + 5
        sim.controller_steps = lambda k: 0 if k in (k0, k0 + 1) else 1  # two own frames skipped
        sim.step(40)
        st = sim.rt.stats()
        assert (st["missed_frames"], st["missed_events"], st["longest_missed_run"]) == (2, 1, 2)
        texts = [m.text for m in sim.rt.messages.recent(1000)]
        assert any(f"missed own frames {k0}..{k0 + 1} (2): caught up" in t for t in texts), texts[-5:]
        assert sim.rt.all_status(Status.START_UP_COMPLETE)  # two in a row are allowed
        k1 = sim.rt.prev_frame + 5
        sim.controller_steps = lambda k: 0 if k1 <= k < k1 + 3 else 1  # three: one too many
        sim.step(40)
        assert sim.rt.servo.error_code == ERR_MISSED
        assert any(f"controller missed own frames {k1}..{k1 + 2} (3 in a row > max_missed_run 2)" in m.text
                   for m in sim.rt.messages.recent(1000))
        assert sim.rt.status("updown") == Status.ERROR


def test_a_silent_service_does_not_stop_the_own_clock_and_is_named():
    """Locked, a controller waits for the service's next frame; on its own clock it goes on,
    and Data Acquisition names the inputs that stopped changing (fault 32)."""
    with SystemSimulator(frames=_own()) as sim:
        sim.step(10)
        sim.power_up(2000)
        n0 = sim.rt.stats()["frames"]
        sim.svc.loop.body = lambda info: None  # the service's frames do nothing: no new inputs
        sim.step(40)
        assert sim.rt.stats()["frames"] - n0 >= 30  # 40 x 3.125 ms at 268 Hz: 33 own frames
        assert any("unchanged for" in m.text for m in sim.rt.messages.recent(1000))
        assert sim.rt.status("daq") == Status.ERROR


def test_locked_stays_the_default_and_a_clock_is_checked():
    assert FrameConfig().clock == "locked" and FrameConfig.profile("overview").clock == "locked"
    with pytest.raises(ScheduleError, match="clock 'wall'"):
        FrameConfig(clock="wall").validate()


def test_two_simulators_on_their_own_clocks_give_identical_traces():
    def run() -> list:
        with SystemSimulator(frames=_own()) as sim:
            sim.step(10)
            sim.power_up(2000)
            sim.step(200)
            return [(r.frame, r.t_s, r.tasks, tuple(lt.status for lt in r.layers)) for r in sim.rt.trace]
    assert run() == run()
