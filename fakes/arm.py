"""Physical model of the PFMA for the simulated rack: joint dynamics behind the amplifiers.

Seven axes (SY, SP, EP, WP, WY, WR and the gripper), each with the analog rate loop of
its PWM/rate servo card (IRSS report 3.6, pfma-model.md 8.4)::

    tach filter   V_tf' = (K_w (1 + e_tach) qdot - V_tf) / tau_f        (10 Hz, IRSS 3.6.3)
    amplifier     I     = sat(K_a (V_cmd - V_tf), +-I_max V_ilim / 10)   (V_ilim < 0 -> 0)
    joint torque  tau_m = N eta K_t I
    brake         engaged below 0.3 V current limit, released above 0.5 V (hysteresis);
                  holds up to 1.5 x the max joint torque, then slips
    front panel   the servo chassis' switches (IRSS 3.6, SimErrors.panel_*): a PWM stage off:
                  I = 0 on that axis; a brake release switch off: that brake set; the
                  +/-15 V converter off (or the +28 V that feeds it): I = 0 on every axis,
                  every brake set, current monitors and tach filter outputs at 0 V
    J qddot = tau_m + tau_gravity + tau_contact + tau_stop - b qdot - F_c sgn(qdot) - brake

The gripper's jaw (axis 6, opening in m) has hard stops at 0 (closed) and its travel; an
object placed between the jaws (:meth:`ArmModel.place_jaw_object`) is a stop at its width,
as stiff as the hard stops: a close stalls on it and presses with the force the amplifier's
current limit sets (:attr:`ArmModel.jaw_force_n`).

Simplifications (documented in docs/simulated-arm.md): decoupled per-joint effective
inertias (8.3) instead of a full rigid-body model; gravity is the exact static gravity of
the 8.3 point masses (links counterbalanced 90 % on J1-J5, payload not), held constant
over one ``step``; contact is a point contact at the tool point, linearised about the
pose at the start of each ``step``. Integration is fixed-step semi-implicit Euler with
substeps of at most ``max_substep_s`` (1 ms): the viscous, stop-damping and Coulomb/brake
terms are implicit (a stick-aware projection, so friction never chatters), the spring
terms explicit. Everything is deterministic: the same inputs give the same trajectory.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fakes.arm_params import BRAKE_LOGIC_ON_15V, N_AXES, N_JOINTS, NOMINAL, ArmParams, SimErrors
from fakes.environment import Environment, point_load_wrench, tool_gravity_wrench
from fakes.kinematics import Kinematics

#: Gravity is recomputed when a joint has moved this far since the last evaluation
#: (<= 0.5 N*m error on any joint, well below the Coulomb friction; simulator choice).
GRAVITY_REQUANTUM_RAD = 1.0e-3


@dataclass(frozen=True)
class ArmState:
    """A snapshot of the simulated arm's true state (axis order SY SP EP WP WY WR GR)."""

    t_s: float  #: simulated time since construction, s
    q: np.ndarray  #: joint angles, rad (gripper: jaw opening, m)
    qdot: np.ndarray  #: joint rates, rad/s (gripper: m/s)
    tach_volts: np.ndarray  #: filtered tach voltage V_tf, V
    current_a: np.ndarray  #: motor current, A
    current_monitor_volts: np.ndarray  #: V_imon = 10 I / I_max, V
    brake_engaged: np.ndarray  #: bool per axis (always False for the gripper, which has none)
    contact_force_n: np.ndarray  #: force of the environment on the tool point, world frame, N
    jaw_force_n: float = 0.0  #: force between the jaws (on an object, or on each other when closed), N


