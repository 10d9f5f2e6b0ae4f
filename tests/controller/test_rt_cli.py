"""`pfma controller` in simulated mode: power-up with a trace, single steps, tables."""

import io

from controller.daq_layer import FAULT_TACH
from controller.servo import TACH_FAULT_BIT
from tools.cli import main


def test_sim_power_up_prints_the_trace_and_the_final_statuses(capsys):
    rc = main(["controller", "--sim", "--wm", "none", "--power-up", "--duration", "0.3", "--trace",
               "--changes", "--messages", "5"])
    out = capsys.readouterr().out
    assert rc == 0
    lines = out.splitlines()
    assert lines[0].split()[:4] == ["frame", "t", "ms", "UPDN"]
    assert any("*INIT>INIT.. r11" in l for l in lines)  # System Up/Down starts the initialisation
    assert "UPDN=START UP COMPLETE" in out and "DAQ=START UP COMPLETE" in out
    assert "request 1: POWER UP: START UP COMPLETE -> COMPLETE" in out


def test_step_prints_one_line_per_minor_frame(capsys):
    assert main(["controller", "--sim", "--wm", "none", "--step", "4", "--messages", "0"]) == 0
    out = capsys.readouterr().out.splitlines()
    frames = [int(l.split()[0]) for l in out[1:5]]
    assert frames == list(range(frames[0], frames[0] + 4))


def test_halt_single_steps_from_the_keyboard(capsys, monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO("s 2\np\ns 100\nt\nq\n"))  # the power-up with its brake test
    assert main(["controller", "--sim", "--wm", "none", "--halt", "--messages", "3"]) == 0
    out = capsys.readouterr().out
    assert "request 1: POWER UP" in out
    assert "UPDN=START UP COMPLETE" in out  # 't' after 100 single steps


def test_tables_option_prints_tables_and_schedule(capsys):
    assert main(["controller", "--tables", "--profile", "overview"]) == 0
    out = capsys.readouterr().out
    assert "decision table layer" in out and "decision table bottom" in out
    assert "servo_control" in out and "134 Hz" in out


def test_servo_and_daq_agree_on_the_tach_fault_bit():
    assert TACH_FAULT_BIT == FAULT_TACH
