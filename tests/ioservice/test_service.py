"""The data-acquisition service on the simulated rack, in simulated time."""

import numpy as np
import pytest

from bit3.layout import ServiceState
from ioservice.service import DAC_FORCED_SAFE, FAULT_INPUTS, FAULT_WATCHDOG

P = 1 / 320


def test_inputs_refresh_at_documented_rates(rig):
    rig.run(2.0)
    rig.svc.publish_stats()
    st = rig.reader.read_stats()
    rate = {n: st.device_rate_hz[rig.reader.layout.slot("device", n)] for n in ("rtd", "adc", "dac", "ft", "crl")}
    assert rate["rtd"] == pytest.approx(160, rel=0.01)
    assert rate["adc"] == pytest.approx(160, rel=0.01)
    assert rate["dac"] == pytest.approx(320, rel=0.01)
    assert rate["ft"] == pytest.approx(80, rel=0.01)
    assert rate["crl"] == pytest.approx(80, rel=0.01)
    s = rig.reader.read_inputs()
    # the resolver sample matches the simulated arm (wrapped to 0..2 pi, 14-bit)
    truth = rig.world.sim.resolver_angles_rad()
    got = np.array([s.value(n) for n in ("shoulder_yaw_angle", "shoulder_pitch_angle", "elbow_pitch_angle",
                                         "wrist_pitch_angle", "wrist_yaw_angle", "wrist_roll_angle")])
    assert np.allclose(got, truth, atol=2 * 2 * np.pi / 16384)
    # F/T: the tool's weight (1.5 kg) in the sensor frame, through the MVME400 at 19200 baud
    assert np.linalg.norm(s.ft_force_n) == pytest.approx(1.5 * 9.81, rel=0.05)
    link = rig.reader.layout.slot("link", "ft_sensor")
    assert s.link_records[link] > 200 and s.link_bad[link] <= 2
    assert s.t_ft_s > s.t_s - 0.03  # fresh
    # the CRL link: its good-frame rate (the master sends a frame every 20 ms, pfma-model
    # 8.6; the service samples the latest at 80 Hz) and the last good frame's age
    crl = rig.reader.layout.slot("link", "crl_hand_controller")
    assert s.link_rate_hz[crl] == pytest.approx(50, rel=0.02)
    assert 0.0 <= s.link_age_s[crl] < 0.020 + 0.0125  # a frame period + one 80 Hz task period


def test_outputs_start_disconnected_and_zero(rig):
    rig.run(0.1)
    dac = rig.world.bus["dac"]
    assert not dac.outputs_connected
    assert np.all(dac.output_volts_all() == 0.0)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.SAFE and not s.outputs_enabled


def _arm(rig, rates=None, limits=(5, 5, 5, 2.5, 2.5, 2.5, 0)):
    ctl = rig.controller()
    state = {"rates": [0.0] * 6}

    def command(info):
        ctl.write_commands(joint_rate_rad_s=state["rates"], current_limit_a=limits, arm_request=1)
    rig.on_frame.append(command)
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    return ctl, state, command


def test_armed_rate_command_moves_the_joint(rig):
    ctl, state, _ = _arm(rig)
    joints = list(rig.reader.layout.joint_names)
    state["rates"][joints.index("shoulder_yaw")] = 0.1
    q0 = rig.world.sim.true_state().q[0]
    rig.run(1.0)
    q1 = rig.world.sim.true_state().q[0]
    assert 0.07 < q1 - q0 < 0.11  # ~0.1 rad/s after the rate loop's rise
    dac = rig.world.bus["dac"]
    ch = rig.svc.rack.channel("shoulder_yaw_command").channel
    assert dac.output_volts(ch) == pytest.approx(0.1 * 25, abs=0.01)  # K_w = 25 V per rad/s
    s = rig.reader.read_inputs()
    assert s.value("shoulder_yaw_rate") == pytest.approx(0.1, rel=0.1)  # tach via the ADC