class ArmModel:
    """The simulated PFMA: seven rate-servoed axes, brakes, gravity, friction, stops, contact.

    :param params: nominal parameters (default :data:`fakes.arm_params.NOMINAL`)
    :param environment: contact objects (default: free space)
    :param errors: known departures from nominal (``tach_scale_error``, ``payload_kg`` and
        the motion faults ``brake_held``, ``amp_off``, ``load_nm`` and the front-panel
        switches ``panel_*`` act here; resolver/ADC/DAC errors act in ``SimulatedRack``)
    :param q0: initial positions, 7 values (default ``params.q_initial``, the 8.1 ready pose)
    :param shoulder_roll_rad: manual shoulder-roll index (tilts gravity in the base frame)
    """

    n_axes = N_AXES

    def __init__(self, params: ArmParams = NOMINAL, environment: Environment | None = None,
                 errors: SimErrors | None = None, q0: Sequence[float] | None = None,
                 shoulder_roll_rad: float = 0.0) -> None:
        self.params = params
        self.environment = environment if environment is not None else Environment()
        self.errors = errors if errors is not None else SimErrors()
        self.kin = Kinematics(params.dh, shoulder_roll_rad)
        ax = params.axes
        if len(ax) != N_AXES:
            raise ValueError(f"the arm model needs {N_AXES} axes, got {len(ax)}")
        f = lambda fn: np.array([fn(a) for a in ax], dtype=float)  # noqa: E731
        self.inertia = f(lambda a: a.inertia)
        self.viscous = f(lambda a: a.viscous)
        self.coulomb = f(lambda a: a.coulomb)
        self.torque_per_amp = f(lambda a: a.torque_per_amp)
        self._k_a_nominal = np.array(params.k_a())
        self.k_a = self._k_a_nominal.copy()
        self.k_w = f(lambda a: a.k_w)
        self.i_max = f(lambda a: a.i_max_a)
        self.hard_lo = f(lambda a: a.hard_lo)
        self.hard_hi = f(lambda a: a.hard_hi)
        self._jaw_axis = next(i for i, a in enumerate(ax) if a.name == "GR")
        self.brake_fitted = np.array([a.brake for a in ax])
        self.slip = params.brake_slip_factor * f(lambda a: a.torque_max) * self.brake_fitted
        self.k_stop = self.inertia * params.stop_omega_rad_s ** 2
        self.c_stop = 2.0 * params.stop_zeta * params.stop_omega_rad_s * self.inertia
        self._counterbalance = 1.0 - params.counterbalance_fraction * f(lambda a: a.counterbalanced)[:N_JOINTS]
        # point masses for gravity: frame index and homogeneous centre of mass
        lm = params.link_masses
        self._m_frames = np.array([m.frame for m in lm])
        self._m_kg = np.array([m.mass_kg for m in lm])
        self._m_com = np.array([(*m.com_m, 1.0) for m in lm])
        self._m_mask = np.array([[m.frame >= i + 1 for m in lm] for i in range(N_JOINTS)], dtype=float)
        self._d6 = params.dh[-1].d_m
        #: the amplifiers' enable (the rack's charge-pump relay, when it has one: True
        #: without one, the amplifiers then being enabled by the hardware E-stop chain alone)
        self.amplifiers_enabled = True
        self.set_errors(self.errors)
        self.reset(q0)

    # -- configuration ----------------------------------------------------------
    def set_errors(self, errors: SimErrors) -> None:
        """Install new truth errors (tach scale, amplifier gain, payload, motion faults) for
        the following steps."""
        self.errors = errors
        self.k_w_true = self.k_w * (1.0 + np.asarray(errors.tach_scale_error, dtype=float))
        self.k_a = self._k_a_nominal * (1.0 + np.asarray(errors.amp_gain_error, dtype=float))
        # motion faults (sim.faults brake-held / amp-off / load) and the servo control
        # chassis' front-panel switches (sim.faults panel-off:...), kept apart in SimErrors
        # and combined here: either one sets a brake or turns a PWM stage off
        brake_set = np.asarray(errors.brake_held, dtype=bool) | np.asarray(errors.panel_brake_off, dtype=bool)
        stage_off = np.asarray(errors.amp_off, dtype=bool) | np.asarray(errors.panel_pwm_off, dtype=bool)
        #: the +/-15 V DC-DC converter is on (it runs from the chassis' +28 VDC, IRSS 3.6):
        #: False, the rate servo cards, current monitors and tach filter buffers are unpowered
        self.analog_powered = not (errors.panel_28v_off or errors.panel_15v_off)
        if not self.analog_powered:
            stage_off = np.ones(N_AXES, dtype=bool)  # no drive from an unpowered rate servo card
            if errors.panel_28v_off or BRAKE_LOGIC_ON_15V:  # no coil power, or no threshold logic
                brake_set = np.ones(N_AXES, dtype=bool)
        self._brake_held = brake_set & self.brake_fitted
        self._amp_on = ~stage_off
        self._load_nm = np.asarray(errors.load_nm, dtype=float)
        self._faulted = bool(self._brake_held.any() or not self._amp_on.all() or self._load_nm.any())
        self._g_key = None

    @property
    def shoulder_roll_rad(self) -> float:
        return self.kin.shoulder_roll_rad

    @shoulder_roll_rad.setter
    def shoulder_roll_rad(self, value: float) -> None:
        self.kin.shoulder_roll_rad = value
        self._g_key = None

    def reset(self, q0: Sequence[float] | None = None) -> None:
        """At rest at ``q0`` (default: the ready pose), brakes engaged, filters empty."""
        q = np.array(self.params.q_initial if q0 is None else q0, dtype=float)
        if q.shape != (N_AXES,):
            raise ValueError(f"q0 needs {N_AXES} values (SY SP EP WP WY WR GR), got shape {q.shape}")
        self.q = q
        self.qdot = np.zeros(N_AXES)
        self.tach_volts = np.zeros(N_AXES)
        self.current_a = np.zeros(N_AXES)
        self.brake_engaged = self.brake_fitted.copy()
        self.t_s = 0.0
        self.contact_force_n = np.zeros(3)
        self._lo = self.hard_lo.copy()  # the hard stops, and an object between the jaws
        self.jaw_object_m: float | None = None  #: width of the object between the jaws (None: none)
        self._g_key = None
        self._h = None
        self._tau = np.zeros(N_AXES)
        self._tmp = np.zeros(N_AXES)

    def set_state(self, q: Sequence[float] | None = None, qdot: Sequence[float] | None = None) -> None:
        """Place the arm (tests, calibration truth). Filters are set consistent with ``qdot``."""
        if q is not None:
            self.q = np.array(q, dtype=float).reshape(N_AXES)
        if qdot is not None:
            self.qdot = np.array(qdot, dtype=float).reshape(N_AXES)
            self.tach_volts = self.k_w_true * self.qdot
        self._g_key = None

    # -- outputs ------------------------------------------------------------------
    @property
    def current_monitor_volts(self) -> np.ndarray:
        """Motor current monitor, V = 10 I / I_max (8.4); 0 V while the +/-15 V that
        powers the servo cards' monitors is off (``SimErrors.panel_15v_off``, ``panel_28v_off``)."""
        if not self.analog_powered:
            return np.zeros(N_AXES)
        return 10.0 * self.current_a / self.i_max

    @property
    def tach_output_volts(self) -> np.ndarray:
        """What the tach filter cards output, the tach voltage the ADC reads (IRSS 3.6.3: an
        RC filter, then a voltage-follower buffer): V_tf, or 0 V while the +/-15 V that
        powers the buffers is off. The RC filter is passive: ``tach_volts`` (V_tf) keeps
        following the tach meanwhile, and the buffer shows it again once powered."""
        if not self.analog_powered:
            return np.zeros(N_AXES)
        return self.tach_volts

    def state(self) -> ArmState:
        """A copy of the true state."""
        return ArmState(self.t_s, self.q.copy(), self.qdot.copy(), self.tach_volts.copy(),
                        self.current_a.copy(), self.current_monitor_volts,
                        self.brake_engaged.copy(), self.contact_force_n.copy(), self.jaw_force_n)

    # -- the gripper's jaw -----------------------------------------------------------------
    @property
    def jaw_force_n(self) -> float:
        """Force between the jaws, N: the object's (or the closed stop's) spring, k x depth."""
        g = self._jaw_axis
        return float(self.k_stop[g] * max(0.0, self._lo[g] - self.q[g]))

    def place_jaw_object(self, width_m: float | None) -> None:
        """Put an object of ``width_m`` between the jaws (None: take it away). It stays where
        it is (held by the world, not by the jaws) and is as stiff as the hard stops.

        :raises ValueError: a width outside the travel, or wider than the jaw is open now
        """
        g = self._jaw_axis
        if width_m is None:
            self.jaw_object_m = None
            self._lo[g] = self.hard_lo[g]
            return
        w = float(width_m)
        if not (math.isfinite(w) and self.hard_lo[g] < w < self.hard_hi[g]):
            raise ValueError(f"a jaw object of {w:g} m does not fit the jaw's travel "
                             f"{self.hard_lo[g]:g}..{self.hard_hi[g]:g} m")
        if self.q[g] < w:
            raise ValueError(f"the jaw is open {self.q[g] * 1e3:.1f} mm, narrower than the "
                             f"{w * 1e3:.1f} mm object: open it first")
        self.jaw_object_m = w
        self._lo[g] = w

    def frames(self) -> np.ndarray:
        """World transforms of DH frames 0..6 at the current pose, shape (7, 4, 4)."""
        return self.kin.frames(self.q)

    def tool_point_m(self) -> np.ndarray:
        """World position of the tool point (frame 6 origin), m."""
        return self.kin.tool_point(self.q)

    def gravity_torque_nm(self, q: Sequence[float] | None = None) -> np.ndarray:
        """Net gravity torque on each axis after the counterbalance, N*m (gripper 0).

        Links: ``(1 - 0.9) tau_grav`` on J1-J5 (J1 and J5: ``fakes.arm_params.
        SHOULDER_YAW_COUNTERBALANCED``), full on the wrist roll; payload: never counterbalanced.
        """
        q = self.q if q is None else np.asarray(q, dtype=float)
        F = self.kin.frames(q)
        g = self.params.gravity_m_s2
        o = F[:N_JOINTS, :3, 3]
        z = F[:N_JOINTS, :3, 2]
        p = np.einsum("kij,kj->ki", F[self._m_frames, :3, :], self._m_com)
        w = self._m_mask @ (self._m_kg[:, None] * p) - (self._m_mask @ self._m_kg)[:, None] * o
        # z . (w x g) with g = (0, 0, -g):
        tau_links = -g * (z[:, 0] * w[:, 1] - z[:, 1] * w[:, 0])
        tau = np.zeros(N_AXES)
        tau[:N_JOINTS] = tau_links * self._counterbalance
        if self.errors.payload_kg:
            wp = self.errors.payload_kg * (F[-1, :3, 3] - o)
            tau[:N_JOINTS] += -g * (z[:, 0] * wp[:, 1] - z[:, 1] * wp[:, 0])
        return tau

    def ft_load(self) -> tuple[np.ndarray, np.ndarray]:
        """What the wrist F/T sensor feels, in the sensor frame (8.1: parallel to frame 6,
        0.20 m from the wrist centre along z6): tool gravity (8.7), payload and contact.

        :returns: (force_n[3], torque_nm[3]), torque about the sensor origin
        """
        F = self.kin.frames(self.q)
        rot = F[-1, :3, :3]
        p = self.params
        force, torque = tool_gravity_wrench(rot, p.tool_mass_kg, p.tool_com_m, p.gravity_m_s2)
        lever = (0.0, 0.0, self._d6 - p.ft_offset_m)  # tool point, sensor coordinates
        if self.errors.payload_kg:
            f2, t2 = point_load_wrench(rot, np.array([0.0, 0.0, -self.errors.payload_kg * p.gravity_m_s2]), lever)
            force, torque = force + f2, torque + t2
        if self.environment.active:
            tool = F[-1, :3, 3]
            v_tool = Kinematics.position_jacobian(F, tool) @ self.qdot[:N_JOINTS]
            fc = self.environment.contact_force_n(tool, v_tool)
            f3, t3 = point_load_wrench(rot, fc, lever)
            force, torque = force + f3, torque + t3
        return force, torque

    # -- dynamics -----------------------------------------------------------------
    def _set_substep(self, h: float) -> None:
        self._h = h
        self._h_over_j = h / self.inertia
        alpha = 1.0 - math.exp(-h / self.params.tau_f_s)
        self._keep_f = 1.0 - alpha  # exact one-pole update for a rate held over the substep
        self._alpha_kw = alpha * self.k_w_true
        self._hj_tpa = self._h_over_j * self.torque_per_amp
        self._inv_denom_free = 1.0 / (1.0 + h * self.viscous / self.inertia)
        self._inv_denom_stop = 1.0 / (1.0 + h * (self.viscous + self.c_stop) / self.inertia)
        self._hj_kstop = self._h_over_j * self.k_stop

    def _gravity_cached(self) -> np.ndarray:
        # Recompute whenever a joint moved by more than GRAVITY_REQUANTUM_RAD since the last time.
        q6 = self.q[:N_JOINTS]
        if self._g_key is None or np.max(np.abs(q6 - self._g_key)) > GRAVITY_REQUANTUM_RAD:
            self._g_key = q6.copy()
            self._g_tau = self.gravity_torque_nm()
        return self._g_tau

    def step(self, dt_s: float, rate_cmd_volts: Sequence[float], current_limit_volts: Sequence[float]) -> None:
        """Advance the arm by ``dt_s`` with the amplifier inputs held constant (DAC ZOH).

        :param dt_s: time step, s (>= 0)
        :param rate_cmd_volts: 7 rate references, V (clipped to +-10 V)
        :param current_limit_volts: 7 current-limit inputs, V (negative -> 0, clipped to 10 V)
        :raises ValueError: on a negative ``dt_s`` or wrongly sized inputs
        """
        if dt_s < 0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        if dt_s == 0:
            return
        p = self.params
        vr = p.dac_range_v
        v_cmd = np.minimum(np.maximum(np.asarray(rate_cmd_volts, dtype=float), -vr), vr)
        v_ilim = np.minimum(np.maximum(np.asarray(current_limit_volts, dtype=float), 0.0), vr)
        if not self.amplifiers_enabled:
            # the amplifier-enable relay is open: no current, and the brake-release card,
            # fed through the same contact, sets the brakes (as a current limit of 0 V)
            v_ilim = np.zeros_like(v_ilim)
        if v_cmd.shape != (N_AXES,) or v_ilim.shape != (N_AXES,):
            raise ValueError(f"need {N_AXES} rate commands and {N_AXES} current limits (SY SP EP WP WY WR GR)")
        # brake release card with hysteresis: engage below 0.3 V, release above 0.5 V
        brake = (v_ilim < p.brake_engage_v) | (self.brake_engaged & (v_ilim <= p.brake_release_v))
        brake &= self.brake_fitted
        i_lim = self.i_max * v_ilim
        i_lim *= 0.1
        if self._faulted:  # a held brake, an amplifier stage off (no current at all), a panel switch off
            brake = brake | self._brake_held
            i_lim *= self._amp_on
        self.brake_engaged = brake
        neg_i_lim = -i_lim

        n_sub = max(1, math.ceil(dt_s / p.max_substep_s - 1e-9))
        h = dt_s / n_sub
        if h != self._h:
            self._set_substep(h)
        cap = (self.coulomb + self.slip * brake) * self._h_over_j  # friction + brake, as a rate
        kv_cmd = self.k_a * v_cmd
        dv_static = self._gravity_cached() * self._h_over_j
        if self._faulted:  # an external load torque, held over the step like gravity
            dv_static = dv_static + self._load_nm * self._h_over_j

        q, v, vtf, cur, acc, tmp = self.q, self.qdot, self.tach_volts, self.current_a, self._tau, self._tmp
        k_a, keep_f, alpha_kw, hj_tpa = self.k_a, self._keep_f, self._alpha_kw, self._hj_tpa
        inv_denom = self._inv_denom_free
        lo, hi = self._lo, self.hard_hi
        # hard stops need per-substep work only near a stop (or for long steps)
        margin = np.abs(v) * dt_s
        margin += 0.01
        near_stop = dt_s > 0.01 or float((np.minimum(q - lo, hi - q) - margin).min()) < 0.0

        contact = self.environment.active
        if contact:
            F = self.kin.frames(q)
            tool0 = F[-1, :3, 3].copy()
            jac = Kinematics.position_jacobian(F, tool0)
            # skip contact for this step when the tool cannot reach any object in it
            reach = 0.01 + 2.0 * float(np.linalg.norm(jac @ v[:N_JOINTS])) * dt_s
            contact = dt_s > 0.01 or self.environment.clearance_m(tool0) <= reach
        if contact:
            jac_hj = jac.T * self._h_over_j[:N_JOINTS, None]
            q0 = q[:N_JOINTS].copy()
            env = self.environment

        for _ in range(n_sub):
            # tach filter card: V_tf <- V_tf + alpha (K_w qdot - V_tf)
            vtf *= keep_f
            np.multiply(alpha_kw, v, out=tmp)
            vtf += tmp
            # amplifier: I = sat(K_a (V_cmd - V_tf), +-I_lim)
            np.multiply(k_a, vtf, out=cur)
            np.subtract(kv_cmd, cur, out=cur)
            np.maximum(cur, neg_i_lim, out=cur)
            np.minimum(cur, i_lim, out=cur)
            # free velocity: v + h/J (tau_m + tau_gravity [+ tau_contact] [+ tau_stop])
            np.multiply(hj_tpa, cur, out=acc)
            acc += dv_static
            acc += v
            if contact:
                fc = env.contact_force_n(tool0 + jac @ (q[:N_JOINTS] - q0), jac @ v[:N_JOINTS])
                acc[:N_JOINTS] += jac_hj @ fc
                self.contact_force_n = fc
            if near_stop:
                # explicit stop spring, implicit stop damping while in the stop
                pen = q - np.minimum(np.maximum(q, lo), hi)
                acc -= self._hj_kstop * pen
                inv_denom = np.where(pen != 0.0, self._inv_denom_stop, self._inv_denom_free)
            # implicit viscous friction and stick-aware Coulomb/brake projection:
            # v = sign(v_free) max(|v_free| - h F / J, 0) / (1 + h b / J)
            np.abs(acc, out=tmp)
            tmp -= cap
            np.maximum(tmp, 0.0, out=tmp)
            np.copysign(tmp, acc, out=v)
            v *= inv_denom
            np.multiply(v, h, out=tmp)
            q += tmp
        if not contact:
            self.contact_force_n = np.zeros(3)
        self.t_s += dt_s


