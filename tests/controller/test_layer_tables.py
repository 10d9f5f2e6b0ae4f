"""Issue 33 item 1: a decision table per layer, as data, whose rows create and delete the
layer's periodic tasks (report 2.2.4: "these decision tables control all task creation
and deletion")."""

from __future__ import annotations

import numpy as np
import pytest

from controller.decision import Status, compile_table, encode, row_tasks
from controller.layers import Request, Response
from controller.tables import TABLES
from controller.tables.shared import LAYER_ROWS, layer_table
from controller.trajectory import DoneCode
from controller.frames import ScheduleError
from sim.faults import FaultSet
from sim.system import SystemSimulator

S = Status
ORDER = ("updown", "msp", "trajectory", "cartesian", "joint", "servo", "daq")


def test_seven_tables_one_per_layer_each_complete_and_deterministic():
    assert tuple(TABLES) == ORDER
    for key, table in TABLES.items():
        ct = compile_table(table)
        assert table.key == key and sum(ct.coverage.values()) == sum(1 for _ in table.input_space())
        assert all(n > 0 for n in ct.coverage.values()), key  # no dead row
    # the six with a subordinate name it; their case rows are the shared ones, explicitly
    for upper, lower in zip(ORDER, ORDER[1:]):
        assert TABLES[upper].sub_key == lower and TABLES[upper].rows is LAYER_ROWS
    assert not TABLES["daq"].has_subordinate


@pytest.mark.parametrize("key", ORDER)
def test_every_row_of_every_table_decides_what_it_says(key):
    """Each row, looked up through the compiled table on an input it covers: its outputs,
    and the periodic tasks it creates and deletes (the running set after it is exactly
    the set its next status runs)."""
    table = TABLES[key]
    ct = compile_table(table)
    seen = set()
    for c, s, b, t, f in table.input_space():
        out = ct.lookup[encode(c, s, b, t, f)]
        r = next(x for x in table.rows if x.rid == out.rid)
        seen.add(r.rid)
        assert r.matches(c, s, b, t, f)
        assert (out.next_status, out.command_down, out.action) == (r.next_status, r.command_down, r.action)
        assert (table.running_in(s) | out.create) - out.delete == table.running_in(out.next_status)
        assert not (out.create & out.delete)
    assert seen == {r.rid for r in table.rows}


def test_the_tables_differ_in_the_tasks_they_create_and_delete():
    traj, cart, joint = TABLES["trajectory"], TABLES["cartesian"], TABLES["joint"]
    r53 = next(r for r in LAYER_ROWS if r.rid == 53)  # START UP COMPLETE
    r31 = next(r for r in LAYER_ROWS if r.rid == 31)  # INITIALIZATION COMPLETE
    r61 = next(r for r in LAYER_ROWS if r.rid == 61)  # powered up -> shut down
    assert row_tasks(traj, r53) == "+trajectory_planner"
    assert row_tasks(cart, r53) == "+cartesian_fast +cartesian_slow"
    assert row_tasks(joint, r53) == "" and row_tasks(joint, r31) == "+joint_planner"
    assert row_tasks(traj, r61) == "-trajectory_planner" and row_tasks(joint, r61) == "-joint_planner"
    for key in ("updown", "servo"):  # their tasks run in every status: never created or deleted
        assert all(row_tasks(TABLES[key], r) == "" for r in TABLES[key].rows)
    # the Path Planner's planner and its requests task take turns: never both, never neither
    msp = TABLES["msp"]
    assert row_tasks(msp, r53) == "+msp_planner -msp_requests"
    assert row_tasks(msp, r61) == "+msp_requests -msp_planner"
    assert all(len(msp.running_in(s)) == 1 for s in S if s != S.NO_SUBORDINATE)


def test_a_layer_task_its_table_does_not_know_is_refused_at_wiring():
    from controller import tables
    real = tables.TABLES["joint"]
    tables.TABLES["joint"] = layer_table("joint", "Joint Planner", "servo", "Servo Control", (), "no tasks")
    try:
        with pytest.raises(ScheduleError, match="task joint_planner of layer joint is not in its decision table"):
            SystemSimulator().close()
    finally:
        tables.TABLES["joint"] = real


