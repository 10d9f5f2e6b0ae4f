"""The first cause of an ERROR episode (issue 29 item 3): the root message that started
the cascade (not the "subordinate in ERROR" ones that follow) is kept in
``ControllerRuntime.first_cause`` and the world model's ``runtime.first_cause*`` until an
ERROR RESET completes, however many messages come after it."""

from __future__ import annotations

import numpy as np

from controller.decision import Status
from controller.layers import Request, Response
from controller.messages import Level
from controller.params import JOINT_NAMES
from controller.runtime import FIRST_CAUSE_BYTES
from sim.faults import FaultSet


def _wm_cause(rt) -> str:
    return bytes(np.asarray(rt.wm.get("runtime.first_cause"), dtype=np.uint8)).rstrip(b"\0").decode()


def _error_texts(rt) -> list[str]:
    return [m.text for m in rt.messages.recent(min_level=Level.ERROR)]


def test_a_resolver_fault_keeps_its_root_through_the_cascade_and_100_later_messages(powered):
    sim, rt = powered, powered.rt
    assert rt.first_cause is None and _wm_cause(rt) == "" and int(rt.wm.get("runtime.first_cause_frame")) == -1
    FaultSet(sim.world).inject("resolver-los:shoulder_pitch_angle")
    assert sim.run_until(lambda: rt.status("updown") == Status.ERROR, 200) >= 0
    fc = rt.first_cause
    assert fc is not None and fc.source == "daq"
    assert "shoulder_pitch" in fc.text and "subordinate in ERROR" not in fc.text
    # the root is the earliest ERROR message of the episode, before every layer's cascade line
    first_error = next(m for m in rt.messages.recent(min_level=Level.ERROR))
    assert (fc.frame, fc.text) == (first_error.frame, first_error.text)
    assert any("subordinate in ERROR" in t for t in _error_texts(rt))
    assert _wm_cause(rt) == f"daq: {fc.text}"[:FIRST_CAUSE_BYTES]
    assert int(rt.wm.get("runtime.first_cause_frame")) == fc.frame
    assert int(rt.wm.get("runtime.first_cause_code")) == fc.code == rt.daq.error_code
    # 150 later ERROR messages (more than the 100 merged and the 50 per source) change nothing
    for i in range(150):
        rt.post("servo", Level.ERROR, f"a later error {i}")
        rt.post("runtime", Level.WARNING, f"a later warning {i}")
    sim.step(100)
    assert all(fc.text != m.text for m in rt.messages.recent(30))  # scrolled out of the last 30
    assert rt.first_cause == fc and _wm_cause(rt) == f"daq: {fc.text}"
    assert rt.error_episodes == 1


def test_error_reset_clears_the_first_cause_and_a_new_episode_records_its_own_root(powered):
    sim, rt = powered, powered.rt
    faults = FaultSet(sim.world)
    faults.inject("resolver-los:shoulder_pitch_angle")
    sim.run_until(lambda: rt.status("updown") == Status.ERROR, 200)
    assert rt.first_cause is not None and "shoulder_pitch" in rt.first_cause.text
    faults.clear("resolver-los:shoulder_pitch_angle")
    sim.step(400)  # safe tasks finished
    code, text = sim.request(Request.ERROR_RESET, max_frames=600)
    assert code == Response.COMPLETE, text
    assert rt.first_cause is None and _wm_cause(rt) == ""
    assert int(rt.wm.get("runtime.first_cause_frame")) == -1
    # a second episode, another joint: its own root, not the first episode's
    sim.power_up(max_frames=400)
    sim.step(20)
    assert rt.all_status(Status.START_UP_COMPLETE)
    faults.inject("resolver-los:wrist_yaw_angle")
    sim.run_until(lambda: rt.status("updown") == Status.ERROR, 200)
    assert rt.first_cause is not None and "wrist_yaw" in rt.first_cause.text
    assert "shoulder_pitch" not in rt.first_cause.text and rt.error_episodes == 2