def bench_step(dt_s: float = 1.0 / 320.0, n: int = 2000) -> dict[str, float]:
    """Time ``ArmModel.step`` (free space, moving; and in wall contact). Prints and returns us/step."""
    from fakes.environment import Wall

    results = {}
    cmd = np.array([2.0, 2.0, -2.0, 2.0, 2.0, 2.0, 1.0])
    ilim = np.full(N_AXES, 10.0)
    for label, env in (("free space, all axes moving", None),
                       ("at rest, brakes on", None),
                       ("pressing a wall", Environment([Wall((1.528, 0, 0), (-1, 0, 0))]))):
        arm = ArmModel(environment=env)
        c = np.zeros(N_AXES) if label.startswith("at rest") else cmd
        lim = np.zeros(N_AXES) if label.startswith("at rest") else ilim
        if env is not None:
            c = np.zeros(N_AXES)
            c[1] = -2.0
        for _ in range(50):
            arm.step(dt_s, c, lim)
        t0 = time.perf_counter()
        for _ in range(n):
            arm.step(dt_s, c, lim)
        us = (time.perf_counter() - t0) / n * 1e6
        results[label] = us
        print(f"ArmModel.step({dt_s * 1e3:.3f} ms), {label}: {us:.1f} us")
    return results


if __name__ == "__main__":
    bench_step()
