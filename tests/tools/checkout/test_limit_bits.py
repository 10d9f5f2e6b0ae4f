"""A current-limit channel's data bits that no brake holds (issue 32 item 3,
tools/checkout/limitbits.py): a joint's D6 and up pulsed alone after its moves, the jaw's
limit stepped and pulsed with the jaw closed on its stop. A stuck bit is the first failure,
on its channel, with its bit; the shoulder pitch, which cannot hold its weight at a pulse's
limit, keeps its brake set through its pulses. The stuck limit bits named first on their
channel are among test_dac_bits.py's cases."""

import pytest

from fakes.arm_params import AXES
from tools.checkout import PASS
from tools.checkout.limitbits import JAW_PULSE_CHECK, JAW_STEP_CHECK, PULSE_CHECK, zeroing_bits

from tests.tools.checkout.test_checkout import first_failure, run

JOINTS = ("shoulder_pitch", "shoulder_yaw", "elbow_pitch", "wrist_yaw", "wrist_pitch", "wrist_roll")


def test_a_healthy_rack_passes_every_pulse_row_and_the_shoulder_pitch_keeps_its_brake(sim, cfg):
    """Every joint's pulses and the jaw's two rows pass; while the shoulder pitch's brake is
    released its current limit is the moves' 5 V (50 % of I_max, what holds the arm), never a
    pulse's lower limit."""
    arm = sim.world.sim.arm
    ax = [a.joint for a in AXES].index("shoulder_pitch")
    seen = []
    sim.on_frame.append(lambda info: seen.append((bool(arm.brake_engaged[ax]),
                                                  float(sim.world.bus["dac"].output_volts_all()[7]))))
    rep, _ = run(sim, cfg, only=["joints"])
    rows = {(r.channel, r.check): r for r in rep.results}
    for j in JOINTS:
        assert rows[(f"{j}_current_limit", PULSE_CHECK)].status == PASS
    assert rows[("gripper_current_limit", JAW_STEP_CHECK)].status == PASS
    assert rows[("gripper_current_limit", JAW_PULSE_CHECK)].status == PASS
    assert "2^6:" in rows[("shoulder_pitch_current_limit", PULSE_CHECK)].detail
    assert "2^7:" not in rows[("shoulder_pitch_current_limit", PULSE_CHECK)].detail
    released = [v for engaged, v in seen if not engaged]
    assert released and min(released) > 4.9
    assert rep.passed


def test_a_held_brake_s_stall_current_is_not_read_as_a_low_limit(sim, cfg):
    """The wrist pitch held by its brake draws K_a x V_cmd (0.74 A), flat, under its 1 A
    limit: the move fails as a held brake, never as a limit bit."""
    sim.inject_fault("brake-held:wrist_pitch")
    rep, _ = run(sim, cfg, only=["joints"])
    f = first_failure(rep)
    assert f.channel == "wrist_pitch_rate" and "current_limit" not in f.detail
    diag = next(r for r in rep.failures() if r.check == "drive and brake (diagnosis)")
    assert "brake" in diag.detail


@pytest.mark.parametrize("amps, scale, said", [
    (2.0, 1.0, "D11"),  # 0x99A: only D11 takes it under 0.3 V
    (5.0, 1.0, "D10 or D11"),  # 0xC00: D10 alone leaves 0 V, D11 alone -10 V
    (0.0, 1.0, "D11"),  # nothing set above the zero code: the sign bit is all that is left
])
def test_the_bits_that_zero_a_limit_are_those_whose_loss_leaves_it_under_the_brake(amps, scale, said):
    assert zeroing_bits(amps, scale) == said
