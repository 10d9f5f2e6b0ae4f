"""Force control: position-based impedance (admittance) on the wrist F/T sensor.

The PFMA's amplifiers close a rate loop, so the computer can only command motion; an
impedance is realised as a compliant offset added to the commanded Cartesian pose
(pfma-model.md section 5, "position-based impedance"):

    M e'' + B e' + K e = F - F_des            per axis, diagonal M, B, K
    e'_{k+1} = e'_k + T (F_k - F_des - B e'_k - K e_k) / M      (semi-implicit Euler)
    e_{k+1}  = e_k + T e'_{k+1}

e is (translation m, small rotation vector rad) of the compliant frame from the
reference pose, at the tool point, in the world frame (or in the tool frame when
``frame`` is FRAME_TOOL; then rotated into the world with the reference orientation).

F/T processing (section 5: bias-removed, gravity-compensated, transformed to the
control frame, ~10 Hz low-pass, small deadband):

1. ``raw - bias - tool gravity(R)``, R the measured sensor orientation (sensor frame
   parallel to frame 6, 8.1; tool 1.5 kg, centre of mass 0.06 m beyond the sensor along
   z6, 8.7; or the payload of a calibration file, :func:`tool_load_from_calibration`);
2. moved to the tool point (0.10 m beyond the sensor along z6, 8.1) and rotated into
   the world frame;
3. 10 Hz one-pole filter (8.9), exact discretisation at the task period;
4. deadband 2 N / 0.2 N*m (8.9), applied to the vector's length (shrinks it, so there
   is no step at the edge).

Defaults (8.9, per axis): translation M 10 kg, B 200 N*s/m, K 500 N/m; rotation
M 0.5 kg*m^2, B 10 N*m*s/rad, K 20 N*m/rad - except the translation damping, raised to
600 N*s/m for a stable default against the stiff simulated wall (see DEFAULT_DAMPING).

**Task state transitions** (IRSS report 2.2.1, Task State Transition Layer: "transition
between a zeroing of the force/torque sensor to impedance control"): :class:`ForceControl`
is a small state machine inside the Cartesian engine's fast task:

    OFF --enable--> ZEROING --ZERO_TIME_S of samples--> IMPEDANCE --disable--> OFF
    OFF --zero request--> ZEROING --> OFF
    ZEROING --disable--> OFF (bias unchanged)

Zeroing averages ``raw - tool gravity`` (the sensor must be free of contact) into the
bias. Leaving impedance returns the offset reached, which the Cartesian engine folds
into its reference so that nothing moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from controller.quat import q_to_matrix
from controller.teleop import FRAME_NAMES
from controller.worldmodel.var import Var, VarGroup, var
from pfma.errors import ConfigError

SOURCE = "pfma-model.md 5, 8.1, 8.7, 8.9 (assumed)"
GRAVITY_M_S2 = 9.81
#: 8.7 tool behind the sensor: 1.5 kg, centre of mass 0.06 m beyond the sensor along z6
TOOL_MASS_KG = 1.5
TOOL_COM_M = (0.0, 0.0, 0.06)
#: 8.1: sensor 0.20 m from the wrist centre along z6, tool point 0.30 m -> 0.10 m beyond it
SENSOR_TO_TOOL_M = (0.0, 0.0, 0.10)
#: 8.9 force filter (one pole) and deadband
FILTER_HZ = 10.0
DEADBAND_N = 2.0
DEADBAND_NM = 0.2
#: 8.9 impedance defaults (x y z roll pitch yaw), EXCEPT the translation damping: 8.9's
#: 200 N*s/m (zeta 1.4) rings against the simulated stiff wall (2e4 N/m) through the
#: servo's compliance and joint friction (force swinging 10-21 N for 2 s after the
#: reference stops); 600 N*s/m (zeta 4.2, free-space time constant B/K = 1.2 s) settles
#: without a swing (tests/controller/test_force.py). Measured on the simulator; assumed.
DEFAULT_MASS = (10.0, 10.0, 10.0, 0.5, 0.5, 0.5)
DEFAULT_DAMPING = (600.0, 600.0, 600.0, 10.0, 10.0, 10.0)
DEFAULT_STIFFNESS = (500.0, 500.0, 500.0, 20.0, 20.0, 20.0)
#: time the zeroing averages the sensor (assumed: 25 samples of the 100 Hz sensor)
ZERO_TIME_S = 0.25
#: largest compliant offset (assumed safety bound): 0.10 m, 0.35 rad (20 deg)
MAX_OFFSET_M = 0.10
MAX_OFFSET_RAD = 0.35
#: section 5 caution "T sqrt(K/M) << 1": parameters with more than this are refused
MAX_T_OMEGA = 0.5

FRAME_WORLD, FRAME_TOOL = 0, 1
OFF, ZEROING, IMPEDANCE = 0, 1, 2
STATE_NAMES = {OFF: "OFF", ZEROING: "ZEROING", IMPEDANCE: "IMPEDANCE"}


@dataclass(frozen=True)
class ToolLoad:
    """Mass behind the F/T sensor for gravity compensation (sensor frame)."""

    mass_kg: float = TOOL_MASS_KG
    com_m: tuple[float, float, float] = TOOL_COM_M

    def wrench(self, rot_world_sensor: np.ndarray, gravity_m_s2: float = GRAVITY_M_S2) -> tuple[np.ndarray, np.ndarray]:
        """Tool gravity as the sensor reads it: (force N, torque N*m about its origin), sensor axes."""
        f = rot_world_sensor.T @ np.array([0.0, 0.0, -self.mass_kg * gravity_m_s2])
        return f, np.cross(np.asarray(self.com_m, dtype=float), f)


def tool_load_from_calibration(cal) -> ToolLoad:
    """The payload of a calibration file (:func:`pfma.ft_calibration.ft_calibration`) when it
    has one (mass > 0), else the 8.7 default tool."""
    from pfma.ft_calibration import ft_calibration
    ft = ft_calibration(cal) if cal is not None else None
    if ft is None or not ft.payload_mass_kg > 0.0:
        return ToolLoad()
    return ToolLoad(float(ft.payload_mass_kg), tuple(float(x) for x in ft.payload_com_m))


@dataclass(frozen=True)
class ImpedanceParams:
    """Per-axis mass, damping, stiffness (x y z roll pitch yaw; kg | kg*m^2, N*s/m | N*m*s/rad,
    N/m | N*m/rad)."""

    mass: tuple[float, ...] = DEFAULT_MASS
    damping: tuple[float, ...] = DEFAULT_DAMPING
    stiffness: tuple[float, ...] = DEFAULT_STIFFNESS

    def check(self, period_s: float) -> "ImpedanceParams":
        """:raises ConfigError: naming the axis, for a mass <= 0, a negative damping or
        stiffness, a non-finite value, or T sqrt(K/M) above MAX_T_OMEGA"""
        axes = ("x", "y", "z", "roll", "pitch", "yaw")
        for name, vec in (("mass", self.mass), ("damping", self.damping), ("stiffness", self.stiffness)):
            if len(vec) != 6:
                raise ConfigError(f"impedance {name} needs 6 values, got {len(vec)}")
        for i, a in enumerate(axes):
            m, b, k = self.mass[i], self.damping[i], self.stiffness[i]
            if not all(math.isfinite(v) for v in (m, b, k)):
                raise ConfigError(f"impedance axis {a}: non-finite M/B/K ({m}, {b}, {k})")
            if m <= 0.0 or b < 0.0 or k < 0.0:
                raise ConfigError(f"impedance axis {a}: need M > 0, B >= 0, K >= 0 (got {m}, {b}, {k})")
            if period_s * math.sqrt(k / m) > MAX_T_OMEGA or period_s * b / m > 1.0:
                raise ConfigError(f"impedance axis {a}: too fast for a {period_s * 1e3:.1f} ms task "
                                  f"(T sqrt(K/M) = {period_s * math.sqrt(k / m):.2f}, T B/M = "
                                  f"{period_s * b / m:.2f}; pfma-model 5: keep them << 1)")
        return self


class FtProcessor:
    """Bias, tool gravity, tool-point transform, filter and deadband of the wrist F/T."""

    def __init__(self, load: ToolLoad | None = None, filter_hz: float = FILTER_HZ,
                 deadband_n: float = DEADBAND_N, deadband_nm: float = DEADBAND_NM) -> None:
        self.load = load if load is not None else ToolLoad()
        self.filter_hz = filter_hz
        self.deadband_n, self.deadband_nm = deadband_n, deadband_nm
        self.bias = np.zeros(6)  #: sensor axes (force, torque)
        self.filtered = np.zeros(6)  #: tool point, world frame, after the filter
        self._primed = False
        self._sum = np.zeros(6)
        self._n = 0

    def compensated(self, force_n, torque_nm, rot_world_sensor: np.ndarray) -> np.ndarray:
        """Sensor reading minus bias and tool gravity, sensor axes (6)."""
        gf, gt = self.load.wrench(rot_world_sensor)
        raw = np.concatenate([np.asarray(force_n, dtype=float), np.asarray(torque_nm, dtype=float)])
        return raw - self.bias - np.concatenate([gf, gt])

    # zeroing
    def zero_begin(self) -> None:
        self._sum[:] = 0.0
        self._n = 0

    def zero_add(self, force_n, torque_nm, rot_world_sensor: np.ndarray) -> None:
        gf, gt = self.load.wrench(rot_world_sensor)
        self._sum += np.concatenate([np.asarray(force_n, float) - gf, np.asarray(torque_nm, float) - gt])
        self._n += 1

    def zero_end(self) -> np.ndarray:
        """Take the average as the new bias; returns it."""
        if self._n:
            self.bias = self._sum / self._n
        self._primed = False
        self.filtered[:] = 0.0
        return self.bias.copy()

    def tool_wrench_world(self, force_n, torque_nm, rot_world_sensor: np.ndarray, dt_s: float) -> np.ndarray:
        """Filtered, dead-banded wrench on the tool point, world frame: (F N, tau N*m)."""
        c = self.compensated(force_n, torque_nm, rot_world_sensor)
        f_s, t_s = c[:3], c[3:] - np.cross(np.asarray(SENSOR_TO_TOOL_M), c[:3])  # torque about the tool point
        w = np.concatenate([rot_world_sensor @ f_s, rot_world_sensor @ t_s])
        if not self._primed:
            self.filtered[:] = w
            self._primed = True
        else:
            alpha = 1.0 - math.exp(-dt_s * 2.0 * math.pi * self.filter_hz)
            self.filtered += alpha * (w - self.filtered)
        return np.concatenate([shrink(self.filtered[:3], self.deadband_n),
                               shrink(self.filtered[3:], self.deadband_nm)])


def shrink(v: np.ndarray, deadband: float) -> np.ndarray:
    """Deadband on a vector's length: zero inside, shortened by ``deadband`` outside."""
    n = float(np.linalg.norm(v))
    if n <= deadband:
        return np.zeros_like(v)
    return v * ((n - deadband) / n)


