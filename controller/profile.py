"""The rest-to-rest trapezoidal velocity profile: one piece of arithmetic shared by the
trajectory planner's Cartesian segments (:mod:`controller.trajectory`) and the joint
planner's joint moves (:mod:`controller.layers`), in a module of its own so neither layer
imports the other's."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Trapezoid:
    """Rest-to-rest trapezoidal velocity profile over ``distance`` (any unit).

    ``t_acc`` accelerating at ``a``, ``t_flat`` at ``v_peak``, ``t_acc`` decelerating;
    a triangle (``t_flat`` = 0) when the distance is too short to reach ``v_max``.
    """

    distance: float
    v_peak: float
    a: float
    t_acc: float
    t_flat: float

    @property
    def duration_s(self) -> float:
        return 2.0 * self.t_acc + self.t_flat

    def sample(self, t_s: float) -> tuple[float, float, float]:
        """(position, velocity, acceleration) at time ``t_s`` (clamped to the ends)."""
        if self.distance <= 0.0 or t_s <= 0.0:
            return (0.0, 0.0, 0.0) if t_s <= 0.0 or self.distance <= 0.0 else (self.distance, 0.0, 0.0)
        ta, tf, a, v = self.t_acc, self.t_flat, self.a, self.v_peak
        if t_s < ta:
            return 0.5 * a * t_s * t_s, a * t_s, a
        d_acc = 0.5 * a * ta * ta
        if t_s < ta + tf:
            return d_acc + v * (t_s - ta), v, 0.0
        td = t_s - ta - tf
        if td < ta:
            return d_acc + v * tf + v * td - 0.5 * a * td * td, v - a * td, -a
        return self.distance, 0.0, 0.0


def plan_trapezoid(distance: float, v_max: float, a_max: float) -> Trapezoid:
    """The fastest rest-to-rest trapezoid covering ``distance`` within ``v_max``/``a_max``.

    :raises ValueError: a negative distance or a non-positive limit
    """
    if not (distance >= 0.0 and math.isfinite(distance)):
        raise ValueError(f"profile distance {distance!r} must be finite and >= 0")
    if not (v_max > 0.0 and a_max > 0.0 and math.isfinite(v_max) and math.isfinite(a_max)):
        raise ValueError(f"profile limits v_max={v_max!r}, a_max={a_max!r} must be finite and > 0")
    if distance == 0.0:
        return Trapezoid(0.0, 0.0, a_max, 0.0, 0.0)
    t_acc = v_max / a_max
    if a_max * t_acc * t_acc >= distance:  # never reaches v_max: triangle
        t_acc = math.sqrt(distance / a_max)
        return Trapezoid(distance, a_max * t_acc, a_max, t_acc, 0.0)
    return Trapezoid(distance, v_max, a_max, t_acc, (distance - a_max * t_acc * t_acc) / v_max)
