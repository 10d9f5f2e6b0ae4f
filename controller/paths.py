"""Multi-Segment Path Planner layer (20 Hz): record, store, edit, plan and play back paths.

IRSS report 2.2.1: "This layer manages tasks that handle multi-segment path manipulation
(recording and execution) and generates intermediate level commands for the Trajectory
Path Planner Layer which exists below it. ... Tasks at this layer execute at relatively
low frequencies (20 Hz)". 2.2.8: "a small menu tree within the multi-segment path
planner used to edit various path buffers" - here ``pfma path`` and :class:`PathStore`.

Three parts:

* **Path files** (:class:`Path`, :class:`PathStore`): one JSON file per path in a small
  directory (default ``$PFMA_PATH_DIR``, else ``$XDG_DATA_HOME/pfma/paths``, else
  ``~/.local/share/pfma/paths``). Files carry a format version (:data:`FORMAT_VERSION`)
  and a revision counter; they are written atomically (temporary file, fsync, rename)
  and a save refuses to overwrite a revision it did not load. Editing is pure functions
  (:func:`delete_points`, :func:`insert_point`, :func:`move_point`, :func:`set_speed`)
  returning a new :class:`Path`; nothing here needs the controller.
* **Planning** (:func:`simplify`, :func:`plan_path`): the recorded points become
  key points (teach points always kept; continuously captured points reduced with a
  position/angle tolerance, Douglas-Peucker on the pose) and each key point the target
  of one rest-to-rest segment with the path's limits (per-point speed overrides, a
  playback speed scale).
* **The layer** (:class:`MultiSegmentLayer`): ``msp.mode`` 1 records the measured tool
  pose ``joint.tool_pos_m``/``joint.tool_quat`` (a teach point each time ``msp.teach``
  changes; continuous capture whenever the pose moved ``msp.capture_dist_m`` or turned
  ``msp.capture_angle_rad`` since the last point) and saves the path under
  ``msp.path_id`` when the mode leaves 1; ``msp.mode`` 2 loads path ``msp.path_id``,
  plans it and hands the segments one at a time to the Trajectory Planner
  (:mod:`controller.trajectory`), the next one each time ``traj.done_seq`` reports the
  last one done. Mode 0 during a playback stops it (the Trajectory Planner decelerates).
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import numpy as np

from controller.decision import Status
from controller.layers import Layer
from controller.messages import Level
from controller.quat import q_angle, q_normalize, q_slerp
from controller.trajectory import DEFAULT_CAP, DoneCode, Limits, plan_segment, segment_specs
from controller.worldmodel import VarSpec
from pfma.errors import PfmaError

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

FORMAT = "pfma-path"
#: version of the path file format; files of a newer version are refused
FORMAT_VERSION = 1
#: environment variable naming the path directory
PATH_DIR_ENV = "PFMA_PATH_DIR"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")
POINT_KINDS = ("teach", "capture", "edit")

#: Defaults of a new path (assumed, this project): half the trajectory caps, so a
#: playback is slower than the coarse teleoperation limits (pfma-model 8.2).
DEFAULT_LIMITS = Limits(0.05, 0.1, 0.15, 0.2)
#: continuous capture thresholds (assumed): a point per 5 mm or 2 degrees
CAPTURE_DIST_M = 0.005
CAPTURE_ANGLE_RAD = math.radians(2.0)
#: key-point tolerance of the playback plan (assumed): 1 mm, 1 degree
PLAN_TOL_M = 0.001
PLAN_TOL_RAD = math.radians(1.0)


class PathError(PfmaError, ValueError):
    """A path file or edit is not valid; the message names the file, path and point."""


# ----------------------------------------------------------------------------------------
# paths


@dataclass(frozen=True)
class PathPoint:
    """One recorded pose. ``v_lin_m_s``/``v_rot_rad_s``: speed override of the segment that
    ends at this point (None: the path's limits)."""

    pos_m: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    kind: str = "capture"
    t_s: float = 0.0
    v_lin_m_s: float | None = None
    v_rot_rad_s: float | None = None

    def to_json(self) -> dict:
        d: dict[str, Any] = {"pos_m": [round(x, 9) for x in self.pos_m],
                             "quat": [round(x, 12) for x in self.quat], "kind": self.kind,
                             "t_s": round(self.t_s, 6)}
        if self.v_lin_m_s is not None:
            d["v_lin_m_s"] = self.v_lin_m_s
        if self.v_rot_rad_s is not None:
            d["v_rot_rad_s"] = self.v_rot_rad_s
        return d


def make_point(pos_m: Sequence[float], quat: Sequence[float], kind: str = "capture", t_s: float = 0.0,
               v_lin_m_s: float | None = None, v_rot_rad_s: float | None = None, where: str = "point") -> PathPoint:
    """A checked :class:`PathPoint` (finite position, unit quaternion, known kind, speeds > 0).

    :raises PathError: naming ``where``
    """
    try:
        p = np.asarray(pos_m, dtype=float).reshape(3)
        q = np.asarray(quat, dtype=float).reshape(4)
    except (TypeError, ValueError) as err:
        raise PathError(f"{where}: position needs 3 numbers and quat 4 ({err})") from None
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise PathError(f"{where}: position/quaternion not finite")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-3:
        raise PathError(f"{where}: quaternion {q.tolist()} is not unit length (norm {n:.6f})")
    q = q / n
    if kind not in POINT_KINDS:
        raise PathError(f"{where}: kind {kind!r} is not one of {', '.join(POINT_KINDS)}")
    for nm, val in (("v_lin_m_s", v_lin_m_s), ("v_rot_rad_s", v_rot_rad_s)):
        if val is not None and not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
            raise PathError(f"{where}: {nm} {val!r} must be a number > 0 (or absent)")
    return PathPoint(tuple(float(x) for x in p), tuple(float(x) for x in q), kind, float(t_s),
                     None if v_lin_m_s is None else float(v_lin_m_s),
                     None if v_rot_rad_s is None else float(v_rot_rad_s))


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

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": FORMAT_VERSION, "name": self.name, "id": self.id,
                "revision": self.revision, "created": self.created, "modified": self.modified,
                "note": self.note, "frame": "world", "units": {"pos_m": "m", "quat": "w,x,y,z (tool in world)"},
                "limits": dict(zip(Limits._fields, self.limits)),
                "points": [p.to_json() for p in self.points]}

    @classmethod
    def from_json(cls, d: Any, where: str = "path") -> "Path":
        """Parse and check a path document.

        :raises PathError: naming ``where`` and the point index
        """
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise PathError(f"{where}: not a {FORMAT} document")
        ver = d.get("version")
        if not isinstance(ver, int) or ver < 1:
            raise PathError(f"{where}: bad format version {ver!r}")
        if ver > FORMAT_VERSION:
            raise PathError(f"{where}: format version {ver} is newer than this program's {FORMAT_VERSION}")
        name = d.get("name")
        try:
            check_name(name)
        except PathError as err:
            raise PathError(f"{where}: {err}") from None
        pid = d.get("id")
        if not isinstance(pid, int) or isinstance(pid, bool) or not 1 <= pid <= 2**31 - 1:
            raise PathError(f"{where}: id {pid!r} must be an integer 1 .. 2^31-1")
        lim_d = d.get("limits", {})
        if not isinstance(lim_d, dict):
            raise PathError(f"{where}: limits must be an object")
        lim = check_limits([lim_d.get(k, dv) for k, dv in zip(Limits._fields, DEFAULT_LIMITS)], f"{where}: limits")
        pts = d.get("points", [])
        if not isinstance(pts, list):
            raise PathError(f"{where}: points must be a list")
        out = []
        for i, p in enumerate(pts):
            w = f"{where}: point {i}"
            if not isinstance(p, dict):
                raise PathError(f"{w}: not an object")
            out.append(make_point(p.get("pos_m"), p.get("quat"), p.get("kind", "capture"), p.get("t_s", 0.0),
                                  p.get("v_lin_m_s"), p.get("v_rot_rad_s"), where=w))
        rev = d.get("revision", 0)
        if not isinstance(rev, int) or rev < 0:
            raise PathError(f"{where}: revision {rev!r} must be an integer >= 0")
        return cls(name, pid, tuple(out), lim, rev, str(d.get("created", "")), str(d.get("modified", "")),
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
        lines.append(f"  {'#':>4} {'kind':<7} {'t s':>8}  {'x m':>9} {'y m':>9} {'z m':>9}   "
                     f"{'qw':>8} {'qx':>8} {'qy':>8} {'qz':>8}  speed")
        for i, p in enumerate(self.points):
            sp = ""
            if p.v_lin_m_s is not None or p.v_rot_rad_s is not None:
                sp = f"{p.v_lin_m_s or '-'} m/s {p.v_rot_rad_s or '-'} rad/s"
            lines.append(f"  {i:>4} {p.kind:<7} {p.t_s:>8.3f}  " + " ".join(f"{x:>9.4f}" for x in p.pos_m)
                         + "   " + " ".join(f"{x:>8.5f}" for x in p.quat) + f"  {sp}")
        return "\n".join(lines)


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
    """A new point before ``index`` (``len(points)`` appends). Without ``quat`` it takes
    the orientation of its neighbour."""
    j = _index(path, index, allow_end=True)
    if quat is None:
        if not path.points:
            quat = (1.0, 0.0, 0.0, 0.0)
        else:
            quat = path.points[min(j, len(path.points) - 1)].quat
    t = path.points[j - 1].t_s if j > 0 else 0.0
    pt = make_point(pos_m, quat, kind, t, where=f"path {path.name}: inserted point {index}")
    return replace(path, points=path.points[:j] + (pt,) + path.points[j:])


def move_point(path: Path, index: int, pos_m: Sequence[float] | None = None, quat: Sequence[float] | None = None,
               offset_m: Sequence[float] | None = None) -> Path:
    """Point ``index`` at a new position (or shifted by ``offset_m``) and/or orientation."""
    j = _index(path, index)
    p = path.points[j]
    pos = np.asarray(p.pos_m if pos_m is None else pos_m, dtype=float)
    if offset_m is not None:
        pos = pos + np.asarray(offset_m, dtype=float).reshape(3)
    new = make_point(pos, p.quat if quat is None else quat, p.kind, p.t_s, p.v_lin_m_s, p.v_rot_rad_s,
                     where=f"path {path.name}: point {index}")
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
                                where=f"path {path.name}: point {j}")
    return replace(path, points=tuple(pts))


