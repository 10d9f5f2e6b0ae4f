"""Facts about the arm the controller layers use, copied once, with their source.

Source for every joint number below: pfma-model.md section 8 (the project's nominal
PFMA model; ALL VALUES ASSUMED there, the real PFMA data are not public):

- 8.2 joint limits (hard and soft), full-scale rate omega_fs at a 10 V command, the
  software rate limit omega_lim = 0.6 omega_fs, and I_max (current at a 10 V limit);
- 8.4 brake sequencing: "Power-up sequence: set the rate command to 0 V, then raise
  the current limit; the brake then releases." "Safe stop: rate command 0 V, wait
  for |qdot| < 0.01 rad/s or 0.5 s, then current limit 0 V, which engages the brake."
  Brake engaged below V_ilim 0.3 V, released above 0.5 V;
- 8.4 computer-side joint loop: qdot_cmd = qdot_ff + C_j(s) (q_cmd - q), default
  C_j = K_p = 8 1/s, optional lead/lag (section 5), omega_lim saturation;
- 8.4 amplifier rate loop (for the servo's step-response prediction): tach filter
  tau_f = 15.9 ms (10 Hz), K_a = lambda J / (N eta K_t K_w) with lambda = 40 rad/s,
  effective inertia 8.3 and viscous friction 8.3.

Joints are listed in the Bit3 command-area order (``bit3.layout`` joint_names):
shoulder pitch, shoulder yaw, elbow pitch, wrist yaw, wrist pitch, wrist roll.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

SOURCE = "pfma-model.md 8.2-8.4 (nominal model, assumed)"
DEG = math.pi / 180.0


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
    eta: float = 0.8  #: gear efficiency (8.2)

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
    def centre_rad(self) -> float:
        """Middle of the hard range: resolver angles (0..2 pi) are unwrapped around it."""
        return 0.5 * (self.hard_lo_rad + self.hard_hi_rad)


#: pfma-model.md 8.2 (limits, omega_fs, I_max, N, K_t) and 8.3 (inertia, viscous friction)
JOINTS: tuple[JointFacts, ...] = (
    JointFacts("shoulder_pitch", -30 * DEG, 120 * DEG, -25 * DEG, 115 * DEG, 0.40, 10.0, 40.0, 20.0, 200, 0.12),
    JointFacts("shoulder_yaw", -150 * DEG, 150 * DEG, -145 * DEG, 145 * DEG, 0.40, 10.0, 40.0, 20.0, 200, 0.12),
    JointFacts("elbow_pitch", -150 * DEG, 10 * DEG, -145 * DEG, 5 * DEG, 0.50, 10.0, 12.0, 20.0, 150, 0.12),
    JointFacts("wrist_yaw", -110 * DEG, 110 * DEG, -105 * DEG, 105 * DEG, 1.00, 5.0, 0.6, 2.0, 100, 0.06),
    JointFacts("wrist_pitch", -110 * DEG, 110 * DEG, -105 * DEG, 105 * DEG, 1.00, 5.0, 0.6, 2.0, 100, 0.06),
    JointFacts("wrist_roll", -180 * DEG, 180 * DEG, -175 * DEG, 175 * DEG, 2.00, 5.0, 0.08, 2.0, 60, 0.06),
)
JOINT_NAMES: tuple[str, ...] = tuple(j.name for j in JOINTS)
N_JOINTS = len(JOINTS)
#: current-limit channels of the command area: the six joints, then the gripper
N_CURRENT_LIMITS = 7
#: gripper I_max (A): the rack's 0.5 A/V current-limit scale x 10 V (rack_default.toml)
GRIPPER_I_MAX_A = 5.0

#: 8.4 default computer-side joint loop gain K_p (1/s)
DEFAULT_KP_PER_S = 8.0
#: Current limit while powered up, as a fraction of I_max. Assumed (this project): half
#: of I_max holds the counterbalanced arm with margin (192 N*m max at the shoulder vs
#: ~47 N*m residual gravity) and halves the torque in a collision; the demo controller
#: uses the same figures.
RUN_CURRENT_FRACTION = 0.5
#: 8.4 brake released above this current-limit command (volts = 10 I / I_max)
BRAKE_RELEASE_V = 0.5
#: 8.4 safe stop: wait for |qdot| below this, or for SAFE_STOP_TIMEOUT_S, before limits go to 0
SAFE_STOP_RATE_RAD_S = 0.01
SAFE_STOP_TIMEOUT_S = 0.5
#: 8.4 amplifier rate loop: lambda (rad/s) and the 10 Hz tach filter time constant (s)
RATE_LOOP_LAMBDA = 40.0
TACH_TAU_S = 1.0 / (2.0 * math.pi * 10.0)


def joint(name: str) -> JointFacts:
    """Facts of one joint by its command-area name."""
    for j in JOINTS:
        if j.name == name:
            return j
    raise KeyError(f"no joint {name!r}; joints: {', '.join(JOINT_NAMES)}")


def run_current_limits_a() -> tuple[float, ...]:
    """Default current limits while powered up: RUN_CURRENT_FRACTION x I_max, gripper 0."""
    return tuple(RUN_CURRENT_FRACTION * j.i_max_a for j in JOINTS) + (0.0,)


def unwrap_angle(angle_rad: float, centre_rad: float) -> float:
    """A resolver angle (0..2 pi) mapped into the 2 pi window centred on ``centre_rad``."""
    return centre_rad + (angle_rad - centre_rad + math.pi) % (2.0 * math.pi) - math.pi
