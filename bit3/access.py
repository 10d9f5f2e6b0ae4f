"""Who may open the files of a Bit3 buffer: their mode and group (issue 20 item 5).

The service creates three files per buffer ``NAME``: the buffer itself
(``/dev/shm/NAME``), its frame ring (``/dev/shm/NAME.ring``) and, on the simulated rack,
its fault-control socket (``/dev/shm/NAME.faults``, always 0600: faults are the service
user's alone). The buffer and the ring carry **one mode**:

- **private** (the default): ``0600``, owner read-write; only the service's user (and
  root) can attach at all;
- **group** (``group=`` given, e.g. ``"pfma"``): ``0640`` and that group, so the lab PC's
  group model holds -- the service's user writes, the members of the group read (every
  monitor, recorder, scope, Modbus export and console attaches read-only), and nobody
  else can open it. A writer role (a controller, ``pfma wm set`` on the buffer, a
  ``--modbus-writes`` export) needs the service's user.

The ring follows the buffer: :func:`segment_access` reads the buffer's mode and group,
and the ring is created with them. A tool that may not open a file gets one
:class:`Bit3AccessError` naming the file, its mode, owner and group, and what to do.
"""

from __future__ import annotations

import grp
import mmap
import os
import pwd
import stat

from bit3.seqlock import Bit3Error

#: mode of a private buffer and its ring (owner read-write)
PRIVATE_MODE = 0o600
#: mode of a buffer (and ring) shared with a group: owner read-write, group read
GROUP_MODE = 0o640
#: where POSIX shared memory lives on Linux
SHM_DIR = "/dev/shm"


class Bit3AccessError(Bit3Error):
    """No permission to open a buffer's file (a group model mismatch, not a missing service)."""


def resolve_group(group: str | int) -> int:
    """A group name or number -> gid.

    :raises Bit3Error: no such group on this host
    """
    if isinstance(group, int):
        return group
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        if group.isdigit():
            return int(group)
        raise Bit3Error(f"no group {group!r} on this host (create it: groupadd {group}; "
                        f"docs/reliability.md, the pfma group model)") from None


def apply_access(fd: int, path: str, group: str | int | None) -> int:
    """Give the open file ``fd`` (``path``, for messages) its mode: :data:`PRIVATE_MODE`,
    or :data:`GROUP_MODE` and ``group``. Whatever the umask. Returns the mode.

    :raises Bit3Error: unknown group, or this user may not give files to it (not a member)
    """
    if group is None:
        os.fchmod(fd, PRIVATE_MODE)
        return PRIVATE_MODE
    gid = resolve_group(group)
    try:
        os.fchown(fd, -1, gid)
    except PermissionError:
        raise Bit3Error(f"cannot give {path} to group {_group_name(gid)}: this user "
                        f"({_user_name(os.geteuid())}) is not a member of it") from None
    os.fchmod(fd, GROUP_MODE)
    return GROUP_MODE


def segment_access(buffer_name: str) -> tuple[int, int] | None:
    """``(mode, gid)`` of buffer ``buffer_name``'s shared-memory file, or None if absent."""
    try:
        st = os.stat(f"{SHM_DIR}/{buffer_name}")
    except OSError:
        return None
    return stat.S_IMODE(st.st_mode), st.st_gid


def access_error(path: str, writing: bool) -> Bit3AccessError:
    """The one message for a file of a buffer this process may not open."""
    try:
        st = os.stat(path)
        what = (f"mode {stat.S_IMODE(st.st_mode):04o}, owner {_user_name(st.st_uid)}, group "
                f"{_group_name(st.st_gid)}")
        shared = stat.S_IMODE(st.st_mode) & 0o040
    except OSError:
        what, shared = "", 0
    me = _user_name(os.geteuid())
    if writing:
        hint = ("writing needs the service's user; the group model gives other users read access "
                "only (docs/reliability.md)")
    elif shared:
        hint = f"add {me} to group {_group_name(st.st_gid)} (then log in again)"
    else:
        hint = ("the service keeps this buffer private to its user; for operators to read it, "
                "run the service with the pfma group model (docs/reliability.md)")
    return Bit3AccessError(f"no permission to {'write' if writing else 'read'} {path}"
                           f"{f' ({what})' if what else ''} as user {me}: {hint}")


def open_readonly(name: str) -> tuple[mmap.mmap, int]:
    """Map POSIX shared memory ``name`` read-only (``O_RDONLY``, ``PROT_READ``): what a
    group member may do with a :data:`GROUP_MODE` buffer (``SharedMemory`` always asks
    for read-write). Returns ``(mapping, fd)``; the caller closes both.

    :raises PermissionError: not even read access
    :raises FileNotFoundError: no such segment, or one still empty (being created)
    """
    import _posixshmem  # the C module multiprocessing.shared_memory uses on POSIX
    fd = _posixshmem.shm_open("/" + name, os.O_RDONLY, mode=0)
    try:
        size = os.fstat(fd).st_size
        if size == 0:
            raise FileNotFoundError(f"/dev/shm/{name} exists but is still empty (being created)")
        return mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ), fd
    except BaseException:
        os.close(fd)
        raise


def _user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return f"gid {gid}"
