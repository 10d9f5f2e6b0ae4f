"""Joint supervision: the arm stops when a joint does not do what it was told.

Every servo period (160 Hz) the Servo Control layer hands this module each joint's
resolver angle, tach rate, motor current, the rate it commanded and the current limit
it commanded. Five checks, as a commissioned motion system has them (LinuxCNC's
``FERROR``/``MIN_FERROR``, CiA 402's following-error window and time-out, a drive's
overspeed and feedback checks):

=====================  =================================================================
check                  trips when
=====================  =================================================================
resolver jump          the angle moved further between two samples than the joint can
                       (``max(JUMP_MIN_RAD, JUMP_SPEED_FACTOR x omega_fs x dt)``)
overspeed              the resolver rate exceeds ``OVERSPEED_FACTOR x omega_fs``, or the
                       tach reads at least ``TACH_FULL_SCALE_FRACTION`` of full scale (the
                       ADC clips there: beyond it the tach cannot say how fast)
tach against resolver  sign or magnitude disagree by more than ``TACH_ABS_TOL x omega_fs +
                       TACH_REL_TOL x |rate|`` for ``TACH_TIME_S`` (the resolver's rate
                       through the tach's own filters first: the 10 Hz tach card and the
                       anti-aliasing board's lag, so that the two are compared alike)
stall                  (loop closed) a rate command worth more than ``STALL_RATE_FRACTION x
                       omega_fs`` with the joint still and the motor current at its limit
                       (brake held, jam) or none at all (amplifier off), for ``STALL_TIME_S``
following error        (loop closed) the joint is further than the limit from where the
                       commanded rates should have taken it, for ``ferror_time_s``; the
                       limit is ``ferror_min_rad`` at standstill rising linearly to
                       ``ferror_max_rad`` at full-scale rate (LinuxCNC's MIN_FERROR/FERROR);
                       after only ``RUNAWAY_TIME_S`` while the joint runs away: it moves
                       against the command, faster than the stall's rate and not slowing,
                       with the motor at its current limit pushing the commanded way (a
                       load beyond the motor's torque: no transient looks like that)
=====================  =================================================================

"Where the commanded rates should have taken it" is a reference joint: the nominal closed
loop driven by the same position command ``q_cmd`` as the real one - the servo's own
compensator and rate limit on the reference's error, then the nominal model of the
amplifier's proportional rate loop (pfma-model 8.4: ``J w' = N eta K_t K_a (V_cmd -
V_tach) - b w - F_c sgn w``): its steady rate ``(lambda u - F_c/J) / (lambda + b/J)``
(the wrist roll's viscous friction alone makes it 0.62 of the command), reached through a
first-order lag of ``1/(lambda + b/J)`` plus ``MODEL_DELAY_S``. Gravity is not in the
reference: the real position loop corrects it to a small offset (about a degree on the
wrist yaw), except while the servo saturates, when a joint climbing against gravity falls
behind. So while the real joint moves the way the reference does at no less than
``PULL_FRACTION`` of its speed, the reference is pulled back towards the real joint
(time constant ``PULL_S``): a slow but obedient joint is forgiven, a joint that moves the
wrong way, too slowly or not at all never is.

On any trip the layer drops every current limit at once (brakes on, the amplifiers'
current to 0) with the rates: a joint that does not do what it is told may not stop on a
0 V rate command (a DAC bit stuck, a tach reversed into positive feedback), and waiting
for the safe stop's 0.5 s time-out is what let such a joint run to its hard stop.

:func:`diagnose` then names the most likely physical cause from the last samples, by
comparing the measured motor current and motion with the nominal model's prediction
(the amplifier: ``I = K_a K_w (u - w_tach)`` limited to the current limit; the joint:
torque makes motion). It reads only published inputs and the commands the controller
sent, never the simulator's fault list. Every threshold here is assumed (this project's
choice against the nominal arm model of pfma-model.md 8.2-8.4), named once, and listed in
docs/safety.md.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass

import numpy as np

from pfma.arm import JOINTS, RATE_LOOP_LAMBDA, TACH_TAU_S, JointFacts, anti_alias_delay_s  # noqa: F401

#: the anti-aliasing board's lag on the tach channel (pfma.arm.ANTI_ALIAS_HZ), modelled as
#: one more first-order lag of its group delay on the resolver rate the tach is compared with
AA_TAU_S = anti_alias_delay_s()

DEG = math.pi / 180.0

#: a resolver angle that moves further than this between two samples is a sensor fault
#: (assumed: 2 degrees, well above the 0.14-0.7 degrees a joint moves in a servo period at
#: full-scale rate, and below a 14-bit resolver's bit 10, 22.5 degrees)
JUMP_MIN_RAD = 2.0 * DEG
JUMP_SPEED_FACTOR = 3.0
#: overspeed: the resolver rate beyond this multiple of omega_fs (assumed: 20 % above the
#: full-scale rate; the servo never commands more than 0.6 omega_fs)
OVERSPEED_FACTOR = 1.2
#: overspeed: the tach at this fraction of its full-scale reading (the ADC's +-10 V clips
#: the tach at omega_fs, so it cannot show more)
TACH_FULL_SCALE_FRACTION = 0.98
#: tach against resolver: tolerated disagreement, absolute (fraction of omega_fs: the
#: 14-bit resolver's quantisation makes a 6.25 ms difference rate jitter by about 0.06
#: rad/s before filtering) and relative, and how long it must last (assumed)
TACH_ABS_TOL = 0.15
TACH_REL_TOL = 0.3
TACH_TIME_S = 0.06
#: stall: a rate command whose nominal steady rate (after the rate loop's droop and
#: Coulomb dead band) is above this fraction of omega_fs (above the 0.07 omega_fs droop
#: command that holds the shoulder against gravity) ...
STALL_RATE_FRACTION = 0.15
#: ... with the joint still (its rate below this fraction of omega_fs) and the current at
#: its limit (this fraction of it, or all the amplifier gives for this command: the wrist
#: roll's rate loop cannot reach its limit) or none at all (below this fraction of I_max),
#: for this long (assumed)
STALL_MOTION_FRACTION = 0.03
STALL_CURRENT_FRACTION = 0.9
NO_CURRENT_FRACTION = 0.03
STALL_TIME_S = 0.25
#: following error defaults per joint (assumed): 2 degrees at standstill, 8 at full-scale
#: rate, beyond the limit for 0.1 s
FERROR_MIN_RAD = 2.0 * DEG
FERROR_MAX_RAD = 8.0 * DEG
FERROR_TIME_S = 0.1
#: ... or beyond it for this long while the joint runs away against its command (assumed:
#: four servo periods; at the 10 deg bound a wrist roll pushed 2.5 times past its holding
#: torque ran 11.3 deg on the 0.1 s timer)
RUNAWAY_TIME_S = 0.025
#: the reference joint: lag beyond the rate loop's own (half the tach filter's 15.9 ms and
#: about two frames of I/O delay), and its pull-back towards an obedient joint (assumed)
MODEL_DELAY_S = 0.015
PULL_FRACTION = 0.5
PULL_S = 0.3
#: a gap between two samples longer than this (a halt, a controller stalled by its host)
#: re-primes the checks: the reference restarts where the joint is, the timers at zero
#: (the supervision cannot vouch for what happened in between; assumed: 8 service frames)
GAP_S = 0.025
#: samples kept for the diagnosis, and how many of the newest it averages (50 ms)
HISTORY = 16
DIAG_SAMPLES = 8

#: a joint's brake as the sensors show it (``servo.brake_state``; issue 30 item 3), never
#: from the command alone: SET - its current limit is 0 (the brake engaged) and the joint is
#: still, as a set brake holds it; UNPROVEN - neither shown: the limit is raised but the
#: joint has not yet moved the way it was told since, or it moves while its limit is 0;
#: PROVEN RELEASED - since its limit was raised the joint moved the commanded way at more
#: than STALL_MOTION_FRACTION of omega_fs, which a held brake does not allow. A joint
#: holding its pose after power-up stays UNPROVEN until it first moves (there is no brake
#: sensor: pfma-model 8.4).
BRAKE_SET, BRAKE_UNPROVEN, BRAKE_PROVEN = 0, 1, 2
BRAKE_STATE_NAMES = {BRAKE_SET: "SET", BRAKE_UNPROVEN: "UNPROVEN", BRAKE_PROVEN: "PROVEN RELEASED"}

#: the checks, in the order a sample runs them
CHECKS = ("resolver jump", "overspeed", "tach against resolver", "stall", "following error")
#: the causes :func:`diagnose` can name (index = ``servo.trip_cause``)
CAUSES = (
    "not identified",
    "brake not released (or a jam)",
    "amplifier, PWM stage or current limit off",
    "tach reversed",
    "tach wrong gain",
    "DAC bit or channel fault",
    "resolver bit or loss",
    "unexpected load or collision",
)
CAUSE_UNKNOWN, CAUSE_BRAKE, CAUSE_AMP_OFF, CAUSE_TACH_REVERSED, CAUSE_TACH_GAIN, CAUSE_DAC, CAUSE_RESOLVER, \
    CAUSE_LOAD = range(len(CAUSES))


def amp_gain_a_per_rad_s(jf: JointFacts) -> float:
    """The amplifier's current per rad/s of rate error, K_a K_w = lambda J / (N eta K_t)
    (pfma-model 8.4: K_a = lambda J / (N eta K_t K_w))."""
    return jf.amp_gain_a_per_rad_s


#: the columns of one joint's samples, as the diagnosis reads them (a preallocated ring of
#: floats, HISTORY x 5 per joint: nothing is allocated per sample that outlives it): the
#: commanded rate the amplifier acted on (the previous period's), the tach rate, the
#: resolver rate (difference through a tach-like filter), all rad/s; the motor current and
#: the commanded current limit, A
U, W_TACH, W_RES, I, I_LIM = range(5)


@dataclass(frozen=True)
class Trip:
    """A supervision trip: which joint, which check, the likely cause, one message."""

    joint: int
    check: str
    cause: int
    text: str

    @property
    def cause_name(self) -> str:
        return CAUSES[self.cause]


def _sensor_cause(jf: JointFacts, check: str, wt: float, wr: float, i: float, i_lim: float,
                  i_pred: float) -> tuple[int, str] | None:
    """:func:`diagnose`'s first questions, about the sensors and the amplifier's power: a
    reversed or wrong-gain tach, an amplifier that gives no current; None: none of them."""
    fs = jf.omega_fs_rad_s
    moving = abs(wr) > 0.05 * fs
    if moving and wt * wr < 0 and abs(wt) > 0.05 * fs:
        return CAUSE_TACH_REVERSED, f"tach {wt:+.3f} rad/s against resolver {wr:+.3f} rad/s"
    if check == "tach against resolver":
        return CAUSE_TACH_GAIN, f"tach {wt:+.3f} rad/s, resolver {wr:+.3f} rad/s"
    if i_lim > 0.05 * jf.i_max_a and abs(i_pred) > 0.25 * i_lim and abs(i) < 0.03 * jf.i_max_a:
        return CAUSE_AMP_OFF, f"no motor current ({i:+.2f} A) where the amplifier should give {i_pred:+.2f} A"
    return None


def _motion_cause(check: str, fs: float, u: float, wt: float, wr: float, i: float, i_lim: float, i_pred: float,
                  saturated: bool) -> tuple[int, str]:
    """:func:`diagnose`'s last questions, once the amplifier acts on the command it was
    given: does the motor drive, and does the joint move as that drive should make it."""
    # the amplifier drives as told (the current the model predicts, in the command's direction)
    driving = i * u > 0 and (saturated or abs(i) >= 0.75 * abs(i_pred))
    if driving and abs(wr) < 0.03 * fs:
        return CAUSE_BRAKE, f"the motor drives ({i:+.2f} A, limit {i_lim:.2f}), no motion ({wr:+.3f} rad/s)"
    if driving and (wr * u < 0 or abs(wr) < 0.2 * abs(u)):
        return CAUSE_LOAD, (f"the motor drives ({i:+.2f} A, limit {i_lim:.2f}), joint moving {wr:+.3f} rad/s "
                            f"against a {u:+.3f} rad/s command")
    if check == "overspeed" and wr * u <= 0:
        return CAUSE_LOAD, f"joint driven at {wr:+.3f} rad/s against a {u:+.3f} rad/s command"
    return CAUSE_UNKNOWN, (f"command {u:+.3f} rad/s, tach {wt:+.3f}, resolver {wr:+.3f} rad/s, "
                           f"current {i:+.2f} A (limit {i_lim:.2f})")


def diagnose(jf: JointFacts, check: str, recent: np.ndarray) -> tuple[int, str]:
    """The most likely physical cause of a trip of ``check`` on joint ``jf``, from its
    newest samples (rows of the five columns U ... I_LIM): (a CAUSES index, the evidence
    in words). The questions are asked in a fixed order, the first answer wins: the
    sensors and the amplifier's power (:func:`_sensor_cause`), the DAC, then the motion
    (:func:`_motion_cause`)."""
    if check == "resolver jump":
        return CAUSE_RESOLVER, "the angle jumped further than the joint can move"
    u, wt, wr, i, i_lim = (float(x) for x in recent.mean(axis=0))
    i_lim = max(i_lim, 0.0)
    fs = jf.omega_fs_rad_s
    kaw = amp_gain_a_per_rad_s(jf)
    i_pred = max(-i_lim, min(i_lim, kaw * (u - wt)))
    volts = 10.0 / fs  # rate -> DAC/tach volts
    sensor = _sensor_cause(jf, check, wt, wr, i, i_lim, i_pred)
    if sensor is not None:
        return sensor
    saturated = i_lim > 0 and abs(i) >= 0.8 * i_lim
    u_acted = i / kaw + wt  # the rate command the amplifier's current says it acts on
    if not saturated and abs(u_acted - u) > 0.1 * fs:
        return CAUSE_DAC, (f"the amplifier acts on {u_acted * volts:+.1f} V, commanded {u * volts:+.1f} V "
                           f"({i:+.2f} A at {wt:+.3f} rad/s)")
    return _motion_cause(check, fs, u, wt, wr, i, i_lim, i_pred, saturated)


def _floats(values) -> list[float]:
    """A per-joint parameter as a list of floats."""
    return [float(x) for x in values]


class JointSupervisor:
    """The five checks for the six joints (command-area order, :data:`pfma.arm.JOINTS`).

    :param ferror_min_rad: following-error limit at standstill, per joint
    :param ferror_max_rad: following-error limit at full-scale rate, per joint
    :param ferror_time_s: how long the error must stay beyond the limit, per joint
    :param reference: the reference joints' compensator, an object with ``reset(e0)`` and
        ``step(error, limit) -> rates`` (a second instance of the servo's own, so that the
        reference is driven the same way); None: the pure gain ``kp_per_s`` (one value, or
        one per joint), computed in plain floats
    :param rate_limit_rad_s: the servo's rate limit per joint (the reference saturates there)
    """

    def __init__(self, ferror_min_rad=None, ferror_max_rad=None, ferror_time_s=None,
                 joints: tuple[JointFacts, ...] = JOINTS, reference=None, kp_per_s=8.0,
                 rate_limit_rad_s=None) -> None:
        n = len(joints)
        self.joints = joints
        self._set_ferror_limits(ferror_min_rad, ferror_max_rad, ferror_time_s)
        self.fs = [j.omega_fs_rad_s for j in joints]
        self._set_rate_loop_model()
        self.reference = reference
        self.kp = [float(x) for x in (kp_per_s if isinstance(kp_per_s, (list, tuple, np.ndarray))
                                      else [kp_per_s] * n)]
        self.rate_lim = [float(x) for x in (rate_limit_rad_s if rate_limit_rad_s is not None
                                            else [j.omega_lim_rad_s for j in joints])]
        #: the diagnosis's history: per joint, five columns (U ... I_LIM) of a ring of HISTORY
        #: doubles (array.array: a sample stores numbers, it keeps no float object alive)
        self._h = [[array("d", bytes(8 * HISTORY)) for _ in range(5)] for _ in range(n)]
        self._hi = 0  # the ring's next row
        self._filled = 0
        self._dt = -1.0
        self._rows: tuple = ()
        self.ferror_rad = [0.0] * n  #: the following error of the last sample (model - measured)
        #: each joint's brake as its last live sample showed it (BRAKE_*; kept through a
        #: reset: the last thing the sensors showed)
        self.brake_state = [BRAKE_UNPROVEN] * n
        self._bq: list[float] | None = None  # observe_brakes's last angles and their time
        self._bq_t = 0.0
        self._bq_w = [0.0] * n
        self.reset()

    def _set_ferror_limits(self, ferror_min_rad, ferror_max_rad, ferror_time_s) -> None:
        """The following-error limits per joint (None: the module's defaults), checked."""
        n = len(self.joints)
        self.fe_min = _floats(ferror_min_rad if ferror_min_rad is not None else [FERROR_MIN_RAD] * n)
        self.fe_max = _floats(ferror_max_rad if ferror_max_rad is not None else [FERROR_MAX_RAD] * n)
        self.fe_time = _floats(ferror_time_s if ferror_time_s is not None else [FERROR_TIME_S] * n)
        for i, j in enumerate(self.joints):
            if not 0 < self.fe_min[i] <= self.fe_max[i] or not 0 < self.fe_time[i] <= 2.0:
                raise ValueError(f"{j.name} following-error limits {self.fe_min[i]:g}..{self.fe_max[i]:g} rad over "
                                 f"{self.fe_time[i]:g} s: need 0 < min <= max and 0 < time <= 2 s")

    def _set_rate_loop_model(self) -> None:
        """The nominal rate loop per joint: steady gain, amplifier gain, Coulomb dead band
        (rad/s of command), lag."""
        joints = self.joints
        lam = [j.rate_loop_lambda for j in joints]  # with each card's gain switch
        self._gain = [lk / (lk + j.viscous_nm_s / j.inertia_kg_m2) for lk, j in zip(lam, joints)]
        self._kaw = [amp_gain_a_per_rad_s(j) for j in joints]
        self._dead = [j.coulomb_nm / j.inertia_kg_m2 / lk for lk, j in zip(lam, joints)]
        self._tau = [1.0 / (lk + j.viscous_nm_s / j.inertia_kg_m2) + MODEL_DELAY_S for lk, j in zip(lam, joints)]

    def command_for_rate(self, k: int, rate: float) -> float:
        """The rate command (rad/s) whose nominal steady rate on joint ``k`` is ``rate`` (>= 0):
        the rate loop's droop and Coulomb dead band added back (the stall check's model)."""
        return rate / self._gain[k] + self._dead[k]

    def reset(self) -> None:
        """Forget the past (a new power-up): the next sample only primes."""
        n = len(self.joints)
        self._q: list[float] | None = None
        self._w_res = [0.0] * n
        self._w_aa = [0.0] * n  # the resolver rate through the anti-aliasing lag too
        self._w_m = [0.0] * n
        self._q_model = [0.0] * n
        self._closed = False
        self._q_hold = [0.0] * n
        self._t_tach = [0.0] * n
        self._t_stall = [0.0] * n
        self._t_fe = [0.0] * n
        self._t_run = [0.0] * n
        self._hi = self._filled = 0
        self.ferror_rad = [0.0] * n

    def _constants(self, dt: float) -> None:
        """Per-joint figures of one sample period, computed when the period changes (the
        servo's period is constant; a missed frame changes it for one sample)."""
        self._dt = dt
        self._alpha = 1.0 - math.exp(-dt / TACH_TAU_S)
        self._alpha_aa = 1.0 - math.exp(-dt / AA_TAU_S)
        self._pull = dt / (PULL_S + dt)
        self._rows = tuple(
            (k, jf, fs, max(JUMP_MIN_RAD, JUMP_SPEED_FACTOR * fs * dt), OVERSPEED_FACTOR * fs,
             TACH_FULL_SCALE_FRACTION * fs, TACH_ABS_TOL * fs, self._gain[k], self._dead[k],
             dt / (self._tau[k] + dt), self._kaw[k], self.fe_min[k], self.fe_max[k] - self.fe_min[k],
             STALL_RATE_FRACTION * fs, STALL_MOTION_FRACTION * fs, NO_CURRENT_FRACTION * jf.i_max_a)
            for k, (jf, fs) in enumerate(zip(self.joints, self.fs)))

    def update(self, dt: float, q: list[float], w_tach: list[float], i_meas: list[float], u: list[float],
               i_lim: list[float], closed: bool, q_cmd: list[float] | None = None) -> Trip | None:
        """One servo period: ``dt`` since the last sample (s, from the service frames), the
        angles, tach rates, motor currents, the rates commanded last period (what the
        amplifiers acted on since), the current limits commanded, whether the position
        loop is closed (following error and stall are checked only then) and the position
        command the servo acts on this period (clipped to the soft limits; None: hold).
        Returns the first trip, or None. Plain floats throughout: it runs in the servo's
        period, inside the controller's frame budget."""
        if not self._begin(dt, q, closed, q_cmd):
            return None
        qc, u_ref, trip = self._qc, self._u_ref, None
        q_prev, w_res_l, hist, hi, alpha, pull = self._q, self._w_res, self._h, self._hi, self._alpha, self._pull
        w_aa_l, alpha_aa = self._w_aa, self._alpha_aa
        pi, two_pi = math.pi, 2.0 * math.pi
        brake, t_tach, w_m_l, q_m_l, kp_l, rl_l = \
            self.brake_state, self._t_tach, self._w_m, self._q_model, self.kp, self.rate_lim
        t_stall, t_fe, t_run, fe_time = self._t_stall, self._t_fe, self._t_run, self.fe_time
        for (k, jf, fs, jump, over, tach_top, tach_abs, gain, dead, a_m, kaw, fe_min, fe_span, stall_rate,
             stall_motion, no_current) in self._rows:
            qk = q[k]
            d = (qk - q_prev[k] + pi) % two_pi - pi
            w_was = w_res_l[k]
            w_res = w_res_l[k] = w_was + alpha * (d / dt - w_was)
            w_aa = w_aa_l[k] = w_aa_l[k] + alpha_aa * (w_res - w_aa_l[k])
            wt, uk = w_tach[k], u[k]
            h = hist[k]
            h[0][hi], h[1][hi], h[2][hi], h[3][hi], h[4][hi] = uk, wt, w_res, i_meas[k], i_lim[k]
            if i_lim[k] <= 0.0:
                brake[k] = BRAKE_SET if -stall_motion < w_res < stall_motion else BRAKE_UNPROVEN
            elif brake[k] != BRAKE_PROVEN:
                brake[k] = BRAKE_PROVEN if uk * w_res > 0 and abs(w_res) >= stall_motion else BRAKE_UNPROVEN
            if trip is not None:  # the first trip only; later joints still sample (history, brakes)
                continue
            check = ""
            if d > jump or -d > jump:
                check, detail = "resolver jump", f"{d / DEG:+.1f} deg in {dt * 1e3:.1f} ms > {jump / DEG:.1f}"
            elif abs(w_res) > over or abs(wt) >= tach_top:
                check, detail = "overspeed", (f"resolver {w_res:+.3f} rad/s, tach {wt:+.3f} rad/s, full scale "
                                              f"{fs:g}")
            else:
                aw = abs(wt)
                ar = abs(w_aa)
                if abs(wt - w_aa) > tach_abs + TACH_REL_TOL * (aw if aw > ar else ar):
                    t_tach[k] += dt
                    if t_tach[k] >= TACH_TIME_S:
                        check, detail = "tach against resolver", (f"tach {wt:+.3f} rad/s, resolver {w_aa:+.3f} "
                                                                  f"rad/s for {t_tach[k] * 1e3:.0f} ms")
                elif t_tach[k]:
                    t_tach[k] = 0.0
            if closed:  # the reference model: the nominal rate loop driven by the reference's command
                if u_ref is not None:
                    ur = u_ref[k]
                else:
                    ur = kp_l[k] * (qc[k] - q_m_l[k])
                    lim_r = rl_l[k]
                    ur = lim_r if ur > lim_r else (-lim_r if ur < -lim_r else ur)
                m = abs(ur) - dead
                w_ref = (gain * m if ur > 0 else -gain * m) if m > 0 else 0.0
                wm = w_m_l[k] = w_m_l[k] + a_m * (w_ref - w_m_l[k])
                qm = q_m_l[k] + wm * dt
                if wm * w_res > 0 and abs(w_res) >= PULL_FRACTION * abs(wm):  # obedient: forgive its pace
                    qm -= (qm - qk) * pull
                q_m_l[k] = qm
                e = self.ferror_rad[k] = qm - qk
                if not check:  # stall and following error, with their timers
                    # the real command's nominal steady rate (its droop and dead band included)
                    m = abs(uk) - dead
                    ai = abs(i_meas[k])
                    lk = i_lim[k]
                    ts = t_stall[k] = t_stall[k] + dt if (
                        m > 0 and gain * m > stall_rate and abs(w_res) < stall_motion
                        and (ai >= STALL_CURRENT_FRACTION * lk or ai < no_current
                             or ai >= 0.9 * min(lk, kaw * abs(uk - wt)))) else 0.0
                    if ts >= 0.5 * STALL_TIME_S and brake[k] == BRAKE_PROVEN:
                        brake[k] = BRAKE_UNPROVEN  # told to move and not moving: no longer proven
                    lim = fe_min + fe_span * min(1.0, abs(wm) / fs)
                    beyond = e > lim or -e > lim
                    tf = t_fe[k] = t_fe[k] + dt if beyond else 0.0
                    # running away: against the command, not slowing, the motor at its limit the commanded way
                    tr = t_run[k] = (t_run[k] + dt) * (
                        beyond and uk * w_res < 0 and abs(w_res) > stall_rate and abs(w_res) >= abs(w_was)
                        and uk * i_meas[k] > 0 and ai >= STALL_CURRENT_FRACTION * lk)
                    if tf >= fe_time[k] or tr >= RUNAWAY_TIME_S:
                        check, detail = "following error", f"{e / DEG:+.1f} deg > {lim / DEG:.1f}" + (
                            f" for {tf * 1e3:.0f} ms" if tf >= fe_time[k] else
                            f", running away against the command for {tr * 1e3:.0f} ms")
                    elif ts >= STALL_TIME_S:
                        check, detail = "stall", (f"{uk:+.3f} rad/s commanded, {w_res:+.3f} moving for "
                                                  f"{ts * 1e3:.0f} ms")
            if check:
                cause, evidence = diagnose(jf, check, self.recent(k))
                trip = Trip(k, check, cause, f"{jf.name} {check} ({detail}): likely {CAUSES[cause]}: {evidence}")
        self._q = q
        self._hi = (hi + 1) % HISTORY
        if self._filled < HISTORY:
            self._filled += 1
        return trip

    def _begin(self, dt: float, q: list[float], closed: bool, q_cmd: list[float] | None) -> bool:
        """The start of :meth:`update`: False for a sample that only primes (the first, or
        after a gap; a zero period is skipped). Else the period's constants, the loop's
        closing (the reference starts where the joint is, at rest), the position command
        (``_qc``; None: hold) and the reference's rate commands (``_u_ref``: the servo's own
        compensator when it is not a pure gain (a second instance), else None: the gain
        inline in :meth:`update`, plain floats, no list per period)."""
        if self._q is None or dt <= 0 or dt > GAP_S:
            if self._q is None or dt > GAP_S:
                self.reset()
                self._q = q
            return False
        if dt != self._dt:
            self._constants(dt)
        if closed and not self._closed:
            self._q_model = list(q)
            self._q_hold = list(q)
            self._w_m = [0.0] * len(q)
            self._t_fe = [0.0] * len(q)
            self._t_run = [0.0] * len(q)
            self._t_stall = [0.0] * len(q)
            if self.reference is not None:
                self.reference.reset(0.0)
        self._closed = closed
        self._qc = qc = q_cmd if q_cmd is not None else self._q_hold
        self._u_ref = self.reference.step([c - m for c, m in zip(qc, self._q_model)], self.rate_lim).tolist() \
            if closed and self.reference is not None else None
        return True

    def observe_brakes(self, t_s: float, q: list[float], i_lim: list[float]) -> None:
        """Outside the supervised phases (powered down, the limits at 0): the brake state
        from the resolvers alone, at service time ``t_s`` (s): SET while a joint's limit is 0
        and it is still, UNPROVEN while it moves (a set brake would hold it)."""
        prev, t_prev = self._bq, self._bq_t
        self._bq, self._bq_t = q, t_s
        dt = t_s - t_prev
        if prev is None or dt <= 0 or dt > GAP_S:
            return
        pi, two_pi = math.pi, 2.0 * math.pi
        alpha = 1.0 - math.exp(-dt / TACH_TAU_S)  # filtered as the live checks' resolver rate (a
        wf = self._bq_w                            # one-count flicker is not motion)
        for k, fs in enumerate(self.fs):
            w = wf[k] = wf[k] + alpha * (((q[k] - prev[k] + pi) % two_pi - pi) / dt - wf[k])
            if i_lim[k] <= 0.0:
                self.brake_state[k] = BRAKE_SET if abs(w) < STALL_MOTION_FRACTION * fs else BRAKE_UNPROVEN
            elif self.brake_state[k] != BRAKE_PROVEN:
                self.brake_state[k] = BRAKE_UNPROVEN

    def recent(self, k: int, n: int = DIAG_SAMPLES) -> np.ndarray:
        """Joint ``k``'s newest ``n`` samples (fewer before the ring has filled), oldest
        first, as rows of the five columns U ... I_LIM (the newest is the one being taken)."""
        n = min(n, self._filled + 1)
        idx = [(self._hi - n + 1 + j) % HISTORY for j in range(n)]
        cols = self._h[k]
        return np.array([[cols[c][i] for c in range(5)] for i in idx], dtype=float)
