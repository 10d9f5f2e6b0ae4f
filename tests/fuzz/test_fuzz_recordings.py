"""Fuzzed recordings (issue 20 item 3): a real MCAP recording of the simulated-time rig,
cut short at any byte or with bytes of its chunks, records or summary garbled, read by
every ``pfma`` tool that reads MCAP (``record info``, ``record recover``, ``replay``,
``scope --open``): exit 0, or exit 1 with one ``pfma VERB:`` line naming the file --
never a traceback. A file ``record recover`` writes is itself readable (with no message
recoverable it still writes a finished, empty recording and exits 1).

Not repeated here: the hand-picked damaged files of tests/tools/cli/test_bad_inputs.py
(empty, header only, text, a directory, two thirds of the file).
"""

from __future__ import annotations

import re
import uuid
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bit3.buffer import Bit3Buffer
from tests.fuzz._mutate import FUZZ
from tools.cli import main

OFFSET_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> bytes:
    """A 0.2 s recording of the simulated-time rig (64 frames, every topic)."""
    from sim.rig import SimRig
    from tools.recording.writer import Recorder
    path = tmp_path_factory.mktemp("fuzz_rec") / "good.mcap"
    rig = SimRig(name="pfma-fzrec-" + uuid.uuid4().hex[:8])
    try:
        rec = Recorder(rig.reader, path, rack=rig.world.rack_config, epoch_offset_ns=OFFSET_NS)
        rig.on_frame.append(lambda info: rec.poll())
        rig.run(0.2)
        rec.close()
    finally:
        rig.close()
    return path.read_bytes()


#: one damage: (kind, where as a fraction of the file, bytes)
_damage = st.tuples(st.sampled_from(["truncate", "garble", "garble", "zero", "repeat"]),
                    st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=16))


def damage(data: bytes, edits) -> bytes:
    for kind, at, junk in edits:
        i = int(at * len(data))
        if kind == "truncate":
            data = data[:max(i, 8)]  # past the magic: the empty and 8-byte files are rows of test_bad_inputs
        elif kind == "garble":
            data = data[:i] + bytes(b ^ 0xA5 for b in junk) + data[i + len(junk):]
        elif kind == "zero":
            data = data[:i] + bytes(len(junk) * 16) + data[i + len(junk) * 16:]
        else:  # a stretch written twice
            data = data[:i + len(junk) * 16] + data[i:]
    return data


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def one_message_or_success(argv: list[str], path: Path, capsys) -> int:
    code, out, err = run(argv, capsys)
    assert "Traceback" not in out + err, (argv, err)
    assert code in (0, 1), (argv, code, err)
    if code == 1:
        verb = f"pfma {argv[0]}:"
        lines = [ln for ln in err.splitlines() if ln.startswith(verb)]
        assert len(lines) == 1, (argv, err)
        assert str(path) in lines[0], (argv, lines[0])
    return code


@settings(FUZZ, max_examples=30)
@given(st.lists(_damage, min_size=1, max_size=3))
def test_every_tool_reading_a_damaged_recording_exits_0_or_with_one_message(good, tmp_path_factory, capsys, edits):
    d = tmp_path_factory.mktemp("damaged")
    path = d / "damaged.mcap"
    path.write_bytes(damage(good, edits))
    one_message_or_success(["record", "info", str(path)], path, capsys)
    out = d / "recovered.mcap"
    one_message_or_success(["record", "recover", str(path), "-o", str(out)], path, capsys)
    if out.exists():  # written (also when no message was recoverable: a finished, empty file)
        code, _, err = run(["record", "info", str(out)], capsys)
        assert code == 0, f"the recovered file does not read back: {err}"
    buffer = "pfma-fzreplay-" + uuid.uuid4().hex[:8]
    try:
        one_message_or_success(["replay", str(path), "--fast", "--buffer", buffer], path, capsys)
    finally:
        Bit3Buffer.unlink(buffer)
    one_message_or_success(["scope", "--open", str(path)], path, capsys)


def test_the_damage_is_real(good):
    """The fuzzing is not vacuous: garbling the middle of the file breaks it."""
    bad = damage(good, [("garble", 0.5, bytes(16))])
    assert bad != good and len(bad) == len(good)
    assert re.search(rb"\x89MCAP0\r\n$", damage(good, [("truncate", 0.5, b"x")])) is None
