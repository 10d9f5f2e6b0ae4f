"""`pfma serve` end to end for one real-time second (a smoke test: nothing here is timed)."""

import multiprocessing
import uuid
from dataclasses import replace

import pytest

from bit3.client import Client
from bit3.layout import ServiceState, default_layout
from bit3.buffer import Bit3Buffer
from tools.cli import main
from tests.bit3 import _workers


@pytest.mark.realtime
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
        assert main(["stats", "--buffer", name]) == 1  # a stopped service is not shown as live
        cap = capsys.readouterr()
        assert cap.out == "" and f"service on /dev/shm/{name} is not running (it stopped" in cap.err
    finally:
        Bit3Buffer.unlink(name)


def test_bad_schedule_file_refused(tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_text("[schedule]\n[schedule.tasks]\nft = {divider = 4, phase = 7}\n")
    assert main(["serve", "--schedule", str(p), "--duration", "0.1", "--buffer", "unused"]) == 1
    assert "phase 7" in capsys.readouterr().err


@pytest.mark.realtime
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


@pytest.mark.realtime
def test_serve_never_replaces_a_live_service_buffer_of_another_layout(capsys):
    """A buffer of another rack (another layout hash) whose service is alive is left
    alone: serve refuses with the owner's name and pid; once that service is gone the
    buffer is replaced."""
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    mp = multiprocessing.get_context("spawn")
    b = Bit3Buffer.create(name, replace(default_layout(), hash=b"otherrk!"))
    parent, child_end = mp.Pipe()
    child = mp.Process(target=_workers.hold_service_claim, args=(name, b"otherrk!", child_end))
    child.start()
    try:
        assert parent.poll(60.0), "child did not claim"
        pid = parent.recv()
        assert main(["serve", "--duration", "0.1", "--buffer", name]) != 0
        err = capsys.readouterr().err
        assert name in err and "'other-rack-serve'" in err and f"pid {pid}" in err and "--buffer" in err
        assert "Traceback" not in err
        with Client.attach(name, layout=b.layout) as c:  # the same segment, untouched
            h = c.header()
        assert h.layout_hash == b"otherrk!" and h.owners[0].pid == pid
        parent.send("die")
        child.join(60.0)
        assert child.exitcode == 0
        assert main(["serve", "--duration", "0.1", "--buffer", name]) == 0  # gone: replaced
        with Client.attach(name) as c:
            assert c.header().layout_hash == default_layout().hash
    finally:
        if child.is_alive():
            child.kill()
        b.close()
        Bit3Buffer.unlink(name)


@pytest.mark.parametrize("flag", [["--modbus-writes"], ["--modbus-requests", "pfma_wm"]])
def test_a_modbus_write_option_without_the_export_is_one_message(flag, capsys):
    assert main(["serve", "--duration", "0.1", "--buffer", "unused-modbus-flag", *flag]) == 2
    err = capsys.readouterr().err
    assert "needs --modbus HOST:PORT" in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.realtime
def test_serve_says_a_trip_when_it_happens_and_its_first_cause_at_exit(tmp_path, capsys):
    """Issue 29 item 3: a board that stops answering half a second in (a scenario) trips the
    service; the trip is said on the terminal as it happens (one line, time, severity, code)
    and the first trip since the last arm is named again at exit."""
    scenario = tmp_path / "trip.toml"
    scenario.write_text('name = "trip"\ndescription = "the resolver board stops answering"\n'
                        '[[step]]\nat_s = 0.5\ninject = "bus-error:rtd1"\n')
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    try:
        assert main(["serve", "--duration", "2", "--buffer", name, "--scenario", str(scenario)]) == 0
        lines = capsys.readouterr().out.splitlines()
        trips = [l for l in lines if " ERROR " in l and "outputs safe: rtd1 failed" in l]
        assert len(trips) == 1 and trips[0].startswith("pfma serve: ")
        assert any("WARNING 180: simulated fault on: bus-error:rtd1" in l for l in lines)
        stopped = next(i for i, l in enumerate(lines) if l.startswith("pfma serve: stopped after"))
        assert lines.index(trips[0]) < stopped  # said before the end, not only in a summary
        assert lines[stopped + 1].startswith("pfma serve: first trip since the last arm: rtd1 failed")
        c = Client.attach(name)
        s = c.read_inputs()
        assert s.text("first_trip_text").startswith("rtd1 failed") and s.first_trip_code != 0
        c.close()
    finally:
        Bit3Buffer.unlink(name)


@pytest.mark.realtime
def test_serve_quiet_says_no_message_lines(capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    try:
        assert main(["serve", "--duration", "0.5", "--buffer", name, "-q",
                     "--fault", "bus-error:rtd1"]) == 0
        out = capsys.readouterr().out
        assert " ERROR " not in out and "first trip since the last arm: rtd1 failed" in out
    finally:
        Bit3Buffer.unlink(name)