class Admittance:
    """The per-axis M-B-K filter of section 5 (semi-implicit Euler), state e, e'."""

    def __init__(self, params: ImpedanceParams | None = None) -> None:
        self.params = params if params is not None else ImpedanceParams()
        self.e = np.zeros(6)
        self.ed = np.zeros(6)

    def reset(self) -> None:
        self.e[:] = 0.0
        self.ed[:] = 0.0

    def step(self, wrench6: np.ndarray, dt_s: float, wrench_des6: np.ndarray | None = None) -> np.ndarray:
        """One period: returns e (6) after the update, bounded by MAX_OFFSET_M / _RAD."""
        p = self.params
        m, b, k = np.asarray(p.mass), np.asarray(p.damping), np.asarray(p.stiffness)
        f = np.asarray(wrench6, dtype=float) - (0.0 if wrench_des6 is None else np.asarray(wrench_des6, float))
        self.ed += dt_s * (f - b * self.ed - k * self.e) / m
        self.e += dt_s * self.ed
        for sl, lim in ((slice(0, 3), MAX_OFFSET_M), (slice(3, 6), MAX_OFFSET_RAD)):
            n = float(np.linalg.norm(self.e[sl]))
            if n > lim:  # at the bound: stop moving outward
                self.e[sl] *= lim / n
                u = self.e[sl] / lim
                out = float(self.ed[sl] @ u)
                if out > 0.0:
                    self.ed[sl] -= out * u
        return self.e.copy()


