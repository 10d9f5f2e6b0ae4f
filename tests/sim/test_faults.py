"""sim.faults and sim.scenario: every fault kind seen by the real service through registers
and bytes (its published board, channel and link status), and recovering when cleared;
the new fake hooks; scenario files. All in simulated time on a SimRig (deterministic)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bit3.layout import (BOARD_FAULT, BOARD_INIT, BOARD_OK, CHANNEL_BUS_ERROR, LINK_FAULT, LINK_STALE,
                         LINK_SYNCED)
from fakes.board import NoAnswer
from fakes.ft_sensor import FakeFtController
from pfma.errors import BusError, ConfigError
from sim.faults import KINDS, FaultSet, fault_targets, kinds_help, parse_fault, targets_help
from sim.rig import SimRig
from sim.scenario import ScenarioRunner, load_scenario, parse_scenario

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"


@pytest.fixture
def rig():
    with SimRig(prefix="pfma-faults-") as r:
        r.run(0.5)  # links synced, every board sampled
        yield r


def inputs(rig):
    """A copy of the service's published inputs (the reader refreshes its record in place)."""
    from bit3.client import Snapshot
    s = rig.reader.read_inputs()
    return Snapshot(s.record.copy(), s.area, s.layout, s.seq)


def board(rig, s, name):
    i = rig.layout.slot("board", name)
    return int(s.board_status[i]), int(s.board_errors[i])


def link(rig, s, name):
    i = rig.layout.slot("link", name)
    return int(s.link_status[i]), int(s.link_bad[i])


def rtd(rig, s, signal):
    i = rig.layout.slot("rtd", signal)
    return int(s.rtd_status[i]), int(s.rtd_counts[i])


def adc_volts(rig, s, signal):
    return float(s.adc_volts[rig.layout.slot("adc", signal)])


def cycle(rig, spec, seconds=0.5):
    """(inputs before, with the fault, and after clearing it)."""
    fs = FaultSet(rig.world)
    before = inputs(rig)
    fs.inject(spec)
    rig.run(seconds)
    during = inputs(rig)
    fs.clear(spec)
    rig.run(seconds)
    return before, during, inputs(rig)


# -- the grammar ----------------------------------------------------------------------------
def test_every_kind_is_listed_with_its_meaning():
    lines = kinds_help()
    assert len(lines) == len(KINDS)
    for kind, line in zip(KINDS, lines):
        assert line.startswith(kind) and len(line.split("  ", 1)[1].strip()) > 10


@pytest.mark.parametrize("spec, says", [
    ("bus-eror:adc", "did you mean bus-error"),
    ("bus-error:adcc", "did you mean adc"),
    ("bus-error:adc@CRS", "did you mean CSR"),
    ("bus-error:adc@0x999", "outside adc's 0x100-byte window"),
    ("stuck-bit:sio@0x09:1=1", "boards with one: rtd1, rtd2, dac, adc"),
    ("stuck-bit:adc@CSR:16=1", "bit 16 outside 0..15"),
    ("stuck-bit:adc@CSR:3=2", "0 or 1"),
    ("stuck-bit:adc", "expected stuck-bit:BOARD@REG:BIT=0|1"),
    ("adc-busy-stuck:rtd1", "not an A/D board"),
    ("resolver-los:shoulder_pich_angle", "did you mean shoulder_pitch_angle"),
    ("resolver-los:cae_yaw", "not a resolver signal"),
    ("resolver-los:wrist_yaw_angle:melt", "freeze or zero"),
    ("serial-drop:ft_sensr", "did you mean ft_sensor"),
    ("serial-stall", "needs a line"),
    ("ft-unplugged:now", "takes no argument"),
    ("tach-reversed:knee", "no joint 'knee'"),
    ("adc-dead:adc_spare_27=lots", "not a number"),
    ("adc-dead:adc_spare_2=1", "did you mean adc_spare_2"),
    ("", "empty"),
])
def test_bad_specs_are_config_errors_naming_the_closest(spec, says):
    with pytest.raises(ConfigError, match="fault") as e:
        parse_fault(spec)
    assert says in str(e.value)


