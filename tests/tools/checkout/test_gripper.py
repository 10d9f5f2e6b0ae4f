"""The gripper's open-loop test (docs/checkout.md "The gripper"): on the simulated rack,
healthy it passes both moves; each drive fault the matrix injects on it fails the first
move with the words that name it."""

from __future__ import annotations

import pytest

from tools.checkout import Checkout, load_checkout_config
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
    return [r for r in rep.as_dict()["results"] if r["check"].startswith("gripper open-loop")]


def test_a_healthy_gripper_opens_and_closes():
    rows = _gripper_rows(None)
    assert [(r["check"], r["status"]) for r in rows] == [("gripper open-loop open", "PASS"),
                                                         ("gripper open-loop close", "PASS")], rows
    assert rows[0]["channel"] == "end_effector_rate" and rows[0]["measured"] > 0 > rows[1]["measured"]


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
