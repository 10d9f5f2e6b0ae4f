"""The simulated PFMA behind the fake rack: DAC fake -> amplifiers + arm -> RTD/ADC fakes.

``SimulatedRack`` owns a :class:`fakes.rack.FakeRack` built from the rack configuration,
an :class:`fakes.arm.ArmModel` and its :class:`fakes.environment.Environment`. Each
``step(dt_s)`` reads the DAC fake's field voltages (0 V while its outputs are
disconnected), integrates the arm and writes what the sensors would show through the
boards' physical-side hooks:

- resolver angles -> RTD fakes (``<joint>_angle`` signals), wrapped to 0..2 pi:
  ``reading = wrap(q + resolver_offset_rad)`` (resolver zero = DH zero + offset, 0 nominal);
- filtered tach volts V_tf, as the tach filter card's buffer outputs it
  (``ArmModel.tach_output_volts``: 0 V while the servo chassis' +/-15 V is off) -> ADC
  ``<joint>_rate`` (``shoulder_roll_rate`` stays 0 V: the shoulder roll is indexed by hand);
- motor current monitor 10 I / I_max (0 V without the +/-15 V) -> ADC ``<joint>_motor_current``;
- CAE hand-controller volts (``set_cae``) -> ADC ``cae_*``.

The tach, motor-current and CAE axis channels pass through the anti-aliasing filter board
on their way to the A/D (IRSS 3.4.2: four-pole low-pass filters, ``fakes/anti_alias.py``;
corner ``ArmParams.anti_alias_hz``, assumed): their readings lag the signals by about
10 ms. The filters advance in :meth:`SimulatedRack.step` only; a hand-controller voltage
set between steps reaches the A/D through them over the following steps.

Every channel is found by signal name in the rack configuration; nothing here knows a
channel number. The drivers are not used: this module only talks to the fakes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from drivers.rtd.registers import VMIVME4940
from fakes.anti_alias import AntiAliasBank
from fakes.arm import ArmModel, ArmState
from fakes.arm_params import AXES, N_JOINTS, SimErrors
from fakes.environment import Environment
from fakes.rack import FakeRack
from pfma.clock import Clock
from pfma.rack import RackConfig, load_rack

#: ADC signals of the CAE rate hand controller, in ``set_cae`` order (rack config, IRSS 3.4.2).
CAE_AXIS_SIGNALS = ("cae_up_down", "cae_forward_backward", "cae_right_left", "cae_yaw", "cae_pitch", "cae_roll")
CAE_DISCRETE_SIGNALS = ("cae_discrete_1", "cae_discrete_2", "cae_discrete_3")
#: Voltage of a closed CAE discrete given as a bool (assumed: TTL-level switch to +5 V).
CAE_DISCRETE_HIGH_V = 5.0
#: Joints whose monitors read 0 V: the manually indexed shoulder roll (no servo, no motor).
IDLE_JOINTS = ("shoulder_roll",)

_TWO_PI = 2.0 * math.pi
#: one resolver count (drivers/rtd: the ANGLE word's LSB)
_RESOLVER_LSB_RAD = float(VMIVME4940.constants["lsb_rad"])


class _AdcBoardMap:
    """What the simulator drives on one ADC board."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.volts = np.zeros(0)  # set when the board's channel count is known
        self.rate_ch: list[int] = []
        self.rate_axis: list[int] = []
        self.cur_ch: list[int] = []
        self.cur_axis: list[int] = []
        self.gain = np.zeros(0)
        self.offset = np.zeros(0)


