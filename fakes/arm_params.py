"""Nominal parameters of the simulated PFMA: one table, one place.

Source for every number below, unless a line says otherwise: the project's
nominal arm model, pfma-model.md sections 8.1-8.7 (ALL VALUES ASSUMED there:
the real PFMA data are not public), and the IRSS report section 3.6 (seven
PWM/rate servo cards incl. the gripper, six brake release cards, 10 Hz one-pole
tach filter cards). The facts are copied in here; nothing reads the reference
files at run time. The gripper axis has no published numbers at all: its row is
this project's assumption, :data:`pfma.arm.GRIPPER` (one place for the controller and
this simulator).

Axis order everywhere in the simulator is the DH order SY, SP, EP, WP, WY, WR,
then the gripper (index 6). Rotary axes are in rad, rad/s, N*m, kg*m^2; the
gripper is a linear jaw opening in m, m/s, N, kg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pfma.arm import ANTI_ALIAS_HZ, GAIN_SWITCH_POSITIONS, GRIPPER

SOURCE = "pfma-model.md 8.1-8.7 (nominal model, assumed); IRSS report 3.6"
_G = GRIPPER  # the gripper's row below

DEG = math.pi / 180.0


@dataclass(frozen=True)
class AxisParams:
    """One servoed axis: limits, gearing, amplifier and friction (per pfma-model.md 8.2-8.4)."""

    name: str  #: short name: SY, SP, EP, WP, WY, WR, GR
    label: str  #: long name
    joint: str  #: the rack configuration's joint name (channel key ``joint``)
    hard_lo: float  #: hard stop, rad (gripper: m)
    hard_hi: float  #: hard stop, rad (gripper: m)
    soft_lo: float  #: software limit (information only; the controller enforces it)
    soft_hi: float
    gear_n: float  #: gear ratio N
    omega_fs: float  #: joint rate at a full-scale 10 V command, rad/s (gripper: m/s)
    k_t: float  #: motor torque constant, N*m/A
    i_max_a: float  #: amplifier current at a 10 V current limit, A
    inertia: float  #: decoupled effective inertia incl. reflected rotor, kg*m^2 (gripper: kg)
    coulomb: float  #: joint-side Coulomb friction, N*m (gripper: N)
    viscous: float  #: joint-side viscous friction, N*m*s/rad (gripper: N*s/m)
    counterbalanced: bool  #: 90 % of link gravity removed (J1-J5)
    brake: bool  #: brake fitted (six joints; the gripper has none, IRSS 3.6)
    has_angle: bool = True  #: resolver fitted (the gripper has none in the rack)
    eta: float = 0.8  #: gear efficiency

    @property
    def k_w(self) -> float:
        """Rate scale, V per rad/s (gripper: V per m/s): 10 V / omega_fs (8.4)."""
        return 10.0 / self.omega_fs

    @property
    def torque_per_amp(self) -> float:
        """N * eta * K_t: joint torque per motor ampere (8.2)."""
        return self.gear_n * self.eta * self.k_t

    @property
    def torque_max(self) -> float:
        """Joint torque at I_max (8.2 last column)."""
        return self.torque_per_amp * self.i_max_a


#: The seven axes. Columns per pfma-model.md 8.2 (limits, N, omega_fs, K_t, I_max) and
#: 8.3 (inertia, friction); counterbalance on J1-J5 (8.3 names J2-J4; J1 and J5: see
#: below); brakes on the six joints (IRSS 3.6).
#:
#: Assumed (this project), SHOULDER_YAW_COUNTERBALANCED and WRIST_YAW_COUNTERBALANCED: the
#: arm's counterbalances (IRSS report section 1: "counter balanced at the shoulder, elbow and
#: wrist", and a spring counterbalance near the wrist) balance the links about the shoulder
#: point and about the wrist centre, so they take 90 % of the link gravity off the shoulder
#: yaw and the wrist yaw as well as off the pitch joints. 8.3 names J2-J4 because with the
#: shoulder roll at 0 the shoulder yaw axis is vertical (no gravity on it at all) and the
#: wrist yaw carries little (the 4 kg of link 6 at 0.22 m). Once the hand-indexed shoulder
#: roll (8.1) tilts them, without this the nominal arm could not hold its ready pose at any
#: index but 0: 246 N*m on the shoulder yaw at +45 deg against 192 N*m at I_max, and 6.1
#: N*m on the wrist yaw that its weak rate loop (0.5 A/V) holds only with a 0.3 rad/s
#: command, which the supervision takes for a stall.
SHOULDER_YAW_COUNTERBALANCED = True
WRIST_YAW_COUNTERBALANCED = True
AXES: tuple[AxisParams, ...] = (
    AxisParams("SY", "Shoulder Yaw", "shoulder_yaw", -150 * DEG, 150 * DEG,
               -145 * DEG, 145 * DEG, 200, 0.40, 0.12, 10.0, 40.0, 8.0, 20.0, SHOULDER_YAW_COUNTERBALANCED,
               True),
    AxisParams("SP", "Shoulder Pitch", "shoulder_pitch", -30 * DEG, 120 * DEG,
               -25 * DEG, 115 * DEG, 200, 0.40, 0.12, 10.0, 40.0, 8.0, 20.0, True, True),
    AxisParams("EP", "Elbow Pitch", "elbow_pitch", -150 * DEG, 10 * DEG,
               -145 * DEG, 5 * DEG, 150, 0.50, 0.12, 10.0, 12.0, 8.0, 20.0, True, True),
    AxisParams("WP", "Wrist Pitch", "wrist_pitch", -110 * DEG, 110 * DEG,
               -105 * DEG, 105 * DEG, 100, 1.00, 0.06, 5.0, 0.6, 1.0, 2.0, True, True),
    AxisParams("WY", "Wrist Yaw", "wrist_yaw", -110 * DEG, 110 * DEG,
               -105 * DEG, 105 * DEG, 100, 1.00, 0.06, 5.0, 0.6, 1.0, 2.0, WRIST_YAW_COUNTERBALANCED, True),
    AxisParams("WR", "Wrist Roll", "wrist_roll", -180 * DEG, 180 * DEG,
               -175 * DEG, 175 * DEG, 60, 2.00, 0.06, 5.0, 0.08, 1.0, 2.0, False, True),
    # the gripper: the nominal jaw of pfma.arm.GRIPPER (assumed, this project; one place for
    # the controller, the script handle and this simulator): opening 0..0.10 m, 0.05 m/s at
    # 10 V, 40 N/A (N = 500 rotor rad per m of jaw travel), 5 A (the rack's 0.5 A/V scale),
    # 100 kg reflected mass (lead screw), friction 2 N + 20 N*s/m; no brake, no resolver, no
    # gravity. Its "soft limits" are information only (the controller ends moves on a stall).
    AxisParams("GR", "Gripper", "gripper", 0.0, _G.travel_m, 0.005, _G.travel_m - 0.005,
               _G.gear_n, _G.omega_fs_m_s, _G.k_t_nm_per_a, _G.i_max_a, _G.mass_kg, _G.coulomb_n,
               _G.viscous_n_s_m, False, False, has_angle=False, eta=_G.eta),
)

N_AXES = len(AXES)
N_JOINTS = 6  #: the six arm joints (resolver + DH); axis 6 is the gripper

#: Assumed (this project), BRAKE_LOGIC_ON_15V: the brake release cards' threshold logic
#: (release above 0.5 V of current limit, engage below 0.3 V; pfma-model 8.4) is analog and
#: runs on the servo chassis' +/-15 V, so with the +/-15 V DC-DC converter off no card
#: switches the +28 VDC to its release coil and every brake stays set (IRSS 3.6.2 says only
#: that the cards apply 28 VDC to the coils when the front-panel switches are on and the
#: current-limit threshold is raised). Used by the front-panel fault ``panel-off:15v``.
BRAKE_LOGIC_ON_15V = True


@dataclass(frozen=True)
class DhRow:
    """Standard (distal) DH row: T_i = Rz(q_i + offset) Tz(d) Tx(a) Rx(alpha) (8.1)."""

    offset_rad: float
    d_m: float
    a_m: float
    alpha_rad: float


#: pfma-model.md 8.1 DH table (SY, SP, EP, WP, WY, WR).
DH: tuple[DhRow, ...] = (
    DhRow(0.0, 0.0, 0.0, 90 * DEG),
    DhRow(0.0, 0.0, 0.90, 0.0),
    DhRow(0.0, 0.0, 0.90, 0.0),
    DhRow(0.0, 0.0, 0.0, -90 * DEG),
    DhRow(90 * DEG, 0.0, 0.0, 90 * DEG),
    DhRow(0.0, 0.30, 0.0, 0.0),
)


@dataclass(frozen=True)
class PointMass:
    """A lumped mass fixed in DH frame ``frame`` (moved by joints 1..frame) (8.3)."""

    name: str
    mass_kg: float
    frame: int  #: DH frame index 1..6
    com_m: tuple[float, float, float]  #: centre of mass in that frame


#: pfma-model.md 8.3 link masses (arm total 44 kg moving).
LINK_MASSES: tuple[PointMass, ...] = (
    PointMass("upper arm", 20.0, 2, (-0.45, 0.0, 0.0)),
    PointMass("forearm", 12.0, 3, (-0.45, 0.0, 0.0)),
    PointMass("wrist", 8.0, 5, (0.0, 0.0, 0.0)),  # lumped at the wrist centre
    PointMass("roll + F/T + end effector", 4.0, 6, (0.0, 0.0, -0.08)),
)


@dataclass(frozen=True)
class ArmParams:
    """Everything the simulated arm needs besides the axis table."""

    axes: tuple[AxisParams, ...] = AXES
    dh: tuple[DhRow, ...] = DH
    link_masses: tuple[PointMass, ...] = LINK_MASSES
    gravity_m_s2: float = 9.81
    counterbalance_fraction: float = 0.9  #: 8.3: tau_cb = -0.9 tau_grav,links on J2-J4 (and J1, J5 here)
    rate_loop_lambda: float = 40.0  #: 8.4: K_a = lambda J / (N eta K_t K_w), rad/s
    tach_filter_hz: float = 10.0  #: IRSS 3.6.3 (sourced) / 8.4: tau_f = 15.9 ms
    #: the anti-aliasing board's 4-pole filters in front of the A/D on the tach, motor
    #: current and CAE channels (IRSS 3.4.2; corner assumed: pfma.arm.ANTI_ALIAS_HZ);
    #: None: not modelled (the simulator as it was before the board was)
    anti_alias_hz: float | None = ANTI_ALIAS_HZ
    #: each rate servo card's gain adjustment switch (IRSS 3.6.1), a factor on lambda (K_a):
    #: pfma.arm.GAIN_SWITCH_POSITIONS (assumed positions), nominal 1 on every axis. The
    #: amplifier gain spread (SimErrors.amp_gain_error) varies around it.
    gain_switch: tuple[float, ...] = (1.0,) * N_AXES
    brake_engage_v: float = 0.3  #: 8.4: brake engaged when V_ilim < 0.3 V
    brake_release_v: float = 0.5  #: 8.4: released when V_ilim > 0.5 V
    brake_slip_factor: float = 1.5  #: 8.4: slip torque = 1.5 x max joint torque
    dac_range_v: float = 10.0  #: 8.4: +-10 V DAC and ADC
    ft_offset_m: float = 0.20  #: 8.1: F/T frame 0.20 m from the wrist centre along z6
    tool_mass_kg: float = 1.5  #: 8.7: tool behind the sensor
    tool_com_m: float = 0.06  #: 8.7: tool centre of mass beyond the sensor along z6
    # Simulator choices (assumed, documented in docs/simulated-arm.md):
    stop_omega_rad_s: float = 300.0  #: hard stop stiffness k = J * omega^2 (also an object between the jaws)
    stop_zeta: float = 0.7  #: hard stop damping ratio
    max_substep_s: float = 1.0e-3  #: integration substep upper bound (1 kHz or finer)
    q_initial: tuple[float, ...] = (0.0, 30 * DEG, -90 * DEG, 60 * DEG, 0.0, 0.0, 0.05)
    #: q_ready of 8.1 (tool point (1.529, 0, -0.329) m), gripper half open

    @property
    def tau_f_s(self) -> float:
        """Tach filter time constant (1 / (2 pi 10 Hz) = 15.9 ms)."""
        return 1.0 / (2.0 * math.pi * self.tach_filter_hz)

    def k_a(self) -> tuple[float, ...]:
        """Amplifier rate-loop gains, A/V (8.4: 3.33, 3.33, 1.67, 0.50, 0.50, 0.22; gripper 0.1)."""
        return tuple(self.rate_loop_lambda * g * a.inertia / (a.torque_per_amp * a.k_w)
                     for a, g in zip(self.axes, self.gain_switch, strict=True))

    def __post_init__(self) -> None:
        bad = [g for g in self.gain_switch if g not in GAIN_SWITCH_POSITIONS.values()]
        if len(self.gain_switch) != len(self.axes) or bad:
            raise ValueError(f"gain_switch needs {len(self.axes)} positions of "
                             f"{sorted(GAIN_SWITCH_POSITIONS.values())}, got {self.gain_switch}")


NOMINAL = ArmParams()


@dataclass
class SimErrors:
    """Known, settable departures of the simulated truth from the nominal model.

    All zero by default. Calibration tests set them and check that a fit finds them;
    ``--sim-errors SEED`` draws a plausible set (:func:`sim.errors.seeded`). They are the
    fake's ground truth, never published in the Bit3 buffer.
    """

    resolver_offset_rad: tuple[float, ...] = (0.0,) * N_JOINTS
    """Added to each joint's resolver reading (resolver zero = DH zero + offset)."""
    tach_scale_error: tuple[float, ...] = (0.0,) * N_AXES
    """Fractional tach gain error: tach volts = K_w (1 + e) qdot (the rate loop sees it too)."""
    adc_gain_error: dict[str, float] = field(default_factory=dict)
    """Fractional ADC gain error per signal name: read = (1 + g) V + offset."""
    adc_offset_v: dict[str, float] = field(default_factory=dict)
    """ADC offset per signal name, volts."""
    dac_gain_error: dict[str, float] = field(default_factory=dict)
    """Fractional DAC gain error per signal name: amplifier sees (1 + g) V + offset."""
    dac_offset_v: dict[str, float] = field(default_factory=dict)
    """DAC offset per signal name, volts."""
    payload_kg: float = 0.0
    """Payload at the tool point (not counterbalanced; seen by the F/T sensor)."""
    brake_held: tuple[bool, ...] = (False,) * N_AXES
    """Motion fault: the axis's brake stays engaged whatever its current limit (a brake
    release card or its switch off, a seized brake; IRSS 3.6)."""
    amp_off: tuple[bool, ...] = (False,) * N_AXES
    """Motion fault: the axis's PWM output stage is off: no motor current whatever the
    rate command and current limit (IRSS 3.6: the servo chassis' PWM enable switches)."""
    load_nm: tuple[float, ...] = (0.0,) * N_AXES
    """Motion fault: an external torque on each axis, N*m (gripper: N): a snagged cable,
    an unexpected payload, a collision held against the arm."""
    amp_gain_error: tuple[float, ...] = (0.0,) * N_AXES
    """Fractional amplifier (rate servo card) gain spread per axis: K_a (1 + e). The rate
    loop's droop, and so the velocity a command gives under load, moves with it."""
    ft_offset: tuple[float, ...] = (0.0,) * 6
    """The F/T transducer's own bias at t = 0 (strain-gauge offset; N, N, N, N*m, N*m, N*m,
    sensor axes): read whatever the load."""
    ft_drift_per_s: tuple[float, ...] = (0.0,) * 6
    """How that bias drifts, per second of the simulated clock (thermal drift; same units
    per s): the bias at t is ft_offset + t * ft_drift_per_s."""
    adc_noise_counts: float = 0.0
    """Noise of every A/D conversion, counts (1 sigma, all A/D boards): the converter's
    transition noise and the wiring's pick-up. 0: a noiseless converter."""
    resolver_noise_counts: float = 0.0
    """Noise of every resolver reading, counts (1 sigma): pfma-model 8.4 "noise +-1 LSB".
    0: a noiseless converter."""
    noise_seed: int = 0
    """Seed of the noise generators (the same rack reads the same noise)."""
    # The servo control chassis' front-panel switches (IRSS 3.6), the operator's: kept
    # apart from the faults above (a seized brake, a failed stage) so that turning a switch
    # back on never clears one of them; the arm model combines both.
    panel_28v_off: bool = False
    """Central switch: the chassis' +28 VDC supply off. No PWM drive on any axis, no power
    for the brake release coils (every brake set whatever the current limit), and the
    +/-15 V DC-DC converter it feeds unpowered too (every effect of ``panel_15v_off``)."""
    panel_15v_off: bool = False
    """Central switch: the +/-15 V DC-DC converter off. The analog electronics are
    unpowered: the rate servo cards give no drive (no motor current on any axis), the
    motor-current monitors and the tach filter cards' buffers output 0 V, and the brake
    release cards' threshold logic sets every brake (:data:`BRAKE_LOGIC_ON_15V`)."""
    panel_pwm_off: tuple[bool, ...] = (False,) * N_AXES
    """Left switches: the axis's PWM output stage off (seven: six joints and the gripper):
    no motor current on that axis."""
    panel_brake_off: tuple[bool, ...] = (False,) * N_AXES
    """Right switches: +28 VDC to the joint's brake release circuit off (six joints; the
    gripper's entry has no effect, it has no brake): the brake stays set whatever the
    current limit."""

    def __post_init__(self) -> None:
        if len(self.resolver_offset_rad) != N_JOINTS:
            raise ValueError(f"resolver_offset_rad needs {N_JOINTS} values, got {len(self.resolver_offset_rad)}")
        if len(self.tach_scale_error) != N_AXES:
            raise ValueError(f"tach_scale_error needs {N_AXES} values, got {len(self.tach_scale_error)}")
        for name in ("brake_held", "amp_off", "load_nm", "panel_pwm_off", "panel_brake_off", "amp_gain_error"):
            if len(getattr(self, name)) != N_AXES:
                raise ValueError(f"{name} needs {N_AXES} values, got {len(getattr(self, name))}")
        for name in ("ft_offset", "ft_drift_per_s"):
            if len(getattr(self, name)) != 6:
                raise ValueError(f"{name} needs 6 values (Fx Fy Fz Tx Ty Tz), got {len(getattr(self, name))}")
        if self.adc_noise_counts < 0 or self.resolver_noise_counts < 0:
            raise ValueError("adc_noise_counts and resolver_noise_counts must be >= 0")
        if self.payload_kg < 0:
            raise ValueError(f"payload_kg must be >= 0, got {self.payload_kg}")