def _runs(rt):
    return (rt.by_key["trajectory"].runs["trajectory_planner"], rt.by_key["cartesian"].runs["cartesian_fast"])


def test_tasks_run_only_while_their_table_has_created_them():
    """Shut down, the planners' tasks do not exist (they are not run, not merely idle); the
    power-up's rows create them, the power-down's delete them; the tasks that run in every
    status never stop."""
    with SystemSimulator() as sim:
        rt = sim.rt
        ran: list = []
        rt.on_frame.append(ran.append)
        sim.step(32)
        assert _runs(rt) == (0, 0)
        assert not any({"trajectory_planner", "cartesian_fast", "joint_planner"} & set(r.tasks) for r in ran)
        assert all("updown_requests" in r.tasks for r in ran)
        assert sum("servo_control" in r.tasks for r in ran) == 16
        sim.power_up(400)
        assert rt.by_key["joint"].running == {"joint_planner"}
        assert rt.by_key["trajectory"].running == {"trajectory_planner"}
        before = _runs(rt)
        sim.step(32)
        after = _runs(rt)
        assert after[0] - before[0] == 4 and after[1] - before[1] == 8  # 40 Hz, 80 Hz over 0.1 s
        msgs = [m.text for m in rt.messages.recent(400, source="trajectory")]
        assert "task trajectory_planner created" in msgs
        code, text = sim.request(Request.POWER_DOWN, max_frames=600)
        assert code == Response.COMPLETE, text
        sim.step(2)
        assert rt.by_key["trajectory"].running == frozenset() and rt.by_key["joint"].running == frozenset()
        stopped = _runs(rt)
        sim.step(32)
        assert _runs(rt) == stopped
        assert rt.by_key["servo"].running == {"servo_control", "gripper_control"}


def test_an_error_deletes_the_planners_tasks_and_a_segment_in_progress_is_released():
    """A fault while the Trajectory Planner follows a segment: its table's ERROR row deletes
    the planner task, and the deletion answers the segment as stopped."""
    with SystemSimulator() as sim:
        rt = sim.rt
        sim.step(10)
        sim.power_up(400)
        sim.step(20)
        traj = rt.by_key["trajectory"]
        start = np.array(rt.wm.get("cart.pos_cmd_m"), dtype=float)
        rt.wm.post_task_outputs("msp", {"msp.seg_seq": 1, "msp.seg_pos_m": start + [0.0, 0.0, -0.1],
                                        "msp.seg_quat": rt.wm.get("cart.quat_cmd"),
                                        "msp.seg_limits": (0.02, 0.1, 0.1, 0.2), "msp.seg_last": True,
                                        "msp.seg_stop": False})
        sim.step(80)
        assert bool(rt.wm.get("traj.active")) and traj.run is not None  # following the segment
        FaultSet(sim.world).inject("resolver-los:shoulder_pitch_angle")
        sim.run_until(lambda: rt.status("trajectory") == S.ERROR, 200)
        sim.step(2)
        assert "trajectory_planner" not in traj.running
        assert traj.run is None and not traj.active and not bool(rt.wm.get("traj.active"))
        assert int(rt.wm.get("traj.done_seq")) == 1 and int(rt.wm.get("traj.done_code")) == DoneCode.STOPPED
        assert any("task trajectory_planner deleted" in m.text for m in rt.messages.recent(400, source="trajectory"))


def test_docs_show_the_tables_as_they_are():
    from pathlib import Path

    from controller import tables
    text = (Path(__file__).resolve().parents[2] / "docs" / "controller.md").read_text()
    begin, end = text.index(tables.DOC_BEGIN), text.index(tables.DOC_END) + len(tables.DOC_END)
    assert text[begin:end] == tables.markdown(), "docs/controller.md is stale: python -m sim.tables"
