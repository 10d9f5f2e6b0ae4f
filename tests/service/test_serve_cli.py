"""`pfma serve` end to end for one real-time second (a smoke test: nothing here is timed)."""

import uuid

from ioservice.client import Client
from ioservice.layout import ServiceState
from ioservice.shm import Bit3Buffer
from pfma.cli import main


def test_serve_runs_and_leaves_a_stopped_safe_buffer(capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    try:
        assert main(["serve", "--duration", "1", "--buffer", name]) == 0
        out = capsys.readouterr().out
        assert "stopped after" in out and "rtd" in out
        c = Client.attach(name)
        s = c.read_inputs()
        assert s.service_state == ServiceState.STOPPED
        assert s.frame > 100 and not s.outputs_enabled
        assert all(v == 0 for v in s.dac_volts[:16])
        assert any("service stopped" in m.text for m in c.messages())
        c.close()
        assert main(["stats", "--buffer", name]) == 0
        assert "devices:" in capsys.readouterr().out
    finally:
        Bit3Buffer.unlink(name)


def test_bad_schedule_file_refused(tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_text("[schedule]\n[schedule.tasks]\nft = {divider = 4, phase = 7}\n")
    assert main(["serve", "--schedule", str(p), "--duration", "0.1", "--buffer", "unused"]) == 1
    assert "phase 7" in capsys.readouterr().err
