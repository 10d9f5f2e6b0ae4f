"""The start-up checks' whole messages, word for word and in order: a decision table's
problems, a schedule's problems, the runtime's layer keys and its task implementations
(the texts are what a user reads when a configuration is refused)."""

import dataclasses

import pytest

from controller.decision import Status, TableError, compile_table, row
from controller.tables.shared import LAYER_TABLE
from controller.frames import FrameConfig, ScheduleError, TaskSpec, default_tasks
from controller.runtime import ControllerRuntime

#: microseconds of a 320 Hz minor frame left for tasks (400 us for the tables, the
#: communications segment's share off)
USABLE_US = 2256


def test_a_broken_table_lists_row_problems_first_ten_combinations_the_count_and_dead_rows():
    first = LAYER_TABLE.rows[0]
    bad_status = dataclasses.replace(first, next_status=Status.NO_SUBORDINATE)
    twin = row(first.rid, 9, status=Status.ERROR, then=Status.ERROR)  # the same id again
    dead = row(97, 9, status=Status.ERROR, then=Status.ERROR)  # a later section: ERROR is decided before
    rows = (bad_status,) + tuple(r for r in LAYER_TABLE.rows[1:] if r.rid != 53) + (twin, dead)
    with pytest.raises(TableError) as err:
        compile_table(dataclasses.replace(LAYER_TABLE, rows=rows))
    assert str(err.value) == (
        f"decision table layer: row ids are not unique; row {first.rid}: NO SUBORDINATE is not a layer status; "
        "incomplete: no row for command=START_UP status=START_UP sub=START_UP_COMPLETE task=DONE fault=False; "
        "dead rows (never decide anything): 97")


def test_past_ten_missing_combinations_only_their_count_is_given():
    rows = tuple(r for r in LAYER_TABLE.rows if r.status is None or Status.ERROR not in r.status)
    with pytest.raises(TableError) as err:
        compile_table(dataclasses.replace(LAYER_TABLE, rows=rows))
    msg = str(err.value)
    assert msg.count("incomplete: no row for") == 10
    assert msg.endswith(" incomplete and 0 ambiguous combinations in all)")


def test_a_bottom_table_cannot_wait_and_overlaps_are_counted_past_ten():
    everything = row(900, 0, then=Status.WAITING_FOR_SUBORDINATE_TO_INIT)
    again = row(901, 0, then=Status.SHUT_DOWN)
    # every combination of a bottom layer (5 commands x 9 statuses x 4 task states x fault)
    table = dataclasses.replace(LAYER_TABLE, name="flat", rows=(everything, again), has_subordinate=False)
    with pytest.raises(TableError) as err:
        compile_table(table)
    msg = str(err.value)
    assert msg.startswith("decision table flat: row 900: a bottom layer cannot wait for a subordinate; "
                          "not deterministic: rows 900, 901 all match command=NONE status=")
    assert msg.count("not deterministic") == 10
    assert msg.endswith("(0 incomplete and 360 ambiguous combinations in all); "
                        "dead rows (never decide anything): 901")


def test_a_schedule_lists_every_problem_in_order():
    tasks = (TaskSpec("a", "servo", 160.0, phase=2, budget_s=0.003),
             TaskSpec("b", "servo", 0.0),
             TaskSpec("a", "servo", 100.0),
             TaskSpec("c", "joint", 80.0, phase=3))
    f = FrameConfig(tasks=tasks, tables_budget_s=400e-6, max_missed_run=17)
    assert f.problems() == [
        "max_missed_run 17 outside 0..16",
        "task a is listed more than once",
        "task a: phase 2 not in 0..1 for 160 Hz",
        f"task a: budget 3000 us cannot fit its period: {USABLE_US} us of a minor frame are left for tasks",
        "task b: rate 0.0 Hz must be positive",
        "task a: 100 Hz cannot fit its period: on 320 Hz minor frames a task runs every 1, 2, 4, 8 or 16 "
        "frames (320, 160, 80, 40, 20 Hz)",
    ]
    assert FrameConfig(frame_rate_hz=0.5, tasks=tasks).problems() == ["minor-frame rate 0.5 Hz outside 1..5000 Hz"]
    no_time = FrameConfig(tasks=(), tables_budget_s=0.01).problems()
    assert no_time == ["decision tables (10000 us) and the communications segment leave no time in a "
                       "3.125 ms minor frame"]


def test_a_crowded_frame_is_checked_only_when_every_task_fits_alone():
    tasks = tuple(TaskSpec(f"t{i}", "servo", 160.0, 1, budget_s=900e-6) for i in range(3))
    assert FrameConfig(tasks=tasks).problems() == [
        f"minor frame 1: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 3: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 5: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 7: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 9: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 11: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 13: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
        f"minor frame 15: tasks t0, t1, t2 need 2700 us, {USABLE_US} us available: move a phase",
    ]


@pytest.mark.parametrize("keys", [(), ("servo", "gripper")])
def test_unknown_or_no_local_layers_are_refused_before_anything_is_built(keys):
    with pytest.raises(ValueError) as err:
        ControllerRuntime(object(), local_layers=keys)  # the client is never touched
    assert str(err.value) == (f"local_layers {list(keys)}: layer keys are "
                              "updown, msp, trajectory, cartesian, joint, servo, daq")


def test_a_task_without_implementation_and_an_unscheduled_one_are_both_named(sim):
    # Data Acquisition elsewhere: the runtime only reads the simulator's Bit3 inputs
    tasks = tuple(t for t in default_tasks() if t.name != "gripper_control") + (TaskSpec("nobody", "joint", 80.0),)
    with pytest.raises(ScheduleError) as err:
        ControllerRuntime(sim.client, frames=FrameConfig(tasks=tasks), clock=sim.clock,
                          local_layers=("updown", "msp", "trajectory", "cartesian", "joint", "servo"))
    assert str(err.value) == ("controller schedule: task nobody has no implementation in layer joint; "
                              "task gripper_control of a layer is not in the schedule")
