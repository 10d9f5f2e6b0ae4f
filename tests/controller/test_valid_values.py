"""Valid values (issue 33 item 3; report 2.2.2 rule 4: "always a valid value, in type, scope
and magnitude"): every float variable of the controller's table has a valid range, its own
(``valid=``) or its units' (``UNIT_RANGES``); a task's post outside it is refused, counted
and named, the variable keeps its last valid value, and the posting layer goes to ERROR
with the rates at 0 V; a user write outside it is refused with the same words."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.cartesian import CartesianLayer
from controller.decision import Status
from controller.layers import ERR_INVALID_VALUE, JointPlannerLayer, UpDownLayer
from controller.paths.layer import MSP, MultiSegmentLayer
from controller.runtime import runtime_specs
from controller.servo import ServoLayer
from controller.trajectory import TrajectoryLayer
from controller.variables import CART, DAQ, DaqVars
from controller.worldmodel import VarSpec, WorldModel, WorldModelError, WorldModelValueError
from controller.worldmodel.spec import UNIT_RANGES

RATE_CHANNELS = slice(0, 6)


def _upper_specs() -> list[VarSpec]:
    layers = [UpDownLayer(), MultiSegmentLayer(background_save=False), TrajectoryLayer(), CartesianLayer(),
              JointPlannerLayer(), ServoLayer()]
    return [s for l in layers for s in l.specs()] + runtime_specs() + DaqVars.specs()


def test_every_float_variable_of_the_controller_has_a_valid_range() -> None:
    specs = _upper_specs()
    floats = [s for s in specs if s.np_dtype.kind == "f"]
    assert len(floats) > 80
    assert [s.name for s in floats if not s.units] == [], "declare the units (1: dimensionless)"
    unbounded = [s.name for s in floats if not s.bounds]
    assert unbounded == [], f"declare valid= (or units with a row in UNIT_RANGES): {unbounded}"
    for s in floats:
        lo, hi = s.bounds
        assert math.isfinite(lo) and math.isfinite(hi) and lo <= hi
        init = np.asarray(s.initial, dtype=float)
        assert init.min() >= lo and init.max() <= hi, s.name
    # the rest are enumerations, bit sets, booleans or integers in their type's range
    others = [s for s in specs if s.np_dtype.kind != "f"]
    assert all(s.np_dtype.kind in "biu" for s in others)


def test_a_units_range_and_an_own_range() -> None:
    assert DAQ.joint_rate_rad_s.spec.bounds == UNIT_RANGES["rad/s"]
    assert MSP.speed_scale.spec.bounds == (0.0, 10.0) and MSP.speed_scale.spec.range_text() == "0..10"
    with pytest.raises(WorldModelError, match="lo <= hi"):
        VarSpec("x.y", "task_io", "f8", (), "x", 0.0, valid=(1.0, 0.0))
    with pytest.raises(WorldModelError, match="initial value is not valid"):
        VarSpec("x.y", "task_io", "f8", (), "x", 2.0, valid=(0.0, 1.0))
    with pytest.raises(WorldModelError, match="enumeration"):
        VarSpec("x.y", "task_io", "i2", (), "x", 0, enum={0: "A"}, valid=(0, 1))
    # the range survives the table's JSON (a process attaching reads it back)
    s = VarSpec("x.y", "task_io", "i4", (), "x", 3, valid=(0, 9))
    assert VarSpec.from_json(s.to_json()).bounds == (0, 9)


def test_a_post_outside_the_range_is_refused_counted_named_and_the_value_kept() -> None:
    wm = WorldModel.create(DaqVars.specs())
    try:
        wm.post_task_outputs("daq", {DAQ.joint_rate_rad_s: np.full(6, 0.5)})
        wm.communications_segment()
        for bad in (np.array([0.5, 0.5, 80.0, 0.5, 0.5, 0.5]), [0.5, 0.5, 0.5, 0.5, 0.5, -51.0],
                    np.array([0.5] * 5 + [1e300])):
            with pytest.raises(WorldModelValueError, match=r"daq\.joint_rate_rad_s: -?\d+(e\+\d+)? rad/s is outside "
                                                           r"its valid range -50\.\.50 rad/s"):
                wm.post_task_outputs("daq", {DAQ.joint_rate_rad_s: bad, DAQ.service_frame: 9})
        with pytest.raises(WorldModelValueError, match="outside its valid range"):
            wm.post_task_outputs("daq", {DAQ.gripper_current_a: 150.0})  # a scalar on the fast path
        wm.communications_segment()
        assert wm.stats()["refused_posts"] == 4
        assert "daq.gripper_current_a: 150 A is outside" in wm.last_refusal
        # all or nothing: the frame number of the refused posts was not queued either
        assert np.all(wm.get(DAQ.joint_rate_rad_s) == 0.5) and int(wm.get(DAQ.service_frame)) == 0
        wm.post_task_outputs("daq", {DAQ.joint_rate_rad_s: np.full(6, 50.0)})  # the bound is valid
        wm.communications_segment()
        assert np.all(wm.get(DAQ.joint_rate_rad_s) == 50.0)
    finally:
        wm.close()


def test_a_user_write_outside_the_range_is_refused_in_the_same_words(sim) -> None:
    wm = sim.rt.wm
    with pytest.raises(WorldModelValueError, match=r"msp\.speed_scale: 12 is outside its valid range 0\.\.10"):
        wm.set_user(MSP.speed_scale, 12.0, wm.access_key)
    wm.set_user(MSP.speed_scale, 2.0, wm.access_key)
    sim.step(2)
    assert float(wm.get(MSP.speed_scale)) == 2.0


def test_a_layer_whose_task_posts_an_invalid_value_goes_to_error_with_outputs_safe(powered) -> None:
    """The Cartesian Engine's fast task posts a tool command 50 m away: refused, the last
    valid command kept, the layer in ERROR naming the variable and its range, every layer
    above and below it in ERROR, the rate channels at 0 V."""
    sim, rt = powered, powered.rt
    cart = rt.by_key["cartesian"]
    real = cart.fast_task
    last = np.array(rt.wm.get(CART.pos_cmd_m))

    def wild(ctx) -> None:
        real(ctx)
        ctx.wm.post_task_outputs("cartesian", {CART.pos_cmd_m: np.array([50.0, 0.0, 0.0])})

    cart.periodic["cartesian_fast"] = wild
    rt._build_schedule()  # the scheduling table takes the layer's tasks when it is built
    refused = rt.wm.stats()["refused_posts"]
    sim.run_until(lambda: rt.status("cartesian") == Status.ERROR, 20)
    assert cart.error_code == ERR_INVALID_VALUE
    assert "cart.pos_cmd_m: 50 m is outside its valid range -10..10 m" in cart.fault_text
    assert rt.wm.stats()["refused_posts"] > refused
    assert np.all(np.abs(np.array(rt.wm.get(CART.pos_cmd_m)) - last) < 0.05)  # never 50 m
    assert rt.status("updown") == Status.ERROR
    sim.step(3)
    assert np.all(sim.dac_volts()[RATE_CHANNELS] == 0.0)
    assert any("posted an invalid value" in m.text for m in rt.messages.recent(100, source="cartesian"))


def test_an_integer_array_s_own_range_binds_the_fast_path_too() -> None:
    wm = WorldModel.create([VarSpec("x.codes", "task_io", "i4", (3,), "x", [0, 0, 0], valid=(0, 9))])
    try:
        with pytest.raises(WorldModelValueError, match=r"x\.codes: 10 is outside its valid range 0\.\.9"):
            wm.post_task_outputs("x", {"x.codes": np.array([1, 10, 2], dtype=np.int32)})  # the array's own bytes
        wm.post_task_outputs("x", {"x.codes": np.array([1, 9, 2], dtype=np.int32)})
        wm.communications_segment()
        assert list(wm.get("x.codes")) == [1, 9, 2] and wm.stats()["refused_posts"] == 1
    finally:
        wm.close()


def test_a_published_input_outside_its_range_is_a_named_fault_not_a_crash(powered) -> None:
    """The service publishes a shoulder-yaw tach reading of 80 rad/s (the default rack cannot:
    its scales are held to 0.5x..2x nominal at parse, but a lab's allow_nonnominal
    calibration could): the Data Acquisition layer's post is refused, the inputs keep their
    last valid values, the layer faults with code 93 naming the variable, the ERROR climbs
    and the rates go to 0 V; the controller's frame does not raise."""
    sim, rt = powered, powered.rt
    daq = rt.daq
    real = daq.client.read_inputs
    slot = int(daq.tach_slots[1])

    def wild():
        snap = real()
        snap.record["adc_value"][slot] = 80.0
        return snap

    daq.client.read_inputs = wild
    before = np.array(rt.wm.get(DAQ.joint_rate_rad_s))
    sim.run_until(lambda: rt.status("updown") == Status.ERROR, 10)
    assert daq.error_code == ERR_INVALID_VALUE
    assert "daq.joint_rate_rad_s: 80 rad/s is outside its valid range -50..50 rad/s" in daq.fault_text
    assert np.all(np.array(rt.wm.get(DAQ.joint_rate_rad_s)) == before)  # never 80
    sim.step(3)
    assert np.all(sim.dac_volts()[RATE_CHANNELS] == 0.0)
    said = [m.text for m in rt.messages.recent(200, source="daq") if m.text.startswith("fault 93: inputs refused")]
    assert len(said) == 1  # said once, not every frame
