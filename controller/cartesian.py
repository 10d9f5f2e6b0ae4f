"""Cartesian Engine (layer 4): the composite commanded Cartesian pose.

IRSS report 2.2.1: "combine all pertinent Cartesian engine inputs to form a composite
Cartesian commanded position. This composite will be made up of hand controller,
force/torque and op-eye offsets as well as Cartesian trajectories coming from the
Trajectory Path Planner Layer. Some components of this layer will operate at 40 Hz
while others operate at 80 Hz. Note that all Cartesian components use quaternions to
represent orientations."

Tasks (scheduling table, :mod:`controller.frames`):

``cartesian_slow`` (40 Hz)
    mode and source selection (the report's Task State Transition Layer: "determination
    of whether the CRL or rate hand controller task is to be run"), the hand-controller
    sample through the synthetic delay's uplink -> a rate twist (rate mode, per-axis
    gains, world or tool frame, deadman required, 8.2 coarse/vernier limits), the
    trajectory pose (``traj.*`` when ``traj.active``), telemetry through the downlink,
    force reflection for the CRL (``teleop.*``);
``cartesian_fast`` (80 Hz)
    integrates the twist into the reference, runs force control
    (:mod:`controller.force`) and posts the command ``cart.pos_cmd_m`` /
    ``cart.quat_cmd`` with ``cart.cmd_valid`` and a new ``cart.cmd_seq`` every run.

Composition (positions add in the world frame, rotations compose on the left, in the
world frame):

    reference  R = blend (+) teleop offset (+) base
    command    C = force offset (+) R

* base: ``cart.mode`` 0 hold - the measured tool pose when the mode was entered (the
  pose at start-up; 8.5 "hold the current pose"); 1 teleop - the held pose, moved by
  the hand controller (the rate integrates straight into it); 2 trajectory - the
  trajectory pose while ``traj.active``, else the pose it left off at; the hand
  controller adds an offset on top (shared control);
* blend: on every change of base (mode change, a trajectory starting) the offset that
  keeps the command continuous, then decayed to zero at the 8.2 coarse limits
  (0.15 m/s, 0.25 rad/s), so nothing jumps;
* force offset: the admittance offset while impedance is on; leaving impedance folds it
  into the held pose (modes 0/1) or the blend (mode 2).

A hand-controller twist that would take the reference more than MAX_LAG_M / MAX_LAG_RAD
away from the measured pose is cut to its component that does not (no wind-up when the
Joint Planner is rate- or joint-limited or the tool is blocked).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from controller.decision import TaskState
from controller.delay import DELAY, SyntheticDelay
from controller.force import (
    FORCE, STATE_NAMES, ForceControl, ImpedanceParams, ToolLoad,
)
from controller.layers import JOINT, Layer
from controller.messages import Level
from controller.quat import q_conj, q_from_rotvec, q_mul, q_normalize, q_to_matrix, q_to_rotvec
from controller.trajectory import TRAJ
from controller.teleop import (
    TELEOP, COARSE_LIN_M_S, COARSE_ROT_RAD_S, FRAME_TOOL, HC_CRL, HC_SOURCES, HcSample, Telemetry, hc_twist, reflect,
)
from controller.worldmodel import VarSpec
from controller.variables import (  # noqa: F401  (the modes re-exported)
    CART, DAQ, MODE_HOLD, MODE_NAMES, MODE_TELEOP, MODE_TRAJECTORY,
)
from pfma.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

#: largest reference-to-measured distance a hand-controller twist may grow (assumed)
MAX_LAG_M = 0.05
MAX_LAG_RAD = 0.20
#: the shoulder-roll index the Joint Planner took at power-up (8.1: world = base rotated by
#: it); without it in the model (no Joint Planner) the index is 0
ROLL_VAR = JOINT.shoulder_roll_rad
#: the trajectory planner's outputs (T's layer); trajectory mode needs them in the model
TRAJ_VARS = (TRAJ.pos_m, TRAJ.quat, TRAJ.active)
#: the Joint Planner's measured tool pose (K's layer); without it fk(daq angles) is used
TOOL_VARS = (JOINT.tool_pos_m, JOINT.tool_quat)
#: the Joint Planner's joint moves: when one ends the held pose becomes fk of the joint command
#: (the pose it reached), so that Cartesian mode resumes there, not at the pose held before it
JMOVE_VARS = (JOINT.jmove_done_seq, JOINT.q_cmd_rad)


def _compose(offset6: np.ndarray, pos_m: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset (dp, rotation vector; world) (+) pose."""
    return pos_m + offset6[:3], q_normalize(q_mul(q_from_rotvec(offset6[3:]), quat))