@dataclass
class ForceStep:
    """What one :meth:`ForceControl.step` produced."""

    state: int
    offset_world: np.ndarray  #: (dp m, rotation vector rad), world frame
    wrench_world: np.ndarray  #: processed tool-point wrench (zeros unless IMPEDANCE)
    fold: np.ndarray | None = None  #: offset to fold into the reference (leaving impedance)
    events: list[str] = field(default_factory=list)


class ForceControl:
    """The force-control task's state machine and its processing (see the module doc).

    :param period_s: the task period (the Cartesian engine's fast task)
    """

    def __init__(self, period_s: float, load: ToolLoad | None = None,
                 params: ImpedanceParams | None = None, zero_time_s: float = ZERO_TIME_S) -> None:
        self.period_s = period_s
        self.ft = FtProcessor(load)
        self.adm = Admittance((params or ImpedanceParams()).check(period_s))
        self.zero_time_s = zero_time_s
        self.state = OFF
        self.frame = FRAME_WORLD
        self._zero_then = OFF
        self._zero_t0 = 0.0
        self._offset_world = np.zeros(6)

    def set_params(self, params: ImpedanceParams) -> None:
        """:raises ConfigError: invalid parameters (the old ones stay)"""
        self.adm.params = params.check(self.period_s)

    def request_zero(self, t_s: float) -> bool:
        """Zero the sensor now (only from OFF); True when accepted."""
        if self.state != OFF:
            return False
        self._start_zero(t_s, OFF)
        return True

    def _start_zero(self, t_s: float, then: int) -> None:
        self.state, self._zero_then, self._zero_t0 = ZEROING, then, t_s
        self.ft.zero_begin()

    def reset(self) -> None:
        """Power-down/start-up: OFF, no offset (the bias is kept)."""
        self.state = OFF
        self.adm.reset()
        self._offset_world = np.zeros(6)

    def step(self, t_s: float, enable: bool, force_n, torque_nm, quat_meas, quat_ref,
             wrench_des=None) -> ForceStep:
        """One fast-task period. ``quat_meas``: measured tool (= sensor) orientation;
        ``quat_ref``: the reference orientation (tool-frame impedance)."""
        ev: list[str] = []
        rot = q_to_matrix(quat_meas)
        fold = None
        if self.state == OFF and enable:
            self._start_zero(t_s, IMPEDANCE)
            ev.append("OFF -> ZEROING (entering impedance: zeroing the F/T sensor)")
        if self.state == ZEROING:
            if self._zero_then == IMPEDANCE and not enable:
                self.state = OFF
                ev.append("ZEROING -> OFF (impedance disabled before the zeroing finished; bias unchanged)")
            else:
                self.ft.zero_add(force_n, torque_nm, rot)
                if t_s - self._zero_t0 >= self.zero_time_s - 1e-9:
                    b = self.ft.zero_end()
                    self.state = self._zero_then
                    self.adm.reset()
                    ev.append(f"ZEROING -> {STATE_NAMES[self.state]} (bias F {b[0]:+.2f} {b[1]:+.2f} {b[2]:+.2f} N, "
                              f"T {b[3]:+.3f} {b[4]:+.3f} {b[5]:+.3f} N*m)")
            return ForceStep(self.state, self._offset_world.copy(), np.zeros(6), None, ev)
        if self.state == IMPEDANCE and not enable:
            self.state = OFF
            fold = self._offset_world.copy()
            self.adm.reset()
            self._offset_world = np.zeros(6)
            ev.append("IMPEDANCE -> OFF (offset folded into the reference)")
        if self.state != IMPEDANCE:
            return ForceStep(self.state, self._offset_world.copy(), np.zeros(6), fold, ev)
        w = self.ft.tool_wrench_world(force_n, torque_nm, rot, self.period_s)
        if self.frame == FRAME_TOOL:
            r_ref = q_to_matrix(quat_ref)
            w_ctl = np.concatenate([r_ref.T @ w[:3], r_ref.T @ w[3:]])
            e = self.adm.step(w_ctl, self.period_s, wrench_des)
            off = np.concatenate([r_ref @ e[:3], r_ref @ e[3:]])
        else:
            off = self.adm.step(w, self.period_s, wrench_des)
        self._offset_world = off
        return ForceStep(self.state, off.copy(), w, None, ev)


