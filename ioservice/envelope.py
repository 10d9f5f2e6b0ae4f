"""The service's motion envelope (issue 28 item 4): the last line of defence, whatever the
controller does. Limits from the rack file's ``[envelope]`` (:mod:`pfma.envelope`).

Every frame, on the engineering rate commands before they are converted for the DAC
(only while the outputs are live):

- **slew**: a rate command may change by at most ``slew_rad_s2 x dt`` from the one driven
  the frame before; beyond, it is saturated there (``dac_status`` DAC_SLEWED). Going to 0 is
  never slowed (a stop is always obeyed at once).
- **braking distance**: a joint within ``|u| t_react + u^2 / (2 brake_rad_s2)`` (u: the
  requested rate) of the point ``ENVELOPE_MARGIN_RAD`` beyond its soft limit has its rate
  *toward* the limit driven at 0 (``dac_status`` DAC_ENVELOPE), and keeps it at 0 while the
  request points that way; rates away from the limit are obeyed. The position is the
  resolver angle the service itself published last, unwrapped around the joint's centre.
- **overspeed**: a joint's resolver rate (two successive samples, so that one resolver
  glitch is the controller's "resolver jump", not an overspeed) beyond ``overspeed_factor x
  omega_fs``, or its tach at ``TACH_FULL_SCALE_FRACTION`` of full scale, trips the service
  (FAULT: every channel 0 V, brakes set), naming joint and figure.

Each episode is counted and named once: an envelope hold when it starts, a slew
saturation once it has lasted ``SLEW_NAME_S`` (a move's start ramps through the limit for a
few frames and is only counted).
"""

from __future__ import annotations

import math

from bit3.layout import DAC_ENVELOPE, DAC_SLEWED, MessageCode, Severity
from pfma.arm import JOINTS, JointFacts
from pfma.envelope import Envelope, JointEnvelope

#: the point the braking distance protects lies this far beyond the soft limit (assumed:
#: half the controller's 1 degree soft-limit fault margin)
ENVELOPE_MARGIN_RAD = math.radians(0.5)
#: reaction time in the braking distance: the DAC's frame, the rate loop's 25 ms (assumed)
T_REACT_S = 0.03
#: the tach reads at most omega_fs (the ADC clips at 10 V): at this fraction it is overspeed
TACH_FULL_SCALE_FRACTION = 0.98
#: a slew saturation episode is named once it has lasted this long (assumed: the servo's
#: own steps, a move's start or reversal, ramp through the limit in at most 40 ms; a
#: command that keeps demanding more than the limit, such as a writer flipping the rate
#: every frame, is named); every episode is counted
SLEW_NAME_S = 0.1
#: message codes (the service's queue)
CODE_SLEW, CODE_ENVELOPE, CODE_OVERSPEED = MessageCode.SLEW, MessageCode.ENVELOPE, MessageCode.OVERSPEED
_TWO_PI = 2.0 * math.pi