def test_dead_controller_makes_outputs_safe_within_watchdog_plus_one_frame(rig):
    ctl, state, command = _arm(rig)
    joints = list(rig.reader.layout.joint_names)
    state["rates"][joints.index("wrist_roll")] = 0.5
    rig.run(0.2)
    dac = rig.world.bus["dac"]
    ch = rig.svc.rack.channel("wrist_roll_command").channel
    assert dac.output_volts(ch) != 0
    t_dead = rig.clock.now()
    rig.on_frame.remove(command)  # the controller dies: no more heartbeats
    times = []

    def watch(info):
        if not times and np.all(dac.output_volts_all() == 0.0):
            times.append(rig.clock.now())
    rig.on_frame.append(watch)
    rig.run(0.1)
    assert times, "outputs never went to 0 V"
    # the service writes 0 V in the frame it detects the stale heartbeat; `watch` sees it
    # at the start of the next frame
    assert times[0] - t_dead <= 0.015 + 2 * P
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_WATCHDOG
    assert np.all(s.dac_status[:16] == DAC_FORCED_SAFE)
    assert any("stale" in m.text for m in rig.reader.messages())
    # heartbeats come back with the old request: stays safe; nothing jumps to the old setpoint
    rig.on_frame.append(command)
    rig.run(0.1)
    assert rig.reader.read_inputs().service_state == ServiceState.FAULT
    assert np.all(dac.output_volts_all() == 0.0)


def test_stop_disconnects_outputs(rig):
    _arm(rig)
    rig.svc.stop()
    dac = rig.world.bus["dac"]
    assert not dac.outputs_connected and np.all(dac.output_volts_all() == 0.0)
    assert rig.reader.read_inputs().service_state == ServiceState.STOPPED


def test_resolver_board_failure_is_counted_then_trips(rig):
    _arm(rig)
    rig.world.bus["rtd1"].inject("no_answer")
    rig.run(0.05)
    s = rig.reader.read_inputs()
    slot = rig.reader.layout.slot("board", "rtd1")
    assert s.board_errors[slot] >= 3 and s.board_last_error_addr[slot] == 0x0100
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_INPUTS
    assert any("rtd1" in m.text for m in rig.reader.messages())


def test_user_inputs_and_matrix_route(rig):
    ctl = rig.controller()
    rig.world.set_user_inputs(0xA55A)
    ctl.write_commands(matrix_route=0b0110)
    rig.run(0.1)
    s = rig.reader.read_inputs()
    assert s.pio_user_inputs == 0xA55A
    assert s.matrix_route == 0b0110
    assert rig.world.bus["pio_video"].route == 0b0110


def test_cae_stick_reaches_hand_controller_slot(rig):
    rig.world.set_cae([5.0, 0, 0, 0, 0, 0], (True, False, False))
    rig.run(0.1)
    s = rig.reader.read_inputs()
    i = rig.reader.layout.slot("hc", "cae")
    assert s.hc_valid[i] and s.hc_deadman[i]
    assert s.hc_axes[i][2] > 0.1  # up/down -> z


def test_crl_force_reflection_reaches_the_hand_controller_only_while_armed(rig):
    """The command area's CRL force goes out over MVME400 port B (queued, between frames)."""
    crl = rig.world.crl
    ctl = rig.controller()
    ctl.write_commands(crl_reflect_force_n=[10.0, -5.0, 0.0], crl_reflect_enable=1)
    rig.run(0.2)  # not armed: the service sends zero, disabled frames
    assert crl.received and not crl.received[-1].frame.enabled
    assert list(crl.displayed_force_n) == [0.0, 0.0, 0.0]
    rig.on_frame.append(lambda info: ctl.write_commands(current_limit_a=[5, 5, 5, 2.5, 2.5, 2.5, 0],
                                                        arm_request=1))
    crl.deadman = True  # the CRL driver sends forces only while its deadman is held
    rig.run(0.3)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    assert crl.received[-1].frame.enabled
    assert np.allclose(crl.displayed_force_n, [10.0, -5.0, 0.0], atol=0.01)


