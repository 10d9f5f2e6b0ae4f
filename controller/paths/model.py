"""Path buffers: :class:`Path` and :class:`PathPoint`, the path-file document
(:data:`FORMAT`, :data:`FORMAT_VERSION`), the checks every point, name and limit goes
through, and the pure edits (:func:`delete_points`, :func:`insert_point`,
:func:`move_point`, :func:`set_speed`, :func:`set_limits`) returning a new :class:`Path`.
Nothing here needs the controller.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from typing import Any, Iterable, Sequence

import numpy as np

from controller.trajectory import Limits
from pfma.errors import PfmaError
from pfma.gripper import ACTIONS as GRIPPER_ACTIONS, check_force
from pfma.arm import GRIPPER

FORMAT = "pfma-path"
#: version of the path file format; files of a newer version are refused. Version 2 added
#: points without an orientation (``"quat": null``: keep the tool's orientation) and gripper
#: events (points of kind "gripper"); a file with neither is still written as version 1, which
#: older programs read (:meth:`Path.needs_v2`)
FORMAT_VERSION = 2
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
#: "gripper": a gripper event (open, close, stop) at that pose, replayed in order with the motion
POINT_KINDS = ("teach", "capture", "edit", "gripper")
#: the gripper events a path may hold (pfma.gripper.ACTIONS but FORCE, which a request's force_n carries)
PATH_GRIPPER_ACTIONS = tuple(a for a in GRIPPER_ACTIONS if a != "force")

#: Defaults of a new path (assumed, this project): half the trajectory caps, so a
#: playback is slower than the coarse teleoperation limits (pfma-model 8.2).
DEFAULT_LIMITS = Limits(0.05, 0.1, 0.15, 0.2)


class PathError(PfmaError, ValueError):
    """A path file or edit is not valid; the message names the file, path and point."""


@dataclass(frozen=True)
class PathPoint:
    """One recorded pose. ``quat`` None: the point keeps the tool's orientation (resolved at
    playback start: the orientation of the point before it, or, for the first point, the
    tool's orientation when the playback starts; :func:`resolve_orientations`).
    ``v_lin_m_s``/``v_rot_rad_s``: speed override of the segment that ends at this point
    (None: the path's limits)."""

    pos_m: tuple[float, float, float]
    quat: tuple[float, float, float, float] | None
    kind: str = "capture"
    t_s: float = 0.0
    v_lin_m_s: float | None = None
    v_rot_rad_s: float | None = None
    gripper: str | None = None  #: kind "gripper": the event (``open``, ``close``, ``stop``)
    force_n: float | None = None  #: kind "gripper": its grip force (None: the one in force)

    def to_json(self) -> dict:
        d: dict[str, Any] = {"pos_m": [round(x, 9) for x in self.pos_m],
                             "quat": None if self.quat is None else [round(x, 12) for x in self.quat],
                             "kind": self.kind,
                             "t_s": round(self.t_s, 6)}
        if self.v_lin_m_s is not None:
            d["v_lin_m_s"] = self.v_lin_m_s
        if self.v_rot_rad_s is not None:
            d["v_rot_rad_s"] = self.v_rot_rad_s
        if self.gripper is not None:
            d["gripper"] = self.gripper
        if self.force_n is not None:
            d["force_n"] = self.force_n
        return d


def _check_pose(pos_m: Sequence[float], quat: Sequence[float] | None,
                where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`make_point`'s position (3 finite numbers) and quaternion (4 finite numbers of
    unit length, returned normalised, or None)."""
    try:
        p = np.asarray(pos_m, dtype=float).reshape(3)
        q = None if quat is None else np.asarray(quat, dtype=float).reshape(4)
    except (TypeError, ValueError) as err:
        raise PathError(f"{where}: position needs 3 numbers and quat 4 ({err})") from None
    if not (np.all(np.isfinite(p)) and (q is None or np.all(np.isfinite(q)))):
        raise PathError(f"{where}: position/quaternion not finite")
    if q is not None:
        n = float(np.linalg.norm(q))
        if abs(n - 1.0) > 1e-3:
            raise PathError(f"{where}: quaternion {q.tolist()} is not unit length (norm {n:.6f})")
        q = q / n
    return p, q


def _check_speeds(v_lin_m_s: float | None, v_rot_rad_s: float | None, where: str) -> None:
    """:func:`make_point`'s speed overrides: each a number > 0 or None."""
    for nm, val in (("v_lin_m_s", v_lin_m_s), ("v_rot_rad_s", v_rot_rad_s)):
        if val is not None and not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
            raise PathError(f"{where}: {nm} {val!r} must be a number > 0 (or absent)")


def _check_gripper(kind: str, gripper: str | None, force_n: float | None, where: str) -> float | None:
    """:func:`make_point`'s gripper event: an action and a grip force (as a float, or None)
    on a point of kind "gripper", neither on any other point. Returns the force."""
    if kind != "gripper":
        if gripper is not None or force_n is not None:
            raise PathError(f"{where}: gripper/force_n belong to a point of kind 'gripper', not {kind!r}")
        return force_n
    if gripper not in PATH_GRIPPER_ACTIONS:
        raise PathError(f"{where}: a gripper event needs gripper = one of {', '.join(PATH_GRIPPER_ACTIONS)}, "
                        f"not {gripper!r}")
    if force_n is None:
        return None
    # bool is an int to isinstance, but a grip force of True is a mistake in the file
    why = check_force(force_n, GRIPPER.force_max_n) if isinstance(force_n, (int, float)) \
        and not isinstance(force_n, bool) else f"grip force {force_n!r} is not a number"
    if why:
        raise PathError(f"{where}: {why}")
    return float(force_n)


def make_point(pos_m: Sequence[float], quat: Sequence[float] | None, kind: str = "capture", t_s: float = 0.0,
               v_lin_m_s: float | None = None, v_rot_rad_s: float | None = None, where: str = "point",
               gripper: str | None = None, force_n: float | None = None) -> PathPoint:
    """A checked :class:`PathPoint` (finite position, unit quaternion or None - keep the
    tool's orientation -, known kind, speeds > 0; a gripper event has an action of
    :data:`PATH_GRIPPER_ACTIONS` and a grip force within the gripper's range or none, and only
    a gripper event has them).

    :raises PathError: naming ``where``
    """
    p, q = _check_pose(pos_m, quat, where)
    if kind not in POINT_KINDS:
        raise PathError(f"{where}: kind {kind!r} is not one of {', '.join(POINT_KINDS)}")
    _check_speeds(v_lin_m_s, v_rot_rad_s, where)
    force_n = _check_gripper(kind, gripper, force_n, where)
    return PathPoint(tuple(float(x) for x in p), None if q is None else tuple(float(x) for x in q), kind,
                     float(t_s),
                     None if v_lin_m_s is None else float(v_lin_m_s),
                     None if v_rot_rad_s is None else float(v_rot_rad_s), gripper, force_n)


def check_name(name: str) -> str:
    """A path name: letters, digits, ``_ . -``, starting with a letter or digit, <= 64."""
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise PathError(f"path name {name!r} is not valid (letters, digits, '_', '.', '-'; "
                        f"starts with a letter or digit; at most 64 characters)")
    return name


def check_limits(lim: Sequence[float], where: str = "limits") -> Limits:
    try:
        out = Limits(*(float(x) for x in lim))
    except (TypeError, ValueError) as err:
        raise PathError(f"{where}: need v_lin_m_s, a_lin_m_s2, v_rot_rad_s, a_rot_rad_s2 ({err})") from None
    for nm, v in zip(Limits._fields, out):
        if not (math.isfinite(v) and v > 0):
            raise PathError(f"{where}: {nm} = {v!r} must be finite and > 0")
    return out


@dataclass(frozen=True)
class Path:
    """A path buffer: named, numbered, a list of poses in the world frame and its limits."""

    name: str
    id: int
    points: tuple[PathPoint, ...] = ()
    limits: Limits = DEFAULT_LIMITS
    revision: int = 0  #: saves so far (0: never saved)
    created: str = ""
    modified: str = ""
    note: str = ""

    @property
    def has_gripper(self) -> bool:
        """The path holds gripper events."""
        return any(p.kind == "gripper" for p in self.points)

    @property
    def needs_v2(self) -> bool:
        """The path's file must be format version 2: it holds points without an orientation
        and/or gripper events (the one version-bump rule)."""
        return self.has_gripper or any(p.quat is None for p in self.points)

    def to_json(self) -> dict:
        version = FORMAT_VERSION if self.needs_v2 else 1  # older readers still take the rest
        return {"format": FORMAT, "version": version, "name": self.name, "id": self.id,
                "revision": self.revision, "created": self.created, "modified": self.modified,
                "note": self.note, "frame": "world", "units": {"pos_m": "m", "quat": "w,x,y,z (tool in world)"},
                "limits": dict(zip(Limits._fields, self.limits)),
                "points": [p.to_json() for p in self.points]}

    @classmethod
    def from_json(cls, d: Any, where: str = "path") -> "Path":
        """Parse and check a path document: format and version, name, id, limits, points,
        revision, in that order (the first fault is the one reported).

        :raises PathError: naming ``where`` and the point index
        """
        ver = _read_version(d, where)
        name = d.get("name")
        try:
            check_name(name)
        except PathError as err:
            raise PathError(f"{where}: {err}") from None
        pid = d.get("id")
        if not isinstance(pid, int) or isinstance(pid, bool) or not 1 <= pid <= 2**31 - 1:
            raise PathError(f"{where}: id {pid!r} must be an integer 1 .. 2^31-1")
        lim = _read_limits(d, where)
        out = _read_points(d, ver, where)
        rev = d.get("revision", 0)
        if not isinstance(rev, int) or rev < 0:
            raise PathError(f"{where}: revision {rev!r} must be an integer >= 0")
        return cls(name, pid, out, lim, rev, str(d.get("created", "")), str(d.get("modified", "")),
                   str(d.get("note", "")))

    @property
    def length_m(self) -> float:
        p = np.array([x.pos_m for x in self.points]) if self.points else np.zeros((0, 3))
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0

    def describe(self) -> str:
        """Header and one line per point (``pfma path show``)."""
        lim = self.limits
        lines = [f"path {self.name} (id {self.id}, revision {self.revision}, {len(self.points)} points, "
                 f"{self.length_m:.3f} m)",
                 f"  limits: {lim.v_lin_m_s:g} m/s, {lim.a_lin_m_s2:g} m/s^2, {lim.v_rot_rad_s:g} rad/s, "
                 f"{lim.a_rot_rad_s2:g} rad/s^2   modified {self.modified or '-'}"]
        if self.note:
            lines.append(f"  note: {self.note}")
        if any(p.quat is None for p in self.points):
            lines.append("  points without an orientation keep the tool's: the point before's, or at the first the "
                         "tool's orientation when the playback starts")
        lines.append(f"  {'#':>4} {'kind':<7} {'t s':>8}  {'x m':>9} {'y m':>9} {'z m':>9}   "
                     f"{'qw':>8} {'qx':>8} {'qy':>8} {'qz':>8}  speed")
        for i, p in enumerate(self.points):
            sp = ""
            if p.v_lin_m_s is not None or p.v_rot_rad_s is not None:
                sp = f"{p.v_lin_m_s or '-'} m/s {p.v_rot_rad_s or '-'} rad/s"
            if p.kind == "gripper":
                sp = f"gripper {p.gripper}" + (f" {p.force_n:g} N" if p.force_n is not None else "")
            lines.append(f"  {i:>4} {p.kind:<7} {p.t_s:>8.3f}  " + " ".join(f"{x:>9.4f}" for x in p.pos_m)
                         + "   " + (" ".join(f"{x:>8.5f}" for x in p.quat) if p.quat is not None
                                    else f"{'keep the orientation before it':>35}") + f"  {sp}")
        return "\n".join(lines)


# --- reading a path document (Path.from_json) ---------------------------------------------


def _read_version(d: Any, where: str) -> int:
    """The format version of a path document: a :data:`FORMAT` object of a version 1 ..
    :data:`FORMAT_VERSION`."""
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise PathError(f"{where}: not a {FORMAT} document")
    ver = d.get("version")
    if not isinstance(ver, int) or ver < 1:
        raise PathError(f"{where}: bad format version {ver!r}")
    if ver > FORMAT_VERSION:
        raise PathError(f"{where}: format version {ver} is newer than this program's {FORMAT_VERSION}")
    return ver


def _read_limits(d: dict, where: str) -> Limits:
    """A path document's limits object; a limit it leaves out is :data:`DEFAULT_LIMITS`'."""
    lim_d = d.get("limits", {})
    if not isinstance(lim_d, dict):
        raise PathError(f"{where}: limits must be an object")
    return check_limits([lim_d.get(k, dv) for k, dv in zip(Limits._fields, DEFAULT_LIMITS)], f"{where}: limits")


def _read_points(d: dict, ver: int, where: str) -> tuple[PathPoint, ...]:
    """A path document's points, each checked by :func:`make_point`; a point without an
    orientation or a gripper event needs format version 2."""
    pts = d.get("points", [])
    if not isinstance(pts, list):
        raise PathError(f"{where}: points must be a list")
    out = []
    for i, p in enumerate(pts):
        w = f"{where}: point {i}"
        if not isinstance(p, dict):
            raise PathError(f"{w}: not an object")
        if p.get("quat") is None and ver < 2:
            raise PathError(f"{w}: no quat (a point without an orientation needs format version 2)")
        if p.get("kind") == "gripper" and ver < 2:
            raise PathError(f"{w}: a gripper event needs format version 2")
        out.append(make_point(p.get("pos_m"), p.get("quat"), p.get("kind", "capture"), p.get("t_s", 0.0),
                              p.get("v_lin_m_s"), p.get("v_rot_rad_s"), where=w,
                              gripper=p.get("gripper"), force_n=p.get("force_n")))
    return tuple(out)


# --- pure edits (each returns a new Path) ------------------------------------------------


def _index(path: Path, i: int, allow_end: bool = False) -> int:
    n = len(path.points) + (1 if allow_end else 0)
    j = i + len(path.points) if i < 0 else i
    if not 0 <= j < n:
        raise PathError(f"path {path.name}: point {i} does not exist ({len(path.points)} points)")
    return j


def delete_points(path: Path, indices: Iterable[int]) -> Path:
    """Without the points at ``indices``."""
    drop = {_index(path, i) for i in indices}
    return replace(path, points=tuple(p for k, p in enumerate(path.points) if k not in drop))


def insert_point(path: Path, index: int, pos_m: Sequence[float], quat: Sequence[float] | None = None,
                 kind: str = "edit") -> Path:
    """A new point before ``index`` (``len(points)`` appends). Without ``quat`` it keeps
    the tool's orientation (the point before it, or the tool's at playback start)."""
    j = _index(path, index, allow_end=True)
    t = path.points[j - 1].t_s if j > 0 else 0.0
    pt = make_point(pos_m, quat, kind, t, where=f"path {path.name}: inserted point {index}")
    return replace(path, points=path.points[:j] + (pt,) + path.points[j:])


def insert_gripper(path: Path, index: int, action: str, force_n: float | None = None) -> Path:
    """A gripper event before ``index`` (``len(points)`` appends) at the pose of the point
    before it (of the point after it when it is first): replayed once the arm has reached
    that pose, before the motion goes on.

    :raises PathError: no point to take the pose from, a bad action or force
    """
    j = _index(path, index, allow_end=True)
    if not path.points:
        raise PathError(f"path {path.name}: a gripper event needs a point to take its pose from")
    ref = path.points[j - 1] if j > 0 else path.points[0]
    pt = make_point(ref.pos_m, ref.quat, "gripper", ref.t_s, where=f"path {path.name}: gripper event {index}",
                    gripper=action, force_n=force_n)
    return replace(path, points=path.points[:j] + (pt,) + path.points[j:])


def move_point(path: Path, index: int, pos_m: Sequence[float] | None = None, quat: Sequence[float] | None = None,
               offset_m: Sequence[float] | None = None, keep_orientation: bool = False) -> Path:
    """Point ``index`` at a new position (or shifted by ``offset_m``) and/or orientation
    (``keep_orientation``: none of its own, it keeps the tool's)."""
    j = _index(path, index)
    p = path.points[j]
    pos = np.asarray(p.pos_m if pos_m is None else pos_m, dtype=float)
    if offset_m is not None:
        pos = pos + np.asarray(offset_m, dtype=float).reshape(3)
    q = None if keep_orientation else (p.quat if quat is None else quat)
    new = make_point(pos, q, p.kind, p.t_s, p.v_lin_m_s, p.v_rot_rad_s, where=f"path {path.name}: point {index}",
                     gripper=p.gripper, force_n=p.force_n)
    return replace(path, points=path.points[:j] + (new,) + path.points[j + 1:])


def set_speed(path: Path, indices: Iterable[int] | None = None, v_lin_m_s: float | None = None,
              v_rot_rad_s: float | None = None, clear: bool = False) -> Path:
    """Speed overrides of the segments ending at ``indices`` (None: every point), or their
    removal (``clear``)."""
    sel = range(len(path.points)) if indices is None else {_index(path, i) for i in indices}
    pts = list(path.points)
    for j in sel:
        p = pts[j]
        if clear:
            pts[j] = replace(p, v_lin_m_s=None, v_rot_rad_s=None)
        else:
            pts[j] = make_point(p.pos_m, p.quat, p.kind, p.t_s,
                                p.v_lin_m_s if v_lin_m_s is None else v_lin_m_s,
                                p.v_rot_rad_s if v_rot_rad_s is None else v_rot_rad_s,
                                where=f"path {path.name}: point {j}", gripper=p.gripper, force_n=p.force_n)
    return replace(path, points=tuple(pts))


def set_limits(path: Path, **kw: float) -> Path:
    """Path limits with some fields changed (``v_lin_m_s=...``)."""
    bad = set(kw) - set(Limits._fields)
    if bad:
        raise PathError(f"path {path.name}: unknown limit(s) {', '.join(sorted(bad))}; "
                        f"limits: {', '.join(Limits._fields)}")
    return replace(path, limits=check_limits(path.limits._replace(**kw), f"path {path.name}: limits"))


def resolve_orientations(points: Sequence[PathPoint], start_quat: Sequence[float]) -> tuple[PathPoint, ...]:
    """The points with every missing orientation filled in: the orientation of the point
    before (after it was filled in), the first point's ``start_quat`` (the tool's
    orientation when the playback starts). Points that have one are returned unchanged."""
    out = []
    prev = tuple(float(x) for x in np.asarray(start_quat, dtype=float).reshape(4))
    for p in points:
        if p.quat is None:
            p = replace(p, quat=prev)
        out.append(p)
        prev = p.quat  # type: ignore[assignment]
    return tuple(out)