def test_the_dac_control_word_is_no_fault_target_and_is_not_listed_as_one():
    """Issue 32: ``stuck-bit:dac@CTRL:8=1`` said "register 'CTRL' not found" while the error
    for an unknown name listed CTRL. CTRL overlays DAC[0]'s word (the board tells them apart
    by D15 of the word written), so a fault on an address cannot name it: said so, and
    listed nowhere."""
    for spec in ("stuck-bit:dac@CTRL:8=1", "bus-error:dac@CTRL"):
        with pytest.raises(ConfigError) as e:
            parse_fault(spec)
        assert "dac CTRL shares its address (+0x00) with DAC[0]" in str(e.value)
        assert "registers: DAC[0..15]" in str(e.value) and "not found" not in str(e.value)
    with pytest.raises(ConfigError) as e:
        parse_fault("stuck-bit:dac@FOO:8=1")
    assert "registers: DAC[0..15]" in str(e.value) and "CTRL" not in str(e.value)
    assert fault_targets()["stuck-bit"]["REG"]["dac"] == ["DAC[0..15]"]
    assert parse_fault("stuck-bit:dac@DAC[3]:11=1").description == "dac DAC[3] bit 11 stuck at 1"


def test_every_listed_target_is_accepted_by_its_parser():
    """``pfma fault list``'s targets come from the parsers' own lists: each one parses."""
    examples = {"adc-dead": "{}=1.5", "load": "{}=10", "panel-off:pwm": "pwm:{}", "panel-off:brake": "brake:{}"}
    targets = fault_targets()
    assert set(targets) == set(KINDS)
    n = 0
    for kind, args in targets.items():
        stem = kind.partition(":")[0]
        if kind == "bus-error":
            assert set(args["REG"]) == set(args["BOARD"])
            specs = [f"bus-error:{b}" for b in args["BOARD"]]
            specs += [f"bus-error:{b}@{r.replace('[0..', '[')}" for b, regs in args["REG"].items() for r in regs]
        elif kind == "stuck-bit":  # an array as its last element: DAC[0..15] -> DAC[15]
            assert set(args["REG"]) == set(args["BOARD"])
            specs = [f"stuck-bit:{b}@{r.replace('[0..', '[')}:3=1" for b, regs in args["REG"].items() for r in regs]
        elif "SWITCH" in args:
            assert args["SWITCH"] == ["28v", "15v", "pwm", "brake"]
            specs = [kind]
        elif not args:
            specs = [kind]
        else:
            (names,) = args.values()
            assert names, kind
            specs = [f"{stem}:{examples.get(kind, '{}').format(x)}" for x in names]
        for spec in specs:
            parse_fault(spec)
            n += 1
    assert n > 100
    # and a name outside a list is refused: the gripper has no brake, sio no stuck bit
    assert "gripper" in targets["amp-off"]["JOINT"] and "gripper" not in targets["brake-held"]["JOINT"]
    with pytest.raises(ConfigError, match="no brake"):
        parse_fault("brake-held:gripper")
    assert "sio" in targets["bus-error"]["BOARD"] and "sio" not in targets["stuck-bit"]["BOARD"]


def test_the_targets_section_is_wrapped_and_names_each_list_once():
    lines = targets_help()
    assert lines[0] == "targets in rack pfma (REG may also be a byte offset, e.g. 0x04):"
    assert all(len(line) <= 100 for line in lines)
    text = "\n".join(lines)
    assert "  BOARD (stuck-bit): rtd1, rtd2, dac, adc" in lines
    assert "  REG of dac (bus-error, stuck-bit): DAC[0..15]" in lines
    assert "  REG of rtd1, rtd2 (bus-error, stuck-bit): CH0, CH1, CH2, CH3, STATUS, CONTROL" in lines
    assert "  LINE (serial-noise, serial-drop, serial-stall, serial-disconnect): ft_sensor, crl_hand_controller" \
        in lines
    assert "  SWITCH (panel-off): 28v, 15v, pwm, brake" in lines
    assert text.count("cae_up_down") == 1 and "CTRL" not in text.replace("SIO_CTRL", "")