def test_ft_start_dialogue_garbled_by_lost_characters_is_retried():
    """Characters lost on the 3-deep MVME400 FIFO during the F/T start-up dialogue (a
    loaded host that polled the line late) garble a reply; the service asks again and the
    sensor streams at 80 Hz, instead of running without F/T."""
    from fakes.world import FakeWorld
    from bit3.client import Client
    from ioservice.service import IoService
    from bit3.buffer import Bit3Buffer
    from ioservice.ticking import TickingClock
    from pfma.clock import SimClock
    import uuid

    name = "pfma-test-" + uuid.uuid4().hex[:8]
    clock = SimClock()
    world = FakeWorld(clock=clock)
    tclock = TickingClock(clock)
    tclock.hooks.append(world.tick)
    world.ft.drop_next(2, after_bytes=1)  # inside the echo of the first command
    buf = Bit3Buffer.create(name)
    svc = reader = None
    try:
        svc = IoService(world.rack_config, world.bus, buf, tclock)
        tclock.hooks.append(svc.serial_tick)
        assert svc.init_errors == []
        reader = Client.attach(name, clock_now=clock.now)
        assert any(m.code == 122 and "attempts" in m.text for m in reader.messages())
        svc.loop.run(frames=640, freeze_gc=False)
        svc.publish_stats()
        st = reader.read_stats()
        assert st.device_rate_hz[reader.layout.slot("device", "ft")] == pytest.approx(80, rel=0.01)
    finally:
        if reader is not None:
            reader.close()
        if svc is not None:
            svc.stop()
        buf.close()
        Bit3Buffer.unlink(name)


@pytest.mark.parametrize("drain_inside_frame", [True, False])
def test_slow_input_scans_do_not_overrun_the_serial_fifos(rig, monkeypatch, drain_inside_frame):
    """A host that makes the resolver board read take 0.6 ms and the 32-channel ADC scan 1.0 ms
    (a busy VM) must not cost F/T records: the 3-deep MVME400 FIFO fills in 1.56 ms at 19200
    baud, so the service drains it between the tasks of a long frame. Without those drains
    (the False case) characters are lost in every record and the link never re-syncs.
    Each board reading is one block transfer (the resolver board's 4 angles + STATUS, the
    ADC's SCAN buffer after its scan): the slow host is charged on those blocks."""
    slow = {"adc": 1.0e-3, "rtd1": 0.6e-3}  # per block read: one per ADC scan, one per resolver read
    accesses = dict.fromkeys(slow, 0)
    for name, cost in slow.items():
        board = rig.world.bus[name]
        inner = board.read_block16

        def slow_block(offset, n, tick=None, _inner=inner, _name=name, _cost=cost):
            rig.clock.advance(_cost)
            accesses[_name] += 1
            return _inner(offset, n, tick)

        monkeypatch.setattr(board, "read_block16", slow_block)
    if not drain_inside_frame:
        monkeypatch.setattr(rig.svc, "_drain_if_due", lambda: None)
    rig.run(2.0)
    assert accesses == {"adc": 320, "rtd1": 320}  # 2 s of scans at 160 Hz, all slowed
    s = rig.reader.read_inputs()
    link = rig.reader.layout.slot("link", "ft_sensor")
    if drain_inside_frame:
        assert s.link_records[link] >= 150 and s.link_bad[link] == 0
    else:
        assert s.link_records[link] < 10 and s.link_bad[link] >= 1


@pytest.mark.parametrize("retry", [True, False])
def test_a_missed_ft_slot_is_tried_again_in_the_next_frames(rig, monkeypatch, retry):
    """Characters lost on the F/T line (one overrun) cost only the record they hit: the
    decoder re-syncs on the first whole valid record, and the MVME400 line is decoded in the
    drain hook as soon as a record is complete, so every 80 Hz period still publishes a
    record, with the slot retry (True) and without it (False: the retry is now a second
    line of defence, e.g. for a line the drain hook does not decode)."""
    import ioservice.service as service
    if not retry:
        monkeypatch.setattr(service, "FT_RETRY_FRAMES", 0)
    rig.run(0.5)
    dev = rig.svc._devices["ft"]
    n0 = dev.samples
    losses = 0
    for k in range(10):  # one lost character every 0.2 s, at a different phase each time
        rig.world.ft.drop_next(1, after_bytes=7 + 3 * k)
        rig.run(0.2)
        losses += 1
    published = dev.samples - n0
    link = rig.reader.layout.slot("link", "ft_sensor")
    assert rig.reader.read_inputs().link_bad[link] >= losses  # every loss cost a record
    assert rig.world.ft.bytes_dropped == losses
    assert published >= 160 - 1  # 2 s at 80 Hz


