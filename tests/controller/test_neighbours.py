"""Issue 33 item 2: data between neighbours only (IRSS report 2.3.2). Every layer declares
what it reads of the others; the runtime's wiring refuses a declared read of a layer that is
not adjacent, naming it; the world model refuses, while a layer's table or task runs, any
read the layer did not declare; tools read everything (simulated time)."""

from __future__ import annotations

import os

import pytest

from controller import neighbours
from controller.neighbours import HARDWARE_DATA, NOT_YET_NEIGHBOURS, read_rules, why_allowed
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


def test_every_read_still_skipping_a_layer_is_declared_and_would_be_refused(wired):
    """The list of reads not yet through the neighbours can only shrink: each entry is read
    by its layer, and each is a far read that the rule would refuse without it."""
    layers, specs = wired
    by_key = {l.key: l for l in layers}
    by_name = {s.name: s for s in specs}
    for (reader, name), why in NOT_YET_NEIGHBOURS.items():
        assert name in by_key[reader].reads, (reader, name)
        owner = neighbours.owner_layer(by_name[name])
        assert owner in ORDER and abs(ORDER.index(owner) - ORDER.index(reader)) > 1, (reader, name, owner)
        assert name not in HARDWARE_DATA and why


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
    """Its start pose without a valid Cartesian command is the Cartesian engine's relay of
    the Joint Planner's measured pose (cart.tool_*), not joint.tool_* two layers down; the
    relay is the measured pose as of the engine's last command (80 Hz)."""
    import numpy as np

    from controller.trajectory import TrajectoryLayer
    from sim.system import SystemSimulator
    assert not any(n.startswith("joint.") for n in TrajectoryLayer.reads)
    assert not any(layer == "trajectory" for layer, _ in neighbours.NOT_YET_NEIGHBOURS)
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        sim.step(8)
        wm = sim.rt.wm
        assert np.allclose(wm.get("cart.tool_pos_m"), wm.get("joint.tool_pos_m"), atol=1e-4)
        assert np.allclose(wm.get("cart.tool_quat"), wm.get("joint.tool_quat"), atol=1e-4)