def _difference(pos_a, quat_a, pos_b, quat_b) -> np.ndarray:
    """The offset (dp, rotvec) with offset (+) b = a."""
    return np.concatenate([np.asarray(pos_a, float) - np.asarray(pos_b, float),
                           q_to_rotvec(q_mul(quat_a, q_conj(quat_b)))])


def _cut_outward(v: np.ndarray, lag: np.ndarray, limit: float) -> np.ndarray:
    """Remove the part of rate ``v`` that increases ``lag`` beyond ``limit``."""
    n = float(np.linalg.norm(lag))
    if n <= limit:
        return v
    u = lag / n
    out = float(v @ u)
    return v - out * u if out > 0.0 else v


class CartesianLayer(Layer):
    """Cartesian Engine: see the module doc.

    :param tool_load: tool behind the F/T sensor (default pfma-model 8.7; a calibration's
        payload with :func:`controller.force.tool_load_from_calibration`)
    """

    key = "cartesian"
    title = "Cartesian Engine"
    short = "CART"
    #: other layers' variables read (controller/neighbours.py; the far ones are listed there)
    reads = (
        "daq.ft_force_n", "daq.ft_torque_nm", "daq.hc_axes", "daq.hc_deadman", "daq.joint_angle_rad",
        "joint.jmove_done_seq", "joint.shoulder_roll_rad", "joint.tool_pos_m", "joint.tool_quat",
        "servo.q_cmd_rad", "traj.active", "traj.pos_m", "traj.quat",
    )

    def __init__(self, tool_load: ToolLoad | None = None) -> None:
        super().__init__()
        self.tool_load = tool_load
        self.periodic["cartesian_slow"] = self.slow_task
        self.periodic["cartesian_fast"] = self.fast_task
        self.delay: SyntheticDelay = SyntheticDelay()
        self.force: ForceControl | None = None
        self._reset_motion()
        self.seq = 0
        self.runs = {"cartesian_slow": 0, "cartesian_fast": 0}
        self._have: dict[str, bool] | None = None
        self.shoulder_roll_rad = 0.0  #: the index of the kinematics (taken at start-up)

    def _reset_motion(self) -> None:
        self.mode = MODE_HOLD
        self.hold_pos = np.zeros(3)
        self.hold_quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.tele = np.zeros(6)  #: hand-controller offset (trajectory mode)
        self.blend = np.zeros(6)
        self.twist = np.zeros(6)  #: world linear m/s, angular rad/s, from the slow task
        self.traj_active = False
        self.traj_pos = np.zeros(3)
        self.traj_quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.meas_pos = np.zeros(3)
        self.meas_quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.offset = np.zeros(6)  #: force offset
        self.hc_active = False
        self._zero_seq = 0
        self._params_key = None
        self._lag_warned = False
        self._jmove_seen = 0
        self.valid = False

    # --- world model ---------------------------------------------------------------------
    def specs(self) -> list[VarSpec]:
        return self.state_specs() + [
            # user controls (command input)
            *(v.spec for v in CART.all() if v.writer == "user"),
            *(v.spec for v in FORCE.all() if v.writer == "user"),
            *DELAY.specs(),
            # outputs to the Joint Planner, internal status
            *(v.spec for v in CART.all() if v.writer != "user"),
            *(v.spec for v in FORCE.all() if v.writer != "user"),
            *TELEOP.specs(),
        ]

    def _check_model(self, rt: "LayerContext") -> dict[str, bool]:
        if self._have is None:
            names = set(rt.wm.names())
            self._have = {"traj": all(n in names for n in TRAJ_VARS), "tool": all(n in names for n in TOOL_VARS),
                          "roll": ROLL_VAR in names, "jmove": all(n in names for n in JMOVE_VARS)}
        return self._have

    # --- sequences -----------------------------------------------------------------------
    def seq_init(self, rt: "LayerContext") -> TaskState:
        self._check_model(rt)
        self.force = ForceControl(rt.task_period_s("cartesian_fast"), self.tool_load)
        return TaskState.DONE

    def seq_startup(self, rt: "LayerContext") -> TaskState:
        """Hold where the arm is: the measured pose becomes the held pose and the command."""
        self._reset_motion()
        if self.force is None:
            self.force = ForceControl(rt.task_period_s("cartesian_fast"), self.tool_load)
        self.force.reset()
        self.delay.reset()
        v = rt.wm.get_task_inputs((DAQ.joint_angle_rad, CART.mode, FORCE.zero_seq))
        # the index the Joint Planner's kinematics took at its initialisation (before this start-up)
        self.shoulder_roll_rad = float(rt.wm.get(ROLL_VAR)) if self._check_model(rt)["roll"] else 0.0
        from controller.kinematics import fk
        p, q = fk(v[DAQ.joint_angle_rad], self.shoulder_roll_rad)
        self.meas_pos, self.meas_quat = np.asarray(p, float), q_normalize(q)
        self.hold_pos, self.hold_quat = self.meas_pos.copy(), self.meas_quat.copy()
        self.mode = int(v[CART.mode]) if int(v[CART.mode]) in MODE_NAMES else MODE_HOLD
        self._zero_seq = int(v[FORCE.zero_seq])
        if self._check_model(rt)["jmove"]:
            self._jmove_seen = int(rt.wm.get_task_inputs((JOINT.jmove_done_seq,))[JOINT.jmove_done_seq])
        self.valid = True
        self._post_command(rt)
        rt.post(self.key, Level.INFO, f"holding the tool at {self._fmt_pose(self.hold_pos, self.hold_quat)}, "
                                      f"mode {MODE_NAMES[self.mode]}")
        return TaskState.DONE

    def seq_shutdown(self, rt: "LayerContext") -> TaskState:
        self.valid = False
        if self.force is not None:
            self.force.reset()
        rt.wm.post_task_outputs(self.key, {CART.cmd_valid: False, FORCE.state: 0, CART.hc_active: False,
                                           TELEOP.reflect_enabled: False,
                                           TELEOP.reflect_force_n: np.zeros(3),
                                           TELEOP.reflect_torque_nm: np.zeros(3)})
        return TaskState.DONE

    @staticmethod
    def _fmt_pose(p, q) -> str:
        return (f"({p[0]:+.4f}, {p[1]:+.4f}, {p[2]:+.4f}) m, q ({q[0]:+.4f}, {q[1]:+.4f}, {q[2]:+.4f}, "
                f"{q[3]:+.4f})")

    # --- helpers -------------------------------------------------------------------------
    def _running(self, rt: "LayerContext") -> bool:
        """The model has what the tasks need (they exist only while START UP COMPLETE:
        controller/tables/cartesian.py)."""
        return self.valid

    def _measured(self, rt: "LayerContext", v: dict) -> None:
        if self._check_model(rt)["tool"]:
            p, q = v[JOINT.tool_pos_m], v[JOINT.tool_quat]
            if float(np.dot(q, q)) > 0.5:  # a real quaternion (written by the Joint Planner)
                self.meas_pos, self.meas_quat = np.asarray(p, float), q_normalize(q)
                return
        from controller.kinematics import fk
        p, q = fk(v[DAQ.joint_angle_rad], self.shoulder_roll_rad)
        self.meas_pos, self.meas_quat = np.asarray(p, float), q_normalize(q)

    def base(self) -> tuple[np.ndarray, np.ndarray]:
        if self.mode == MODE_TRAJECTORY and self.traj_active:
            return self.traj_pos, self.traj_quat
        return self.hold_pos, self.hold_quat

    def reference(self) -> tuple[np.ndarray, np.ndarray]:
        p, q = self.base()
        if self.mode == MODE_TRAJECTORY:
            p, q = _compose(self.tele, p, q)
        return _compose(self.blend, p, q)

    def _rebase(self, new_mode: int, hold_pos=None, hold_quat=None, new_traj_active=None) -> None:
        """Change the base without moving the command: the difference goes to the blend."""
        p0, q0 = self.reference()
        self.mode = new_mode
        if hold_pos is not None:
            self.hold_pos, self.hold_quat = np.asarray(hold_pos, float).copy(), q_normalize(hold_quat)
        if new_traj_active is not None:
            self.traj_active = new_traj_active
        self.tele = np.zeros(6)
        self.blend = np.zeros(6)
        p1, q1 = self.reference()
        self.blend = _difference(p0, q0, p1, q1)

    # --- slow task (40 Hz) ---------------------------------------------------------------
    def slow_task(self, rt: "LayerContext") -> None:
        self.runs["cartesian_slow"] += 1
        if not self._running(rt):
            return
        have = self._check_model(rt)
        names = [CART.mode, CART.hc_source, CART.hc_frame, CART.hc_gain_lin_m_s, CART.hc_gain_rot_rad_s,
                 CART.vernier, DAQ.hc_axes, DAQ.hc_deadman, DAQ.joint_angle_rad,
                 DELAY.round_trip_s, DELAY.jitter]
        names += list(TRAJ_VARS) if have["traj"] else []
        names += list(TOOL_VARS) if have["tool"] else []
        names += list(JMOVE_VARS) if have["jmove"] else []
        v = rt.wm.get_task_inputs(names)
        self._measured(rt, v)
        now = rt.now
        if have["jmove"] and int(v[JOINT.jmove_done_seq]) != self._jmove_seen:
            self._jmove_seen = int(v[JOINT.jmove_done_seq])
            self._hold_joint_command(rt, v[JOINT.q_cmd_rad])
        self._delay_settings(rt, v)
        self._mode_inputs(rt, v, have)
        src, deadman, active = self._hand_controller(rt, v, now)
        self._downlink(rt, now, src, deadman, active)

    def _delay_settings(self, rt: "LayerContext", v: dict) -> None:
        """The synthetic delay's settings (``delay.round_trip_s``, ``delay.jitter``)."""
        try:
            rtt = SyntheticDelay.check_round_trip(float(v[DELAY.round_trip_s]))
        except ConfigError as err:
            rtt = self.delay.round_trip_s
            self._warn_once(rt, "rtt", f"{err}; keeping {rtt:g} s")
        if rtt != self.delay.round_trip_s:
            rt.post(self.key, Level.INFO, f"synthetic delay: round trip {self.delay.round_trip_s:g} s -> {rtt:g} s")
            self.delay.set_round_trip(rtt)
        jit = float(v[DELAY.jitter])
        if 0.0 <= jit <= 0.5:
            self.delay.up.jitter = self.delay.down.jitter = jit

    def _mode_inputs(self, rt: "LayerContext", v: dict, have: dict) -> None:
        """The mode (task state transition) and the trajectory planner's pose."""
        mode = int(v[CART.mode])
        if mode not in MODE_NAMES or (mode == MODE_TRAJECTORY and not have["traj"]):
            self._warn_once(rt, f"mode{mode}", f"cart.mode {mode} is not available "
                                               f"({'no trajectory planner in the world model' if mode == 2 else 'unknown'}); "
                                               f"holding")
            mode = MODE_HOLD
        traj_active = bool(v[TRAJ.active]) if have["traj"] else False
        if have["traj"] and traj_active:
            self.traj_pos = np.asarray(v[TRAJ.pos_m], float)
            tq = np.asarray(v[TRAJ.quat], float)
            if float(tq @ tq) > 0.5:
                self.traj_quat = q_normalize(tq)
        if mode != self.mode:
            old = self.mode
            if mode == MODE_HOLD:  # 8.5 / contract: hold the measured pose at entry
                self._rebase(mode, self.meas_pos, self.meas_quat, traj_active)
            else:  # continue from the current reference
                p, q = self.reference()
                self._rebase(mode, p, q, traj_active)
            rt.post(self.key, Level.INFO, f"mode {MODE_NAMES[old]} -> {MODE_NAMES[mode]}")
        elif self.mode == MODE_TRAJECTORY and traj_active != self.traj_active:
            if traj_active:
                self._rebase(self.mode, new_traj_active=True)
                rt.post(self.key, Level.INFO, "trajectory active: following traj.pos_m/traj.quat")
            else:  # finished: hold where the trajectory left the reference
                p, q = self.reference()
                self.traj_active = False
                self.hold_pos, self.hold_quat = p, q
                self.tele = np.zeros(6)
                self.blend = np.zeros(6)
                rt.post(self.key, Level.INFO, "trajectory inactive: holding its last pose")

    def _hand_controller(self, rt: "LayerContext", v: dict, now: float) -> tuple[int, np.ndarray, bool]:
        """The hand controller through the uplink (operator -> robot): the commanded twist.
        Returns the source, the deadmen and whether the hand controller is active."""
        src = int(v[CART.hc_source])
        if not 0 <= src < len(HC_SOURCES):
            self._warn_once(rt, f"src{src}", f"cart.hc_source {src} unknown; using CAE")
            src = 0
        axes = np.asarray(v[DAQ.hc_axes], float)
        dead = np.asarray(v[DAQ.hc_deadman], bool)
        sample = HcSample(now, src, tuple(float(x) for x in axes[src]), bool(dead[src]))
        seen = self.delay.send_up(now, sample)
        active = (seen is not None and self.mode in (MODE_TELEOP, MODE_TRAJECTORY) and seen.deadman
                  and seen.source == src)
        if active:
            lin, ang = hc_twist(seen.axes, v[CART.hc_gain_lin_m_s], v[CART.hc_gain_rot_rad_s],
                                bool(v[CART.vernier]))
            if int(v[CART.hc_frame]) == FRAME_TOOL:
                _, q_ref = self.reference()
                r = q_to_matrix(q_ref)
                lin, ang = r @ lin, r @ ang
            twist = np.concatenate([lin, ang])
        else:
            twist = np.zeros(6)
        if active != self.hc_active:
            rt.post(self.key, Level.INFO, f"hand controller {HC_SOURCES[src].upper()} "
                                          f"{'active (deadman held)' if active else 'inactive: zero rate, holding'}")
            self.hc_active = active
        self.twist = twist
        return src, dead, active

    def _downlink(self, rt: "LayerContext", now: float, src: int, dead: np.ndarray, active: bool) -> None:
        """Telemetry through the downlink (robot -> operator) and force reflection."""
        wrench = self._last_wrench if hasattr(self, "_last_wrench") else np.zeros(6)
        tel = Telemetry(now, tuple(self.meas_pos), tuple(self.meas_quat), tuple(wrench[:3]), tuple(wrench[3:]))
        seen_t = self.delay.send_down(now, tel)
        out = {CART.hc_active: active}
        if seen_t is not None:
            out.update({TELEOP.seen_pos_m: seen_t.pos_m, TELEOP.seen_quat: seen_t.quat,
                        TELEOP.seen_force_n: seen_t.force_n})
            f, t, on = reflect(seen_t.force_n, seen_t.torque_nm, self.delay.round_trip_s,
                               src == HC_CRL and bool(dead[src]) and self.mode != MODE_HOLD)
        else:
            f, t, on = np.zeros(3), np.zeros(3), False
        out.update({TELEOP.reflect_force_n: f, TELEOP.reflect_torque_nm: t, TELEOP.reflect_enabled: on})
        rt.wm.post_task_outputs(self.key, out)

    def _hold_joint_command(self, rt: "LayerContext", q_cmd) -> None:
        """A joint move ended: hold fk(joint command), the pose it reached, with no blend (the
        Joint Planner ran the joints, not this command: continuity with the command held before
        would pull the arm back)."""
        if self.mode == MODE_TRAJECTORY and self.traj_active:
            return  # a trajectory commands the pose (not while the Path Planner runs a joint move)
        from controller.kinematics import fk
        p, q = fk(q_cmd, self.shoulder_roll_rad)
        self.hold_pos, self.hold_quat = np.asarray(p, float), q_normalize(q)
        self.tele = np.zeros(6)
        self.blend = np.zeros(6)
        rt.post(self.key, Level.INFO, f"joint move {self._jmove_seen} ended: holding the pose it reached, "
                                      f"{self._fmt_pose(self.hold_pos, self.hold_quat)}")

    def _warn_once(self, rt, key: str, text: str) -> None:
        seen = getattr(self, "_warned", set())
        if key not in seen:
            seen.add(key)
            self._warned = seen
            rt.post(self.key, Level.WARNING, text)

    # --- fast task (80 Hz) ---------------------------------------------------------------
    def fast_task(self, rt: "LayerContext") -> None:
        self.runs["cartesian_fast"] += 1
        if not self._running(rt):
            return
        dt = rt.task_period_s("cartesian_fast")
        have = self._check_model(rt)
        names = [DAQ.joint_angle_rad, DAQ.ft_force_n, DAQ.ft_torque_nm, FORCE.enable, FORCE.zero_seq,
                 FORCE.frame, FORCE.mass, FORCE.damping, FORCE.stiffness, FORCE.wrench_des]
        names += list(TOOL_VARS) if have["tool"] else []
        v = rt.wm.get_task_inputs(names)
        self._measured(rt, v)
        # hand-controller rate -> reference (no wind-up beyond MAX_LAG)
        if self.twist.any():
            p_ref, q_ref = self.reference()
            c_pos = p_ref + self.offset[:3]
            lag = _difference(c_pos, q_mul(q_from_rotvec(self.offset[3:]), q_ref), self.meas_pos, self.meas_quat)
            lin = _cut_outward(self.twist[:3], lag[:3], MAX_LAG_M)
            ang = _cut_outward(self.twist[3:], lag[3:], MAX_LAG_RAD)
            if (lin is not self.twist[:3] or ang is not self.twist[3:]) and not self._lag_warned:
                if not (np.allclose(lin, self.twist[:3]) and np.allclose(ang, self.twist[3:])):
                    rt.post(self.key, Level.WARNING, "hand-controller rate cut: the arm lags the reference "
                                                     f"by more than {MAX_LAG_M} m / {MAX_LAG_RAD} rad")
                    self._lag_warned = True
            step = np.concatenate([lin, ang]) * dt
            if self.mode == MODE_TELEOP:
                self.hold_pos, self.hold_quat = _compose(step, self.hold_pos, self.hold_quat)
            else:
                tp, tq = _compose(step, *_compose(self.tele, np.zeros(3), np.array([1.0, 0, 0, 0])))
                self.tele = np.concatenate([tp, q_to_rotvec(tq)])
        elif self._lag_warned:
            self._lag_warned = False
        # blend decays at the coarse limits
        if self.blend.any():
            for sl, lim in ((slice(0, 3), COARSE_LIN_M_S * dt), (slice(3, 6), COARSE_ROT_RAD_S * dt)):
                n = float(np.linalg.norm(self.blend[sl]))
                self.blend[sl] = 0.0 if n <= lim else self.blend[sl] * (1.0 - lim / n)
        # force control (task state transitions inside ForceControl)
        fc = self.force
        out: dict = {}
        key = (tuple(v[FORCE.mass]), tuple(v[FORCE.damping]), tuple(v[FORCE.stiffness]))
        if key != self._params_key:
            try:
                fc.set_params(ImpedanceParams(*key))
                if self._params_key is not None:
                    rt.post(self.key, Level.INFO, "impedance parameters changed")
            except ConfigError as err:
                rt.post(self.key, Level.WARNING, f"impedance parameters refused, keeping the previous ones: {err}")
            self._params_key = key
        fc.frame = int(v[FORCE.frame])
        zs = int(v[FORCE.zero_seq])
        if zs != self._zero_seq:
            self._zero_seq = zs
            if not fc.request_zero(rt.now):
                rt.post(self.key, Level.WARNING, f"F/T zero request {zs} refused: force control is "
                                                 f"{STATE_NAMES[fc.state]} (zero only while impedance is off)")
            else:
                rt.post(self.key, Level.INFO, f"F/T zero request {zs}: OFF -> ZEROING")
        p_ref, q_ref = self.reference()
        res = fc.step(rt.now, bool(v[FORCE.enable]), v[DAQ.ft_force_n], v[DAQ.ft_torque_nm],
                      self.meas_quat, q_ref, v[FORCE.wrench_des])
        for e in res.events:
            rt.post(self.key, Level.INFO, f"force control: {e}")
            out[FORCE.bias] = fc.ft.bias
        if res.fold is not None:  # leaving impedance: keep the pose it reached
            if self.mode == MODE_TRAJECTORY:
                self.blend = self.blend + res.fold
            else:
                self.hold_pos, self.hold_quat = _compose(res.fold, self.hold_pos, self.hold_quat)
            p_ref, q_ref = self.reference()
        self.offset = res.offset_world
        self._last_wrench = res.wrench_world
        out.update({FORCE.state: res.state, FORCE.offset: self.offset, FORCE.wrench_n: res.wrench_world})
        rt.wm.post_task_outputs(self.key, out)
        self._post_command(rt, p_ref, q_ref)

    def _post_command(self, rt: "LayerContext", p_ref=None, q_ref=None) -> None:
        if p_ref is None:
            p_ref, q_ref = self.reference()
        p, q = _compose(self.offset, p_ref, q_ref)
        self.seq = (self.seq + 1) & 0x7FFFFFFF
        rt.wm.post_task_outputs(self.key, {CART.pos_cmd_m: p, CART.quat_cmd: q, CART.cmd_valid: self.valid,
                                           CART.cmd_seq: self.seq, CART.ref_pos_m: p_ref,
                                           CART.ref_quat: q_ref})