class ForceVars(VarGroup, prefix="force", writer="cartesian"):
    """Force control's world-model variables: the user's impedance controls and the
    Cartesian layer's force state (controller/cartesian.py)."""

    enable: Var[bool] = var("command_input", "b1", (), False, writer="user",
                            doc="impedance control on (zeroes the F/T sensor first)")
    zero_seq: Var[int] = var("command_input", "i4", (), 0, writer="user",
                             doc="increment to zero the F/T sensor (only while impedance is off; no contact!)")
    frame: Var[int] = var("command_input", "i2", (), 0, writer="user", doc="impedance axes: world or tool frame",
                          enum=FRAME_NAMES)
    mass: Var[np.ndarray] = var("command_input", "f8", (6,), list(DEFAULT_MASS), "kg|kg*m^2", writer="user",
                                doc="impedance mass per axis x y z roll pitch yaw")
    damping: Var[np.ndarray] = var("command_input", "f8", (6,), list(DEFAULT_DAMPING), "N*s/m|N*m*s/rad",
                                   writer="user", doc="impedance damping per axis")
    stiffness: Var[np.ndarray] = var("command_input", "f8", (6,), list(DEFAULT_STIFFNESS), "N/m|N*m/rad",
                                     writer="user", doc="impedance stiffness per axis (0: pure damping)")
    wrench_des: Var[np.ndarray] = var("command_input", "f8", (6,), [0.0] * 6, "N|N*m", writer="user",
                                      doc="desired contact wrench on the tool point, world (or tool) frame")
    state: Var[int] = var("task_status", "i2", (), 0, doc="force control state", enum=STATE_NAMES)
    offset: Var[np.ndarray] = var("task_status", "f8", (6,), [0.0] * 6, "m|rad",
                                  doc="compliant offset (world dp, rotation vector)")
    wrench_n: Var[np.ndarray] = var("task_io", "f8", (6,), [0.0] * 6, "N|N*m",
                                    doc="processed tool-point wrench, world (bias, gravity, 10 Hz, deadband)")
    bias: Var[np.ndarray] = var("task_status", "f8", (6,), [0.0] * 6, "N|N*m", doc="F/T bias (sensor axes)")


FORCE = ForceVars
