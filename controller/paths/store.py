"""The path store: one JSON file per path in a small directory (default
``$PFMA_PATH_DIR``, else ``$XDG_DATA_HOME/pfma/paths``, else ``~/.local/share/pfma/paths``).
Files carry a format version and a revision counter; they are written atomically
(temporary file, fsync, rename) and a save refuses to overwrite a revision it did not
load. Usable without the controller.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path as FsPath
from typing import Sequence

from controller.paths.model import DEFAULT_LIMITS, _NAME_RE, Path, PathError, PathPoint, check_limits, check_name
from controller.trajectory import Limits

#: environment variable naming the path directory
PATH_DIR_ENV = "PFMA_PATH_DIR"


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


def path_missing(err: PathError) -> bool:
    return str(err).startswith("no path")
