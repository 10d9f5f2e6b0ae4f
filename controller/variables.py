"""The layers' world-model variables, declared once as typed attributes
(:class:`controller.worldmodel.var.VarGroup`): the variable table, ``pfma wm list`` and the
code that reads and writes them are made from these declarations (docs/world-model.md
"Variables a tool can follow").

A group lives here rather than in its layer's module when layers that import each other
read it (``DAQ``: the Servo, Joint Planner, Cartesian, Path Planner and gripper layers;
``CART``: the Cartesian layer's command, read by the Joint Planner, the trajectory planner
and the Path Planner).
"""

from __future__ import annotations

import numpy as np

from bit3.layout import HAND_CONTROLLERS, HC_AXES, ServiceState
from controller.params import JOINTS, N_JOINTS
from controller.teleop import COARSE_LIN_M_S, COARSE_ROT_RAD_S, FRAME_NAMES, HC_SOURCE_NAMES
from controller.worldmodel.var import UNIT_QUATERNION, Var, VarGroup, var

#: the Data Acquisition layer's hardware checks (``daq.fault_bits``, a bit each)
FAULT_RESOLVER, FAULT_TACH, FAULT_FT, FAULT_BOARD, FAULT_SERVICE, FAULT_STALE = 1, 2, 4, 8, 16, 32
FAULT_COMMAND = 64
#: not a hardware reading but Data Acquisition's own output check: the servo's rates were
#: not there for the current servo period, so 0 V went out (an event: latched until ERROR RESET)
FAULT_NO_OUTPUT = 128
FAULT_NAMES = {FAULT_RESOLVER: "resolver", FAULT_TACH: "tach ADC", FAULT_FT: "F/T link",
               FAULT_BOARD: "board fault", FAULT_SERVICE: "service state", FAULT_STALE: "service not publishing",
               FAULT_COMMAND: "command refused/stale at the service", FAULT_NO_OUTPUT: "no servo output"}

_NH, _NA = len(HAND_CONTROLLERS), len(HC_AXES)
_Z6 = [0.0] * N_JOINTS


class DaqVars(VarGroup, prefix="daq", writer="daq"):
    """The Data Acquisition layer's inputs and statuses (its commands and decision-table
    state are every layer's: ``Layer.state_specs``)."""

    joint_angle_rad: Var[np.ndarray] = var(
        "task_io", "f8", (N_JOINTS,), [j.centre_rad * 0 for j in JOINTS], "rad",  # -0.0 kept: the table's hash
        doc="resolver joint angles unwrapped to each joint's range (command-area order)")
    joint_rate_rad_s: Var[np.ndarray] = var("task_io", "f8", (N_JOINTS,), _Z6, "rad/s",
                                            doc="tachometer joint rates (filtered tach, ADC)")
    motor_current_a: Var[np.ndarray] = var(
        "task_io", "f8", (N_JOINTS,), _Z6, "A",
        doc="motor currents (amplifier current monitors, ADC; command-area order)")
    ft_force_n: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "N", doc="wrist F/T force")
    ft_torque_nm: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "N*m", doc="wrist F/T torque")
    hc_axes: Var[np.ndarray] = var(  # deflections about -1..1; a wider bound leaves room for calibration
        "task_io", "f8", (_NH, _NA), [[0.0] * _NA] * _NH, "1", valid=(-10.0, 10.0),
        doc=f"hand-controller axes ({', '.join(HAND_CONTROLLERS)} x {', '.join(HC_AXES)})")
    hc_deadman: Var[np.ndarray] = var("task_io", "b1", (_NH,), [False] * _NH, doc="hand-controller deadman")
    service_frame: Var[int] = var("task_io", "i8", (), 0, doc="service frame of the inputs")
    gripper_rate_m_s: Var[float] = var("task_io", "f8", (), 0.0, "m/s",
                                       doc="gripper jaw rate (end-effector tach, ADC; opening positive)")
    gripper_current_a: Var[float] = var("task_io", "f8", (), 0.0, "A",
                                        doc="gripper motor current (end-effector current monitor, ADC)")
    service_state: Var[int] = var("status_output", "i2", (), 0,
                                  doc="I/O service state (bit3.layout.ServiceState)", enum=ServiceState)
    brakes_released: Var[bool] = var("task_io", "b1", (), False,
                                     doc="the service sees a current limit above the brake release level "
                                         "with outputs live")
    outputs_enabled: Var[bool] = var("task_io", "b1", (), False, doc="the DAC drives the arm")
    user_inputs: Var[int] = var("task_io", "i4", (), 0, "bits",
                                doc="the user I/F box's 16 input bits (docs/cameras.md: closed switch = 0)")
    camera_route: Var[int] = var("task_io", "i4", (), 0, "bits",
                                 doc="matrix switcher route this layer commands (commands.matrix_route; "
                                     "controller/routes.py)")
    camera_route_applied: Var[int] = var("task_io", "i4", (), -1, "bits",
                                         doc="route the service has applied to the switcher (inputs.matrix_route)")
    fault_bits: Var[int] = var("error_reports", "i4", (), 0, doc="hardware checks that tripped (a bit each)",
                               flags=FAULT_NAMES)


