"""Servo Control: independent first-order joint compensators, limits, brake sequencing.

IRSS report 2.2.1: the servo layer "combines the current commanded joint positions
with the current joint angles (and tachometer data) to produce motor control
voltages. During Phase II of IRSS first order compensators are being used to perform
independent joint control." pfma-model.md 8.4 and 5 (copied in controller.params):

* joint loop ``qdot_cmd = C_j(z) (q_cmd - q)`` with C_j(s) = K (tau_z s + 1) /
  (tau_p s + 1), discretised by Tustin at the servo period T::

      u_k = a u_{k-1} + b0 e_k + b1 e_{k-1}
      a = (2 tau_p - T) / (2 tau_p + T),  b0 = K (2 tau_z + T) / (2 tau_p + T),
      b1 = K (T - 2 tau_z) / (2 tau_p + T)

  (tau_z = tau_p = 0: the pure gain K, the default K = 8 1/s);
* rate command saturated at omega_lim = 0.6 omega_fs, commanded positions clipped to
  the soft limits, no rate further out beyond a soft limit, a fault 1 degree beyond;
* power-up: rate command 0 V, then raise the current limit (the brake releases);
  safe stop: rate 0 V, wait for |qdot| < 0.01 rad/s or 0.5 s, then current limit 0 V.

The control-law parameters are protected world-model variables (``servo.kp_per_s``
...): ``pfma wm set`` refuses them while powered up; the layer latches them in its
initialisation task.

:func:`predict_step` is the compensator design's prediction of a position step: the
same discrete compensator, the controller's I/O delay, and the amplifier's rate loop of
pfma-model 8.4 (tach filter, lambda, viscous friction, current saturation), linear
otherwise. Tests compare the simulated arm's response with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from controller.decision import Status, TaskState
from controller.gripper import GRIPPER_LIMIT_INDEX, GripperDrive, gripper_specs
from controller.layers import ERROR_NAMES, JOINT, Layer
from controller.messages import Level
from controller.params import (
    DEFAULT_KP_PER_S, GAIN_SWITCH_POSITIONS, GRIPPER_I_MAX_A, JOINTS, N_CURRENT_LIMITS, N_JOINTS, SAFE_STOP_RATE_RAD_S,
    SAFE_STOP_TIMEOUT_S, TACH_TAU_S, JointFacts, run_current_limits_a,
)
from controller.supervision import (
    BRAKE_PROVEN, BRAKE_STATE_NAMES, BRAKE_UNPROVEN, CAUSES, CHECKS, FERROR_MAX_RAD, FERROR_MIN_RAD, FERROR_TIME_S,
    STALL_MOTION_FRACTION, JointSupervisor, Trip, diagnose,
)
from controller.worldmodel import VarSpec
from controller.worldmodel.var import Var, VarGroup, var
from controller.variables import DAQ

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

#: a joint this far beyond its soft limit is a servo fault (assumed: 1 degree)
LIMIT_FAULT_MARGIN_RAD = math.radians(1.0)
#: brakes must report released within this time of raising the current limits (assumed)
BRAKE_RELEASE_TIMEOUT_S = 0.5
#: the power-up brake test (issue 30 item 3; ``servo.brake_test``): each joint is driven,
#: away from its nearer soft limit, by the rate command whose nominal steady rate is this
#: fraction of its full-scale rate, until the sensors prove its brake released and its drive
#: answering (``servo.brake_state`` PROVEN RELEASED: it moved the commanded way at more than
#: supervision.STALL_MOTION_FRACTION of full scale), then back for as long; a joint that has
#: not proved it within BRAKE_TEST_MAX_S fails the power-up, named with its likely cause.
#: The loop then closes on the pose the power-up started from. While the joints move, the
#: supervision's resolver, overspeed and tach-against-resolver checks run, so a reversed tach
#: or a DAC driving the wrong way trips here, before any commanded motion (assumed figures:
#: a quarter of full scale proves a joint in 40-80 ms, about 0.2-1 degree out and back)
BRAKE_TEST_RATE_FRACTION = 0.25
BRAKE_TEST_MAX_S = 0.4
#: a joint proves itself only when its tach also shows the commanded direction (a reversed
#: tach, or a DAC driving the wrong way, never passes), and fails at once when it goes further
#: than this from where the test started (assumed: 2 degrees bounds a runaway to a small one)
BRAKE_TEST_MAX_EXCURSION_RAD = math.radians(2.0)

#: Data Acquisition's "tach ADC failed" hardware-check bit (controller.daq_layer.FAULT_TACH)
TACH_FAULT_BIT = 2
#: error report codes of the servo layer: 10 soft limit, 11 bad parameters, 12 the controller
#: missed more frames in a row than FrameConfig.max_missed_run (the servo slot did not run in
#: its period). (13, no servo output at Data Acquisition's output, is now Data Acquisition's
#: own fault, ``daq.fault_bits`` 128, reported through its status: the neighbours rule)
ERR_LIMIT, ERR_PARAMS, ERR_MISSED = 10, 11, 12
#: error report codes of the joint supervision (controller.supervision), one per check:
#: 14 resolver jump, 15 overspeed, 16 tach against resolver, 17 stall, 18 following error;
#: 19 the power-up brake test: a joint did not prove its brake released and its drive answering
SUPERVISION_CODES = {check: 14 + n for n, check in enumerate(CHECKS)}
ERR_BRAKE_TEST = 19
#: ``servo.error`` by name: the codes above and every layer's (controller.layers.ERROR_NAMES)
SERVO_ERROR_NAMES = {**ERROR_NAMES, ERR_LIMIT: "soft limit", ERR_PARAMS: "bad parameters",
                     ERR_MISSED: "controller missed frames",
                     **{code: check for check, code in SUPERVISION_CODES.items()}, ERR_BRAKE_TEST: "brake test"}
#: ``servo.brake_phase`` by name (the brake release and stop sequence)
BRAKE_PHASE_NAMES = {0: "BRAKES SET", 1: "RATE ZEROED", 2: "LIMITS RAISED", 3: "RELEASED",
                     4: "STOPPING", 5: "LIMITS ZERO", 6: "BRAKE TEST"}
PHASE_BRAKE_TEST = 6
#: brake phases in which the current limits may be raised: the joints are supervised
_LIVE_PHASES = (2, 3, 4, PHASE_BRAKE_TEST)


class LeadLag:
    """Independent first-order compensators, one per joint, Tustin-discretised.

    :param k: DC gain K per joint (1/s: rad/s of rate per rad of error)
    :param tau_z: zero time constants (s)
    :param tau_p: pole time constants (s); > 0 whenever tau_z > 0
    :param period_s: sample period T
    """

    def __init__(self, k, tau_z, tau_p, period_s: float) -> None:
        k, tz, tp = (np.asarray(x, dtype=float).copy() for x in (k, tau_z, tau_p))
        if np.any(k <= 0) or np.any(tz < 0) or np.any(tp < 0):
            raise ValueError("compensator: K must be > 0 and time constants >= 0")
        if np.any((tp == 0) & (tz > 0)):
            raise ValueError("compensator: a zero (tau_z > 0) needs a pole (tau_p > 0) to be proper")
        if period_s <= 0:
            raise ValueError("compensator: period must be positive")
        T = float(period_s)
        pure = (tz == 0) & (tp == 0)
        d = 2 * tp + T
        self.k, self.tau_z, self.tau_p, self.period_s = k, tz, tp, T
        self.a = np.where(pure, 0.0, (2 * tp - T) / d)
        self.b0 = np.where(pure, k, k * (2 * tz + T) / d)
        self.b1 = np.where(pure, 0.0, k * (T - 2 * tz) / d)
        self.u = np.zeros_like(k)
        self.e = np.zeros_like(k)

    def reset(self, e0=0.0) -> None:
        """Start in steady state for a constant error ``e0`` (u = K e0)."""
        self.e = np.broadcast_to(np.asarray(e0, dtype=float), self.k.shape).copy()
        self.u = self.k * self.e

    def step(self, e: np.ndarray, limit=None) -> np.ndarray:
        """One sample: the new outputs (rad/s), saturated at +-``limit`` when given.

        Anti-windup: the state ``u_{k-1}`` the next sample builds on is the *saturated*
        output (the rate actually commanded), not the unsaturated one. With a lag design
        (tau_p > tau_z, a close to 1) the unsaturated state would keep integrating the
        error during a long saturation and overshoot on the way back; this way it never
        leaves the limits (back-calculation with the tracking time constant equal to the
        sample period: the state is re-set to the applied output every sample). A caller
        that limits the output further (a soft limit) reports it with :meth:`track`.
        """
        u = self.a * self.u + self.b0 * e + self.b1 * self.e
        if limit is not None:
            u = np.clip(u, -np.asarray(limit, dtype=float), np.asarray(limit, dtype=float))
        self.u = u
        self.e = np.array(e, dtype=float)
        return u

    def track(self, applied: np.ndarray) -> None:
        """The output that was actually applied (after every limit): the state follows it."""
        self.u = np.array(applied, dtype=float)


@dataclass
class StepPrediction:
    t_s: np.ndarray
    q_rad: np.ndarray
    step_rad: float
    overshoot_rad: float  #: max excursion beyond the target, in the step's direction (>= 0)
    settle_s: float  #: last time outside 2 % of the step


def predict_step(jf: JointFacts, step_rad: float, *, kp: float = DEFAULT_KP_PER_S, tau_z: float = 0.0,
                 tau_p: float = 0.0, servo_period_s: float = 1 / 160, delay_s: float = 2 / 320,
                 rate_limit: float | None = None, current_limit_a: float | None = None,
                 duration_s: float = 3.0, substeps: int = 16) -> StepPrediction:
    """Predicted response of one joint to a position step of the servo's command.

    The compensator runs every ``servo_period_s`` on the angle sampled then; its output
    reaches the amplifier ``delay_s`` later and is held (ZOH). The amplifier is the
    rate loop of pfma-model 8.4: ``w' = lambda (u - y) - (b/J) w`` with the tach filter
    ``y' = (w - y) / tau_f``, torque saturated at the current limit. Coulomb friction,
    gravity and resolver quantisation are left out (they only take energy out or add
    a dead band; the tests allow for the quantisation).
    """
    comp = LeadLag([kp], [tau_z], [tau_p], servo_period_s)
    comp.reset(0.0)
    lim = jf.omega_lim_rad_s if rate_limit is None else rate_limit
    i_lim = (0.5 * jf.i_max_a) if current_limit_a is None else current_limit_a
    acc_max = jf.torque_per_amp * i_lim / jf.inertia_kg_m2
    lam, tf, damp = jf.rate_loop_lambda, TACH_TAU_S, jf.viscous_nm_s / jf.inertia_kg_m2
    dt = servo_period_s / substeps
    n = int(round(duration_s / dt))
    q = w = y = 0.0
    pending: list[tuple[float, float]] = []  # (time it reaches the amplifier, value)
    u_amp = 0.0
    ts = np.empty(n)
    qs = np.empty(n)
    next_sample = 0.0
    for i in range(n):
        t = i * dt
        if t >= next_sample - 1e-12:
            u = float(comp.step(np.array([step_rad - q]), lim)[0])
            pending.append((t + delay_s, u))
            next_sample += servo_period_s
        while pending and pending[0][0] <= t + 1e-12:
            u_amp = pending.pop(0)[1]
        acc = lam * (u_amp - y)
        acc = max(-acc_max, min(acc_max, acc)) - damp * w
        w += acc * dt
        y += (w - y) / tf * dt
        q += w * dt
        ts[i], qs[i] = t, q
    sgn = 1.0 if step_rad >= 0 else -1.0
    over = max(0.0, float(np.max(sgn * (qs - step_rad))))
    outside = np.nonzero(np.abs(qs - step_rad) > 0.02 * abs(step_rad))[0]
    settle = float(ts[outside[-1]]) if outside.size else 0.0
    return StepPrediction(ts, qs, step_rad, over, settle)


class BrakeTest:
    """The power-up brake test's motion (:data:`BRAKE_TEST_RATE_FRACTION`): one instance per
    test, stepped once per servo period with the supervision's brake states; plain floats
    (it runs in the controller's frame, at power-up only).

    Each joint: out at its test rate, away from its nearer soft limit, until its brake
    state is PROVEN RELEASED and its tach shows the same way, or :data:`BRAKE_TEST_MAX_S` has
    passed (then it failed: 0 at once, a stuck joint is not driven back); back at the
    opposite rate until the tach shows that way too and for at least as long as it went out
    (a command that reaches the joint one way only fails here); then 0. Beyond
    :data:`BRAKE_TEST_MAX_EXCURSION_RAD` from the start it fails at once. The first failure
    ends the test for every joint (all 0, then the layer sets every current limit to 0): a
    joint that does not follow is not left powered while the others finish."""

    def __init__(self, sup: JointSupervisor, q0: list[float], q_min: list[float], q_max: list[float],
                 rate_limit: list[float]) -> None:
        self.sup = sup
        self.q0 = list(q0)
        n = len(q0)
        self.u: list[float] = []
        #: whether the way back must be shown by the tach too: only with room for it before
        #: the soft limit (a joint powered up at its limit comes back to the limit, where the
        #: service's envelope holds the command at 0 V)
        self.check_back: list[bool] = []
        for k in range(n):
            away = 1.0 if q0[k] <= 0.5 * (q_min[k] + q_max[k]) else -1.0
            mag = min(sup.command_for_rate(k, BRAKE_TEST_RATE_FRACTION * sup.fs[k]), rate_limit[k])
            self.u.append(away * mag)
            room = q0[k] - q_min[k] if away > 0 else q_max[k] - q0[k]
            self.check_back.append(room >= BRAKE_TEST_MAX_EXCURSION_RAD)
        self.stage = [0] * n  # 0 out, 1 back, 2 done
        #: the tach rate that shows a joint moving (the brake state's own motion threshold)
        self.moving = [STALL_MOTION_FRACTION * fs for fs in sup.fs]
        self.t = 0.0
        self.t_out = [0.0] * n
        self.t_back = [0.0] * n
        self.back = [False] * n  # the tach has shown the way back
        self.excursion = [0.0] * n  #: furthest each joint went from q0 (rad)
        self.failed: dict[int, str] = {}  #: joint -> what it did, its likely cause and the evidence
        self.causes: dict[int, int] = {}  #: joint -> its likely cause (supervision.CAUSES index)

    @property
    def done(self) -> bool:
        return all(st == 2 for st in self.stage)

    def step(self, dt: float, q: list[float], w_tach: list[float]) -> list[float]:
        """The rates for the next servo period (the supervision has taken this period's
        sample, so its brake states are this period's)."""
        self.t += dt
        out = [0.0] * len(self.u)
        brake = self.sup.brake_state
        for k, u in enumerate(self.u):
            if self.stage[k] == 2:
                continue
            d = abs((q[k] - self.q0[k] + math.pi) % (2 * math.pi) - math.pi)
            if d > self.excursion[k]:
                self.excursion[k] = d
            if d > BRAKE_TEST_MAX_EXCURSION_RAD:
                self._fail(k, u if self.stage[k] == 0 else -u, f"went {math.degrees(d):.1f} deg, beyond the test's "
                                 f"{math.degrees(BRAKE_TEST_MAX_EXCURSION_RAD):g} deg")
                continue
            if self.stage[k] == 0:
                shown = w_tach[k] * u > 0 and abs(w_tach[k]) >= self.moving[k]
                if brake[k] == BRAKE_PROVEN and shown:
                    self.stage[k], self.t_out[k] = 1, self.t
                elif self.t >= BRAKE_TEST_MAX_S:
                    self._fail(k, u, f"not within {BRAKE_TEST_MAX_S * 1e3:.0f} ms")
                    continue
                else:
                    out[k] = u
                    continue
            self.t_back[k] += dt
            if w_tach[k] * u < 0 and abs(w_tach[k]) >= self.moving[k]:
                self.back[k] = True  # it answers the other direction too (the direction check)
            if (self.back[k] or not self.check_back[k]) and self.t_back[k] >= self.t_out[k]:
                self.stage[k] = 2
            elif self.t_back[k] >= BRAKE_TEST_MAX_S:
                self._fail(k, -u, f"not back within {BRAKE_TEST_MAX_S * 1e3:.0f} ms")
            else:
                out[k] = -u
        if self.failed:  # the test ends here for every joint
            self.stage = [2] * len(self.u)
            return [0.0] * len(self.u)
        return out

    def _fail(self, k: int, u: float, how: str) -> None:
        """Joint ``k`` failed: 0 at once (a stuck or runaway joint is not driven back), its
        likely cause from its newest samples."""
        jf = self.sup.joints[k]
        cause, evidence = diagnose(jf, "stall", self.sup.recent(k))
        self.failed[k] = (f"{jf.name} did not move as told at {u:+.3f} rad/s ({how}): likely "
                          f"{CAUSES[cause]}: {evidence}")
        self.causes[k] = cause
        self.stage[k] = 2


_Z6 = [0.0] * N_JOINTS


def _par(value, units: str, doc: str):
    """A control-law parameter: one per joint, set by the user only while powered down."""
    return var("control_flags", "f8", (len(value),), list(value), units, writer="user", protected=True,
               doc=doc + " (protected: not while powered up)")


class ServoVars(VarGroup, prefix="servo", writer="servo"):
    """Servo Control's parameters (user, protected), statuses and outputs (the Joint
    Planner's ``servo.q_cmd_rad`` command is the Joint Planner's)."""

    kp_per_s: Var[np.ndarray] = _par([DEFAULT_KP_PER_S] * N_JOINTS, "1/s", "compensator DC gain K (pfma-model 8.4: 8)")
    tau_z_s: Var[np.ndarray] = _par(_Z6, "s", "compensator zero time constant (0 = none)")
    tau_p_s: Var[np.ndarray] = _par(_Z6, "s", "compensator pole time constant (0 = none; > 0 if tau_z > 0)")
    rate_limit_rad_s: Var[np.ndarray] = _par([j.omega_lim_rad_s for j in JOINTS], "rad/s",
                                             "joint rate limit (pfma-model 8.2: 0.6 omega_fs)")
    current_limit_a: Var[np.ndarray] = _par(
        run_current_limits_a(), "A",
        "current limits while powered up (6 joints), and the most the gripper may use (its grip "
        "force sets its limit, up to this x 40 N/A)")
    q_min_rad: Var[np.ndarray] = _par([j.soft_lo_rad for j in JOINTS], "rad", "soft lower joint limits (8.2)")
    q_max_rad: Var[np.ndarray] = _par([j.soft_hi_rad for j in JOINTS], "rad", "soft upper joint limits (8.2)")
    ferror_min_rad: Var[np.ndarray] = _par([FERROR_MIN_RAD] * N_JOINTS, "rad",
                                           "following-error limit at standstill (LinuxCNC MIN_FERROR; docs/safety.md)")
    ferror_max_rad: Var[np.ndarray] = _par([FERROR_MAX_RAD] * N_JOINTS, "rad",
                                           "following-error limit at full-scale rate (LinuxCNC FERROR; docs/safety.md)")
    ferror_time_s: Var[np.ndarray] = _par(
        [FERROR_TIME_S] * N_JOINTS, "s",
        "time the following error must stay beyond its limit (CiA 402 following-error time-out)")
    ferror_rad: Var[np.ndarray] = var(
        "task_status", "f8", (N_JOINTS,), _Z6, "rad",
        doc="following error of the last servo run: where the commanded rates should have "
            "taken each joint minus where it is (controller/supervision.py)")
    trip_joint: Var[int] = var("task_status", "i2", (), -1,
                               doc="joint (command-area order) of the last supervision trip, -1 none",
                               enum={-1: "none", **{n: j.name for n, j in enumerate(JOINTS)}})
    trip_cause: Var[int] = var("task_status", "i2", (), -1,
                               doc="likely cause of the last supervision trip (controller.supervision.CAUSES), -1 none",
                               enum={-1: "none", **dict(enumerate(CAUSES))})
    rate_cmd_rad_s: Var[np.ndarray] = var("task_io", "f8", (N_JOINTS,), _Z6, "rad/s",
                                          doc="joint rate commands to Data Acquisition (command-area joint order)")
    rate_cmd_frame: Var[int] = var(
        "task_io", "i8", (), -1,
        doc="service frame of the inputs servo.rate_cmd_rad_s was computed from (-1: a "
            "constant 0 posted by a sequence task, not computed from inputs)")
    current_limit_cmd_a: Var[np.ndarray] = var("task_io", "f8", (N_CURRENT_LIMITS,), [0.0] * N_CURRENT_LIMITS, "A",
                                               doc="current-limit commands (0 = brakes set)")
    error_rad: Var[np.ndarray] = var("task_status", "f8", (N_JOINTS,), _Z6, "rad",
                                     doc="position error q_cmd - q of the last servo run")
    brake_state: Var[np.ndarray] = var(
        "task_status", "u1", (N_JOINTS,), [BRAKE_UNPROVEN] * N_JOINTS,
        doc="each joint's brake as the sensors show it, never from the command alone: "
            + ", ".join(f"{k} {v}" for k, v in BRAKE_STATE_NAMES.items())
            + " (SET: limit 0, joint still; PROVEN RELEASED: moved as told since its limit was "
              "raised; controller/supervision.py)")
    brake_phase: Var[int] = var(
        "task_status", "i2", (), 0,
        doc="the brake sequence: set, rate zeroed, limits raised, brake test, released (loop "
            "closed), stopping, limits zero", enum=BRAKE_PHASE_NAMES)
    brake_test: Var[int] = var(
        "control_flags", "i2", (), 1, writer="user", protected=True, enum={0: "off", 1: "on"},
        doc="the power-up brake test: each joint moves a little out and back (at a quarter of "
            "its full-scale rate, about 0.2-1 deg) to prove its brake released and its drive "
            "answering before START UP COMPLETE; a joint that does not fails the power-up, "
            "named (off: the brakes are taken as released when the limits are raised; "
            "protected: not while powered up)")
    gain_switch: Var[np.ndarray] = var(
        "control_flags", "f8", (N_JOINTS,), [1.0] * N_JOINTS, "1", writer="user", protected=True,
        valid=(min(GAIN_SWITCH_POSITIONS.values()), max(GAIN_SWITCH_POSITIONS.values())),
        doc="each rate servo card's gain adjustment switch as set on the chassis (IRSS 3.6.1), a factor on "
            "the rate loop's lambda: 0.5 low, 1 nominal, 2 high (assumed positions, pfma.arm); the joint "
            "supervision's model uses it (protected: not while powered up)")


SERVO = ServoVars


class ServoLayer(Layer):
    """Servo Control (layer 6)."""

    key = "servo"
    title = "Servo Control"
    short = "SERV"
    #: other layers' variables read (controller/neighbours.py; the far ones are listed there)
    reads = (
        "daq.brakes_released", "daq.fault_bits", "daq.gripper_current_a", "daq.gripper_rate_m_s", "daq.joint_angle_rad",
        "daq.joint_rate_rad_s", "daq.motor_current_a", "daq.service_frame", "joint.msp_gripper_force_n",
        "joint.msp_gripper_request", "joint.msp_gripper_seq", "servo.q_cmd_rad", "servo.q_cmd_valid",
    )
    error_names = SERVO_ERROR_NAMES

    def __init__(self) -> None:
        super().__init__()
        self.periodic["servo_control"] = self.control_task
        self.comp: LeadLag | None = None
        self.period_s = 1 / 160
        self.params: dict[str, np.ndarray] = {}
        self.hold = np.zeros(N_JOINTS)
        self._phase = 0
        self._t_phase = 0.0
        self.sup: JointSupervisor | None = None  #: the joint supervision, latched at init
        self.trip: Trip | None = None  #: the last supervision trip
        #: the brake states last posted (servo.brake_state; posted only when they change)
        self._brake_posted: list[int] = [BRAKE_UNPROVEN] * N_JOINTS
        self.frame_period_s = 1 / 320
        self._sup_frame = -1  # service frame of the last supervised sample
        self._u_sent = [0.0] * N_JOINTS  # the rates posted last servo period (what the amplifiers act on)
        self._zero_limits = np.zeros(N_CURRENT_LIMITS)
        #: the seventh amplifier (controller/gripper.py): its own task, 40 Hz
        self.gripper = GripperDrive(self)
        self.periodic["gripper_control"] = self.gripper.task
        #: the power-up brake test (servo.brake_test, latched at init) and the running one
        self.brake_test_on = True
        self.brake_test: BrakeTest | None = None
        self._q_powerup: list[float] = []  # the pose the power-up started from (the test returns there)
        self._testing = False  # the start-up sequence is in its brake test
        self._tach: list[float] = [0.0] * N_JOINTS  # the tach rates of the last supervised sample

    @property
    def brake_phase(self) -> int:
        """``servo.brake_phase`` as this layer last set it (3: loop closed)."""
        return self._phase

    def limits_cmd(self, gripper_a: float) -> np.ndarray:
        """The current-limit command: the six joints' latched limits, then ``gripper_a`` (the
        gripper's current limit, which its grip force sets: controller/gripper.py)."""
        out = np.array(self.params["current_limit_a"], dtype=float)
        out[GRIPPER_LIMIT_INDEX] = gripper_a
        return out

    def specs(self) -> list[VarSpec]:
        return self.state_specs() + SERVO.specs() + gripper_specs()

    # --- sequence tasks ------------------------------------------------------------------
    def seq_init(self, rt: "LayerContext") -> TaskState:
        names = ("kp_per_s", "tau_z_s", "tau_p_s", "rate_limit_rad_s", "current_limit_a", "q_min_rad", "q_max_rad",
                 "ferror_min_rad", "ferror_max_rad", "ferror_time_s", "gain_switch")
        v = rt.wm.get_task_inputs([getattr(SERVO, n) for n in names] + [SERVO.brake_test])
        self.brake_test_on = bool(int(v[SERVO.brake_test]))
        p = {n: np.array(v[getattr(SERVO, n)], dtype=float) for n in names}
        self.period_s = rt.task_period_s("servo_control")
        try:
            self.comp = LeadLag(p["kp_per_s"], p["tau_z_s"], p["tau_p_s"], self.period_s)
            problems = []
            for i, j in enumerate(JOINTS):
                if not 0 < p["rate_limit_rad_s"][i] <= j.omega_fs_rad_s:
                    problems.append(f"{j.name} rate limit {p['rate_limit_rad_s'][i]} outside (0, {j.omega_fs_rad_s}]")
                if not j.hard_lo_rad <= p["q_min_rad"][i] < p["q_max_rad"][i] <= j.hard_hi_rad:
                    problems.append(f"{j.name} soft limits {p['q_min_rad'][i]:.3f}..{p['q_max_rad'][i]:.3f} "
                                    f"not inside the hard limits")
                if not 0 <= p["current_limit_a"][i] <= j.i_max_a:
                    problems.append(f"{j.name} current limit {p['current_limit_a'][i]} A outside 0..{j.i_max_a}")
                if float(p["gain_switch"][i]) not in GAIN_SWITCH_POSITIONS.values():
                    problems.append(f"{j.name} gain switch {p['gain_switch'][i]:g} is no position of the card's "
                                    f"switch ({', '.join(f'{k} {v:g}' for k, v in GAIN_SWITCH_POSITIONS.items())})")
            g = p["current_limit_a"][GRIPPER_LIMIT_INDEX]
            if not 0 <= g <= GRIPPER_I_MAX_A:
                problems.append(f"gripper current limit {g} A outside 0..{GRIPPER_I_MAX_A}")
            if problems:
                raise ValueError("; ".join(problems))
            pure = not (np.any(p["tau_z_s"]) or np.any(p["tau_p_s"]))  # the reference: the same compensator
            joints = tuple(replace(j, gain_switch=float(g)) for j, g in zip(JOINTS, p["gain_switch"]))
            self.sup = JointSupervisor(p["ferror_min_rad"], p["ferror_max_rad"], p["ferror_time_s"], joints=joints,
                                       reference=None if pure else LeadLag(p["kp_per_s"], p["tau_z_s"],
                                                                           p["tau_p_s"], self.period_s),
                                       kp_per_s=p["kp_per_s"].tolist(), rate_limit_rad_s=p["rate_limit_rad_s"])
        except ValueError as err:
            self.set_fault(rt, ERR_PARAMS, f"control-law parameters: {err}")
            return TaskState.FAILED
        self.params = p
        frames = getattr(rt, "frames", None)  # the minor frame = the service frame (the resolver samples)
        self.frame_period_s = float(frames.period_s) if frames is not None else self.period_s / 2
        self._sup_frame = -1
        rt.post(self.key, Level.INFO, f"compensators latched: T={self.period_s * 1e3:.3f} ms, "
                                      f"K={' '.join(f'{x:g}' for x in p['kp_per_s'])}")
        return TaskState.DONE

    def _brake_phase(self, rt, phase: int) -> None:
        self._phase = phase
        self._t_phase = rt.now
        rt.wm.post_task_outputs("servo", {SERVO.brake_phase: phase})

    def seq_startup(self, rt: "LayerContext") -> TaskState:
        """Brake release (pfma-model 8.4): rate 0 V, then raise the current limits, wait
        until the brakes report released; then hold the present angles and close the loop.
        While the runtime is halted the outputs are held safe (brakes set): the wait goes on,
        its time-out counting from the first frame after the resume's re-arm."""
        if self.task_frames == 0:
            rt.wm.post_task_outputs("servo", {SERVO.rate_cmd_rad_s: np.zeros(N_JOINTS), SERVO.rate_cmd_frame: -1})
            self._testing = False
            self._brake_phase(rt, 1)
            return TaskState.RUNNING
        if self._phase == 1:  # the gripper's stays 0 until its drive runs (START UP COMPLETE)
            rt.wm.post_task_outputs("servo", {SERVO.current_limit_cmd_a: self.limits_cmd(0.0)})
            self._brake_phase(rt, 2)
            return TaskState.RUNNING
        if self._testing:
            return self._brake_test_result(rt)
        v = rt.wm.get_task_inputs((DAQ.brakes_released, DAQ.joint_angle_rad))
        if bool(v[DAQ.brakes_released]):
            self.hold = np.array(v[DAQ.joint_angle_rad], dtype=float)
            rt.post(self.key, Level.INFO, f"brakes released {(rt.now - self._t_phase) * 1e3:.1f} ms after the "
                                          f"current limits were raised"
                                          + ("; brake test: each joint out and back" if self.brake_test_on else
                                             "; holding the present angles (brake test off)"))
            if self.brake_test_on:
                self._q_powerup = self.hold.tolist()
                self.brake_test = None  # started by the next servo period (control_task)
                self._testing = True
                self._brake_phase(rt, PHASE_BRAKE_TEST)
                return TaskState.RUNNING
            self.comp.reset(0.0)
            self._brake_phase(rt, 3)
            return TaskState.DONE
        if rt.halted:
            self._t_phase = rt.now
            return TaskState.RUNNING
        if rt.now - self._t_phase > BRAKE_RELEASE_TIMEOUT_S:
            rt.post(self.key, Level.ERROR, f"brakes not released {BRAKE_RELEASE_TIMEOUT_S} s after the "
                                           f"current limits were raised")
            return TaskState.FAILED
        return TaskState.RUNNING

    def _brake_test_result(self, rt: "LayerContext") -> TaskState:
        """The brake test's end: every joint proved -> the loop closes on the power-up's
        pose (DONE); a joint that did not -> the layer's fault naming it (every current
        limit 0 at once, as a supervision trip) and FAILED."""
        bt = self.brake_test
        if self.fault:  # a supervision check tripped while the joints moved (it named the joint)
            self._testing = False
            return TaskState.FAILED
        if bt is None or not bt.done:
            return TaskState.RUNNING
        self._testing = False
        if bt.failed:
            k = min(bt.failed)
            self._trip(rt, Trip(k, "brake test", bt.causes[k], "brake test: " + "; ".join(
                bt.failed[j] for j in sorted(bt.failed))), ERR_BRAKE_TEST)
            return TaskState.FAILED
        self.hold = np.array(self._q_powerup, dtype=float)
        self.comp.reset(0.0)
        worst = max(range(N_JOINTS), key=lambda j: bt.excursion[j])
        rt.post(self.key, Level.INFO, f"brake test passed in {bt.t * 1e3:.0f} ms: every joint moved as told "
                                      f"(brakes PROVEN RELEASED; furthest {math.degrees(bt.excursion[worst]):.2f} deg, "
                                      f"{JOINTS[worst].name}); holding the power-up pose")
        self._brake_phase(rt, 3)
        return TaskState.DONE

    def seq_shutdown(self, rt: "LayerContext") -> TaskState:
        """Safe stop (pfma-model 8.4): rate 0 V; wait |qdot| < 0.01 rad/s or 0.5 s; limits 0 V."""
        if self.task_frames == 0:
            rt.wm.post_task_outputs("servo", {SERVO.rate_cmd_rad_s: np.zeros(N_JOINTS), SERVO.rate_cmd_frame: -1})
            self._brake_phase(rt, 4)
            return TaskState.RUNNING
        v = rt.wm.get_task_inputs((DAQ.joint_rate_rad_s, DAQ.fault_bits))
        qdot = np.asarray(v[DAQ.joint_rate_rad_s], dtype=float)
        tach_ok = not int(v[DAQ.fault_bits]) & TACH_FAULT_BIT  # a failed tach ADC proves nothing
        still = tach_ok and bool(np.all(np.abs(qdot) < SAFE_STOP_RATE_RAD_S))
        if still or rt.now - self._t_phase >= SAFE_STOP_TIMEOUT_S:
            rt.wm.post_task_outputs("servo", {SERVO.current_limit_cmd_a: np.zeros(N_CURRENT_LIMITS)})
            rt.post(self.key, Level.INFO, f"safe stop: current limits 0 after "
                                          f"{(rt.now - self._t_phase) * 1e3:.1f} ms "
                                          f"({'joints still' if still else 'timeout'})")
            self._brake_phase(rt, 5)
            return TaskState.DONE
        return TaskState.RUNNING

    def seq_safe(self, rt: "LayerContext") -> TaskState:
        return self.seq_shutdown(rt)

    # --- the control law -----------------------------------------------------------------
    _BRAKE_IN = (DAQ.joint_angle_rad, DAQ.service_frame, SERVO.current_limit_cmd_a)
    _IN = (DAQ.joint_angle_rad, DAQ.service_frame, DAQ.joint_rate_rad_s, DAQ.motor_current_a,
           SERVO.current_limit_cmd_a, JOINT.q_cmd_rad, JOINT.q_cmd_valid)

    def control_task(self, rt: "LayerContext") -> None:
        """Supervise the joints (whenever the current limits may be raised), then commanded
        joint positions -> rate commands (only while START UP COMPLETE)."""
        wm = rt.wm
        # the status this frame's table decided (the posted one is applied next frame): a
        # safe stop or shut-down starting this frame posted 0 rates the loop must not overwrite
        closed = self.decided == Status.START_UP_COMPLETE and not self.fault
        live = self.sup is not None and self._phase in _LIVE_PHASES and not self.fault
        if not closed and not live:
            if self._sup_frame >= 0 and self.sup is not None:
                self.sup.reset()
                self._sup_frame = -1
            if self.sup is not None:  # the brakes as the sensors show them, powered down too
                b = wm.get_task_inputs(self._BRAKE_IN)
                self.sup.observe_brakes(int(b[DAQ.service_frame]) * self.frame_period_s,
                                        np.asarray(b[DAQ.joint_angle_rad]).tolist(),
                                        np.asarray(b[SERVO.current_limit_cmd_a]).tolist())
                self._post_brakes(wm)
            return
        v = wm.get_task_inputs(self._IN)
        q = np.asarray(v[DAQ.joint_angle_rad], dtype=float)
        frame = int(v[DAQ.service_frame])
        p = self.params
        q_cmd = np.asarray(v[JOINT.q_cmd_rad], dtype=float) if bool(v[JOINT.q_cmd_valid]) else self.hold
        q_cmd = np.clip(q_cmd, p["q_min_rad"], p["q_max_rad"])
        if live:
            if not closed and self._phase != PHASE_BRAKE_TEST:
                self._u_sent = [0.0] * N_JOINTS
            dt = (frame - self._sup_frame) * self.frame_period_s if self._sup_frame >= 0 else 0.0
            self._sup_frame = frame
            self._tach = np.asarray(v[DAQ.joint_rate_rad_s]).tolist()
            trip = self.sup.update(dt, q.tolist(), self._tach, np.asarray(v[DAQ.motor_current_a]).tolist(),
                                   self._u_sent, np.asarray(v[SERVO.current_limit_cmd_a]).tolist(),
                                   closed and self._phase == 3, q_cmd.tolist())
            self._post_brakes(wm)
            if trip is not None:
                self._trip(rt, trip)
                return
        if self._phase == PHASE_BRAKE_TEST:
            self._brake_test_step(rt, q, frame)
            return
        if not closed:
            return
        e = q_cmd - q
        rate = self.comp.step(e, p["rate_limit_rad_s"])  # saturated, the state follows (anti-windup)
        below, above = q < p["q_min_rad"], q > p["q_max_rad"]
        rate[(below & (rate < 0)) | (above & (rate > 0))] = 0.0
        out = (q < p["q_min_rad"] - LIMIT_FAULT_MARGIN_RAD) | (q > p["q_max_rad"] + LIMIT_FAULT_MARGIN_RAD)
        if np.any(out):
            names = [JOINTS[i].name for i in np.nonzero(out)[0]]
            self.set_fault(rt, ERR_LIMIT, f"beyond the soft limit: {', '.join(names)}")
            rate[:] = 0.0
        self.comp.track(rate)
        self._u_sent = rate.tolist()
        # stamped with the service frame of the inputs it was computed from: Data Acquisition
        # sends it only within its servo period, the service only while young enough
        wm.post_task_outputs("servo", {SERVO.rate_cmd_rad_s: rate, SERVO.error_rad: e,
                                       SERVO.ferror_rad: self.sup.ferror_rad,
                                       SERVO.rate_cmd_frame: frame})

    def _brake_test_step(self, rt: "LayerContext", q: np.ndarray, frame: int) -> None:
        """One servo period of the power-up brake test (:class:`BrakeTest`): its rates,
        stamped with this frame. Halted (the outputs held safe, nothing moves): the test
        starts again after the resume."""
        if rt.halted:
            self.brake_test = None
            self._u_sent = [0.0] * N_JOINTS
            return
        p = self.params
        if self.brake_test is None:
            assert self.sup is not None
            self.brake_test = BrakeTest(self.sup, self._q_powerup or q.tolist(), p["q_min_rad"].tolist(),
                                        p["q_max_rad"].tolist(), p["rate_limit_rad_s"].tolist())
        rates = self.brake_test.step(self.period_s, q.tolist(), self._tach)
        self._u_sent = rates
        rt.wm.post_task_outputs("servo", {SERVO.rate_cmd_rad_s: np.array(rates), SERVO.rate_cmd_frame: frame})

    def _post_brakes(self, wm) -> None:
        """``servo.brake_state``, posted when it changes (rarely)."""
        if self.sup is not None and self.sup.brake_state != self._brake_posted:
            self._brake_posted = list(self.sup.brake_state)
            wm.post_task_outputs("servo", {SERVO.brake_state: self._brake_posted})

    def _trip(self, rt: "LayerContext", trip: Trip, code: int | None = None) -> None:
        """A supervision trip: the layer's fault (one message naming joint, check and likely
        cause), the rates and every current limit to 0 at once (brakes on): the safe stop's
        wait for still joints is no use when a joint does not follow its command."""
        self.trip = trip
        self.set_fault(rt, SUPERVISION_CODES[trip.check] if code is None else code,
                       f"{trip.text}; current limits 0 (brakes on)")
        self._u_sent = [0.0] * N_JOINTS
        rt.wm.post_task_outputs("servo", {SERVO.rate_cmd_rad_s: np.zeros(N_JOINTS), SERVO.rate_cmd_frame: -1,
                                          SERVO.current_limit_cmd_a: self._zero_limits,
                                          SERVO.trip_joint: trip.joint, SERVO.trip_cause: trip.cause})
        self._brake_phase(rt, 5)
