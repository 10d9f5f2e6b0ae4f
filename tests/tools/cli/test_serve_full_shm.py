"""`pfma serve` on a full /dev/shm: one line, a non-zero exit, nothing left behind (issue 29
item 8). The full /dev/shm is simulated as in tests/bit3/test_space.py."""

from __future__ import annotations

import uuid

from tests.bit3.test_space import _full_for, _left
from tools.cli import main


def test_pfma_serve_with_no_room_for_the_buffer_exits_2_in_one_line_leaving_nothing(monkeypatch, capsys):
    name = "pfma-full-" + uuid.uuid4().hex[:6]
    _full_for(monkeypatch, name)
    code = main(["serve", "--buffer", name, "--duration", "0.2"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith(f"pfma serve: no room for the Bit3 buffer '{name}'"), err
    assert _left(name) == []


def test_pfma_serve_with_no_room_for_the_ring_exits_1_in_one_line_leaving_nothing(monkeypatch, capsys):
    name = "pfma-full-" + uuid.uuid4().hex[:6]
    _full_for(monkeypatch, ".ring")
    code = main(["serve", "--buffer", name, "--duration", "0.2"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 1 and err[-1].startswith(f"pfma serve: no room for the frame ring of '{name}'"), err
    assert not any("Traceback" in ln for ln in err)
    assert _left(name) == []  # the buffer removed as well, and no faults file yet