class SimulatedRack:
    """A fake rack with the simulated arm wired to it.

    :param rack: rack configuration (default: ``pfma/rack_default.toml``)
    :param clock: clock shared by the fake boards (default: a new ``SimClock``)
    :param fake_rack: an existing fake rack to wire (default: built from ``rack``)
    :param arm: an existing arm model (default: a new ``ArmModel`` at the ready pose)
    :param environment: contact objects (default: free space; ignored when ``arm`` is given)
    :param errors: known truth errors (resolver offsets, tach scale, ADC/DAC gain and
        offset per signal, payload); default all zero
    :param shoulder_roll_rad: where the arm's manually indexed shoulder roll is pinned
        (pfma-model 8.1; ignored when ``arm`` is given): it tilts the arm under gravity and
        moves the tool in the world. No sensor reports it (``shoulder_roll_rate`` stays 0 V)
    :raises KeyError: when the rack configuration lacks a signal the arm needs
    """

    def __init__(self, rack: RackConfig | None = None, *, clock: Clock | None = None,
                 fake_rack: FakeRack | None = None, arm: ArmModel | None = None,
                 environment: Environment | None = None, errors: SimErrors | None = None,
                 shoulder_roll_rad: float = 0.0) -> None:
        self.config = rack if rack is not None else load_rack()
        self.fake_rack = fake_rack if fake_rack is not None else FakeRack.from_config(self.config, clock=clock)
        self.clock = self.fake_rack.clock
        self.errors = errors if errors is not None else SimErrors()
        self.arm = arm if arm is not None else ArmModel(environment=environment, errors=self.errors,
                                                        shoulder_roll_rad=shoulder_roll_rad)
        self.environment = self.arm.environment
        self._ft_push = None
        #: the amplifier-enable charge-pump relay (``fakes.mvme410.ChargePumpRelay``) when the
        #: rack file names one (``[amplifier_enable]``); None: the amplifiers are always enabled
        self.relay = None
        amp = self.config.amplifier_enable
        if amp is not None:
            self.relay = self.fake_rack[amp.board].attach_charge_pump(amp.port, amp.bit)
        self._wire()
        self.set_errors(self.errors)
        self._cae_axes = np.zeros(len(CAE_AXIS_SIGNALS))
        self._cae_discretes = np.zeros(len(CAE_DISCRETE_SIGNALS))
        #: the anti-aliasing filters of the tach (7), motor-current (7) and CAE axis (6) channels
        self.anti_alias = AntiAliasBank(2 * len(AXES) + len(CAE_AXIS_SIGNALS), self.arm.params.anti_alias_hz)
        self.settle_filters()

    def settle_filters(self) -> None:
        """Put the anti-aliasing filters at rest on what their inputs show now (at
        construction, and after a test or a calibration has placed the arm)."""
        self.anti_alias.settle(self._filter_inputs())
        self._write_sensors()

    def _filter_inputs(self) -> np.ndarray:
        """What enters the anti-aliasing board: tach volts, current-monitor volts, CAE axes."""
        arm = self.arm
        return np.concatenate((arm.tach_output_volts, arm.current_monitor_volts, self._cae_axes))

    # -- wiring -----------------------------------------------------------------------
    def _where(self, signal: str) -> tuple[str, int]:
        c = self.config.channel(signal)
        return c.board, c.channel

    def _role(self, joint: str, quantity: str) -> tuple[str, int]:
        c = self.config.joint_channel(joint, quantity)
        return c.board, c.channel

    def _wire(self) -> None:
        """Look up every channel the simulator touches: a joint's by its role (the rack's
        channel keys joint, quantity), the hand controller's by signal name."""
        command = {a.joint: "gripper_command" if a.name == "GR" else "rate_command" for a in AXES}
        self.command = [self._role(a.joint, command[a.joint]) for a in AXES]
        self.current_limit = [self._role(a.joint, "current_limit") for a in AXES]
        self.angle = {i: self._role(a.joint, "angle") for i, a in enumerate(AXES) if a.has_angle}
        self.rate = [self._role(a.joint, "rate") for a in AXES]
        self.motor_current = [self._role(a.joint, "motor_current") for a in AXES]
        self.cae_axes = [self._where(s) for s in CAE_AXIS_SIGNALS]
        self.cae_discretes = [self._where(s) for s in CAE_DISCRETE_SIGNALS]
        self.idle = [(c.board, c.channel) for j in IDLE_JOINTS for q in ("rate", "motor_current")
                     if (c := self.config.find(j, q)) is not None]
        self._adc: dict[str, _AdcBoardMap] = {}
        for role, chans in (("rate", self.rate), ("cur", self.motor_current)):
            for axis, (board, ch) in enumerate(chans):
                m = self._adc_board(board)
                getattr(m, f"{role}_ch").append(ch)
                getattr(m, f"{role}_axis").append(axis)
        for board, _ in self.cae_axes + self.cae_discretes + self.idle:
            self._adc_board(board)
        for m in self._adc.values():
            m.rate_ch, m.rate_axis = np.array(m.rate_ch, dtype=int), np.array(m.rate_axis, dtype=int)
            m.cur_ch, m.cur_axis = np.array(m.cur_ch, dtype=int), np.array(m.cur_axis, dtype=int)
        self._dac_boards = sorted({b for b, _ in self.command + self.current_limit})

    def _adc_board(self, name: str) -> _AdcBoardMap:
        if name not in self._adc:
            m = _AdcBoardMap(name)
            m.volts = np.array(self.fake_rack[name].input_volts, dtype=float)
            m.gain, m.offset = np.ones(len(m.volts)), np.zeros(len(m.volts))
            self._adc[name] = m
        return self._adc[name]

    # -- truth errors -------------------------------------------------------------------
    def set_errors(self, errors: SimErrors) -> None:
        """Install known truth errors (see :class:`fakes.arm_params.SimErrors`).

        :raises KeyError: for an ADC/DAC error on a signal the rack does not have
        :raises ValueError: for an ADC error on a non-ADC signal (or DAC likewise)
        """
        self.errors = errors
        self.arm.set_errors(errors)
        self._ft_offset = np.asarray(errors.ft_offset, dtype=float)
        self._ft_drift = np.asarray(errors.ft_drift_per_s, dtype=float)
        self._resolver_offset = np.asarray(errors.resolver_offset_rad, dtype=float)
        self._resolver_noise_rad = errors.resolver_noise_counts * _RESOLVER_LSB_RAD
        self._noise = np.random.default_rng(errors.noise_seed)
        for k, board in enumerate(sorted(self._adc)):
            self.fake_rack[board].noise_counts = errors.adc_noise_counts
            self.fake_rack[board].seed_noise(errors.noise_seed * 1000 + k)
        for m in self._adc.values():
            n = len(m.volts)
            m.gain, m.offset = np.ones(n), np.zeros(n)
        for sig, g in errors.adc_gain_error.items():
            board, ch = self._where_on(sig, "adc")
            self._adc_board(board).gain[ch] = 1.0 + g
        for sig, off in errors.adc_offset_v.items():
            board, ch = self._where_on(sig, "adc")
            self._adc_board(board).offset[ch] = off
        self._dac_gain = {}
        self._dac_offset = {}
        for sig, g in errors.dac_gain_error.items():
            self._dac_gain[self._where_on(sig, "dac")] = 1.0 + g
        for sig, off in errors.dac_offset_v.items():
            self._dac_offset[self._where_on(sig, "dac")] = off

    def _where_on(self, signal: str, device: str) -> tuple[str, int]:
        c = self.config.channel(signal)
        if c.device != device:
            raise ValueError(f"signal {signal!r} is on {c.device} board {c.board} channel {c.channel} "
                             f"(A16 0x{c.address:04X}), not on an {device} board")
        return c.board, c.channel

    # -- physical inputs ------------------------------------------------------------------
    def set_cae(self, axes_volts: Sequence[float], discretes: Sequence[bool | float] = (False, False, False)) -> None:
        """Hold the CAE hand controller: six axis voltages (up/down, forward/backward,
        right/left, yaw, pitch, roll; +-10 V full deflection, pfma-model.md 8.5) and three
        discretes (bool -> 5 V / 0 V, or a voltage).

        :raises ValueError: on the wrong number of values
        """
        axes = np.asarray(axes_volts, dtype=float)
        if axes.shape != (len(CAE_AXIS_SIGNALS),):
            raise ValueError(f"set_cae needs {len(CAE_AXIS_SIGNALS)} axis voltages "
                             f"({', '.join(CAE_AXIS_SIGNALS)}), got shape {axes.shape}")
        if len(discretes) != len(CAE_DISCRETE_SIGNALS):
            raise ValueError(f"set_cae needs {len(CAE_DISCRETE_SIGNALS)} discretes, got {len(discretes)}")
        self._cae_axes = axes
        self._cae_discretes = np.array([(CAE_DISCRETE_HIGH_V if d else 0.0) if isinstance(d, bool) else float(d)
                                        for d in discretes])
        self._write_sensors()

    def hold_adc_volts(self, signal: str, volts: float) -> None:
        """Hold any other ADC input (spares, test signals) at ``volts``. The simulator owns
        every input of its ADC boards, so set them here, not on the board fake.

        :raises ValueError: for a signal the simulator drives itself or one not on an ADC
        """
        board, ch = self._where_on(signal, "adc")
        m = self._adc_board(board)
        driven = set(m.rate_ch.tolist()) | set(m.cur_ch.tolist()) | {
            c for b, c in self.cae_axes + self.cae_discretes + self.idle if b == board}
        if ch in driven:
            raise ValueError(f"ADC signal {signal!r} (board {board} channel {ch}) is driven by the simulator")
        m.volts[ch] = float(volts)
        self._write_sensors()

    def attach_ft(self, fake) -> None:
        """Feed the arm's F/T load to an F/T fake: sets its ``load_fn`` if it has one,
        otherwise calls its ``set_load(force_n, torque_nm)`` after every step."""
        if hasattr(fake, "load_fn"):
            fake.load_fn = self.ft_reading
            self._ft_push = None
        elif hasattr(fake, "set_load"):
            self._ft_push = fake
            fake.set_load(*self.ft_reading(self.clock.now()))
        else:
            raise TypeError(f"{type(fake).__name__} has neither load_fn nor set_load")

    # -- simulation -----------------------------------------------------------------------
    def amplifier_inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """(rate command volts[7], current limit volts[7]) as the amplifiers see them now."""
        dac = {b: self.fake_rack[b].output_volts_all() for b in self._dac_boards}
        v_cmd = np.array([dac[b][ch] for b, ch in self.command])
        v_ilim = np.array([dac[b][ch] for b, ch in self.current_limit])
        if self._dac_gain or self._dac_offset:  # only while the board drives the field
            live = {b: self.fake_rack[b].outputs_connected for b in self._dac_boards}
            for arr, chans in ((v_cmd, self.command), (v_ilim, self.current_limit)):
                for i, key in enumerate(chans):
                    if live[key[0]]:
                        arr[i] = arr[i] * self._dac_gain.get(key, 1.0) + self._dac_offset.get(key, 0.0)
        return v_cmd, v_ilim

    def step(self, dt_s: float, *, boards: bool = True) -> None:
        """Advance the world by ``dt_s``: amplifiers + arm, then every fake board's physical
        side (``FakeRack.step``), then the sensor outputs. Does not move the clock.

        :param boards: also step the fake boards; pass False when the clock has already
            moved to the new time (boards that follow the clock catch up by themselves,
            and stepping them too would run them ``dt_s`` ahead of it)
        """
        v_cmd, v_ilim = self.amplifier_inputs()
        if self.relay is not None:
            self.arm.amplifiers_enabled = self.relay.energized()
        self.arm.step(dt_s, v_cmd, v_ilim)
        if boards:
            self.fake_rack.step(dt_s)
        self.anti_alias.step(dt_s, self._filter_inputs())
        self._write_sensors()
        if self._ft_push is not None:
            self._ft_push.set_load(*self.ft_reading(self.clock.now()))

    def advance(self, dt_s: float) -> None:
        """``step(dt_s)`` and move the clock by ``dt_s`` (single-step mode, tests)."""
        self.step(dt_s)
        self.clock.advance(dt_s)

    def _write_sensors(self) -> None:
        arm = self.arm
        q = arm.q
        at = self._resolver_offset  # the perfect rack's resolvers read no noise: nothing drawn
        if self._resolver_noise_rad:
            at = at + self._noise.normal(0.0, self._resolver_noise_rad, len(at))
        for axis, (board, ch) in self.angle.items():
            self.fake_rack[board].set_angle_rad(ch, (q[axis] + at[axis]) % _TWO_PI)
        # through the anti-aliasing board: tach (0 V without the +/-15 V), current monitor, CAE
        out = self.anti_alias.output() if self.anti_alias.corner_hz else self._filter_inputs()
        n = len(AXES)
        tach, imon, cae = out[:n], out[n:2 * n], out[2 * n:]
        for m in self._adc.values():
            m.volts[m.rate_ch] = tach[m.rate_axis]
            m.volts[m.cur_ch] = imon[m.cur_axis]
        for (board, ch), v in zip(self.cae_axes, cae):
            self._adc[board].volts[ch] = v
        for (board, ch), v in zip(self.cae_discretes, self._cae_discretes):
            self._adc[board].volts[ch] = v
        for board, ch in self.idle:
            self._adc[board].volts[ch] = 0.0
        for m in self._adc.values():
            self.fake_rack[m.name].set_inputs_volts(m.volts * m.gain + m.offset)

    # -- truth ----------------------------------------------------------------------------
    def true_state(self) -> ArmState:
        """The arm's true state (for tests and calibration truth)."""
        return self.arm.state()

    def ft_bias(self, t_s: float) -> np.ndarray:
        """The F/T transducer's own bias at ``t_s`` (``SimErrors.ft_offset`` drifting by
        ``ft_drift_per_s``), six values in sensor axes: N, N*m."""
        return self._ft_offset + t_s * self._ft_drift

    def ft_reading(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """What the F/T transducer puts out at ``t_s``: the arm's load (:meth:`ft_load`) plus
        its own bias (:meth:`ft_bias`)."""
        f, t = self.arm.ft_load()
        b = self.ft_bias(t_s)
        return f + b[:3], t + b[3:]

    def ft_load(self) -> tuple[np.ndarray, np.ndarray]:
        """F/T load in the sensor frame, see :meth:`ArmModel.ft_load`."""
        return self.arm.ft_load()

    def resolver_angles_rad(self) -> np.ndarray:
        """What the six resolvers are set to (0..2 pi), in axis order SY..WR."""
        return (self.arm.q[:N_JOINTS] + self._resolver_offset) % _TWO_PI


__all__ = ["SimulatedRack", "CAE_AXIS_SIGNALS", "CAE_DISCRETE_SIGNALS"]
