"""Who may open a buffer's files (issue 20 item 5, bit3/access.py): the ring carries the
buffer's mode and group; the pfma group model (service user writes, group members read);
a tool without permission says so in one line, no traceback.

Root reads a chmod-000 file, so "another user" is a real other user here: as root the
tools run as ``nobody`` (``setpriv``, subprocesses: realtime); as another user the
segment is made mode 000 instead (its owner then has no access either).
"""

from __future__ import annotations

import functools
import os
import shutil
import stat
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from bit3.access import GROUP_MODE, PRIVATE_MODE, Bit3AccessError
from bit3.buffer import Bit3Buffer, Bit3Error
from bit3.layout import default_layout
from bit3.ring import FrameRing, RingError, ring_path
from tools.cli import main

ROOT = Path(__file__).resolve().parents[2]
NOBODY = 65534
IS_ROOT = os.geteuid() == 0
#: a tool as another user: root switches to nobody; needs util-linux setpriv
as_nobody = pytest.mark.skipif(not IS_ROOT or shutil.which("setpriv") is None,
                               reason="running a tool as another user needs root and setpriv")


@functools.lru_cache(maxsize=1)
def nobody_cannot_run_the_checkout() -> str:
    """Why user nobody cannot import this checkout's tools with this interpreter ('' when it
    can): a clone in a private directory (mktemp -d, a 0700 home) or an interpreter under
    one. Then the tests that run a tool as nobody skip saying so (issue 29 item 9): what
    they check, a second user's view of the buffer, cannot be staged without the code."""
    try:
        p = subprocess.run(["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups",
                            sys.executable, "-c", "import tools.cli"], capture_output=True, text=True, cwd=ROOT,
                           timeout=60)
    except OSError as err:
        return f"user nobody cannot start {sys.executable}: {err}"
    if p.returncode == 0:
        return ""
    last = (p.stderr.strip().splitlines() or ["?"])[-1]
    return (f"user nobody cannot run this checkout ({ROOT}) with {sys.executable}: {last} (a private "
            f"directory: clone where every user can enter to run these)")


def skip_unless_nobody_can_run_the_checkout() -> None:
    why = nobody_cannot_run_the_checkout()
    if why:
        pytest.skip(why)


@pytest.fixture
def name():
    n = f"pfma_acc{os.getpid()}_{uuid.uuid4().hex[:8]}"
    yield n
    FrameRing.unlink(n)
    Bit3Buffer.unlink(n)


def mode(path: str) -> tuple[int, int]:
    st = os.stat(path)
    return stat.S_IMODE(st.st_mode), st.st_gid


def make_ring(name: str) -> FrameRing:
    lay = default_layout()
    return FrameRing.create(name, lay.area("inputs").body_size, lay.hash)


def other_group() -> int:
    """A group to share with: nobody's group as root; else one of this user's groups."""
    if IS_ROOT:
        return NOBODY
    groups = [g for g in os.getgroups() if g != os.getegid()]
    return groups[0] if groups else os.getegid()


def run_as(uid: int, gid: int, argv: list[str]) -> subprocess.CompletedProcess:
    skip_unless_nobody_can_run_the_checkout()
    return subprocess.run(["setpriv", f"--reuid={uid}", f"--regid={gid}", "--clear-groups",
                           sys.executable, *argv], capture_output=True, text=True, cwd=ROOT, timeout=60)


# --- modes ----------------------------------------------------------------------------------


def test_a_private_buffer_and_its_ring_are_0600_whatever_the_umask(name):
    old = os.umask(0)
    try:
        b = Bit3Buffer.create(name)
        make_ring(name).close()
    finally:
        os.umask(old)
    try:
        assert mode(f"/dev/shm/{name}")[0] == PRIVATE_MODE == 0o600
        assert mode(ring_path(name))[0] == 0o600
    finally:
        b.close()


def test_the_ring_carries_the_buffer_s_mode_and_group(name):
    gid = other_group()
    b = Bit3Buffer.create(name, group=gid)
    try:
        assert mode(f"/dev/shm/{name}") == (GROUP_MODE, gid) and GROUP_MODE == 0o640
        make_ring(name).close()
        assert mode(ring_path(name)) == (0o640, gid)
        make_ring(name).close()  # a restarted service replaces the ring: the same again
        assert mode(ring_path(name)) == (0o640, gid)
    finally:
        b.close()


def test_an_unknown_group_is_refused_and_leaves_no_buffer(name):
    with pytest.raises(Bit3Error, match="no group 'pfma-no-such-group' on this host"):
        Bit3Buffer.create(name, group="pfma-no-such-group")
    assert not os.path.exists(f"/dev/shm/{name}")


@pytest.mark.skipif(IS_ROOT, reason="root may give a file to any group")
def test_a_group_this_user_is_not_in_is_refused(name):
    import grp
    mine = set(os.getgroups()) | {os.getegid()}
    other = next((g.gr_gid for g in grp.getgrall() if g.gr_gid not in mine), None)
    if other is None:
        pytest.skip("this user is in every group")
    with pytest.raises(Bit3Error, match="is not a member of it"):
        Bit3Buffer.create(name, group=other)
    assert not os.path.exists(f"/dev/shm/{name}")


