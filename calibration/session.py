"""How a calibration procedure talks to the rack: through the running service's Bit3 buffer.

A procedure never touches a register. It reads the input area (raw fields:
``adc_volts``, ``rtd_counts``, ``ft_counts``; never the service's converted values,
so the result does not depend on the calibration the service happens to run) and,
when a joint must move, claims the command area as a controller: ``arm_request`` with
a new ``rearm_counter`` and zero rates, then a slow constant rate, heartbeat every
frame (the service's watchdog is 15 ms), and disarm at the end.

Two sessions share one interface:

- :class:`SimSession` wraps a simulated-time rig (``FakeWorld`` + ``IoService`` +
  clients on one ``SimClock``; any object with ``run(seconds)``, ``on_frame``,
  ``reader``, ``controller()``, ``world``, ``svc``, e.g. ``sim.rig.SimRig``
  or :func:`sim.calibration.build_rig`); time passes only when the procedure waits.
- :class:`LiveSession` attaches to a running service (``pfma serve``) by buffer name
  and runs in real time (command heartbeat every 2 ms).

Operators: :class:`ConsoleOperator` prints the prompt and waits for Enter (or, with
``--non-interactive``, goes on at once); on the simulated rack
``sim.calibration.SimOperator`` acts instead of a person.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, TextIO

import numpy as np

from bit3.layout import ServiceState
from pfma.errors import CalibrationError

#: current limits while a procedure moves joints, A (command order of the layout's
#: current_limit_names: SP SY EP WY WP WR GR); the service tests' values, brakes released
MOVE_CURRENT_LIMIT_A = {"shoulder_pitch": 5.0, "shoulder_yaw": 5.0, "elbow_pitch": 5.0, "wrist_yaw": 2.5,
                        "wrist_pitch": 2.5, "wrist_roll": 2.5, "gripper": 0.0}


class Operator(Protocol):
    def prompt(self, step: str, text: str, **params: Any) -> float | None:
        """Ask the operator to act (``step`` names the action for a simulated operator).
        Returns a value the operator typed (e.g. the measured reference volts) or None."""

    def show(self, text: str) -> None:
        """Progress and results."""


class ConsoleOperator:
    """A person at a terminal. ``interactive=False`` prints prompts and goes on."""

    def __init__(self, out: TextIO | None = None, interactive: bool = True,
                 read: Callable[[str], str] = input) -> None:
        self.out = out or sys.stdout
        self.interactive = interactive
        self._read = read

    def show(self, text: str) -> None:
        print(text, file=self.out, flush=True)

    def prompt(self, step: str, text: str, **params: Any) -> float | None:
        ask = params.get("ask")
        self.show(f"  >>> {text}")
        if not self.interactive:
            return None
        while True:
            answer = self._read(f"      {ask + ' (Enter = as asked)' if ask else 'press Enter when done'}: ").strip()
            if not answer or not ask:
                return None
            try:
                return float(answer)
            except ValueError:
                self.show(f"      not a number: {answer!r}")


@dataclass
class Samples:
    """Samples taken once per new input record: ``t`` and one array per field."""

    t: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]

    def __len__(self) -> int:
        return len(self.t)


class Session:
    """Base: sampling and the commanding logic shared by the simulated and live sessions."""

    layout: Any

    def __init__(self) -> None:
        self._ctl = None
        self._cmd: dict[str, Any] | None = None
        self._rearm = 0
        self._hooks: list[Callable[[], None]] = []

    # provided by subclasses
    def _spin(self, duration_s: float) -> None:
        raise NotImplementedError

    def _controller(self):
        raise NotImplementedError

    def read(self):
        """The latest input-area snapshot (preallocated; copy to keep)."""
        raise NotImplementedError

    def messages_text(self) -> str:
        return ""

    def calibration_hash(self) -> bytes | None:
        """The calibration hash the service stamped in the buffer header (None if unknown)."""
        reader = getattr(self, "reader", None) or getattr(getattr(self, "rig", None), "reader", None)
        if reader is None:
            return None
        return bytes(reader.header().calibration_hash)

    # common
    def wait(self, duration_s: float) -> None:
        """Let ``duration_s`` pass (commands, if armed, keep their heartbeat)."""
        self._spin(duration_s)

    def tick(self) -> None:
        """Once per service frame (sim) or per 2 ms (live): heartbeat + hooks."""
        if self._cmd is not None:
            self._ctl.write_commands(**self._cmd)
        for h in self._hooks:
            h()

    def collect(self, duration_s: float, fields: tuple[str, ...], key: str = "t_adc_s") -> Samples:
        """Sample ``fields`` of the input area each time ``key`` (a sample time) changes."""
        ts: list[float] = []
        vals: dict[str, list] = {f: [] for f in fields}
        last = [None]

        def hook() -> None:
            s = self.read()
            t = s[key]
            if t != last[0] and t > 0:
                last[0] = t
                ts.append(t)
                for f in fields:
                    v = s[f]
                    vals[f].append(v.copy() if isinstance(v, np.ndarray) else v)
        self._hooks.append(hook)
        try:
            self._spin(duration_s)
        finally:
            self._hooks.remove(hook)
        if not ts:
            raise CalibrationError(f"no new samples ({key}) in {duration_s:g} s: is the service running?")
        return Samples(np.array(ts), {f: np.array(v) for f, v in vals.items()})

    def joint_index(self, stem: str) -> int:
        return list(self.layout.joint_names).index(stem)

    def arm(self) -> None:
        """Claim the commands, request arming with zero rates; brakes release.

        :raises CalibrationError: when the service does not arm within 0.2 s
        """
        if self._ctl is None:
            self._ctl = self._controller()
        limits = [MOVE_CURRENT_LIMIT_A.get(self.layout.channel(n, "commands").joint, 0.0)
                  for n in self.layout.current_limit_names]
        self._rearm += 1
        rec = self._ctl.command
        self._rearm = max(self._rearm, int(rec["rearm_counter"]) + 1)
        self._cmd = {"joint_rate_rad_s": [0.0] * len(self.layout.joint_names), "current_limit_a": limits,
                     "arm_request": 1, "rearm_counter": self._rearm}
        for _ in range(20):
            self._spin(0.01)
            if self.read()["service_state"] == ServiceState.ARMED:
                self._spin(0.1)  # brakes release
                return
        self.disarm()
        raise CalibrationError("the service did not arm (state "
                               f"{ServiceState(self.read()['service_state']).name}); {self.messages_text()}")

    def set_rates(self, rates: dict[str, float]) -> None:
        """Joint rate commands (rad/s) by joint stem; others 0. Needs :meth:`arm`."""
        if self._cmd is None:
            raise CalibrationError("set_rates before arm()")
        r = [0.0] * len(self.layout.joint_names)
        for stem, v in rates.items():
            r[self.joint_index(stem)] = float(v)
        self._cmd["joint_rate_rad_s"] = r

    def armed(self) -> bool:
        return self.read()["service_state"] == ServiceState.ARMED

    def disarm(self) -> None:
        """Rates 0, let the joints stop, then clear ``arm_request`` (brakes set)."""
        if self._cmd is None:
            return
        self._cmd["joint_rate_rad_s"] = [0.0] * len(self.layout.joint_names)
        self._spin(0.3)
        self._cmd["arm_request"] = 0
        self._cmd["current_limit_a"] = [0.0] * len(self.layout.current_limit_names)
        self._spin(0.05)
        self._cmd = None

    def close(self) -> None:
        self.disarm()


class SimSession(Session):
    """A procedure session on a simulated-time rig (see module doc)."""

    def __init__(self, rig: Any) -> None:
        super().__init__()
        self.rig = rig
        self.layout = rig.reader.layout
        self.world = rig.world
        self.svc = rig.svc
        self.period_s = rig.svc.schedule.period_s
        self._hook = lambda info: self.tick()
        rig.on_frame.append(self._hook)

    def _spin(self, duration_s: float) -> None:
        self.rig.run(duration_s)

    def _controller(self):
        return self.rig.controller() if getattr(self.rig, "ctl", None) is None else self.rig.ctl

    def read(self):
        return self.rig.reader.read_inputs()

    def messages_text(self) -> str:
        return "; ".join(m.text for m in self.rig.reader.messages()[-3:])

    def reload_service(self, path: str | Path) -> None:
        """Tell the in-process service to load ``path`` (refused while armed)."""
        self.svc.reload_calibration(path)
        self._spin(2 * self.period_s * 4)

    def close(self) -> None:
        super().close()
        if self._hook in self.rig.on_frame:
            self.rig.on_frame.remove(self._hook)


class LiveSession(Session):
    """A procedure session on a running service, in real time."""

    def __init__(self, buffer: str = "pfma", rack: str | None = None, tick_s: float = 0.002) -> None:
        super().__init__()
        from bit3.client import Client
        self._Client = Client
        self.buffer = buffer
        self.rack = rack
        self.reader = Client.attach(buffer, rack=rack)
        self.layout = self.reader.layout
        self.tick_s = tick_s
        self.world = None

    def _spin(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        while True:
            self.tick()
            now = time.monotonic()
            if now >= end:
                return
            time.sleep(min(self.tick_s, end - now))  # real time: the live rack's own pace

    def _controller(self):
        return self._Client.attach(self.buffer, writer="commands", owner="pfma-calibrate", rack=self.rack)

    def read(self):
        return self.reader.read_inputs()

    def messages_text(self) -> str:
        return "; ".join(m.text for m in self.reader.messages()[-3:])

    def reload_service(self, path: str | Path) -> None:
        raise CalibrationError(f"a running service loads a new calibration at start "
                               f"(pfma serve --calibration {path}) or on its reload request")

    def close(self) -> None:
        try:
            super().close()
        finally:
            if self._ctl is not None:
                self._ctl.close()
            self.reader.close()
