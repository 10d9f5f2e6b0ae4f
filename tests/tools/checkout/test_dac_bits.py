"""The rate command's DAC data bits, checked through the loop with the brake set (issue 32
item 3): before a joint's moves its current limit sits below the brake-release cards'
0.3 V engage threshold, the rate command at codes 0x7FF and 0x800 (every data bit at 1 and
at 0 between them), then at a bounded saturating voltage; the motor current against the
set brake names a stuck bit on the rate channel or the current-limit channel."""

import pytest

from fakes.arm_params import AXES
from tools.checkout import FAIL, PASS, SKIP

from tests.tools.checkout.test_checkout import first_failure, run

JOINTS = ("shoulder_pitch", "shoulder_yaw", "elbow_pitch", "wrist_yaw", "wrist_pitch", "wrist_roll")


def test_a_healthy_rack_passes_both_rows_on_every_joint(sim, cfg):
    rep, _ = run(sim, cfg, only=["joints"])
    rows = {(r.channel, r.check): r for r in rep.results if r.check.startswith("DAC data bits")}
    for j in JOINTS:
        assert rows[(f"{j}_command", "DAC data bits (brake set)")].status == PASS
        assert rows[(f"{j}_command", "DAC data bits: the low bits stepped (brake set)")].status == PASS
        assert rows[(f"{j}_current_limit", "DAC data bits: the current limit's low bits stepped (brake set)")
                    ].status == PASS
        assert rows[(f"{j}_current_limit", "DAC data bits: the current limit (brake set)")].status == PASS
        assert rows[(f"{j}_current_limit", "DAC data bits: the current limit walked (brake set)")].status == PASS
    assert rep.passed


@pytest.mark.parametrize("spec, channel, words", [
    ("stuck-bit:dac@DAC[0]:5=0", "shoulder_pitch_command", "a data bit of D0..D10 stuck at 0"),
    ("stuck-bit:dac@DAC[0]:11=1", "shoulder_pitch_command", "data bit D11 stuck at 1"),
    ("stuck-bit:dac@DAC[2]:11=0", "elbow_pitch_command", "data bit D11 stuck at 0"),
    ("stuck-bit:dac@DAC[5]:7=1", "wrist_roll_command", "a data bit of D0..D10 stuck at 1"),
    ("stuck-bit:dac@DAC[8]:9=1", "shoulder_yaw_current_limit",
     "a data bit of DAC channel shoulder_yaw_current_limit stuck at 1 (the current limit reads high"),
    ("stuck-bit:dac@DAC[8]:5=0", "shoulder_yaw_current_limit",
     "a data bit of DAC channel shoulder_yaw_current_limit stuck at 0 (the current limit reads low"),
    # the limit's middle bits, walked from 0x820 by 4, 8 and 16 codes (a bit stuck adds nothing)
    ("stuck-bit:dac@DAC[8]:3=0", "shoulder_yaw_current_limit",
     "data bit D3 of DAC channel shoulder_yaw_current_limit stuck at 0"),
    ("stuck-bit:dac@DAC[12]:2=1", "wrist_roll_current_limit",
     "data bit D2 of DAC channel wrist_roll_current_limit stuck at 1"),
    ("stuck-bit:dac@DAC[10]:4=0", "wrist_yaw_current_limit",
     "data bit D4 of DAC channel wrist_yaw_current_limit stuck at 0"),
    # the limit's bits no brake holds (tools/checkout/limitbits.py, test_limit_bits.py)
    # the shoulder pitch's D6 with its brake set (0.31 V: a set brake stays set up to 0.5 V)
    ("stuck-bit:dac@DAC[7]:6=0", "shoulder_pitch_current_limit",
     "data bit D6 of DAC channel shoulder_pitch_current_limit stuck at 0"),
    # the wrist yaw runs at 2^7 codes when healthy: stuck, its limit is 0 V and it is held
    ("stuck-bit:dac@DAC[10]:7=0", "wrist_yaw_current_limit",
     "data bit D7 of DAC channel wrist_yaw_current_limit stuck at 0"),
    # the jaw's low bits, stepped on its stop through the monitor's noise
    ("stuck-bit:dac@DAC[13]:1=0", "gripper_current_limit",
     "data bit D1 of DAC channel gripper_current_limit stuck"),
    ("stuck-bit:dac@DAC[13]:8=0", "gripper_current_limit",
     "data bit D8 of DAC channel gripper_current_limit stuck at 0"),
    # the elbow cannot lift itself at 0.75 A: its first move fails, the current flat under
    # both the limit and what the held drive draws at that command
    ("stuck-bit:dac@DAC[9]:8=0", "elbow_pitch_rate",
     "data bit D8 of DAC channel elbow_pitch_current_limit stuck at 0?"),
])
def test_a_stuck_dac_bit_is_the_first_failure_on_its_channel(sim, cfg, spec, channel, words):
    sim.inject_fault(spec)
    rep, _ = run(sim, cfg, only=["joints"])
    f = first_failure(rep)
    assert (f.group, f.channel, f.status) == ("joints", channel, FAIL)
    assert words in f.detail


