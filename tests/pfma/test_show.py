"""pfma/show.py: the one way a value is shown (issue 29 item 5)."""

import enum
import math

import pytest

from pfma.show import flag_names, name_of, named, value_of, wrap_angle


class Colour(enum.IntEnum):
    DARK_RED = 0
    GREEN = 2


@pytest.mark.parametrize("a", [0.0, 1.0, -1.0, math.pi, -math.pi, 3 * math.pi / 2, 4.71239, -4.71239, 7.0, -7.0,
                               2 * math.pi, 1e-12, -1e-12, 100.0])
def test_an_angle_is_shown_in_minus_pi_to_pi_and_is_the_same_angle(a):
    w = wrap_angle(a)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-9) and math.isclose(math.sin(w), math.sin(a), abs_tol=1e-9)


def test_the_elbow_the_issue_saw_twice_reads_once():
    # the console's -1.5712 and pfma read's 4.71239 rad were the same elbow angle
    assert wrap_angle(4.71239) == pytest.approx(4.71239 - 2 * math.pi)
    assert wrap_angle(-math.pi) == math.pi and wrap_angle(math.pi) == math.pi  # the closed end is +pi


def test_an_enumeration_by_name_with_its_number_and_an_unknown_value_says_so():
    names = {0: "HOLD", 1: "TELEOP"}
    assert named(1, names) == "TELEOP (1)" and name_of(1, names) == "TELEOP"
    assert named(7, names) == "7 (unknown)" and name_of(7, names) == "7 (unknown)"
    assert named(2, Colour) == "GREEN (2)" and name_of(0, Colour) == "DARK RED"  # an IntEnum: "_" as " "
    assert named(1, [(1, "ONE")]) == "ONE (1)"  # (value, name) pairs
    assert named("x", names) == "x (unknown)"


def test_a_bit_set_by_the_names_of_its_bits():
    bits = {1: "LOS", 2: "NOREF", 0x100: "BUSERR"}
    assert flag_names(0, bits) == "ok" and flag_names(0, bits, clear="none") == "none"
    assert flag_names(3, bits) == "LOS|NOREF" and flag_names(0x101, bits) == "LOS|BUSERR"
    assert flag_names(0x41, bits) == "LOS|0x40"  # a bit without a name: hex, never dropped


@pytest.mark.parametrize("text,want", [("TELEOP", 1), ("teleop", 1), (" Teleop ", 1), ("ERROR_RESET", 4),
                                       ("error reset", 4), ("error-reset", 4), ("TELE", None), ("1", None)])
def test_a_name_typed_by_a_person_gives_its_number(text, want):
    assert value_of(text, {0: "HOLD", 1: "TELEOP", 4: "ERROR RESET"}) == want
