"""``pfma ft`` against the fake controller on a real pty."""

from __future__ import annotations

import pytest

from tools.cli import main

pytestmark = pytest.mark.realtime


def test_pfma_ft_fake_polls_and_prints_forces(capsys):
    assert main(["ft", "--port", "fake", "--count", "3", "--interval", "0.01"]) == 0
    out = capsys.readouterr().out
    assert out.count("F[N]") == 3 and "records 3  bad 0" in out


def test_pfma_ft_stream_stops_after_count(capsys):
    assert main(["ft", "--port", "fake", "--stream", "--checksum", "--count", "2", "--interval", "0.05"]) == 0
    out = capsys.readouterr().out
    assert out.count("F[N]") == 2 and "Hz" in out


def test_pfma_ft_ascii_stream_warns_about_the_line_limit(capsys):
    assert main(["ft", "--port", "fake", "--ascii", "--stream", "--duration", "0.3", "--interval", "0.1"]) == 0
    assert "at most 42.7 records/s, below the 80 Hz" in capsys.readouterr().err


def test_pfma_ft_bias(capsys):
    assert main(["ft", "bias", "--port", "fake"]) == 0
    out = capsys.readouterr().out
    assert "bias: done" in out and out.count("F[N]") == 1


def test_pfma_ft_stops_cleanly_on_ctrl_c():
    import signal
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-m", "tools.cli", "ft", "--port", "fake", "--stream", "--checksum",
                          "--interval", "0.02"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        for line in p.stdout:  # wait for live values, then press Ctrl-C
            if "F[N]" in line:
                break
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=10)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0 and "interrupted" in err
    assert out.strip().splitlines()[-1].startswith("records ")
