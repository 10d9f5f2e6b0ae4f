"""Playback planning: the recorded points become key points (:func:`simplify`: teach
points always kept; continuously captured points reduced with a position/angle tolerance,
Douglas-Peucker on the pose) and each key point the target of one rest-to-rest segment
with the path's limits (:func:`plan_path`: per-point speed overrides, a playback speed
scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from controller.paths.model import Path, PathError, PathPoint, resolve_orientations
from controller.quat import q_angle, q_slerp
from controller.trajectory import DEFAULT_CAP, Limits, plan_segment

#: key-point tolerance of the playback plan (assumed): 1 mm, 1 degree
PLAN_TOL_M = 0.001
PLAN_TOL_RAD = math.radians(1.0)


def segment_deviation(x: np.ndarray, q: Sequence[float], p0: np.ndarray, q0: Sequence[float], p1: np.ndarray,
                      q1: Sequence[float], tol: tuple[float, float] | None = None) -> tuple[float, float]:
    """(distance m, angle rad) of the pose (``x``, ``q``) from the straight segment
    (p0, q0) -> (p1, q1) executed with one parameter: the point of the segment nearest
    ``x`` (by the orientation for a pure rotation), and the orientation there. With
    ``tol`` (m, rad) the parameter nearest by the orientation is tried too and the one
    with the smaller error relative to ``tol`` kept (a segment that mostly turns)."""
    d = p1 - p0
    L2 = float(d @ d)
    ang = q_angle(q0, q1)
    u_rot = min(1.0, q_angle(q0, q) / ang) if ang > 1e-9 else 0.0
    cands = [min(1.0, max(0.0, float((x - p0) @ d) / L2))] if L2 > 1e-12 else []
    if not cands or (tol is not None and ang > 1e-9):
        cands.append(u_rot)
    best = (math.inf, math.inf)
    for u in cands:
        e = (float(np.linalg.norm(x - (p0 + u * d))), q_angle(q, q_slerp(q0, q1, u)))
        if tol is None or max(e[0] / tol[0], e[1] / tol[1]) < max(best[0] / tol[0], best[1] / tol[1]):
            best = e
            if tol is None:
                break
    return best


def _pose_deviation(p: PathPoint, a: PathPoint, b: PathPoint) -> tuple[float, float]:
    """(distance m, angle rad) of ``p`` from the straight segment a->b (points with their
    orientations resolved)."""
    return segment_deviation(np.array(p.pos_m), p.quat, np.array(a.pos_m), a.quat,  # type: ignore[arg-type]
                             np.array(b.pos_m), b.quat)  # type: ignore[arg-type]


def simplify(points: Sequence[PathPoint], tol_m: float = PLAN_TOL_M, tol_rad: float = PLAN_TOL_RAD) -> list[int]:
    """Indices of the key points: the ends, every teach/edit point, and the captured points
    needed so that every point lies within ``tol_m`` and ``tol_rad`` of the straight
    segments between key points (Douglas-Peucker on the pose)."""
    n = len(points)
    if n <= 2:
        return list(range(n))
    fixed = [0] + [i for i in range(1, n - 1) if points[i].kind != "capture"] + [n - 1]
    keep = set(fixed)

    def rec(i: int, j: int) -> None:
        worst, k = 0.0, -1
        for m in range(i + 1, j):
            dm, da = _pose_deviation(points[m], points[i], points[j])
            e = max(dm / tol_m, da / tol_rad)
            if e > worst:
                worst, k = e, m
        if worst > 1.0:
            keep.add(k)
            rec(i, k)
            rec(k, j)

    for i, j in zip(fixed, fixed[1:]):
        if j - i > 1:
            rec(i, j)
    return sorted(keep)


@dataclass(frozen=True)
class PlannedSegment:
    """One segment of a playback: the target pose and its limits."""

    index: int  #: the path point it ends at
    pos_m: np.ndarray
    quat: np.ndarray
    limits: Limits
    gripper: str | None = None  #: a gripper event to do once the segment has ended (open/close/stop)
    force_n: float | None = None  #: its grip force (None: the one in force)


def offline_start_quat(path: Path) -> tuple[float, float, float, float]:
    """The orientation a plan made without the controller assumes for the tool at the start
    (``pfma path show --plan``): the first point's that has one, else the identity."""
    for p in path.points:
        if p.quat is not None:
            return p.quat
    return (1.0, 0.0, 0.0, 0.0)


def plan_path(path: Path, speed_scale: float = 1.0, tol_m: float = PLAN_TOL_M, tol_rad: float = PLAN_TOL_RAD,
              cap: Limits = DEFAULT_CAP, start_quat: Sequence[float] | None = None) -> list[PlannedSegment]:
    """The playback plan: one rest-to-rest segment per key point (:func:`simplify`).

    A gripper event (a point of kind "gripper") is a key point: its segment ends at the pose
    where the event was recorded (often where the arm already is: a segment of zero length),
    and the playback does the event there before the next segment.

    Points without an orientation keep the tool's (:func:`resolve_orientations`):
    ``start_quat`` is the tool's orientation when the playback starts (None: the one
    :func:`offline_start_quat` assumes).

    The segment into key point k has the path's limits, speeds times ``speed_scale``
    (0 < scale), lowered by the smallest speed override among the points it covers, all
    within ``cap`` (the Trajectory Planner's caps). The first segment starts wherever
    the tool is (the Trajectory Planner starts it from the present Cartesian command).

    :raises PathError: no points, or a bad speed scale
    """
    if not path.points:
        raise PathError(f"path {path.name}: no points to play")
    if not (math.isfinite(speed_scale) and speed_scale > 0):
        raise PathError(f"speed scale {speed_scale!r} must be > 0")
    points = resolve_orientations(path.points, offline_start_quat(path) if start_quat is None else start_quat)
    keys = simplify(points, tol_m, tol_rad)
    out = []
    prev = -1
    base = path.limits.scaled(speed_scale)
    for k in keys:
        covered = points[prev + 1:k + 1]
        vl = min([base.v_lin_m_s] + [p.v_lin_m_s * speed_scale for p in covered if p.v_lin_m_s])
        vr = min([base.v_rot_rad_s] + [p.v_rot_rad_s * speed_scale for p in covered if p.v_rot_rad_s])
        lim = Limits(vl, base.a_lin_m_s2, vr, base.a_rot_rad_s2).clipped(cap)
        p = points[k]
        out.append(PlannedSegment(k, np.array(p.pos_m), np.array(p.quat), lim, p.gripper, p.force_n))
        prev = k
    return out


def plan_duration_s(path: Path, start: PathPoint | None = None, speed_scale: float = 1.0) -> float:
    """Time the plan takes at its limits (without the hand-over gaps between segments),
    from ``start`` (default: point 0 with the orientation :func:`offline_start_quat`
    assumes)."""
    q_start = offline_start_quat(path) if start is None or start.quat is None else start.quat
    segs = plan_path(path, speed_scale, start_quat=q_start)
    t = 0.0
    p0 = np.array((start or path.points[0]).pos_m)
    q0 = np.array(q_start)
    for s in segs:
        t += plan_segment(p0, q0, s.pos_m, s.quat, s.limits).duration_s
        p0, q0 = s.pos_m, s.quat
    return t