def _stats_calls(rig, monkeypatch):
    """Record, for every publish_stats call, the loop's frame and whether a frame was running."""
    calls, in_frame = [], [False]
    body, publish = rig.svc.loop.body, rig.svc.publish_stats

    def frame(info):
        in_frame[0] = True
        try:
            body(info)
        finally:
            in_frame[0] = False

    def recorded():
        calls.append((rig.svc.loop.k, in_frame[0]))
        return publish()
    rig.svc.loop.body = frame
    monkeypatch.setattr(rig.svc, "publish_stats", recorded)
    return calls


def test_statistics_are_computed_between_frames_when_the_service_runs(rig, monkeypatch):
    """``IoService.run`` publishes the statistics a frame asks for (every 160th) in the sleep
    after it, so their ~1 ms percentile work is not a periodic spike in the frame work."""
    calls = _stats_calls(rig, monkeypatch)
    rig.svc.run(frames=400)
    # loop.k is the next frame's number in the sleep after frames 0, 160 and 320
    between = [k for k, inside in calls[:-1] if not inside]  # the last call is stop()'s
    assert between == [1, 161, 321] and not any(inside for _, inside in calls)
    st = rig.reader.read_stats()
    assert st.frame == 400 and st.frames == 400  # stop() published the final figures


def test_statistics_fall_back_into_a_frame_when_there_is_no_idle_time(rig, monkeypatch):
    """Hooks run only in sleeps of at least a tick; with ticks longer than the frame they never
    run, and the frame publishes the statistics itself STATS_MAX_DEFER_FRAMES frames late."""
    from ioservice.service import STATS_MAX_DEFER_FRAMES
    rig.tclock.tick_s = 1.0
    calls = _stats_calls(rig, monkeypatch)
    rig.svc.run(frames=400)
    d = STATS_MAX_DEFER_FRAMES
    assert [k for k, inside in calls if inside] == [d, 160 + d, 320 + d]


def test_a_dead_controller_is_caught_between_frames_within_the_watchdog_plus_a_tick(rig, monkeypatch):
    """Under ``IoService.run`` the heartbeat is also checked in the sleeps between frames, so
    outputs go to 0 V within the watchdog plus one hook tick of the last heartbeat the service
    saw, not at the next frame. The controller here beats from the clock's ticks (between
    frames) and dies 0.3 s after arming; the kill time is chosen so the watchdog expires
    early in a frame period, where waiting for the next frame would cost ~2 ms more."""
    ctl = rig.controller()
    ctl.write_commands(arm_request=1, current_limit_a=[1.0] * len(ctl.command["current_limit_a"]))
    t0 = rig.clock.now()
    t_kill = t0 + 100 * P + 0.0016  # the last beat is the first tick of frame 100's period
    beats = []

    def controller(now):
        if now < t_kill:
            ctl.publish_commands()
            beats.append(now)
    rig.tclock.hooks.insert(0, controller)
    zeros = []
    write = rig.svc._write_dac

    def recorded(volts, status, eng):
        if rig.clock.now() > t_kill and not zeros and not any(volts):
            zeros.append(rig.clock.now())
        return write(volts, status, eng)
    monkeypatch.setattr(rig.svc, "_write_dac", recorded)
    rig.svc.run(frames=200)
    t_beat = beats[-1]
    next_frame = t0 + P * (int((t_beat + 0.015 - t0) / P) + 1)
    assert next_frame - (t_beat + 0.015) > rig.tclock.tick_s + 0.0005  # the case is telling
    assert zeros and 0.015 < zeros[0] - t_beat <= 0.015 + rig.tclock.tick_s + 0.0005
    assert rig.svc.state == ServiceState.FAULT or rig.svc.state == ServiceState.STOPPED
    assert any("between frames" in m.text for m in rig.reader.messages())
    assert np.all(rig.world.bus["dac"].output_volts_all() == 0.0)
