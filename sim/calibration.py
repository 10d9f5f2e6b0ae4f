"""The simulated rack for calibration: an in-process rig and an operator that acts.

:class:`SimOperator` plays the person at the rack: it sets reference voltages on ADC
inputs, moves joints to their index marks, releases and deflects the CAE stick,
removes and mounts the tool, applies known loads and poses the wrist. Its truth (the
stick's real null and full-deflection voltages, the F/T sensor's real coupling and
offset) is what the procedures must find; the rack's own truth errors (ADC/DAC gain
and offset, resolver offsets, tach scale, payload) are set on the simulated rack with
``world.sim.set_errors(SimErrors(...))``.

:class:`CalibrationRig` is the simulated-time rig ``pfma calibrate --rack fake`` runs on
(``sim.rig.SimRig`` with the calibration passed to the service).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from drivers.crl.cae import CAE_AXES
from fakes.sim_rack import CAE_AXIS_SIGNALS, CAE_DISCRETE_SIGNALS
from fakes.world import FakeWorld
from bit3.client import Client
from sim.rig import SimRig as _BaseSimRig

#: CAE axis name (x, y, ...) -> its ADC signal
CAE_SIGNAL_OF = {axis: sig for sig, axis, _ in CAE_AXES}


@dataclass
class StickTruth:
    """The real CAE stick, per axis name (x, y, z, roll, pitch, yaw), volts at the ADC."""

    centre_v: dict[str, float] = field(default_factory=lambda: {a: 0.0 for a in CAE_SIGNAL_OF})
    plus_v: dict[str, float] = field(default_factory=lambda: {a: 10.0 for a in CAE_SIGNAL_OF})
    minus_v: dict[str, float] = field(default_factory=lambda: {a: -10.0 for a in CAE_SIGNAL_OF})
    #: how far from the null the spring returns the stick, release k: rest_scatter_v * pattern[k]
    rest_scatter_v: float = 0.0
    pattern: tuple[float, ...] = (0.0, 1.0, -1.0, 0.5, -0.5, 0.8, -0.8)

    def rest(self, k: int) -> dict[str, float]:
        s = self.rest_scatter_v * self.pattern[k % len(self.pattern)]
        return {a: c + s for a, c in self.centre_v.items()}


class SensorTruth:
    """The real F/T sensor: output = coupling @ load + offset (N, N*m) + the rack's
    ``SimErrors`` F/T bias and its drift (``SimulatedRack.ft_bias``), then the
    controller's nominal counts per unit. Loads: the arm's tool (when mounted) plus a
    fixture load (calibration rig) in sensor axes."""

    def __init__(self, world: FakeWorld, coupling=None, offset=None) -> None:
        self.world = world
        self.coupling = np.eye(6) if coupling is None else np.asarray(coupling, dtype=float)
        self.offset = np.zeros(6) if offset is None else np.asarray(offset, dtype=float)
        self.tool_on = True
        self.fixture = np.zeros(6)
        world.ft.load_fn = self.load

    def load(self, t_s: float):
        w = np.zeros(6)
        if self.tool_on:
            f, t = self.world.sim.ft_load()
            w[:3], w[3:] = f, t
        out = self.coupling @ (w + self.fixture) + self.offset + self.world.sim.ft_bias(t_s)
        return tuple(out[:3]), tuple(out[3:])


class SimOperator:
    """Acts on the simulated rack for each prompt a procedure gives (see module doc)."""

    def __init__(self, world: FakeWorld, stick: StickTruth | None = None,
                 sensor: SensorTruth | None = None, out=None) -> None:
        self.world = world
        self.stick = stick or StickTruth()
        self.sensor = sensor
        self.out = out
        self.log: list[tuple[str, dict]] = []
        self._cae = np.array([self.stick.centre_v[axis] for _, axis, _ in CAE_AXES])
        self._disc = [False, False, False]
        self._rest_k = 0
        self.world.set_cae(self._cae, self._disc)

    def show(self, text: str) -> None:
        if self.out is not None:
            print(text, file=self.out)

    def _set_cae(self) -> None:
        self.world.set_cae(self._cae.copy(), list(self._disc))

    def prompt(self, step: str, text: str, **p: Any) -> float | None:
        self.log.append((step, p))
        self.show(f"  >>> {text}  [simulated operator: {step}]")
        act = self._ACTIONS.get(step)
        if act is not None:
            act(self, step, p)
        return None

    def _centred_cae(self) -> np.ndarray:
        return np.array([self.stick.centre_v[axis] for _, axis, _ in CAE_AXES])

    def _set_arm_q(self, index: Any, value: Any) -> None:
        sim = self.world.sim
        q = sim.arm.q.copy()
        q[index] = value
        sim.arm.set_state(q=q, qdot=np.zeros_like(q))

    def _adc_reference(self, step: str, p: dict) -> None:
        for sig in p["signals"]:
            if sig in CAE_AXIS_SIGNALS:
                self._cae[CAE_AXIS_SIGNALS.index(sig)] = p["volts"]
            elif sig in CAE_DISCRETE_SIGNALS:
                self._disc[CAE_DISCRETE_SIGNALS.index(sig)] = float(p["volts"])
            else:
                self.world.sim.hold_adc_volts(sig, p["volts"])
        self._set_cae()

    def _adc_restore(self, step: str, p: dict) -> None:
        self._cae = self._centred_cae()
        self._disc = [False, False, False]
        self._set_cae()
        for sig in p.get("signals", ()):
            if sig not in CAE_AXIS_SIGNALS and sig not in CAE_DISCRETE_SIGNALS:
                self.world.sim.hold_adc_volts(sig, 0.0)

    def _resolver_index(self, step: str, p: dict) -> None:
        self._set_arm_q(p["axis"], p["index_rad"])

    def _cae_release(self, step: str, p: dict) -> None:
        rest = self.stick.rest(self._rest_k)
        self._rest_k += 1
        self._cae = np.array([rest[axis] for _, axis, _ in CAE_AXES])
        self._disc = [False, False, False]
        self._set_cae()

    def _cae_deflect(self, step: str, p: dict) -> None:
        axis, d = p["axis"], p["direction"]
        i = [a for _, a, _ in CAE_AXES].index(axis)
        self._cae = self._centred_cae()
        self._cae[i] = self.stick.plus_v[axis] if d > 0 else self.stick.minus_v[axis]
        self._set_cae()

    def _ft_sensor(self, step: str, p: dict) -> None:
        """The tool and fixture loads on the F/T sensor (created on first use)."""
        if self.sensor is None:
            self.sensor = SensorTruth(self.world)
        if step == "ft.unload":
            self.sensor.tool_on = False
        elif step == "ft.mount":
            self.sensor.tool_on = True
        elif step == "ft.apply_load":
            self.sensor.fixture = np.asarray(p["wrench"], dtype=float)
        else:
            self.sensor.fixture = np.zeros(6)

    def _ft_pose(self, step: str, p: dict) -> None:
        self._set_arm_q(slice(None, 6), p["q_rad"])

    def _ft_known_weight(self, step: str, p: dict) -> None:
        sim = self.world.sim
        sim.set_errors(replace(sim.errors, payload_kg=sim.errors.payload_kg + p["mass_kg"]))

    def _ft_remove_weight(self, step: str, p: dict) -> None:
        sim = self.world.sim
        sim.set_errors(replace(sim.errors, payload_kg=max(0.0, sim.errors.payload_kg - p["mass_kg"])))

    #: prompt step -> what the operator does
    _ACTIONS: dict[str, Callable[[SimOperator, str, dict], None]] = {
        "adc.reference": _adc_reference,
        "adc.restore": _adc_restore,
        "resolver.index": _resolver_index,
        "cae.release": _cae_release,
        "cae.deflect": _cae_deflect,
        "ft.unload": _ft_sensor,
        "ft.mount": _ft_sensor,
        "ft.apply_load": _ft_sensor,
        "ft.release_load": _ft_sensor,
        "ft.pose": _ft_pose,
        "ft.known_weight": _ft_known_weight,
        "ft.remove_weight": _ft_remove_weight,
    }


class CalibrationRig(_BaseSimRig):
    """Simulated rack + service + reader on one SimClock (``pfma calibrate --rack fake``).

    :param calibration: passed to the service (path or loaded calibration)
    """

    def __init__(self, calibration=None, name: str | None = None, **world_kw: Any) -> None:
        super().__init__(name=name, prefix="pfma-cal-",
                         service_kw={"calibration": calibration} if calibration is not None else None,
                         **world_kw)

    def controller(self, owner: str = "pfma-calibrate") -> Client:
        return super().controller(owner)

