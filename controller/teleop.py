"""Teleoperation: hand-controller rate commands and force reflection to the CRL master.

Facts (pfma-model.md, ASSUMED there):

* 8.2 Cartesian teleoperation limits, which normally govern before the joint limits:
  coarse 0.15 m/s and 0.25 rad/s, vernier 0.03 m/s and 0.05 rad/s;
* 8.5 rate mode: ``v_cart = u v_max`` (u the shaped -1..1 demand of each axis); the
  deadman is active high, motion only while pressed; on release command zero rate and
  hold the current pose, without engaging the brakes;
* 8.6 force reflection to the force-reflecting hand controller (CRL):
  ``F_master = k_f F_tool`` with k_f = 0.25, saturated at the display limits 40 N and
  2 N*m, disabled when the synthetic round trip exceeds 0.5 s (section 6).

Hand-controller frame (drivers/crl/state.py): x forward, y left, z up, roll/pitch/yaw
about x/y/z - the orientation of the world frame (the arm's mount: frame 0 at q = 0 while
the shoulder roll index is 0), so in "world" mode axis i moves the tool along world axis
i whatever the index (up stays up: the kinematics take the index, pfma-model 8.1). In
"tool" mode the same numbers are taken in the tool frame.

All three sources (CAE, CRL, HID) are used in rate mode here: the CRL's number is the
master's position in its workspace (-1..1 = +-0.20 m / +-60 deg), so with rate mode the
master works like a spring-centred joystick. The 1:1 position mapping with the index
clutch (8.6) is not implemented (the world model has no CRL index button).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controller.worldmodel.var import UNIT_QUATERNION, Var, VarGroup, var

SOURCE = "pfma-model.md 8.2, 8.5, 8.6 (assumed)"
#: hand-controller sources, the rows of daq.hc_axes (bit3.layout.HAND_CONTROLLERS)
HC_SOURCES: tuple[str, ...] = ("cae", "crl", "hid")
HC_CAE, HC_CRL, HC_HID = 0, 1, 2
FRAME_WORLD, FRAME_TOOL = 0, 1
#: ``cart.hc_source`` and ``cart.hc_frame`` / ``force.frame`` by name
HC_SOURCE_NAMES = {n: s.upper() for n, s in enumerate(HC_SOURCES)}
FRAME_NAMES = {FRAME_WORLD: "WORLD", FRAME_TOOL: "TOOL"}
#: 8.2 Cartesian teleoperation limits (translation m/s, rotation rad/s)
COARSE_LIN_M_S, COARSE_ROT_RAD_S = 0.15, 0.25
VERNIER_LIN_M_S, VERNIER_ROT_RAD_S = 0.03, 0.05
#: 8.6 force reflection gain and display limits
REFLECT_GAIN = 0.25
REFLECT_FORCE_LIMIT_N = 40.0
REFLECT_TORQUE_LIMIT_NM = 2.0
#: 6 / 8.6: force reflection disabled above this round-trip delay (s)
REFLECT_MAX_ROUND_TRIP_S = 0.5


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


def rate_limits(vernier: bool) -> tuple[float, float]:
    """(linear m/s, angular rad/s) teleoperation limits (8.2)."""
    return (VERNIER_LIN_M_S, VERNIER_ROT_RAD_S) if vernier else (COARSE_LIN_M_S, COARSE_ROT_RAD_S)


def hc_twist(axes6, gain_lin_m_s, gain_rot_rad_s, vernier: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Rate mode: six shaped axes (-1..1) -> (linear m/s, angular rad/s) in the
    hand-controller frame.

    ``v_i = u_i gain_i`` per axis (8.5 with per-axis gains), scaled by the vernier/coarse
    ratio in vernier mode, then each vector limited in norm to the 8.2 limits.
    """
    u = np.clip(np.asarray(axes6, dtype=float).reshape(6), -1.0, 1.0)
    u = np.where(np.isfinite(u), u, 0.0)
    lin = u[:3] * np.asarray(gain_lin_m_s, dtype=float)
    rot = u[3:] * np.asarray(gain_rot_rad_s, dtype=float)
    if vernier:
        lin = lin * (VERNIER_LIN_M_S / COARSE_LIN_M_S)
        rot = rot * (VERNIER_ROT_RAD_S / COARSE_ROT_RAD_S)
    lim_lin, lim_rot = rate_limits(vernier)
    return _clip_norm(lin, lim_lin), _clip_norm(rot, lim_rot)


@dataclass(frozen=True)
class HcSample:
    """One hand-controller sample as it travels the (delayed) command path."""

    t_s: float  #: when the operator made it
    source: int
    axes: tuple[float, ...]
    deadman: bool


@dataclass(frozen=True)
class Telemetry:
    """What travels down to the operator: tool pose and the tool-point wrench (world)."""

    t_s: float
    pos_m: tuple[float, ...]
    quat: tuple[float, ...]
    force_n: tuple[float, ...]
    torque_nm: tuple[float, ...]


def reflect(force_world_n, torque_world_nm, round_trip_s: float, active: bool,
            gain: float = REFLECT_GAIN,
            max_round_trip_s: float = REFLECT_MAX_ROUND_TRIP_S) -> tuple[np.ndarray, np.ndarray, bool]:
    """Force reflection for the CRL master (8.6): ``k_f F``, saturated in norm at the
    display limits; zero and disabled when not ``active`` (CRL not the source, deadman
    released) or the round trip exceeds ``max_round_trip_s``.

    :returns: (force_n[3], torque_nm[3], enabled) in the hand-controller (world) frame
    """
    enabled = bool(active) and math.isfinite(round_trip_s) and round_trip_s <= max_round_trip_s + 1e-12
    if not enabled:
        return np.zeros(3), np.zeros(3), False
    f = _clip_norm(gain * np.asarray(force_world_n, dtype=float), REFLECT_FORCE_LIMIT_N)
    t = _clip_norm(gain * np.asarray(torque_world_nm, dtype=float), REFLECT_TORQUE_LIMIT_NM)
    return f, t, True


class TeleopVars(VarGroup, prefix="teleop", writer="cartesian"):
    """Teleoperation's world-model variables, written by the Cartesian layer: force
    reflection to the CRL and the tool as the operator sees it (after the downlink delay)."""

    reflect_force_n: Var[np.ndarray] = var(
        "task_io", "f8", (3,), [0.0] * 3, "N",
        doc="force to display on the CRL (hand-controller frame; not yet routed to the Bit3 area)")
    reflect_torque_nm: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "N*m",
                                             doc="torque to display on the CRL")
    reflect_enabled: Var[bool] = var("task_io", "b1", (), False,
                                     doc="force reflection on (CRL in use, deadman, round trip <= 0.5 s)")
    seen_pos_m: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "m",
                                      doc="tool position as the operator sees it (after the downlink delay)")
    seen_quat: Var[np.ndarray] = var("task_io", "f8", (4,), [1.0, 0.0, 0.0, 0.0], "1", valid=UNIT_QUATERNION,
                                     doc="tool orientation as the operator sees it")
    seen_force_n: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "N",
                                        doc="tool-point force as the operator sees it")


TELEOP = TeleopVars
