"""``pfma reg``, ``pfma read`` and ``pfma regs`` through tools.cli.main."""

from __future__ import annotations

import json
import math

import pytest

from drivers.bus import open_bus
from fakes.modbus_gateway import ModbusGateway
from tools.cli import main
from pfma.clock import SimClock
from pfma.rack import load_rack
from drivers.rackio import RackIO
from tests.drivers.bus.tinybus import free_port, quiet_pymodbus


@pytest.fixture
def rack_gateway():
    """A fake rack served by a real Modbus gateway on 127.0.0.1 (state persists across commands)."""
    rack = open_bus("fake", clock=SimClock())
    with quiet_pymodbus(), ModbusGateway(rack) as gw:
        yield rack, gw


# -- reg read / write ----------------------------------------------------------------------
def test_reg_read_names_board_and_register(capsys):
    assert main(["reg", "read", "0x0108"]) == 0
    out = capsys.readouterr().out
    assert "read16 0x0108 rtd1 STATUS (vmivme4940 at 0x0100+0x08)" in out
    assert "reference_present=1" in out  # R1: the fake has its 400 Hz reference


def test_reg_read_accepts_decimal_and_picks_8_bits_for_a_byte_register(capsys):
    assert main(["reg", "read", str(0x0021)]) == 0
    assert "read8 0x0021 pio_video PIA1_PRA" in capsys.readouterr().out


def test_reg_read_of_an_empty_address_is_a_bus_error(capsys):
    assert main(["reg", "read", "0x8000"]) == 1
    err = capsys.readouterr().err
    assert "0x8000" in err and "bus error" in err


def test_reg_read_rejects_bad_numbers_and_widths(capsys):
    with pytest.raises(SystemExit) as info:
        main(["reg", "read", "D000"])
    assert info.value.code == 2
    with pytest.raises(SystemExit):
        main(["reg", "read", "0xD000", "--width", "32"])
    assert main(["reg", "read", "0x10000"]) == 2
    assert "outside the A16 space" in capsys.readouterr().err


def test_reg_write_is_refused_without_confirmation(capsys):
    assert main(["reg", "write", "0xD000", "0xC100"]) == 2
    captured = capsys.readouterr()
    assert "refusing" in captured.err and "--yes-i-know" in captured.err
    assert "dac" in captured.err and "CTRL" in captured.err
    assert "written" not in captured.out


def test_reg_write_with_confirmation(capsys):
    assert main(["reg", "write", "0xD000", "0xC100", "--yes-i-know"]) == 0
    assert "write16 0xD000 dac DAC[0]/CTRL" in capsys.readouterr().out


