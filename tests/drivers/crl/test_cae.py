"""CAE rate hand controller: centre, deadband, span, quadratic shaping, deadman, channel map."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from drivers.crl import CaeAxisCal, CaeCalibration, CaeHandController
from drivers.crl.cae import CAE_AXES, CAE_SIGNALS
from pfma.clock import SimClock
from pfma.errors import CalibrationError

# rack order (channels 16..24): up/down, fwd/back, right/left, yaw, pitch, roll, d1, d2, d3
UP, FWD, RIGHT, YAW, PITCH, ROLL, D1, D2, D3 = range(9)


def volts(**kw) -> list[float]:
    v = [0.0] * 9
    for name, val in kw.items():
        v[globals()[name]] = val
    return v


def shaped(v: float, db: float = 0.5, span: float = 10.0) -> float:
    """pfma-model 8.5: u = sign(v) * ((|v| - 0.5) / 9.5)**2 beyond the deadband."""
    a = abs(v) - db
    return 0.0 if a <= 0 else math.copysign(min(1.0, (a / (span - db)) ** 2), v)


@pytest.fixture
def cae():
    return CaeHandController(clock=SimClock(3.0))


def test_channels_come_from_the_rack(cae):
    assert cae.adc_channels == tuple(range(16, 25))
    assert cae.channels[0] == 16 and cae.channels[2] == 18  # cae_up_down, cae_right_left


def test_centre_and_deadband_give_zero(cae):
    st = cae.from_volts(volts(UP=0.49, FWD=-0.5, RIGHT=0.2, YAW=-0.3))
    assert st.axes == (0.0,) * 6 and st.valid and st.source == "cae" and st.t_s == 3.0


@pytest.mark.parametrize("v", [0.51, 0.6, 1.0, 2.5, 5.0, 9.0, 10.0, -0.6, -5.0, -10.0])
def test_quadratic_shaping_matches_model(cae, v):
    st = cae.from_volts(volts(UP=v))
    assert st.axis("z") == pytest.approx(shaped(v), abs=1e-12)
    assert st.axis("z") == pytest.approx(math.copysign(((abs(v) - 0.5) / 9.5) ** 2, v))


def test_axis_mapping_and_signs(cae):
    st = cae.from_volts(volts(UP=5.0, FWD=-5.0, RIGHT=5.0, YAW=10.0, PITCH=-10.0, ROLL=7.0))
    u5 = shaped(5.0)
    assert st.axis("z") == pytest.approx(u5)  # up is +z
    assert st.axis("x") == pytest.approx(-u5)  # backward is -x
    assert st.axis("y") == pytest.approx(-u5)  # right is -y (y is left)
    assert (st.axis("yaw"), st.axis("pitch")) == (1.0, -1.0)
    assert st.axis("roll") == pytest.approx(shaped(7.0))
    assert st.raw[RIGHT] == 5.0


def test_full_scale_clips_and_overrange_is_a_fault(cae):
    assert cae.from_volts(volts(FWD=10.4)).axis("x") == 1.0
    st = cae.from_volts(volts(FWD=11.0, D1=5.0))
    assert st.fault and not st.valid and not st.deadman
    assert "cae_forward_backward" in st.reason and "17" in st.reason
    st = cae.from_volts(volts(PITCH=math.nan, D1=5.0))
    assert st.fault and not st.deadman and "cae_pitch" in st.reason


def test_custom_calibration_centre_deadband_span_sign():
    axes = dict(CaeCalibration().axes)
    axes["z"] = CaeAxisCal(centre_v=1.0, deadband_v=0.2, span_v=5.0, sign=-1)
    cae = CaeHandController(CaeCalibration(axes=axes), clock=SimClock())
    assert cae.from_volts(volts(UP=1.15)).axis("z") == 0.0
    assert cae.from_volts(volts(UP=3.4)).axis("z") == pytest.approx(-((2.4 - 0.2) / 4.8) ** 2)
    assert cae.from_volts(volts(UP=-0.2)).axis("z") == pytest.approx(((1.2 - 0.2) / 4.8) ** 2)
    assert cae.from_volts(volts(UP=6.0)).axis("z") == -1.0


@pytest.mark.parametrize("cal, match", [
    (CaeAxisCal(deadband_v=5.0, span_v=5.0), "deadband"),
    (CaeAxisCal(sign=2), "sign"),
    (CaeAxisCal(centre_v=math.inf), "non-finite"),
])
def test_bad_calibration_is_refused(cal, match):
    axes = dict(CaeCalibration().axes)
    axes["yaw"] = cal
    with pytest.raises(CalibrationError, match=match):
        CaeCalibration(axes=axes)
    with pytest.raises(CalibrationError, match="lacks"):
        CaeCalibration(axes={"x": CaeAxisCal()})


def test_deadman_and_discretes_with_hysteresis(cae):
    assert not cae.from_volts(volts(D1=2.6)).deadman  # below threshold + hysteresis/2 (2.75)
    st = cae.from_volts(volts(D1=5.0, D3=5.0))
    assert st.deadman and st.buttons == 0b101 and st.active
    assert cae.from_volts(volts(D1=2.4, D3=5.0)).deadman  # still above 2.25: stays pressed
    st = cae.from_volts(volts(D1=0.0, D2=5.0))
    assert not st.deadman and st.buttons == 0b010


def test_wrong_number_of_volts(cae):
    with pytest.raises(ValueError, match="16, 17"):
        cae.from_volts([0.0] * 6)


@dataclass
class _Ch:
    channel: int


class PermutedRack:
    """A rack whose CAE signals sit on channels 0..8 in a different order."""

    MAP = {s: ch for s, ch in zip(CAE_SIGNALS, (8, 7, 6, 5, 4, 3, 0, 1, 2))}

    def channel(self, signal):
        return _Ch(self.MAP[signal])


def test_channel_order_follows_the_rack_config():
    cae = CaeHandController(rack=PermutedRack(), clock=SimClock())
    assert cae.adc_channels == tuple(range(9))
    v = [0.0] * 9
    v[8] = 10.0  # cae_up_down on channel 8
    v[0] = 5.0  # cae_discrete_1 on channel 0
    st = cae.from_volts(v)
    assert st.axis("z") == 1.0 and st.deadman and st.axes.count(0.0) == 5


def test_null_calibration(cae):
    samples = [volts(UP=0.30 + 0.01 * (i % 3), ROLL=-0.2) for i in range(80)]
    cal = cae.calibrate_null(samples)
    assert cal.axes["z"].centre_v == pytest.approx(sum(s[UP] for s in samples) / 80)
    assert cal.axes["roll"].centre_v == pytest.approx(-0.2)
    assert cal.axes["y"].sign == -1  # signs kept
    cae.calibration = cal
    assert cae.from_volts(volts(UP=0.30 + 0.49, ROLL=-0.2)).axes == (0.0,) * 6  # inside the shifted deadband
    assert cae.from_volts(volts(UP=0.30 + 0.52)).axis("z") > 0
    with pytest.raises(CalibrationError, match="deadman"):
        cae.calibrate_null([volts(D1=5.0)])
    with pytest.raises(CalibrationError, match="cae_yaw"):
        cae.calibrate_null([volts(YAW=0.0), volts(YAW=1.0)])
    with pytest.raises(CalibrationError, match="no samples"):
        cae.calibrate_null([])


def test_polarity_table_is_one_table():
    assert [a for _, a, _ in CAE_AXES] == ["z", "x", "y", "yaw", "pitch", "roll"]


def test_through_the_fake_adc_on_the_fake_rack():
    import drivers.adc as adc_mod
    import fakes.rack as rack_mod
    from pfma.rack import load_rack

    rack = load_rack()
    fake_rack = rack_mod.FakeRack.from_config(rack)
    adc_board = rack.board(rack.channel("cae_up_down").board)
    fake_adc = fake_rack[adc_board.name]
    adc = adc_mod.Dvme611(fake_rack, adc_board.base)
    cae = CaeHandController(rack=rack, clock=fake_rack.clock)
    for sig, v in (("cae_up_down", 6.0), ("cae_right_left", -3.0), ("cae_yaw", 0.3),
                   ("cae_discrete_1", 5.0), ("cae_discrete_3", 5.0)):
        fake_adc.set_input_volts(rack.channel(sig).channel, v)
    st = cae.read(adc.read_volts)
    lsb = 20.0 / 4096
    assert st.valid and st.deadman and st.buttons == 0b101
    assert st.axis("z") == pytest.approx(shaped(6.0), abs=2 * lsb)
    assert st.axis("y") == pytest.approx(shaped(3.0), abs=2 * lsb)  # left (negative volts) is +y
    assert st.axis("yaw") == 0.0
    fake_adc.inject("no_answer")
    st = cae.read(adc.read_volts)
    assert st.fault and not st.deadman and "0xC0" in st.reason
