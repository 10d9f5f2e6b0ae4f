"""Issue 32 item 1: a simulated rack with a real rack's imperfections, drawn from a seed
(sim/errors.py), reachable from every tool that starts one, the fake's ground truth (said by
``pfma fault list --active``, never in the Bit3 buffer)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from fakes.arm_params import NOMINAL, SimErrors
from fakes.world import FakeWorld
from pfma.rack import load_rack
from sim.errors import BOUNDS, NOISE, describe, parse_seed, seeded
from sim.rig import SimRig
from tools.cli import main


def test_a_seed_gives_the_same_errors_each_time_within_their_bounds_and_0_none():
    rack = load_rack()
    a, b, c = seeded(5, rack), seeded(5, rack), seeded(6, rack)
    assert a == b and a != c
    assert seeded(0, rack) == SimErrors()
    assert set(a.adc_gain_error) == {ch.signal for ch in rack.channels() if ch.device == "adc"}
    assert set(a.dac_offset_v) == {ch.signal for ch in rack.channels() if ch.device == "dac"}
    for name, values in (("adc_gain_error", a.adc_gain_error.values()), ("adc_offset_v", a.adc_offset_v.values()),
                         ("dac_gain_error", a.dac_gain_error.values()), ("dac_offset_v", a.dac_offset_v.values()),
                         ("resolver_offset_rad", a.resolver_offset_rad), ("tach_scale_error", a.tach_scale_error),
                         ("amp_gain_error", a.amp_gain_error)):
        v = np.abs(np.asarray(list(values)))
        assert v.max() <= BOUNDS[name].limit and v.max() > 0.3 * BOUNDS[name].limit, name
    assert np.all(np.abs(a.ft_offset[:3]) <= BOUNDS["ft_offset_force"].limit)
    assert np.all(np.abs(a.ft_drift_per_s[3:]) <= BOUNDS["ft_drift_torque"].limit)
    for name, (low, bound) in NOISE.items():
        assert low <= getattr(a, name) <= bound.limit, name
    assert a.noise_seed == 5 and seeded(0, rack).adc_noise_counts == 0.0
    # the motion faults and panel switches are --sim-fault's, never drawn
    assert not any(a.brake_held) and not any(a.amp_off) and not a.panel_28v_off


def test_a_bad_seed_is_one_message():
    assert parse_seed("12") == 12
    for bad in ("-1", "x", "1.5"):
        with pytest.raises(ValueError, match="a whole number >= 0"):
            parse_seed(bad)


def test_the_fake_reads_and_moves_with_the_errors():
    """The seeded ADC gain and offset show in what the board reads, the F/T bias in what the
    transducer puts out, the amplifier gain in the current a rate error drives."""
    e = seeded(3)
    w0, w = FakeWorld(), FakeWorld(errors=e)
    for world in (w0, w):
        world.sim.hold_adc_volts("adc_spare_25", 5.0)
    board, ch = w.sim._where("adc_spare_25")
    m = w.sim._adc[board]
    assert m.gain[ch] == pytest.approx(1 + e.adc_gain_error["adc_spare_25"])
    assert m.offset[ch] == pytest.approx(e.adc_offset_v["adc_spare_25"])
    f0, t0 = w0.sim.ft_reading(100.0)
    f, t = w.sim.ft_reading(100.0)
    bias = np.asarray(e.ft_offset) + 100.0 * np.asarray(e.ft_drift_per_s)
    assert np.allclose(f - f0, bias[:3]) and np.allclose(t - t0, bias[3:])
    assert np.allclose(w.sim.arm.k_a, np.asarray(NOMINAL.k_a()) * (1 + np.asarray(e.amp_gain_error)))
    assert np.allclose(w0.sim.arm.k_a, NOMINAL.k_a())


def test_a_seeded_rack_reads_noise_a_perfect_one_none():
    """Each A/D conversion and each resolver reading of a seeded rack carries its seeded
    noise (1 sigma, counts); the perfect rack's are exact."""
    e = seeded(4)
    for world, adc_sigma, rtd_sigma in ((FakeWorld(), 0.0, 0.0),
                                        (FakeWorld(errors=e), e.adc_noise_counts, e.resolver_noise_counts)):
        board, _ = world.sim._where("adc_spare_25")
        codes = np.array([world.sim.fake_rack[board].code_for_volts(1.2345) for _ in range(4000)])
        assert np.std(codes) == pytest.approx(adc_sigma, abs=0.08), (adc_sigma, np.std(codes))
        rboard, rch = next(iter(world.sim.angle.values()))
        counts = []
        for _ in range(4000):
            world.sim._write_sensors()
            counts.append(world.sim.fake_rack[rboard].counts(rch))
        # the converter truncates to whole counts: a noiseless reading never moves
        spread = np.std(counts)
        assert (spread == 0.0) if rtd_sigma == 0.0 else (0.5 * rtd_sigma < spread < 2.0 * rtd_sigma + 0.5), spread


