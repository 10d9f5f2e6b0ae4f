"""The gripper's open-loop test (docs/checkout.md "The gripper"): on the simulated rack,
healthy it passes both moves; each drive fault the matrix injects on it fails the first
move with the words that name it."""

from __future__ import annotations

import pytest

from tools.checkout import Checkout, load_checkout_config
from tools.checkout.runner import GRIPPER_BITS_CHECK
from tools.checkout.target import make_sim_target


def _gripper_rows(fault: str | None) -> list[dict]:
    t = make_sim_target(None, sim_errors=1)
    try:
        if fault:
            t.inject_fault(fault)
        rep = Checkout(t, load_checkout_config(None), only=["joints"], interactive=False,
                       say=lambda line: None, keep_going=True).run()
    finally:
        t.close()
    return [r for r in rep.as_dict()["results"] if r["check"].startswith("gripper open-loop")
            or r["check"] == GRIPPER_BITS_CHECK]


def test_a_healthy_gripper_opens_and_closes_and_its_command_bits_step():
    rows = _gripper_rows(None)
    assert [(r["check"], r["status"]) for r in rows] == [("gripper open-loop open", "PASS"),
                                                         ("gripper open-loop close", "PASS"),
                                                         (GRIPPER_BITS_CHECK, "PASS")], rows
    assert rows[0]["channel"] == "end_effector_rate" and rows[0]["measured"] > 0 > rows[1]["measured"]
    # every step of D0..D5, opening and closing, added at least half its worth, D0 judged too
    assert rows[2]["channel"] == "gripper_command" and rows[2]["measured"] >= 0.5, rows[2]
    assert "not judged" not in rows[2]["detail"] and rows[2]["detail"].count("+2^0:") == 2, rows[2]


@pytest.mark.parametrize("bit, value", [(0, 0), (3, 1), (5, 1)])
def test_a_stuck_bit_of_the_jaws_command_is_named(bit, value):
    """The moves pass (a few codes of a 205-code command); the steps while the jaw runs name
    the bit (docs/checkout.md "The gripper")."""
    rows = _gripper_rows(f"stuck-bit:dac@DAC[6]:{bit}={value}")
    assert [r["status"] for r in rows] == ["PASS", "PASS", "FAIL"], rows
    assert f"data bit D{bit} of DAC channel gripper_command stuck at 0 or at 1" in rows[2]["detail"], rows[2]


@pytest.mark.parametrize("fault, words", [
    ("amp-off:gripper", "no motor current"),
    ("panel-off:pwm:gripper", "PWM stage switch"),
    ("tach-reversed:gripper", "TACH POLARITY REVERSED"),
    ("load:gripper=300", "held by a load"),
    ("stuck-bit:dac@DAC[6]:11=1", "data bit D11 stuck at 1 (2048 codes) on DAC channel gripper_command"),
])
def test_a_gripper_fault_fails_its_move_naming_the_kind(fault, words):
    rows = _gripper_rows(fault)
    bad = [r for r in rows if r["status"] == "FAIL"]
    assert bad and words in bad[0]["detail"], rows
    assert not [r for r in rows if r["check"] == GRIPPER_BITS_CHECK]  # a failed move: not stepped further