def test_same_fault_twice_refused_and_clearing_what_is_not_active_names_the_active(rig):
    fs = FaultSet(rig.world)
    fs.inject("resolver-los:wrist_yaw_angle")
    with pytest.raises(ConfigError, match="already active"):
        fs.inject("resolver-los:wrist_yaw_angle:zero")  # the same channel: the same fault
    with pytest.raises(ConfigError, match="not active; active: resolver-los:wrist_yaw_angle"):
        fs.clear("resolver-los:shoulder_pitch_angle")
    assert [a["spec"] for a in fs.listing()] == ["resolver-los:wrist_yaw_angle"]
    assert [f.spec for f in fs.clear("all")] == ["resolver-los:wrist_yaw_angle"] and fs.active == []


# -- each kind through the service ---------------------------------------------------------------
@pytest.mark.parametrize("spec, name", [("bus-error:adc", "adc"), ("adc-busy-stuck", "adc"),
                                        ("adc-busy-stuck:adc", "adc"), ("bus-error:rtd1", "rtd1"),
                                        ("bus-error:rtd1@CH1", "rtd1")])
def test_board_faults_make_the_board_fault_and_count_errors_then_recover(rig, spec, name):
    before, during, after = cycle(rig, spec)
    assert board(rig, before, name) == (BOARD_OK | BOARD_INIT, 0)
    st, errors = board(rig, during, name)
    assert st & BOARD_FAULT and errors > 0
    st2, errors2 = board(rig, after, name)
    assert st2 == BOARD_OK | BOARD_INIT
    rig.run(0.5)
    assert board(rig, inputs(rig), name)[1] == errors2  # no more errors once cleared
    if name == "rtd1":
        assert rtd(rig, during, "wrist_yaw_angle")[0] & CHANNEL_BUS_ERROR
        assert rtd(rig, after, "wrist_yaw_angle")[0] == 0


def test_bus_error_at_one_register_only_that_word_fails():
    """The new FakeBoard hook: ``no_answer`` with ``offset`` silences one 16-bit word."""
    with SimRig(prefix="pfma-faults-") as r:
        rtd1 = r.world.bus["rtd1"]
        base = r.world.bus.bases["rtd1"]
        f = parse_fault("bus-error:rtd1@CH1")
        f.apply(r.world)
        r.world.bus.read16(base + 0)  # CH0 answers
        with pytest.raises(BusError, match="rtd1 CH1 at A16 0x0102: register does not answer"):
            r.world.bus.read16(base + 2)
        with pytest.raises(NoAnswer):
            rtd1.read16(2)
        f.clear(r.world)
        r.world.bus.read16(base + 2)


def test_stuck_bit_on_a_resolver_word_forces_that_bit_of_the_published_counts(rig):
    true = rig.world.bus["rtd1"].counts(0)  # elbow_pitch_angle is rtd1 CH0
    value = 1 - (true >> 12 & 1)  # the opposite of what the converter reads
    before, during, after = cycle(rig, f"stuck-bit:rtd1@CH0:12={value}")
    _, counts = rtd(rig, during, "elbow_pitch_angle")
    assert counts >> 12 & 1 == value and counts != rig.world.bus["rtd1"].counts(0)
    assert rtd(rig, after, "elbow_pitch_angle")[1] >> 12 & 1 == 1 - value


def test_stuck_bit_on_an_adc_scan_word_moves_the_published_volts(rig):
    # a spare input at 0 V reads code 0x800 (offset binary): bit 11 stuck at 0 reads -10 V
    before, during, after = cycle(rig, "stuck-bit:adc@SCAN[27]:11=0")
    assert adc_volts(rig, before, "adc_spare_27") == pytest.approx(0.0, abs=0.01)
    assert adc_volts(rig, during, "adc_spare_27") == pytest.approx(-10.0, abs=0.01)
    assert adc_volts(rig, after, "adc_spare_27") == pytest.approx(0.0, abs=0.01)


