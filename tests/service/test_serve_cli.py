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


def test_serve_with_ft_on_a_pyserial_port(capsys):
    """The F/T sensor on a real pty (a USB-serial adapter's stand-in) instead of MVME400 port A."""
    from fakes.ft_sensor import FakeFtController
    from fakes.pty import PtyDevice
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    ft = FakeFtController()
    ft.set_load((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
    try:
        with PtyDevice(ft, baud=19200) as dev:
            assert main(["serve", "--duration", "1.5", "--buffer", name, "--ft-port", dev.port_name]) == 0
        c = Client.attach(name)
        s = c.read_inputs()
        link = c.layout.slot("link", "ft_sensor")
        assert s.link_records[link] > 20 and s.link_bad[link] == 0
        assert list(s.ft_force_n) == [1.0, 2.0, 3.0]  # 16 counts per N: exact in binary
        c.close()
    finally:
        Bit3Buffer.unlink(name)
