"""World-model variables declared once as typed attributes (controller/variables.py,
controller/worldmodel/var.py): the names are the old strings, the layer's table is made
from the declarations, a misspelt variable fails, docs/world-model.md lists them."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest

import controller.variables as variables
from controller import vardoc
from controller.variables import DAQ, DaqVars
from controller.worldmodel import VarSpec, WorldModel, WorldModelError
from controller.worldmodel.var import Var, VarGroup, var

DOC = Path(__file__).resolve().parents[2] / "docs" / "world-model.md"


def test_names_are_the_old_strings() -> None:
    assert DAQ.joint_angle_rad == "daq.joint_angle_rad"
    assert isinstance(DAQ.joint_angle_rad, str) and isinstance(DAQ.joint_angle_rad, Var)
    assert [str(v) for v in DAQ.all()] == [
        "daq.joint_angle_rad", "daq.joint_rate_rad_s", "daq.motor_current_a", "daq.ft_force_n", "daq.ft_torque_nm",
        "daq.hc_axes", "daq.hc_deadman", "daq.service_frame", "daq.gripper_rate_m_s", "daq.gripper_current_a",
        "daq.service_state", "daq.brakes_released", "daq.outputs_enabled", "daq.user_inputs", "daq.camera_route",
        "daq.camera_route_applied", "daq.fault_bits"]
    assert all(v.writer == "daq" for v in DAQ.all())


def test_a_misspelt_variable_fails() -> None:
    with pytest.raises(AttributeError):
        DAQ.joint_angl_rad  # type: ignore[attr-defined]  # noqa: B018


def test_a_bad_declaration_fails_at_import() -> None:
    with pytest.raises(WorldModelError, match="dtype"):
        class Bad(VarGroup, prefix="bad"):  # noqa: F841
            x: Var[float] = var("task_io", "c16")


def test_the_table_is_made_from_the_declarations() -> None:
    specs = DAQ.specs()
    assert all(isinstance(s, VarSpec) for s in specs)
    assert [s.name for s in specs] == list(DAQ.all())
    assert all(s.name is v for s, v in zip(specs, DAQ.all()))  # the model's tables are keyed by the Var
    text = json.dumps([s.to_json() for s in specs])
    assert json.loads(text)[0]["name"] == "daq.joint_angle_rad"
    assert DAQ.fault_bits.spec.flag_names == variables.FAULT_NAMES


def test_a_var_reads_and_writes_the_model_as_its_name() -> None:
    wm = WorldModel.create(DaqVars.specs())
    try:
        wm.post_task_outputs("daq", {DAQ.service_frame: 7})
        wm.communications_segment()
        assert int(wm.get(DAQ.service_frame)) == int(wm.get("daq.service_frame")) == 7
        v = wm.get_task_inputs((DAQ.service_frame, "daq.fault_bits"))
        assert int(v["daq.service_frame"]) == 7 and int(v[DAQ.fault_bits]) == 0
    finally:
        wm.close()


def test_a_var_pickles_as_its_name() -> None:
    back = pickle.loads(pickle.dumps(DAQ.joint_angle_rad))
    assert back == "daq.joint_angle_rad" and type(back) is str


def test_docs_list_the_variables() -> None:
    text = DOC.read_text()
    begin, end = text.index(vardoc.DOC_BEGIN), text.index(vardoc.DOC_END) + len(vardoc.DOC_END)
    assert text[begin:end] == vardoc.markdown(), "docs/world-model.md is stale: python -m controller.vardoc"


def test_a_var_shows_as_its_name() -> None:
    v = DAQ.joint_angle_rad
    assert repr(v) == repr("daq.joint_angle_rad") and f"{v}" == str(v) == "daq.joint_angle_rad"
    assert hash(v) == hash("daq.joint_angle_rad")


def test_servo_names_are_the_old_strings() -> None:
    from controller.servo import SERVO, ServoVars
    assert SERVO is ServoVars and SERVO.current_limit_cmd_a == "servo.current_limit_cmd_a"
    assert [str(v) for v in SERVO.all()] == [f"servo.{n}" for n in (
        "kp_per_s", "tau_z_s", "tau_p_s", "rate_limit_rad_s", "current_limit_a", "q_min_rad", "q_max_rad",
        "ferror_min_rad", "ferror_max_rad", "ferror_time_s", "ferror_rad", "trip_joint", "trip_cause",
        "rate_cmd_rad_s", "rate_cmd_frame", "current_limit_cmd_a", "error_rad", "brake_state", "brake_phase",
        "brake_test", "gain_switch")]
    assert SERVO.kp_per_s.writer == "user" and SERVO.kp_per_s.spec.protected
    assert SERVO.rate_cmd_rad_s.writer == "servo"


def test_joint_planner_names_are_the_old_strings() -> None:
    from controller.layers import JOINT, JointPlannerLayer
    assert JOINT.q_cmd_rad == "servo.q_cmd_rad" and JOINT.q_cmd_rad.writer == "joint"
    assert JOINT.goal_rad == "joint.goal_rad" and JOINT.goal_rad.writer == "user"
    assert JointPlannerLayer.MODE_NAMES == dict(JOINT.mode.spec.enum)
    specs = {s.name: s for s in JointPlannerLayer(shoulder_roll_deg=45).specs()}
    assert specs["joint.shoulder_roll_deg"].initial == 45.0
    assert specs["joint.shoulder_roll_rad"].initial == pytest.approx(0.7853981633974483)
    assert specs["joint.shoulder_roll_deg"].name is JOINT.shoulder_roll_deg  # still the Var


def test_force_delay_teleop_names_are_the_old_strings() -> None:
    from controller.cartesian import CartesianLayer
    from controller.delay import DELAY
    from controller.force import FORCE
    from controller.teleop import TELEOP
    assert [str(v) for v in FORCE.all()] == [f"force.{n}" for n in (
        "enable", "zero_seq", "frame", "mass", "damping", "stiffness", "wrench_des", "state", "offset", "wrench_n",
        "bias")]
    assert [str(v) for v in DELAY.all()] == ["delay.round_trip_s", "delay.jitter"]
    assert [str(v) for v in TELEOP.all()] == [f"teleop.{n}" for n in (
        "reflect_force_n", "reflect_torque_nm", "reflect_enabled", "seen_pos_m", "seen_quat", "seen_force_n")]
    assert FORCE.enable.writer == "user" and FORCE.state.writer == "cartesian"
    assert all(v.writer == "user" for v in DELAY.all()) and all(v.writer == "cartesian" for v in TELEOP.all())
    specs = {s.name: s for s in CartesianLayer().specs()}
    for v in (*FORCE.all(), *DELAY.all(), *TELEOP.all()):
        assert specs[v].name is v  # the layer's table is made from the declarations


def test_runtime_names_are_the_old_strings() -> None:
    from controller.runtime import RUNTIME, runtime_specs
    assert [str(v) for v in RUNTIME.all()] == [f"runtime.{n}" for n in (
        "frames", "missed_frames", "missed_events", "longest_missed_run", "missed_task_slots", "overruns", "rate_hz",
        "wake_latency_us", "work_us", "halted", "steps_left", "step_frames", "step_trace", "first_cause",
        "first_cause_code", "first_cause_frame")]
    assert all(v.writer == "runtime" for v in RUNTIME.all())
    assert [s.name for s in runtime_specs()] == list(RUNTIME.all())


def test_a_table_cell_keeps_its_bars() -> None:
    from controller.force import FORCE
    assert f"| {FORCE.mass.units.replace('|', chr(92) + '|')} |" in vardoc.markdown()


def test_gripper_names_are_the_old_strings() -> None:
    from controller.gripper import GRIP, GripperVars, gripper_specs
    assert GRIP is GripperVars
    assert [str(v) for v in GRIP.all()] == [f"gripper.{n}" for n in (
        "request", "request_force_n", "request_seq", "response", "response_seq", "response_text", "state", "force_n",
        "motor_force_n", "jaw_m", "jaw_known", "rate_cmd_m_s", "msp_done_seq", "msp_done_code", "event_seq", "event",
        "event_force_n")]
    assert [v.writer for v in GRIP.all()[:3]] == ["user"] * 3 and all(v.writer == "servo" for v in GRIP.all()[3:])
    assert all(s.name is v for s, v in zip(gripper_specs(), GRIP.all()))


def test_ui_names_are_the_old_strings() -> None:
    from controller.layers import ANSWER_VARS, UI, UpDownLayer
    assert [str(v) for v in UI.all()] == [
        "ui.request", "ui.request_seq", "ui.queue", "ui.active", "updown.route_request", "updown.route_request_seq",
        "ui.response_text", "ui.response", "ui.response_seq", "ui.answer_count", "ui.answer_seq", "ui.answer_code",
        "ui.answer_text"]
    assert UI.request.writer == "user" and all(v.writer == "updown_requests" for v in UI.all()[1:])
    assert "Kinds: " in UI.request.doc and ANSWER_VARS[0] is UI.answer_count
    specs = UpDownLayer().specs()
    assert [s.name for s in specs if s.name in set(UI.all())] == list(UI.all())
    assert all(s.name is v for s, v in zip(specs[-len(UI.all()):], UI.all()))


def test_cart_names_are_the_old_strings() -> None:
    import controller.cartesian as cartesian
    from controller.variables import CART
    assert [str(v) for v in CART.all()] == [f"cart.{n}" for n in (
        "mode", "hc_source", "hc_frame", "hc_gain_lin_m_s", "hc_gain_rot_rad_s", "vernier", "pos_cmd_m", "quat_cmd",
        "cmd_valid", "cmd_seq", "ref_pos_m", "ref_quat", "hc_active")]
    assert [v.writer for v in CART.all()] == ["user"] * 6 + ["cartesian"] * 7
    assert cartesian.MODE_NAMES is variables.MODE_NAMES and cartesian.MODE_TRAJECTORY == 2  # still importable there
    specs = {s.name: s for s in cartesian.CartesianLayer().specs()}
    assert all(specs[v].name is v for v in CART.all())


def test_traj_names_are_the_old_strings() -> None:
    from controller.trajectory import CAP_VARS, TRAJ, TrajectoryLayer
    assert [str(v) for v in TRAJ.all()] == [f"traj.{n}" for n in (
        "pos_m", "quat", "vel_m_s", "omega_rad_s", "t_s", "active", "seg_seq", "progress", "done_seq", "done_code",
        "v_lin_max_m_s", "a_lin_max_m_s2", "v_rot_max_rad_s", "a_rot_max_rad_s2")]
    assert all(v.writer == "user" and v.spec.protected for v in CAP_VARS)
    assert all(v.writer == "trajectory" for v in TRAJ.all()[:10])
    specs = {s.name: s for s in TrajectoryLayer().specs()}
    assert all(specs[v].name is v for v in TRAJ.all())


def test_every_layer_variable_is_declared_in_a_group() -> None:
    """Every row of the six upper layers' tables (and the runtime's) is a declared ``Var``,
    so "find references" follows it; only the decision-table state every layer has
    (``<key>.command``, ``.status``, ``.row``, ``.task``, ``.error``) is made from the key."""
    from controller.cartesian import CartesianLayer
    from controller.layers import JMOVE, JointPlannerLayer, UpDownLayer
    from controller.paths.layer import MSP, MultiSegmentLayer
    from controller.runtime import runtime_specs
    from controller.servo import ServoLayer
    from controller.trajectory import SEG, TrajectoryLayer

    layers = [UpDownLayer(), MultiSegmentLayer(background_save=False), TrajectoryLayer(), CartesianLayer(),
              JointPlannerLayer(), ServoLayer()]
    for layer in layers:
        state = {s.name for s in layer.state_specs()}
        strays = [s.name for s in layer.specs() if s.name not in state and not isinstance(s.name, Var)]
        assert strays == [], f"{layer.key}: declared as plain strings: {strays}"
    assert all(isinstance(s.name, Var) for s in runtime_specs())
    assert MSP.mode == "msp.mode" and MSP.mode.writer == "user" and MSP.state.writer == "msp"
    assert [str(v) for v in SEG.all()] == ["msp.seg_seq", "msp.seg_pos_m", "msp.seg_quat", "msp.seg_limits",
                                           "msp.seg_last", "msp.seg_stop"]
    assert JMOVE.jmove_speed.spec.initial == 0.25
