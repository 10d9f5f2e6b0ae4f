"""Issue 33 item 2: data between neighbours only (IRSS report 2.3.2). Every layer declares
what it reads of the others; the runtime's wiring refuses a declared read of a layer that is
not adjacent, naming it; the world model refuses, while a layer's table or task runs, any
read the layer did not declare; tools read everything (simulated time)."""

from __future__ import annotations

import os

import pytest

from controller import neighbours
from controller.neighbours import HARDWARE_DATA, read_rules, why_allowed
from controller.relays import RELAYS, Relay, at, relayed, wire
from controller.worldmodel import WorldModel, WorldModelError

ORDER = ["updown", "msp", "trajectory", "cartesian", "joint", "servo", "daq"]


@pytest.fixture(scope="module")
def wired():
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        yield sim.rt.layers, list(sim.rt.wm.specs)


def test_every_declared_read_is_allowed_and_says_why(wired):
    layers, specs = wired
    assert [l.key for l in layers] == ORDER
    rows = neighbours.table(layers, specs)
    assert rows and all(why != "REFUSED" for *_, why in rows)
    by_name = {s.name: s for s in specs}
    for reader, name, owner, why in rows:
        if why == "a neighbour's":
            assert abs(ORDER.index(owner) - ORDER.index(reader)) == 1
        elif why == "hardware data":
            assert name in HARDWARE_DATA and by_name[name].writer == "daq"
        elif why == "user-interface data":
            assert by_name[name].writer == "user"


def test_no_layer_reads_further_than_its_neighbour(wired):
    """Issue 33 item 2 done: every declared read is the reader's neighbour's, hardware data or
    user-interface data; what comes from further away is the neighbour's copy."""
    layers, specs = wired
    rows = neighbours.table(layers, specs)
    assert {why for *_, why in rows} == {"a neighbour's", "hardware data", "user-interface data"}
    by_key = {l.key: l for l in layers}
    for r in RELAYS:
        for name in r.names:
            assert name not in by_key[r.to].reads, (r.to, name)  # not the origin ...
            assert at(r.to, name) in by_key[r.to].reads, (r.to, name)
            # ... but the copy of the layer next to it, which each layer between passes on
            src = name
            for k in r.via:
                assert (relayed(k, name), src) in by_key[k].relay_pairs
                src = relayed(k, name)


def test_a_relay_must_be_a_run_of_neighbours_and_name_something(wired):
    layers, specs = wired
    with pytest.raises(WorldModelError, match="msp -> cartesian -> joint is not a run of neighbours"):
        wire(layers, specs, (Relay(("msp.jmove_seq",), ("msp", "cartesian"), "joint", "skips"),))
    with pytest.raises(WorldModelError, match="relay of msp.no_such: no layer declares it"):
        wire(layers, specs, (Relay(("msp.no_such",), ("trajectory", "cartesian"), "joint", "nothing"),))


def test_requests_and_answers_arrive_a_layer_a_minor_frame_whole():
    """A joint move's request posted by the Path Planner reaches the Joint Planner as the
    Cartesian engine's copy two minor frames later (one per layer between), payload and
    sequence number in the same frame; the camera route request reaches Data Acquisition
    through the five layers between."""
    import numpy as np

    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        sim.step(4)
        wm = sim.rt.wm
        goal = np.asarray(wm.get("servo.q_cmd_rad"), float)
        seen = []

        def watch():
            seen.append((int(wm.get("traj.msp_jmove_seq")), int(wm.get("cart.msp_jmove_seq")),
                         np.asarray(wm.get("cart.msp_jmove_goal_rad"), float).copy()))
        wm.post_task_outputs("msp", {"msp.jmove_goal_rad": goal, "msp.jmove_seq": 77})
        wm.communications_segment()
        for _ in range(3):
            sim.step(1)
            watch()
        assert [s[:2] for s in seen] == [(77, 0), (77, 77), (77, 77)]
        assert np.allclose(seen[1][2], goal)  # with its payload
        seq0 = int(wm.get("servo.updown_route_request_seq"))
        wm.post_task_outputs("updown_requests", {"updown.route_request": 1 * 16 + 2,
                                                 "updown.route_request_seq": seq0 + 1})
        wm.communications_segment()
        frames = sim.run_until(lambda: int(wm.get("servo.updown_route_request_seq")) == seq0 + 1, 20)
        assert frames == 5 and int(wm.get("servo.updown_route_request")) == 18


def test_wiring_refuses_a_far_read_naming_layer_variable_and_owner(wired, monkeypatch):
    layers, specs = wired
    updown = layers[0]
    monkeypatch.setattr(type(updown), "reads", updown.reads + ("servo.rate_cmd_rad_s", "servo.no_such_thing",
                                                               "runtime.first_cause"))
    with pytest.raises(WorldModelError) as err:
        read_rules(layers, specs)
    text = str(err.value)
    assert "updown may not read servo.rate_cmd_rad_s (written by servo, 5 layers away)" in text
    assert "data passes between neighbours only (report 2.3.2)" in text
    assert "updown declares a read of 'servo.no_such_thing', which no layer declares" in text
    assert "updown may not read runtime.first_cause (written by runtime)" in text  # no layer: no distance
    by_name = {s.name: s for s in specs}
    assert why_allowed("servo", by_name["servo.rate_cmd_rad_s"], ORDER) == "its own"
    assert why_allowed("daq", by_name["servo.rate_cmd_rad_s"], ORDER) == "a neighbour's"
    assert why_allowed("msp", by_name["daq.joint_angle_rad"], ORDER) == "hardware data"
    assert why_allowed("updown", by_name["servo.kp_per_s"], ORDER) == "user-interface data"
    assert why_allowed("updown", by_name["daq.fault_bits"], ORDER) is None


