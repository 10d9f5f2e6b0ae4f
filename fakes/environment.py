"""Virtual surroundings of the simulated arm: contact objects for the F/T sensor.

Contact is a point contact at the **tool point** (origin of DH frame 6, pfma-model.md
8.1) against penalty objects: a spring-damper along the surface normal, unilateral
(an object only pushes), no tangential friction. Positions are in the world frame
of :mod:`fakes.kinematics` (shoulder base, z up; equal to base frame 0 when the
shoulder roll index is 0). All stiffness/damping defaults are simulator choices
(assumed), stiff enough to feel like metal through a 0.1 m/s approach yet slow
enough for the 1 kHz substep (see docs/simulated-arm.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class ContactObject(Protocol):
    def force_n(self, point_m: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
        """Force (N, world frame) the object applies to a point at ``point_m`` moving at ``velocity_m_s``."""
        ...


def _penalty(depth_m: float, normal: np.ndarray, velocity_m_s: np.ndarray,
             stiffness_n_m: float, damping_n_s_m: float) -> np.ndarray:
    """Unilateral spring-damper along ``normal`` (unit, pointing out of the object)."""
    approach = float(normal @ velocity_m_s)  # > 0 while leaving
    f = stiffness_n_m * depth_m - damping_n_s_m * approach
    return normal * f if f > 0.0 else np.zeros(3)


@dataclass
class Wall:
    """A stiff infinite plane. Free space is on the side ``normal`` points to.

    :param point_m: a point on the surface, world frame, m
    :param normal: outward normal (normalised on construction)
    """

    point_m: Sequence[float]
    normal: Sequence[float]
    stiffness_n_m: float = 2.0e4
    damping_n_s_m: float = 400.0

    def __post_init__(self) -> None:
        self.point_m = np.asarray(self.point_m, dtype=float)
        n = np.asarray(self.normal, dtype=float)
        norm = float(np.linalg.norm(n))
        if norm == 0.0:
            raise ValueError("wall normal must not be zero")
        self.normal = n / norm
        if self.stiffness_n_m < 0 or self.damping_n_s_m < 0:
            raise ValueError("stiffness and damping must be >= 0")

    def depth_m(self, point_m: np.ndarray) -> float:
        """Penetration depth, m (negative: in free space)."""
        return -float(self.normal @ (point_m - self.point_m))

    def clearance_m(self, point_m: np.ndarray) -> float:
        """Distance from the surface, m (<= 0: touching)."""
        return -self.depth_m(point_m)

    def force_n(self, point_m: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
        depth = self.depth_m(point_m)
        if depth <= 0.0:
            return np.zeros(3)
        return _penalty(depth, self.normal, velocity_m_s, self.stiffness_n_m, self.damping_n_s_m)


@dataclass
class Box:
    """A solid axis-aligned box; a point inside is pushed out through the nearest face.

    :param centre_m: box centre, world frame, m
    :param half_size_m: half extents along x, y, z, m
    """

    centre_m: Sequence[float]
    half_size_m: Sequence[float]
    stiffness_n_m: float = 2.0e4
    damping_n_s_m: float = 400.0

    def __post_init__(self) -> None:
        self.centre_m = np.asarray(self.centre_m, dtype=float)
        self.half_size_m = np.asarray(self.half_size_m, dtype=float)
        if np.any(self.half_size_m <= 0):
            raise ValueError(f"box half sizes must be > 0, got {self.half_size_m}")

    def clearance_m(self, point_m: np.ndarray) -> float:
        """Distance from the box, m (<= 0: inside)."""
        outside = np.maximum(np.abs(point_m - self.centre_m) - self.half_size_m, 0.0)
        return float(np.linalg.norm(outside)) if outside.any() else 0.0

    def force_n(self, point_m: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
        rel = point_m - self.centre_m
        depth_each = self.half_size_m - np.abs(rel)
        if np.any(depth_each <= 0.0):
            return np.zeros(3)
        axis = int(np.argmin(depth_each))
        normal = np.zeros(3)
        normal[axis] = 1.0 if rel[axis] >= 0.0 else -1.0
        return _penalty(float(depth_each[axis]), normal, velocity_m_s,
                        self.stiffness_n_m, self.damping_n_s_m)


class Environment:
    """The contact objects around the arm (empty: free space).

    :param objects: walls, boxes or anything with ``force_n(point_m, velocity_m_s)``
    """

    def __init__(self, objects: Iterable[ContactObject] = ()) -> None:
        self.objects: list[ContactObject] = list(objects)

    def __repr__(self) -> str:
        return f"Environment({self.objects!r})"

    def add(self, obj: ContactObject) -> ContactObject:
        self.objects.append(obj)
        return obj

    def clear(self) -> None:
        self.objects.clear()

    @property
    def active(self) -> bool:
        """True when there is anything to touch."""
        return bool(self.objects)

    def clearance_m(self, point_m: np.ndarray) -> float:
        """Smallest distance from the point to any object, m (0 for objects that cannot tell)."""
        return min((obj.clearance_m(point_m) if hasattr(obj, "clearance_m") else 0.0
                    for obj in self.objects), default=math.inf)

    def contact_force_n(self, point_m: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
        """Total force on the tool point, N, world frame."""
        total = np.zeros(3)
        for obj in self.objects:
            total += obj.force_n(point_m, velocity_m_s)
        return total


def point_load_wrench(rot_world_sensor: np.ndarray, force_world_n: np.ndarray,
                      lever_sensor_m: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Wrench at the sensor origin, in sensor axes, of a force applied at ``lever_sensor_m``.

    :param rot_world_sensor: 3x3 rotation of the sensor frame in the world frame
    :param force_world_n: the force, world frame, N
    :param lever_sensor_m: point of application in sensor coordinates, m
    :returns: (force_n[3], torque_nm[3]) in the sensor frame
    """
    f = rot_world_sensor.T @ np.asarray(force_world_n, dtype=float)
    return f, np.cross(np.asarray(lever_sensor_m, dtype=float), f)


def tool_gravity_wrench(rot_world_sensor: np.ndarray, mass_kg: float, com_along_z_m: float,
                        gravity_m_s2: float = 9.81) -> tuple[np.ndarray, np.ndarray]:
    """Tool gravity seen by the F/T sensor (pfma-model.md 8.7: 1.5 kg, 0.06 m along z6).

    :returns: (force_n[3], torque_nm[3]) in the sensor frame, torque about the sensor origin
    """
    weight = np.array([0.0, 0.0, -mass_kg * gravity_m_s2])
    return point_load_wrench(rot_world_sensor, weight, (0.0, 0.0, com_along_z_m))
