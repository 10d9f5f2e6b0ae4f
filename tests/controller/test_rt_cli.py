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


def test_tables_option_prints_seven_tables_and_the_schedule(capsys):
    assert main(["controller", "--sim", "--power-up", "--tables", "--profile", "overview"]) == 0
    out = capsys.readouterr().out
    titles = ("System Up/Down (updown)", "Multi-Segment Path Planner (msp)", "Trajectory Path Planner (trajectory)",
              "Cartesian Engine (cartesian)", "Joint Planner (joint)", "Servo Control (servo)",
              "Data Acquisition (daq)")
    blocks = out.split("decision table ")[1:]
    assert [b.split(":")[0] for b in blocks] == list(titles)
    assert len({b.split("\n", 1)[1] for b in blocks}) == 7  # seven distinct tables, not one printed seven times
    assert "+trajectory_planner" in blocks[2] and "-joint_planner" in blocks[4]
    assert "servo_control" in out and "134 Hz" in out


def test_servo_and_daq_agree_on_the_tach_fault_bit():
    assert TACH_FAULT_BIT == FAULT_TACH
