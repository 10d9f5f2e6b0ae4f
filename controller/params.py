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
- 8.1 the manually indexed shoulder roll's positions (-90..+90 deg in 45 deg steps;
  ``SHOULDER_ROLL_STEPS_DEG``), a parameter of the kinematics, not a servoed joint;
- 8.4 amplifier rate loop (for the servo's step-response prediction): tach filter
  tau_f = 15.9 ms (10 Hz), K_a = lambda J / (N eta K_t K_w) with lambda = 40 rad/s,
  effective inertia 8.3 and viscous friction 8.3.

Joints are listed in the Bit3 command-area order (``bit3.layout`` joint_names):
shoulder pitch, shoulder yaw, elbow pitch, wrist yaw, wrist pitch, wrist roll.
"""

from __future__ import annotations

# the joint table lives in pfma.arm (the service's envelope and the file checks read it too)
from pfma.arm import (  # noqa: F401  (re-exported: the controller's one import of arm facts)
    DEG, GRIPPER, GRIPPER_I_MAX_A, JOINT_NAMES, JOINTS, N_JOINTS, SOURCE, JointFacts, joint, unwrap_angle,
    GAIN_SWITCH_POSITIONS, RATE_LOOP_LAMBDA, RUN_CURRENT_FRACTION, TACH_TAU_S,
    SHOULDER_ROLL_STEPS_DEG, SHOULDER_ROLL_STEPS_TEXT, check_shoulder_roll_deg, shoulder_roll_text,
)

#: current-limit channels of the command area: the six joints, then the gripper
N_CURRENT_LIMITS = 7

#: 8.4 default computer-side joint loop gain K_p (1/s)
DEFAULT_KP_PER_S = 8.0
#: 8.4 brake released above this current-limit command (volts = 10 I / I_max)
BRAKE_RELEASE_V = 0.5
#: 8.4 safe stop: wait for |qdot| below this, or for SAFE_STOP_TIMEOUT_S, before limits go to 0
SAFE_STOP_RATE_RAD_S = 0.01
SAFE_STOP_TIMEOUT_S = 0.5
# 8.4 amplifier rate loop: lambda (RATE_LOOP_LAMBDA) and the 10 Hz tach filter time constant
# (TACH_TAU_S) come from pfma.arm, with RUN_CURRENT_FRACTION (the one value of each)


def run_current_limits_a() -> tuple[float, ...]:
    """Default current limits while powered up: RUN_CURRENT_FRACTION x I_max; the gripper's
    entry is the most its grip force may use (I_max: 200 N at 40 N/A; controller/gripper.py)."""
    return tuple(RUN_CURRENT_FRACTION * j.i_max_a for j in JOINTS) + (GRIPPER_I_MAX_A,)
