"""The service's motion envelope (issue 28 item 4): the last line of defence whatever the
controller does. A claim holder that commands what the controller never would (a rate
flipped every frame, a joint driven into its soft limit, a runaway) meets the service's
slew limit, braking distance and overspeed trip. Simulated time (``SimRig``)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bit3.layout import DAC_ENVELOPE, DAC_SLEWED, ServiceState
from ioservice.envelope import ENVELOPE_MARGIN_RAD, ServiceEnvelope
from ioservice.service import FAULT_OVERSPEED
from pfma.arm import JOINTS
from pfma.envelope import Envelope, default
from pfma.errors import ConfigError
from pfma.rack import load_rack, parse_rack
from sim.faults import FaultSet
from tests.ioservice.test_command_path import Ctl

P = 1 / 320
DEFAULT = load_rack()
LIMITS = [5.0, 5.0, 5.0, 2.5, 2.5, 2.5, 0.0]


def _armed(rig):
    ctl = Ctl(rig)
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    return ctl


def _messages(rig, code):
    return [m.text for m in rig.reader.messages() if m.code == code]


# --- the rack file ------------------------------------------------------------------------------
def test_the_default_envelope_is_the_nominal_arm():
    env = DEFAULT.envelope
    assert env.overspeed_factor == 1.2
    assert [j.joint for j in env.joints] == list(DEFAULT.joints)
    for j in env.joints:
        jf = next(f for f in JOINTS if f.name == j.joint)
        assert (j.soft_lo_rad, j.soft_hi_rad) == (jf.soft_lo_rad, jf.soft_hi_rad)
        assert j.slew_rad_s2 == pytest.approx(20 * jf.omega_fs_rad_s)


@pytest.mark.parametrize("section,needle", [
    ("[envelope.elbow_pitch]\nsoft_hi_deg = 20.0", "inside the nominal hard limits -150..10 deg"),
    ("[envelope.elbow_pitch]\nsoft_lo_deg = 0.0\nsoft_hi_deg = -5.0", "lo < hi"),
    ("[envelope.shoulder_pitch]\nbrake_rad_s2 = 50.0", "brake_rad_s2 50 must be in (0, 4.8]"),
    ("[envelope.wrist_roll]\nslew_rad_s2 = 0", "slew_rad_s2 0 must be in (0, 200]"),
    ("[envelope]\noverspeed_factor = 3", "overspeed_factor must be a number in (1, 2]"),
    ("[envelope]\nwrist_rol = {soft_lo_deg = 0}", "unknown key(s) wrist_rol"),
    ("[envelope.wrist_roll]\nsoft_lo = 0", "unknown key(s) soft_lo"),
    ("[envelope.wrist_roll]\nsoft_lo_deg = \"low\"", "must be a finite number"),
])
def test_an_envelope_the_nominal_arm_cannot_keep_is_refused_naming_the_line(section, needle):
    text = open(DEFAULT.source).read()
    if section.startswith("[envelope]\n"):  # keys of the default file's own [envelope] table
        if "overspeed_factor" in section:
            text = text.replace("overspeed_factor = 1.2", "", 1)
        text = text.replace("[envelope]\n", section + "\n", 1)
    else:
        text += "\n" + section + "\n"
    with pytest.raises(ConfigError) as err:
        parse_rack(text, "lab.toml")
    assert needle in str(err.value) and "lab.toml:" in str(err.value)


def test_a_lab_may_narrow_the_envelope():
    text = open(DEFAULT.source).read() + "\n[envelope.elbow_pitch]\nsoft_lo_deg = -120.0\nbrake_rad_s2 = 2.0\n"
    env = parse_rack(text, "lab.toml").envelope.of("elbow_pitch")
    assert env is not None and env.soft_lo_rad == pytest.approx(math.radians(-120)) and env.brake_rad_s2 == 2.0


# --- the slew limit -----------------------------------------------------------------------------
def test_a_rate_flipped_every_frame_is_slew_limited_and_named_once(rig):
    ctl = _armed(rig)
    seen = []
    sign = [1.0]

    def flip(info):
        sign[0] = -sign[0]
        ctl.cmd["joint_rate_rad_s"] = [0.39 * sign[0], 0, 0, 0, 0, 0]  # +-9.75 V on shoulder pitch
    rig.on_frame.insert(0, flip)

    def watch(info):
        seen.append(float(rig.world.bus["dac"].output_volts_all()[0]))
    rig.on_frame.append(watch)
    rig.run(1.0)
    volts = np.array(seen[5:])
    # 8 rad/s^2 x 3.125 ms = 0.025 rad/s (0.625 V) a frame: a small dither instead of +-9.75 V
    assert np.max(np.abs(volts)) < 1.0
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.ARMED and s.dac_status[0] & DAC_SLEWED
    assert len(_messages(rig, 173)) == 1 and "shoulder_pitch" in _messages(rig, 173)[0]
    assert rig.svc.envelope.slew_episodes == 1


def test_a_move_start_ramps_through_the_limit_counted_not_named(rig):
    ctl = _armed(rig)
    ctl.cmd["joint_rate_rad_s"] = [0.24, 0, 0, 0, 0, 0]
    rig.run(0.2)
    assert float(rig.world.bus["dac"].output_volts_all()[0]) == pytest.approx(0.24 / 0.04, abs=0.01)
    assert rig.svc.envelope.slew_episodes == 1 and _messages(rig, 173) == []
    ctl.cmd["joint_rate_rad_s"] = [0.0] * 6  # a stop is obeyed at once, never slowed
    rig.run_frames(2)
    assert float(rig.world.bus["dac"].output_volts_all()[0]) == 0.0


# --- the braking distance ---------------------------------------------------------------------------
def _joint_deg(rig, joint):
    from fakes.arm_params import AXES
    q = rig.world.sim.true_state().q
    return math.degrees(q[[a.joint for a in AXES].index(joint)])


@pytest.mark.parametrize("joint,rate", [("shoulder_pitch", 0.39), ("wrist_roll", -1.9), ("elbow_pitch", 0.49)])
def test_a_joint_driven_into_its_soft_limit_stops_inside_the_envelope(rig, joint, rate):
    """A claim holder drives one joint at ~full scale towards its soft limit and never stops
    (a controller without its soft limits): the service holds the rate at 0 V within the
    braking distance; the joint stops no further than the margin past the soft limit."""
    k = DEFAULT.joints.index(joint)
    order = list(rig.reader.layout.joint_names)
    ctl = _armed(rig)
    rates = [0.0] * 6
    rates[order.index(joint)] = rate
    ctl.cmd["joint_rate_rad_s"] = rates
    env = DEFAULT.envelope.joints[k]
    limit = env.soft_hi_rad if rate > 0 else env.soft_lo_rad
    furthest = [-math.inf]  # how far past the soft limit the joint ever got (negative: short of it)

    def track(info):
        q = math.radians(_joint_deg(rig, joint))
        furthest[0] = max(furthest[0], (q - limit) if rate > 0 else (limit - q))
    rig.on_frame.append(track)
    rig.run(12.0)
    assert furthest[0] <= ENVELOPE_MARGIN_RAD + math.radians(0.2), math.degrees(furthest[0])
    assert furthest[0] > -math.radians(5.0)  # it got there: held near the limit, not far before it
    s = rig.reader.read_inputs()
    ch = rig.svc.dac.rate_list[order.index(joint)]
    assert s.service_state == ServiceState.ARMED and s.dac_status[ch] & DAC_ENVELOPE
    assert len(_messages(rig, 174)) == 1 and joint in _messages(rig, 174)[0]
    # the rate away from the limit is obeyed at once
    rates[order.index(joint)] = -rate / 4
    ctl.cmd["joint_rate_rad_s"] = rates
    rig.run(0.3)
    assert not rig.reader.read_inputs().dac_status[ch] & DAC_ENVELOPE
    assert abs(rig.world.bus["dac"].output_volts_all()[ch]) > 0.5


@settings(max_examples=30, deadline=None)
@given(q=st.floats(-3.0, 3.0), u=st.floats(-2.0, 2.0), k=st.integers(0, 5))
def test_the_braking_distance_rule(q, u, k):
    """A rate toward the limit is held at 0 exactly when the joint's braking distance
    reaches the limit (plus the margin); a rate away is never held."""
    jf = JOINTS[k]
    env = Envelope(tuple(default(j) for j in JOINTS))
    e = ServiceEnvelope(env, [(j.name, i, i, i) for i, j in enumerate(JOINTS)], lambda *a: None)
    e.q[k] = q
    e.last[k] = u  # no slew in the way
    eng = [0.0] * 16
    eng[k] = u
    st_ = [0] * 16
    e.apply(eng, P, st_)
    je = env.joints[k]
    need = abs(u) * 0.03 + u * u / (2 * je.brake_rad_s2)
    room = (je.soft_hi_rad + ENVELOPE_MARGIN_RAD - q) if u > 0 else (q - je.soft_lo_rad + ENVELOPE_MARGIN_RAD)
    held = u != 0 and room <= need
    assert (eng[k] == 0.0) == (held or u == 0.0)
    assert bool(st_[k] & DAC_ENVELOPE) == held
    assert jf.name == je.joint


# --- overspeed on the service's own inputs ----------------------------------------------------------
def test_a_runaway_trips_the_service_on_its_own_inputs(rig):
    """A reversed tach makes the amplifier's rate loop positive feedback; whatever the claim
    holder keeps commanding, the service trips on the resolver rate (or the tach at full
    scale): every channel 0 V, brakes set, the joint and the figure named."""
    ctl = _armed(rig)
    FaultSet(rig.world).inject("tach-reversed:shoulder_yaw")
    ctl.cmd["joint_rate_rad_s"] = [0.0, 0.05, 0, 0, 0, 0]
    start = _joint_deg(rig, "shoulder_yaw")
    for _ in range(640):
        rig.run_frames(1)
        if rig.reader.read_inputs().service_state == ServiceState.FAULT:
            break
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.FAULT and s.fault_code == FAULT_OVERSPEED
    text = [m.text for m in rig.reader.messages() if "overspeed" in m.text]
    assert text and "shoulder_yaw" in text[0]
    assert np.all(np.asarray(rig.world.bus["dac"].output_volts_all()) == 0.0)
    rig.run(1.0)
    assert abs(_joint_deg(rig, "shoulder_yaw") - start) < 10.0