def test_the_check_keeps_the_brake_set_and_the_joint_still_even_at_plus_10_volts(sim, cfg):
    """D11 stuck at 1 turns the -1 LSB code into +10 V: the joint still does not move (the
    brake holds against at most the test limit's current), and the run stops there."""
    sim.inject_fault("stuck-bit:dac@DAC[0]:11=1")  # shoulder pitch: the arm's weight on it
    arm = sim.world.sim.arm
    ax = [a.joint for a in AXES].index("shoulder_pitch")
    seen = []
    sim.on_frame.append(lambda info: seen.append((bool(arm.brake_engaged[ax]), float(arm.q[ax]),
                                                  float(sim.world.bus["dac"].output_volts_all()[0]))))
    rep, _ = run(sim, cfg, only=["joints"])
    assert first_failure(rep).channel == "shoulder_pitch_command"
    assert max(v for _, _, v in seen) > 9.9  # the stuck bit did drive +10 V
    assert all(b for b, _, _ in seen)
    qs = [q for _, q, _ in seen]
    assert max(qs) - min(qs) < float(cfg.joint("shoulder_pitch", "max_brake_creep_rad"))


def test_a_current_limit_stuck_at_zero_volts_is_named_by_the_moves_diagnosis(sim, cfg):
    """No current at all reads the same, brake set, for the drive, a dead monitor and a
    limit stuck at 0 V: the check skips its limit row and the moves tell (no motion, no
    current: the drive, or D11 of the limit channel stuck at 0)."""
    sim.inject_fault("stuck-bit:dac@DAC[9]:11=0")  # elbow pitch's current limit
    rep, _ = run(sim, cfg, only=["joints"])
    lim = next(r for r in rep.results if r.channel == "elbow_pitch_current_limit")
    assert lim.status == SKIP and "not judged here" in lim.detail
    diag = next(r for r in rep.failures() if r.check == "drive and brake (diagnosis)")
    assert "no motor current" in diag.detail
    assert "data bit D11 of DAC channel elbow_pitch_current_limit stuck at 0" in diag.detail


@pytest.mark.parametrize("code, lo, hi, scale, said", [
    (0xA00, -0.25, 0.25, 1.0, "data bit D9 stuck at 1?"),  # 2.5 V on a 0 A motor-current input
    (0x000, -0.5, 0.5, 1.0, "data bit D11 stuck at 0?"),  # -10 V on a centred CAE axis
    (0x90A, -0.5, 0.5, 1.0, "not one data bit away"),  # 1.3 V: 10 codes off once D8 is flipped
    (0x804, -0.25, 0.25, 1.0, "not one data bit away"),  # D2 flips are noise, never named
    # a CAE discrete idles released at 0 V in its -0.5..1 V range (not at its 0.25 V centre)
    (0x6FE, -0.5, 1.0, 1.0, "data bit D8 stuck at 0?"),
])
def test_an_idle_reading_one_flipped_bit_from_its_idle_code_names_that_bit_first(code, lo, hi, scale, said):
    from tools.checkout.runner import _idle_why
    text = _idle_why(code, lo, hi, scale)
    assert said in text and "dead input" in text