class ServiceEnvelope:
    """The envelope of the joints the service drives.

    :param env: the rack's envelope
    :param joints: per joint (in the DAC task's rate-channel order): (name, DAC channel,
        resolver slot in ``rtd_angle_rad``, tach slot in ``adc_value``)
    :param post: callable(severity, code, text)
    """

    def __init__(self, env: Envelope, joints: list[tuple[str, int, int, int]], post) -> None:
        facts = {j.name: j for j in JOINTS}
        rows: list[tuple[str, int, int, int, JointEnvelope, JointFacts]] = []
        for name, ch, rs, ts in joints:
            je, jf = env.of(name), facts.get(name)
            if je is not None and jf is not None:  # a joint the nominal arm does not know has no envelope
                rows.append((name, ch, rs, ts, je, jf))
        self.names = [r[0] for r in rows]
        self.ch = [r[1] for r in rows]
        self.rtd_slot = [r[2] for r in rows]
        self.tach_slot = [r[3] for r in rows]
        self.lo = [r[4].soft_lo_rad - ENVELOPE_MARGIN_RAD for r in rows]
        self.hi = [r[4].soft_hi_rad + ENVELOPE_MARGIN_RAD for r in rows]
        self.two_a = [2.0 * r[4].brake_rad_s2 for r in rows]
        self.slew = [r[4].slew_rad_s2 for r in rows]
        self.centre = [r[5].centre_rad for r in rows]
        self.overspeed = [env.overspeed_factor * r[5].omega_fs_rad_s for r in rows]
        self.tach_top = [TACH_FULL_SCALE_FRACTION * r[5].omega_fs_rad_s for r in rows]
        self.factor = env.overspeed_factor
        self.post = post
        n = len(rows)
        self.q = [0.0] * n  #: unwrapped resolver angle per joint (the newest sample)
        self.last = [0.0] * n  #: the rate driven last frame per joint
        self.slewed = [False] * n  # in a saturation episode
        self.held = [False] * n  # in an envelope episode
        self.slew_episodes = 0  #: counted saturation episodes (all joints)
        self.envelope_episodes = 0
        self._t_rtd: float | None = None  # time of the resolver sample last looked at
        self._fast = [0] * n
        self._sat_run = [0.0] * n  # how long the current saturation episode has lasted
        self._named = [False] * n
        self._dir = [0] * n  # the direction of the last nonzero request
        #: per joint, what the frame's fast path needs, in one tuple
        self._rows = tuple(zip(range(n), self.ch, self.slew, self.hi, self.lo, [1.0 / a for a in self.two_a]))  # successive resolver samples beyond the overspeed rate
        self._q_ok = False

    def reset(self) -> None:
        """Outputs went safe: the next live frame starts from 0 rates."""
        for k in range(len(self.last)):
            self.last[k] = 0.0

    def sample(self, angles, tach, t_rtd: float) -> str | None:
        """Note the newest inputs; returns the overspeed trip reason, or None."""
        if t_rtd == self._t_rtd:
            return None  # no new resolver/ADC sample since the last frame (160 Hz of 320)
        reason = None
        dt = t_rtd - self._t_rtd if self._t_rtd is not None else 0.0
        self._t_rtd = t_rtd
        q = self.q
        angles = angles.tolist()  # plain floats: cheaper to index than numpy scalars
        tach = tach.tolist()
        for k, slot in enumerate(self.rtd_slot):
            c = self.centre[k]
            new = c + (angles[slot] - c + math.pi) % _TWO_PI - math.pi
            if self._q_ok and dt > 0:
                rate = (new - q[k]) / dt
                if abs(rate) > self.overspeed[k]:
                    self._fast[k] += 1
                    if self._fast[k] >= 2 and reason is None:
                        reason = (f"overspeed {self.names[k]}: resolver {rate:+.2f} rad/s > {self.overspeed[k]:.2f} "
                                  f"({self.factor:g} x full scale)")
                else:
                    self._fast[k] = 0
            q[k] = new
        self._q_ok = True
        if reason is None:
            for k, slot in enumerate(self.tach_slot):
                w = tach[slot]
                if abs(w) >= self.tach_top[k]:
                    reason = (f"overspeed {self.names[k]}: tach {w:+.2f} rad/s at full scale "
                              f"({self.tach_top[k]:.2f})")
                    break
        return reason

    def apply(self, eng: list[float], dt: float, status: list[int]) -> None:
        """Slew and braking distance on the rate commands ``eng`` (in place); sets the
        channels' ``status`` bits. A joint in no episode whose request needs neither costs a
        few float operations (the service's frame budget); episodes take :meth:`_episode`."""
        last, q, held, slewed = self.last, self.q, self.held, self.slewed
        for k, ch, slew, hi, lo, inv2a in self._rows:
            r = eng[ch]
            if r == 0.0:  # a stop is obeyed at once and ends any episode
                if held[k] or slewed[k]:
                    self._episode(k, ch, 0.0, 0.0, False, False, dt, status)
                last[k] = 0.0
                continue
            prev = last[k]
            step = slew * dt
            u, sat = r, False
            if r > prev + step:
                u, sat = prev + step, True
            elif r < prev - step:
                u, sat = prev - step, True
            # the braking distance of the *requested* rate (what the joint runs at once the
            # slew lets it); an episode holds while the request keeps pointing at the limit
            if r > 0.0:
                hold = hi - q[k] <= r * (T_REACT_S + r * inv2a) or (held[k] and self._dir[k] > 0)
            else:
                hold = q[k] - lo <= -r * (T_REACT_S - r * inv2a) or (held[k] and self._dir[k] < 0)
            if sat or hold or slewed[k] or held[k]:
                u = self._episode(k, ch, r, u, sat, hold, dt, status)
            eng[ch] = u
            last[k] = u

    def _episode(self, k: int, ch: int, r: float, u: float, sat: bool, hold: bool, dt: float,
                 status: list[int]) -> float:
        """The bookkeeping of a saturation or hold (starts, names, ends); returns the rate."""
        prev = self.last[k]
        if sat:
            run = self._sat_run[k] = self._sat_run[k] + dt
            if not self.slewed[k]:
                self.slewed[k] = True
                self.slew_episodes += 1
                self._named[k] = False
            if run >= SLEW_NAME_S and not self._named[k]:
                self._named[k] = True
                self.post(Severity.WARNING, CODE_SLEW,
                          f"slew limit: {self.names[k]} command {r:+.3f} rad/s after {prev:+.3f}: "
                          f"saturated at {self.slew[k]:g} rad/s^2 for {run * 1e3:.0f} ms")
        elif self.slewed[k]:
            self.slewed[k] = False
            self._sat_run[k] = 0.0
        if r != 0.0:
            self._dir[k] = 1 if r > 0.0 else -1
        if hold != self.held[k]:
            self.held[k] = hold
            if hold:
                self.envelope_episodes += 1
                q = self.q[k]
                lim = self.hi[k] if r > 0 else self.lo[k]
                self.post(Severity.WARNING, CODE_ENVELOPE,
                          f"envelope: {self.names[k]} at {math.degrees(q):.1f} deg, "
                          f"{abs(math.degrees(lim - q)):.1f} deg from its soft limit: rate toward it 0 V")
        if hold:
            status[ch] |= DAC_ENVELOPE
            return 0.0
        if sat:
            status[ch] |= DAC_SLEWED
        return u