DAQ = DaqVars

#: ``cart.mode``: the Cartesian layer's modes (controller/cartesian.py)
MODE_HOLD, MODE_TELEOP, MODE_TRAJECTORY = 0, 1, 2
MODE_NAMES = {MODE_HOLD: "HOLD", MODE_TELEOP: "TELEOP", MODE_TRAJECTORY: "TRAJECTORY"}


class CartVars(VarGroup, prefix="cart", writer="cartesian"):
    """The Cartesian layer's user controls (writer ``user``), its command to the Joint
    Planner and its status (controller/cartesian.py)."""

    mode: Var[int] = var("command_input", "i2", (), 0, writer="user", doc="Cartesian mode", enum=MODE_NAMES)
    hc_source: Var[int] = var("command_input", "i2", (), 0, writer="user",
                              doc="the hand controller teleoperation follows", enum=HC_SOURCE_NAMES)
    hc_frame: Var[int] = var("command_input", "i2", (), 0, writer="user",
                             doc="hand-controller rates in the world frame or the tool frame", enum=FRAME_NAMES)
    hc_gain_lin_m_s: Var[np.ndarray] = var(
        "command_input", "f8", (3,), [COARSE_LIN_M_S] * 3, "m/s", writer="user",
        doc="rate at full deflection, x y z (then limited to 0.15 m/s coarse, 0.03 vernier)")
    hc_gain_rot_rad_s: Var[np.ndarray] = var(
        "command_input", "f8", (3,), [COARSE_ROT_RAD_S] * 3, "rad/s", writer="user",
        doc="rate at full deflection, roll pitch yaw (then limited to 0.25 rad/s coarse, 0.05 vernier)")
    vernier: Var[bool] = var("command_input", "b1", (), False, writer="user",
                             doc="vernier rates (x0.2, limits 0.03 m/s 0.05 rad/s; pfma-model 8.2)")
    pos_cmd_m: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "m", doc="commanded tool point, world")
    quat_cmd: Var[np.ndarray] = var("task_io", "f8", (4,), [1.0, 0.0, 0.0, 0.0], "1", valid=UNIT_QUATERNION,
                                    doc="commanded tool orientation (w x y z), world")
    cmd_valid: Var[bool] = var("task_io", "b1", (), False, doc="the Cartesian command is valid")
    cmd_seq: Var[int] = var("task_io", "i4", (), 0, doc="new with every Cartesian command (80 Hz)")
    ref_pos_m: Var[np.ndarray] = var("task_status", "f8", (3,), [0.0] * 3, "m",
                                     doc="reference before the force offset")
    ref_quat: Var[np.ndarray] = var("task_status", "f8", (4,), [1.0, 0.0, 0.0, 0.0], "1", valid=UNIT_QUATERNION,
                                    doc="reference orientation before the force offset")
    hc_active: Var[bool] = var("task_status", "b1", (), False,
                               doc="the (delayed) hand controller moves the reference (deadman held)")


CART = CartVars