def test_reg_write_to_the_simulated_rack_says_nothing_real_was_written(capsys):
    """Issue 32: the default bus is a fake in this process; the write says so."""
    assert main(["reg", "write", "0xD000", "0xC100", "--yes-i-know"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ("write16 0xD000 dac DAC[0]/CTRL (vmivme4100 at 0xD000+0x00): 0xC100 (49408) "
                        "written (simulated rack)")
    assert lines[1] == ("  simulated rack: a fake in this process: nothing real was written, and the "
                        "value is gone when the command ends")
    assert len(lines) == 2
    assert main(["reg", "write", "0xD000", "0xC100", "--yes-i-know", "--bus", "spy+fake"]) == 0
    assert "nothing real was written" in capsys.readouterr().out


def test_reg_read_and_dump_of_the_simulated_rack_say_so(capsys):
    assert main(["reg", "read", "0xD000"]) == 0
    assert capsys.readouterr().out.rstrip().endswith("  (simulated rack, power-up state)")
    assert main(["reg", "read", "0xD000", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["source"] == "simulated rack"
    assert main(["reg", "dump", "dac"]) == 0
    assert capsys.readouterr().out.splitlines()[0].endswith("  (simulated rack, power-up state)")


def test_reg_write_value_too_wide_is_refused(capsys):
    assert main(["reg", "write", "0x0021", "0x1FF", "--yes-i-know"]) == 2
    assert "does not fit 8 bits" in capsys.readouterr().err


def test_reg_dump_reads_every_readable_register(capsys):
    assert main(["reg", "dump", "rtd2"]) == 0
    out = capsys.readouterr().out
    for name in ("CH0", "CH1", "CH2", "CH3", "STATUS", "CONTROL"):
        assert name in out
    assert main(["reg", "dump", "nope"]) == 2
    assert "no board named 'nope'" in capsys.readouterr().err


# -- over Modbus -----------------------------------------------------------------------------
def test_reg_read_and_write_over_modbus(rack_gateway, capsys):
    rack, gw = rack_gateway
    with gw.lock:
        rack["rtd1"].set_counts(0, 0x1234)
    assert main(["reg", "read", "0x0100", "--bus", gw.url]) == 0
    out = capsys.readouterr().out
    assert "rtd1 CH0" in out and "0x1234 (4660)" in out
    assert main(["reg", "write", "0xD000", "0xC100", "--yes-i-know", "--bus", gw.url]) == 0
    out = capsys.readouterr().out  # a real bus (whatever answers behind the gateway): no simulated note
    assert out.endswith("written\n") and "simulated" not in out
    assert main(["reg", "read", "0xD000", "--bus", gw.url]) == 0
    out = capsys.readouterr().out
    assert "0x4100" in out and "simulated" not in out  # R2: CTRL reads back in bits 14..8
    with gw.lock:
        assert rack["dac"].outputs_connected


def test_read_over_a_bus_shows_a_resolver_angle_in_minus_pi_to_pi_and_its_status(rack_gateway, capsys):
    """``pfma read --bus``: the resolver's 0..2 pi shown in (-pi, pi], its status from the
    board's STATUS register beside it (LOS, NOREF), as the service would publish it."""
    import json
    import math
    rack, gw = rack_gateway
    with gw.lock:
        rack["rtd1"].set_counts(0, 12288)  # 3/4 turn: 4.71239 rad on the board
    assert main(["read", "elbow_pitch_angle", "--bus", gw.url, "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["value"] == pytest.approx(-math.pi / 2) and row["status_name"] == "ok" and row["status"] == 0
    with gw.lock:
        rack["rtd1"].inject("loss_of_signal", channel=0)
    assert main(["read", "elbow_pitch_angle", "wrist_yaw_angle", "--bus", gw.url]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[1:4] == ["-1.5708", "rad", "LOS"] and lines[1].split()[3] == "ok"


def test_modbus_bus_error_is_named_from_the_rack(rack_gateway, capsys):
    rack, gw = rack_gateway
    with gw.lock:
        rack["rtd2"].inject("no_answer")
    assert main(["reg", "read", "0x0208", "--bus", gw.url]) == 1
    err = capsys.readouterr().err
    assert "rtd2 STATUS at A16 0x0208" in err and "exception 2" in err


@pytest.mark.realtime
def test_gateway_down_is_a_clear_error(capsys):
    port = free_port()
    with quiet_pymodbus():
        assert main(["reg", "read", "0xD000", "--bus", f"modbus://127.0.0.1:{port}?timeout=0.5"]) == 1
    assert f"gateway 127.0.0.1:{port} unreachable" in capsys.readouterr().err


def test_bad_bus_url_is_a_usage_error(capsys):
    assert main(["reg", "read", "0xD000", "--bus", "modbus://127.0.0.1:502?slave=1"]) == 2
    assert "unknown option 'slave'" in capsys.readouterr().err


# -- pfma read -------------------------------------------------------------------------------
def test_read_signals_in_engineering_units_over_modbus(rack_gateway, capsys):
    rack, gw = rack_gateway
    with gw.lock:
        rack["rtd1"].set_angle_rad(0, 1.0)
        rack["adc"].set_input_volts(0, 2.5)  # shoulder yaw motor current, scale 1 A/V
    assert main(["read", "elbow_pitch_angle", "shoulder_yaw_motor_current", "--json",
                 "--bus", gw.url]) == 0
    rows = {r["signal"]: r for r in json.loads(capsys.readouterr().out)}
    lsb = 2 * math.pi / 16384
    assert rows["elbow_pitch_angle"]["units"] == "rad"
    assert rows["elbow_pitch_angle"]["value"] == pytest.approx(1.0, abs=lsb)
    assert rows["shoulder_yaw_motor_current"]["units"] == "A"
    assert rows["shoulder_yaw_motor_current"]["value"] == pytest.approx(2.5, abs=0.01)
    assert rows["shoulder_yaw_motor_current"]["board"] == "adc"


def test_read_text_output_and_dac_shadow(capsys):
    assert main(["read", "--bus", "fake", "elbow_pitch_angle", "wrist_roll_command"]) == 0
    out = capsys.readouterr().out
    assert "elbow_pitch_angle" in out and " rad " in out
    assert "wrist_roll_command" in out and "shadow" in out


def test_read_unknown_and_serial_signals_fail_clearly(capsys):
    assert main(["read", "--bus", "fake", "elbow_pitch_angle", "no_such_signal", "ft_sensor"]) == 1
    captured = capsys.readouterr()
    assert "elbow_pitch_angle" in captured.out
    assert "no channel named 'no_such_signal'" in captured.err
    assert "ft_sensor" in captured.err and "serial line" in captured.err


def test_rackio_dac_reads_its_shadow():
    bus = open_bus("fake", clock=SimClock())
    io = RackIO(bus, load_rack())
    io.driver("dac").write_volts(5, 2.0)  # wrist roll command, scale 0.2 (rad/s)/V
    value, units, raw = io.read_signal("wrist_roll_command")
    assert units == "rad/s" and value == pytest.approx(0.4, abs=0.2 * 0.005)
    assert raw == io.driver("dac").shadow_counts[5]


def test_rackio_builds_a_driver_for_every_board():
    clock = SimClock()
    io = RackIO(open_bus("fake", clock=clock), load_rack(), clock=clock)
    drivers = io.drivers()
    assert set(drivers) == {"rtd1", "rtd2", "dac", "adc", "sio", "pio_user", "pio_video"}
    assert type(drivers["rtd1"]).__name__ == "Vmivme4940"
    assert type(drivers["sio"]).__name__ == "Mvme400" and drivers["sio"].clock is clock
    assert io.driver("rtd1") is drivers["rtd1"]  # built once


# -- pfma regs -------------------------------------------------------------------------------
def test_regs_lists_tables_and_assumptions(capsys):
    assert main(["regs", "dac"]) == 0
    out = capsys.readouterr().out
    assert "vmivme4100" in out and "CTRL" in out and "dac@0xD000" in out
    assert main(["regs", "--assumptions"]) == 0
    out = capsys.readouterr().out
    for kind in ("vmivme4940", "vmivme4100", "dvme611", "mvme400", "mvme410"):
        assert kind in out
    assert "R1" in out  # the RDC register map is assumed
    assert main(["regs", "rtd1"]) == 0
    assert "vmivme4940" in capsys.readouterr().out
    assert main(["regs", "nothing"]) == 2


def test_help_says_the_fake_rack_starts_fresh(capsys):
    with pytest.raises(SystemExit):
        main(["reg", "read", "--help"])
    assert "fresh fake rack" in capsys.readouterr().out


def test_interactive_tools_wait_longer_than_one_frame_for_a_gateway_unless_the_url_says():
    from drivers.bus.modbus import DEFAULT_TIMEOUT_S
    from pfma.rack import load_rack
    from tools.regs import INTERACTIVE_MODBUS_TIMEOUT_S, open_cli_bus
    rack = load_rack()
    assert open_cli_bus("modbus://127.0.0.1:9", rack).timeout == INTERACTIVE_MODBUS_TIMEOUT_S > DEFAULT_TIMEOUT_S
    assert open_cli_bus("modbus://127.0.0.1:9?timeout=0.01", rack).timeout == 0.01