# --- no permission: one message ----------------------------------------------------------------


@pytest.mark.skipif(IS_ROOT, reason="root reads a chmod 000 segment; the rows below run as nobody")
def test_a_tool_on_a_buffer_it_may_not_read_says_so_in_one_line(name, capsys):
    b = Bit3Buffer.create(name)
    make_ring(name).close()
    os.chmod(f"/dev/shm/{name}", 0)
    os.chmod(ring_path(name), 0)
    try:
        assert main(["stats", "--buffer", name]) == 1
        err = capsys.readouterr().err
        assert "Traceback" not in err and err.count("\n") == 1
        assert f"pfma stats: no permission to read /dev/shm/{name} (mode 0000" in err
        with pytest.raises(RingError, match=f"no permission to read {ring_path(name)}"):
            FrameRing.attach(name)
    finally:
        b.close()


@as_nobody
@pytest.mark.realtime
@pytest.mark.parametrize("argv", [["stats"], ["read", "elbow_pitch_angle"], ["monitor"], ["watch", "elbow_pitch_angle"]],
                         ids=["stats", "read", "monitor", "watch"])
def test_a_tool_run_by_another_user_on_a_private_buffer_says_so_in_one_line(name, argv):
    b = Bit3Buffer.create(name)
    b.claim("service", "test-service")
    try:
        p = run_as(NOBODY, NOBODY, ["-m", "tools.cli", *argv, "--buffer", name])
        assert p.returncode == 1, (p.stdout, p.stderr)
        assert "Traceback" not in p.stderr + p.stdout
        lines = p.stderr.splitlines()
        assert len(lines) == 1, p.stderr
        assert lines[0].startswith(f"pfma {argv[0]}: no permission to read /dev/shm/{name} "
                                   f"(mode 0600, owner root, group root) as user nobody")
        assert "group model (docs/reliability.md)" in lines[0]
    finally:
        b.close()


# --- the group model -----------------------------------------------------------------------------


@as_nobody
@pytest.mark.realtime
def test_group_members_read_the_buffer_and_ring_others_and_writers_are_refused(name):
    """The service (root here) shares with group nogroup: nobody in nogroup reads the
    buffer (pfma read) and the ring; nobody in another group is refused; a writer role
    (a controller) is refused to the group member with one message."""
    b = Bit3Buffer.create(name, group=NOBODY)
    b.claim("service", "test-service")
    w = b.writer("inputs")
    w.record["frame"] = 4242
    w.publish()
    ring = make_ring(name)
    ring.write(bytes(ring.body_size))
    try:
        p = run_as(NOBODY, NOBODY, ["-m", "tools.cli", "read", "--buffer", name, "elbow_pitch_angle"])
        assert p.returncode == 0 and "(frame 4242)" in p.stdout, (p.stdout, p.stderr)
        code = (f"from bit3.ring import FrameRing; r = FrameRing.attach({name!r}); "
                f"print(r.count(), r.read(0) is not None)")
        p = run_as(NOBODY, NOBODY, ["-c", code])
        assert p.stdout.split() == ["1", "True"], p.stderr
        p = run_as(NOBODY, 4321, ["-m", "tools.cli", "read", "--buffer", name, "elbow_pitch_angle"])
        assert p.returncode == 1 and "Traceback" not in p.stderr
        assert "(mode 0640, owner root, group nogroup) as user nobody: add nobody to group nogroup" in p.stderr
        code = ("from bit3.client import Client\n"
                "from bit3.access import Bit3AccessError\n"
                f"try:\n    Client.attach({name!r}, writer='commands', owner='x')\n"
                "except Bit3AccessError as err:\n    print(err)")
        p = run_as(NOBODY, NOBODY, ["-c", code])
        assert p.stdout.startswith(f"no permission to write /dev/shm/{name}"), (p.stdout, p.stderr)
        assert "writing needs the service's user" in p.stdout
    finally:
        ring.close()
        b.close()


def test_a_read_only_attachment_of_a_group_buffer_is_a_read_only_mapping(name, monkeypatch):
    """What a group member gets (SharedMemory asks for read-write, which a 0640 segment
    refuses it): the read-only mapping, every area readable; modelled here by refusing
    the read-write open."""
    import bit3.buffer as bb
    b = Bit3Buffer.create(name, group=other_group())
    b.claim("service", "test-service")
    w = b.writer("inputs")
    w.record["frame"] = 99
    w.publish()

    def refuse(n, create, size=0):
        raise PermissionError(13, "Permission denied", "/" + n)
    monkeypatch.setattr(bb, "_open_shm", refuse)
    try:
        r = Bit3Buffer.attach(name)  # readonly
        try:
            rd = r.reader("inputs")
            rd.read()
            assert int(rd.record["frame"]) == 99 and r.readonly
            with pytest.raises(TypeError):  # the memory itself is read-only
                r._root[0] = 0
        finally:
            r.close()
        with pytest.raises(Bit3AccessError, match="no permission to write"):
            Bit3Buffer.attach(name, readonly=False)
    finally:
        b.close()
