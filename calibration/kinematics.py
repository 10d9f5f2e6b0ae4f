"""Wrist orientation for the F/T payload fit: forward kinematics of the nominal PFMA.

The DH table is copied from the project's nominal model, pfma-model.md section 8.1
(ALL VALUES ASSUMED there): standard (distal) DH ``T_i = Rz(q_i + offset_i) Tz(d_i)
Tx(a_i) Rx(alpha_i)``; world = base rotated by the manually indexed shoulder roll,
``T_world_base = Rx(phi_SR)``; gravity is (0, 0, -g) in the world; the F/T sensor
frame is parallel to frame 6 (8.1), so only the rotation of frame 6 matters here.
"""

from __future__ import annotations

import math

import numpy as np

DEG = math.pi / 180.0
#: (offset_rad, d_m, a_m, alpha_rad) per joint SY SP EP WP WY WR; pfma-model.md 8.1
DH_8_1 = (
    (0.0, 0.0, 0.0, 90 * DEG),
    (0.0, 0.0, 0.90, 0.0),
    (0.0, 0.0, 0.90, 0.0),
    (0.0, 0.0, 0.0, -90 * DEG),
    (90 * DEG, 0.0, 0.0, 90 * DEG),
    (0.0, 0.30, 0.0, 0.0),
)
GRAVITY_M_S2 = 9.81


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
                     [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]])


def tool_pose(q_rad, shoulder_roll_rad: float = 0.0) -> np.ndarray:
    """World transform of frame 6 for the six joint angles (rad)."""
    c, s = math.cos(shoulder_roll_rad), math.sin(shoulder_roll_rad)
    t = np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])
    for qi, (off, d, a, alpha) in zip(np.asarray(q_rad, dtype=float)[:6], DH_8_1):
        t = t @ _dh(qi + off, d, a, alpha)
    return t


def gravity_in_sensor(q_rad, shoulder_roll_rad: float = 0.0, g_m_s2: float = GRAVITY_M_S2) -> np.ndarray:
    """Gravity acceleration (m/s^2) in F/T sensor axes at joint angles ``q_rad``."""
    rot = tool_pose(q_rad, shoulder_roll_rad)[:3, :3]
    return rot.T @ np.array([0.0, 0.0, -g_m_s2])
