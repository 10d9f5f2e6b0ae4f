"""The nominal arm's joint table: one place that the service, the controller and the
file checks read (issue 28: the envelope and the file checks need it without ``fakes``).

Source for every joint number below: pfma-model.md section 8 (the project's nominal
PFMA model; ALL VALUES ASSUMED there, the real PFMA data are not public):

- 8.2 joint limits (hard and soft), full-scale rate omega_fs at a 10 V command, the
  software rate limit omega_lim = 0.6 omega_fs, and I_max (current at a 10 V limit);
- 8.3 effective inertia, viscous and Coulomb friction (for predictions and braking distances).

Joints are listed in the Bit3 command-area order (``bit3.layout`` joint_names):
shoulder pitch, shoulder yaw, elbow pitch, wrist yaw, wrist pitch, wrist roll.
``fakes.arm_params`` holds the simulated arm's own truth (which a test may make depart
from this table); this table is what the software *expects* of the arm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SOURCE = "pfma-model.md 8.2-8.4 (nominal model, assumed)"
DEG = math.pi / 180.0
#: the amplifier's rate-loop bandwidth lambda (1/s) of pfma-model.md 8.4 (assumed there):
#: K_a = lambda J / (N eta K_t K_w), so the motor current per rad/s of rate error is
#: lambda J / (N eta K_t) (controller.params and controller.supervision use this one value)
RATE_LOOP_LAMBDA = 40.0
#: the 10 Hz tach filter cards' time constant (s): IRSS report 3.6.3 (sourced), pfma-model 8.4
TACH_TAU_S = 1.0 / (2.0 * math.pi * 10.0)
#: the anti-aliasing filter board in front of the A/D (IRSS report 3.4.2, sourced: "four
#: pole low pass" filters on the tach, motor-current and CAE hand-controller channels).
#: ASSUMED (the schematics are not public): Butterworth, corner 40 Hz (half the 80 Hz
#: Nyquist frequency of the 160 Hz A/D rate), unity gain. The simulator models it
#: (fakes/anti_alias.py); the joint supervision allows for its lag.
ANTI_ALIAS_HZ = 40.0
ANTI_ALIAS_POLES = 4


def butterworth_zetas(poles: int = ANTI_ALIAS_POLES) -> tuple[float, ...]:
    """The damping ratios of a Butterworth low-pass's pole pairs (``poles`` even)."""
    return tuple(math.sin(math.pi * (2 * k + 1) / (2 * poles)) for k in range(poles // 2))


def anti_alias_delay_s(corner_hz: float = ANTI_ALIAS_HZ, poles: int = ANTI_ALIAS_POLES) -> float:
    """The group delay at DC of the Butterworth anti-aliasing filter (s): the lag its
    channels' readings carry, sum over the pole pairs of 2 zeta / w (10.4 ms at 40 Hz)."""
    return sum(2.0 * z for z in butterworth_zetas(poles)) / (2.0 * math.pi * corner_hz)


#: Current limit while powered up, as a fraction of I_max. Assumed (this project): half
#: of I_max holds the counterbalanced arm with margin (192 N*m max at the shoulder vs
#: ~47 N*m residual gravity) and halves the torque in a collision; the controller, the demo
#: controller and the service's envelope (its braking deceleration) use this one figure.
RUN_CURRENT_FRACTION = 0.5
#: the rate servo cards' gain adjustment switch (IRSS report 3.6.1, sourced: "a gain
#: adjustment switch is provided" on each joint's card): its positions as a factor on the
#: rate loop's lambda (K_a). ASSUMED (the card's drawings are not public): three positions,
#: half, nominal and double; the nominal model of pfma-model 8.4 is the middle one.
GAIN_SWITCH_POSITIONS = {"low": 0.5, "nominal": 1.0, "high": 2.0}


@dataclass(frozen=True)
class JointFacts:
    """One joint's nominal limits and amplifier data (pfma-model.md 8.2-8.4)."""

    name: str  #: command-area joint name
    hard_lo_rad: float
    hard_hi_rad: float
    soft_lo_rad: float
    soft_hi_rad: float
    omega_fs_rad_s: float  #: joint rate at a full-scale 10 V rate command
    i_max_a: float  #: motor current at a 10 V current-limit command
    inertia_kg_m2: float  #: decoupled effective inertia (8.3), for the prediction model
    viscous_nm_s: float  #: joint-side viscous friction (8.3), for the prediction model
    gear_n: float  #: gear ratio N (8.2)
    k_t_nm_per_a: float  #: motor torque constant K_t (8.2)
    coulomb_nm: float = 0.0  #: joint-side Coulomb friction (8.3), for the prediction model
    eta: float = 0.8  #: gear efficiency (8.2)
    #: the rate servo card's gain switch as set on the chassis (GAIN_SWITCH_POSITIONS), a
    #: factor on the rate loop's lambda; 1: nominal (``servo.gain_switch`` sets it)
    gain_switch: float = 1.0

    @property
    def rate_loop_lambda(self) -> float:
        """The rate loop's bandwidth lambda (1/s) with this joint's gain switch (8.4)."""
        return RATE_LOOP_LAMBDA * self.gain_switch

    @property
    def torque_per_amp(self) -> float:
        """N eta K_t: joint torque per motor ampere (8.2)."""
        return self.gear_n * self.eta * self.k_t_nm_per_a

    @property
    def omega_lim_rad_s(self) -> float:
        """Software rate limit: 0.6 omega_fs (8.2)."""
        return 0.6 * self.omega_fs_rad_s

    @property
    def k_w_v_per_rad_s(self) -> float:
        """Rate scale of command and tach: 10 V / omega_fs (8.4)."""
        return 10.0 / self.omega_fs_rad_s

    @property
    def amp_gain_a_per_rad_s(self) -> float:
        """The amplifier's motor current per rad/s of rate error, K_a K_w = lambda J / (N eta K_t)
        (pfma-model.md 8.4)."""
        return self.rate_loop_lambda * self.inertia_kg_m2 / self.torque_per_amp

    @property
    def breakaway_rate_rad_s(self) -> float:
        """The smallest rate command that moves the joint from rest: below it the amplifier's
        torque at zero speed, N eta K_t K_a K_w u = lambda J u, does not beat the Coulomb
        friction (pfma-model.md 8.3-8.4; nominal values, gravity not counted)."""
        return self.coulomb_nm / (self.rate_loop_lambda * self.inertia_kg_m2)

    @property
    def breakaway_current_a(self) -> float:
        """The smallest current limit whose torque beats the Coulomb friction: coulomb / (N eta K_t)."""
        return self.coulomb_nm / self.torque_per_amp

    @property
    def centre_rad(self) -> float:
        """Middle of the hard range: resolver angles (0..2 pi) are unwrapped around it."""
        return 0.5 * (self.hard_lo_rad + self.hard_hi_rad)


#: pfma-model.md 8.2 (limits, omega_fs, I_max, N, K_t) and 8.3 (inertia, viscous and Coulomb friction)
JOINTS: tuple[JointFacts, ...] = (
    JointFacts("shoulder_pitch", -30 * DEG, 120 * DEG, -25 * DEG, 115 * DEG, 0.40, 10.0, 40.0, 20.0, 200, 0.12, 8.0),
    JointFacts("shoulder_yaw", -150 * DEG, 150 * DEG, -145 * DEG, 145 * DEG, 0.40, 10.0, 40.0, 20.0, 200, 0.12, 8.0),
    JointFacts("elbow_pitch", -150 * DEG, 10 * DEG, -145 * DEG, 5 * DEG, 0.50, 10.0, 12.0, 20.0, 150, 0.12, 8.0),
    JointFacts("wrist_yaw", -110 * DEG, 110 * DEG, -105 * DEG, 105 * DEG, 1.00, 5.0, 0.6, 2.0, 100, 0.06, 1.0),
    JointFacts("wrist_pitch", -110 * DEG, 110 * DEG, -105 * DEG, 105 * DEG, 1.00, 5.0, 0.6, 2.0, 100, 0.06, 1.0),
    JointFacts("wrist_roll", -180 * DEG, 180 * DEG, -175 * DEG, 175 * DEG, 2.00, 5.0, 0.08, 2.0, 60, 0.06, 1.0),
)
JOINT_NAMES: tuple[str, ...] = tuple(j.name for j in JOINTS)
#: gripper I_max (A): the current at a 10 V current-limit command (the rack's 0.5 A/V
#: current-limit scale x 10 V, rack_default.toml); the gripper is not a servoed joint
GRIPPER_I_MAX_A = 5.0
N_JOINTS = len(JOINTS)


@dataclass(frozen=True)
class GripperFacts:
    """The end effector's nominal jaw: the seventh amplifier (IRSS report section 1: "7 pulse
    width modulated amplifiers (6 DOF + end effector)"; 3.6: seven PWM/rate servo cards). The
    rack drives it with DAC channel 6 (gripper command: a rate, 10 V = ``omega_fs_m_s``) and
    13 (its current limit), and senses its rate (ADC 15, tach volts) and motor current (ADC
    7); it has no position sensor and no brake.

    Every figure but ``i_max_a`` is this project's assumption (the report gives none; named
    once here, used by the controller, the script handle and the simulated arm, and listed in
    docs/simulated-arm.md "The gripper")."""

    travel_m: float  #: jaw opening from closed (0) to fully open, m
    omega_fs_m_s: float  #: jaw speed at a full-scale 10 V command, m/s (opening positive)
    gear_n: float  #: motor rad per m of jaw travel (lead screw)
    k_t_nm_per_a: float  #: motor torque constant
    i_max_a: float  #: motor current at a 10 V current-limit command (the rack's scale)
    mass_kg: float  #: reflected mass of the jaw drive (rotor inertia x N^2), kg
    coulomb_n: float  #: jaw-side Coulomb friction, N
    viscous_n_s_m: float  #: jaw-side viscous friction, N*s/m
    eta: float = 0.8  #: screw efficiency

    @property
    def force_per_amp(self) -> float:
        """N eta K_t: jaw force per motor ampere (N/A); at a stall the grip force is this
        times the current limit (the amplifier saturates there)."""
        return self.gear_n * self.eta * self.k_t_nm_per_a

    @property
    def force_max_n(self) -> float:
        """Grip force at I_max (N)."""
        return self.force_per_amp * self.i_max_a

    @property
    def k_w_v_per_m_s(self) -> float:
        """Rate scale of command and tach: 10 V / omega_fs (V per m/s)."""
        return 10.0 / self.omega_fs_m_s


#: the nominal jaw (assumed, this project): 0..100 mm travel, 50 mm/s at 10 V, 40 N per
#: ampere (200 N at I_max 5 A), 100 kg reflected mass (its rate card's K_a is then
#: lambda J / (N eta K_t K_w) = 0.5 A/V: a full-scale command saturates at any current
#: limit, so a stalled jaw presses with the force the current limit sets), 2 N + 20 N*s/m friction
GRIPPER = GripperFacts(travel_m=0.10, omega_fs_m_s=0.05, gear_n=500.0, k_t_nm_per_a=0.10,
                       i_max_a=GRIPPER_I_MAX_A, mass_kg=100.0, coulomb_n=2.0, viscous_n_s_m=20.0)


def joint(name: str) -> JointFacts:
    """Facts of one joint by its command-area name."""
    for j in JOINTS:
        if j.name == name:
            return j
    raise KeyError(f"no joint {name!r}; joints: {', '.join(JOINT_NAMES)}")


def unwrap_angle(angle_rad: float, centre_rad: float) -> float:
    """A resolver angle (0..2 pi) mapped into the 2 pi window centred on ``centre_rad``."""
    return centre_rad + (angle_rad - centre_rad + math.pi) % (2.0 * math.pi) - math.pi


# --- the manually indexed shoulder roll (pfma-model.md 8.1) -------------------------------------
#: The shoulder roll is indexed by hand, not servoed: a constant mount transform before joint 1,
#: ``T_world_base = T_mount Rx(phi_SR)`` (T_mount = identity here), at one of these positions
#: (deg; 45 deg steps, default 0). It has no sensor: the controller takes it as a parameter the
#: operator sets and confirms (docs/controller.md "The shoulder-roll index").
SHOULDER_ROLL_STEPS_DEG: tuple[int, ...] = (-90, -45, 0, 45, 90)


def shoulder_roll_text(deg: float) -> str:
    """An index position as the tools say it: ``+45 deg``, ``0 deg``, ``-90 deg``."""
    return f"{deg:+g} deg" if deg else "0 deg"


#: the positions in words, for every refusal of another value
SHOULDER_ROLL_STEPS_TEXT = (", ".join(shoulder_roll_text(d) for d in SHOULDER_ROLL_STEPS_DEG)
                            + " (45 deg steps, pfma-model 8.1)")


def check_shoulder_roll_deg(deg: float) -> int:
    """``deg`` as an index position (an int), or a :class:`ValueError` naming the positions."""
    try:
        value = float(deg)
    except (TypeError, ValueError):
        raise ValueError(f"shoulder roll {deg!r} is not a number; the index positions are "
                         f"{SHOULDER_ROLL_STEPS_TEXT}") from None
    if value not in SHOULDER_ROLL_STEPS_DEG:
        raise ValueError(f"shoulder roll {value:g} deg is not an index position; the shoulder roll is indexed "
                         f"by hand at {SHOULDER_ROLL_STEPS_TEXT}")
    return int(value)
