"""Forward kinematics of the simulated PFMA (simulator-private; the controller has its own).

Standard (distal) DH per pfma-model.md 8.1: ``T_i = Rz(q_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``.
Coordinates are in the *world* frame: world = base frame 0 rotated by the manually
indexed shoulder roll, ``T_world_base = Rx(phi_SR)`` (T_mount taken as identity),
so gravity is always ``(0, 0, -g)`` in world coordinates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from fakes.arm_params import DH, DhRow


def rot_x(angle_rad: float) -> np.ndarray:
    """4x4 homogeneous rotation about x."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


class Kinematics:
    """DH forward kinematics for the six arm joints.

    :param dh: DH rows (default: pfma-model.md 8.1)
    :param shoulder_roll_rad: the manual shoulder-roll index (8.1: -90..+90 deg in 45 deg steps)
    """

    def __init__(self, dh: Sequence[DhRow] = DH, shoulder_roll_rad: float = 0.0) -> None:
        self.dh = tuple(dh)
        self._offset = np.array([r.offset_rad for r in self.dh])
        self._d = np.array([r.d_m for r in self.dh])
        self._a = np.array([r.a_m for r in self.dh])
        self._ca = np.array([math.cos(r.alpha_rad) for r in self.dh])
        self._sa = np.array([math.sin(r.alpha_rad) for r in self.dh])
        # rows 0 and 1 of each DH matrix are ct * U + st * V and ct * W + st * U
        n = len(self.dh)
        self._U = np.zeros((n, 4))
        self._U[:, 0] = 1.0
        self._U[:, 3] = self._a
        self._V = np.zeros((n, 4))
        self._V[:, 1] = -self._ca
        self._V[:, 2] = self._sa
        self._W = np.zeros((n, 4))
        self._W[:, 1] = self._ca
        self._W[:, 2] = -self._sa
        self._A = np.zeros((n, 4, 4))
        self._A[:, 2, 1] = self._sa
        self._A[:, 2, 2] = self._ca
        self._A[:, 2, 3] = self._d
        self._A[:, 3, 3] = 1.0
        self.shoulder_roll_rad = shoulder_roll_rad

    @property
    def shoulder_roll_rad(self) -> float:
        return self._roll

    @shoulder_roll_rad.setter
    def shoulder_roll_rad(self, value: float) -> None:
        self._roll = float(value)
        self._base = rot_x(self._roll)

    def frames(self, q_rad: Sequence[float]) -> np.ndarray:
        """World transforms of frames 0..6, shape (7, 4, 4); frame 0 is the shoulder base.

        :param q_rad: the six joint angles (extra entries, e.g. the gripper, are ignored)
        """
        n = len(self.dh)
        th = np.asarray(q_rad, dtype=float)[:n] + self._offset
        ct, st = np.cos(th)[:, None], np.sin(th)[:, None]
        A = self._A
        A[:, 0, :] = ct * self._U + st * self._V
        A[:, 1, :] = ct * self._W + st * self._U
        out = np.empty((n + 1, 4, 4))
        out[0] = self._base
        for i in range(n):
            np.matmul(out[i], A[i], out=out[i + 1])
        return out

    def tool_pose(self, q_rad: Sequence[float]) -> np.ndarray:
        """World transform of the tool frame 6 (origin = tool point)."""
        return self.frames(q_rad)[-1]

    def tool_point(self, q_rad: Sequence[float]) -> np.ndarray:
        """World position of the tool point, m."""
        return self.frames(q_rad)[-1, :3, 3].copy()

    @staticmethod
    def position_jacobian(frames: np.ndarray, point_m: np.ndarray, n_joints: int | None = None) -> np.ndarray:
        """3 x n Jacobian of a point fixed to the last link: column i = z_{i-1} x (p - o_{i-1})."""
        n = (frames.shape[0] - 1) if n_joints is None else n_joints
        z = frames[:n, :3, 2]
        o = frames[:n, :3, 3]
        return np.cross(z, point_m - o).T