def test_a_runtime_whose_layer_declares_a_far_read_is_not_built(monkeypatch):
    from controller.layers import UpDownLayer
    from sim.system import SystemSimulator
    monkeypatch.setattr(UpDownLayer, "reads", UpDownLayer.reads + ("daq.fault_bits",))
    with pytest.raises(WorldModelError, match="updown may not read daq.fault_bits"):
        SystemSimulator()


def test_an_undeclared_read_in_a_task_is_refused_and_faults_its_layer(monkeypatch):
    """Cartesian's slow task made to read the servo's rate command (two layers down, not
    declared): the world model refuses it, the task raises, its layer reports error 90
    naming the read, and the arm is not flown on it."""
    from controller.decision import Status
    from controller.cartesian import CartesianLayer
    from sim.system import SystemSimulator

    real = CartesianLayer.slow_task

    def nosy(self, rt):
        rt.wm.get("servo.rate_cmd_rad_s")
        return real(self, rt)

    monkeypatch.setattr(CartesianLayer, "slow_task", nosy)
    with SystemSimulator(wm_name=f"pfma-nb-{os.getpid()}") as sim:
        sim.step(10)
        try:  # the task exists from the Cartesian engine's START UP COMPLETE (its table creates it)
            sim.power_up(max_frames=300)
        except TimeoutError:
            pass  # its first run may come before System Up/Down is up
        sim.run_until(lambda: int(sim.rt.wm.get("cartesian.status")) == Status.ERROR, 100)
        cart = sim.rt.by_key["cartesian"]
        assert int(sim.rt.wm.get("cartesian.status")) == Status.ERROR
        assert "layer cartesian reads servo.rate_cmd_rad_s (written by servo) without declaring it" in cart.fault_text
        # outside a layer's table or task nothing is refused: the runtime, tools
        assert sim.rt.wm.get("servo.rate_cmd_rad_s").shape == (6,)
        ro = WorldModel.attach(sim.rt.wm.name)
        try:
            assert ro.get("servo.rate_cmd_rad_s").shape == (6,)
        finally:
            ro.close()


def test_docs_show_the_declared_reads(wired):
    from pathlib import Path
    layers, specs = wired
    text = (Path(__file__).resolve().parents[2] / "docs" / "controller.md").read_text()
    begin, end = text.index(neighbours.DOC_BEGIN), text.index(neighbours.DOC_END) + len(neighbours.DOC_END)
    assert text[begin:end] == neighbours.markdown(layers, specs), "docs/controller.md is stale: python -m sim.neighbours"


def test_the_trajectory_planner_reads_the_tool_pose_through_the_cartesian_engine():
    """Its start pose without a valid Cartesian command is the Cartesian engine's copy of the
    Joint Planner's measured pose (cart.joint_tool_*), not joint.tool_* two layers down."""
    import numpy as np

    from controller.trajectory import TrajectoryLayer
    from sim.system import SystemSimulator
    assert not any(n.startswith("joint.") for n in TrajectoryLayer.reads)
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        sim.step(8)
        wm = sim.rt.wm
        assert np.allclose(wm.get("cart.joint_tool_pos_m"), wm.get("joint.tool_pos_m"), atol=1e-4)
        assert np.allclose(wm.get("cart.joint_tool_quat"), wm.get("joint.tool_quat"), atol=1e-4)
        assert np.allclose(wm.get("traj.joint_tool_pos_m"), wm.get("joint.tool_pos_m"), atol=1e-4)


def test_a_relay_copies_like_for_like_and_only_what_changed():
    from controller.worldmodel import VarSpec
    specs = [VarSpec("a.x", "task_io", "f8", (3,), "a", [0.0] * 3, "m"),
             VarSpec("b.a_x", "task_io", "f8", (3,), "b", [0.0] * 3, "m"),
             VarSpec("b.n", "task_io", "i4", (), "b", 0)]
    wm = WorldModel.create(specs)
    try:
        pairs = (("b.a_x", "a.x"),)
        assert wm.relay("b", pairs) == 0  # equal bytes: nothing queued
        wm.post_task_outputs("a", {"a.x": [1.0, 2.0, 3.0]})
        wm.communications_segment()
        assert wm.relay("b", pairs) == 1
        wm.communications_segment()
        assert list(wm.get("b.a_x")) == [1.0, 2.0, 3.0]
        assert wm.relay("b", pairs) == 0
        with pytest.raises(WorldModelError, match="written only by 'b'"):
            wm.relay("a", pairs)
        with pytest.raises(WorldModelError, match="relay a.x -> b.n"):
            wm.relay("b", (("b.n", "a.x"),))
    finally:
        wm.close()


def test_a_read_only_attachment_cannot_relay(wired):
    from sim.system import SystemSimulator
    with SystemSimulator(wm_name=f"pfma-nb-ro-{os.getpid()}") as sim:
        ro = WorldModel.attach(sim.rt.wm.name)
        try:
            with pytest.raises(WorldModelError, match="attached read-only here; relaying belongs to its owner"):
                ro.relay("trajectory", (("traj.joint_tool_pos_m", "cart.joint_tool_pos_m"),))
        finally:
            ro.close()