def test_a_monitor_bit_stuck_at_1_fails_on_the_monitor_before_the_dac_is_judged(sim, cfg):
    """D4 of the wrist roll's current monitor stuck at 1 reads 0.039 A with no current
    possible (not armed, limits 0): named on the monitor, not on the DAC."""
    sim.inject_fault("stuck-bit:adc@SCAN[6]:4=1")
    rep, _ = run(sim, cfg, only=["joints"])
    f = first_failure(rep)
    assert (f.channel, f.check) == ("wrist_roll_motor_current", "zero with no current (limits 0)")
    assert "data bit D4 stuck at 1?" in f.detail


def test_a_small_current_at_a_test_code_names_the_monitor_bit_as_the_other_reading(sim, cfg):
    """D3 of a current monitor stuck at 0 reads a small negative current 8 codes low, at both
    test codes alike: the DAC row, judged on the step between them, passes (its DAC is
    healthy); the run fails on the monitor: its codes name its bit, or a DAC row whose step
    across the monitor's edge rose by more than its codes' worth (which no stuck DAC bit
    does) points at the monitor, and the codes then name the bit."""
    sim.inject_fault("stuck-bit:adc@SCAN[0]:3=0")  # shoulder yaw's monitor
    rep, _ = run(sim, cfg, only=["joints"])
    f = first_failure(rep)
    rows = {(r.channel, r.check): r for r in rep.results}
    assert rows[("shoulder_yaw_command", "DAC data bits (brake set)")].status == PASS
    if f.channel == "shoulder_yaw_motor_current":
        assert "bit 3 stuck at 0" in f.detail, f.detail
    else:
        assert f.channel == "shoulder_yaw_current_limit", (f.channel, f.detail)
        assert "which no stuck bit of DAC channel shoulder_yaw_current_limit does" in f.detail
        assert "the motor-current monitor shoulder_yaw_motor_current" in f.detail
        diag = rows[("shoulder_yaw_motor_current", "data bits (diagnosis)")]
        assert diag.status == FAIL and "bit 3 stuck at 0" in diag.detail


@pytest.mark.parametrize("spec, channel, words", [
    # the rate command's lowest bits, each stepped alone from 0 V (the 200-case matrix's misses)
    ("stuck-bit:dac@DAC[1]:1=1", "shoulder_yaw_command", "data bit D1 of DAC channel shoulder_yaw_command stuck"),
    ("stuck-bit:dac@DAC[2]:1=0", "elbow_pitch_command", "data bit D1 of DAC channel elbow_pitch_command stuck"),
    ("stuck-bit:dac@DAC[3]:3=1", "wrist_yaw_command", "data bit D3 of DAC channel wrist_yaw_command stuck"),
    # the current limit's D0 and D1, stepped while the drive saturates
    ("stuck-bit:dac@DAC[9]:0=1", "elbow_pitch_current_limit",
     "data bit D0 of DAC channel elbow_pitch_current_limit stuck at 0 or at 1"),
    ("stuck-bit:dac@DAC[10]:1=1", "wrist_yaw_current_limit",
     "data bit D1 of DAC channel wrist_yaw_current_limit stuck at 0 or at 1"),
])
def test_a_low_dac_bit_is_found_by_its_step_through_the_monitor_s_noise(cfg, spec, channel, words):
    """On a rack with a real rack's noise (``--sim-errors 1``, the matrix's), a step of 1 to 8
    codes that adds nothing is that bit stuck: the first failure, on its channel."""
    from tools.checkout.target import make_sim_target
    t = make_sim_target(None, sim_errors=1)
    try:
        t.inject_fault(spec)
        rep, _ = run(t, cfg, only=["joints"])
    finally:
        t.close()
    f = first_failure(rep)
    assert (f.group, f.channel, f.status) == ("joints", channel, FAIL), (f.channel, f.detail)
    assert words in f.detail, f.detail