def test_stuck_bit_on_a_dac_latch_and_two_stuck_bits_clear_one_at_a_time(rig):
    dac = rig.world.bus["dac"]
    fs = FaultSet(rig.world)
    fs.inject("stuck-bit:dac@DAC[14]:0=1")
    fs.inject("stuck-bit:dac@DAC[15]:1=1")
    rig.run(0.1)
    assert dac.codes[14] & 1 and dac.codes[15] & 2
    fs.clear("stuck-bit:dac@DAC[14]:0=1")  # the fake clears stuck bits as a whole ...
    assert not dac.codes[14] & 1 and dac.codes[15] & 2  # ... the other one is put back


@pytest.mark.parametrize("mode", ["freeze", "zero"])
def test_resolver_loss_of_signal_sets_the_status_bit_and_clears_per_channel(rig, mode):
    fs = FaultSet(rig.world)
    fs.inject(f"resolver-los:shoulder_pitch_angle:{mode}")
    fs.inject("resolver-los:shoulder_yaw_angle")  # the same board, rtd2
    rig.run(0.2)
    st, counts = rtd(rig, inputs(rig), "shoulder_pitch_angle")
    assert st & 1  # the board's loss-of-signal bit for the channel
    if mode == "zero":
        assert counts == 0
    fs.clear("resolver-los:shoulder_pitch_angle")
    rig.run(0.2)
    s = inputs(rig)
    assert rtd(rig, s, "shoulder_pitch_angle")[0] == 0
    assert rtd(rig, s, "shoulder_pitch_angle")[1] == rig.world.bus["rtd2"].counts(1)
    assert rtd(rig, s, "shoulder_yaw_angle")[0] & 1  # the other channel is still lost


@pytest.mark.parametrize("spec, lines", [
    ("serial-noise:ft_sensor", ["ft_sensor"]), ("ft-noise", ["ft_sensor"]),
    ("serial-noise:crl_hand_controller", ["crl_hand_controller"]),
    ("serial-noise", ["ft_sensor", "crl_hand_controller"]),
    ("serial-drop:ft_sensor", ["ft_sensor"]), ("serial-drop:crl_hand_controller", ["crl_hand_controller"]),
])
def test_noise_and_drops_count_bad_records_until_cleared(rig, spec, lines):
    before, during, after = cycle(rig, spec, seconds=1.0)
    for ln in lines:
        assert link(rig, before, ln)[1] == 0
        assert link(rig, during, ln)[1] > 0
        assert link(rig, after, ln)[0] & LINK_SYNCED
    rig.run(1.0)
    later = inputs(rig)
    for ln in lines:  # a record damaged at the moment of the clear may still count: then none
        assert link(rig, later, ln)[1] == link(rig, after, ln)[1]


@pytest.mark.parametrize("spec, line, bad", [
    ("serial-stall:ft_sensor", "ft_sensor", LINK_STALE),
    ("serial-disconnect:ft_sensor", "ft_sensor", LINK_STALE),
    ("ft-unplugged", "ft_sensor", LINK_STALE),
    ("serial-stall:crl_hand_controller", "crl_hand_controller", LINK_FAULT),
    ("serial-disconnect:crl_hand_controller", "crl_hand_controller", LINK_FAULT),
    ("hand-unplugged", "crl_hand_controller", LINK_FAULT),
])
def test_silent_lines_go_stale_or_fault_and_sync_again(rig, spec, line, bad):
    before, during, after = cycle(rig, spec)
    assert link(rig, before, line)[0] & LINK_SYNCED
    assert link(rig, during, line)[0] & bad and not link(rig, during, line)[0] & LINK_SYNCED
    assert link(rig, after, line)[0] & LINK_SYNCED


def test_unplugged_line_takes_the_far_end_off_and_puts_it_back(rig):
    sio = rig.world.bus["sio"]
    fs = FaultSet(rig.world)
    fs.inject("ft-unplugged")
    assert sio.peer(0).device is None
    fs.inject("serial-noise:ft_sensor")  # a line fault while unplugged reaches the model
    fs.clear("ft-unplugged")
    assert sio.peer(0).device is rig.world.ft and rig.world.ft._noise_every is not None


def test_adc_dead_holds_the_published_volts_and_clear_restores(rig):
    before, during, after = cycle(rig, "adc-dead:adc_spare_27=2.0")
    assert adc_volts(rig, during, "adc_spare_27") == pytest.approx(2.0, abs=0.01)
    assert adc_volts(rig, after, "adc_spare_27") == pytest.approx(0.0, abs=0.01)
    assert "adc_spare_27" not in rig.world.sim.errors.adc_gain_error


