"""Decision tables as data: validation for completeness and determinism; scheduling table;
message queues."""

import dataclasses

import pytest

from controller.decision import Action, Command, Status, TableError, TaskState, compile_table, describe, row
from controller.tables.shared import BOTTOM_TABLE, LAYER_TABLE
from controller.frames import FrameConfig, ScheduleError, TaskSpec
from controller.messages import MessageBoard


def test_both_tables_are_complete_and_deterministic():
    for t in (LAYER_TABLE, BOTTOM_TABLE):
        ct = compile_table(t)
        n = sum(1 for _ in t.input_space())
        assert sum(ct.coverage.values()) == n  # every combination decided exactly once
        assert all(v > 0 for v in ct.coverage.values())  # no dead row


def test_missing_row_is_reported_as_incomplete():
    rows = tuple(r for r in LAYER_TABLE.rows if r.rid != 53)  # START UP COMPLETE row removed
    with pytest.raises(TableError, match="incomplete: no row for command=START_UP status=START_UP"):
        compile_table(dataclasses.replace(LAYER_TABLE, rows=rows))


def test_overlapping_rows_are_reported_as_not_deterministic():
    extra = row(99, 2, status=Status.SHUT_DOWN, command=Command.INIT_TO_START, then=Status.ERROR)
    with pytest.raises(TableError, match="not deterministic: rows 11, 99"):
        compile_table(dataclasses.replace(LAYER_TABLE, rows=LAYER_TABLE.rows + (extra,)))


def test_dead_row_is_reported():
    # section 1 already decides every "subordinate in ERROR" case of an active layer
    dead = row(98, 2, status=Status.SHUT_DOWN, sub=Status.ERROR, command=Command.NONE, then=Status.ERROR)
    rows = tuple(r for r in LAYER_TABLE.rows)
    with pytest.raises(TableError, match="dead rows .*98"):
        compile_table(dataclasses.replace(LAYER_TABLE, rows=rows + (dead,)))


def test_key_decisions_of_the_layer_table():
    ct = compile_table(LAYER_TABLE)
    S, C, T = Status, Command, TaskState
    # no SHUT DOWN before INITIALIZATION COMPLETE: the initialisation goes on
    out = ct.decide(C.SHUT_DOWN, S.INITIALIZATION_IN_PROGRESS, S.SHUT_DOWN, T.RUNNING, False)
    assert out.next_status == S.INITIALIZATION_IN_PROGRESS and out.command_down == -1
    # ... and after INITIALIZATION COMPLETE it shuts down, passing SHUT DOWN down at once
    out = ct.decide(C.SHUT_DOWN, S.INITIALIZATION_COMPLETE, S.INITIALIZATION_COMPLETE, T.IDLE, False)
    assert (out.next_status, out.command_down, out.action) == (S.SHUT_DOWN_IN_PROGRESS, C.SHUT_DOWN,
                                                               Action.SHUTDOWN)
    # a subordinate in ERROR makes any active layer ERROR and commands SHUT DOWN below
    out = ct.decide(C.START_UP, S.START_UP_COMPLETE, S.ERROR, T.DONE, False)
    assert (out.next_status, out.command_down, out.action) == (S.ERROR, C.SHUT_DOWN, Action.SAFE)
    # START UP before INITIALIZATION COMPLETE is an inappropriate command
    assert ct.decide(C.START_UP, S.SHUT_DOWN, S.SHUT_DOWN, T.IDLE, False).next_status == S.ERROR
    # ERROR RESET is refused while the layer's own fault is present
    assert ct.decide(C.ERROR_RESET, S.ERROR, S.SHUT_DOWN, T.DONE, True).next_status == S.ERROR


def test_describe_lists_every_row_in_four_parts():
    text = describe(LAYER_TABLE)
    assert text.count("\n") == len(LAYER_TABLE.rows) + 7  # title, read, tasks, two labels and headers, post
    assert "INIT TO START: schedule own initialisation task" in text
    for part in ("part 1, read:", "part 2, error check", "part 3, the case statement", "part 4, post:"):
        assert part in text


def test_default_schedule_rates_and_phases():
    f = FrameConfig().validate()
    rates = {t.name: t.rate_hz for t in f.tasks}
    assert rates["msp_planner"] == 20 and rates["trajectory_planner"] == 40
    assert rates["cartesian_slow"] == 40 and rates["cartesian_fast"] == 80
    assert rates["joint_planner"] == 80 and rates["servo_control"] == 160
    table = f.table()
    assert len(table) == 16
    servo_frames = [k for k, fr in enumerate(table) if any(t.name == "servo_control" for t in fr)]
    assert servo_frames == list(range(0, 16, 2))  # the frames the service samples the resolvers in
    assert sum(any(t.name == "msp_planner" for t in fr) for fr in table) == 1


def test_report_overview_profile_gives_134_67_33_hz():
    f = FrameConfig.profile("overview").validate()
    rates = {t.name: t.rate_hz for t in f.tasks}
    assert f.frame_rate_hz == 268 and rates["servo_control"] == 134
    assert rates["joint_planner"] == 67 and rates["msp_planner"] == 33.5


def test_a_task_that_cannot_fit_its_period_is_reported():
    bad = FrameConfig(tasks=(TaskSpec("servo_control", "servo", 134.0),
                             TaskSpec("joint_planner", "joint", 80.0, phase=5),
                             TaskSpec("big", "servo", 20.0, budget_s=0.01)))
    with pytest.raises(ScheduleError) as err:
        bad.validate()
    msg = str(err.value)
    assert "servo_control: 134 Hz cannot fit its period" in msg
    assert "joint_planner: phase 5 not in 0..3" in msg
    assert "big: budget 10000 us cannot fit its period" in msg
    crowded = FrameConfig(tasks=tuple(TaskSpec(f"t{i}", "servo", 160.0, 0, budget_s=800e-6) for i in range(3)))
    assert any("minor frame 0: tasks t0, t1, t2 need 2400 us" in p for p in crowded.problems())


def test_message_queues_hold_50_per_source_and_show_the_last_100_in_time_order():
    mb = MessageBoard()
    for i in range(80):
        mb.post("servo", 1, f"s{i}", t_s=i * 1e-3, frame=i)
    for i in range(30):
        mb.post("daq", 1, f"d{i}", t_s=i * 2e-3 + 0.5e-3, frame=i)
    assert len(mb.queues["servo"]) == 50 and mb.dropped["servo"] == 30
    recent = mb.recent()
    assert len(recent) == 80 and recent[0].text == "d0"
    assert [m.t_s for m in recent] == sorted(m.t_s for m in recent)
    for i in range(100):
        mb.post(f"src{i % 4}", 2, "x", t_s=1.0 + i, frame=i)
    assert len(mb.recent()) == 100 and mb.recent()[-1].t_s == 100.0


def test_each_layer_message_reaches_the_bit3_queue_at_its_own_level():
    """A DEBUG line (a task created) stays DEBUG in the controller's Bit3 queue, where it was
    once forwarded as INFO; INFO, WARNING and ERROR keep theirs."""
    from bit3.layout import Severity
    from controller.messages import Level
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(1000)
        for lvl in (Level.INFO, Level.WARNING, Level.ERROR):
            sim.rt.post("runtime", lvl, f"a {lvl.name} line")
        got = {m.text: m.severity for m in sim.client.messages(queue="controller")}
    assert got["trajectory: task trajectory_planner created"] == Severity.DEBUG
    assert got["runtime: a INFO line"] == Severity.INFO
    assert got["runtime: a WARNING line"] == Severity.WARNING
    assert got["runtime: a ERROR line"] == Severity.ERROR