def test_a_reversed_tach_keeps_the_supervision_trip_as_the_root(powered):
    """The servo's joint supervision names the joint and the likely cause; that sentence is
    the root, the layers' cascade after it is not."""
    sim, rt = powered, powered.rt
    k = JOINT_NAMES.index("shoulder_yaw")
    goal = np.array(rt.wm.get("daq.joint_angle_rad"))
    goal[k] += 0.3
    FaultSet(sim.world).inject("tach-reversed:shoulder_yaw")
    rt.set_joint_goal(goal)
    assert sim.run_until(lambda: rt.status("updown") == Status.ERROR, 1600) >= 0
    fc = rt.first_cause
    assert fc is not None and fc.source == "servo", fc
    assert "shoulder_yaw" in fc.text and fc.code == rt.servo.error_code != 0
    assert fc.text == rt.messages.recent(min_level=Level.ERROR)[0].text


def test_pfma_wm_and_stats_show_the_first_cause_of_a_running_controller(capsys):
    import json
    import uuid

    from controller.worldmodel import WorldModel
    from sim.system import SystemSimulator
    from tools.cli import main
    from tools.cli.stats import controller_first_cause
    name = "pfma-test-fc-" + uuid.uuid4().hex[:6]
    sim = SystemSimulator(wm_name=name)
    try:
        sim.step(10)
        assert main(["wm", "list", "--name", name, "--filter", "runtime.frames"]) == 0
        out = capsys.readouterr().out.splitlines()
        assert not out[1].startswith("first cause")  # no episode: no line
        assert controller_first_cause(name) == ""
        sim.power_up(max_frames=400)
        FaultSet(sim.world).inject("resolver-los:shoulder_pitch_angle")
        sim.run_until(lambda: sim.rt.status("updown") == Status.ERROR, 200)
        want = f"{sim.rt.first_cause.source}: {sim.rt.first_cause.text}"
        assert main(["wm", "list", "--name", name, "--filter", "runtime.frames"]) == 0
        out = capsys.readouterr().out.splitlines()
        assert out[0].startswith(f"world model '{name}'") and out[1] == f"first cause of the ERROR: {want}"
        assert main(["wm", "get", "runtime.frames", "--name", name]) == 0
        assert capsys.readouterr().out.splitlines()[1] == f"first cause of the ERROR: {want}"
        assert main(["wm", "get", "runtime.frames", "--name", name, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["first_cause"] == want
        assert controller_first_cause(name) == want and "shoulder_pitch" in want
    finally:
        sim.close()
        WorldModel.remove_segment(name)
    assert controller_first_cause(name) is None  # gone: nothing shown


def test_distributed_each_process_keeps_its_own_root_and_an_error_reset_clears_both():
    """A distributed controller: the rack process keeps the rack's root message; the
    planners' process (which sees the rack only through its sections) keeps its first local
    ERROR; System Up/Down's ERROR RESET, seen across the boundary, clears both."""
    from sim.distributed import DistributedSimulator
    two = {"process": {"planners": {"layers": ["updown", "msp", "trajectory", "cartesian"]},
                       "rack": {"layers": ["joint", "servo", "daq"]}}}
    with DistributedSimulator(two) as sim:
        sim.step(10)
        sim.power_up(1000)
        faults = FaultSet(sim.world)
        faults.inject("resolver-los:shoulder_pitch_angle")
        sim.run_until(lambda: sim.all_status(Status.ERROR), 100)
        rack, top = sim.rt("rack").first_cause, sim.rt("planners").first_cause
        assert rack is not None and rack.source == "daq" and "shoulder_pitch" in rack.text
        assert top is not None and top.source == "cartesian" and "subordinate in ERROR" in top.text
        faults.clear("resolver-los:shoulder_pitch_angle")
        sim.step(400)
        code, text = sim.request(Request.ERROR_RESET, max_frames=600)
        assert code == Response.COMPLETE, text
        sim.step(5)
        assert sim.rt("rack").first_cause is None and sim.rt("planners").first_cause is None
