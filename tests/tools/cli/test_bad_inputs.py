"""No traceback for a user's mistake (issue 17): every verb below, given a bad input,
exits 2 (usage, argparse) or 1 (runtime) with one ``pfma VERB:`` line on stderr naming
the file or field, and prints no traceback.

Verbs run in-process through :func:`tools.cli.main`. The MCAP files are a real 0.3 s
recording of the simulated-time rig (``sim.rig``) and copies of it cut short.
"""

from __future__ import annotations

import os
import re
import uuid
from dataclasses import dataclass
from pathlib import Path

import pytest

from tools.cli import main
from pfma.rack import DEFAULT_RACK

OFFSET_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Name -> path of every input the table refers to."""
    from tools.recording.writer import Recorder
    from sim.rig import SimRig

    d = tmp_path_factory.mktemp("bad_inputs")
    good = d / "good.mcap"
    rig = SimRig(name="pfma-bad-" + uuid.uuid4().hex[:8])
    try:
        rec = Recorder(rig.reader, good, rack=rig.world.rack_config, epoch_offset_ns=OFFSET_NS)
        rig.on_frame.append(lambda info: rec.poll())
        rig.run(0.3)
        rec.close()
    finally:
        rig.close()
    data = good.read_bytes()
    out = {"good": good, "missing": d / "missing.mcap", "dir": d / "dir.mcap"}
    out["dir"].mkdir()
    for name, content in {
        "text": b"this is a text file, not a recording\n",
        "empty": b"",
        "truncated": data[: len(data) * 2 // 3],   # a recorder killed mid-file
        "header_only": data[:8],                    # the magic and nothing after
        "noperm": data,
    }.items():
        out[name] = d / f"{name}.mcap"
        out[name].write_bytes(content)
    out["noperm"].chmod(0)

    rack = DEFAULT_RACK.read_text()

    def rack_with(name: str, old: str, new: str) -> None:
        assert old in rack, old
        out[name] = d / f"{name}.toml"
        out[name].write_text(rack.replace(old, new, 1))
    rack_with("rate_fast", "rate_hz = 320", 'rate_hz = "fast"')
    rack_with("odd_base", "base = 0x0200", "base = 0x0201")
    rack_with("bad_baud", "baud = 19200", "baud = 19201")
    rack_with("bit3_size", "size = 32768", "size = 4096")
    rack_with("bad_scale", "scale = 0.04", 'scale = "0.04"')
    out["not_toml"] = d / "not_toml.toml"
    out["not_toml"].write_text("[[board]\nname = 1\n")
    out["latin1"] = d / "latin1.toml"
    out["latin1"].write_bytes(b"# caf\xe9\n" + rack.encode())
    out["rack_noperm"] = d / "rack_noperm.toml"
    out["rack_noperm"].write_text(rack)
    out["rack_noperm"].chmod(0)
    return out


@dataclass(frozen=True)
class Row:
    id: str
    argv: tuple[str, ...]  #: ``{name}`` is replaced by the path of ``files[name]``
    code: int  #: 2 usage, 1 runtime
    needles: tuple[str, ...]  #: each must be in the ``pfma VERB:`` line (``{name}`` as above)
    needs_non_root: bool = False


ROWS = [
    # --- recordings: missing, not MCAP, empty, truncated, a directory --------------------
    *[Row(f"{verb}-{kind}", (*argv, "{" + kind + "}", *tail), 1, ("{" + kind + "}", words))
      for verb, argv, tail in [
          ("replay", ("replay",), ("--fast", "--buffer", "pfma-bad-replay")),
          ("replay-fakes", ("replay",), ("--through-fakes",)),
          ("info", ("record", "info"), ()),
          ("scope", ("scope", "--open"), ()),
      ]
      for kind, words in [
          ("missing", "No such file or directory"),
          ("dir", "Is a directory"),
          ("text", "not an MCAP file"),
          ("empty", "empty file"),
          ("header_only", "truncated or unfinished"),
          ("truncated", "truncated or unfinished"),
      ]],
    *[Row(f"recover-{kind}", ("record", "recover", "{" + kind + "}", "-o", "{" + kind + "}.out"), 1,
          ("{" + kind + "}", words))
      for kind, words in [
          ("missing", "No such file or directory"),
          ("dir", "Is a directory"),
          ("text", "not an MCAP file"),
          ("empty", "empty file"),
          ("header_only", "no message recoverable"),
      ]],
    Row("replay-noperm", ("replay", "{noperm}", "--fast"), 1, ("Permission denied", "{noperm}"),
        needs_non_root=True),
    Row("info-noperm", ("record", "info", "{noperm}"), 1, ("Permission denied", "{noperm}"),
        needs_non_root=True),
    # --- rack files ------------------------------------------------------------------------
    Row("rack-missing", ("channels", "--rack", "{missing}"), 1, ("cannot read rack file", "{missing}")),
    Row("rack-not-toml", ("channels", "--rack", "{not_toml}"), 1, ("{not_toml}", "not valid TOML")),
    Row("rack-latin1", ("channels", "--rack", "{latin1}"), 1, ("{latin1}:1:", "not UTF-8")),
    Row("rack-rate-fast", ("channels", "--rack", "{rate_fast}"), 1, ("{rate_fast}:", "rate_hz", "'fast'")),
    Row("rack-odd-base", ("channels", "--rack", "{odd_base}"), 1, ("{odd_base}:", "base 0x0201 is odd")),
    Row("rack-bad-baud", ("channels", "--rack", "{bad_baud}"), 1, ("{bad_baud}:", "baud 19201")),
    Row("rack-bit3-size", ("channels", "--rack", "{bit3_size}"), 1, ("{bit3_size}:", "[bit3] size")),
    Row("rack-bad-scale", ("channels", "--rack", "{bad_scale}"), 1, ("{bad_scale}:", "scale must be a number")),
    Row("rack-noperm", ("channels", "--rack", "{rack_noperm}"), 1, ("{rack_noperm}", "Permission denied"),
        needs_non_root=True),
    Row("replay-bad-rack", ("replay", "{good}", "--rack", "{odd_base}", "--fast"), 1,
        ("{odd_base}:", "is odd")),
    # --- names and usage -------------------------------------------------------------------
    Row("read-unknown-signal", ("read", "--bus", "fake", "no_such_signal"), 1, ("no_such_signal",)),
    # a mistyped signal: exit 1 and the close matches, in every verb that takes signal names
    Row("read-typo-signal", ("read", "--bus", "fake", "elbow_pitch_angel"), 1,
        ("elbow_pitch_angel", "did you mean elbow_pitch_angle")),
    Row("scope-typo-signal", ("scope", "wrist_roll_rat"), 1, ("wrist_roll_rat", "did you mean wrist_roll_rate")),
    Row("replay-no-file", ("replay",), 2, ("required",)),
    Row("replay-bad-speed", ("replay", "{good}", "--speed", "fast"), 2, ("--speed", "'fast'")),
    Row("record-info-no-file", ("record", "info"), 2, ("usage: pfma record info FILE.mcap",)),
    Row("record-recover-no-file", ("record", "recover"), 2, ("usage: pfma record recover",)),
    Row("unknown-verb", ("no-such-verb",), 2, ("invalid choice",)),
    # an output file that cannot be written: said at once, before waiting for a service
    Row("record-into-no-dir", ("record", "/nonexistent-dir/x.mcap", "--buffer", "pfma-bad-nobody"), 1,
        ("cannot write /nonexistent-dir/x.mcap", "no directory /nonexistent-dir", "nothing recorded")),
    Row("record-onto-a-dir", ("record", "/tmp", "--buffer", "pfma-bad-nobody"), 1,
        ("cannot write /tmp", "it is a directory")),
    # --- numbers out of their range: usage mistakes, refused before anything runs ------------
    *[Row(f"range-{'-'.join(argv[:2])}", argv, 2, (flag, says))
      for argv, flag, says in [
          (("serve", "--duration", "-1"), "--duration", "greater than 0"),
          (("serve", "--frame-rate", "0"), "--frame-rate", "outside 1..5000 Hz"),
          (("serve", "--watchdog-ms", "-3"), "--watchdog-ms", "greater than 0"),
          (("serve", "--max-input-age", "0"), "--max-input-age", "1 or more"),
          (("hand", "--source", "cae", "--count", "-1"), "--count", "1 or more"),
          (("hand", "--source", "cae", "--bus", "modbus://"), "--bus modbus://", "needs a host and a port"),
          (("controller", "--sim", "--speed", "0"), "--speed", "greater than 0"),
          (("controller", "--sim", "--delay", "-1"), "--delay", "not be negative"),
          (("controller", "--sim", "--duration", "nan"), "--duration", "not a finite number"),
          (("monitor", "--once", "--page-s", "-1"), "--page-s", "greater than 0"),
          (("watch", "elbow_pitch_angle", "--count", "-2"), "--count", "not be negative"),
          (("scope", "elbow_pitch_angle", "--post", "0"), "--post", "greater than 0"),
          (("gateway", "--duration", "0"), "--duration", "greater than 0"),
          (("ft", "--interval", "0"), "--interval", "greater than 0"),
          (("record", "out/x.mcap", "--duration", "-2"), "--duration", "greater than 0"),
          (("record", "out/x.mcap", "--flush-s", "0"), "--flush-s", "greater than 0"),
      ]],
    # --- fault specs: the same grammar and exit code wherever one is taken ------------------
    Row("serve-bad-fault", ("serve", "--duration", "1", "--fault", "resolver-lo:x"), 2,
        ("resolver-lo", "did you mean resolver-los")),
    Row("checkout-bad-sim-fault", ("checkout", "-q", "--sim-fault", "bus-error:no_board"), 2,
        ("--sim-fault", "no_board")),
    Row("checkout-bad-panel-off", ("checkout", "-q", "--panel-off", "brake:gripper"), 2,
        ("--panel-off", "the gripper has no brake")),
    Row("fault-bad-spec", ("fault", "inject", "stuck-bit:adc", "--buffer", "pfma-bad-nobody"), 2,
        ("stuck-bit",)),
]


def _fill(s: str, files: dict[str, Path]) -> str:
    return re.sub(r"\{(\w+)\}", lambda m: str(files[m.group(1)]), s)


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as e:  # argparse
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("row", ROWS, ids=[r.id for r in ROWS])
def test_bad_input_is_one_message_not_a_traceback(row: Row, files, capsys):
    if row.needs_non_root and os.geteuid() == 0:
        pytest.skip("running as root: root reads a chmod 000 file, so there is no permission error")
    argv = [_fill(a, files) for a in row.argv]
    code, out, err = _run(argv, capsys)
    assert "Traceback" not in out + err
    assert code == row.code, (code, out, err)
    verb = "pfma" if row.argv[0] == "no-such-verb" else f"pfma {row.argv[0]}"
    lines = [ln for ln in err.splitlines() if ln.startswith(f"{verb}:")] if verb != "pfma" else \
        [ln for ln in err.splitlines() if ln.startswith("pfma: error:")]
    assert len(lines) == 1, err
    for needle in row.needles:
        assert _fill(needle, files) in lines[0], (needle, lines[0])


def test_nothing_half_written_for_a_bad_recover_input(files, capsys):
    out = files["text"].with_name("text-recovered.mcap")
    code, _, _ = _run(["record", "recover", str(files["text"])], capsys)
    assert code == 1 and not out.exists()


def test_replay_of_a_short_recording_exits_0(files, capsys):
    code, out, err = _run(["replay", str(files["good"]), "--fast", "--buffer", "pfma-bad-" + uuid.uuid4().hex[:8]],
                          capsys)
    assert code == 0, err
    m = re.search(r"pfma replay: (\d+) frames published", out)
    assert m and int(m.group(1)) >= 90, out  # 0.3 s at 320 Hz
    assert "Traceback" not in out + err


def test_replay_through_the_fakes_of_a_short_recording_exits_0(files, capsys):
    code, out, err = _run(["replay", str(files["good"]), "--through-fakes"], capsys)
    assert code == 0, out + err
    assert "0 with mismatches" in out


def test_info_and_scope_open_read_a_good_recording(files, capsys):
    code, out, err = _run(["record", "info", str(files["good"])], capsys)
    assert code == 0 and "/pfma/inputs_raw" in out and "lossless=True" in out, out + err
    code, out, err = _run(["scope", "--open", str(files["good"])], capsys)
    assert code == 0 and "0 samples" in out, out + err


def test_truncated_recording_recovers_and_then_reads(files, capsys, tmp_path):
    fixed = tmp_path / "fixed.mcap"
    code, out, err = _run(["record", "recover", str(files["truncated"]), "-o", str(fixed)], capsys)
    assert code == 0, out + err
    code, out, err = _run(["record", "info", str(fixed)], capsys)
    assert code == 0 and "/pfma/inputs_raw" in out, out + err


def test_os_error_escaping_a_verb_is_one_line(monkeypatch, capsys):
    """Any OSError a verb lets out (here from ``pfma channels``) becomes ``strerror: file``."""
    import tools.cli.channels as channels

    def boom(_args):
        raise PermissionError(13, "Permission denied", "/var/lib/pfma/stats.json")
    monkeypatch.setattr(channels, "run", boom)
    code, out, err = _run(["channels"], capsys)
    assert code == 1
    assert err == "pfma channels: Permission denied: /var/lib/pfma/stats.json\n"


def test_programming_errors_are_not_hidden(monkeypatch):
    import tools.cli.channels as channels

    def bug(_args):
        raise TypeError("a bug")
    monkeypatch.setattr(channels, "run", bug)
    with pytest.raises(TypeError):
        main(["channels"])