def test_tach_reversed_flips_the_published_rate_against_the_truth(rig):
    from fakes.arm_params import AXES
    i = [a.joint for a in AXES].index("elbow_pitch")
    arm = rig.world.sim.arm
    fs = FaultSet(rig.world)

    def published_rate_volts_while_moving_up():
        qdot = np.zeros(len(AXES))
        qdot[i] = 0.2  # rad/s, positive
        arm.set_state(qdot=qdot)
        rig.world.sim.settle_filters()  # the anti-aliasing filters at rest on that rate
        rig.run_frames(2)  # one A/D scan
        return adc_volts(rig, inputs(rig), "elbow_pitch_rate")

    fs.inject("tach-reversed:elbow_pitch")
    assert rig.world.sim.errors.tach_scale_error[i] == -2.0
    assert published_rate_volts_while_moving_up() < -0.5
    fs.clear("tach-reversed:elbow_pitch")
    assert rig.world.sim.errors.tach_scale_error[i] == 0.0
    assert published_rate_volts_while_moving_up() > 0.5


# -- the new hooks of the byte-line model ------------------------------------------------------------
def streaming_ft():
    ft = FakeFtController()
    ft.receive(b"QS\r")
    ft.transmit(1000)  # the echo and prompt
    return ft


def pump(ft, seconds=1.0):
    out = b""
    for _ in range(int(seconds * 100)):
        ft.advance(0.01)
        out += ft.transmit(64)
    return out


def test_noise_every_repeats_until_stopped():
    ft = streaming_ft()
    ft.noise_every(b"\x55\xaa\x13", 50)
    pump(ft)
    n = ft.noise_bytes_sent
    assert n >= 3 * 5 and n % 3 == 0
    ft.stop_noise()
    pump(ft)
    assert ft.noise_bytes_sent == n


def test_drop_every_stall_resume_disconnect_reconnect():
    ft = streaming_ft()
    ft.drop_every(2, 40)
    pump(ft)
    dropped = ft.bytes_dropped
    assert dropped >= 2 * 5
    ft.stop_drops()
    pump(ft)
    assert ft.bytes_dropped == dropped
    ft.stall()
    assert pump(ft) == b"" and ft.stalled
    ft.resume()
    assert pump(ft) != b""
    ft.disconnect()
    assert pump(ft) == b""
    ft.reconnect()
    assert pump(ft) != b""


# -- scenarios ------------------------------------------------------------------------------------------------
def run_scenario(rig, scenario, seconds):
    fs = FaultSet(rig.world)
    events = []
    runner = ScenarioRunner(scenario, fs, rig.svc.schedule.frame_rate_hz,
                            say=lambda st, done, err: events.append((st.spec, err)))
    rig.on_frame.append(lambda info: runner.on_frame(info.index))
    return fs, runner, events


def test_resolver_dropout_scenario_runs_on_frame_time():
    sc = load_scenario(SCENARIOS / "resolver-dropout.toml")
    assert sc.name == "resolver-dropout" and sc.description
    with SimRig(prefix="pfma-faults-") as r:
        fs, runner, events = run_scenario(r, sc, 6.0)
        seen = []
        for t in (1.5, 2.5, 3.5, 4.5, 5.5):
            r.run(t - r.svc.loop.k / 320.0)
            s = inputs(r)
            seen.append((rtd(r, s, "shoulder_pitch_angle")[0] & 1, rtd(r, s, "wrist_yaw_angle")))
        assert [k for k, _ in runner.done] == [640, 960, 1280, 1600]  # at_s * 320 Hz
        assert [e for e in events if e[1] is not None] == [] and runner.finished
        assert [p for p, _ in seen] == [0, 1, 1, 1, 0]
        assert seen[2][1] == (1, 0)  # wrist yaw lost, reading 0, from 3 s to 4 s
        assert seen[3][1][0] == 0 and seen[4][1][0] == 0
        assert fs.active == []


