"""Unit quaternions for the motion layers: (w, x, y, z), Hamilton product, "tool in world".

Convention (docs/controller.md, "Kinematics and the Joint Planner"): a quaternion ``q``
rotates a vector from the tool frame into the world frame, ``v_world = R(q) v_tool``,
and ``q_mul(a, b)`` is the rotation ``b`` followed by ``a`` (``R(a b) = R(a) R(b)``).
All functions take array-likes and return new float numpy arrays; ``q`` and ``-q`` are
the same rotation, functions that return an angle take the short way round.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

ArrayLike = Sequence[float] | np.ndarray

#: the identity rotation
Q_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def q_normalize(q: ArrayLike) -> np.ndarray:
    """``q`` scaled to unit length; raises ValueError for a zero (or non-finite) quaternion."""
    a = np.asarray(q, dtype=float).reshape(4)
    n = math.sqrt(float(a @ a))
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {a.tolist()} has no direction (norm {n})")
    return a / n


def q_mul(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Hamilton product ``a b`` (apply ``b`` first, then ``a``)."""
    aw, ax, ay, az = (float(v) for v in np.asarray(a, dtype=float).reshape(4))
    bw, bx, by, bz = (float(v) for v in np.asarray(b, dtype=float).reshape(4))
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def q_conj(q: ArrayLike) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    a = np.asarray(q, dtype=float).reshape(4)
    return np.array([a[0], -a[1], -a[2], -a[3]])


def q_to_matrix(q: ArrayLike) -> np.ndarray:
    """3x3 rotation matrix of ``q`` (normalised first)."""
    w, x, y, z = q_normalize(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def q_from_matrix(m: ArrayLike) -> np.ndarray:
    """Unit quaternion of a 3x3 rotation matrix (or the rotation part of a 4x4), w >= 0.

    Shepperd's method: divides by the largest of the four diagonal combinations, so it
    is accurate for every rotation including 180 degrees.
    """
    r = np.asarray(m, dtype=float)[:3, :3]
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = np.array([0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = np.array([(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = np.array([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = np.array([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s])
    if q[0] < 0.0:
        q = -q
    return q_normalize(q)


def q_from_axis_angle(axis: ArrayLike, angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about ``axis`` (normalised; a zero axis gives identity)."""
    a = np.asarray(axis, dtype=float).reshape(3)
    n = math.sqrt(float(a @ a))
    if n < 1e-15:
        return Q_IDENTITY.copy()
    h = 0.5 * float(angle_rad)
    return np.concatenate(([math.cos(h)], math.sin(h) * a / n))


def q_from_rotvec(rv: ArrayLike) -> np.ndarray:
    """Rotation of a rotation vector (axis times angle, rad)."""
    v = np.asarray(rv, dtype=float).reshape(3)
    return q_from_axis_angle(v, math.sqrt(float(v @ v)))


def q_to_rotvec(q: ArrayLike) -> np.ndarray:
    """Rotation vector (axis times angle, angle in [0, pi]) of ``q``: the short way round."""
    a = q_normalize(q)
    if a[0] < 0.0:
        a = -a
    v = a[1:]
    s = math.sqrt(float(v @ v))
    if s < 1e-12:
        return 2.0 * v  # small-angle limit
    angle = 2.0 * math.atan2(s, a[0])
    return v * (angle / s)


def q_angle(a: ArrayLike, b: ArrayLike) -> float:
    """Angle (rad, 0..pi) of the rotation taking ``b`` to ``a``."""
    d = q_mul(q_normalize(a), q_conj(q_normalize(b)))  # atan2 form: accurate near 0 and pi
    return 2.0 * math.atan2(math.sqrt(float(d[1:] @ d[1:])), abs(float(d[0])))


def q_slerp(a: ArrayLike, b: ArrayLike, s: float) -> np.ndarray:
    """Spherical interpolation from ``a`` (s = 0) to ``b`` (s = 1), the short way round."""
    qa, qb = q_normalize(a), q_normalize(b)
    d = float(qa @ qb)
    if d < 0.0:
        qb, d = -qb, -d
    if d > 0.9995:  # nearly equal: normalised linear interpolation is exact enough
        return q_normalize(qa + float(s) * (qb - qa))
    th = math.acos(d)
    st = math.sin(th)
    return (math.sin((1.0 - s) * th) / st) * qa + (math.sin(s * th) / st) * qb


def q_rotate(q: ArrayLike, v: ArrayLike) -> np.ndarray:
    """Vector ``v`` rotated by ``q`` (tool to world for a tool pose)."""
    return q_to_matrix(q) @ np.asarray(v, dtype=float).reshape(3)