def set_limits(path: Path, **kw: float) -> Path:
    """Path limits with some fields changed (``v_lin_m_s=...``)."""
    bad = set(kw) - set(Limits._fields)
    if bad:
        raise PathError(f"path {path.name}: unknown limit(s) {', '.join(sorted(bad))}; "
                        f"limits: {', '.join(Limits._fields)}")
    return replace(path, limits=check_limits(path.limits._replace(**kw), f"path {path.name}: limits"))


# ----------------------------------------------------------------------------------------
# the store


def default_dir() -> FsPath:
    """``$PFMA_PATH_DIR``, else ``$XDG_DATA_HOME/pfma/paths``, else ``~/.local/share/pfma/paths``."""
    env = os.environ.get(PATH_DIR_ENV)
    if env:
        return FsPath(env).expanduser()
    xdg = os.environ.get("XDG_DATA_HOME")
    base = FsPath(xdg).expanduser() if xdg else FsPath.home() / ".local" / "share"
    return base / "pfma" / "paths"


def _now_text() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


@dataclass(frozen=True)
class PathInfo:
    name: str
    id: int
    points: int
    revision: int
    modified: str
    length_m: float


class PathStore:
    """The directory of path files (``<name>.json``). Usable without the controller.

    :param directory: where the files live (default :func:`default_dir`); created on
        the first save
    """

    def __init__(self, directory: str | os.PathLike | None = None) -> None:
        self.dir = FsPath(directory).expanduser() if directory is not None else default_dir()

    def file(self, name: str) -> FsPath:
        return self.dir / f"{check_name(name)}.json"

    def names(self) -> list[str]:
        if not self.dir.is_dir():
            return []
        return sorted(f.stem for f in self.dir.glob("*.json") if _NAME_RE.match(f.stem))

    def exists(self, name: str) -> bool:
        return self.file(name).is_file()

    def load(self, name: str) -> Path:
        """:raises PathError: no such path, or a bad file (named)"""
        f = self.file(name)
        try:
            text = f.read_text(encoding="utf-8")
        except FileNotFoundError:
            known = ", ".join(self.names()) or "none"
            raise PathError(f"no path {name!r} in {self.dir} (paths: {known})") from None
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as err:
            raise PathError(f"{f}: not valid JSON (truncated or corrupt?): {err}") from None
        p = Path.from_json(doc, str(f))
        if p.name != name:
            raise PathError(f"{f}: holds path {p.name!r}, not {name!r} (renamed by hand?)")
        return p

    def list(self) -> list[PathInfo]:
        """Every readable path (bad files are skipped; :meth:`problems` lists them)."""
        out = []
        for n in self.names():
            try:
                p = self.load(n)
            except PathError:
                continue
            out.append(PathInfo(p.name, p.id, len(p.points), p.revision, p.modified, p.length_m))
        return out

    def problems(self) -> list[str]:
        bad = []
        for n in self.names():
            try:
                self.load(n)
            except PathError as err:
                bad.append(str(err))
        return bad

    def by_id(self, path_id: int) -> Path:
        """The path numbered ``path_id`` (the world model's ``msp.path_id``).

        :raises PathError: none or more than one
        """
        hits = [i for i in self.list() if i.id == int(path_id)]
        if not hits:
            raise PathError(f"no path with id {path_id} in {self.dir}")
        if len(hits) > 1:
            raise PathError(f"paths {', '.join(h.name for h in hits)} in {self.dir} share id {path_id}")
        return self.load(hits[0].name)

    def next_id(self) -> int:
        return max((i.id for i in self.list()), default=0) + 1

    def new(self, name: str, points: Sequence[PathPoint] = (), limits: Limits = DEFAULT_LIMITS,
            note: str = "") -> Path:
        """Create and save a new path with the next free id.

        :raises PathError: the name exists
        """
        if self.exists(name):
            raise PathError(f"path {name!r} already exists in {self.dir}")
        now = _now_text()
        return self.save(Path(check_name(name), self.next_id(), tuple(points), check_limits(limits), 0, now, now,
                              note))

    def save(self, path: Path, force: bool = False) -> Path:
        """Write ``path`` atomically with revision + 1; returns what was written.

        Refuses (``PathError``) when the file on disk has another revision than
        ``path.revision`` (someone saved it since it was loaded) unless ``force``.
        """
        f = self.file(path.name)
        if not force and f.exists():
            try:
                on_disk = json.loads(f.read_text(encoding="utf-8")).get("revision")
            except (OSError, json.JSONDecodeError, AttributeError):
                on_disk = None
            if on_disk is not None and on_disk != path.revision:
                raise PathError(f"{f}: revision {on_disk} on disk, this copy is revision {path.revision} "
                                f"(changed since it was loaded; load it again)")
        out = replace(path, revision=path.revision + 1, modified=_now_text(), created=path.created or _now_text())
        self.dir.mkdir(parents=True, exist_ok=True)
        data = (json.dumps(out.to_json(), indent=1) + "\n").encode("utf-8")
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=self.dir)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, f)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        try:
            dfd = os.open(self.dir, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:  # pragma: no cover - directories that cannot be fsynced
            pass
        return out

    def delete(self, name: str) -> None:
        f = self.file(name)
        try:
            f.unlink()
        except FileNotFoundError:
            raise PathError(f"no path {name!r} in {self.dir}") from None

    def rename(self, name: str, new_name: str) -> Path:
        """The path under a new name (same id; revision + 1)."""
        p = self.load(name)
        if self.exists(new_name):
            raise PathError(f"path {new_name!r} already exists in {self.dir}")
        out = self.save(replace(p, name=check_name(new_name)), force=True)
        self.delete(name)
        return out


# ----------------------------------------------------------------------------------------
# planning


def _pose_deviation(p: PathPoint, a: PathPoint, b: PathPoint) -> tuple[float, float]:
    """(distance m, angle rad) of ``p`` from the straight segment a->b executed with one
    parameter (the point of the segment nearest ``p``, and the orientation there)."""
    pa, pb, pp = np.array(a.pos_m), np.array(b.pos_m), np.array(p.pos_m)
    d = pb - pa
    L2 = float(d @ d)
    if L2 > 1e-12:
        u = min(1.0, max(0.0, float((pp - pa) @ d) / L2))
    else:
        ang = q_angle(a.quat, b.quat)
        u = min(1.0, q_angle(a.quat, p.quat) / ang) if ang > 1e-9 else 0.0
    dist = float(np.linalg.norm(pp - (pa + u * d)))
    return dist, q_angle(p.quat, q_slerp(a.quat, b.quat, u))


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


def plan_path(path: Path, speed_scale: float = 1.0, tol_m: float = PLAN_TOL_M, tol_rad: float = PLAN_TOL_RAD,
              cap: Limits = DEFAULT_CAP) -> list[PlannedSegment]:
    """The playback plan: one rest-to-rest segment per key point (:func:`simplify`).

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
    keys = simplify(path.points, tol_m, tol_rad)
    out = []
    prev = -1
    base = path.limits.scaled(speed_scale)
    for k in keys:
        covered = path.points[prev + 1:k + 1]
        vl = min([base.v_lin_m_s] + [p.v_lin_m_s * speed_scale for p in covered if p.v_lin_m_s])
        vr = min([base.v_rot_rad_s] + [p.v_rot_rad_s * speed_scale for p in covered if p.v_rot_rad_s])
        lim = Limits(vl, base.a_lin_m_s2, vr, base.a_rot_rad_s2).clipped(cap)
        p = path.points[k]
        out.append(PlannedSegment(k, np.array(p.pos_m), np.array(p.quat), lim))
        prev = k
    return out


def plan_duration_s(path: Path, start: PathPoint | None = None, speed_scale: float = 1.0) -> float:
    """Time the plan takes at its limits (without the hand-over gaps between segments)."""
    segs = plan_path(path, speed_scale)
    t = 0.0
    p0 = np.array((start or path.points[0]).pos_m)
    q0 = np.array((start or path.points[0]).quat)
    for s in segs:
        t += plan_segment(p0, q0, s.pos_m, s.quat, s.limits).duration_s
        p0, q0 = s.pos_m, s.quat
    return t


# ----------------------------------------------------------------------------------------
# the layer


class MspMode:
    """``msp.mode`` (user) and ``msp.state`` (the layer)."""

    IDLE = 0
    RECORD = 1
    PLAY = 2
    NAMES = {0: "IDLE", 1: "RECORD", 2: "PLAY"}


class MspResult:
    """``msp.result``: how the last recording or playback ended (``msp.finished`` counts them)."""

    OK = 0
    CANCELLED = 1  #: playback stopped by the user or the layer shutting down
    NO_POSE = 2  #: no measured tool pose (Joint Planner kinematics missing)
    NO_PATH = 3  #: path id unknown or its file bad
    EMPTY = 4  #: nothing recorded / nothing to play
    REFUSED = 5  #: the Trajectory Planner refused a segment
    SAVE_FAILED = 6
    NAMES = {0: "OK", 1: "CANCELLED", 2: "NO POSE", 3: "NO PATH", 4: "EMPTY", 5: "REFUSED", 6: "SAVE FAILED"}


TOOL_POSE = ("joint.tool_pos_m", "joint.tool_quat")
CMD_POSE = ("cart.cmd_valid", "cart.pos_cmd_m", "cart.quat_cmd")
USER_VARS = ("msp.mode", "msp.path_id", "msp.teach", "msp.capture", "msp.capture_dist_m", "msp.capture_angle_rad",
             "msp.speed_scale", "msp.record_source")


class RecordSource:
    """``msp.record_source``: which pose a recording stores."""

    MEASURED = 0  #: the measured tool pose (fk of the resolver angles): where the tool was
    COMMAND = 1  #: the Cartesian command: played back, the arm retraces the recorded motion
    #: including the servo's static error (teach-and-repeat: repeatability, not accuracy)
    NAMES = {0: "MEASURED", 1: "COMMAND"}


class MultiSegmentLayer(Layer):
    """Multi-Segment Path Planner: path recording and playback (see the module doc).

    :param store: where paths are saved and loaded (default: :class:`PathStore` in the
        default directory)
    :param background_save: write recordings from a thread (the real-time task only hands
        the points over); tests may turn it off or call :meth:`wait_saved`
    """

    key = "msp"
    title = "Multi-Segment Path Planner"
    short = "MSPP"

    def __init__(self, store: PathStore | None = None, background_save: bool = True) -> None:
        super().__init__()
        self.store = store if store is not None else PathStore()
        self.background_save = background_save
        self.periodic["msp_planner"] = self.plan_task
        self.runs = {"msp_planner": 0}  #: task runs (as the placeholder counted them)
        self.state = MspMode.IDLE
        self._mode_seen = MspMode.IDLE
        self._teach_seen = 0
        self._rec: list[PathPoint] = []
        self._rec_id = 0
        self._source = RecordSource.MEASURED
        self._rec_t0 = 0.0
        self._plan: list[PlannedSegment] = []
        self._seg_i = 0
        self._seg_seq = 0
        self._finished = 0
        self._end_lock = threading.Lock()
        self._names: set[str] | None = None
        self._saver: threading.Thread | None = None
        self.last_saved: Path | None = None
        self.last_error = ""

    def specs(self) -> list[VarSpec]:
        return self.state_specs() + segment_specs() + [
            VarSpec("msp.mode", "command_input", "i2", (), "user", 0,
                    doc="path planner mode: 0 idle, 1 record, 2 play (path msp.path_id)"),
            VarSpec("msp.path_id", "command_input", "i4", (), "user", 0,
                    doc="the path to record into or play (the id in its file; pfma path list)"),
            VarSpec("msp.teach", "command_input", "i4", (), "user", 0,
                    doc="increment while recording to store the present tool pose as a teach point"),
            VarSpec("msp.capture", "command_input", "b1", (), "user", True,
                    doc="while recording, also capture points continuously (distance/angle threshold)"),
            VarSpec("msp.capture_dist_m", "command_input", "f8", (), "user", CAPTURE_DIST_M, "m",
                    doc="continuous capture: a point each time the tool moved this far"),
            VarSpec("msp.capture_angle_rad", "command_input", "f8", (), "user", CAPTURE_ANGLE_RAD, "rad",
                    doc="continuous capture: a point each time the tool turned this far"),
            VarSpec("msp.record_source", "command_input", "i2", (), "user", RecordSource.MEASURED,
                    doc="recording stores 0 the measured tool pose (joint.tool_*) or 1 the Cartesian command "
                        "(cart.pos_cmd_m/quat_cmd: playback repeats the recorded motion)"),
            VarSpec("msp.speed_scale", "command_input", "f8", (), "user", 1.0,
                    doc="playback speed factor on the path's speeds (capped by traj.*_max)"),
            VarSpec("msp.state", "status_output", "i2", (), "msp", 0,
                    doc="path planner state: 0 idle, 1 recording, 2 playing"),
            VarSpec("msp.points", "status_output", "i4", (), "msp", 0,
                    doc="points recorded so far (recording) or in the path (playing)"),
            VarSpec("msp.segment", "status_output", "i4", (), "msp", 0,
                    doc="playback: the segment running (1-based; 0 none)"),
            VarSpec("msp.segments", "status_output", "i4", (), "msp", 0,
                    doc="playback: segments in the plan"),
            VarSpec("msp.finished", "status_output", "i4", (), "msp", 0,
                    doc="counts recordings saved and playbacks ended (msp.result says how)"),
            VarSpec("msp.result", "status_output", "i2", (), "msp", 0,
                    doc="last recording/playback: 0 OK 1 CANCELLED 2 NO POSE 3 NO PATH 4 EMPTY 5 REFUSED "
                        "6 SAVE FAILED"),
        ]

    # --- helpers ---------------------------------------------------------------------------
    def _has(self, rt: "LayerContext", names: Sequence[str]) -> bool:
        if self._names is None:
            self._names = set(rt.wm.names())
        return all(n in self._names for n in names)

    def _tool_pose(self, rt: "LayerContext") -> tuple[np.ndarray, np.ndarray] | None:
        if self._source == RecordSource.COMMAND:
            if not self._has(rt, CMD_POSE):
                return None
            v = rt.wm.get_task_inputs(CMD_POSE)
            if not bool(v["cart.cmd_valid"]):
                return None
            return np.asarray(v["cart.pos_cmd_m"], dtype=float), q_normalize(v["cart.quat_cmd"])
        if not self._has(rt, TOOL_POSE):
            return None
        v = rt.wm.get_task_inputs(TOOL_POSE)
        q = np.asarray(v["joint.tool_quat"], dtype=float)
        if float(q @ q) < 0.5:
            return None
        return np.asarray(v["joint.tool_pos_m"], dtype=float), q_normalize(q)

    def _status(self, rt: "LayerContext", **kw: int) -> None:
        rt.wm.post_task_outputs("msp", {f"msp.{k}": v for k, v in kw.items()})

    def _end(self, rt: "LayerContext", result: int, text: str, idle: bool = True) -> None:
        with self._end_lock:  # the background save ends recordings from its thread
            self._finished += 1
            n = self._finished
        if idle:
            self.state = MspMode.IDLE
            self._status(rt, state=MspMode.IDLE, segment=0)
        self._status(rt, finished=n, result=result)
        lvl = Level.INFO if result == MspResult.OK else Level.WARNING
        rt.post(self.key, lvl, f"{text} -> {MspResult.NAMES[result]}")

    # --- recording -------------------------------------------------------------------------
    def _add_point(self, rt, p: np.ndarray, q: np.ndarray, kind: str) -> None:
        self._rec.append(PathPoint(tuple(float(x) for x in p), tuple(float(x) for x in q), kind,
                                   round(rt.now - self._rec_t0, 6)))

    def _start_record(self, rt, v) -> None:
        self._source = int(v["msp.record_source"])
        if self._source not in RecordSource.NAMES:
            rt.post(self.key, Level.WARNING, f"msp.record_source {self._source} unknown; recording the measured pose")
            self._source = RecordSource.MEASURED
        pose = self._tool_pose(rt)
        self._rec_id = int(v["msp.path_id"])
        if pose is None:
            self._end(rt, MspResult.NO_POSE, f"record: no {RecordSource.NAMES[self._source].lower()} tool pose "
                                             f"({'cart.pos_cmd_m' if self._source else 'joint.tool_pos_m'})")
            return
        self._rec, self._rec_t0 = [], rt.now
        self._teach_seen = int(v["msp.teach"])
        self.state = MspMode.RECORD
        if bool(v["msp.capture"]):
            self._add_point(rt, *pose, "capture")
        self._status(rt, state=MspMode.RECORD, points=len(self._rec))
        rt.post(self.key, Level.INFO, f"recording path id {self._rec_id} "
                                      f"({RecordSource.NAMES[self._source].lower()} pose)")

    def _record(self, rt, v) -> None:
        pose = self._tool_pose(rt)
        if pose is None:
            return
        p, q = pose
        n0 = len(self._rec)
        teach = int(v["msp.teach"])
        if teach != self._teach_seen:
            self._teach_seen = teach
            self._add_point(rt, p, q, "teach")
            rt.post(self.key, Level.INFO, f"teach point {len(self._rec) - 1}: "
                                          + " ".join(f"{x:+.4f}" for x in p) + " m")
        elif bool(v["msp.capture"]):
            if not self._rec:
                self._add_point(rt, p, q, "capture")
            else:
                last = self._rec[-1]
                moved = float(np.linalg.norm(p - np.array(last.pos_m)))
                turned = q_angle(q, last.quat)
                if moved >= float(v["msp.capture_dist_m"]) or turned >= float(v["msp.capture_angle_rad"]):
                    self._add_point(rt, p, q, "capture")
        if len(self._rec) != n0:
            self._status(rt, points=len(self._rec))

    def _stop_record(self, rt, v) -> None:
        pose = self._tool_pose(rt)
        if pose is not None and bool(v["msp.capture"]) and self._rec:
            last = self._rec[-1]
            if np.linalg.norm(pose[0] - np.array(last.pos_m)) > 1e-4 or q_angle(pose[1], last.quat) > 1e-3:
                self._add_point(rt, *pose, "capture")  # the end of the motion is part of the path
        pts, pid = tuple(self._rec), self._rec_id
        self._rec = []
        if not pts:
            self._end(rt, MspResult.EMPTY, f"record path id {pid}: no points")
            return
        self.state = MspMode.IDLE
        self._status(rt, state=MspMode.IDLE, points=len(pts))
        if self.background_save:
            self.wait_saved()
            self._saver = threading.Thread(target=self._save, args=(rt, pid, pts), daemon=True,
                                           name="msp-save")
            self._saver.start()
        else:
            self._save(rt, pid, pts)

    def _save(self, rt, pid: int, pts: tuple[PathPoint, ...]) -> None:
        """Write a recording into path ``pid`` (a new ``path-<id>`` if there is none). Posts
        msp.finished / msp.result (a post is thread-safe: it goes to the next segment)."""
        try:
            try:
                old = self.store.by_id(pid) if pid > 0 else None
            except PathError:
                old = None
            if old is not None:
                saved = self.store.save(replace(old, points=pts))
            else:
                if pid <= 0:
                    pid = self.store.next_id()
                name = f"path-{pid}"
                now = _now_text()
                saved = self.store.save(Path(name, pid, pts, DEFAULT_LIMITS, 0, now, now,
                                             "recorded by the controller"), force=True)
            self.last_saved = saved
            self._end(rt, MspResult.OK, f"recorded {len(pts)} points into path {saved.name} (id {saved.id}, "
                                        f"revision {saved.revision})", idle=False)
        except Exception as err:  # noqa: BLE001 - a failed save is reported, never a crash
            self.last_error = f"{type(err).__name__}: {err}"
            self._end(rt, MspResult.SAVE_FAILED, f"saving path id {pid} failed: {self.last_error}", idle=False)

    def wait_saved(self, timeout_s: float = 10.0) -> None:
        """Wait for a background save to finish (host time; not a world wait)."""
        t = self._saver
        if t is not None:
            t.join(timeout_s)
            self._saver = None

    # --- playback --------------------------------------------------------------------------
    def _start_play(self, rt, v) -> None:
        pid = int(v["msp.path_id"])
        try:
            path = self.store.by_id(pid)
            self._plan = plan_path(path, float(v["msp.speed_scale"]))
        except PathError as err:
            self.last_error = str(err)
            self._end(rt, MspResult.NO_PATH if path_missing(err) else MspResult.EMPTY,
                      f"play path id {pid}: {err}")
            return
        self.state = MspMode.PLAY
        self._seg_i = 0
        self._status(rt, state=MspMode.PLAY, points=len(path.points), segments=len(self._plan))
        rt.post(self.key, Level.INFO, f"playing path {path.name} (id {pid}): {len(self._plan)} segments "
                                      f"from {len(path.points)} points")
        self._send(rt)

    def _send(self, rt) -> None:
        s = self._plan[self._seg_i]
        self._seg_seq += 1
        rt.wm.post_task_outputs("msp", {
            "msp.seg_seq": self._seg_seq, "msp.seg_pos_m": s.pos_m, "msp.seg_quat": s.quat,
            "msp.seg_limits": np.array(s.limits, dtype=float), "msp.seg_last": self._seg_i == len(self._plan) - 1,
            "msp.seg_stop": False, "msp.segment": self._seg_i + 1})

    def _play(self, rt) -> None:
        v = rt.wm.get_task_inputs(("traj.done_seq", "traj.done_code"))
        if int(v["traj.done_seq"]) != self._seg_seq:
            return
        code = int(v["traj.done_code"])
        if code == DoneCode.REFUSED:
            self._end(rt, MspResult.REFUSED, f"playback: segment {self._seg_i + 1} refused by the "
                                             f"Trajectory Planner")
            return
        if code == DoneCode.STOPPED:
            self._end(rt, MspResult.CANCELLED, f"playback: segment {self._seg_i + 1} stopped")
            return
        self._seg_i += 1
        if self._seg_i >= len(self._plan):
            self._end(rt, MspResult.OK, f"playback done ({len(self._plan)} segments)")
            return
        self._send(rt)

    def _cancel_play(self, rt, why: str) -> None:
        rt.wm.post_task_outputs("msp", {"msp.seg_stop": True})
        self._end(rt, MspResult.CANCELLED, f"playback stopped: {why}")

    # --- sequences and the periodic task --------------------------------------------------------
    def _leave(self, rt, why: str) -> None:
        if self.state == MspMode.PLAY:
            self._cancel_play(rt, why)
        elif self.state == MspMode.RECORD:
            v = rt.wm.get_task_inputs(USER_VARS)
            self._stop_record(rt, v)  # keep what was recorded

    def seq_shutdown(self, rt: "LayerContext"):
        self._leave(rt, "shut down")
        return super().seq_shutdown(rt)

    def plan_task(self, rt: "LayerContext") -> None:
        self.runs["msp_planner"] += 1
        if rt.wm.get_state_variable(self.v_status) != Status.START_UP_COMPLETE:
            if self.state != MspMode.IDLE:
                self._leave(rt, "Multi-Segment Path Planner not running")
            self._mode_seen = MspMode.IDLE  # a mode still set at the next start up acts again
            return
        v = rt.wm.get_task_inputs(USER_VARS)
        mode = int(v["msp.mode"])
        if mode != self._mode_seen:
            old, self._mode_seen = self._mode_seen, mode
            if self.state == MspMode.RECORD:
                self._stop_record(rt, v)
            elif self.state == MspMode.PLAY:
                self._cancel_play(rt, f"msp.mode {MspMode.NAMES.get(old, old)} -> {MspMode.NAMES.get(mode, mode)}")
            if mode == MspMode.RECORD:
                self._start_record(rt, v)
            elif mode == MspMode.PLAY:
                self._start_play(rt, v)
            elif mode != MspMode.IDLE:
                rt.post(self.key, Level.WARNING, f"msp.mode {mode} unknown (0 idle, 1 record, 2 play)")
            return
        if self.state == MspMode.RECORD:
            self._record(rt, v)
        elif self.state == MspMode.PLAY:
            self._play(rt)


def path_missing(err: PathError) -> bool:
    return str(err).startswith("no path")


__all__ = ["Path", "PathPoint", "PathStore", "PathInfo", "PathError", "make_point", "delete_points",
           "insert_point", "move_point", "set_speed", "set_limits", "simplify", "plan_path", "plan_duration_s",
           "PlannedSegment", "MultiSegmentLayer", "MspMode", "MspResult", "RecordSource", "default_dir", "FORMAT_VERSION",
           "DEFAULT_LIMITS"]