def test_ft_unplug_scenario_runs():
    sc = load_scenario(SCENARIOS / "ft-unplug.toml")
    with SimRig(prefix="pfma-faults-") as r:
        fs, runner, events = run_scenario(r, sc, 5.0)
        states = []
        for t in (0.9, 1.9, 2.9, 3.9, 4.3, 4.9):
            r.run(t - r.svc.loop.k / 320.0)
            states.append(link(r, inputs(r), "ft_sensor"))
        assert states[0][0] & LINK_SYNCED and states[1][0] & LINK_STALE
        assert states[2][0] & LINK_SYNCED and states[2][1] == 0
        assert states[3][1] > 0  # noise: bad records
        assert states[5][1] == states[4][1] and states[5][0] & LINK_SYNCED  # cleared at 4 s
        assert runner.finished and fs.active == [] and all(e is None for _, e in events)


@pytest.mark.parametrize("text, says", [
    ('name = "x"\n[[step]]\nat_s = 1.0\ninjct = "ft-noise"\n', "line 2 (step 1): unknown field 'injct'; did you mean inject?"),
    ('name = "x"\n[[step]]\nat_s = -1\ninject = "ft-noise"\n', "line 2 (step 1): at_s must be a number of seconds >= 0"),
    ('name = "x"\n[[step]]\nat_s = "soon"\ninject = "ft-noise"\n', "at_s must be a number"),
    ('[[step]]\nat_s = 1\ninject = "ft-noise"\nclear = "all"\n', "line 1 (step 1): give exactly one of inject"),
    ('[[step]]\nat_s = 1\ninject = "ft-noise"\n\n[[step]]\nat_s = 2\nclear = "ft-unplugged"\n',
     "line 5 (clear at 2 s): 'ft-unplugged' is not injected by an earlier step; active then: ft-noise"),
    ('[[step]]\nat_s = 1\ninject = "resolver-los:elbow_pich_angle"\n',
     "line 1 (inject at 1 s): fault 'resolver-los:elbow_pich_angle': no resolver signal"),
    ('[[step]]\nat_s = 1\ninject = "ft-noise"\n[[step]]\nat_s = 2\ninject = "serial-noise:ft_sensor"\n',
     "already injected"),
    ('nme = "x"\n', "unknown key 'nme'; did you mean name?"),
    ('name = "x"\n', "no steps"),
    ('name = \n', "not valid TOML"),
])
def test_bad_scenarios_name_file_line_and_field(text, says):
    with pytest.raises(ConfigError) as e:
        parse_scenario(text, "bad.toml")
    assert "scenario bad.toml" in str(e.value) and says in str(e.value)


def test_scenario_file_not_utf8(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(b'name = "caf\xe9"\n')
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_scenario(p)


def test_steps_at_the_same_time_run_in_file_order():
    sc = parse_scenario('[[step]]\nat_s = 1\ninject = "ft-noise"\n[[step]]\nat_s = 0.5\ninject = "ft-unplugged"\n'
                        '[[step]]\nat_s = 1\nclear = "ft-noise"\n')
    assert [(s.at_s, s.action, s.spec) for s in sc.steps] == [
        (0.5, "inject", "ft-unplugged"), (1.0, "inject", "ft-noise"), (1.0, "clear", "ft-noise")]
    assert np.array_equal([s.frame(320.0) for s in sc.steps], [160, 320, 320])


def test_switcher_silent_route_is_not_acknowledged_and_named_once_then_recovers(rig):
    """The matrix switcher latches the route byte but never acknowledges (its strobe
    handshake): the service names the failed route once; cleared, the next route works."""
    ctl = rig.controller()
    fs = FaultSet(rig.world)
    fs.inject("switcher-silent")
    ctl.write_commands(matrix_route=0x21)
    rig.run(0.5)
    failed = [t for m in rig.reader.messages() if m.code == 141 for t in [m.text]]
    assert len(failed) == 1 and "0x21" in failed[0], failed
    assert int(inputs(rig).matrix_route) != 0x21  # not reported as applied
    fs.clear("switcher-silent")
    ctl.write_commands(matrix_route=0x12)
    rig.run(0.5)
    assert int(inputs(rig).matrix_route) == 0x12