def test_fault_list_active_says_the_rack_errors_and_the_buffer_never_holds_them():
    from tools.faultctl import FaultController
    e = seeded(9)
    with SimRig(prefix="pfma-simerr-", errors=e) as r:
        ctl = FaultController(r.svc, r.world, say=None)
        reply = ctl.handle({"op": "list"})
        assert reply["ok"] and reply["faults"] == []
        lines = reply["rack_errors"]
        assert lines == describe(e) and len(lines) == 9  # 8 kinds of error and the noise
        worst = max(e.resolver_offset_rad, key=abs)
        assert any(ln.startswith("rack error: resolver zero: 6 channel(s), largest") and
                   f"{math.degrees(worst):+.3f} deg" in ln for ln in lines), lines
        r.run(0.05)
        seg = Path("/dev/shm") / r.name
        assert seg.exists(), seg
        raw = seg.read_bytes()
        assert len(raw) >= 32 * 1024
        for v in (e.adc_gain_error["cae_yaw"], e.resolver_offset_rad[0]):  # the truth is not published
            assert np.float64(v).tobytes() not in raw and np.float32(v).tobytes() not in raw
    with SimRig(prefix="pfma-simerr-") as r:
        assert FaultController(r.svc, r.world, say=None).handle({"op": "list"})["rack_errors"] == []


def test_a_motion_fault_keeps_the_seeded_errors():
    from sim.faults import FaultSet
    e = seeded(2)
    world = FakeWorld(errors=e)
    FaultSet(world).inject("brake-held:elbow_pitch")
    now = world.sim.errors
    assert now.brake_held[2] and dataclasses.replace(now, brake_held=e.brake_held) == e


@pytest.mark.parametrize("argv, says", [
    (["serve", "--sim-errors", "x"], "--sim-errors: a seed, a whole number >= 0"),
    (["serve", "--sim-errors", "3", "--rack", "pfma/rack_default.toml", "--bus", "modbus://127.0.0.1:1"],
     "--sim-errors gives the simulated rack (--rack fake) a real rack's imperfections"),
    (["checkout", "--buffer", "nosuch", "--sim-errors", "3"], "--sim-errors gives the simulated rack"),
    (["calibrate", "adc", "--buffer", "nosuch", "--sim-errors", "3"], "need the simulated rack (no --buffer)"),
    (["calibrate", "adc", "--sim-fault", "nosuch:thing"], "pfma calibrate: --sim-fault"),
    (["controller", "--sim-errors", "3"], "--sim-errors needs --sim"),
])
def test_a_misused_sim_errors_is_one_message_and_exit_2(argv, says, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        raise SystemExit(main(argv))
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_a_scenario_runs_on_its_own_errors_seed_and_a_different_flag_is_refused(tmp_path, capsys):
    from argparse import Namespace

    from tools.cli.fault import _scenario_errors
    from sim.scenario import parse_scenario
    sc = parse_scenario('errors_seed = 4\n[[step]]\nat_s = 1\ninject = "ft-noise"\n', "s.toml")
    world = FakeWorld()
    _scenario_errors(Namespace(sim_errors=0), sc, world)
    assert world.sim.errors == seeded(4, world.rack_config)
    _scenario_errors(Namespace(sim_errors=4), sc, world)
    with pytest.raises(SystemExit) as e:
        _scenario_errors(Namespace(sim_errors=5), sc, world)
    assert e.value.code == 2 and "disagree" in capsys.readouterr().err
