"""``pfma serve --group``: the pfma group model from the command line (docs/reliability.md),
and a Modbus export that cannot start leaves no buffer or frame ring behind."""

from __future__ import annotations

import grp
import os
import socket
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from tools.cli import main


def _left(name: str) -> list[str]:
    return [f for f in os.listdir("/dev/shm") if f.startswith(name)]


def test_an_unknown_group_is_one_line_exit_2_and_no_buffer(capsys):
    name = "pfma-tg-" + uuid.uuid4().hex[:6]
    code = main(["serve", "--buffer", name, "--group", "no-such-group-" + uuid.uuid4().hex[:4],
                 "--duration", "0.2"])
    err = capsys.readouterr().err
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("pfma serve:") and "group" in lines[0], err
    assert _left(name) == []


@pytest.mark.realtime  # a service runs 0.2 s of wall clock
def test_serve_with_a_group_makes_the_buffer_and_ring_0640_with_that_group(capsys):
    gid = os.getgid()
    name = "pfma-tg-" + uuid.uuid4().hex[:6]
    seen: dict[str, tuple[int, int]] = {}

    import tools.cli.serve as serve  # look at the files while the service runs (its fault hook)
    orig = serve.install_serve_faults

    def look(args, svc, world):
        for f in _left(name):
            st = os.stat("/dev/shm/" + f)
            seen[f] = (st.st_mode & 0o777, st.st_gid)
        return orig(args, svc, world)

    serve.install_serve_faults = look
    try:
        code = main(["serve", "--buffer", name, "--group", grp.getgrgid(gid).gr_name, "--duration", "0.2"])
    finally:
        serve.install_serve_faults = orig
    assert code == 0, capsys.readouterr().err
    assert len(seen) >= 2  # the buffer and its frame ring
    assert all(v == (0o640, gid) for v in seen.values()), seen
    assert [f for f in _left(name) if f != name] == []  # the ring removed; the stopped buffer stays
    Bit3Buffer.unlink(name)


@pytest.mark.realtime  # the export is a process of its own
def test_an_export_that_cannot_listen_leaves_no_buffer_or_ring(capsys):
    name = "pfma-tg-" + uuid.uuid4().hex[:6]
    with socket.socket() as s:  # the port is taken
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        code = main(["serve", "--buffer", name, "--modbus", f"127.0.0.1:{port}", "--duration", "0.5"])
    out = capsys.readouterr()
    assert code != 0
    assert "Traceback" not in out.err
    assert [f for f in _left(name) if f != name] == []  # no frame ring behind
    Bit3Buffer.unlink(name)
