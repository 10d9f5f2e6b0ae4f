"""Move-to requests: one world-model variable, ``msp.move_request``, so that a request is
applied whole (the world model applies each user write at once; several variables could be
applied in two frames).

``msp.move_request`` (16 floats; ``pfma controller move``, the console's MOVE TO and
:meth:`tools.console.control.ControllerLink.move_pose` write it):

=======  ==========================================================================
index    meaning
=======  ==========================================================================
0        request number: a new value is a new request (answered in
         ``msp.move_done_seq``, ``msp.result``, ``msp.result_text``)
1        kind: 0 STOP (the running move or playback decelerates to rest), 1 POSE,
         2 JOINTS
2..4     POSE: tool point x, y, z (m, world frame)
5..8     POSE: orientation qw, qx, qy, qz (tool in world); all 0: keep the tool's
         orientation
9..14    JOINTS: joint angles (rad, command-area order: shoulder pitch, shoulder yaw,
         elbow pitch, wrist yaw, wrist pitch, wrist roll)
15       largest tool rotation this move may make (rad); 0: ``msp.max_turn_rad``
=======  ==========================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from controller.paths.model import PathError

#: length of ``msp.move_request``
MOVE_REQUEST_LEN = 16


class MoveKind:
    STOP = 0
    POSE = 1
    JOINTS = 2
    NAMES = {0: "STOP", 1: "POSE", 2: "JOINTS"}


@dataclass(frozen=True)
class MoveRequest:
    """One move-to request (the layout in the module doc)."""

    seq: int
    kind: int
    pos_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] | None = None  #: None: keep the tool's orientation
    joints_rad: tuple[float, ...] = (0.0,) * 6
    max_turn_rad: float | None = None  #: None: msp.max_turn_rad

    # --- building (checked: one clear PathError) -------------------------------------------
    @classmethod
    def pose(cls, seq: int, pos_m: Sequence[float], quat: Sequence[float] | None = None,
             max_turn_rad: float | None = None) -> "MoveRequest":
        p = _finite(pos_m, 3, "the position (x, y, z m)")
        q = None
        if quat is not None:
            a = np.asarray(_finite(quat, 4, "the orientation (qw, qx, qy, qz)"))
            n = float(np.linalg.norm(a))
            if abs(n - 1.0) > 1e-3:
                raise PathError(f"orientation {a.tolist()} is not a unit quaternion (norm {n:.6f})")
            q = tuple(float(x) for x in a / n)
        return cls(int(seq), MoveKind.POSE, p, q, max_turn_rad=_turn(max_turn_rad))  # type: ignore[arg-type]

    @classmethod
    def joints(cls, seq: int, joints_rad: Sequence[float], max_turn_rad: float | None = None) -> "MoveRequest":
        return cls(int(seq), MoveKind.JOINTS, joints_rad=_finite(joints_rad, 6, "the joint angles"),
                   max_turn_rad=_turn(max_turn_rad))

    @classmethod
    def stop(cls, seq: int) -> "MoveRequest":
        return cls(int(seq), MoveKind.STOP)

    # --- the world-model variable ------------------------------------------------------------
    def to_array(self) -> np.ndarray:
        a = np.zeros(MOVE_REQUEST_LEN)
        a[0], a[1] = self.seq, self.kind
        a[2:5] = self.pos_m
        if self.quat is not None:
            a[5:9] = self.quat
        a[9:15] = self.joints_rad
        a[15] = self.max_turn_rad or 0.0
        return a

    @classmethod
    def from_array(cls, a: Sequence[float]) -> "MoveRequest":
        """Decode ``msp.move_request`` (no checks beyond the layout: the layer checks)."""
        v = np.asarray(a, dtype=float).reshape(MOVE_REQUEST_LEN)
        q = v[5:9]
        return cls(int(v[0]), int(v[1]), tuple(float(x) for x in v[2:5]),  # type: ignore[arg-type]
                   None if not q.any() else tuple(float(x) for x in q),  # type: ignore[arg-type]
                   tuple(float(x) for x in v[9:15]), float(v[15]) if v[15] > 0 else None)

    def describe(self) -> str:
        """The request in words (messages, the CLI)."""
        if self.kind == MoveKind.STOP:
            return "stop"
        if self.kind == MoveKind.JOINTS:
            return "joints " + ", ".join(f"{math.degrees(x):+.1f}" for x in self.joints_rad) + " deg"
        x, y, z = self.pos_m
        ori = ("keeping the tool's orientation" if self.quat is None
               else "q (" + ", ".join(f"{c:+.4f}" for c in self.quat) + ")")
        return f"pose ({x:+.4f}, {y:+.4f}, {z:+.4f}) m, {ori}"


def _finite(values: Sequence[float], n: int, what: str) -> tuple[float, ...]:
    try:
        a = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise PathError(f"{what}: {values!r} are not numbers") from None
    if a.shape[0] != n:
        raise PathError(f"{what}: {n} numbers needed, {a.shape[0]} given")
    if not np.all(np.isfinite(a)):
        raise PathError(f"{what}: {a.tolist()} not finite")
    return tuple(float(x) for x in a)


def _turn(max_turn_rad: float | None) -> float | None:
    if max_turn_rad is None:
        return None
    if not (math.isfinite(max_turn_rad) and 0.0 < max_turn_rad <= math.pi):
        raise PathError(f"largest tool rotation {max_turn_rad!r} rad must be > 0 and at most pi (180 deg)")
    return float(max_turn_rad)


__all__ = ["MoveRequest", "MoveKind", "MOVE_REQUEST_LEN"]
